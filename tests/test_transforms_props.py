"""Property tests: any depth map and any detections give valid, finite features."""

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from tensordict import TensorDict

from torchrl_causal.perception.goal import GoalDetector, GoalMeter, SimGoalDetector
from torchrl_causal.schema import DEFAULT_SCHEMA
from torchrl_causal.transforms import DepthSections, Discretize, GoalFeatures

CARD = torch.tensor(DEFAULT_SCHEMA.cardinalities)
MAX_DEPTH = 10.0

wild = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32),
    st.sampled_from([0.0, -0.0, float("nan"), float("inf"), -float("inf"), 1e30, 3.4e38, 0.1]),
)
depth_maps = st.integers(4, 12).flatmap(
    lambda h: st.integers(4, 12).flatmap(
        lambda w: st.integers(1, 3).flatmap(
            lambda b: arrays(np.float32, (b, h, w), elements=wild)
        )
    )
)
box_lists = st.integers(0, 4).flatmap(
    lambda k: st.tuples(
        arrays(np.float32, (k, 4), elements=wild), arrays(np.float32, (k,), elements=wild)
    )
)


class ListDetector(GoalDetector):
    """Returns the same given boxes and scores for every image."""

    def __init__(self, boxes, scores):
        self.boxes, self.scores = torch.from_numpy(boxes), torch.from_numpy(scores)

    def detect(self, pixels, depth=None, **gt):
        B = pixels.shape[0]
        return self.boxes.expand(B, *self.boxes.shape), self.scores.expand(B, *self.scores.shape)


def check_valid(out, batch):
    state, feats = out["causal_state"], out["causal_features"]
    assert state.shape == (*batch, 9) and state.dtype == torch.int64
    assert ((state >= 0) & (state < CARD)).all()
    assert feats.dtype == torch.float32 and torch.isfinite(feats).all()
    assert ((feats[..., :5] >= 0) & (feats[..., :5] <= MAX_DEPTH)).all()


@settings(max_examples=50, deadline=None)
@given(depth=depth_maps, boxes=box_lists, exact=st.booleans(),
       altitude=st.floats(allow_nan=True, allow_infinity=True, width=32))
def test_any_depth_map_and_any_boxes_give_valid_categories(depth, boxes, exact, altitude):
    depth = torch.from_numpy(depth)
    B, h, w = depth.shape
    td = TensorDict(
        {
            "pixels": torch.zeros(B, h, w, 3, dtype=torch.uint8),
            "depth": depth,
            "altitude": torch.full((B, 1), altitude),
        },
        [B],
    )
    goal = GoalFeatures(GoalMeter(ListDetector(*boxes), hfov_deg=70.0, max_depth=MAX_DEPTH))
    out = Discretize(max_depth=MAX_DEPTH)(DepthSections(exact=exact, seed=0)(goal(td)))
    check_valid(out, (B,))
    seen = out["goal_in_sight"].squeeze(-1)
    assert (out["causal_state"][seen, 6] < 2).all() and (out["causal_state"][~seen, 6] == 2).all()
    assert ((out["goal_distance"] >= 0) & (out["goal_distance"] <= MAX_DEPTH)).all()
    assert (out["goal_angle"].abs() <= 90).all()


@settings(max_examples=50, deadline=None)
@given(depth=depth_maps, box=arrays(np.float32, (4,), elements=wild), count=wild)
def test_sim_detector_with_any_ground_truth_gives_valid_categories(depth, box, count):
    depth = torch.from_numpy(depth)
    B, h, w = depth.shape
    td = TensorDict(
        {
            "pixels": torch.zeros(B, h, w, 3, dtype=torch.uint8),
            "depth": depth,
            "altitude": torch.ones(B, 1),
            "goal_box": torch.from_numpy(box).expand(B, 4).clone(),
            "goal_pixels": torch.full((B, 1), count),
        },
        [B],
    )
    goal = GoalFeatures(GoalMeter(SimGoalDetector(min_pixels=1), hfov_deg=90.0))
    check_valid(Discretize()(DepthSections(seed=1)(goal(td))), (B,))


@settings(max_examples=50, deadline=None)
@given(values=arrays(np.float32, (2, 9), elements=wild), in_sight=st.booleans())
def test_discretize_alone_accepts_any_values(values, in_sight):
    v = torch.from_numpy(values)
    td = TensorDict(
        {
            "depth_sections": v[:, :5],
            "goal_in_sight": torch.full((2, 1), in_sight),
            "goal_distance": v[:, 6:7],
            "goal_angle": v[:, 7:8],
            "altitude": v[:, 8:9],
        },
        [2],
    )
    check_valid(Discretize()(td), (2,))
