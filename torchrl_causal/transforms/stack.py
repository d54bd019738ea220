"""One-call feature stack for :class:`~torchrl_causal.envs.DroneNavEnv`."""

from __future__ import annotations

import math
import os

import torch
from torchrl.envs.transforms import Compose

from torchrl_causal.perception.goal import GoalMeter
from torchrl_causal.transforms.depth import DepthSections
from torchrl_causal.transforms.discretize import Discretize, Thresholds
from torchrl_causal.transforms.goal import GoalFeatures

__all__ = ["make_causal_transforms", "PERCEPTIONS"]

_GOAL_KEYS = ("goal_in_sight", "goal_distance", "goal_angle")
_DEFAULT_MAX_DEPTH = 10.0
#: Accepted values of ``make_causal_transforms(perception=...)``.
PERCEPTIONS: tuple[str, ...] = ("sim", "rgb")


def _env_hfov(env):
    """The camera's horizontal field of view of an env (or its base env), if it says."""
    for obj in (env, getattr(env, "base_env", None)):
        hfov = getattr(obj, "hfov_deg", None) if obj is not None else None
        if isinstance(hfov, (int, float)) and 0 < hfov < 180:
            return float(hfov)
    return None


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
    perception: str = "sim",
    detector=None,
    depth_estimator=None,
    hfov_deg: float | None = None,
    confidence_threshold: float = 0.7,
) -> Compose:
    """Builds the whole feature stack: ``DepthSections`` then ``Discretize``.

    ``perception`` chooses where depth and goal come from:

    * ``"sim"`` (default): the env's own ``depth`` (the simulator's exact
      depth) and goal keys, as described below;
    * ``"rgb"``: the nine features from the RGB image alone, as on a real
      drone: :class:`~torchrl_causal.transforms.EstimatedDepth` writes
      ``depth`` from ``pixels`` with ``depth_estimator`` (default: the shipped
      :class:`~torchrl_causal.perception.depth.MonoDepth`), then
      :class:`~torchrl_causal.transforms.GoalFeatures` writes the goal keys with
      a :class:`~torchrl_causal.perception.goal.GoalMeter` over ``detector``
      (default: the shipped
      :class:`~torchrl_causal.perception.yolo.YoloGoalDetector`, which needs
      the ``perception`` extra) and the thesis's 0.7 confidence rule. On a
      :class:`~torchrl_causal.envs.DroneNavEnv` both replace the simulator's
      values in the tensordict (the env's reward still uses its own
      measurement); on :class:`~torchrl_causal.envs.tello.TelloEnv` they are
      the only source. The env needs ``pixels`` and ``altitude``.

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
        perception: ``"sim"`` or ``"rgb"`` (see above).
        detector: ``perception="rgb"``: the
            :class:`~torchrl_causal.perception.goal.GoalDetector` (default: the
            shipped YOLOv8 detector).
        depth_estimator: ``perception="rgb"``: a callable ``uint8 [B, H, W, 3]
            -> float32 [B, H, W]`` metres, or the path of ``MonoDepth`` weights
            (``recipes/train_depth.py``'s ``--out``; a recipe's
            ``features.options.depth_estimator``) (default: the shipped ``MonoDepth``).
        hfov_deg: ``perception="rgb"``: the camera's horizontal field of view
            (default: the env's ``hfov_deg``).
        confidence_threshold: ``perception="rgb"``: detector score needed for
            ``goal_in_sight`` (thesis: 0.7).

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

        RGB only, with any detector and depth estimator (here trivial ones):

        >>> from torchrl_causal.perception import SimGoalDetector
        >>> class NoGoal(SimGoalDetector):
        ...     def detect(self, pixels, depth=None, **gt):
        ...         return torch.zeros(len(pixels), 0, 4), torch.zeros(len(pixels), 0)
        >>> rgb = make_causal_transforms(perception="rgb", detector=NoGoal(), hfov_deg=60.0,
        ...                              depth_estimator=lambda px: torch.full(px.shape[:-1], 0.3),
        ...                              seed=0)
        >>> td = TensorDict({"pixels": torch.zeros(2, 84, 84, 3, dtype=torch.uint8),
        ...                  "altitude": torch.ones(2, 1)}, [2])
        >>> rgb(td)["causal_state"][0].tolist()
        [0, 0, 0, 0, 0, 0, 2, 0, 1]
    """
    if perception not in PERCEPTIONS:
        raise ValueError(f"perception must be one of {PERCEPTIONS}, got {perception!r}")
    if goal_meter is not None and not isinstance(goal_meter, GoalMeter):
        raise ValueError(f"goal_meter must be a GoalMeter or None, got {goal_meter!r}")
    if perception == "rgb":
        return _rgb_stack(
            env, n_points=n_points, exact=exact, seed=seed, thresholds=thresholds,
            max_depth=max_depth, center_frac=center_frac, invalid_value=invalid_value,
            goal_meter=goal_meter, device=device, detector=detector,
            depth_estimator=depth_estimator, hfov_deg=hfov_deg,
            confidence_threshold=confidence_threshold,
        )
    if detector is not None or depth_estimator is not None or hfov_deg is not None:
        raise ValueError(
            "detector, depth_estimator and hfov_deg are options of perception='rgb'; with "
            "perception='sim' set the env's `detector` option instead"
        )
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


def _rgb_stack(env, *, n_points, exact, seed, thresholds, max_depth, center_frac,
               invalid_value, goal_meter, device, detector, depth_estimator, hfov_deg,
               confidence_threshold) -> Compose:
    """``perception="rgb"``: EstimatedDepth -> GoalFeatures -> DepthSections -> Discretize."""
    from torchrl_causal.perception.goal import GoalDetector
    from torchrl_causal.transforms.estimated_depth import EstimatedDepth

    if detector is not None and not isinstance(detector, GoalDetector):
        raise ValueError(f"detector must be a GoalDetector or None, got {detector!r}")
    weights = depth_estimator if isinstance(depth_estimator, (str, os.PathLike)) else None
    if weights is not None:  # a MonoDepth weights file, loaded below (missing: named there)
        depth_estimator = None
    if depth_estimator is not None and not callable(depth_estimator):
        raise ValueError(f"depth_estimator must be callable, a MonoDepth weights path or None, "
                         f"got {depth_estimator!r}")
    if goal_meter is not None and detector is not None:
        raise ValueError("give either goal_meter or detector, not both")
    env_md = None
    if env is not None:
        keys = set(env.observation_spec.keys(True, True))
        missing = [k for k in ("pixels", "altitude") if k not in keys]
        if missing:
            raise ValueError(
                f"perception='rgb' needs the env's 'pixels' and 'altitude'; "
                f"env={type(env).__name__} lacks {missing}"
            )
        if "depth" in keys:
            env_md = _env_max_depth(env)
        if hfov_deg is None:
            hfov_deg = _env_hfov(env)
        if device is None:
            device = env.device
    if goal_meter is None and hfov_deg is None:
        raise ValueError(
            "perception='rgb' needs the camera's horizontal field of view: pass hfov_deg= "
            "(or an env with an `hfov_deg` attribute)"
        )
    if depth_estimator is None:
        from torchrl_causal.perception.depth import MonoDepth

        depth_estimator = MonoDepth.load(weights, device=device)
    if max_depth is None:
        max_depth = env_md or getattr(depth_estimator, "max_depth", None) or _DEFAULT_MAX_DEPTH
    max_depth = float(max_depth)
    if goal_meter is None:
        if detector is None:
            from torchrl_causal.perception.yolo import YoloGoalDetector

            detector = YoloGoalDetector(device=device)
        goal_meter = GoalMeter(detector, hfov_deg=float(hfov_deg),
                               confidence_threshold=confidence_threshold, max_depth=max_depth)
    return Compose(
        EstimatedDepth(depth_estimator, max_depth=max_depth),
        # the detector's box over the simulator's: EgoMap reads the goal's elevation from it
        GoalFeatures(goal_meter, gt_keys=None, box_key="goal_box"),
        DepthSections(n_points, exact=exact, max_depth=max_depth, invalid_value=invalid_value,
                      center_frac=center_frac, seed=seed, device=device),
        Discretize(thresholds, max_depth=max_depth),
    )
