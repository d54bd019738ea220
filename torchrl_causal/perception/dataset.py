"""Synthetic perception datasets rendered by :class:`~torchrl_causal.envs.DroneNavEnv`.

Every view is rendered by the env's own scene code (the same MuJoCo model,
camera and :class:`~torchrl_causal.envs.scene.SceneRenderer`, through the env's
observation function), so images, depth and goal boxes are exactly what the
env shows an agent. Per view:

* ``rgb`` uint8 ``[H, W, 3]`` and ``depth`` float32 ``[H, W]`` (metric z-depth,
  clipped to ``max_depth``);
* ``box`` ``(x0, y0, x1, y1)`` float pixels (exclusive ends), the goal board's
  visible box from segmentation rendering (the env's ``goal_box``), or None when
  fewer than ``min_fraction`` of the image's pixels show the goal (default
  0.0028: the env's ``goal_min_pixels=20`` at 84 x 84, scaled to the image);
* ``goal_pixels``: how many pixels show the goal.

**Splits.** ``"train"`` and ``"val"`` use disjoint layout indices of
``RandomLayoutGenerator("train", seed=layout_seed)`` (val: every 5th index,
``i % 5 == 4``; train: the others); ``"test"`` uses
``RandomLayoutGenerator("heldout", seed=layout_seed)``, whose layouts can never
be train layouts (see :mod:`~torchrl_causal.envs.layouts`). ``views_per_layout``
consecutive views share a layout.

**Views.** Four kinds, drawn per view: ``"absent"`` (probability
``goal_absent_frac``; a random collision-free pose looking away from the goal),
``"obstacle"`` (probability ``obstacle_frac``, default 0; a close-up of an
obstacle, 0.25-1.5 m from its surface (``obstacle_distance``), looking at it:
the views where a pillar fills the frame, the detector's hard negatives and
MonoDepth's near obstacles), ``"start"`` (the rest's ``start_frac``: around the layout's start pose looking
towards the goal, where the generator puts an obstacle across the line of
sight, so the goal is often partly or fully hidden), and ``"goal"`` (a pose in
front of the board at a log-uniform distance of 0.5-9 m (``goal_distance``), up to 70 deg off its
normal, the goal anywhere across the image's width, some views cut by the
image border). Every view also gets a small random roll and pitch (as the
physics execution mode shows), and random lighting (light direction and
intensity, ambient level) and texture/colour tints of the floor, obstacles,
walls and the heliport board.

**Determinism.** View ``i`` of a split is a pure function of ``(seed, split,
i, layout_seed)`` and the options, whatever ``start`` and ``n`` are.

Example:
    >>> from torchrl_causal.perception.dataset import render_views
    >>> views = list(render_views("val", 2, seed=0, image_size=(48, 64)))
    >>> v = views[0]
    >>> v.rgb.shape, v.rgb.dtype.name, v.depth.shape, v.depth.dtype.name, v.split
    ((48, 64, 3), 'uint8', (48, 64), 'float32', 'val')
    >>> v.layout_index % 5
    4

Command line (writes the YOLO and the depth dataset, see :func:`write_datasets`)::

    python -m torchrl_causal.perception.dataset --out data/perception \\
        --n-train 1000 --n-val 200 --n-test 300 --seed 0 --image-size 240 320
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

__all__ = [
    "View",
    "DATASET_SPLITS",
    "DEFAULT_MIN_FRACTION",
    "render_views",
    "write_datasets",
    "layout_indices",
    "load_views",
    "evaluate_detector",
    "box_iou",
]

#: Dataset splits: train / val from disjoint train layouts, test from held-out layouts.
DATASET_SPLITS: tuple[str, ...] = ("train", "val", "test")
#: Smallest goal share of the image that counts as "goal visible" (20 px at 84 x 84).
DEFAULT_MIN_FRACTION: float = 0.0028
#: View kinds (see the module docstring).
VIEW_KINDS: tuple[str, ...] = ("goal", "start", "absent", "obstacle")

_SPLIT_ID = {"train": 0, "val": 1, "test": 2}
_VAL_EVERY = 5
_DRONE_RADIUS = 0.18  # horizontal clearance of a sampled pose from obstacles (m)


@dataclass
class View:
    """One rendered view.

    Attributes:
        rgb: uint8 ``[H, W, 3]``.
        depth: float32 ``[H, W]``, metric z-depth (m), clipped to ``max_depth``.
        box: ``(x0, y0, x1, y1)`` float pixels, exclusive ends, or None when the
            goal covers fewer than ``min_fraction`` of the image.
        goal_pixels: pixels showing the goal (segmentation), even below the threshold.
        layout_index: index of the layout in its generator (``"train"`` generator
            for the train and val splits, ``"heldout"`` for test).
        split: ``"train"``, ``"val"`` or ``"test"``.
        index: the view's number in its split.
        kind: ``"goal"``, ``"start"`` or ``"absent"`` (how the pose was drawn).
        pose: ``(x, y, z, yaw_deg, pitch_deg, roll_deg)`` of the drone (body
            quaternion ``yaw (z) * pitch (y) * roll (x)``).

    Example:
        >>> import numpy as np
        >>> v = View(np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.float32), None, 0, 3, "val")
        >>> v.box is None, v.layout_index
        (True, 3)
    """

    rgb: np.ndarray
    depth: np.ndarray
    box: tuple[float, float, float, float] | None
    goal_pixels: int
    layout_index: int
    split: str
    index: int = 0
    kind: str = "goal"
    pose: tuple[float, ...] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0))


def _check_image_size(image_size) -> tuple[int, int]:
    if isinstance(image_size, (int, np.integer)) and not isinstance(image_size, bool):
        image_size = (int(image_size), int(image_size))
    if (
        not isinstance(image_size, (tuple, list))
        or len(image_size) != 2
        or not all(
            isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 32
            for v in image_size
        )
    ):
        raise ValueError(
            f"image_size must be an int or (height, width) pair, each >= 32, got {image_size!r}"
        )
    return int(image_size[0]), int(image_size[1])


def _check_int(name, value, low):
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < low:
        raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    return int(value)


def _check_frac(name, value, high=1.0):
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0.0 <= value <= high:
        raise ValueError(f"{name} must be a number in [0, {high}], got {value!r}")
    return float(value)


def layout_indices(split: str, count: int) -> list[int]:
    """The first ``count`` layout indices a split uses (in its generator).

    Example:
        >>> layout_indices("train", 6), layout_indices("val", 3), layout_indices("test", 2)
        ([0, 1, 2, 3, 5, 6], [4, 9, 14], [0, 1])
    """
    if split not in DATASET_SPLITS:
        raise ValueError(f"split must be one of {DATASET_SPLITS}, got {split!r}")
    if split == "train":
        per = _VAL_EVERY - 1
        return [j + j // per for j in range(count)]
    if split == "val":
        return [_VAL_EVERY * j + _VAL_EVERY - 1 for j in range(count)]
    return list(range(count))


# --------------------------------------------------------------------------- poses
def _pose_free(layout, x, y, z) -> bool:
    """Whether a drone at ``(x, y, z)`` is clear of every obstacle, the board and the floor."""
    if z < 0.15 or z > layout.height - 0.1:
        return False
    for o in layout.obstacles + (layout.board_obstacle(),):
        top, bottom = o.center[2] + o.half_size[2], o.center[2] - o.half_size[2]
        if z - 0.1 > top or z + 0.1 < bottom:
            continue
        if o.footprint_mask(np.array([x]), np.array([y]), _DRONE_RADIUS)[0]:
            return False
    return True


def _inside(layout, x, y, margin=0.15) -> bool:
    xmin, ymin, xmax, ymax = layout.arena
    return xmin + margin <= x <= xmax - margin and ymin + margin <= y <= ymax - margin


def _draw_pose(rng, layout, kind: str, hfov_deg: float, goal_distance=(0.5, 9.0),
               obstacle_distance=(0.25, 1.5), obstacle_yaw_spread=0.5):
    """``(x, y, z, yaw_deg)`` for a view of ``kind`` (falls back to the start pose)."""
    g = np.asarray(layout.goal_center, dtype=np.float64)
    xmin, ymin, xmax, ymax = layout.arena
    ztop = min(layout.height - 0.15, 2.6)
    half = hfov_deg / 2.0
    if kind == "obstacle" and not layout.obstacles:
        kind = "absent"
    for _ in range(200):
        if kind == "obstacle":
            o = layout.obstacles[int(rng.integers(len(layout.obstacles)))]
            d = math.exp(rng.uniform(math.log(obstacle_distance[0]),
                                     math.log(obstacle_distance[1])))
            phi = rng.uniform(-math.pi, math.pi)
            # walk out along phi from the centre until the footprint is d away
            r = d + o.footprint_radius()
            for _ in range(8):
                x, y = o.center[0] + r * math.cos(phi), o.center[1] + r * math.sin(phi)
                r += d - float(o.footprint_distance(x, y))
            top = o.center[2] + o.half_size[2]
            z = rng.uniform(0.3, max(min(top, ztop), 0.35))
            bearing = math.degrees(math.atan2(o.center[1] - y, o.center[0] - x))
            yaw = bearing + rng.uniform(-obstacle_yaw_spread, obstacle_yaw_spread) * half
            if not _inside(layout, x, y, margin=0.1):
                continue
        elif kind == "goal":
            d = math.exp(rng.uniform(math.log(goal_distance[0]), math.log(goal_distance[1])))
            phi = math.radians(layout.goal_yaw_deg + rng.uniform(-70.0, 70.0))
            x = g[0] + math.cos(phi) * d
            y = g[1] + math.sin(phi) * d
            z = rng.uniform(0.3, ztop)
            bearing = math.degrees(math.atan2(g[1] - y, g[0] - x))
            yaw = bearing + rng.uniform(-1.0, 1.0) * (half + 5.0)
            if not _inside(layout, x, y, margin=-1.0):  # a little outside the geofence is fine
                continue
        elif kind == "start":
            sx, sy, sz = layout.start_pos
            x = sx + rng.normal(0.0, 0.35)
            y = sy + rng.normal(0.0, 0.35)
            z = float(np.clip(sz + rng.normal(0.0, 0.25), 0.3, ztop))
            bearing = math.degrees(math.atan2(g[1] - y, g[0] - x))
            yaw = bearing + rng.uniform(-0.6, 0.6) * half
        else:  # absent: anywhere, looking away from the goal
            x = rng.uniform(xmin + 0.2, xmax - 0.2)
            y = rng.uniform(ymin + 0.2, ymax - 0.2)
            z = rng.uniform(0.3, ztop)
            bearing = math.degrees(math.atan2(g[1] - y, g[0] - x))
            yaw = bearing + rng.choice([-1.0, 1.0]) * rng.uniform(half + 15.0, 180.0)
        if _pose_free(layout, x, y, z):
            return float(x), float(y), float(z), float((yaw + 180.0) % 360.0 - 180.0)
    sx, sy, sz = layout.start_pos
    return float(sx), float(sy), float(sz), float(layout.start_yaw_deg)


def _quat(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Body quaternion ``yaw (z) * pitch (y) * roll (x)``."""
    out = np.zeros(4)
    tmp = np.zeros(4)
    qz = np.array([math.cos(math.radians(yaw_deg) / 2), 0, 0, math.sin(math.radians(yaw_deg) / 2)])
    qy = np.array(
        [math.cos(math.radians(pitch_deg) / 2), 0, math.sin(math.radians(pitch_deg) / 2), 0]
    )
    qx = np.array([math.cos(math.radians(roll_deg) / 2), math.sin(math.radians(roll_deg) / 2), 0, 0])
    mujoco.mju_mulQuat(tmp, qz, qy)
    mujoco.mju_mulQuat(out, tmp, qx)
    return out


# --------------------------------------------------------------------------- appearance
class _Appearance:
    """Randomises lighting and colour/texture tints of a loaded model, per view."""

    def __init__(self, model, ids):
        self.model = model
        self.light_dir = model.light_dir.copy()
        self.light_diffuse = model.light_diffuse.copy()
        self.ambient = np.array(model.vis.headlight.ambient, dtype=np.float64)
        self.head_diffuse = np.array(model.vis.headlight.diffuse, dtype=np.float64)
        self.geom_rgba = model.geom_rgba.copy()
        self.mat_rgba = model.mat_rgba.copy()
        self.goal_geoms = set(ids.goal_geoms)
        self.drone_geoms = set(ids.drone_geoms)
        helipad = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, "helipad_mat")
        self.helipad_mat = int(helipad)

    def apply(self, rng: np.random.Generator):
        m = self.model
        d = self.light_dir.copy()
        d[:, :2] += rng.normal(0.0, 0.2, size=d[:, :2].shape)
        m.light_dir[:] = d / np.linalg.norm(d, axis=1, keepdims=True)
        m.light_diffuse[:] = np.clip(self.light_diffuse * rng.uniform(0.75, 1.6), 0.05, 1.0)
        m.vis.headlight.ambient[:] = np.clip(self.ambient * rng.uniform(0.75, 1.7), 0.05, 0.8)
        m.vis.headlight.diffuse[:] = np.clip(self.head_diffuse * rng.uniform(0.7, 1.6), 0.0, 0.6)
        # colour / texture tints: per object and channel, milder on the goal board
        tint = rng.uniform(0.75, 1.25, size=(m.ngeom, 3))
        for g in self.goal_geoms:
            tint[g] = rng.uniform(0.85, 1.15) * rng.uniform(0.93, 1.07, size=3)
        rgba = self.geom_rgba.copy()
        rgba[:, :3] = np.clip(rgba[:, :3] * tint, 0.0, 1.0)
        # a geom with a material takes the material's colour only while its own rgba
        # is MuJoCo's default: leave those (and the drone) untouched
        keep = list(self.drone_geoms) + [g for g in range(m.ngeom) if m.geom_matid[g] >= 0]
        rgba[keep] = self.geom_rgba[keep]
        m.geom_rgba[:] = rgba
        # (material colours multiply the textures; most are white, so tints darken only)
        mt = rng.uniform(0.8, 1.0, size=(m.nmat, 3))
        if self.helipad_mat >= 0:
            mt[self.helipad_mat] = rng.uniform(0.85, 1.0) * rng.uniform(0.93, 1.0, size=3)
        mat = self.mat_rgba.copy()
        mat[:, :3] = np.clip(mat[:, :3] * mt, 0.0, 1.0)
        m.mat_rgba[:] = mat


# --------------------------------------------------------------------------- rendering
def render_views(
    split: str,
    n: int,
    *,
    seed: int,
    image_size: int | Sequence[int] = (240, 320),
    layout_seed: int = 0,
    goal_absent_frac: float = 0.2,
    start_frac: float = 0.2,
    views_per_layout: int = 8,
    min_fraction: float = DEFAULT_MIN_FRACTION,
    fov_deg: float = 60.0,
    max_depth: float = 10.0,
    max_tilt_deg: float = 4.0,
    randomize_appearance: bool = True,
    start: int = 0,
    goal_distance: Sequence[float] = (0.5, 9.0),
    video_path=None,
    goal_size: Sequence[float] | None = None,
    obstacle_frac: float = 0.0,
    obstacle_distance: Sequence[float] = (0.25, 1.5),
    obstacle_yaw_spread: float = 0.5,
) -> Iterator[View]:
    """Renders ``n`` views of ``split``, lazily (see the module docstring).

    Args:
        split: ``"train"``, ``"val"`` or ``"test"``.
        n: number of views.
        seed: seed of the poses and appearance.
        image_size: ``(height, width)`` (or an int), each >= 32.
        layout_seed: seed of the layout generators (the "world").
        goal_absent_frac: share of views drawn looking away from the goal.
        start_frac: share of the other views drawn around the layout's start
            pose (goal often partly hidden by an obstacle).
        views_per_layout: consecutive views that share a layout.
        min_fraction: smallest share of the image the goal must cover for a box.
        fov_deg: vertical field of view (the env's ``fov_deg``).
        max_depth: depth clip (m, the env's ``max_depth``).
        max_tilt_deg: largest random roll / pitch (deg).
        randomize_appearance: randomise lighting and tints per view.
        start: number of the first view (views ``start .. start + n - 1``).
        goal_distance: ``(low, high)`` horizontal distance (m) of ``"goal"`` views
            from the board's centre, drawn log-uniformly (default 0.5-9 m; e.g.
            ``(0.3, 1.2)`` for close-ups where the board fills the view).
        video_path: a :class:`~torchrl_causal.perception.video_path.VideoPath`:
            each view's RGB is rendered at its ``stream_size`` (the Tello's
            960 x 720), sent through it (camera jitter, H.264 in a continuing
            stream) and centre-cropped and resized to ``image_size`` as
            ``TelloEnv`` does (:func:`~torchrl_causal.perception.video_path.crop_resize`);
            depth and box stay exact (rendered at ``image_size``: the crop keeps
            the vertical field of view, so the two renders show the same view).
            ``image_size`` must not be wider than the stream's aspect.
        goal_size: ``(width, height)`` (m) of every goal board (e.g. the printed
            board of a real flight) instead of the layouts' drawn sizes; the
            layouts then differ from the default ones (see
            :class:`~torchrl_causal.envs.layouts.RandomLayoutGenerator`).
        obstacle_frac: share of views drawn as obstacle close-ups (kind
            ``"obstacle"``; drawn after ``goal_absent_frac``, so the default 0
            leaves every other view as it was). Their box is the goal's as the
            segmentation sees it, usually none.
        obstacle_distance: ``(low, high)`` horizontal distance (m) of
            ``"obstacle"`` views from the obstacle's surface, log-uniform.
        obstacle_yaw_spread: how far an ``"obstacle"`` view's heading strays
            from the bearing of the obstacle's centre, as a fraction of half the
            horizontal field of view (uniform in +-``spread``; default 0.5, the
            obstacle ahead; above 1 the obstacle is often at the image's side
            edge, the close-ups a sideways pass or a turn beside it shows).

    Yields:
        :class:`View` objects.

    Raises:
        ValueError: on a bad option (before anything is rendered).

    Example:
        >>> v = next(render_views("test", 1, seed=3, image_size=64))
        >>> v.split, v.rgb.shape, v.box is None or v.goal_pixels >= 0.0028 * 64 * 64
        ('test', (64, 64, 3), True)
    """
    if split not in DATASET_SPLITS:
        raise ValueError(f"split must be one of {DATASET_SPLITS}, got {split!r}")
    n = _check_int("n", n, 0)
    seed = _check_int("seed", seed, 0)
    layout_seed = _check_int("layout_seed", layout_seed, 0)
    start = _check_int("start", start, 0)
    views_per_layout = _check_int("views_per_layout", views_per_layout, 1)
    h, w = _check_image_size(image_size)
    goal_absent_frac = _check_frac("goal_absent_frac", goal_absent_frac)
    start_frac = _check_frac("start_frac", start_frac)
    min_fraction = _check_frac("min_fraction", min_fraction)
    max_tilt_deg = _check_frac("max_tilt_deg", max_tilt_deg, high=45.0)
    if not isinstance(fov_deg, (int, float)) or not 0 < fov_deg < 180:
        raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg!r}")
    if not isinstance(max_depth, (int, float)) or not max_depth > 0:
        raise ValueError(f"max_depth must be > 0, got {max_depth!r}")
    try:
        lo, hi = (float(v) for v in goal_distance)
    except (TypeError, ValueError):
        lo = hi = float("nan")
    if not 0 < lo < hi:
        raise ValueError(f"goal_distance must be (low, high) with 0 < low < high, "
                         f"got {goal_distance!r}")
    obstacle_frac = _check_frac("obstacle_frac", obstacle_frac)
    if goal_absent_frac + obstacle_frac > 1.0:
        raise ValueError(f"goal_absent_frac + obstacle_frac must be <= 1, got "
                         f"{goal_absent_frac} + {obstacle_frac}")
    try:
        olo, ohi = (float(v) for v in obstacle_distance)
    except (TypeError, ValueError):
        olo = ohi = float("nan")
    if not 0.2 <= olo < ohi:
        raise ValueError(f"obstacle_distance must be (low, high) with 0.2 <= low < high "
                         f"(the drone's clearance is 0.18 m), got {obstacle_distance!r}")
    if isinstance(obstacle_yaw_spread, bool) or not isinstance(obstacle_yaw_spread, (int, float)) \
            or not 0.0 <= obstacle_yaw_spread <= 3.0:
        raise ValueError(f"obstacle_yaw_spread must be a number in [0, 3] (fractions of half "
                         f"the field of view), got {obstacle_yaw_spread!r}")
    from ..envs.layouts import check_goal_size

    goal_size = check_goal_size(goal_size)
    if video_path is not None:
        from .video_path import VideoPath

        if not isinstance(video_path, VideoPath):
            raise ValueError(f"video_path must be a VideoPath or None, got {video_path!r}")
        sh, sw = video_path.stream_size
        if w * sh > sw * h:
            raise ValueError(f"image_size {(h, w)} is wider than the video stream "
                             f"{video_path.stream_size}: its view cannot be cropped from it")
    return _render(
        split, n, seed, (h, w), layout_seed, goal_absent_frac, start_frac, views_per_layout,
        min_fraction, float(fov_deg), float(max_depth), max_tilt_deg,
        bool(randomize_appearance), start, (lo, hi), video_path, goal_size,
        obstacle_frac, (olo, ohi), float(obstacle_yaw_spread),
    )


def _render(
    split, n, seed, image_size, layout_seed, absent_frac, start_frac, per_layout,
    min_fraction, fov_deg, max_depth, max_tilt, randomize, start, goal_distance=(0.5, 9.0),
    video_path=None, goal_size=None, obstacle_frac=0.0, obstacle_distance=(0.25, 1.5),
    obstacle_yaw_spread=0.5,
) -> Iterator[View]:
    from ..envs.drone import DroneNavEnv
    from ..envs.scene import SceneRenderer

    if n == 0:
        return
    gen_split = "heldout" if split == "test" else "train"
    env = DroneNavEnv(
        "random",
        split=gen_split,
        layout_seed=layout_seed,
        goal_size=goal_size,
        image_size=image_size,
        fov_deg=fov_deg,
        max_depth=max_depth,
        seed=0,
    )
    h, w = image_size
    min_pixels = min_fraction * h * w
    last_layout = (start + n - 1) // per_layout
    indices = layout_indices(split, last_layout + 1)
    appearance = None
    current = None
    stream = None  # the video path's renderer, at the stream's size
    try:
        for i in range(start, start + n):
            lay_idx = indices[i // per_layout]
            if lay_idx != current:
                env.layout_index = lay_idx
                env._load(env._select_layout())
                appearance = _Appearance(env.model, env.ids)
                current = lay_idx
                if video_path is not None:
                    sh, sw = video_path.stream_size
                    g = env.model.vis.global_
                    g.offwidth, g.offheight = max(g.offwidth, sw), max(g.offheight, sh)
                    if stream is None:
                        stream = SceneRenderer(env.model, sh, sw, camera=env.ids.camera,
                                               max_depth=max_depth)
                    else:
                        stream.set_model(env.model, env.ids.camera)
            rng = np.random.default_rng(
                np.random.SeedSequence([seed, _SPLIT_ID[split], i, layout_seed])
            )
            u = rng.uniform()
            if u < absent_frac:
                kind = "absent"
            elif u < absent_frac + obstacle_frac:
                kind = "obstacle"
            elif rng.uniform() < start_frac:
                kind = "start"
            else:
                kind = "goal"
            x, y, z, yaw = _draw_pose(rng, env.layout, kind, env.hfov_deg, goal_distance,
                                      obstacle_distance, obstacle_yaw_spread)
            pitch, roll = rng.uniform(-max_tilt, max_tilt, size=2) if max_tilt > 0 else (0.0, 0.0)
            if randomize:
                appearance.apply(rng)
            qa = env.ids.qpos_adr
            env.data.qpos[qa : qa + 3] = (x, y, z)
            env.data.qpos[qa + 3 : qa + 7] = _quat(yaw, float(pitch), float(roll))
            obs = env._observe(False, False)  # the env's own render + segmentation box
            count = int(obs["goal_pixels"][0])
            box = tuple(float(v) for v in obs["goal_box"].tolist())
            rgb = obs["pixels"].numpy().copy()
            if video_path is not None:  # the same view through the camera path
                from .video_path import crop_resize

                frame, _ = stream.render(env.data)  # kinematics / lights set by _observe
                rgb = crop_resize(video_path(frame.copy()), (h, w)).numpy()
            yield View(
                rgb=rgb,
                depth=obs["depth"].numpy().copy(),
                box=box if count > 0 and count >= min_pixels else None,
                goal_pixels=count,
                layout_index=int(lay_idx),
                split=split,
                index=i,
                kind=kind,
                pose=(x, y, z, yaw, float(pitch), float(roll)),
            )
    finally:
        if stream is not None:
            stream.close()
        env.close()


# --------------------------------------------------------------------------- writing
def _yolo_line(box, h: int, w: int) -> str:
    x0, y0, x1, y1 = box
    return (
        f"0 {(x0 + x1) / 2 / w:.6f} {(y0 + y1) / 2 / h:.6f} {(x1 - x0) / w:.6f} {(y1 - y0) / h:.6f}\n"
    )


def write_datasets(
    root: str | os.PathLike,
    *,
    n_train: int,
    n_val: int,
    n_test: int,
    seed: int,
    image_size: int | Sequence[int] = (240, 320),
    layout_seed: int = 0,
    progress: bool = True,
    **view_options,
) -> dict:
    """Writes the YOLO detection dataset and the RGB / depth dataset under ``root``.

    Layout::

        root/yolo/data.yaml                      (absolute paths, nc: 1, names: [heliport])
        root/yolo/images/{train,val,test}/*.png
        root/yolo/labels/{train,val,test}/*.txt  ("0 xc yc w h" normalised; empty = background)
        root/depth/{train,val,test}.npz          (rgb uint8 [N,H,W,3], depth float16 [N,H,W] m,
                                                  layout int32 [N], box float32 [N,4] (NaN: none),
                                                  goal_pixels int32 [N])
        root/meta.json                           (the options and counts)

    Args:
        root: output folder (created).
        n_train: train views.
        n_val: val views.
        n_test: test views (held-out layouts).
        seed: seed of the views (see :func:`render_views`).
        image_size: ``(height, width)``.
        layout_seed: seed of the layout generators.
        progress: show a tqdm progress bar.
        **view_options: passed on to :func:`render_views`.

    Returns:
        The metadata written to ``meta.json`` (counts, positives, options, seconds).

    Example:
        >>> import tempfile, pathlib
        >>> d = tempfile.mkdtemp()
        >>> meta = write_datasets(d, n_train=2, n_val=1, n_test=1, seed=0, image_size=(48, 64),
        ...                       progress=False)
        >>> sorted(p.name for p in (pathlib.Path(d) / "depth").iterdir())
        ['test.npz', 'train.npz', 'val.npz']
        >>> meta["counts"]
        {'train': 2, 'val': 1, 'test': 1}
    """
    counts = {
        "train": _check_int("n_train", n_train, 1),
        "val": _check_int("n_val", n_val, 1),
        "test": _check_int("n_test", n_test, 0),
    }
    seed = _check_int("seed", seed, 0)
    h, w = _check_image_size(image_size)
    # validate the view options now (render_views is lazy about rendering only)
    render_views("train", 0, seed=seed, image_size=(h, w), layout_seed=layout_seed, **view_options)
    import cv2

    root = Path(root).resolve()
    yolo = root / "yolo"
    for sub in ("images", "labels"):
        for s in DATASET_SPLITS:
            (yolo / sub / s).mkdir(parents=True, exist_ok=True)
    (root / "depth").mkdir(parents=True, exist_ok=True)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=sum(counts.values()), desc="rendering", unit="view")
    t0 = time.perf_counter()
    positives = {}
    for s in DATASET_SPLITS:
        n = counts[s]
        rgb = np.empty((n, h, w, 3), np.uint8)
        depth = np.empty((n, h, w), np.float16)
        layout = np.empty(n, np.int32)
        boxes = np.full((n, 4), np.nan, np.float32)
        pixels = np.empty(n, np.int32)
        for k, v in enumerate(
            render_views(s, n, seed=seed, image_size=(h, w), layout_seed=layout_seed, **view_options)
        ):
            rgb[k], depth[k], layout[k], pixels[k] = v.rgb, v.depth, v.layout_index, v.goal_pixels
            name = f"{s}_{k:06d}"
            cv2.imwrite(str(yolo / "images" / s / f"{name}.png"), v.rgb[..., ::-1])
            with open(yolo / "labels" / s / f"{name}.txt", "w") as f:
                if v.box is not None:
                    boxes[k] = v.box
                    f.write(_yolo_line(v.box, h, w))
            if bar is not None:
                bar.update(1)
        positives[s] = int(np.isfinite(boxes[:, 0]).sum())
        np.savez_compressed(
            root / "depth" / f"{s}.npz",
            rgb=rgb, depth=depth, layout=layout, box=boxes, goal_pixels=pixels,
        )
    if bar is not None:
        bar.close()
    (yolo / "data.yaml").write_text(
        f"path: {yolo}\n"
        f"train: {yolo / 'images' / 'train'}\n"
        f"val: {yolo / 'images' / 'val'}\n"
        f"test: {yolo / 'images' / 'test'}\n"
        "nc: 1\n"
        'names: ["heliport"]\n'
    )
    meta = {
        "counts": counts,
        "positives": positives,
        "seed": seed,
        "layout_seed": int(layout_seed),
        "image_size": [h, w],
        "view_options": {k: (v.to_dict() if hasattr(v, "to_dict") else v)
                         for k, v in view_options.items()},
        "seconds": round(time.perf_counter() - t0, 1),
    }
    (root / "meta.json").write_text(json.dumps(meta, indent=1) + "\n")
    return meta


def load_views(root: str | os.PathLike, split: str) -> list[View]:
    """Reads a split written by :func:`write_datasets` back as views (from the ``.npz``).

    Example:
        >>> import tempfile
        >>> d = tempfile.mkdtemp()
        >>> _ = write_datasets(d, n_train=1, n_val=1, n_test=2, seed=0, image_size=48,
        ...                    progress=False)
        >>> [v.split for v in load_views(d, "test")]
        ['test', 'test']
    """
    if split not in DATASET_SPLITS:
        raise ValueError(f"split must be one of {DATASET_SPLITS}, got {split!r}")
    path = Path(root) / "depth" / f"{split}.npz"
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} does not exist: write it with "
            "`python -m torchrl_causal.perception.dataset --out DIR ...`"
        )
    with np.load(path) as f:  # (every f[key] decompresses the whole array: read each once)
        z = {k: f[k] for k in ("rgb", "depth", "layout", "box", "goal_pixels")}
    out = []
    for k in range(len(z["layout"])):
        b = z["box"][k]
        out.append(
            View(
                rgb=z["rgb"][k],
                depth=z["depth"][k].astype(np.float32),
                box=None if not np.isfinite(b[0]) else tuple(float(v) for v in b),
                goal_pixels=int(z["goal_pixels"][k]),
                layout_index=int(z["layout"][k]),
                split=split,
                index=k,
            )
        )
    return out


# --------------------------------------------------------------------------- evaluation
def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU matrix of boxes ``a [N, 4]`` and ``b [M, 4]`` (``x0, y0, x1, y1``).

    Example:
        >>> iou = box_iou(np.array([[0, 0, 2, 2.]]), np.array([[1, 0, 3, 2.], [0, 0, 2, 2]]))
        >>> iou.shape, [round(float(x), 3) for x in iou[0]]
        ((1, 2), [0.333, 1.0])
    """
    a = np.asarray(a, np.float64).reshape(-1, 4)
    b = np.asarray(b, np.float64).reshape(-1, 4)
    ix = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    iy = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = ix * iy
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def _average_precision(scores, tp, npos) -> float:
    """Area under the interpolated precision / recall curve (101 points, as COCO)."""
    if npos == 0:
        return float("nan")
    if len(scores) == 0:
        return 0.0
    order = np.argsort(-np.asarray(scores), kind="stable")
    tp = np.asarray(tp, np.float64)[order]
    ctp = np.cumsum(tp)
    cfp = np.cumsum(1.0 - tp)
    recall = ctp / npos
    precision = ctp / np.maximum(ctp + cfp, 1e-12)
    mpre = np.concatenate([[1.0], precision, [0.0]])
    mrec = np.concatenate([[0.0], recall, [1.0]])
    mpre = np.flip(np.maximum.accumulate(np.flip(mpre)))
    x = np.linspace(0, 1, 101)
    return float(np.trapezoid(np.interp(x, mrec, mpre), x))


def evaluate_detector(
    detector,
    views_or_dataset_dir,
    *,
    split: str = "test",
    conf_threshold: float = 0.7,
    iou_threshold: float = 0.5,
    batch_size: int = 16,
    max_views: int | None = None,
) -> dict:
    """Precision, recall and mAP50 of a :class:`~torchrl_causal.perception.goal.GoalDetector`.

    A ground-truth positive is a view with a box (the goal covers at least the
    dataset's ``min_fraction`` of the image). A detection is a true positive
    when its IoU with the view's box is >= ``iou_threshold`` (one match per
    box, best score first). ``precision`` / ``recall`` count the detections
    scoring above ``conf_threshold`` (the thesis's 0.7 rule of the
    :class:`~torchrl_causal.perception.goal.GoalMeter`); ``map50`` is the
    101-point average precision over all returned detections (ranked by
    score); ``precision_best_f1`` / ``recall_best_f1`` / ``conf_best_f1`` are the
    point of the precision/recall curve with the best F1 (what ultralytics
    prints). ``image_accuracy`` is the share of views where "best score > conf"
    agrees with "has a box" (the ``goal_in_sight`` decision);
    ``false_sight_rate`` is the share of views *without* a box where some
    detection scores above ``conf_threshold`` (a goal seen where there is none:
    on obstacle close-ups, the arrival rule's false "reached").

    Args:
        detector: a ``GoalDetector`` (called with ``pixels uint8 [B, H, W, 3]``,
            ``depth`` and the ground truth ``gt_box`` / ``gt_pixels``).
        views_or_dataset_dir: an iterable of :class:`View` or a dataset root
            written by :func:`write_datasets` (reads ``depth/<split>.npz``).
        split: the split to read from a dataset root.
        conf_threshold: the in-sight rule.
        iou_threshold: IoU for a match.
        batch_size: frames per detector call.
        max_views: evaluate at most this many views.

    Returns:
        dict with ``precision``, ``recall``, ``map50``, ``f1``,
        ``precision_best_f1``, ``recall_best_f1``, ``conf_best_f1``,
        ``image_accuracy``, ``false_sight_rate``, ``n_views``, ``n_positives``,
        ``ms_per_frame``.

    Example:
        >>> from torchrl_causal.perception.goal import SimGoalDetector
        >>> views = list(render_views("test", 4, seed=1, image_size=48))
        >>> m = evaluate_detector(SimGoalDetector(min_pixels=7), views)
        >>> m["n_views"], m["precision"] in (1.0, 0.0) or m["n_positives"] == 0
        (4, True)
    """
    import torch

    if isinstance(views_or_dataset_dir, (str, os.PathLike)):
        views = load_views(views_or_dataset_dir, split)
    else:
        views = list(views_or_dataset_dir)
    if max_views is not None:
        views = views[: _check_int("max_views", max_views, 1)]
    _check_frac("conf_threshold", conf_threshold)
    _check_frac("iou_threshold", iou_threshold)
    batch_size = _check_int("batch_size", batch_size, 1)
    all_scores, all_tp = [], []
    tp_at = fp_at = 0
    agree = 0
    npos = 0
    false_sight = 0
    seconds = 0.0
    for b0 in range(0, len(views), batch_size):
        chunk = views[b0 : b0 + batch_size]
        pixels = torch.from_numpy(np.stack([v.rgb for v in chunk]))
        depth = torch.from_numpy(np.stack([v.depth for v in chunk]).astype(np.float32))
        gt_box = torch.tensor(
            [v.box if v.box is not None else (0.0, 0.0, 0.0, 0.0) for v in chunk],
            dtype=torch.float32,
        )
        gt_pixels = torch.tensor([float(v.goal_pixels) for v in chunk])
        t0 = time.perf_counter()
        boxes, scores = detector(pixels, depth, gt_box=gt_box, gt_pixels=gt_pixels)
        seconds += time.perf_counter() - t0
        boxes = torch.as_tensor(boxes, dtype=torch.float32).reshape(len(chunk), -1, 4).numpy()
        scores = torch.as_tensor(scores, dtype=torch.float32).reshape(len(chunk), -1).numpy()
        for v, bx, sc in zip(chunk, boxes, scores):
            keep = sc > 0
            bx, sc = bx[keep], sc[keep]
            order = np.argsort(-sc, kind="stable")
            bx, sc = bx[order], sc[order]
            tp = np.zeros(len(sc))
            if v.box is not None:
                npos += 1
                if len(sc):
                    iou = box_iou(bx, np.asarray([v.box]))[:, 0]
                    hit = np.flatnonzero(iou >= iou_threshold)
                    if hit.size:
                        tp[hit[0]] = 1.0  # the best-scoring match; the rest are duplicates
            all_scores.extend(sc.tolist())
            all_tp.extend(tp.tolist())
            above = sc > conf_threshold
            tp_at += int(tp[above].sum())
            fp_at += int(above.sum() - tp[above].sum())
            agree += int(bool(above.any()) == (v.box is not None))
            false_sight += int(v.box is None and bool(above.any()))
    precision = tp_at / (tp_at + fp_at) if tp_at + fp_at else float("nan")
    recall = tp_at / npos if npos else float("nan")
    f1 = (
        2 * precision * recall / (precision + recall)
        if npos and tp_at and precision + recall > 0
        else 0.0
    )
    # best-F1 point of the curve
    p_best = r_best = c_best = float("nan")
    if all_scores and npos:
        order = np.argsort(-np.asarray(all_scores), kind="stable")
        s = np.asarray(all_scores)[order]
        t = np.asarray(all_tp)[order]
        ctp, cfp = np.cumsum(t), np.cumsum(1 - t)
        p, r = ctp / (ctp + cfp), ctp / npos
        f = 2 * p * r / np.maximum(p + r, 1e-12)
        k = int(np.argmax(f))
        p_best, r_best, c_best = float(p[k]), float(r[k]), float(s[k])
    n = len(views)
    return {
        "precision": precision,
        "recall": recall,
        "f1": f1,
        "map50": _average_precision(all_scores, all_tp, npos),
        "precision_best_f1": p_best,
        "recall_best_f1": r_best,
        "conf_best_f1": c_best,
        "image_accuracy": agree / n if n else float("nan"),
        "false_sight_rate": false_sight / (n - npos) if n > npos else float("nan"),
        "n_views": n,
        "n_positives": npos,
        "conf_threshold": float(conf_threshold),
        "iou_threshold": float(iou_threshold),
        "ms_per_frame": 1e3 * seconds / n if n else float("nan"),
    }


# --------------------------------------------------------------------------- CLI
def main(argv: Sequence[str] | None = None) -> dict:
    """``python -m torchrl_causal.perception.dataset`` (see :func:`write_datasets`)."""
    p = argparse.ArgumentParser(
        prog="python -m torchrl_causal.perception.dataset",
        description="Render the YOLO heliport dataset and the RGB/depth dataset with DroneNavEnv.",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--n-train", type=int, required=True)
    p.add_argument("--n-val", type=int, required=True)
    p.add_argument("--n-test", type=int, required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--image-size", type=int, nargs=2, default=(240, 320), metavar=("H", "W"))
    p.add_argument("--layout-seed", type=int, default=0)
    p.add_argument("--goal-absent-frac", type=float, default=0.2)
    p.add_argument("--views-per-layout", type=int, default=8)
    p.add_argument("--start-frac", type=float, default=0.2)
    p.add_argument("--goal-distance", type=float, nargs=2, default=(0.5, 9.0),
                   metavar=("LOW", "HIGH"), help="distance range (m) of views of the goal")
    p.add_argument("--video-path", action="store_true",
                   help="RGB through the Tello camera path: rendered at 960x720, jitter, "
                        "H.264 at the emulator's settings, cropped/resized to --image-size")
    p.add_argument("--goal-size", type=float, nargs=2, default=None, metavar=("W", "H"),
                   help="every goal board this size (m), e.g. 1.0 0.8 for the thesis board "
                        "(default: the layouts' drawn sizes, 0.7-1.2 x 0.6-0.9 m)")
    p.add_argument("--obstacle-frac", type=float, default=0.0,
                   help="share of views drawn as obstacle close-ups (hard negatives for the "
                        "detector, near obstacles for MonoDepth)")
    p.add_argument("--obstacle-distance", type=float, nargs=2, default=(0.25, 1.5),
                   metavar=("LOW", "HIGH"),
                   help="distance range (m) of obstacle close-ups from the obstacle's surface")
    p.add_argument("--obstacle-yaw-spread", type=float, default=0.5, metavar="F",
                   help="obstacle close-ups' heading off the obstacle's centre, up to F x half "
                        "the field of view (default 0.5: ahead; 1.6: often at the side edge)")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    extra = {}
    if a.obstacle_frac:
        extra["obstacle_frac"] = a.obstacle_frac
        extra["obstacle_distance"] = tuple(a.obstacle_distance)
    if a.obstacle_yaw_spread != 0.5:  # checked by render_views, before anything is rendered
        extra["obstacle_yaw_spread"] = a.obstacle_yaw_spread
    if a.goal_size is not None:
        extra["goal_size"] = tuple(a.goal_size)
    if a.video_path:
        from .video_path import VideoPath

        extra["video_path"] = VideoPath(seed=a.seed)
    meta = write_datasets(
        a.out,
        n_train=a.n_train,
        n_val=a.n_val,
        n_test=a.n_test,
        seed=a.seed,
        image_size=tuple(a.image_size),
        layout_seed=a.layout_seed,
        goal_absent_frac=a.goal_absent_frac,
        start_frac=a.start_frac,
        goal_distance=tuple(a.goal_distance),
        views_per_layout=a.views_per_layout,
        progress=not a.no_progress,
        **extra,
    )
    # the command that made the data set, for the weights' provenance (train_depth.py)
    meta["command"] = "python -m torchrl_causal.perception.dataset " + shlex.join(
        sys.argv[1:] if argv is None else list(argv))
    (Path(a.out) / "meta.json").write_text(json.dumps(meta, indent=1) + "\n")
    print(json.dumps(meta), file=sys.stdout)
    return meta


if __name__ == "__main__":
    main()
