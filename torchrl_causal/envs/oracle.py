"""A shortest-path oracle over :class:`~torchrl_causal.envs.DroneNavEnv`'s own moves.

:class:`ShortestPathPlanner` searches (A*) over the env's own eight discrete
actions from the env's *current* state to the goal point, executing every
candidate move with the env's own :class:`~torchrl_causal.envs.control.KinematicExecutor`
(the same collision sweep and reach test an ``env.step`` uses) and the
layout's own geofence (:meth:`~torchrl_causal.envs.layouts.Layout.inside`).
No geometry is modelled again: a plan replayed through ``env.step`` on a
noise-free env is judged ``reached`` by the env itself.

* Cost: one step per action (the env's step count); the plan is the fewest
  actions that reach the goal point (optimal up to the search's 1 cm / 1 deg
  state rounding).
* Heuristic: ``ceil((distance to the goal point - reach_radius) / step_size)``;
  a move changes the drone's position by exactly ``step_size``, so it never
  over-estimates and A* returns an optimal plan.
* Budget: ``max_expansions`` states (and the env's remaining steps); a layout it
  cannot solve within it raises :class:`PlanningError`, naming the budget.

:class:`OraclePolicy` acts by the plan as a TorchRL module (a baseline row in
results, and the teacher of :mod:`torchrl_causal.training.imitation`).
The oracle reads the simulator's state: it is privileged and exists only in
simulation.

Example:
    >>> from torchrl_causal.envs import DroneNavEnv
    >>> env = DroneNavEnv(image_size=32, seed=0)
    >>> _ = env.reset()
    >>> plan = ShortestPathPlanner(env).plan()
    >>> len(plan)
    12
"""

from __future__ import annotations

import contextlib
import heapq
import math
import time

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

__all__ = ["ShortestPathPlanner", "OraclePolicy", "PlanningError", "base_drone_env"]


class PlanningError(RuntimeError):
    """No plan was found within the planner's search budget (or none exists).

    Example:
        >>> from torchrl_causal.envs import DroneNavEnv
        >>> env = DroneNavEnv(image_size=32, seed=0)
        >>> _ = env.reset()
        >>> try:
        ...     ShortestPathPlanner(env, max_expansions=1).plan()
        ... except PlanningError as err:
        ...     print("max_expansions=1" in str(err))
        True
    """


def base_drone_env(env):
    """The :class:`~torchrl_causal.envs.DroneNavEnv` under ``env`` (through
    ``TransformedEnv`` wrappers), or ``None`` when there is none.

    Example:
        >>> from torchrl.envs import TransformedEnv, StepCounter
        >>> from torchrl_causal.envs import DroneNavEnv
        >>> base = DroneNavEnv(image_size=32)
        >>> base_drone_env(TransformedEnv(base, StepCounter())) is base
        True
    """
    from .drone import DroneNavEnv

    seen = 0
    while env is not None and seen < 16:
        if isinstance(env, DroneNavEnv):
            return env
        env = getattr(env, "base_env", None)
        seen += 1
    return None


class ShortestPathPlanner:
    """Optimal action sequence from a :class:`~torchrl_causal.envs.DroneNavEnv`'s current state.

    Args:
        env: a ``DroneNavEnv`` (or a ``TransformedEnv`` over one) with
            ``execution="kinematic"``, already reset.
        max_expansions: search budget (states expanded) before
            :class:`PlanningError`.
        max_steps: longest plan accepted (default: the env's steps left in the
            episode).
        resolution: states closer than this (m, per axis) with the same heading
            class are one search state.
        clearance: keep this much more distance (m) from everything: the
            search runs with the drone's collision hull inflated by it (the env's
            own collision check on a larger box, within a quarter of
            ``max_expansions``), and falls back to the real hull when no such
            plan is found. 0 (default): shortest plans, which graze
            obstacles; the imitation teacher uses a margin so that a student's
            small deviations do not crash.
        actions: the actions the plan may use (indices or
            :data:`~torchrl_causal.schema.ACTION_NAMES`; default: all eight). The
            imitation teacher can leave out the sideways and backward moves, which
            a forward-looking camera cannot see into.
        weight: heuristic weight; 1 (default) is A* and returns an optimal plan,
            ``w > 1`` is weighted A*: far fewer expansions, a plan at most ``w``
            times longer than optimal (the imitation teacher uses 1.5).

    The env's state (drone pose) is restored after every search; its noise
    options are ignored while planning (the plan is for noise-free moves).

    Example:
        >>> import torch
        >>> from torchrl_causal.envs import DroneNavEnv
        >>> env = DroneNavEnv(image_size=32, seed=0)
        >>> _ = env.reset()
        >>> planner = ShortestPathPlanner(env)
        >>> plan = planner.plan()
        >>> from tensordict import TensorDict
        >>> for a in plan:
        ...     td = env.step(TensorDict({"action": torch.tensor(a)}, []))
        >>> bool(td["next", "reached"]), len(plan)
        (True, 12)
    """

    def __init__(self, env, *, max_expansions: int = 60_000, max_steps: int | None = None,
                 resolution: float = 0.02, weight: float = 1.0, clearance: float = 0.0,
                 actions=None):
        base = base_drone_env(env)
        if base is None:
            raise ValueError(
                f"ShortestPathPlanner needs a DroneNavEnv (or a TransformedEnv over one), "
                f"got {type(env).__name__}")
        if base.execution != "kinematic":
            raise ValueError(
                f"ShortestPathPlanner plans kinematic moves; env has execution={base.execution!r} "
                "(use DroneNavEnv(execution='kinematic'))")
        if not isinstance(max_expansions, int) or isinstance(max_expansions, bool) \
                or max_expansions < 1:
            raise ValueError(f"max_expansions must be an int >= 1, got {max_expansions!r}")
        if max_steps is not None and (not isinstance(max_steps, int) or max_steps < 1):
            raise ValueError(f"max_steps must be None or an int >= 1, got {max_steps!r}")
        self.env = base
        self.max_expansions = int(max_expansions)
        self.max_steps = max_steps
        if not isinstance(resolution, (int, float)) or not 0 < resolution <= 0.1:
            raise ValueError(f"resolution must be in (0, 0.1] m, got {resolution!r}")
        self.resolution = float(resolution)
        if not isinstance(weight, (int, float)) or isinstance(weight, bool) or weight < 1:
            raise ValueError(f"weight must be a number >= 1, got {weight!r}")
        self.weight = float(weight)
        if not isinstance(clearance, (int, float)) or isinstance(clearance, bool) \
                or not 0 <= clearance <= 0.5:
            raise ValueError(f"clearance must be in [0, 0.5] m, got {clearance!r}")
        self.clearance = float(clearance)
        from ..schema import ACTION_NAMES

        if actions is None:
            actions = range(len(ACTION_NAMES))
        chosen = []
        for a in actions:
            if isinstance(a, str) and a in ACTION_NAMES:
                chosen.append(ACTION_NAMES.index(a))
            elif isinstance(a, (int, np.integer)) and not isinstance(a, bool) \
                    and 0 <= a < len(ACTION_NAMES):
                chosen.append(int(a))
            else:
                raise ValueError(f"actions: {a!r} is not an action index or one of "
                                 f"{ACTION_NAMES}")
        if not chosen:
            raise ValueError("actions must name at least one action")
        self.actions = tuple(sorted(set(chosen)))
        self.last_expansions = 0
        self.last_seconds = 0.0

    # ------------------------------------------------------------------ search
    def plan(self, pose: tuple[float, float, float, float] | None = None) -> list[int]:
        """The fewest actions from the env's current pose (or ``pose`` =
        ``(x, y, z, yaw_rad)``) that reach the goal point.

        Raises:
            RuntimeError: the env was not reset.
            PlanningError: the start is in collision or outside the flight
                volume, or no plan is found within ``max_expansions`` states
                or the steps left in the episode.
        """
        env = self.env
        if env._executor is None or env.layout is None:
            raise RuntimeError("ShortestPathPlanner.plan: reset the env first")
        t0 = time.perf_counter()
        try:
            with self.scratch():
                ex = env._executor
                start = tuple(ex.pose()) if pose is None else tuple(float(v) for v in pose)
                if self.clearance > 0:
                    try:
                        with self._inflated_hull(self.clearance):
                            # a quarter of the budget: where the margin cannot be kept
                            # (a narrow gap, a drone already inside it) the failed
                            # search would otherwise cost a full budget at every replan
                            return self._search(start, max(1, self.max_expansions // 4))
                    except PlanningError:
                        pass  # no plan keeps the margin: plan with the real hull
                return self._search(start)
        finally:
            self.last_seconds = time.perf_counter() - t0

    @contextlib.contextmanager
    def scratch(self):
        """Noise-free moves inside the block; the drone's state is restored after it."""
        import mujoco

        env = self.env
        ex, data = env._executor, env.data
        qpos0, qvel0 = data.qpos.copy(), data.qvel.copy()
        noise = (ex.position_noise_std, ex.yaw_noise_std)
        ex.position_noise_std, ex.yaw_noise_std = 0.0, 0.0
        try:
            yield
        finally:
            ex.position_noise_std, ex.yaw_noise_std = noise
            data.qpos[:] = qpos0
            data.qvel[:] = qvel0
            mujoco.mj_kinematics(env.model, data)

    @contextlib.contextmanager
    def _inflated_hull(self, margin: float):
        """The drone's colliding geoms grown by ``margin`` (m) while inside the block."""
        model = self.env.model
        geoms = [g for g in self.env.ids.drone_geoms if model.geom_contype[g]
                 or model.geom_conaffinity[g]]
        size = model.geom_size[geoms].copy()
        rbound = model.geom_rbound[geoms].copy()
        try:
            model.geom_size[geoms] = size + margin
            model.geom_rbound[geoms] = rbound + margin * math.sqrt(3.0)
            yield
        finally:
            model.geom_size[geoms] = size
            model.geom_rbound[geoms] = rbound

    def _broadphase(self):
        """A test ``free(pose) -> bool``: no geom the drone can collide with comes
        within one move of the drone's bounding sphere at ``pose``, so every
        move from it is collision-free without the swept test.

        Built from MuJoCo's own bounding volumes at the current kinematics: the
        drone's bounding sphere about its body origin, every other geom's
        oriented bounding box (``geom_aabb`` in the geom's frame), planes by
        their normal. ``None`` when some collidable geom moves (then every move
        is swept).
        """
        import mujoco

        env = self.env
        model, data = env.model, env.data
        drone_all = set(env.ids.drone_geoms)
        drone = [g for g in drone_all if model.geom_contype[g] or model.geom_conaffinity[g]]
        if not drone:
            return None
        mujoco.mj_kinematics(model, data)
        body = model.geom_bodyid[drone[0]]
        origin = data.xpos[body].copy()
        radius = max(float(np.linalg.norm(data.geom_xpos[g] - origin) + model.geom_rbound[g])
                     for g in drone)
        centres, rots, halves, planes = [], [], [], []
        for g in range(model.ngeom):
            if g in drone_all:
                continue
            if not any((model.geom_contype[g] & model.geom_conaffinity[d])
                       or (model.geom_conaffinity[g] & model.geom_contype[d]) for d in drone):
                continue
            b = model.geom_bodyid[g]
            if b != 0 and (model.body_jntnum[b] > 0 or model.body_mocapid[b] >= 0):
                return None  # a moving obstacle: no static broadphase
            rot = data.geom_xmat[g].reshape(3, 3).copy()
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
                planes.append((data.geom_xpos[g].copy(), rot[:, 2].copy()))
                continue
            aabb = model.geom_aabb[g]  # centre (3) and half sizes (3), geom frame
            centres.append(data.geom_xpos[g] + rot @ aabb[:3])
            rots.append(rot)
            halves.append(aabb[3:].copy())
        reach = radius + env.step_size + 1e-3  # the farthest a move takes any point of the hull
        centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        rots = np.asarray(rots, dtype=np.float64).reshape(-1, 3, 3)
        halves = np.asarray(halves, dtype=np.float64).reshape(-1, 3)

        def free(pose) -> bool:
            p = np.array(pose[:3], dtype=np.float64)
            for point, normal in planes:
                if float(np.dot(p - point, normal)) <= reach:
                    return False
            if len(centres):
                local = np.einsum("nji,nj->ni", rots, p - centres)  # R^T (p - c)
                outside = np.maximum(np.abs(local) - halves, 0.0)
                if bool(((outside ** 2).sum(axis=1) <= reach * reach).any()):
                    return False
            return True

        return free

    def _search(self, start, budget: int | None = None) -> list[int]:
        env = self.env
        budget = self.max_expansions if budget is None else int(budget)
        ex = env._executor
        goal = np.asarray(env._goal_point, dtype=np.float64)
        gx, gy, gz = (float(v) for v in goal)
        r = env.reach_radius
        step = env.step_size
        deltas = env._deltas
        layout = env.layout
        limit = self.max_steps if self.max_steps is not None else env.max_steps - env._steps
        rng = np.random.default_rng(0)  # unused: noise is off while planning

        slack = math.sqrt(2.0) * r
        res = self.resolution

        def h(p) -> int:
            # every move is either vertical or horizontal (step_size each): at least
            # (|dz| + horizontal distance) / step moves, less the reach ball's slack
            dxy = math.hypot(p[0] - gx, p[1] - gy)
            return max(0, math.ceil((abs(p[2] - gz) + dxy - slack) / step - 1e-9))

        # with all four horizontal moves, headings 90 deg apart have the same moves:
        # one search state
        period = 90 if {0, 1, 2, 3} <= set(self.actions) else 360

        def key(p):
            yaw = round(math.degrees(p[3])) % period
            return (round(p[0] / res), round(p[1] / res), round(p[2] / res), yaw)

        ex.set_pose(*start)
        if ex.in_collision():
            raise PlanningError(f"the start pose {tuple(round(v, 3) for v in start)} is in "
                                "collision: no plan")
        if not layout.inside(start):
            raise PlanningError(f"the start pose {tuple(round(v, 3) for v in start)} is outside "
                                "the flight volume: no plan")
        if h(start) == 0 and (start[0] - gx) ** 2 + (start[1] - gy) ** 2 + (start[2] - gz) ** 2 \
                <= r * r:
            return []
        free = self._broadphase()
        nodes = [(start, -1, -1)]  # (pose, parent index, action)
        best_g = {key(start): 0}
        w = self.weight
        heap = [(w * h(start), 0, 0)]  # (f, -g, node index): ties go to the deeper node
        expansions = 0
        while heap:
            f, neg_g, idx = heapq.heappop(heap)
            g = -neg_g
            pose, _, _ = nodes[idx]
            if best_g.get(key(pose), 1 << 30) < g:
                continue
            if g + 1 > limit:
                continue
            expansions += 1
            if expansions > budget:
                self.last_expansions = expansions
                raise PlanningError(
                    f"no plan within max_expansions={budget} states (layout "
                    f"{layout.name!r}); raise max_expansions")
            sweep = free is None or not free(pose)  # far from everything: no swept test
            for a in self.actions:
                delta = deltas[a]
                ex.set_pose(*pose)
                out = ex.execute(delta, rng, goal, r, check_collisions=sweep)
                if out.crashed:
                    continue
                nxt = ex.pose()
                if out.reached:
                    self.last_expansions = expansions
                    plan = [a]
                    while idx > 0:
                        _, idx, act = nodes[idx][0], nodes[idx][1], nodes[idx][2]
                        plan.append(act)
                    return plan[::-1]
                if not layout.inside(nxt):
                    continue
                k = key(nxt)
                if best_g.get(k, 1 << 30) <= g + 1:
                    continue
                best_g[k] = g + 1
                nodes.append((nxt, idx, a))
                heapq.heappush(heap, (g + 1 + w * h(nxt), -(g + 1), len(nodes) - 1))
        self.last_expansions = expansions
        raise PlanningError(f"no plan of at most {limit} steps exists from this state "
                            f"(layout {layout.name!r})")


class OraclePolicy(TensorDictModuleBase):
    """Acts by :class:`ShortestPathPlanner`'s plan: a privileged baseline policy.

    It plans when an episode starts and replans whenever the drone is not
    where the plan expected it (e.g. under move noise); writes ``"action"``
    (int64 scalar). It reads the simulator's state through ``env`` (not the
    tensordict), so it works on the unbatched env it was built for.

    Args:
        env: the ``DroneNavEnv`` (or a ``TransformedEnv`` over one) it acts in.
        max_expansions: see :class:`ShortestPathPlanner`.
        fallback_action: taken when no plan exists (default 0, forward).
        weight, clearance, actions: see :class:`ShortestPathPlanner`.

    Example:
        >>> from torchrl_causal.envs import DroneNavEnv
        >>> env = DroneNavEnv(image_size=32, seed=0)
        >>> td = env.rollout(50, OraclePolicy(env))
        >>> td.shape[0], bool(td["next", "reached"][-1])
        (12, True)
    """

    in_keys: list = []
    out_keys = ["action"]

    def __init__(self, env, *, max_expansions: int = 60_000, fallback_action: int = 0,
                 weight: float = 1.0, clearance: float = 0.0, actions=None):
        super().__init__()
        self.planner = ShortestPathPlanner(env, max_expansions=max_expansions, weight=weight,
                                           clearance=clearance, actions=actions)
        self.fallback_action = int(fallback_action)
        self._plan: list[int] = []
        self._expect: tuple | None = None
        self.replans = 0

    def _pose_matches(self, pose) -> bool:
        if self._expect is None:
            return False
        e = self._expect
        dyaw = (pose[3] - e[3] + math.pi) % (2 * math.pi) - math.pi
        return (abs(pose[0] - e[0]) < 1e-6 and abs(pose[1] - e[1]) < 1e-6
                and abs(pose[2] - e[2]) < 1e-6 and abs(dyaw) < 1e-6)

    def next_action(self) -> int:
        """The oracle's action at the env's current state (``fallback_action`` when
        no plan exists)."""
        action = self.expert_action()
        return self.fallback_action if action is None else action

    def expert_action(self) -> int | None:
        """The oracle's action at the env's current state, or ``None`` when no plan
        exists (within the planner's budget) from it."""
        env = self.planner.env
        pose = env._executor.pose()
        if env._steps == 0 or not self._plan or not self._pose_matches(pose):
            self.replans += 1
            try:
                self._plan = self.planner.plan()
            except PlanningError:
                self._plan = []
        if not self._plan:
            self._expect = None
            return None
        action = self._plan.pop(0)
        # where the action will put the drone (noise-free), to detect deviations
        with self.planner.scratch():
            env._executor.execute(env._deltas[action], np.random.default_rng(0),
                                  env._goal_point, env.reach_radius)
            self._expect = env._executor.pose()
        return action

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = self.next_action()
        shape = tensordict.batch_size
        tensordict.set("action", torch.full(shape, action, dtype=torch.int64,
                                            device=tensordict.device))
        return tensordict
