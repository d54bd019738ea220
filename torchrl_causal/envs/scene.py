"""MuJoCo scene for :class:`~torchrl_causal.envs.DroneNavEnv`, built in code with ``MjSpec``.

No asset files are read: the heliport texture is drawn into a numpy array
(:func:`helipad_image`) and handed to MuJoCo in memory; floor and obstacle
checker textures use MuJoCo's built-in texture generator.

The model contains:

* the floor (a plane with a checker texture); for an ``enclosed`` layout also
  four walls and a ceiling (an open layout's flight volume is a geofence the
  env checks, not geometry);
* the layout's obstacles (boxes or cylinders);
* the goal: a board with the heliport texture on its face, on a thin post;
* the drone: a free-joint body (collision hull ``DRONE_HALF_EXTENTS``, 0.5 kg)
  with four rotor sites, four thrust actuators (force along the rotor axis plus
  a reaction torque of alternating sign) and the forward-looking camera
  ``"front"`` at the front of the hull.

Rendering speed (DESIGN.md sec. 4): shadows, multisampling, reflections,
skybox and fog are off, the off-screen buffer is the image size, textures are
small. :class:`SceneRenderer` renders RGB and depth in one pass and the
segmentation pass (for the goal's visible box) only when the goal board can be
in the image.

Example:
    >>> from torchrl_causal.envs.layouts import thesis_layout
    >>> from torchrl_causal.envs.scene import build_model
    >>> model, ids = build_model(thesis_layout())
    >>> model.nu, model.nq, ids.camera
    (4, 7, 0)
"""

from __future__ import annotations

import math
import os
import threading
from dataclasses import dataclass

os.environ.setdefault("MUJOCO_GL", "egl")
# 84x84 frames render fastest in the calling thread (no llvmpipe worker threads)
os.environ.setdefault("LP_NUM_THREADS", "0")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from .layouts import DRONE_HALF_EXTENTS, Layout, Obstacle  # noqa: E402

__all__ = ["build_model", "helipad_image", "board_face_image", "SceneIds", "SceneRenderer", "DRONE_MASS"]

# GL contexts of a closed renderer that were current in another (live) thread:
# freeing them here would delete objects of this thread's context instead
_UNFREED: list = []

#: Mass of the drone (kg).
DRONE_MASS = 0.5
#: Rotor positions in the body frame (x forward, y left).
ROTOR_XY = ((0.085, 0.085), (-0.085, 0.085), (-0.085, -0.085), (0.085, -0.085))
#: Sign of each rotor's reaction torque about body z.
ROTOR_SPIN = (1.0, -1.0, 1.0, -1.0)
#: Reaction torque per newton of thrust (m).
ROTOR_TORQUE_COEF = 0.02
#: Maximum thrust per rotor (N).
ROTOR_MAX_THRUST = 4.0
#: Camera offset from the drone centre, body frame.
CAMERA_OFFSET = (DRONE_HALF_EXTENTS[0] + 0.005, 0.0, 0.0)


def helipad_image(
    size: int = 64,
    background=(0.12, 0.25, 0.55),
    marking=(0.97, 0.97, 0.97),
) -> np.ndarray:
    """The heliport sign: a ring and an "H" on a coloured square, ``uint8 [size, size, 3]``.

    Example:
        >>> img = helipad_image(64)
        >>> img.shape, img.dtype.name
        ((64, 64, 3), 'uint8')
    """
    bg = (np.asarray(background) * 255).astype(np.uint8)
    fg = (np.asarray(marking) * 255).astype(np.uint8)
    img = np.empty((size, size, 3), np.uint8)
    img[:] = bg
    c = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size]
    r = np.hypot(xx - c, yy - c)
    img[(r <= 0.47 * size) & (r >= 0.39 * size)] = fg
    u = size / 64.0
    x0, x1 = int(round(20 * u)), int(round(44 * u))
    y0, y1 = int(round(16 * u)), int(round(48 * u))
    bar = max(1, int(round(6 * u)))
    img[y0:y1, x0 : x0 + bar] = fg
    img[y0:y1, x1 - bar : x1] = fg
    ym = (y0 + y1) // 2
    img[ym - bar // 2 : ym - bar // 2 + bar, x0:x1] = fg
    return img


def board_face_image(layout=None, pixels_per_m: float = 400.0) -> np.ndarray:
    """The goal board's face as the simulator shows it, at true proportions, for print.

    MuJoCo stretches the square heliport texture (:func:`helipad_image`, in the
    layout's colours) over the board's ``goal_size`` face (1.0 x 0.8 m in the
    thesis scene); the detector learned that look, so a real board should
    print this image at ``goal_size`` (``recipes/print_board.py``).

    Args:
        layout: a :class:`~torchrl_causal.envs.layouts.Layout` (default: the
            thesis scene's).
        pixels_per_m: resolution (400 px/m ~ 100 dpi).

    Returns:
        ``uint8 [round(h * ppm), round(w * ppm), 3]``.

    Example:
        >>> board_face_image(pixels_per_m=100).shape
        (80, 100, 3)
    """
    import cv2

    from .layouts import thesis_layout

    layout = thesis_layout() if layout is None else layout
    if not isinstance(pixels_per_m, (int, float)) or not 10 <= pixels_per_m <= 4000:
        raise ValueError(f"pixels_per_m must be in [10, 4000], got {pixels_per_m!r}")
    w, h = layout.goal_size
    W, H = int(round(w * pixels_per_m)), int(round(h * pixels_per_m))
    square = helipad_image(1024, *layout.helipad_rgb)
    return cv2.resize(square, (W, H), interpolation=cv2.INTER_NEAREST)


@dataclass
class SceneIds:
    """Indices into the compiled model that the env needs."""

    drone_body: int
    drone_geoms: tuple[int, ...]
    goal_geoms: tuple[int, ...]
    camera: int
    qpos_adr: int
    qvel_adr: int
    goal_corners: np.ndarray  # [8, 3] world corners of the goal board


def _quat_yaw(deg: float) -> list[float]:
    a = math.radians(deg) / 2
    return [math.cos(a), 0.0, 0.0, math.sin(a)]


def _add_textured_material(spec: mujoco.MjSpec, name: str, texture: str, **kw) -> None:
    """Adds material ``name`` whose RGB texture is ``texture``."""
    mat = spec.add_material(name=name, **kw)
    tx = list(mat.textures)
    tx[mujoco.mjtTextureRole.mjTEXROLE_RGB] = texture
    mat.textures = tx


def _add_obstacle(spec: mujoco.MjSpec, o: Obstacle, k: int):
    kw = {}
    if o.pattern == "checker":
        rgb1 = list(o.rgba[:3])
        rgb2 = [v * 0.75 for v in o.rgba[:3]]
        spec.add_texture(
            name=f"obst_tex{k}",
            type=mujoco.mjtTexture.mjTEXTURE_2D,
            builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
            width=32,
            height=32,
            rgb1=rgb1,
            rgb2=rgb2,
        )
        _add_textured_material(
            spec, f"obst_mat{k}", f"obst_tex{k}", texrepeat=[4, 4], texuniform=True
        )
        kw["material"] = f"obst_mat{k}"
    if o.shape == "box":
        spec.worldbody.add_geom(
            name=f"obstacle{k}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=list(o.half_size),
            pos=list(o.center),
            quat=_quat_yaw(o.yaw_deg),
            rgba=list(o.rgba),
            **kw,
        )
    else:
        spec.worldbody.add_geom(
            name=f"obstacle{k}",
            type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            size=[o.half_size[0], o.half_size[2], 0.0],
            pos=list(o.center),
            rgba=list(o.rgba),
            **kw,
        )


def build_model(
    layout: Layout,
    *,
    image_size: tuple[int, int] = (84, 84),
    fov_deg: float = 60.0,
    max_depth: float = 10.0,
    timestep: float = 0.02,
    board_back: str = "heliport",
) -> tuple[mujoco.MjModel, SceneIds]:
    """Compiles ``layout`` into an ``MjModel``.

    Args:
        layout: the arena.
        image_size: ``(height, width)`` of the camera images (sets the
            off-screen buffer size).
        fov_deg: vertical field of view of the camera (deg).
        max_depth: far range of interest (m); the far clipping plane is beyond it.
        timestep: physics time step (s).
        board_back: ``"heliport"`` (default: the board is one textured box, its back shows
            the heliport too, as every policy and perception model here was trained on) or
            ``"blank"``: a plain grey sheet covers the back, as on a printed board (not part
            of the goal's segmentation; docs/tello.rst, "A head that can decline").

    Returns:
        ``(model, ids)``.

    Example:
        >>> from torchrl_causal.envs.layouts import thesis_layout
        >>> model, ids = build_model(thesis_layout(), image_size=(64, 64))
        >>> int(model.vis.global_.offwidth)
        64
    """
    h, w = image_size
    spec = mujoco.MjSpec()
    spec.modelname = f"drone_nav_{layout.name}"
    spec.option.timestep = timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    # rendering: cheap
    vis = spec.visual
    vis.quality.shadowsize = 0
    vis.quality.offsamples = 0
    vis.global_.offwidth = w
    vis.global_.offheight = h
    xmin, ymin, xmax, ymax = layout.arena
    extent = max(xmax - xmin, ymax - ymin, layout.height)
    spec.stat.extent = extent
    spec.stat.center = [(xmin + xmax) / 2, (ymin + ymax) / 2, layout.height / 2]
    vis.map.znear = 0.01 / extent
    vis.map.zfar = max(2.0 * max_depth, 2.0 * math.hypot(extent, extent)) / extent
    vis.map.haze = 0.0
    vis.headlight.ambient = [layout.ambient] * 3
    vis.headlight.diffuse = [0.25] * 3
    vis.headlight.specular = [0.0] * 3
    wb = spec.worldbody

    # floor: checker texture, uniform metric tiles of 0.5 m
    spec.add_texture(
        name="floor_tex",
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        width=32,
        height=32,
        rgb1=list(layout.floor_rgb[0]),
        rgb2=list(layout.floor_rgb[1]),
    )
    _add_textured_material(spec, "floor_mat", "floor_tex", texrepeat=[1, 1], texuniform=True)
    cx, cy = (xmin + xmax) / 2, (ymin + ymax) / 2
    hx, hy = (xmax - xmin) / 2, (ymax - ymin) / 2
    # an open field's floor reaches past the depth range in every direction
    fx, fy = (hx, hy) if layout.enclosed else (hx + max_depth, hy + max_depth)
    wb.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[fx, fy, 0.5],
        pos=[cx, cy, 0.0],
        material="floor_mat",
    )
    t = 0.05
    H = layout.height
    if layout.enclosed:
        walls = [
            ([xmin - t, cy, H / 2], [t, hy + 2 * t, H / 2]),
            ([xmax + t, cy, H / 2], [t, hy + 2 * t, H / 2]),
            ([cx, ymin - t, H / 2], [hx + 2 * t, t, H / 2]),
            ([cx, ymax + t, H / 2], [hx + 2 * t, t, H / 2]),
        ]
        for k, (pos, size) in enumerate(walls):
            wb.add_geom(
                name=f"wall{k}", type=mujoco.mjtGeom.mjGEOM_BOX, size=size, pos=pos,
                rgba=list(layout.wall_rgba),
            )
        wb.add_geom(
            name="ceiling", type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx + 2 * t, hy + 2 * t, t],
            pos=[cx, cy, H + t], rgba=list(layout.ceiling_rgba),
        )
    for k, o in enumerate(layout.obstacles):
        _add_obstacle(spec, o, k)

    # goal board with the heliport texture, on a post
    tex = spec.add_texture(
        name="helipad", type=mujoco.mjtTexture.mjTEXTURE_2D, width=64, height=64, nchannel=3
    )
    tex.data = helipad_image(64, *layout.helipad_rgb).tobytes()
    _add_textured_material(spec, "helipad_mat", "helipad")
    gw, gh = layout.goal_size
    gt = layout.goal_thickness
    gquat = _quat_yaw(layout.goal_yaw_deg)
    wb.add_geom(
        name="goal_board", type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[gt / 2, gw / 2, gh / 2], pos=list(layout.goal_center), quat=gquat,
        material="helipad_mat",
    )
    if board_back not in ("heliport", "blank"):
        raise ValueError(f"board_back must be 'heliport' or 'blank', got {board_back!r}")
    if board_back == "blank":  # a 1 mm sheet just behind the back face, a little larger
        sheet = np.asarray(layout.goal_center) - layout.goal_normal() * (gt / 2 + 0.0015)
        wb.add_geom(
            name="goal_back", type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[0.0005, gw / 2 + 0.002, gh / 2 + 0.002], pos=list(sheet), quat=gquat,
            rgba=[0.62, 0.6, 0.56, 1.0],
        )
    bottom = layout.goal_center[2] - gh / 2
    if bottom > 0.05:
        back = np.asarray(layout.goal_center) - layout.goal_normal() * (gt / 2 + 0.03)
        wb.add_geom(
            name="goal_post", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            size=[0.025, bottom / 2, 0.0], pos=[back[0], back[1], bottom / 2],
            rgba=[0.3, 0.3, 0.3, 1.0],
        )
    wb.add_light(
        name="sun", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, dir=list(layout.light_dir),
        pos=[cx, cy, H], castshadow=False, diffuse=[layout.light_diffuse] * 3,
        specular=[0.05] * 3,
    )

    # the drone
    dx, dy, dz = DRONE_HALF_EXTENTS
    body = wb.add_body(name="drone", pos=list(layout.start_pos), quat=_quat_yaw(layout.start_yaw_deg))
    body.add_freejoint(name="drone_root")
    body.add_geom(
        name="drone_hull", type=mujoco.mjtGeom.mjGEOM_BOX, size=[dx, dy, dz],
        mass=DRONE_MASS, rgba=[0.15, 0.15, 0.15, 1.0], margin=0.0,
    )
    for k, ((rx, ry), spin) in enumerate(zip(ROTOR_XY, ROTOR_SPIN)):
        body.add_geom(
            name=f"rotor{k}", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.035, 0.004, 0],
            pos=[rx, ry, dz], contype=0, conaffinity=0, mass=0.0, group=1,
            rgba=[0.8, 0.1, 0.1, 0.6],
        )
        body.add_site(name=f"rotor{k}", pos=[rx, ry, dz])
        spec.add_actuator(
            name=f"thrust{k}",
            trntype=mujoco.mjtTrn.mjTRN_SITE,
            target=f"rotor{k}",
            gear=[0, 0, 1, 0, 0, spin * ROTOR_TORQUE_COEF],
            ctrllimited=True,
            ctrlrange=[0.0, ROTOR_MAX_THRUST],
        )
    body.add_camera(
        name="front", pos=list(CAMERA_OFFSET), xyaxes=[0, -1, 0, 0, 0, 1], fovy=fov_deg
    )
    model = spec.compile()

    gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "goal_board")
    corners = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            for sz in (-1, 1):
                corners.append([sx * gt / 2, sy * gw / 2, sz * gh / 2])
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, np.asarray(gquat, dtype=np.float64))
    corners = np.asarray(corners) @ rot.reshape(3, 3).T + np.asarray(layout.goal_center)
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "drone")
    jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "drone_root")
    drone_geoms = tuple(int(g) for g in np.nonzero(model.geom_bodyid == bid)[0])
    ids = SceneIds(
        drone_body=int(bid),
        drone_geoms=drone_geoms,
        goal_geoms=(int(gid),),
        camera=int(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "front")),
        qpos_adr=int(model.jnt_qposadr[jid]),
        qvel_adr=int(model.jnt_dofadr[jid]),
        goal_corners=corners,
    )
    return model, ids


class SceneRenderer:
    """Lean off-screen renderer: RGB + metric depth in one pass, goal mask on demand.

    Owns one OpenGL context for its lifetime; :meth:`set_model` swaps the
    model (new layout) without creating a new context. Output buffers are
    allocated once and overwritten by every call; copy them if you keep them.

    Thread-aware: an EGL context is bound to one thread, so the first call from
    another thread (e.g. a collector's worker thread stepping an env that was
    reset in the main thread) builds a context for that thread, once, and the
    renderer switches between the threads' contexts after that; frames are the
    same from any thread. Calls must not run in two threads at the same time.

    Args:
        model: the compiled model (its off-screen buffer must be >= the image).
        height: image height.
        width: image width.
        camera: camera id to render from.
        max_depth: depth values beyond it (and background) are clipped to it.

    Example:
        >>> import mujoco
        >>> from torchrl_causal.envs.layouts import thesis_layout
        >>> model, ids = build_model(thesis_layout())
        >>> data = mujoco.MjData(model); mujoco.mj_forward(model, data)
        >>> r = SceneRenderer(model, 84, 84, ids.camera)
        >>> rgb, depth = r.render(data)
        >>> rgb.shape, depth.shape, bool(depth.max() <= 10.0)
        ((84, 84, 3), (84, 84), True)
        >>> r.close()
    """

    def __init__(self, model, height: int, width: int, camera: int, max_depth: float = 10.0):
        from mujoco import gl_context

        self._gl_factory = gl_context.GLContext
        self.height, self.width = int(height), int(width)
        self.max_depth = float(max_depth)
        self._thread = threading.get_ident()
        self._gl = self._gl_factory(self.width, self.height)
        self._gl.make_current()
        self._ctx = None
        # contexts of other threads that rendered: {thread id: (gl, ctx, model version)}
        self._other_threads: dict[int, tuple] = {}
        self._model_version = 0
        self._ctx_version = 0
        self._rect = mujoco.MjrRect(0, 0, self.width, self.height)
        self._cam = mujoco.MjvCamera()
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._opt = mujoco.MjvOption()
        self._opt.geomgroup[1] = 0  # rotor discs: not needed by the onboard camera
        self._pert = mujoco.MjvPerturb()
        self.rgb = np.empty((self.height, self.width, 3), np.uint8)
        self.depth = np.empty((self.height, self.width), np.float32)
        self._seg_rgb = np.empty((self.height, self.width, 3), np.uint8)
        self._zbuf = np.empty((self.height, self.width), np.float32)
        self.set_model(model, camera)

    def _current(self) -> None:
        """Makes this thread's GL context current (built here once, on first use).

        An EGL context can be current in one thread only: a renderer used from
        a thread other than the one that built it gets a GL + MuJoCo render
        context of its own for that thread (kept for the thread's next calls;
        the other thread's context stays with it). The contexts render the same
        model with the same settings, so the frames are the same.
        """
        ident = threading.get_ident()
        if ident != self._thread:
            self._other_threads[self._thread] = (self._gl, self._ctx, self._ctx_version)
            self._gl, self._ctx, self._ctx_version = self._other_threads.pop(
                ident, (None, None, -1))
            self._thread = ident
            if self._gl is None:
                self._gl = self._gl_factory(self.width, self.height)
        self._gl.make_current()
        if self._ctx_version != self._model_version:  # a model set in another thread
            self._make_ctx()

    def _make_ctx(self) -> None:
        if self._ctx is not None:
            self._ctx.free()
        self._ctx = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_50.value)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._ctx)
        self._ctx.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._ctx_version = self._model_version

    def set_model(self, model, camera: int):
        """Switches to a new model (keeps the GL context)."""
        self.model = model
        self._model_version += 1
        self._current()  # (re)builds this thread's MuJoCo render context for the model
        self._segid_cache = {}
        self._scene = mujoco.MjvScene(model=model, maxgeom=max(64, 4 * model.ngeom))
        self._cam.fixedcamid = int(camera)
        extent = model.stat.extent
        znear = np.float32(model.vis.map.znear * extent)
        zfar = np.float32(model.vis.map.zfar * extent)
        c = -(zfar + znear) / (zfar - znear)
        d = -(np.float32(2) * zfar * znear) / (zfar - znear)
        self._c = float(np.float32(-0.5) * c - np.float32(0.5))
        self._d = float(np.float32(-0.5) * d)

    def render(self, data) -> tuple[np.ndarray, np.ndarray]:
        """Renders the camera view; returns the (reused) ``rgb`` and ``depth`` buffers."""
        self._current()
        mujoco.mjv_updateScene(
            self.model, data, self._opt, self._pert, self._cam,
            mujoco.mjtCatBit.mjCAT_ALL.value, self._scene,
        )
        mujoco.mjr_render(self._rect, self._scene, self._ctx)
        mujoco.mjr_readPixels(self.rgb, self._zbuf, self._rect, self._ctx)
        # OpenGL rows are bottom-up
        self.rgb[:] = self.rgb[::-1]
        z = self._zbuf[::-1]
        # reversed-Z depth buffer -> metric z-depth (as mujoco.Renderer does)
        np.divide(self._d, z + self._c, out=self.depth)
        np.minimum(self.depth, self.max_depth, out=self.depth)
        self.depth[~np.isfinite(self.depth) | (self.depth < 0)] = self.max_depth
        return self.rgb, self.depth

    def geom_mask(self, geom_ids) -> np.ndarray:
        """Bool mask ``[H, W]`` of the pixels showing any of ``geom_ids``.

        Re-renders the scene of the last :meth:`render` call in segmentation mode.
        """
        self._current()
        scn = self._scene
        flags = scn.flags
        flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = 1
        flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 1
        try:
            mujoco.mjr_render(self._rect, scn, self._ctx)
            mujoco.mjr_readPixels(self._seg_rgb, None, self._rect, self._ctx)
        finally:
            flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = 0
            flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 0
        segids = self._segids(tuple(int(g) for g in geom_ids))
        seg = self._seg_rgb[::-1]
        ids = (
            seg[..., 0].astype(np.int32)
            | (seg[..., 1].astype(np.int32) << 8)
            | (seg[..., 2].astype(np.int32) << 16)
        )
        if not segids:
            return np.zeros(ids.shape, dtype=bool)
        if len(segids) == 1:
            return ids == segids[0]
        return np.isin(ids, segids)

    def _segids(self, geom_ids: tuple[int, ...]) -> list[int]:
        """Segmentation ids (+1) of ``geom_ids`` in the current scene (cached per model)."""
        scn = self._scene
        cached = self._segid_cache.get(geom_ids)
        if cached is not None:
            ngeom, idx, segids = cached
            # the scene's geom order is fixed for a model; verify cheaply
            if ngeom == scn.ngeom and all(scn.geoms[i].objid == g for i, g in zip(idx, geom_ids)):
                return segids
        idx, segids = [], []
        for g in geom_ids:
            for i in range(scn.ngeom):
                sg = scn.geoms[i]
                if sg.objtype == mujoco.mjtObj.mjOBJ_GEOM and sg.objid == g:
                    idx.append(i)
                    segids.append(sg.segid + 1)
                    break
        if len(idx) == len(geom_ids):
            self._segid_cache[geom_ids] = (scn.ngeom, idx, segids)
        return segids

    def close(self):
        """Frees the GL resources (idempotent).

        A context still current in another live thread cannot be freed from
        this one; it is kept (not freed) rather than freed in the wrong context.
        """
        contexts = list(self._other_threads.values()) if hasattr(self, "_other_threads") else []
        self._other_threads = {}
        if getattr(self, "_gl", None) is not None:
            contexts.append((self._gl, self._ctx, None))
            self._gl, self._ctx = None, None
        for gl, ctx, _ in contexts:
            if gl is None:
                continue
            try:
                gl.make_current()
            except Exception:  # current in another thread: leave it there
                _UNFREED.append((gl, ctx))
                continue
            if ctx is not None:
                ctx.free()
            gl.free()

    def __del__(self):
        try:
            self.close()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass
