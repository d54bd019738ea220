"""Greedy evaluation of a policy: success rate, reward, collisions, steps to goal.

:func:`evaluate` runs whole episodes with TorchRL's deterministic exploration
type (epsilon 0; a :class:`~torchrl_causal.modules.CBNGate` still vetoes when
its ``eval_gate`` is on) and reads the env's outcome flags: ``reached`` (success),
``crashed`` and ``out_of_bounds`` by default, or any keys you name.
:func:`seed_transforms` reseeds the transforms that sample (TorchRL's
``env.set_seed`` does not reach them), so that an evaluation does not depend
on what ran before it.
"""

from __future__ import annotations

import weakref
from typing import Mapping

import numpy as np
import torch

__all__ = ["evaluate", "seed_transforms", "OUTCOME_KEYS", "env_max_steps", "spl_of"]

#: What each outcome of an episode is read from (``("next", key)`` of its steps).
OUTCOME_KEYS: dict[str, str] = {
    "success": "reached",
    "crash": "crashed",
    "out_of_bounds": "out_of_bounds",
}


def seed_transforms(env, seed: int) -> None:
    """Reseeds every transform of ``env`` that has a ``set_seed`` method.

    TorchRL's ``env.set_seed`` seeds the base env only; transforms that draw
    random numbers (e.g. :class:`~torchrl_causal.transforms.DepthSections`'
    pixel samples) must restart their streams with it for a resumed run or an
    evaluation to repeat exactly.

    Args:
        env: any TorchRL env (a ``TransformedEnv`` or not; batched envs are
            left to their workers).
        seed: the seed.

    Example:
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl_causal.envs import DroneNavEnv
        >>> from torchrl_causal.transforms import make_causal_transforms
        >>> base = DroneNavEnv(image_size=32)
        >>> env = TransformedEnv(base, make_causal_transforms(base, seed=0))
        >>> seed_transforms(env, 3)  # DepthSections restarts its pixel draws
    """
    from torchrl.envs import Compose

    transform = getattr(env, "transform", None)
    transforms = list(transform) if isinstance(transform, Compose) else [transform]
    for t in transforms:
        if t is not None and hasattr(t, "set_seed"):
            t.set_seed(int(seed))


def env_max_steps(env, default: int = 1000) -> int:
    """The episode step limit the base env declares (``max_steps``), else ``default``.

    Example:
        >>> from torchrl_causal.envs import make_gridnav_env
        >>> env_max_steps(make_gridnav_env(max_steps=30))
        30
    """
    base = getattr(env, "base_env", env)
    for obj in (base, getattr(base, "_env", None)):
        steps = getattr(obj, "max_steps", None)
        if isinstance(steps, int) and steps > 0:
            return steps
    return default


def _policy_generators(policy) -> list:
    """The ``torch.Generator`` s of a policy's modules (e.g. the CBN gate's), in module order."""
    modules = getattr(policy, "modules", None)
    if not callable(modules):
        return []
    out = []
    for m in modules():
        g = getattr(m, "generator", None)
        if isinstance(g, torch.Generator) and all(g is not h for h in out):
            out.append(g)
    return out


def _flag(td, key) -> bool:
    val = td.get(key, None)
    return bool(val.any()) if val is not None else False


@torch.no_grad()
def evaluate(
    policy,
    env,
    episodes: int,
    seed: int,
    *,
    max_steps: int | None = None,
    outcome_keys: Mapping[str, str] | None = None,
    spl: bool | None = None,
    per_episode: bool = False,
) -> dict:
    """Greedy episodes of ``policy`` on ``env``.

    Args:
        policy: a TorchRL policy (e.g. ``TensorDictSequential(actor, gate)``).
        env: the env to run (a single, unbatched env).
        episodes: the number of episodes (> 0).
        seed: seeds the env and its sampling transforms first.
        max_steps: step limit of an episode (default: the env's ``max_steps``,
            else 1000).
        outcome_keys: ``{"success" | "crash" | "out_of_bounds": key}`` overrides
            of :data:`OUTCOME_KEYS`; a key the env does not write counts as False.
        spl: also measure SPL (Success weighted by Path Length, Anderson et al.
            2018): per episode ``S * l / max(p, l)``, ``l`` the
            :class:`~torchrl_causal.envs.oracle.ShortestPathPlanner`'s step count
            from the episode's start, ``p`` the steps taken. ``None`` (default):
            whenever the env is (over) a kinematic
            :class:`~torchrl_causal.envs.DroneNavEnv`.
        per_episode: also return ``episodes``: one dict per episode
            (``success``, ``crash``, ``out_of_bounds``, ``steps``, ``reward``,
            ``oracle_steps``, ``spl``, ``goal_in_view_at_start`` -- whether the
            reset's ``goal_in_sight`` feature was set, None where the env does
            not write it; over a ``DroneNavEnv`` also ``layout``
            and ``path``, the drone's ``(x, y, z, yaw_deg)`` before every step
            and at the end, and ``oracle_plan``, the oracle's actions from the
            start -- what :func:`~torchrl_causal.training.flightmap.plot_flight_map`
            draws).

    Returns:
        ``success_rate``, ``mean_reward``, ``collisions``, ``out_of_bounds``,
        ``mean_length`` and ``steps_to_goal`` (mean length of the successful
        episodes; NaN when none succeeded); with SPL also ``spl`` (mean over the
        episodes whose oracle plan was found) and ``oracle_steps`` (their mean
        shortest-path length).

    Raises:
        ValueError: ``episodes`` is not a positive int.

    Example:
        >>> import torch
        >>> from torchrl.envs import GymEnv
        >>> from torchrl_causal.training import evaluate
        >>> env = GymEnv("CartPole-v1")
        >>> policy = lambda td: td.set("action", env.action_spec.rand())
        >>> res = evaluate(policy, env, episodes=3, seed=0, max_steps=20,
        ...                outcome_keys={"success": "truncated"})
        >>> sorted(res)
        ['collisions', 'mean_length', 'mean_reward', 'out_of_bounds', 'steps_to_goal', 'success_rate']
    """
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes <= 0:
        raise ValueError(f"episodes must be an int > 0, got {episodes!r}")
    keys = {**OUTCOME_KEYS, **(outcome_keys or {})}
    steps = max_steps or env_max_steps(env)
    planner = _spl_planner(env) if spl or spl is None else None
    if spl and planner is None:
        raise ValueError("evaluate(spl=True) needs an env over a kinematic DroneNavEnv")
    env.set_seed(int(seed))
    seed_transforms(env, seed)
    # the policy's own random draws (the CBN gate's, from its generator or from torch's global
    # one) restart from the seed too, so that two evaluations of one policy on one seed fly
    # the same episodes; their streams are put back afterwards, so that an evaluation in the
    # middle of training does not move them
    generators = _policy_generators(policy)
    saved = [g.get_state() for g in generators]
    cuda = list(range(torch.cuda.device_count())) if torch.cuda.is_initialized() else []
    try:
        with torch.random.fork_rng(devices=cuda):
            torch.manual_seed(int(seed))
            for i, g in enumerate(generators):
                g.manual_seed(int(seed) + 7919 * (i + 1))
            return _evaluate(policy, env, episodes, keys, steps, planner, per_episode)
    finally:
        for g, state in zip(generators, saved):
            g.set_state(state)


def _evaluate(policy, env, episodes, keys, steps, planner, per_episode) -> dict:
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    rewards, successes, crashes, exits, lengths, oracle = [], [], [], [], [], []
    in_view = []  # goal_in_sight at the reset (None: the env does not write it)
    from ..envs.oracle import base_drone_env

    base = base_drone_env(env) if per_episode else None
    paths, plans, layouts = [], [], []
    acting = policy
    if base is not None:
        def acting(td):  # records the pose the action is taken from
            paths[-1].append(base.drone_pose())
            return policy(td)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(episodes):
            start = env.reset()
            seen = start.get("goal_in_sight", None)
            in_view.append(None if seen is None else bool(seen.reshape(-1)[0]))
            if planner is not None:
                plan = _oracle_plan(planner)
                oracle.append(float(len(plan)) if plan is not None else float("nan"))
                plans.append(plan)
            if base is not None:
                paths.append([])
                layouts.append(base.layout)
            td = env.rollout(steps, acting, break_when_any_done=True, auto_reset=False,
                             tensordict=start)
            if base is not None:
                paths[-1].append(base.drone_pose())
            nxt = td["next"]
            rewards.append(float(nxt["reward"].sum()))
            lengths.append(td.numel())
            successes.append(_flag(nxt, keys["success"]))
            crashes.append(_flag(nxt, keys["crash"]))
            exits.append(_flag(nxt, keys["out_of_bounds"]))
    to_goal = [n for n, ok in zip(lengths, successes) if ok]
    out = {
        "success_rate": float(np.mean(successes)),
        "mean_reward": float(np.mean(rewards)),
        "collisions": int(np.sum(crashes)),
        "out_of_bounds": int(np.sum(exits)),
        "mean_length": float(np.mean(lengths)),
        "steps_to_goal": float(np.mean(to_goal)) if to_goal else float("nan"),
    }
    spls = [spl_of(ok, p, l) for ok, p, l in zip(successes, lengths, oracle)]
    if planner is not None:
        known = [v for v in spls if not np.isnan(v)]
        out["spl"] = float(np.mean(known)) if known else float("nan")
        found = [v for v in oracle if not np.isnan(v)]
        out["oracle_steps"] = float(np.mean(found)) if found else float("nan")
    if per_episode:
        out["episodes"] = [
            {"success": ok, "crash": c, "out_of_bounds": o, "steps": p, "reward": r,
             "oracle_steps": oracle[i] if oracle else float("nan"),
             "spl": spls[i] if spls else float("nan"), "goal_in_view_at_start": in_view[i]}
            for i, (ok, c, o, p, r) in enumerate(zip(successes, crashes, exits, lengths, rewards))
        ]
        for i, ep in enumerate(out["episodes"]):
            if base is not None:
                ep["layout"], ep["path"] = layouts[i], paths[i]
            if plans:
                ep["oracle_plan"] = plans[i]
    return out


def spl_of(success: bool, steps: int, oracle_steps: float) -> float:
    """One episode's SPL term ``S * l / max(p, l)`` (NaN when ``l`` is unknown).

    Example:
        >>> spl_of(True, 20, 12), spl_of(False, 5, 12), spl_of(True, 12, 12)
        (0.6, 0.0, 1.0)
    """
    if np.isnan(oracle_steps):
        return float("nan")
    if not success:
        return 0.0
    return float(oracle_steps / max(steps, oracle_steps)) if oracle_steps > 0 else 1.0


def _spl_planner(env):
    from ..envs.oracle import ShortestPathPlanner, base_drone_env

    base = base_drone_env(env)
    if base is None or base.execution != "kinematic":
        return None
    return ShortestPathPlanner(base)


# the oracle's plans per env, keyed by the episode's layout and start pose: evaluations with
# fixed episodes (``eval.fixed_episodes``, the same seeds at every periodic evaluation) plan
# each start once, not once per evaluation (a search can take seconds on a cluttered layout)
_PLANS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _oracle_plan(planner) -> list[int] | None:
    from ..envs.oracle import PlanningError

    env = planner.env
    key = (env.layout, tuple(round(float(v), 6) for v in env._executor.pose()),
           planner.max_expansions, planner.max_steps, planner.resolution, planner.weight,
           planner.clearance, planner.actions, env.max_steps, env._steps)
    plans = _PLANS.setdefault(env, {})
    if key not in plans:
        try:
            plans[key] = planner.plan()
        except PlanningError:
            plans[key] = None
        if len(plans) > 4096:  # many random episodes: keep the memory bounded
            plans.pop(next(iter(plans)))
    plan = plans[key]
    return None if plan is None else list(plan)
