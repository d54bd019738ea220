"""The nine causal state features as TorchRL transforms (thesis sec. 4.2-4.3).

* :class:`DepthSections` -- minimum depth in the five image sections (Fig. 4.2).
* :class:`EstimatedDepth` -- ``depth`` estimated from ``pixels`` by a monocular
  depth estimator (:class:`~torchrl_causal.perception.depth.MonoDepth`), in place of
  the simulator's depth.
* :class:`GoalFeatures` -- goal in sight / distance / angle from a
  :class:`~torchrl_causal.perception.goal.GoalMeter` (for envs that do not
  measure the goal themselves; ``DroneNavEnv`` does).
* :class:`Discretize` -- ``causal_features`` (float32 ``[..., n_vars]``, 9 for the default schema) and
  ``causal_state`` (int64 ``[..., n_vars]``, ``MultiCategorical``) for any ``VariableSchema``.
* :func:`make_causal_transforms` -- the whole stack for a ``DroneNavEnv``.
* :class:`ActionHistory` -- the last actions as an observation (the policy's
  short-term memory; not one of the nine variables).
* :class:`EgoMap` -- an egocentric occupancy map and the goal's remembered place,
  from depth, the goal measurement and dead reckoning (the generalist's memory).
* :class:`VisitMemory` -- the actions already taken from the dead-reckoned pose
  the drone is at (read by :class:`~torchrl_causal.modules.RevisitGuard`).

The altitude needs no transform: ``Discretize`` reads the env's ``altitude``
key directly (rename another env's key with TorchRL's ``RenameTransform`` or
pass ``altitude_key``).
"""

from torchrl_causal.transforms.depth import SECTION_NAMES, DepthSections, section_masks
from torchrl_causal.transforms.discretize import Discretize, Thresholds
from torchrl_causal.transforms.estimated_depth import EstimatedDepth
from torchrl_causal.transforms.goal import GoalFeatures
from torchrl_causal.transforms.egomap import CLEARANCE_FIELDS, GOAL_MEMORY_FIELDS, EgoMap
from torchrl_causal.transforms.history import ActionHistory
from torchrl_causal.transforms.stack import make_causal_transforms
from torchrl_causal.transforms.visits import VisitMemory

__all__ = [
    "ActionHistory",
    "CLEARANCE_FIELDS",
    "DepthSections",
    "Discretize",
    "EgoMap",
    "EstimatedDepth",
    "GOAL_MEMORY_FIELDS",
    "GoalFeatures",
    "SECTION_NAMES",
    "Thresholds",
    "VisitMemory",
    "make_causal_transforms",
    "section_masks",
]
