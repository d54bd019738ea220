"""GoalMeter / SimGoalDetector: the one goal measurement used by reward and features."""

import math

import pytest
import torch

from torchrl_causal.perception.goal import (
    GoalDetector,
    GoalMeter,
    SimGoalDetector,
    box_angle_deg,
)

H = W = 84
NAN, INF = float("nan"), float("inf")


class Boxes(GoalDetector):
    def __init__(self, boxes, scores):
        self.boxes = torch.as_tensor(boxes, dtype=torch.float32)
        self.scores = torch.as_tensor(scores, dtype=torch.float32)

    def detect(self, pixels, depth=None, **gt):
        return self.boxes, self.scores


def measure(boxes, scores, depth, **kw):
    meter = GoalMeter(Boxes(boxes, scores), hfov_deg=kw.pop("hfov_deg", 90.0), **kw)
    B = depth.shape[0]
    return meter(torch.zeros(B, H, W, 3, dtype=torch.uint8), depth)


def test_crop_and_masked_medians_agree():
    g = torch.Generator().manual_seed(0)
    depth = torch.rand(8, H, W, generator=g) * 12
    depth[depth > 11] = NAN
    depth[depth < 0.3] = INF
    depth[:, :5] = 0.0
    boxes = torch.randint(0, H + 1, (8, 4), generator=g)
    boxes[:, 2:] = torch.maximum(boxes[:, 2:], boxes[:, :2])
    boxes[0] = torch.tensor([3, 3, 3, 9])  # empty
    boxes[1] = torch.tensor([0, 0, 84, 5])  # only invalid zeros
    meter = GoalMeter(SimGoalDetector(), hfov_deg=60.0)
    a = meter._median_crops(depth, boxes)
    b = meter._median_masked(depth, boxes)
    assert torch.equal(a.isnan(), b.isnan()) and a.isnan()[:2].all()
    assert torch.equal(a[~a.isnan()], b[~b.isnan()])
    # the public call gives the same for small (crop) and large (masked) batches
    gt = dict(gt_box=boxes.float(), gt_pixels=torch.full((8,), 100.0))
    px = torch.zeros(8, H, W, 3, dtype=torch.uint8)
    big = meter(px, depth, **gt)
    small = [meter(px[i : i + 1], depth[i : i + 1], gt_box=gt["gt_box"][i : i + 1],
                   gt_pixels=gt["gt_pixels"][i : i + 1]) for i in range(8)]
    assert torch.equal(big.in_sight, torch.cat([m.in_sight for m in small]))
    torch.testing.assert_close(
        big.distance, torch.cat([m.distance for m in small]), equal_nan=True
    )


def test_confidence_is_strict_nan_scores_count_as_zero_and_best_box_wins():
    depth = torch.full((1, H, W), 3.0)
    assert not measure([[[0, 0, 10, 10]]], [[0.7]], depth).in_sight.any()
    assert not measure([[[0, 0, 10, 10]]], [[NAN]], depth).in_sight.any()
    m = measure([[[0, 0, 10, 10], [60, 0, 84, 10]]], [[0.71, 0.9]], depth)
    assert m.in_sight.all() and m.box[0, 0] == 60 and m.confidence[0] == pytest.approx(0.9)
    empty = measure(torch.zeros(1, 0, 4), torch.zeros(1, 0), depth)
    assert not empty.in_sight.any() and empty.angle[0] == 0 and empty.distance.isnan().all()


def test_angle_sign_and_distance_modes():
    depth = torch.full((1, H, W), 2.0)
    left = measure([[[0, 32, 20, 52]]], [[1.0]], depth)
    right = measure([[[64, 32, 84, 52]]], [[1.0]], depth)
    assert left.angle[0] == pytest.approx(math.degrees(math.atan(32 / 42)), abs=1e-4)
    assert right.angle[0] == pytest.approx(-left.angle[0].item(), abs=1e-4)
    assert left.distance[0] == pytest.approx(2.0 / math.cos(math.atan(32 / 42)), rel=1e-5)
    flat = measure([[[0, 32, 20, 52]]], [[1.0]], depth, distance="depth")
    assert flat.distance[0] == pytest.approx(2.0)
    assert box_angle_deg(torch.tensor([32.0, 0, 52, 10]), 84, 90.0).item() == pytest.approx(0.0)


def test_boxes_are_clipped_and_invalid_depth_is_never_measured():
    depth = torch.full((3, H, W), 4.0)
    depth[1] = NAN
    depth[2, :, :42] = 20.0  # beyond range on the left half
    boxes = [[[-INF, NAN, INF, 1e30]], [[10, 10, 30, 30]], [[0, 0, 84, 84]]]
    scores = [[1.0], [1.0], [1.0]]
    m = measure(boxes, scores, depth.clone(), distance="depth")
    assert m.in_sight.tolist() == [True, False, True]
    assert torch.equal(m.box[0], torch.tensor([0.0, 0.0, 84.0, 84.0]))
    assert m.distance[0] == 4.0 and m.distance[2] == 4.0  # the 20 m half is ignored
    assert m.angle[1] == 0.0 and torch.isfinite(m.angle).all()
    far = measure([[[0, 0, 84, 84]]], [[1.0]], torch.full((1, H, W), 9.9), max_depth=10.0)
    assert far.distance[0] <= 10.0  # range is clipped to the sensor range


def test_sim_detector_and_meter_options():
    det = SimGoalDetector(min_pixels=10)
    boxes, scores = det(torch.zeros(2, H, W, 3), gt_box=torch.zeros(2, 4),
                        gt_pixels=torch.tensor([[9.0], [10.0]]))
    assert boxes.shape == (2, 1, 4) and scores.squeeze(-1).tolist() == [0.0, 1.0]
    with pytest.raises(ValueError, match="gt_box"):
        det(torch.zeros(1, H, W, 3))
    with pytest.raises(ValueError, match="min_pixels"):
        SimGoalDetector(min_pixels=0)
    with pytest.raises(ValueError, match="distance"):
        GoalMeter(det, hfov_deg=60.0, distance="euclid")
    with pytest.raises(ValueError, match="hfov_deg"):
        GoalMeter(det, hfov_deg=180.0)
    with pytest.raises(ValueError, match="confidence_threshold"):
        GoalMeter(det, hfov_deg=60.0, confidence_threshold=1.5)
