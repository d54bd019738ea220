"""The goal measurement as a transform, for envs that do not measure it themselves."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs.transforms import Transform

from torchrl_causal.perception.goal import GoalMeter, SimGoalDetector

__all__ = ["GoalFeatures"]


class GoalFeatures(Transform):
    """Goal in sight, distance and angle from a :class:`~torchrl_causal.perception.goal.GoalMeter`.

    Runs ``meter`` on ``pixels`` (``uint8 [..., H, W, 3]``) and ``depth``
    (``float32 [..., H, W]``, metres) and writes ``goal_in_sight`` (bool
    ``[..., 1]``), ``goal_distance`` (float32 ``[..., 1]``, m, 0.0 when not in
    sight) and ``goal_angle`` (float32 ``[..., 1]``, deg, positive = goal left
    of the image centre, 0.0 when not in sight). The rules (confidence
    threshold, median depth inside the box, pinhole bearing) are the meter's:
    see :mod:`torchrl_causal.perception.goal`.

    :class:`~torchrl_causal.envs.DroneNavEnv` already writes these keys with its
    own ``env.goal_meter`` (the one its reward uses), so
    :func:`~torchrl_causal.transforms.make_causal_transforms` does not add this
    transform; use it on other envs, the Tello, or offline data.

    When the meter's detector is a
    :class:`~torchrl_causal.perception.goal.SimGoalDetector`, the simulator's
    ground truth is read from ``gt_keys`` (default ``("goal_box",
    "goal_pixels")``) and passed as ``gt_box`` / ``gt_pixels``.

    Args:
        meter: the goal meter.
        pixels_key, depth_key: input keys.
        gt_keys: ``(box_key, pixels_key)`` of the simulator ground truth, or
            None to pass none (default: automatic, from the detector type).
        out_keys: ``(in_sight, distance, angle)`` output keys.
        box_key: also write the measured box there (float32 ``[..., 4]``, pixels,
            zeros when not in sight), or None (default). The RGB stack of
            :func:`~torchrl_causal.transforms.make_causal_transforms` writes it to
            ``"goal_box"``, over ``DroneNavEnv``'s ground truth, so that
            :class:`~torchrl_causal.transforms.EgoMap` reads the goal's elevation from
            the detector's box, as it does on the Tello (``TelloEnv``'s ``goal_box``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_causal.perception.goal import GoalMeter, SimGoalDetector
        >>> t = GoalFeatures(GoalMeter(SimGoalDetector(min_pixels=4), hfov_deg=90.0))
        >>> td = TensorDict({
        ...     "pixels": torch.zeros(2, 84, 84, 3, dtype=torch.uint8),
        ...     "depth": torch.full((2, 84, 84), 2.0),
        ...     "goal_box": torch.tensor([[32.0, 32.0, 52.0, 52.0], [0.0, 0.0, 0.0, 0.0]]),
        ...     "goal_pixels": torch.tensor([[400.0], [0.0]]),
        ... }, [2])
        >>> out = t(td)
        >>> out["goal_in_sight"].tolist(), out["goal_distance"].tolist()
        ([[True], [False]], [[2.0], [0.0]])
    """

    def __init__(
        self,
        meter: GoalMeter,
        *,
        pixels_key="pixels",
        depth_key="depth",
        gt_keys="auto",
        out_keys=("goal_in_sight", "goal_distance", "goal_angle"),
        box_key: str | None = None,
    ):
        if not isinstance(meter, GoalMeter):
            raise ValueError(f"meter must be a GoalMeter, got {meter!r}")
        if gt_keys == "auto":
            gt_keys = (
                ("goal_box", "goal_pixels")
                if isinstance(meter.detector, SimGoalDetector)
                else None
            )
        if gt_keys is not None and len(tuple(gt_keys)) != 2:
            raise ValueError(f"gt_keys must be (box_key, pixels_key) or None, got {gt_keys!r}")
        out_keys = tuple(out_keys)
        if len(out_keys) != 3:
            raise ValueError(f"out_keys must be 3 keys (in_sight, distance, angle), got {out_keys!r}")
        if box_key is not None and not isinstance(box_key, str):
            raise ValueError(f"box_key must be a key (str) or None, got {box_key!r}")
        in_keys = [pixels_key, depth_key] + (list(gt_keys) if gt_keys is not None else [])
        super().__init__(in_keys=in_keys,
                         out_keys=list(out_keys) + ([box_key] if box_key is not None else []))
        self.box_key = box_key
        self.meter = meter
        self.gt_keys = None if gt_keys is None else tuple(gt_keys)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        pixels = next_tensordict.get(self.in_keys[0])
        depth = next_tensordict.get(self.in_keys[1])
        H, W = depth.shape[-2:]
        batch = depth.shape[:-2]
        gt = {}
        if self.gt_keys is not None:
            gt["gt_box"] = next_tensordict.get(self.gt_keys[0]).reshape(-1, 4)
            gt["gt_pixels"] = next_tensordict.get(self.gt_keys[1]).reshape(-1)
        m = self.meter(pixels.reshape(-1, *pixels.shape[-3:]), depth.reshape(-1, H, W), **gt)
        in_sight = m.in_sight
        # not in sight: the meter gives distance NaN (the features want 0) and angle 0
        distance = torch.where(in_sight, m.distance, torch.zeros_like(m.distance))
        next_tensordict.set(self.out_keys[0], in_sight.reshape(*batch, 1))
        next_tensordict.set(self.out_keys[1], distance.to(torch.float32).reshape(*batch, 1))
        next_tensordict.set(self.out_keys[2], m.angle.to(torch.float32).reshape(*batch, 1))
        if self.box_key is not None:
            box = torch.where(in_sight[:, None], m.box.to(torch.float32), torch.zeros_like(m.box,
                                                                                       dtype=torch.float32))
            next_tensordict.set(self.box_key, box.reshape(*batch, 4))
        return next_tensordict

    forward = _call

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase):
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        shape = (*observation_spec.shape, 1)
        device = observation_spec.device
        observation_spec[self.out_keys[0]] = Categorical(
            2, shape=shape, dtype=torch.bool, device=device
        )
        for key in self.out_keys[1:3]:
            observation_spec[key] = Unbounded(shape=shape, dtype=torch.float32, device=device)
        if self.box_key is not None:
            h, w = observation_spec[self.in_keys[1]].shape[-2:]
            observation_spec[self.box_key] = Bounded(
                0.0, float(max(h, w)), shape=(*observation_spec.shape, 4), dtype=torch.float32,
                device=device)
        return observation_spec
