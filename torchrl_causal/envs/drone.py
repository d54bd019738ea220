"""``DroneNavEnv``: visual drone navigation to a heliport sign, in MuJoCo (TorchRL ``EnvBase``).

See :doc:`/envs` for the user guide (options, keys, layouts, splits, execution
modes, reward).
"""

from __future__ import annotations

import math
import os
import time
from collections import OrderedDict

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tensordict import TensorDict, TensorDictBase  # noqa: E402
from torchrl.data import Bounded, Unbounded  # noqa: E402
from torchrl.envs import EnvBase  # noqa: E402

from ..perception.goal import (  # noqa: E402
    GoalDetector,
    GoalMeter,
    SimGoalDetector,
    horizontal_fov,
)
from .control import KinematicExecutor, PhysicsExecutor, action_deltas  # noqa: E402
from .layouts import (  # noqa: E402
    SPLITS,
    Layout,
    RandomLayoutGenerator,
    check_goal_size,
    thesis_layout,
)
from .rewards import REWARDS, StepOutcome, make_reward  # noqa: E402
from .scene import SceneRenderer, build_model  # noqa: E402
from .specs import navigation_specs  # noqa: E402

__all__ = ["DroneNavEnv", "EXECUTION_MODES", "LAYOUTS", "REWARDS"]

#: Accepted values of the ``execution`` option.
EXECUTION_MODES: tuple[str, ...] = ("kinematic", "physics")
#: Accepted layout names (a :class:`~torchrl_causal.envs.layouts.Layout` is accepted too).
LAYOUTS: tuple[str, ...] = ("thesis", "random")

_OBS_KEYS = (
    "pixels",
    "depth",
    "altitude",
    "goal_box",
    "goal_pixels",
    "goal_true_distance",
    "goal_true_bearing",
    "goal_in_sight",
    "goal_distance",
    "goal_angle",
    "crashed",
    "reached",
    "out_of_bounds",
)


def _scalars_count(count: int) -> torch.Tensor:
    return torch.from_numpy(np.array([count], dtype=np.float32))


def _positive(name, value, allow_zero=False):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value >= 0 if allow_zero else value > 0)
    if not ok:
        need = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be a finite number {need}, got {value!r}")


class DroneNavEnv(EnvBase):
    """Drone navigation to a heliport-marked goal board, rendered by MuJoCo.

    One env is unbatched (``batch_size=[]``); batch it with
    :class:`~torchrl.envs.SerialEnv` / :class:`~torchrl.envs.ParallelEnv`.
    Observations (per env): ``pixels`` uint8 ``[H, W, 3]``; ``depth`` float32
    ``[H, W]`` (metric z-depth, clipped to ``max_depth``); ``altitude`` float32
    ``[1]``; simulation ground truth ``goal_box`` ``[4]`` (visible box
    ``x0, y0, x1, y1``, exclusive ends, zeros if not visible), ``goal_pixels``
    ``[1]``, ``goal_true_distance`` ``[1]`` (camera to board centre, m),
    ``goal_true_bearing`` ``[1]`` (deg, positive = left); the goal measurement
    of :attr:`goal_meter` used by the reward: ``goal_in_sight`` bool ``[1]``,
    ``goal_distance`` ``[1]`` (m, 0 when not in sight), ``goal_angle`` ``[1]``
    (deg, positive = left, 0 when not in sight); ``crashed``, ``reached`` and
    ``out_of_bounds`` bool ``[1]``. Action: ``Categorical(8)`` in
    :data:`~torchrl_causal.schema.ACTION_NAMES` order.

    Reward (:mod:`torchrl_causal.envs.rewards`): ``reward="progress"``
    (default): ``+10`` on reaching the goal point, ``-10`` on a crash or a
    geofence exit, else the metres of progress towards the goal point minus
    ``0.01``. ``reward="thesis"`` (thesis sec. 5.1, exactly): ``-1000`` on a
    crash (or geofence exit), ``+1000`` on reaching, else
    ``100 - goal_distance - |goal_angle|`` if the goal is recognised
    (``goal_in_sight``), else ``-9``. Termination on crash, reach or leaving
    the layout's flight volume (an open layout's geofence), truncation after
    ``max_steps`` steps.

    Args:
        layout: ``"thesis"`` (default scene, thesis Fig. 2.3), ``"random"``
            (seeded generator, see ``split``) or a
            :class:`~torchrl_causal.envs.layouts.Layout`.
        split: random-layout split, ``"train"`` or ``"heldout"``.
        layout_seed: seed of the random-layout generator (the "world").
        layout_index: pin one random layout (else a layout is drawn at every
            reset from the env's seeded generator).
        n_layouts: draw random layouts from indices ``[0, n_layouts)`` only
            (None: unbounded).
        goal_size: random layouts only: ``(width, height)`` (m) of every goal
            board, e.g. the printed board of a real flight, instead of a drawn
            size (``RandomLayoutGenerator(goal_size=)``). ``None``: drawn.
        board_back: ``"heliport"`` (default: the back of the board shows the
            heliport, as in every render the shipped models were trained on) or
            ``"blank"`` (a printed board's plain back;
            :func:`~torchrl_causal.envs.scene.build_model`).
        execution: ``"kinematic"`` or ``"physics"`` (see
            :mod:`torchrl_causal.envs.control`).
        step_size: translation per move action (m).
        turn_deg: rotation per turn action (deg).
        image_size: ``int`` or ``(height, width)``, each >= 32.
        fov_deg: vertical field of view of the camera (deg).
        max_depth: depth clip (m).
        max_steps: truncation horizon.
        reach_radius: the drone's centre within this distance of the goal
            point counts as reached (m).
        reward: ``"progress"`` (default), ``"thesis"`` (see
            :data:`~torchrl_causal.envs.rewards.REWARDS`) or a callable of a
            :class:`~torchrl_causal.envs.rewards.StepOutcome`.
        goal_min_pixels: visible goal pixels the default detector needs.
        detector: a :class:`~torchrl_causal.perception.goal.GoalDetector`
            (default ``SimGoalDetector(min_pixels=goal_min_pixels)``).
        confidence_threshold: detector score needed for ``goal_in_sight``.
        altitude_noise_std: std of the barometer noise (m).
        position_noise_std: kinematic mode: std of the executed move's noise (m).
        yaw_noise_std_deg: kinematic mode: std of the executed turn's noise (deg).
        action_duration: physics mode: simulated seconds per action.
        physics_timestep: physics time step (s).
        seed: initial seed (None: random). It draws the random layouts; the noise
            (barometer, moves, turns) of episode ``i`` after a seed draws from its
            own generator, ``numpy.random.default_rng([seed, i])``
            (:attr:`episode_noise_seed`), so an episode's noise does not depend
            on what earlier episodes did: two runs of one setting and seed fly
            the same layouts under the same noise.
        device: device of the output tensors.

    Example:
        >>> env = DroneNavEnv(seed=0)
        >>> td = env.reset()
        >>> td["pixels"].shape, td["depth"].dtype, bool(td["goal_in_sight"])
        (torch.Size([84, 84, 3]), torch.float32, True)
        >>> td = env.rand_step(td)
        >>> sorted(td["next"].keys())[:4]
        ['altitude', 'crashed', 'depth', 'done']
        >>> env.close()
    """

    batch_locked = True

    def __init__(
        self,
        layout: str | Layout = "thesis",
        *,
        split: str = "train",
        layout_seed: int = 0,
        layout_index: int | None = None,
        n_layouts: int | None = None,
        goal_size: tuple[float, float] | None = None,
        board_back: str = "heliport",
        execution: str = "kinematic",
        step_size: float = 0.25,
        turn_deg: float = 15.0,
        image_size: int | tuple[int, int] = 84,
        fov_deg: float = 60.0,
        max_depth: float = 10.0,
        max_steps: int = 200,
        reach_radius: float = 0.2,
        reward="progress",
        goal_min_pixels: int = 20,
        detector: GoalDetector | None = None,
        confidence_threshold: float = 0.7,
        altitude_noise_std: float = 0.0,
        position_noise_std: float = 0.0,
        yaw_noise_std_deg: float = 0.0,
        action_duration: float = 1.0,
        physics_timestep: float = 0.02,
        seed: int | None = None,
        device: torch.device | str | None = None,
    ):
        # ---- validate everything before MuJoCo is touched ----
        if not (isinstance(layout, Layout) or layout in LAYOUTS):
            raise ValueError(f"layout must be one of {LAYOUTS} or a Layout, got {layout!r}")
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if execution not in EXECUTION_MODES:
            raise ValueError(f"execution must be one of {EXECUTION_MODES}, got {execution!r}")
        if isinstance(image_size, (int, np.integer)) and not isinstance(image_size, bool):
            image_size = (int(image_size), int(image_size))
        if (
            not isinstance(image_size, (tuple, list))
            or len(image_size) != 2
            or not all(isinstance(v, (int, np.integer)) and v >= 32 for v in image_size)
        ):
            raise ValueError(
                f"image_size must be an int or (height, width) pair, each >= 32, got {image_size!r}"
            )
        _positive("step_size", step_size)
        _positive("turn_deg", turn_deg)
        if not (isinstance(fov_deg, (int, float)) and 0 < fov_deg < 180):
            raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg!r}")
        _positive("max_depth", max_depth)
        if not isinstance(max_steps, (int, np.integer)) or isinstance(max_steps, bool) or max_steps < 1:
            raise ValueError(f"max_steps must be an int >= 1, got {max_steps!r}")
        _positive("reach_radius", reach_radius)
        self.reward_fn = make_reward(reward)
        if not isinstance(goal_min_pixels, (int, np.integer)) or goal_min_pixels < 1:
            raise ValueError(f"goal_min_pixels must be an int >= 1, got {goal_min_pixels!r}")
        if detector is not None and not isinstance(detector, GoalDetector):
            raise ValueError(f"detector must be a GoalDetector, got {detector!r}")
        if not (isinstance(confidence_threshold, (int, float)) and 0 <= confidence_threshold <= 1):
            raise ValueError(
                f"confidence_threshold must be in [0, 1], got {confidence_threshold!r}"
            )
        _positive("altitude_noise_std", altitude_noise_std, allow_zero=True)
        _positive("position_noise_std", position_noise_std, allow_zero=True)
        _positive("yaw_noise_std_deg", yaw_noise_std_deg, allow_zero=True)
        _positive("action_duration", action_duration)
        _positive("physics_timestep", physics_timestep)
        if physics_timestep > action_duration:
            raise ValueError(
                f"physics_timestep must be <= action_duration, got {physics_timestep!r}"
            )
        if not isinstance(layout_seed, (int, np.integer)) or layout_seed < 0:
            raise ValueError(f"layout_seed must be an int >= 0, got {layout_seed!r}")
        if layout_index is not None and (
            not isinstance(layout_index, (int, np.integer)) or layout_index < 0
        ):
            raise ValueError(f"layout_index must be None or an int >= 0, got {layout_index!r}")
        if n_layouts is not None and (not isinstance(n_layouts, (int, np.integer)) or n_layouts < 1):
            raise ValueError(f"n_layouts must be None or an int >= 1, got {n_layouts!r}")
        if seed is not None and (not isinstance(seed, (int, np.integer)) or seed < 0):
            raise ValueError(f"seed must be None or an int >= 0, got {seed!r}")
        goal_size = check_goal_size(goal_size)
        if board_back not in ("heliport", "blank"):
            raise ValueError(f"board_back must be 'heliport' or 'blank', got {board_back!r}")
        if goal_size is not None and layout != "random":
            raise ValueError(f"goal_size applies to layout='random' only, got layout={layout!r} "
                             f"with goal_size={goal_size!r}")

        super().__init__(device=device if device is not None else "cpu", batch_size=torch.Size([]))
        self._to_device = self.device.type != "cpu"
        self.layout_option = layout
        self.board_back = board_back
        self.split = split
        self.execution = execution
        self.step_size = float(step_size)
        self.turn_deg = float(turn_deg)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.fov_deg = float(fov_deg)
        self.max_depth = float(max_depth)
        self.max_steps = int(max_steps)
        self.reach_radius = float(reach_radius)
        self.altitude_noise_std = float(altitude_noise_std)
        self.position_noise_std = float(position_noise_std)
        self.yaw_noise_std_deg = float(yaw_noise_std_deg)
        self.action_duration = float(action_duration)
        self.physics_timestep = float(physics_timestep)
        self.layout_index = None if layout_index is None else int(layout_index)
        self.n_layouts = None if n_layouts is None else int(n_layouts)
        self._generator = (
            RandomLayoutGenerator(split=split, seed=int(layout_seed), goal_size=goal_size)
            if layout == "random" else None
        )
        self._layout_cache: OrderedDict[int, Layout] = OrderedDict()
        self.detector = detector if detector is not None else SimGoalDetector(int(goal_min_pixels))
        # the GoalMeter works on the horizontal field of view
        h, w = self.image_size
        hfov = horizontal_fov(self.fov_deg, h, w)
        self.hfov_deg = hfov
        self.goal_meter = GoalMeter(
            self.detector,
            hfov_deg=hfov,
            confidence_threshold=float(confidence_threshold),
            max_depth=self.max_depth,
        )
        self._deltas = action_deltas(self.step_size, self.turn_deg)
        self._focal = (h / 2.0) / math.tan(math.radians(self.fov_deg) / 2.0)
        self._make_specs()

        # scene state (built lazily: the renderer's GL context belongs to the
        # process that steps the env, e.g. a ParallelEnv worker)
        self.layout: Layout | None = None
        self.model = None
        self.data = None
        self.ids = None
        self._renderer: SceneRenderer | None = None
        self._executor = None
        self._goal_point = np.zeros(3)
        self._steps = 0
        self._timing = {"render_s": 0.0, "physics_s": 0.0, "steps": 0}
        self._rng = np.random.default_rng(seed)
        self._seed_noise(seed)

    # ------------------------------------------------------------------ specs
    def _make_specs(self):
        f32 = torch.float32
        specs = navigation_specs(
            self.image_size, self.max_depth, self.device,
            goal_box=lambda h, w, dev: Bounded(0.0, float(max(h, w)), shape=(4,), dtype=f32,
                                               device=dev),
            goal_pixels=lambda h, w, dev: Bounded(0.0, float(h * w), shape=(1,), dtype=f32,
                                                  device=dev),
            goal_true_distance=lambda h, w, dev: Unbounded(shape=(1,), dtype=f32, device=dev),
            goal_true_bearing=lambda h, w, dev: Bounded(-180.0, 180.0, shape=(1,), dtype=f32,
                                                        device=dev),
        )
        for name, spec in specs.items():
            setattr(self, name, spec)

    # ---------------------------------------------------------------- scene
    def _select_layout(self) -> Layout:
        opt = self.layout_option
        if isinstance(opt, Layout):
            return opt
        if opt == "thesis":
            return self.layout if self.layout is not None else thesis_layout()
        if self.layout_index is not None:
            index = self.layout_index
        else:
            high = self.n_layouts if self.n_layouts is not None else 2**31 - 1
            index = int(self._rng.integers(high))
        lay = self._layout_cache.get(index)
        if lay is None:
            lay = self._generator.layout(index)
            self._layout_cache[index] = lay
            if len(self._layout_cache) > 64:
                self._layout_cache.popitem(last=False)
        return lay

    def _load(self, layout: Layout):
        if self.layout is not None and layout is self.layout:
            return
        self.model, self.ids = build_model(
            layout,
            image_size=self.image_size,
            fov_deg=self.fov_deg,
            max_depth=self.max_depth,
            timestep=self.physics_timestep,
            board_back=self.board_back,
        )
        self.data = mujoco.MjData(self.model)
        self.layout = layout
        self._goal_point = layout.goal_point()
        self._goal_center = np.asarray(layout.goal_center, dtype=np.float64)
        if self._renderer is None:
            self._renderer = SceneRenderer(
                self.model, *self.image_size, camera=self.ids.camera, max_depth=self.max_depth
            )
        else:
            self._renderer.set_model(self.model, self.ids.camera)
        args = (self.model, self.data, self.ids.qpos_adr, self.ids.qvel_adr)
        if self.execution == "kinematic":
            self._executor = KinematicExecutor(
                *args,
                position_noise_std=self.position_noise_std,
                yaw_noise_std_deg=self.yaw_noise_std_deg,
            )
        else:
            self._executor = PhysicsExecutor(
                *args, drone_body=self.ids.drone_body, action_duration=self.action_duration
            )

    # ------------------------------------------------------------ observing
    def _goal_maybe_visible(self, cam_pos, cam_rot) -> bool:
        """Cheap frustum test of the goal board's corners (skips the segmentation pass)."""
        pc = (self.ids.goal_corners - cam_pos) @ cam_rot  # camera frame: x right, y up, -z fwd
        z = -pc[:, 2]
        if (z <= 1e-3).all():
            return False
        if (z <= 1e-3).any():
            return True
        u = pc[:, 0] / z * self._focal
        v = pc[:, 1] / z * self._focal
        h, w = self.image_size
        return not (
            u.max() < -w / 2 - 1 or u.min() > w / 2 + 1 or v.max() < -h / 2 - 1 or v.min() > h / 2 + 1
        )

    def _observe(self, crashed: bool, reached: bool, out_of_bounds: bool = False) -> dict:
        m, d = self.model, self.data
        t0 = time.perf_counter()
        mujoco.mj_kinematics(m, d)
        mujoco.mj_camlight(m, d)
        rgb, depth = self._renderer.render(d)
        cam = self.ids.camera
        cam_pos = d.cam_xpos[cam].copy()
        cam_rot = d.cam_xmat[cam].reshape(3, 3).copy()
        box = [0.0, 0.0, 0.0, 0.0]
        count = 0
        if self._goal_maybe_visible(cam_pos, cam_rot):
            mask = self._renderer.geom_mask(self.ids.goal_geoms)
            cols = np.flatnonzero(mask.any(0))
            if cols.size:
                rows = np.flatnonzero(mask.any(1))
                box = [float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)]
                count = int(mask.sum())
        self._timing["render_s"] += time.perf_counter() - t0
        rel = (self._goal_center - cam_pos) @ cam_rot
        true_dist = float(np.linalg.norm(rel))
        bearing = math.degrees(math.atan2(-rel[0], -rel[2]))
        alt = float(d.qpos[self.ids.qpos_adr + 2])
        if self.altitude_noise_std > 0:
            alt += float(self._noise_rng.normal(0.0, self.altitude_noise_std))

        pixels = torch.from_numpy(rgb.copy())
        depth_t = torch.from_numpy(depth.copy())
        box_t = torch.from_numpy(np.array([box], dtype=np.float32))
        meas = self.goal_meter(
            pixels.unsqueeze(0),
            depth_t.unsqueeze(0),
            gt_box=box_t,
            gt_pixels=_scalars_count(count),
        )
        in_sight = bool(meas.in_sight[0])
        g_dist = float(meas.distance[0]) if in_sight else 0.0
        g_angle = float(meas.angle[0]) if in_sight else 0.0
        scalars = torch.from_numpy(
            np.array([alt, count, true_dist, bearing, g_dist, g_angle], dtype=np.float32)
        )
        flags = torch.from_numpy(
            np.array([in_sight, crashed, reached, out_of_bounds], dtype=np.bool_)
        )
        obs = {
            "pixels": pixels,
            "depth": depth_t,
            "altitude": scalars[0:1],
            "goal_box": box_t[0],
            "goal_pixels": scalars[1:2],
            "goal_true_distance": scalars[2:3],
            "goal_true_bearing": scalars[3:4],
            "goal_in_sight": flags[0:1],
            "goal_distance": scalars[4:5],
            "goal_angle": scalars[5:6],
            "crashed": flags[1:2],
            "reached": flags[2:3],
            "out_of_bounds": flags[3:4],
        }
        return obs

    def _pack(self, obs: dict) -> TensorDict:
        if self._to_device:
            return TensorDict(obs, batch_size=torch.Size([])).to(self.device)
        return TensorDict(obs, batch_size=torch.Size([]), device=self.device)

    # ------------------------------------------------------------- EnvBase
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        self._load(self._select_layout())
        self.episode_noise_seed = (self._noise_seed, self._episode)
        self._noise_rng = np.random.default_rng(list(self.episode_noise_seed))
        self._episode += 1
        x, y, z = self.layout.start_pos
        self._executor.reset(x, y, z, math.radians(self.layout.start_yaw_deg))
        self._steps = 0
        obs = self._observe(False, False)
        false = torch.zeros(1, dtype=torch.bool)
        obs["done"] = false
        obs["terminated"] = false.clone()
        obs["truncated"] = false.clone()
        return self._pack(obs)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = int(tensordict.get("action"))
        d_before = self._distance_to_goal_point(self._executor.pose())
        t0 = time.perf_counter()
        out = self._executor.execute(
            self._deltas[action], self._noise_rng, self._goal_point, self.reach_radius
        )
        self._timing["physics_s"] += time.perf_counter() - t0
        self._timing["steps"] += 1
        self._steps += 1
        pose = self._executor.pose()
        out_of_bounds = not (out.crashed or out.reached) and not self.layout.inside(pose)
        obs = self._observe(out.crashed, out.reached, out_of_bounds)
        reward = self.reward_fn(
            StepOutcome(  # goal distance and angle are already 0 when not in sight
                crashed=out.crashed,
                reached=out.reached,
                out_of_bounds=out_of_bounds,
                in_sight=bool(obs["goal_in_sight"]),
                goal_distance=float(obs["goal_distance"]),
                goal_angle=float(obs["goal_angle"]),
                distance_before=d_before,
                distance_after=self._distance_to_goal_point(pose),
            )
        )
        terminated = out.crashed or out.reached or out_of_bounds
        truncated = (not terminated) and self._steps >= self.max_steps
        obs["reward"] = torch.from_numpy(np.array([reward], dtype=np.float32))
        ends = torch.from_numpy(
            np.array([terminated, truncated, terminated or truncated], dtype=np.bool_)
        )
        obs["terminated"] = ends[0:1]
        obs["truncated"] = ends[1:2]
        obs["done"] = ends[2:3]
        return self._pack(obs)

    def _distance_to_goal_point(self, pose) -> float:
        x, y, z = pose[:3]
        g = self._goal_point
        return math.sqrt((x - g[0]) ** 2 + (y - g[1]) ** 2 + (z - g[2]) ** 2)

    def _set_seed(self, seed: int | None) -> None:
        self._rng = np.random.default_rng(seed)
        self._seed_noise(seed)

    def _seed_noise(self, seed: int | None) -> None:
        """Episode ``i`` from now draws its noise from ``default_rng([base, i])``."""
        self._noise_seed = int(seed) if seed is not None else int(
            np.random.SeedSequence().generate_state(1)[0])
        self._episode = 0
        self.episode_noise_seed = (self._noise_seed, 0)
        self._noise_rng = np.random.default_rng(list(self.episode_noise_seed))

    # ------------------------------------------------------------- helpers
    def timings(self, reset: bool = False) -> dict:
        """Mean per-step cost so far: ``{"render_ms", "physics_ms", "steps"}``.

        ``render_ms`` covers RGB-D and (when needed) segmentation rendering,
        ``physics_ms`` the action's execution (sweep or simulation). Both are
        divided by the step count; the renders of :meth:`reset` are included in
        ``render_ms``. ``reset=True`` clears the counters after reading them.
        """
        n = max(1, self._timing["steps"])
        out = {
            "render_ms": 1e3 * self._timing["render_s"] / n,
            "physics_ms": 1e3 * self._timing["physics_s"] / n,
            "steps": self._timing["steps"],
        }
        if reset:
            self._timing = {"render_s": 0.0, "physics_s": 0.0, "steps": 0}
        return out

    def drone_pose(self) -> tuple[float, float, float, float]:
        """Current ``(x, y, z, yaw_deg)`` of the drone."""
        x, y, z, yaw = self._executor.pose()
        return x, y, z, math.degrees(yaw)

    def close(self, *, raise_if_closed: bool = True):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        try:
            super().close(raise_if_closed=raise_if_closed)
        except TypeError:  # pragma: no cover - older signature
            super().close()
