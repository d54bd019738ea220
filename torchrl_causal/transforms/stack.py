"""One-call feature stack for :class:`~torchrl_causal.envs.DroneNavEnv`."""

from __future__ import annotations

import math

import torch
from torchrl.envs.transforms import Compose

from torchrl_causal.perception.goal import GoalMeter
from torchrl_causal.transforms.depth import DepthSections
from torchrl_causal.transforms.discretize import Discretize, Thresholds
from torchrl_causal.transforms.goal import GoalFeatures

__all__ = ["make_causal_transforms"]

_GOAL_KEYS = ("goal_in_sight", "goal_distance", "goal_angle")
_DEFAULT_MAX_DEPTH = 10.0


def _env_max_depth(env):
    """The depth sensor's range: the upper bound of the env's ``depth`` spec, if bounded."""
    spec = env.observation_spec["depth"]
    high = getattr(getattr(spec, "space", None), "high", None)
    if high is None:
        return None
    high = float(torch.as_tensor(high).max())
    return high if math.isfinite(high) and high > 0 else None


def make_causal_transforms(
    env=None,
    *,
    n_points: int = 20,
    exact: bool = False,
    seed: int | None = None,
    thresholds: Thresholds | None = None,
    max_depth: float | None = None,
    center_frac: float = 0.5,
    invalid_value: float | None = None,
    goal_meter: GoalMeter | None = None,
    device=None,
) -> Compose:
    """Builds the whole feature stack: ``DepthSections`` then ``Discretize``.

    On a :class:`~torchrl_causal.envs.DroneNavEnv` the goal is **not** detected
    again: the env already writes ``goal_in_sight`` / ``goal_distance`` /
    ``goal_angle`` with ``env.goal_meter``, the same measurement its reward
    uses, and the stack reads those keys. To swap the detector, use the env's
    ``detector`` option: reward and features then change together.

    Args:
        env: the env (or batched / transformed env) the stack will be
            appended to (optional); the upper bound of its ``depth`` spec is
            used as ``max_depth`` and it is checked to provide the goal keys.
        n_points, exact, seed, center_frac, invalid_value: see
            :class:`~torchrl_causal.transforms.DepthSections`.
        thresholds: see :class:`~torchrl_causal.transforms.Thresholds`.
        max_depth: sensor range in metres (default: the env's, else 10.0).
        goal_meter: for an env that does not measure the goal itself, a
            :class:`~torchrl_causal.perception.goal.GoalMeter`; a
            :class:`~torchrl_causal.transforms.GoalFeatures` step is then added
            first. Must be None when the env already writes the goal keys.
        device: device of the pixel sampler (default: the env's device, else CPU).

    Returns:
        a :class:`~torchrl.envs.transforms.Compose` writing ``depth_sections``,
        ``causal_features`` and ``causal_state``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> stack = make_causal_transforms(seed=0)
        >>> td = TensorDict({
        ...     "depth": torch.full((3, 84, 84), 4.0),
        ...     "goal_in_sight": torch.zeros(3, 1, dtype=torch.bool),
        ...     "goal_distance": torch.zeros(3, 1),
        ...     "goal_angle": torch.zeros(3, 1),
        ...     "altitude": torch.ones(3, 1),
        ... }, [3])
        >>> stack(td)["causal_state"][0].tolist()
        [1, 1, 1, 1, 1, 0, 2, 0, 1]
    """
    if goal_meter is not None and not isinstance(goal_meter, GoalMeter):
        raise ValueError(f"goal_meter must be a GoalMeter or None, got {goal_meter!r}")
    env_md = None
    if env is not None:
        keys = set(env.observation_spec.keys(True, True))
        if "depth" not in keys:
            raise ValueError(
                f"env={type(env).__name__} has no 'depth' observation; build the stack "
                "from the individual transforms (see docs/features)"
            )
        has_goal = all(k in keys for k in _GOAL_KEYS)
        if has_goal and goal_meter is not None:
            raise ValueError(
                "goal_meter must be None: the env already measures the goal "
                "(set the env's `detector` option to change the detector)"
            )
        if not has_goal and goal_meter is None:
            raise ValueError(
                f"env={type(env).__name__} writes no {_GOAL_KEYS}; pass goal_meter=GoalMeter(...)"
            )
        env_md = _env_max_depth(env)
        if device is None:
            device = env.device
    if max_depth is None:
        max_depth = env_md if env_md is not None else _DEFAULT_MAX_DEPTH
    steps = []
    if goal_meter is not None:
        steps.append(GoalFeatures(goal_meter))
    steps.append(
        DepthSections(
            n_points,
            exact=exact,
            max_depth=max_depth,
            invalid_value=invalid_value,
            center_frac=center_frac,
            seed=seed,
            device=device,
        )
    )
    steps.append(Discretize(thresholds, max_depth=max_depth))
    return Compose(*steps)
