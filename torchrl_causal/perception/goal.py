"""Goal detection interface and the one goal measurement (thesis sec. 4.2, Fig. 4.6).

The reward of :class:`~torchrl_causal.envs.DroneNavEnv` and the
``goal_in_sight`` / ``goal_distance`` / ``goal_angle`` features are computed by
the same :class:`GoalMeter`, so swapping the detector changes both
consistently.

Conventions:
    * boxes are ``(x0, y0, x1, y1)`` in pixels, ``x1``/``y1`` exclusive;
    * the angle is in degrees, **positive when the goal is left of the image
      centre** (thesis: "far left (> 15)"), from the box centre and the
      camera's horizontal field of view (pinhole model);
    * the distance is the median metric z-depth of the valid depth pixels
      inside the box (robust to the background seen through/around the
      board's edges), converted to the range along the ray through the box
      centre (``distance="range"``, the default: times
      ``sqrt(1 + ((cx - W/2) / f)**2 + ((cy - H/2) / f)**2)`` for the box
      centre ``(cx, cy)``, square pixels, focal ``f`` from the field of view),
      so an off-axis goal is not reported closer than it is;
      ``distance="depth"`` keeps the plain z-depth. Either is clipped to
      ``max_depth``;
    * boxes are clipped to the image (NaN coordinates count as 0), so a box
      partly outside the image is measured on its visible part; NaN scores
      count as 0; a box without any valid depth pixel is not in sight;
    * while the goal is not in sight the distance is ``nan`` and the angle 0.

Example:
    >>> import torch
    >>> from torchrl_causal.perception.goal import GoalMeter, SimGoalDetector
    >>> meter = GoalMeter(SimGoalDetector(min_pixels=4), hfov_deg=90.0)
    >>> pixels = torch.zeros(1, 84, 84, 3, dtype=torch.uint8)
    >>> depth = torch.full((1, 84, 84), 2.0)
    >>> gt_box = torch.tensor([[32.0, 32.0, 52.0, 52.0]])
    >>> m = meter(pixels, depth, gt_box=gt_box, gt_pixels=torch.tensor([400.0]))
    >>> bool(m.in_sight[0]), round(float(m.distance[0]), 2), round(float(m.angle[0]), 2)
    (True, 2.0, 0.0)
    >>> off_axis = torch.tensor([[0.0, 32.0, 20.0, 52.0]])  # centre 32 px left of the axis
    >>> m = meter(pixels, depth, gt_box=off_axis, gt_pixels=torch.tensor([400.0]))
    >>> round(float(m.distance[0]), 2), round(float(m.angle[0]), 1)
    (2.51, 37.3)
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass

import torch

__all__ = ["GoalDetector", "SimGoalDetector", "GoalMeasurement", "GoalMeter", "box_angle_deg",
           "horizontal_fov"]


class GoalDetector(abc.ABC):
    """Finds the goal marker in a batch of images.

    Subclasses implement :meth:`detect`. Inputs are batched: ``pixels`` is
    ``uint8 [B, H, W, 3]``, ``depth`` ``float32 [B, H, W]`` (metres) or None.
    Simulation-only ground truth (``gt_box [B, 4]``, ``gt_pixels [B]``) is
    passed as keyword arguments; real detectors ignore it.

    Example:
        >>> import torch
        >>> class RedDetector(GoalDetector):
        ...     # boxes the red pixels of each image; confidence 1 if any
        ...     def detect(self, pixels, depth=None, **gt):
        ...         red = (pixels[..., 0] > 200) & (pixels[..., 1] < 50)
        ...         boxes, scores = [], []
        ...         for m in red:
        ...             ys, xs = torch.nonzero(m, as_tuple=True)
        ...             if len(xs):
        ...                 boxes.append([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1])
        ...             else:
        ...                 boxes.append([0, 0, 0, 0])
        ...             scores.append(float(len(xs) > 0))
        ...         return (torch.tensor(boxes, dtype=torch.float32)[:, None],
        ...                 torch.tensor(scores)[:, None])
        >>> img = torch.zeros(1, 32, 32, 3, dtype=torch.uint8)
        >>> img[0, 8:16, 20:28, 0] = 255
        >>> boxes, scores = RedDetector()(img)
        >>> boxes[0, 0].tolist(), scores.tolist()
        ([20.0, 8.0, 28.0, 16.0], [[1.0]])
    """

    @abc.abstractmethod
    def detect(self, pixels: torch.Tensor, depth: torch.Tensor | None = None, **gt):
        """Returns ``(boxes [B, K, 4] float32, scores [B, K] float32)``; K may be 0."""

    def __call__(self, pixels, depth=None, **gt):
        return self.detect(pixels, depth, **gt)


class SimGoalDetector(GoalDetector):
    """Ground-truth detector: the goal's visible box from segmentation rendering.

    Confidence is 1 when at least ``min_pixels`` pixels of the goal are visible,
    else 0.

    Args:
        min_pixels: visible goal pixels needed to count as recognised.

    Example:
        >>> import torch
        >>> det = SimGoalDetector(min_pixels=10)
        >>> boxes, scores = det(torch.zeros(2, 84, 84, 3, dtype=torch.uint8),
        ...                     gt_box=torch.tensor([[0., 0, 5, 5], [10, 10, 30, 30]]),
        ...                     gt_pixels=torch.tensor([5., 400.]))
        >>> scores.squeeze(-1).tolist()
        [0.0, 1.0]
    """

    def __init__(self, min_pixels: int = 20):
        if min_pixels < 1:
            raise ValueError(f"min_pixels must be >= 1, got {min_pixels!r}")
        self.min_pixels = int(min_pixels)

    def detect(self, pixels, depth=None, *, gt_box=None, gt_pixels=None, **_):
        if gt_box is None or gt_pixels is None:
            raise ValueError(
                "SimGoalDetector needs the simulator's ground truth: gt_box and gt_pixels"
            )
        gt_box = torch.as_tensor(gt_box, dtype=torch.float32)
        gt_pixels = torch.as_tensor(gt_pixels, dtype=torch.float32).reshape(gt_box.shape[:-1])
        scores = (gt_pixels >= self.min_pixels).to(torch.float32)
        return gt_box.unsqueeze(-2), scores.unsqueeze(-1)


@dataclass
class GoalMeasurement:
    """Batched goal measurement: ``in_sight`` bool ``[B]``, ``distance`` (m, nan when
    not in sight) ``[B]``, ``angle`` (deg, 0 when not in sight) ``[B]``,
    ``confidence`` ``[B]`` and the chosen ``box`` ``[B, 4]``.

    Example:
        >>> import torch
        >>> meter = GoalMeter(SimGoalDetector(min_pixels=4), hfov_deg=90.0)
        >>> m = meter(torch.zeros(1, 84, 84, 3, dtype=torch.uint8), torch.full((1, 84, 84), 2.0),
        ...           gt_box=torch.tensor([[0.0, 0.0, 0.0, 0.0]]), gt_pixels=torch.tensor([0.0]))
        >>> bool(m.in_sight[0]), bool(m.distance[0].isnan()), float(m.angle[0])
        (False, True, 0.0)
    """

    in_sight: torch.Tensor
    distance: torch.Tensor
    angle: torch.Tensor
    confidence: torch.Tensor
    box: torch.Tensor


def _focal_px(width: int, hfov_deg: float) -> float:
    """Pinhole focal length in pixels: ``(W/2) / tan(hfov/2)``."""
    return (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)


def horizontal_fov(vfov_deg: float, height: int, width: int) -> float:
    """Horizontal field of view (deg) of a pinhole camera with square pixels.

    Example:
        >>> round(horizontal_fov(60.0, 240, 320), 2), round(horizontal_fov(60.0, 84, 84), 6)
        (75.18, 60.0)
    """
    return math.degrees(2 * math.atan(math.tan(math.radians(vfov_deg) / 2) * width / height))


def box_angle_deg(box: torch.Tensor, width: int, hfov_deg: float) -> torch.Tensor:
    """Bearing (deg, positive = left of centre) of box centres ``[..., 4]``.

    Pinhole model: ``atan((W/2 - cx) / f)`` with ``f = (W/2) / tan(hfov/2)``.

    Example:
        >>> import torch
        >>> box_angle_deg(torch.tensor([[0.0, 0.0, 2.0, 2.0]]), width=84, hfov_deg=90.0).round()
        tensor([44.])
    """
    focal = _focal_px(width, hfov_deg)
    cx = (box[..., 0] + box[..., 2]) / 2.0
    return torch.rad2deg(torch.atan((width / 2.0 - cx) / focal))


class GoalMeter:
    """Turns detections into the goal measurement used by the reward and the features.

    Args:
        detector: a :class:`GoalDetector`.
        hfov_deg: horizontal field of view of the camera, degrees.
        confidence_threshold: in sight when the best score is strictly above it
            (thesis: 0.7).
        max_depth: depth values above this (or non-finite, or <= 0) are invalid.
        distance: ``"range"`` (along the ray through the box centre) or
            ``"depth"`` (metric z-depth), see the module docs.

    Example:
        >>> meter = GoalMeter(SimGoalDetector(), hfov_deg=90.0, confidence_threshold=0.7)
        >>> meter.confidence_threshold
        0.7
    """

    def __init__(
        self,
        detector: GoalDetector,
        hfov_deg: float,
        confidence_threshold: float = 0.7,
        max_depth: float = 10.0,
        distance: str = "range",
    ):
        if distance not in ("range", "depth"):
            raise ValueError(f"distance must be 'range' or 'depth', got {distance!r}")
        if not 0.0 <= confidence_threshold <= 1.0:
            raise ValueError(
                f"confidence_threshold must be in [0, 1], got {confidence_threshold!r}"
            )
        if not 0.0 < hfov_deg < 180.0:
            raise ValueError(f"hfov_deg must be in (0, 180), got {hfov_deg!r}")
        self.detector = detector
        self.hfov_deg = float(hfov_deg)
        self.confidence_threshold = float(confidence_threshold)
        self.max_depth = float(max_depth)
        self.distance = distance

    #: up to this batch size, medians are taken on per-frame crops (cheaper than full masks)
    _CROP_MAX_BATCH = 4

    def _median_crops(self, depth: torch.Tensor, box_i: torch.Tensor) -> torch.Tensor:
        out = []
        for d, (x0, y0, x1, y1) in zip(depth, box_i.tolist()):
            crop = d[y0:y1, x0:x1]
            v = crop[(crop > 0) & (crop <= self.max_depth)]  # NaN and +-inf fail these
            out.append(v.median() if v.numel() else d.new_tensor(float("nan")))
        return torch.stack(out) if out else depth.new_zeros(0)

    def _median_masked(self, depth: torch.Tensor, box_i: torch.Tensor) -> torch.Tensor:
        B, H, W = depth.shape
        x0, y0, x1, y1 = box_i.unbind(-1)
        xs = torch.arange(W, device=depth.device).view(1, 1, W)
        ys = torch.arange(H, device=depth.device).view(1, H, 1)
        inside = (
            (xs >= x0.view(B, 1, 1))
            & (xs < x1.view(B, 1, 1))
            & (ys >= y0.view(B, 1, 1))
            & (ys < y1.view(B, 1, 1))
        )
        valid = (depth > 0) & (depth <= self.max_depth) & inside
        masked = torch.where(valid, depth, torch.full_like(depth, float("nan")))
        return masked.reshape(B, -1).nanmedian(-1).values

    def ray_scale(self, box: torch.Tensor, height: int, width: int) -> torch.Tensor:
        """Range / z-depth ratio of the rays through box centres ``[..., 4]`` (square pixels)."""
        focal = _focal_px(width, self.hfov_deg)
        u = ((box[..., 0] + box[..., 2]) / 2.0 - width / 2.0) / focal
        v = ((box[..., 1] + box[..., 3]) / 2.0 - height / 2.0) / focal
        return torch.sqrt(1.0 + u * u + v * v)

    def __call__(self, pixels, depth, **gt) -> GoalMeasurement:
        pixels = torch.as_tensor(pixels)
        depth = torch.as_tensor(depth, dtype=torch.float32)
        B, H, W = depth.shape[0], depth.shape[-2], depth.shape[-1]
        boxes, scores = self.detector(pixels, depth, **gt)
        boxes = torch.as_tensor(boxes, dtype=torch.float32).reshape(B, -1, 4)
        scores = torch.as_tensor(scores, dtype=torch.float32).reshape(B, -1)
        if scores.shape[-1] == 0:
            conf = torch.zeros(B, device=depth.device)
            box = torch.zeros(B, 4, device=depth.device)
        else:
            conf, best = scores.max(-1)
            box = boxes.gather(1, best.view(B, 1, 1).expand(B, 1, 4)).squeeze(1)
        conf = torch.nan_to_num(conf, nan=0.0)
        in_sight = conf > self.confidence_threshold
        # clip boxes to the image before any integer cast (NaN -> 0, +-inf -> border):
        # the measurement only uses the visible part of a box
        box = torch.nan_to_num(box, nan=0.0, posinf=float(max(H, W)), neginf=0.0)
        limits = torch.tensor([W, H, W, H], dtype=torch.float32, device=depth.device)
        box = torch.minimum(box.clamp(min=0.0), limits)
        # median valid z-depth inside each box (valid: finite, > 0, <= max_depth)
        box_i = box.round().long()
        if B <= self._CROP_MAX_BATCH:
            dist = self._median_crops(depth, box_i)
        else:
            dist = self._median_masked(depth, box_i)
        if self.distance == "range":
            dist = dist * self.ray_scale(box, H, W)
        dist = dist.clamp(max=self.max_depth)  # like the depth itself
        in_sight = in_sight & torch.isfinite(dist)
        distance = torch.where(in_sight, dist, torch.full_like(dist, float("nan")))
        angle = torch.where(in_sight, box_angle_deg(box, W, self.hfov_deg), torch.zeros_like(dist))
        return GoalMeasurement(in_sight, distance, angle, conf, box)
