"""Compiled reward inference equals pgmpy's VariableElimination; CPTs equal pgmpy's estimator."""

import numpy as np
import pandas as pd
import pytest
import torch

from torchrl_causal.causal import (
    CBN,
    RewardTables,
    compile_tables,
    fit_cbn,
    learn_structure,
    markov_blanket,
)
from torchrl_causal.causal.inference import random_cbn
from torchrl_causal.schema import DEFAULT_SCHEMA

NODES = DEFAULT_SCHEMA.node_names()
STATE_NAMES = {n: list(range(c)) for n, c in DEFAULT_SCHEMA.node_cardinalities().items()}

# a generating network where the reward depends on t+1 nodes with several t parents and on t nodes
GEN_EDGES = [
    ("goal_in_sight_t", "goal_in_sight_t1"),
    ("goal_angle_t", "goal_in_sight_t1"),
    ("goal_distance_t", "goal_distance_t1"),
    ("goal_in_sight_t", "goal_distance_t1"),
    ("altitude_t", "altitude_t1"),
    ("depth_center_t", "depth_center_t1"),
    ("goal_in_sight_t1", "reward"),
    ("goal_distance_t1", "reward"),
    ("depth_center_t", "reward"),
]


def pgmpy_model(edges, data, prior):
    from pgmpy.models import DiscreteBayesianNetwork
    from pgmpy.parameter_estimator import DiscreteBayesianEstimator

    model = DiscreteBayesianNetwork()
    model.add_nodes_from(NODES)
    model.add_edges_from(edges)
    est = DiscreteBayesianEstimator(state_names=STATE_NAMES, prior_type="dirichlet", pseudo_counts=prior)
    model.fit(pd.DataFrame(data.astype(np.int64), columns=NODES), estimator=est)
    return model


@pytest.mark.parametrize("seed,backend", [(0, "fast"), (1, "pgmpy")])
def test_compiled_table_equals_variable_elimination_on_every_state(seed, backend):
    from pgmpy.inference import VariableElimination

    data = random_cbn(GEN_EDGES, seed=seed, concentration=0.4).sample(3000, seed=seed)
    learned = learn_structure(data, backend=backend).edges
    assert any(u.endswith("_t1") for u, v in learned if v == "reward"), "reward should have a t+1 parent"
    cbn = fit_cbn(learned, data, prior=1.0)
    table = cbn.reward_table()
    # reference: CPTs fitted by pgmpy itself on the full 19-node network, then VE per state
    ve = VariableElimination(pgmpy_model(learned, data, 1.0))
    states = DEFAULT_SCHEMA.all_states()
    t_names = [n + "_t" for n in DEFAULT_SCHEMA.names]
    ref = np.empty(len(states))
    for i, s in enumerate(states):
        q = ve.query(["reward"], evidence=dict(zip(t_names, s.tolist())), show_progress=False)
        ref[i] = q.values[1]
    np.testing.assert_allclose(table, ref, atol=1e-6, rtol=0)
    assert table.min() < 0.3 and table.max() > 0.7  # the table really discriminates states


def test_cpts_equal_pgmpy_dirichlet_estimator():
    data = random_cbn(GEN_EDGES, seed=3).sample(500, seed=3)
    cbn = fit_cbn(GEN_EDGES, data, prior=2.5)
    model = pgmpy_model(GEN_EDGES, data, 2.5)
    for n in NODES:
        cpd = model.get_cpds(n)
        pa = list(cpd.variables[1:])
        assert sorted(pa) == sorted(cbn.parents[n])
        # pgmpy may order the parents differently: permute its axes into ours
        vals = cpd.values.transpose([0] + [1 + pa.index(p) for p in cbn.parents[n]])
        np.testing.assert_allclose(vals.reshape(cbn.cpts[n].shape), cbn.cpts[n], atol=1e-12)
    # and the conversion to pgmpy carries the same numbers
    back = CBN.from_pgmpy(cbn.to_pgmpy())
    for n in NODES:
        np.testing.assert_allclose(back.cpts[n], cbn.cpts[n], atol=1e-15)


def test_markov_blanket_and_inference_nodes():
    cbn = fit_cbn(GEN_EDGES, np.zeros((0, 19), np.int64))
    assert markov_blanket(GEN_EDGES) == ["depth_center_t", "goal_distance_t1", "goal_in_sight_t1"]
    assert set(cbn.inference_nodes()) == {
        "reward", "goal_in_sight_t1", "goal_distance_t1", "depth_center_t",
        "goal_in_sight_t", "goal_angle_t", "goal_distance_t",
    }
    # a node outside the ancestors (altitude) does not change P(reward | s_t)
    table = random_cbn(GEN_EDGES, seed=0).reward_table().reshape(DEFAULT_SCHEMA.cardinalities)
    np.testing.assert_array_equal(table[..., 0], table[..., 2])


def test_degenerate_data_gives_prior_not_errors():
    # no data at all: every CPT uniform
    empty = fit_cbn(GEN_EDGES, np.zeros((0, 19), np.int64))
    np.testing.assert_allclose(empty.reward_table(), 0.5)
    # one row: the Dirichlet prior keeps P away from 0/1; unseen parent configurations stay uniform
    row = np.zeros((1, 19), np.int64)
    row[0, -1] = 1
    one = fit_cbn([("depth_center_t", "reward")], row, prior=1.0)
    table = one.reward_table().reshape(DEFAULT_SCHEMA.cardinalities)
    assert table[0].max() == pytest.approx(2 / 3) and np.allclose(table[1], 0.5)
    with pytest.raises(ValueError, match="prior"):
        fit_cbn([], row, prior=0.0)
    with pytest.raises(ValueError, match="node"):
        fit_cbn([("x", "reward")], row)


def test_compile_tables_and_batched_lookup():
    cbns = [random_cbn(GEN_EDGES, seed=s) for s in range(3)] + [None]
    tables = compile_tables(cbns)
    assert isinstance(tables, RewardTables)
    assert tables.known.tolist() == [True, True, True, False]
    g = torch.Generator().manual_seed(0)
    cards = torch.tensor(DEFAULT_SCHEMA.cardinalities)
    states = (torch.rand(256, 9, generator=g) * cards).long()
    p_pos, p_neg, known = tables.lookup(states)
    assert p_pos.shape == (256, 4) and known.shape == (256, 4)
    idx = DEFAULT_SCHEMA.state_index(states).numpy()
    for a in range(3):
        np.testing.assert_allclose(p_pos[:, a].numpy(), cbns[a].reward_table()[idx], atol=1e-6)
    np.testing.assert_allclose((p_pos + p_neg).numpy(), 1.0, atol=1e-6)
    assert torch.all(p_pos[:, 3] == 0.5)
