"""CausalLearner: thesis Alg. 2 end to end on synthetic transitions."""

import numpy as np
import pytest
import torch

from torchrl_causal.causal import CausalLearner, expert_dags, load_cbn
from torchrl_causal.schema import ACTION_NAMES, DEFAULT_SCHEMA

CARDS = torch.tensor(DEFAULT_SCHEMA.cardinalities)
GOAL = DEFAULT_SCHEMA.index("goal_in_sight")
CENTER = DEFAULT_SCHEMA.index("depth_center")


def transitions(n, seed, actions=(0, 1, 2, 3, 4, 5, 6)):
    """Forward crashes when the centre is close; seeing the goal at t+1 gives a positive reward."""
    g = torch.Generator().manual_seed(seed)
    s0 = (torch.rand(n, 9, generator=g) * CARDS).long()
    s1 = torch.where(torch.rand(n, 9, generator=g) < 0.7, s0, (torch.rand(n, 9, generator=g) * CARDS).long())
    a = torch.tensor(actions)[torch.randint(0, len(actions), (n,), generator=g)]
    reward = torch.where(s1[:, GOAL] == 1, 50.0, -9.0)
    crash = (a == 0) & (s0[:, CENTER] == 0)
    reward = torch.where(crash, torch.tensor(-1000.0), reward)
    return s0, a, s1, reward


def test_learned_mode_end_to_end():
    learner = CausalLearner(min_rows=30)
    assert learner.tables is None and learner.n_relearns == 0
    learner.add(*transitions(2400, 0))
    tables = learner.relearn()
    assert learner.tables is tables and learner.n_relearns == 1
    # action 7 (turn_right) was never taken: unknown
    assert tables.known.tolist() == [True] * 7 + [False]
    dags = learner.dags()
    assert ("goal_in_sight_t1", "reward") in dags["forward"]
    assert ("depth_center_t", "reward") in dags["forward"]
    assert ("depth_center_t", "reward") not in dags["backward"]
    # the compiled table says what the data says: forward with the centre close is a crash
    s = torch.zeros(2, 9, dtype=torch.long)
    s[:, GOAL] = 1
    s[1, CENTER] = 1
    p_pos, p_neg, known = tables.lookup(s)
    assert p_neg[0, 0] > 0.9 and p_pos[1, 0] > 0.5
    assert known.shape == (2, 8)
    rec = learner.history[0]["actions"]["forward"]
    assert rec["n_rows"] > 0 and rec["known"] and "reward" not in rec["markov_blanket"]


def test_warm_start_and_history():
    learner = CausalLearner(min_rows=30)
    learner.add(*transitions(1200, 1))
    learner.relearn()
    first = learner.history_dags(0)
    learner.add(*transitions(1200, 2))
    learner.relearn()
    assert len(learner.history) == 2 and learner.n_relearns == 2
    last = learner.history_dags(-1)
    assert set(first) == set(ACTION_NAMES) == set(last)
    assert learner.history[1]["frames"] == 2400
    # warm start from the previous DAG gives the same result as a cold start here (a strict optimum)
    cold = CausalLearner(min_rows=30, warm_start=False)
    cold.data.load_state_dict(learner.data.state_dict())
    cold.relearn()
    assert cold.dags() == learner.dags()


def test_degenerate_actions_are_unknown_and_never_crash():
    learner = CausalLearner(min_rows=50)
    s0, a, s1, r = transitions(400, 3, actions=(0, 1))
    # action 1: reward never varies; action 2: too few rows; constant state columns everywhere
    r = torch.where(a == 1, torch.tensor(-9.0), r)
    s0[:, 8] = 1
    s1[:, 8] = 1
    learner.add(s0, a, s1, r)
    few = transitions(10, 4, actions=(2,))
    learner.add(*few)
    tables = learner.relearn()
    assert tables.known.tolist() == [True, False, False, False, False, False, False, False]
    reasons = {k: v["reason"] for k, v in learner.history[0]["actions"].items()}
    assert "never varied" in reasons["backward"] and "min_rows" in reasons["left"]
    assert "min_rows" in reasons["turn_right"]
    assert torch.all((tables.p_pos >= 0) & (tables.p_pos <= 1))


def test_defined_mode_uses_expert_structures():
    learner = CausalLearner(mode="defined", min_rows=30)
    learner.add(*transitions(1200, 5))
    tables = learner.relearn()
    assert learner.dags() == {a: list(map(tuple, e)) for a, e in expert_dags().items()}
    assert tables.known[:7].all() and not tables.known[7]
    # the CPTs come from the data: forward with the centre close is likely negative
    s = torch.zeros(1, 9, dtype=torch.long)
    s[0, GOAL] = 1
    assert tables.lookup(s)[1][0, 0] > 0.7


def test_state_dict_round_trip_and_resume():
    learner = CausalLearner(min_rows=30)
    learner.add(*transitions(1000, 6))
    learner.relearn()
    sd = learner.state_dict()
    other = CausalLearner(min_rows=30)
    other.load_state_dict(sd)
    assert torch.equal(other.tables.p_pos, learner.tables.p_pos)
    assert other.dags() == learner.dags() and other.n_relearns == 1
    np.testing.assert_array_equal(other.data.counts(), learner.data.counts())
    more = transitions(500, 7)
    learner.add(*more)
    other.add(*more)
    assert torch.allclose(learner.relearn().p_pos, other.relearn().p_pos)
    assert learner.history[-1]["actions"]["left"]["edges"] == other.history[-1]["actions"]["left"]["edges"]


def test_save_writes_standard_files(tmp_path):
    learner = CausalLearner(min_rows=30)
    learner.add(*transitions(800, 8))
    learner.relearn()
    learner.save(tmp_path)
    assert (tmp_path / "learner.json").exists()
    for a, name in enumerate(ACTION_NAMES):
        cbn = load_cbn(tmp_path / f"{name}.xmlbif")
        assert set(cbn.edges) == set(learner.dags()[name])
        np.testing.assert_allclose(cbn.reward_table(), learner.tables.p_pos[a].numpy(), atol=1e-6)


def test_bad_options_raise():
    for kwargs, match in [
        ({"mode": "expert"}, "mode"),
        ({"backend": "gpu"}, "backend"),
        ({"synchronous": "x"}, "synchronous"),
        ({"min_rows": 0}, "min_rows"),
        ({"prior": -1.0}, "prior"),
        ({"mode": "defined", "n_actions": 4}, "n_actions"),
    ]:
        with pytest.raises(ValueError, match=match):
            CausalLearner(**kwargs)
    learner = CausalLearner()
    s = torch.zeros(2, 9, dtype=torch.long)
    with pytest.raises(ValueError, match="action"):
        learner.add(s, torch.tensor([0, 8]), s, torch.zeros(2))
    with pytest.raises(ValueError, match="cardinalities"):
        learner.add(s + 3, torch.tensor([0, 1]), s, torch.zeros(2))


def test_first_searched_dags_skip_relearns_before_an_action_had_data():
    learner = CausalLearner(min_rows=30)
    learner.add(*transitions(600, 0, actions=(0,)))  # only forward has data at relearn 1
    learner.relearn()
    learner.add(*transitions(600, 1, actions=(1,)))  # backward gets data for relearn 2
    learner.relearn()
    first = learner.first_searched_dags()
    assert first["forward"] == learner.history_dags(0)["forward"] != []
    assert learner.history_dags(0)["backward"] == []  # not searched at relearn 1 ...
    assert first["backward"] == learner.history_dags(1)["backward"] != []  # ... but at 2
    assert first["turn_right"] == []  # never taken
