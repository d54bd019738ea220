"""Structure learning: the fast backend reproduces pgmpy's HillClimbSearch + BIC."""

import itertools

import numpy as np
import pandas as pd
import pytest

from torchrl_causal.causal.inference import fit_cbn
from torchrl_causal.causal.structure import BICScore, allowed_edges, learn_structure, time_tiers
from torchrl_causal.schema import DEFAULT_SCHEMA

NODES = DEFAULT_SCHEMA.node_names()
CARDS = DEFAULT_SCHEMA.node_cardinalities()

TRUE_EDGES = [
    ("depth_center_t", "depth_center_t1"),
    ("depth_top_left_t", "depth_center_t1"),
    ("goal_in_sight_t", "goal_in_sight_t1"),
    ("goal_angle_t", "goal_in_sight_t1"),
    ("altitude_t", "altitude_t1"),
    ("goal_distance_t", "goal_distance_t1"),
    ("goal_angle_t", "goal_angle_t1"),
    ("goal_in_sight_t1", "reward"),
    ("goal_angle_t1", "reward"),
    ("depth_center_t", "reward"),
]


def noisy_max_cbn(edges, noise=0.2):
    """A known network: child = min(card - 1, sum of parent codes), replaced by noise w.p. ``noise``."""
    cbn = fit_cbn(edges, np.zeros((0, len(NODES)), np.int64))
    for v, pa in cbn.parents.items():
        if not pa:
            continue
        r = CARDS[v]
        cfgs = list(itertools.product(*[range(CARDS[p]) for p in pa]))
        cpt = np.full((r, len(cfgs)), noise / r)
        for j, cfg in enumerate(cfgs):
            cpt[min(r - 1, sum(cfg)), j] += 1 - noise
        cbn.cpts[v] = cpt
    return cbn


def random_transitions(n, seed, synchronous_dependence=False):
    """Loosely structured transitions with a noisy reward (no known ground truth)."""
    rng = np.random.default_rng(seed)
    cards = np.array(DEFAULT_SCHEMA.cardinalities)
    s0 = (rng.random((n, 9)) * cards).astype(np.int64)
    s1 = np.where(rng.random((n, 9)) < 0.6, s0, (rng.random((n, 9)) * cards).astype(np.int64))
    if synchronous_dependence:  # a same-slice link the "delete_after" search can pick
        s1[:, 6] = np.where(rng.random(n) < 0.8, np.minimum(s1[:, 5] * 2, 2), s1[:, 6])
    reward = ((s1[:, 5] == 1) ^ (rng.random(n) < 0.15)) | ((s0[:, 0] == 1) & (rng.random(n) < 0.3))
    return np.concatenate([s0, s1, reward[:, None]], 1)


@pytest.mark.parametrize(
    "seed,kwargs",
    [
        (0, {}),
        (1, {"cardinality": "observed"}),
        (2, {"synchronous": "delete_after"}),
        (3, {"max_indegree": 1}),
    ],
)
def test_fast_equals_pgmpy(seed, kwargs):
    data = random_transitions(1500, seed, synchronous_dependence=kwargs.get("synchronous") == "delete_after")
    fast = learn_structure(data, backend="fast", **kwargs)
    ref = learn_structure(data, backend="pgmpy", **kwargs)
    assert fast.score == pytest.approx(ref.score, abs=1e-6)
    assert set(fast.edges) == set(ref.edges)
    assert set(fast.deleted_edges) == set(ref.deleted_edges)
    assert len(fast.edges) > 0
    if kwargs.get("synchronous") == "delete_after":
        assert fast.deleted_edges, "the same-slice dependence should be found, then deleted"
    if "max_indegree" in kwargs:
        targets = [v for _, v in fast.edges]
        assert max(targets.count(v) for v in set(targets)) <= 1


def test_warm_start_equals_pgmpy_and_drops_forbidden_edges():
    data = random_transitions(1500, 4)
    start = [("goal_in_sight_t1", "reward"), ("altitude_t", "goal_angle_t1"),
             ("reward", "altitude_t1"),  # against the time order: dropped
             ("depth_center_t1", "depth_top_left_t1")]  # synchronous: dropped under "forbid"
    fast = learn_structure(data, backend="fast", start_dag=start)
    ref = learn_structure(data, backend="pgmpy", start_dag=start)
    assert fast.score == pytest.approx(ref.score, abs=1e-6)
    assert set(fast.edges) == set(ref.edges)
    assert ("reward", "altitude_t1") not in fast.edges
    assert ("depth_center_t1", "depth_top_left_t1") not in fast.edges
    # warm start from the learned DAG: already a local optimum, no move
    again = learn_structure(data, backend="fast", start_dag=fast.edges)
    assert set(again.edges) == set(fast.edges) and again.n_moves == 0


def test_both_backends_recover_a_known_network():
    # Speed (the >= 20x target) is measured by benchmarks/causal_learning.py, not here.
    truth = noisy_max_cbn(TRUE_EDGES)
    for seed in range(3):
        data = truth.sample(20000, seed=seed)
        assert set(learn_structure(data, backend="fast").edges) == set(TRUE_EDGES)
    data = truth.sample(4000, seed=0)
    fast = learn_structure(data, backend="fast")
    ref = learn_structure(data, backend="pgmpy")
    assert set(ref.edges) == set(fast.edges) == set(TRUE_EDGES)
    assert fast.score == pytest.approx(ref.score, abs=1e-6)


def test_bic_local_scores_equal_pgmpy():
    from pgmpy.structure_score import BIC

    data = random_transitions(800, 5)
    df = pd.DataFrame(data, columns=NODES)
    state_names = {n: list(range(c)) for n, c in CARDS.items()}
    ref = BIC(df, state_names=state_names)
    ref_obs = BIC(df)
    cards = [CARDS[n] for n in NODES]
    ours = BICScore(data, cards, cards)
    obs_cards = [len(np.unique(data[:, j])) for j in range(data.shape[1])]
    ours_obs = BICScore(data, cards, obs_cards)
    rng = np.random.default_rng(0)
    for _ in range(15):
        child = int(rng.integers(9, 19))
        parents = tuple(int(p) for p in rng.choice(9, size=int(rng.integers(0, 4)), replace=False))
        names = tuple(NODES[p] for p in parents)
        assert ours.local(child, parents) == pytest.approx(ref.local_score(NODES[child], names), abs=1e-8)
        assert ours_obs.local(child, parents) == pytest.approx(ref_obs.local_score(NODES[child], names), abs=1e-8)


def test_constraints_and_degenerate_data():
    allowed = allowed_edges(DEFAULT_SCHEMA, "forbid")
    tiers = {n: i for i, tier in enumerate(time_tiers()) for n in tier}
    for i, u in enumerate(NODES):
        for j, v in enumerate(NODES):
            assert allowed[i, j] == (tiers[u] < tiers[v])
    # constant columns, a single row: no crash, no edge into a constant column
    data = np.zeros((50, 19), np.int64)
    data[:25, 0] = 1
    data[:25, 9] = 1
    res = learn_structure(data)
    assert res.edges == [("depth_center_t", "depth_center_t1")]
    assert learn_structure(data[:1]).edges == []


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"backend": "torch"}, "backend"),
        ({"synchronous": "keep"}, "synchronous"),
        ({"cardinality": "max"}, "cardinality"),
        ({"max_indegree": -1}, "max_indegree"),
        ({"start_dag": [("nope", "reward")]}, "start_dag"),
    ],
)
def test_bad_options_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        learn_structure(np.zeros((10, 19), np.int64), **kwargs)
    with pytest.raises(ValueError, match="shape"):
        learn_structure(np.zeros((10, 18), np.int64))


@pytest.mark.parametrize("backend", ["fast", "pgmpy"])
def test_cyclic_start_dag_raises_on_both_backends(backend):
    cycle = [("depth_center_t1", "goal_in_sight_t1"), ("goal_in_sight_t1", "depth_center_t1")]
    with pytest.raises(ValueError, match="start_dag is not acyclic"):
        learn_structure(np.zeros((10, 19), np.int64), backend=backend, start_dag=cycle,
                        synchronous="delete_after")
