"""Feature transforms without an env: geometry, invalid-depth rule, thresholds,
goal features, specs, and the TorchRL checklist parts that need no env
(Compose, before an nn.Module, inside a replay buffer, batch sizes)."""

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.data import LazyTensorStorage, MultiCategorical, ReplayBuffer
from torchrl.envs.transforms import Compose

from torchrl_causal.perception.goal import GoalDetector, GoalMeter, SimGoalDetector
from torchrl_causal.schema import DEFAULT_SCHEMA
from torchrl_causal.transforms import (
    SECTION_NAMES,
    DepthSections,
    Discretize,
    GoalFeatures,
    Thresholds,
    make_causal_transforms,
    section_masks,
)

H = W = 84
NAN, INF = float("nan"), float("inf")


def frame_td(batch=(), depth=4.0, in_sight=False, distance=0.0, angle=0.0, altitude=1.0):
    b = tuple(batch)
    return TensorDict(
        {
            "depth": torch.full((*b, H, W), float(depth)),
            "pixels": torch.zeros((*b, H, W, 3), dtype=torch.uint8),
            "goal_in_sight": torch.full((*b, 1), bool(in_sight)),
            "goal_distance": torch.full((*b, 1), float(distance)),
            "goal_angle": torch.full((*b, 1), float(angle)),
            "altitude": torch.full((*b, 1), float(altitude)),
        },
        list(b),
    )


# ---------------------------------------------------------------- geometry
def test_sections_are_disjoint_cover_the_image_and_follow_fig_4_2():
    m = section_masks(H, W)
    assert m.shape == (5, H, W)
    assert torch.equal(m.sum(0), torch.ones(H, W, dtype=torch.long))
    c = m[0].nonzero()
    assert c.min(0).values.tolist() == [21, 21] and c.max(0).values.tolist() == [62, 62]
    # corners: each section lies in its own quadrant
    for k, (rows, cols) in enumerate(
        [(slice(0, 42), slice(0, 42)), (slice(0, 42), slice(42, 84)),
         (slice(42, 84), slice(0, 42)), (slice(42, 84), slice(42, 84))], start=1
    ):
        assert m[k][rows, cols].sum() == m[k].sum() > 0
    assert SECTION_NAMES == DEFAULT_SCHEMA.names[:5]


def test_section_geometry_options_are_validated():
    with pytest.raises(ValueError, match="center_frac"):
        section_masks(H, W, center_frac=1.0)
    with pytest.raises(ValueError, match="2x2"):
        section_masks(1, 5)
    for kwargs, name in [
        (dict(n_points=19), "n_points"),
        (dict(n_points=20.0), "n_points"),
        (dict(max_depth=-1.0), "max_depth"),
        (dict(max_depth=INF), "max_depth"),
        (dict(invalid_value=11.0), "invalid_value"),
        (dict(center_frac=0.0), "center_frac"),
    ]:
        with pytest.raises(ValueError, match=name):
            DepthSections(**kwargs)


# ---------------------------------------------------------------- DepthSections
def test_exact_min_matches_masked_min_and_random_min_is_an_upper_bound():
    g = torch.Generator().manual_seed(1)
    depth = torch.rand(6, H, W, generator=g) * 9 + 0.5
    masks = section_masks(H, W)
    ref = torch.stack([depth[:, m].amin(-1) for m in masks], -1)
    exact = DepthSections(exact=True).sections(depth)
    assert torch.equal(exact, ref)
    rnd = DepthSections(n_points=20, seed=0).sections(depth)
    assert (rnd >= exact).all() and (rnd > exact).any()
    # the sampled values are pixels of the right section
    for b in range(6):
        for k in range(5):
            assert (depth[b][masks[k]] == rnd[b, k]).any()
    # many points: the sampled min converges to the exact one
    many = DepthSections(n_points=4000, seed=0).sections(depth)
    assert (many - exact).abs().max() < 0.05


def test_an_obstacle_in_one_section_is_seen_only_there():
    depth = torch.full((H, W), 6.0)
    depth[50:84, 60:84] = 0.3  # bottom-right corner region only
    out = DepthSections(n_points=40, seed=3).sections(depth)
    assert out[4] == pytest.approx(0.3)
    assert torch.equal(out[:4], torch.full((4,), 6.0))


def test_sampling_is_seeded_and_independent_of_batching():
    depth = torch.rand(5, H, W, generator=torch.Generator().manual_seed(0)) * 10
    a = DepthSections(seed=7).sections(depth)
    b = DepthSections(seed=7)
    one_by_one = torch.stack([b.sections(depth[i]) for i in range(5)])
    assert torch.equal(a, one_by_one)
    c = DepthSections(seed=8).sections(depth)
    assert not torch.equal(a, c)
    # frames get fresh points each call (the thesis's random points per step)
    t = DepthSections(seed=7)
    assert not torch.equal(t.sections(depth), t.sections(depth))
    t.set_seed(7)
    assert torch.equal(t.sections(depth), a)


@pytest.mark.parametrize("exact", [False, True])
def test_invalid_depth_rule(exact):
    t = DepthSections(exact=exact, max_depth=10.0, seed=0)
    depth = torch.full((4, H, W), 3.0)
    depth[0] = NAN  # no valid reading anywhere -> max_depth
    depth[1] = INF  # nothing within range -> max_depth
    depth[2] = 0.0
    depth[2, ::2] = 25.0  # zeros ignored, beyond range clipped
    depth[3, ::2] = -INF  # ignored; the rest is valid
    depth[3, 1::2] = 2.0
    out = t.sections(depth)
    assert torch.isfinite(out).all()
    assert torch.equal(out[:3], torch.full((3, 5), 10.0))
    assert torch.equal(out[3], torch.full((5,), 2.0))
    low = DepthSections(exact=exact, invalid_value=0.0).sections(depth)
    assert torch.equal(low[0], torch.zeros(5))  # no reading at all -> invalid_value
    assert torch.equal(low[1], torch.full((5,), 10.0))  # +inf is a valid "far"


def test_depth_sections_spec_and_reset():
    t = DepthSections(seed=0)
    from torchrl.data import Composite, Unbounded

    spec = Composite(depth=Unbounded(shape=(3, 2, H, W)), shape=(3, 2))
    out = t.transform_observation_spec(spec.clone())
    assert out["depth_sections"].shape == (3, 2, 5)
    td = frame_td((3, 2))
    reset = t._reset(td.empty(), td.clone())
    assert out["depth_sections"].is_in(reset["depth_sections"])


# ---------------------------------------------------------------- Discretize
def _codes(**kw):
    depth = kw.pop("depth", torch.full((5,), 5.0))
    td = TensorDict(
        {
            "depth_sections": torch.as_tensor(depth, dtype=torch.float32),
            "goal_in_sight": torch.tensor([kw.pop("in_sight", True)]),
            "goal_distance": torch.tensor([float(kw.pop("distance", 2.0))]),
            "goal_angle": torch.tensor([float(kw.pop("angle", 0.0))]),
            "altitude": torch.tensor([float(kw.pop("altitude", 1.0))]),
        },
        [],
    )
    out = Discretize(**kw)(td)
    return out["causal_state"].tolist(), out["causal_features"]


@pytest.mark.parametrize(
    "kw,index,code",
    [
        (dict(depth=[0.5, 0.51, 0.0, 10.0, 0.49]), slice(0, 5), [0, 1, 0, 1, 0]),
        (dict(distance=0.5), 6, 0),
        (dict(distance=0.51), 6, 1),
        (dict(in_sight=False, distance=0.2), 6, 2),
        (dict(angle=15.0), 7, 0),
        (dict(angle=-15.0), 7, 0),
        (dict(angle=15.01), 7, 1),
        (dict(angle=-15.01), 7, 2),
        (dict(in_sight=False, angle=40.0), 7, 0),
        (dict(altitude=0.49), 8, 0),
        (dict(altitude=0.5), 8, 1),
        (dict(altitude=1.5), 8, 1),
        (dict(altitude=1.51), 8, 2),
        (dict(in_sight=True), 5, 1),
        (dict(in_sight=False), 5, 0),
        (dict(angle=20.0, thresholds=Thresholds(angle_good=25.0)), 7, 0),
        (dict(depth=[0.7] * 5, thresholds=Thresholds(depth_close=0.8)), slice(0, 5), [0] * 5),
        (dict(altitude=1.9, thresholds=Thresholds(altitude_high=2.0)), 8, 1),
    ],
)
def test_thesis_thresholds(kw, index, code):
    codes, _ = _codes(**kw)
    assert codes[index] == code


def test_features_hold_the_continuous_values_and_zero_when_goal_unseen():
    codes, f = _codes(depth=[1.0, 2.0, 3.0, 4.0, 5.0], distance=2.5, angle=-7.0, altitude=1.2)
    assert f.dtype == torch.float32
    assert f.tolist() == pytest.approx([1, 2, 3, 4, 5, 1, 2.5, -7.0, 1.2])
    codes, f = _codes(in_sight=False, distance=2.5, angle=-70.0)
    assert f[5:8].tolist() == [0.0, 0.0, 0.0]


def test_discretize_sanitises_inputs():
    codes, f = _codes(depth=[NAN, INF, -INF, -3.0, 1e30], distance=NAN, angle=INF, altitude=NAN)
    assert torch.isfinite(f).all()
    assert f[:5].tolist() == [10.0, 10.0, 0.0, 0.0, 10.0]
    assert codes == [1, 1, 0, 0, 1, 1, 1, 1, 0]


def test_thresholds_and_options_are_validated():
    for kw, name in [
        (dict(depth_close=0.0), "depth_close"),
        (dict(angle_good=NAN), "angle_good"),
        (dict(altitude_low=2.0, altitude_high=1.0), "altitude_low"),
        (dict(goal_close="1"), "goal_close"),
    ]:
        with pytest.raises(ValueError, match=name):
            Thresholds(**kw)
    with pytest.raises(ValueError, match="thresholds"):
        Discretize(thresholds={"depth_close": 0.5})
    with pytest.raises(ValueError, match="max_depth"):
        Discretize(max_depth=0.0)


def test_discretize_spec_is_multicategorical_with_schema_cardinalities():
    from torchrl.data import Composite, Unbounded

    spec = Composite(
        depth_sections=Unbounded(shape=(3, 2, 5)),
        altitude=Unbounded(shape=(3, 2, 1)),
        shape=(3, 2),
    )
    out = Discretize().transform_observation_spec(spec)
    state = out["causal_state"]
    assert isinstance(state, MultiCategorical)
    assert state.shape == (3, 2, 9) and state.dtype == torch.int64
    assert state.nvec[..., :].reshape(-1, 9)[0].tolist() == list(DEFAULT_SCHEMA.cardinalities)
    assert out["causal_features"].shape == (3, 2, 9)
    assert out["causal_features"].dtype == torch.float32


# ---------------------------------------------------------------- GoalFeatures
class FixedDetector(GoalDetector):
    """A real detector implementation returning given boxes and scores."""

    def __init__(self, boxes, scores):
        self.boxes = torch.as_tensor(boxes, dtype=torch.float32)
        self.scores = torch.as_tensor(scores, dtype=torch.float32)

    def detect(self, pixels, depth=None, **gt):
        B = pixels.shape[0]
        return self.boxes.expand(B, *self.boxes.shape), self.scores.expand(B, *self.scores.shape)


def test_goal_features_with_sim_detector_and_batch_dims():
    meter = GoalMeter(SimGoalDetector(min_pixels=20), hfov_deg=90.0)
    t = GoalFeatures(meter)
    assert t.in_keys == ["pixels", "depth", "goal_box", "goal_pixels"]
    td = frame_td((3, 2), depth=3.0)
    td["goal_box"] = torch.tensor([0.0, 20.0, 20.0, 40.0]).expand(3, 2, 4).clone()
    td["goal_pixels"] = torch.full((3, 2, 1), 400.0)
    td["goal_pixels"][1, 1] = 5.0  # too few pixels -> not recognised
    out = t(td)
    assert out["goal_in_sight"].shape == (3, 2, 1) and out["goal_in_sight"].dtype == torch.bool
    assert out["goal_in_sight"].sum() == 5 and not out["goal_in_sight"][1, 1]
    # range along the ray through the box centre (10, 30): z-depth 3 m times the ray's scale
    f = 42.0  # focal length of an 84 px wide, 90 deg image
    scale = math.sqrt(1 + ((10 - 42) / f) ** 2 + ((30 - 42) / f) ** 2)
    assert out["goal_distance"][0, 0].item() == pytest.approx(3.0 * scale, rel=1e-5)
    depth_only = GoalFeatures(GoalMeter(SimGoalDetector(20), hfov_deg=90.0, distance="depth"))
    assert depth_only(td.clone())["goal_distance"][0, 0].item() == pytest.approx(3.0)
    assert out["goal_distance"][1, 1].item() == 0.0 and out["goal_angle"][1, 1].item() == 0.0
    # box centre x = 10 on an 84-wide, 90 deg image: left of centre -> positive
    expected = math.degrees(math.atan((42 - 10) / 42))
    assert out["goal_angle"][0, 0].item() == pytest.approx(expected, abs=1e-4)


def test_goal_features_confidence_threshold_is_strict_and_best_box_wins():
    depth = torch.full((1, H, W), 2.0)
    depth[0, :, 60:] = 5.0
    boxes = [[0.0, 0.0, 10.0, 10.0], [64.0, 0.0, 84.0, 20.0]]
    t = GoalFeatures(GoalMeter(FixedDetector(boxes, [0.7, 0.65]), hfov_deg=60.0))
    assert t.in_keys == ["pixels", "depth"]
    td = TensorDict({"pixels": torch.zeros(1, H, W, 3, dtype=torch.uint8), "depth": depth}, [1])
    assert not t(td)["goal_in_sight"].any()  # 0.7 is not > 0.7
    t = GoalFeatures(GoalMeter(FixedDetector(boxes, [0.6, 0.95]), hfov_deg=60.0, distance="depth"))
    out = t(td)
    assert out["goal_in_sight"].all() and out["goal_distance"].item() == pytest.approx(5.0)
    assert out["goal_angle"].item() < 0  # right of centre
    none = GoalFeatures(GoalMeter(FixedDetector(torch.zeros(0, 4), torch.zeros(0)), 60.0))
    assert not none(td)["goal_in_sight"].any()


def test_goal_features_options_are_validated():
    with pytest.raises(ValueError, match="meter"):
        GoalFeatures(SimGoalDetector())
    meter = GoalMeter(SimGoalDetector(), hfov_deg=60.0)
    with pytest.raises(ValueError, match="gt_keys"):
        GoalFeatures(meter, gt_keys=("a",))
    with pytest.raises(ValueError, match="out_keys"):
        GoalFeatures(meter, out_keys=("a", "b"))


# ---------------------------------------------------------------- checklist (no env)
@pytest.mark.parametrize("batch", [(), (1,), (3, 2)])
def test_stack_without_env_in_compose_and_batch_sizes(batch):
    stack = make_causal_transforms(seed=0)
    assert isinstance(stack, Compose)
    td = frame_td(batch, depth=0.3, in_sight=True, distance=2.0, angle=20.0, altitude=2.0)
    out = stack(td)
    assert out["causal_state"].shape == (*batch, 9)
    assert out["causal_features"].shape == (*batch, 9)
    expected = torch.tensor([0, 0, 0, 0, 0, 1, 1, 1, 2])
    assert (out["causal_state"] == expected).all()
    # each transform alone gives the same as the composed stack
    alone = Discretize()(DepthSections(seed=0)(frame_td(batch, 0.3, True, 2.0, 20.0, 2.0)))
    assert torch.equal(alone["causal_state"], out["causal_state"])


def test_stack_before_a_module():
    stack = make_causal_transforms(seed=0)
    head = TensorDictModule(torch.nn.Linear(9, 8), in_keys=["causal_features"], out_keys=["q"])
    policy = torch.nn.Sequential(stack, head)
    out = policy(frame_td((4,)))
    assert out["q"].shape == (4, 8)


def test_stack_inside_a_replay_buffer():
    rb = ReplayBuffer(storage=LazyTensorStorage(16), transform=make_causal_transforms(seed=0))
    data = frame_td((10,), depth=0.2, altitude=0.1)
    rb.extend(data)
    sample = rb.sample(4)
    assert sample["causal_state"].shape == (4, 9)
    assert (sample["causal_state"][:, :5] == 0).all() and (sample["causal_state"][:, 8] == 0).all()
    # the buffer stores raw frames; the transform runs when data is read
    assert "causal_state" not in rb.storage[0:10].keys()


def test_make_causal_transforms_with_goal_meter_and_errors():
    meter = GoalMeter(SimGoalDetector(min_pixels=4), hfov_deg=90.0)
    stack = make_causal_transforms(goal_meter=meter, seed=0)
    assert isinstance(stack[0], GoalFeatures)
    td = frame_td((2,), depth=2.0)
    td["goal_box"] = torch.tensor([[32.0, 32.0, 52.0, 52.0], [0, 0, 0, 0]])
    td["goal_pixels"] = torch.tensor([[400.0], [0.0]])
    out = stack(td)
    assert out["causal_state"][:, 5:8].tolist() == [[1, 1, 0], [0, 2, 0]]
    with pytest.raises(ValueError, match="goal_meter"):
        make_causal_transforms(goal_meter="yolo")
    with pytest.raises(ValueError, match="n_points"):
        make_causal_transforms(n_points=3)
