"""Discretize for any VariableSchema.

* The default schema reproduces, bit for bit, the hard-coded nine-variable
  ``Discretize`` it replaced (frozen below as ``_ReferenceDiscretize``) on
  thousands of random inputs with NaN / inf, several thresholds and batch shapes.
* A custom 3-variable schema on torchrl's ``GymEnv("CartPole-v1")`` (three
  variables read from elements of one ``observation`` vector): standalone on a
  TensorDict, in a ``Compose`` inside a ``TransformedEnv`` (``check_env_specs``),
  inside and outside a ``ParallelEnv`` of 2 workers, and with a
  ``TensorDictReplayBuffer`` (stored codes and as the buffer's transform).
* Schema rules of their own (validity flag, missing category, code inputs,
  nested keys) and every bad-input error.
"""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import (
    Composite,
    LazyTensorStorage,
    MultiCategorical,
    TensorDictReplayBuffer,
    Unbounded,
)
from torchrl.envs import Compose, ParallelEnv, StepCounter, TransformedEnv
from torchrl.envs.transforms import Transform
from torchrl.envs.utils import check_env_specs

from torchrl_causal.schema import DEFAULT_SCHEMA, Variable, VariableSchema, thesis_schema
from torchrl_causal.transforms import Discretize, Thresholds, make_causal_transforms

NAN, INF = float("nan"), float("inf")


# ----------------------------------------------------------------------------------------
# Frozen copy of Discretize before schemas carried their rules (commit 4c335cd). Do not
# edit: it is the reference the default schema must reproduce bit for bit.
class _ReferenceDiscretize(Transform):
    """The nine thesis variables, hard-coded (the pre-schema implementation)."""

    def __init__(
        self,
        thresholds: Thresholds | None = None,
        *,
        max_depth: float = 10.0,
        depth_key="depth_sections",
        in_sight_key="goal_in_sight",
        distance_key="goal_distance",
        angle_key="goal_angle",
        altitude_key="altitude",
        features_key="causal_features",
        state_key="causal_state",
    ):
        if thresholds is None:
            thresholds = Thresholds()
        if not isinstance(thresholds, Thresholds):
            raise ValueError(f"thresholds must be a Thresholds instance, got {thresholds!r}")
        if not (math.isfinite(max_depth) and max_depth > 0):
            raise ValueError(f"max_depth must be a positive finite number, got {max_depth!r}")
        super().__init__(
            in_keys=[depth_key, in_sight_key, distance_key, angle_key, altitude_key],
            out_keys=[features_key, state_key],
        )
        self.thresholds = thresholds
        self.max_depth = float(max_depth)
        self.schema = DEFAULT_SCHEMA
        self._const: dict = {}

    def _constants(self, device):
        const = self._const.get(device)
        if const is None:
            th, md, big = self.thresholds, self.max_depth, 1e30
            inf = float("inf")
            # columns: [depth x5, in_sight, distance, angle, altitude]
            lo = [0.0] * 5 + [0.0, 0.0, -90.0, -big]
            hi = [md] * 5 + [1.0, md, 90.0, big]
            nan_fill = [md] * 5 + [0.0, md, 0.0, 0.0]
            keep_unseen = [True] * 5 + [False, False, False, True]
            # code = sum_k weight_k * (x > edge_k) + bias
            edges = [[th.depth_close, inf]] * 5 + [
                [0.5, inf],
                [th.goal_close, inf],
                [th.angle_good, -th.angle_good],
                [th.altitude_low, th.altitude_high],
            ]
            # ">= e" is "> nextafter(e, -inf)", taken in float32 (the features' dtype)
            strict = [[False, False]] * 7 + [[False, True], [True, False]]
            weights = [[1, 1]] * 7 + [[1, -2], [1, 1]]  # angle: (x > a) + 2 * (x < -a)
            bias_seen = [0] * 7 + [2, 0]
            bias_unseen = [0] * 6 + [2, 2, 0]  # distance -> not_visible
            f32 = dict(dtype=torch.float32, device=device)
            i64 = dict(dtype=torch.int64, device=device)
            const = self._const[device] = (
                torch.tensor(lo, **f32),
                torch.tensor(hi, **f32),
                torch.tensor(nan_fill, **f32),
                torch.tensor(keep_unseen, dtype=torch.bool, device=device),
                torch.where(
                    torch.tensor(strict, device=device),
                    torch.nextafter(torch.tensor(edges, **f32), torch.tensor(-inf, **f32)),
                    torch.tensor(edges, **f32),
                ),
                torch.tensor(weights, **i64),
                torch.tensor(bias_seen, **i64),
                torch.tensor(bias_unseen, **i64),
            )
        return const

    def discretize(self, depth, in_sight, distance, angle, altitude):
        """Tensors in (shapes ``[..., 5]`` and ``[..., 1]``) -> ``(features, codes)`` ``[..., 9]``."""
        batch = depth.shape[:-1]
        lo, hi, nan_fill, keep_unseen, edges, weights, bias_seen, bias_unseen = self._constants(
            depth.device
        )
        if in_sight.dtype != torch.bool:
            in_sight = in_sight > 0.5
        col = (*batch, 1)
        if in_sight.shape != col:
            in_sight = in_sight.reshape(col)
        cols = [depth, in_sight.to(torch.float32)]
        for v in (distance, angle, altitude):
            cols.append(v if v.shape == col else v.reshape(col))
        x = torch.cat(cols, -1)  # promotes to float32 (or float64 inputs' dtype)
        if x.dtype != torch.float32:
            x = x.to(torch.float32)
        x = torch.where(x == x, x, nan_fill).clamp(lo, hi)  # x != x only for NaN
        features = x * (in_sight | keep_unseen)
        codes = ((features.unsqueeze(-1) > edges) * weights).sum(-1) + torch.where(
            in_sight, bias_seen, bias_unseen
        )
        return features, codes

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        features, codes = self.discretize(*(next_tensordict.get(k) for k in self.in_keys))
        next_tensordict.set(self.out_keys[0], features)
        next_tensordict.set(self.out_keys[1], codes)
        return next_tensordict

    forward = _call

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase):
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        shape = (*observation_spec.shape, len(self.schema))
        device = observation_spec.device
        observation_spec[self.out_keys[0]] = Unbounded(
            shape=shape, dtype=torch.float32, device=device
        )
        observation_spec[self.out_keys[1]] = MultiCategorical(
            nvec=list(self.schema.cardinalities), shape=shape, dtype=torch.int64, device=device
        )
        return observation_spec


# ----------------------------------------------------------------------------------------
# 1. the default schema reproduces the reference bit for bit
SPECIAL = torch.tensor([NAN, INF, -INF, 0.0, -0.0, 1e30, -1e30, 3.4e38, -3.4e38, 1e-30])


def _wild(g, shape, scale, edges, dtype=torch.float32):
    """Uniform values, values on an edge or one float32 ulp beside it, and specials."""
    n = math.prod(shape)
    uniform = (torch.rand(n, generator=g) * 2 - 1) * scale
    wide = (torch.rand(n, generator=g) * 2 - 1) * 1e4
    e = torch.tensor(edges, dtype=torch.float32)[torch.randint(0, len(edges), (n,), generator=g)]
    side = torch.randint(-1, 2, (n,), generator=g)
    near = torch.where(side > 0, torch.nextafter(e, torch.tensor(INF)), e)
    near = torch.where(side < 0, torch.nextafter(e, torch.tensor(-INF)), near)
    special = SPECIAL[torch.randint(0, len(SPECIAL), (n,), generator=g)]
    kind = torch.randint(0, 10, (n,), generator=g)
    out = torch.where(kind < 4, uniform, torch.where(kind < 7, near, torch.where(kind < 8, wide, special)))
    return out.reshape(shape).to(dtype)


def _frames(g, batch, th, md, *, flag="bool", dtype=torch.float32):
    b = tuple(batch)
    if flag == "bool":
        in_sight = torch.rand((*b, 1), generator=g) < 0.6
    else:  # a number: in sight when > 0.5, NaN is not
        in_sight = _wild(g, (*b, 1), 1.5, [0.5, 0.0, 1.0])
    return TensorDict(
        {
            "depth_sections": _wild(g, (*b, 5), md * 1.2, [th.depth_close, md, 0.0], dtype),
            "goal_in_sight": in_sight,
            "goal_distance": _wild(g, (*b, 1), md * 1.2, [th.goal_close, md, 0.0], dtype),
            "goal_angle": _wild(g, (*b, 1), 120.0, [th.angle_good, -th.angle_good, 90.0, -90.0], dtype),
            "altitude": _wild(g, (*b, 1), 3.0, [th.altitude_low, th.altitude_high, 0.0], dtype),
        },
        list(b),
    )


def _assert_bit_exact(out, ref):
    assert out["causal_state"].dtype == ref["causal_state"].dtype == torch.int64
    assert torch.equal(out["causal_state"], ref["causal_state"])
    f, r = out["causal_features"], ref["causal_features"]
    assert f.dtype == r.dtype == torch.float32 and f.shape == r.shape
    assert torch.equal(f.view(torch.int32), r.view(torch.int32))  # bits, -0.0 included


THRESHOLDS = [
    Thresholds(),
    Thresholds(depth_close=0.8, goal_close=1.3, angle_good=25.0, altitude_low=0.3, altitude_high=2.2),
    Thresholds(depth_close=0.1, goal_close=0.7, angle_good=0.3, altitude_low=0.0, altitude_high=0.1),
]


@pytest.mark.parametrize("th", THRESHOLDS, ids=["thesis", "wide", "tiny"])
@pytest.mark.parametrize("md", [None, 6.5])
def test_default_schema_reproduces_the_reference_bit_for_bit(th, md):
    g = torch.Generator().manual_seed(hash((th, md)) % 2**31)
    kw = {} if md is None else {"max_depth": md}
    new = Discretize(th, **kw) if th != Thresholds() or kw else Discretize()
    ref = _ReferenceDiscretize(th, **kw)
    assert new.in_keys == ref.in_keys and new.out_keys == ref.out_keys
    assert new.schema == DEFAULT_SCHEMA and new.max_depth == ref.max_depth
    n = 0
    for batch, flag, dtype in [
        ((), "bool", torch.float32),
        ((7,), "number", torch.float32),
        ((4, 50), "bool", torch.float32),
        ((1500,), "number", torch.float32),
        ((1500,), "bool", torch.float64),
    ]:
        td = _frames(g, batch, th, ref.max_depth, flag=flag, dtype=dtype)
        _assert_bit_exact(new(td.clone()), ref(td.clone()))
        # the positional discretize() of the old API too
        args = [td[k] for k in ref.in_keys]
        for a, b in zip(new.discretize(*args), ref.discretize(*args)):
            assert torch.equal(a, b)
        n += td.numel()
    assert n > 3000


def test_default_schema_is_the_thesis_rules_and_thresholds_build_it():
    assert Discretize().schema == DEFAULT_SCHEMA == thesis_schema()
    # the rule fields do not take part in equality: other thresholds, same variables
    wide = Thresholds(depth_close=0.8, angle_good=25.0)
    assert Discretize(wide).schema == DEFAULT_SCHEMA
    assert Discretize(wide).schema["goal_angle"].bins == (-25.0, 25.0)
    assert wide.to_schema(6.0)["depth_center"].clip == (0.0, 6.0)
    assert thesis_schema(depth_close=0.8, max_depth=6.0)["depth_top_left"].nan_as == 6.0
    # the same transform from the schema itself
    g = torch.Generator().manual_seed(3)
    td = _frames(g, (500,), wide, 6.0)
    _assert_bit_exact(
        Discretize(schema=wide.to_schema(6.0))(td.clone()),
        _ReferenceDiscretize(wide, max_depth=6.0)(td.clone()),
    )
    assert [v.categories for v in Discretize().schema][6:] == [
        ("close", "far", "not_visible"),
        ("good", "far_left", "far_right"),
        ("close_ground", "good", "far_ground"),
    ]


def test_legacy_key_options_and_spec_match_the_reference():
    keys = dict(depth_key="ds", in_sight_key=("goal", "seen"), altitude_key="height",
                features_key="f", state_key="s")
    new, ref = Discretize(**keys), _ReferenceDiscretize(**keys)
    assert new.in_keys == ref.in_keys == ["ds", ("goal", "seen"), "goal_distance", "goal_angle", "height"]
    td = _frames(torch.Generator().manual_seed(5), (64,), Thresholds(), 10.0)
    td.rename_key_("depth_sections", "ds").rename_key_("altitude", "height")
    td["goal", "seen"] = td.pop("goal_in_sight")
    a, b = new(td.clone()), ref(td.clone())
    assert torch.equal(a["s"], b["s"]) and torch.equal(a["f"], b["f"])
    spec = Composite(ds=Unbounded(shape=(3, 2, 5)), shape=(3, 2))
    assert new.transform_observation_spec(spec.clone()) == ref.transform_observation_spec(spec.clone())
    # make_causal_transforms builds its Discretize from the default schema
    assert make_causal_transforms(seed=0)[-1].schema == DEFAULT_SCHEMA


# ----------------------------------------------------------------------------------------
# 2. a custom schema on CartPole
gymnasium = pytest.importorskip("gymnasium")
from torchrl.envs.libs.gym import GymEnv  # noqa: E402

CART = VariableSchema(
    (
        Variable("cart_position", ("left", "centre", "right"), "cart x (m)",
                 bins=(-0.5, 0.5), source="observation", index=0, clip=(-2.4, 2.4)),
        Variable("cart_velocity", ("to_left", "to_right"), "cart x velocity (m/s)",
                 bins=(0.0,), on_edge="above", source="observation", index=1),
        Variable("pole_angle", ("upright", "left", "right"), "pole angle (rad)",
                 bins=(-0.02, 0.02), on_edge=("above", "below"),
                 codes=("left", "upright", "right"), source="observation", index=2),
    )
)


def cart_codes(obs: torch.Tensor) -> torch.Tensor:
    """CART's rules written out by hand (float32 comparisons)."""
    x, v, a = obs[..., 0].clamp(-2.4, 2.4), obs[..., 1], obs[..., 2]
    pos = (x > -0.5).long() + (x > 0.5).long()
    vel = (v >= 0.0).long()
    angle = torch.tensor([1, 0, 2])[(a >= -0.02).long() + (a > 0.02).long()]
    return torch.stack([pos, vel, angle], -1)


def make_cartpole(seed: int = 0):
    env = TransformedEnv(
        GymEnv("CartPole-v1"),
        Compose(StepCounter(), Discretize(schema=CART, state_key="cart_state",
                                          features_key="cart_features")),
    )
    env.set_seed(seed)
    return env


def test_custom_schema_standalone_on_a_tensordict():
    obs = torch.tensor(
        [
            [-0.6, -1.0, -0.03, 0.0],
            [-0.5, 0.0, -0.02, 0.0],
            [0.5, 2.0, 0.02, 0.0],
            [9.0, NAN, 0.5, 0.0],
            [NAN, -INF, NAN, 0.0],
        ]
    )
    t = Discretize(schema=CART)
    assert t.in_keys == ["observation"]
    out = t(TensorDict(observation=obs, batch_size=[5]))
    assert out["causal_state"].tolist() == [[0, 0, 1], [0, 1, 0], [1, 1, 0], [2, 1, 2], [1, 0, 0]]
    assert out["causal_features"][3].tolist() == pytest.approx([2.4, 0.0, 0.5])
    assert torch.isfinite(out["causal_features"]).all()
    assert torch.equal(out["causal_state"][:3], cart_codes(obs[:3]))
    labels = [t.schema[n].categories[c] for n, c in zip(CART.names, out["causal_state"][0])]
    assert labels == ["left", "to_left", "left"]
    # batch dims [2, 3] and []
    many = torch.randn(2, 3, 4) * 0.5
    out = t(TensorDict(observation=many, batch_size=[2, 3]))
    assert out["causal_state"].shape == (2, 3, 3)
    assert torch.equal(out["causal_state"], cart_codes(many))
    assert t(TensorDict(observation=many[0, 0], batch_size=[]))["causal_state"].shape == (3,)


def test_custom_schema_in_compose_in_a_transformed_env():
    env = make_cartpole()
    try:
        check_env_specs(env)
        spec = env.observation_spec["cart_state"]
        assert isinstance(spec, MultiCategorical) and spec.dtype == torch.int64
        assert spec.nvec.tolist() == [3, 2, 3] and spec.shape == (3,)
        assert env.observation_spec["cart_features"].dtype == torch.float32
        # push right for 5 steps, then left for 5, and so on: the cart moves both ways,
        # whatever the global RNG state is (a random rollout once saw one sign only)
        step = iter(range(10**6))

        def sway(td):
            right = (next(step) // 5) % 2 == 0
            return td.set("action", torch.tensor([0, 1] if right else [1, 0]))

        roll = env.rollout(30, sway, break_when_any_done=False)
        for td in (roll, roll["next"]):
            assert spec.is_in(td["cart_state"])
            assert torch.equal(td["cart_state"], cart_codes(td["observation"]))
        assert roll["next", "cart_state"][:, 1].unique().numel() == 2  # both velocities seen
    finally:
        env.close()


def test_custom_schema_inside_and_outside_a_parallel_env():
    base = ParallelEnv(2, make_cartpole, create_env_kwargs=[{"seed": 0}, {"seed": 1}],
                       mp_start_method="fork")
    # the same schema again, outside the workers, under other keys
    env = TransformedEnv(base, Discretize(schema=CART))
    try:
        check_env_specs(env)
        assert env.observation_spec["causal_state"].shape == (2, 3)
        roll = env.rollout(5, break_when_any_done=False)
        assert roll["next", "cart_state"].shape == (2, 5, 3)
        assert torch.equal(roll["next", "cart_state"], roll["next", "causal_state"])
        assert torch.equal(roll["next", "cart_state"], cart_codes(roll["next", "observation"]))
        assert env.observation_spec["causal_state"].is_in(roll["next", "causal_state"][:, 0])
    finally:
        env.close()


def test_custom_schema_with_a_replay_buffer():
    env = make_cartpole()
    try:
        roll = env.rollout(20, break_when_any_done=False)
    finally:
        env.close()
    # codes survive storage: dtype, values, spec
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(64), batch_size=8)
    rb.extend(roll)
    stored = rb[:]
    assert stored["cart_state"].dtype == torch.int64
    assert torch.equal(stored["cart_state"], roll["cart_state"])
    sample = rb.sample()
    assert torch.equal(sample["next", "cart_state"], cart_codes(sample["next", "observation"]))
    assert MultiCategorical(nvec=[3, 2, 3], shape=(8, 3), dtype=torch.int64).is_in(sample["cart_state"])
    # as the buffer's transform: raw observations stored, codes computed on read
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(64), batch_size=8,
                                transform=Discretize(schema=CART))
    rb.extend(roll.select("observation", ("next", "observation")))
    assert "causal_state" not in rb.storage[0:20].keys()
    out = rb[:]
    assert torch.equal(out["causal_state"], roll["cart_state"])
    assert out["causal_state"].dtype == torch.int64


# ----------------------------------------------------------------------------------------
# 3. rules of one's own: validity flag, missing category, code inputs, nested keys
ROBOT = VariableSchema(
    (
        Variable("door", ("closed", "open")),  # a bool flag, no bins
        Variable("mode", ("idle", "walk", "run")),  # an integer code, no bins
        Variable("target", ("near", "far", "unseen"), bins=(1.0,), source=("sensors", "target"),
                 clip=(0.0, 5.0), nan_as=5.0, valid=("sensors", "target_seen"), missing="unseen"),
        Variable("battery", ("low", "ok", "full"), bins=(20.0, 90.0), on_edge="above",
                 source="battery_pct"),
    )
)


def test_validity_flag_missing_category_codes_and_nested_keys():
    t = Discretize(schema=ROBOT)
    assert t.in_keys == ["door", "mode", ("sensors", "target"), ("sensors", "target_seen"),
                         "battery_pct"]
    td = TensorDict(
        {
            "door": torch.tensor([[True], [False], [True], [False]]),
            "mode": torch.tensor([[0], [2], [7], [-1]]),
            "sensors": {
                "target": torch.tensor([[1.0], [0.5], [NAN], [3.0]]),
                "target_seen": torch.tensor([[1.0], [0.0], [0.9], [NAN]]),
            },
            "battery_pct": torch.tensor([[20.0], [19.9], [90.0], [90.1]]),
        },
        [4],
    )
    out = t(td)
    assert out["causal_state"].tolist() == [[1, 0, 0, 1], [0, 2, 2, 0], [1, 2, 1, 2], [0, 0, 2, 2]]
    assert out["causal_features"][:, 2].tolist() == [1.0, 0.0, 5.0, 0.0]  # 0 where unseen
    assert out["causal_features"][:, :2].tolist() == [[1, 0], [0, 2], [1, 2], [0, 0]]
    # a float input to a code variable is rounded (halves down) and clipped; NaN -> nan_as
    td["mode"] = torch.tensor([[0.5], [0.51], [1.7], [NAN]])
    out = t(td)
    assert out["causal_state"][:, 1].tolist() == [0, 1, 2, 0]
    assert out["causal_features"][:, 1].tolist() == [0.0, 1.0, 2.0, 0.0]
    spec = t.transform_observation_spec(Composite(shape=(4,)))
    assert spec["causal_state"].nvec[0].tolist() == [2, 3, 3, 3]
    assert spec["causal_state"].is_in(out["causal_state"])


def test_schema_replace_changes_one_rule():
    # resolved codes / edge sides are not fields: another number of bins just works
    three = DEFAULT_SCHEMA.replace("depth_center", labels=("close", "mid", "far"), bins=(0.5, 2.0))
    assert three["depth_center"].bin_codes == (0, 1, 2) and three.cardinalities[0] == 3
    assert DEFAULT_SCHEMA["goal_angle"].bin_codes == (2, 0, 1)
    assert DEFAULT_SCHEMA["altitude"].edge_sides == ("above", "below")
    s = DEFAULT_SCHEMA.replace("altitude", bins=(0.3, 2.0), source="height")
    t = Discretize(schema=s)
    assert t.in_keys[-1] == "height" and s == DEFAULT_SCHEMA
    td = _frames(torch.Generator().manual_seed(1), (8,), Thresholds(), 10.0)
    td["height"] = torch.tensor([0.29, 0.3, 1.0, 2.0, 2.01, NAN, INF, -INF]).unsqueeze(-1)
    assert t(td)["causal_state"][:, -1].tolist() == [0, 1, 1, 1, 2, 0, 2, 0]


# ----------------------------------------------------------------------------------------
# 4. bad input: clear errors naming the variable
@pytest.mark.parametrize(
    "kw,match",
    [
        (dict(bins=(1.0, 0.5)), r"'v'.*bins \(1.0, 0.5\) must be strictly increasing"),
        (dict(bins=(0.5, 0.5)), r"'v'.*strictly increasing"),
        (dict(bins=(0.0, INF)), r"'v'.*finite"),
        (dict(bins=(NAN, 1.0)), r"'v'.*finite"),
        (dict(bins=(0.1, 0.1 + 1e-12)), r"'v'.*strictly increasing in float32"),
        (dict(bins=(0.0, 1e39)), r"'v'.*finite \(float32\)"),
        (dict(bins=()), r"'v'.*at least one edge"),
        (dict(bins="0.5"), r"'v'.*finite"),
        (dict(bins=(0.5,)), r"'v': 3 categories \('a', 'b', 'c'\) do not match bins \(0.5,\)"),
        (dict(bins=(1.0, 2.0, 3.0)), r"'v': 3 categories .* make 4 bins"),
        (dict(bins=(1.0, 2.0), codes=(0, 0, 1)), r"'v': codes \(0, 0, 1\) must give each"),
        (dict(bins=(1.0, 2.0), codes=(0, 1)), r"'v': codes .* each exactly once"),
        (dict(bins=(1.0, 2.0), codes=(0, 1, 3)), r"'v': codes"),
        (dict(bins=(1.0, 2.0), codes=("a", "b", "z")), r"'v': codes"),
        (dict(bins=(1.0,), codes=(0, 2), valid="ok", missing="c"), r"'v': codes .* \('a', 'b'\)"),
        (dict(bins=(1.0, 2.0), codes=2), r"'v': codes 2 must give"),
        (dict(bins=(1.0, 2.0), on_edge=1), r"'v': on_edge"),
        (dict(bins=(1.0, 2.0), on_edge="left"), r"'v': on_edge"),
        (dict(bins=(1.0, 2.0), on_edge=("above",)), r"'v': on_edge"),
        (dict(bins=(1.0, 2.0), clip=(3.0, 1.0)), r"'v': clip"),
        (dict(bins=(1.0, 2.0), clip=(0.0, INF)), r"'v': clip"),
        (dict(clip=(0.0, 1.0)), r"'v': clip=.*needs bins"),
        (dict(codes=(0, 1, 2)), r"'v': codes=.*needs bins"),
        (dict(valid="ok"), r"'v': valid and missing go together"),
        (dict(missing="a"), r"'v': valid and missing go together"),
        (dict(valid="ok", missing="nope"), r"'v': missing='nope' is not one of"),
        (dict(source=3), r"'v': source must be a key"),
        (dict(index=-1), r"'v': index"),
        (dict(nan_as=NAN), r"'v': nan_as"),
    ],
)
def test_bad_rules_are_rejected_naming_the_variable(kw, match):
    with pytest.raises(ValueError, match=match):
        Variable("v", ("a", "b", "c"), **kw)


def test_bad_schema_and_transform_options():
    with pytest.raises(ValueError, match="duplicate labels"):
        Variable("v", ("a", "a"))
    with pytest.raises(ValueError, match="Variable instances"):
        VariableSchema(("v",))
    with pytest.raises(ValueError, match=r"thresholds must be a Thresholds.*schema=\.\.\."):
        Discretize(CART)
    with pytest.raises(ValueError, match="thresholds and max_depth build the default schema"):
        Discretize(Thresholds(), schema=CART)
    with pytest.raises(ValueError, match="thresholds and max_depth build the default schema"):
        Discretize(schema=DEFAULT_SCHEMA, max_depth=6.0)
    with pytest.raises(ValueError, match="schema must be a VariableSchema"):
        Discretize(schema=[Variable("a", ("x", "y"))])
    with pytest.raises(ValueError, match="max_depth"):
        Discretize(max_depth=-1.0)
    with pytest.raises(ValueError, match="altitude_key='height' replaces the key 'altitude'"):
        Discretize(schema=CART, altitude_key="height")
    # thresholds that cannot make sorted bins are named by the schema too
    with pytest.raises(ValueError, match="'goal_angle'.*strictly increasing"):
        thesis_schema(angle_good=-1.0)


def test_missing_input_key_and_bad_shapes_are_named():
    t = Discretize(schema=ROBOT)
    td = TensorDict(door=torch.ones(2, 1, dtype=torch.bool), mode=torch.zeros(2, 1), batch_size=[2])
    with pytest.raises(KeyError, match=r"no key \('sensors', 'target'\), read by variable\(s\) \['target'\]"):
        t(td)
    with pytest.raises(KeyError, match=r"'observation', read by variable\(s\) \['cart_position', 'cart_velocity', 'pole_angle'\]"):
        Discretize(schema=CART)(td)
    with pytest.raises(KeyError, match="'altitude'"):
        Discretize()(_frames(torch.Generator().manual_seed(0), (2,), Thresholds(), 10.0).exclude("altitude"))
    short = TensorDict(observation=torch.zeros(4, 2), batch_size=[4])
    with pytest.raises(ValueError, match=r"variable\(s\) \('cart_position', 'cart_velocity', 'pole_angle'\).*got shape \[4, 2\]"):
        Discretize(schema=CART)(short)
    td = TensorDict(observation=torch.zeros(4, 3), other=torch.zeros(3, 1), batch_size=[])
    two = VariableSchema((Variable("a", ("x", "y"), bins=(0.0,), source="observation"),
                          Variable("b", ("x", "y"), bins=(0.0,), source="other")))
    with pytest.raises(ValueError, match=r"variable\(s\) \('b',\).*batch \[4\].*got shape \[3, 1\]"):
        Discretize(schema=two)(td)
