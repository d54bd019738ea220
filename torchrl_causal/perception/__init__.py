"""Goal perception: the detector interface and the one goal measurement (thesis sec. 4.2).

* :class:`GoalDetector` -- interface: batched RGB (+ depth) -> boxes and confidences.
* :class:`SimGoalDetector` -- the simulator's ground-truth box (segmentation rendering).
* :class:`GoalMeter` -- detections -> :class:`GoalMeasurement` (in sight, distance,
  angle); used by :class:`~torchrl_causal.envs.drone.DroneNavEnv`'s reward and by
  :class:`~torchrl_causal.transforms.goal.GoalFeatures`.

Example:
    >>> from torchrl_causal.perception import GoalMeter, SimGoalDetector
    >>> GoalMeter(SimGoalDetector(), hfov_deg=60.0).confidence_threshold
    0.7
"""

from torchrl_causal.perception.goal import (
    GoalDetector,
    GoalMeasurement,
    GoalMeter,
    SimGoalDetector,
    box_angle_deg,
    horizontal_fov,
)

__all__ = ["GoalDetector", "SimGoalDetector", "GoalMeasurement", "GoalMeter", "box_angle_deg",
           "horizontal_fov"]

# Imported on first use (MuJoCo rendering, ultralytics): the package stays light and
# importable without the ``perception`` extra.
_LAZY = {
    "View": "torchrl_causal.perception.dataset",
    "render_views": "torchrl_causal.perception.dataset",
    "write_datasets": "torchrl_causal.perception.dataset",
    "load_views": "torchrl_causal.perception.dataset",
    "evaluate_detector": "torchrl_causal.perception.dataset",
    "YoloGoalDetector": "torchrl_causal.perception.yolo",
    "MonoDepth": "torchrl_causal.perception.depth",
    "evaluate_depth": "torchrl_causal.perception.depth",
    "VideoPath": "torchrl_causal.perception.video_path",
    "crop_resize": "torchrl_causal.perception.video_path",
    "GoalOffsetNet": "torchrl_causal.perception.arrival",
    "GoalOffsetEstimator": "torchrl_causal.perception.arrival",
}
__all__ += list(_LAZY)


def __getattr__(name):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)
