"""Agreement of an RGB-only feature stack with the ground-truth one.

:func:`feature_agreement` runs two feature stacks on the same rendered views
(:func:`~torchrl_causal.perception.dataset.render_views`) and compares the
discretised ``causal_state`` variable by variable:

* the **reference** stack (:func:`reference_stack`) reads the simulator's exact
  depth and the goal's segmentation box, i.e. what
  :class:`~torchrl_causal.envs.DroneNavEnv` gives the agent in training;
* the **stack under test** (typically
  ``make_causal_transforms(perception="rgb")``) sees the RGB image only.

Both stacks get the same altitude (the drone's height from the view's pose;
altitude never comes from the image, so it agrees by construction) and their
depth-pixel samplers are reseeded with the same seed before the run, so any
difference comes from perception alone.

Example:
    >>> from torchrl_causal.perception.agreement import feature_agreement, reference_stack
    >>> from torchrl_causal.perception.dataset import render_views
    >>> views = list(render_views("test", 4, seed=0, image_size=84))
    >>> res = feature_agreement(views, reference_stack(hfov_deg=60.0), hfov_deg=60.0)
    >>> res["n"], res["all_nine"], min(res["per_variable"].values())
    (4, 1.0, 1.0)
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_causal.perception.goal import GoalMeter, SimGoalDetector

__all__ = ["reference_stack", "views_to_tensordict", "feature_agreement"]

#: the env's ``goal_min_pixels`` (20) at its default 84 x 84, as a share of the image
_MIN_FRACTION = 0.0028


def reference_stack(hfov_deg: float, *, seed: int = 0, min_fraction: float = _MIN_FRACTION,
                    max_depth: float = 10.0, image_size: Sequence[int] = (84, 84)):
    """The ground-truth feature stack of :class:`~torchrl_causal.envs.DroneNavEnv`.

    ``GoalFeatures`` over a :class:`~torchrl_causal.perception.goal.SimGoalDetector`
    (segmentation box; in sight from ``min_fraction`` of the image, the env's
    ``goal_min_pixels=20`` at 84 x 84) on the exact depth, then
    ``DepthSections`` and ``Discretize`` as in
    :func:`~torchrl_causal.transforms.make_causal_transforms`.

    Args:
        hfov_deg: horizontal field of view (deg).
        seed: seed of the depth-pixel sampler.
        min_fraction: goal share of the image needed to be in sight.
        max_depth: depth range (m).
        image_size: ``(height, width)`` of the views (sets the pixel threshold).

    Example:
        >>> reference_stack(60.0)[0].meter.detector.min_pixels
        20
    """
    from torchrl_causal.transforms import make_causal_transforms

    h, w = int(image_size[0]), int(image_size[1])
    min_pixels = max(1, int(math.ceil(min_fraction * h * w - 1e-9)))
    meter = GoalMeter(SimGoalDetector(min_pixels), hfov_deg=hfov_deg, max_depth=max_depth)
    return make_causal_transforms(goal_meter=meter, seed=seed, max_depth=max_depth)


def views_to_tensordict(views: Sequence) -> TensorDict:
    """Stacks :class:`~torchrl_causal.perception.dataset.View` objects into a batch.

    Keys: ``pixels`` uint8 ``[N, H, W, 3]``, ``depth`` ``[N, H, W]``, ``altitude``
    ``[N, 1]`` (the pose's height), ``goal_box`` ``[N, 4]`` (zeros when no box),
    ``goal_pixels`` ``[N, 1]``.

    Example:
        >>> import numpy as np
        >>> from torchrl_causal.perception.dataset import View
        >>> v = View(np.zeros((32, 32, 3), np.uint8), np.ones((32, 32), np.float32), None, 0, 0,
        ...          "test", pose=(0.0, 0.0, 1.2, 0.0, 0.0, 0.0))
        >>> views_to_tensordict([v, v])["altitude"].squeeze(-1).tolist()
        [1.2000000476837158, 1.2000000476837158]
    """
    if len(views) == 0:
        raise ValueError("views is empty")
    boxes = [v.box if v.box is not None else (0.0, 0.0, 0.0, 0.0) for v in views]
    return TensorDict(
        {
            "pixels": torch.from_numpy(np.stack([v.rgb for v in views])),
            "depth": torch.from_numpy(np.stack([v.depth for v in views]).astype(np.float32)),
            "altitude": torch.tensor([[float(v.pose[2])] for v in views], dtype=torch.float32),
            "goal_box": torch.tensor(boxes, dtype=torch.float32),
            "goal_pixels": torch.tensor([[float(v.goal_pixels)] for v in views]),
        },
        batch_size=[len(views)],
    )


def _reseed(stack, seed: int) -> None:
    from torchrl_causal.transforms import DepthSections

    for t in stack:
        if isinstance(t, DepthSections):
            t.set_seed(seed)


@torch.no_grad()
def feature_agreement(views: Iterable, stack, *, hfov_deg: float, reference=None,
                      seed: int = 0, batch_size: int = 64) -> dict:
    """Per-variable agreement of ``stack``'s ``causal_state`` with the reference.

    Args:
        views: :class:`~torchrl_causal.perception.dataset.View` objects (all of
            one image size).
        stack: the feature stack under test (a ``Compose`` writing ``causal_state``).
        hfov_deg: the views' horizontal field of view (for the reference).
        reference: the reference stack (default: :func:`reference_stack`).
        seed: both stacks' depth samplers are reseeded with it first.
        batch_size: views per call.

    Returns:
        ``n`` (views), ``per_variable`` (share of views where the variable's
        category is the same, by variable name), ``all_nine`` (share where every
        variable agrees), ``confusion`` (per variable, a ``[reference][test]``
        count table as nested lists).
    """
    from torchrl_causal.schema import DEFAULT_SCHEMA

    if not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(f"batch_size must be an int >= 1, got {batch_size!r}")
    views = list(views)
    if not views:
        raise ValueError("views is empty")
    shape = views[0].rgb.shape[:2]
    if reference is None:
        reference = reference_stack(hfov_deg, seed=seed, image_size=shape)
    _reseed(reference, seed)
    _reseed(stack, seed)
    ref_states, test_states = [], []
    for i in range(0, len(views), batch_size):
        td = views_to_tensordict(views[i : i + batch_size])
        ref_states.append(reference(td.clone())["causal_state"])
        test_states.append(stack(td.clone())["causal_state"])
    ref = torch.cat(ref_states)
    test = torch.cat(test_states)
    names = DEFAULT_SCHEMA.names
    cards = DEFAULT_SCHEMA.cardinalities
    per_var, confusion = {}, {}
    for j, name in enumerate(names):
        per_var[name] = float((ref[:, j] == test[:, j]).float().mean())
        table = torch.zeros(cards[j], cards[j], dtype=torch.int64)
        table.index_put_((ref[:, j], test[:, j]), torch.ones(len(ref), dtype=torch.int64),
                         accumulate=True)
        confusion[name] = table.tolist()
    return {
        "n": len(views),
        "per_variable": per_var,
        "all_nine": float((ref == test).all(-1).float().mean()),
        "confusion": confusion,
    }
