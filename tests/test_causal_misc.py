"""Expert CBNs, transition storage, graph comparison, save/load and drawing."""

import csv

import numpy as np
import pytest
import torch

from torchrl_causal.causal import (
    TransitionData,
    compare_dags,
    draw_cbn,
    expert_dags,
    expert_edges,
    fit_cbn,
    load_cbn,
    save_cbn,
    shd,
    table_5_1,
    write_table_5_1,
)
from torchrl_causal.causal.expert import TABLE_5_1_TOTALS
from torchrl_causal.causal.inference import random_cbn
from torchrl_causal.causal.structure import allowed_edges
from torchrl_causal.schema import ACTION_NAMES, DEFAULT_SCHEMA, Variable, VariableSchema

NODES = DEFAULT_SCHEMA.node_names()


def test_expert_dags_follow_table_5_1_and_the_time_tiers():
    dags = expert_dags()
    assert list(dags) == list(ACTION_NAMES)
    allowed = allowed_edges(DEFAULT_SCHEMA, "forbid")
    idx = {n: i for i, n in enumerate(NODES)}
    for action, edges in dags.items():
        assert len(edges) == TABLE_5_1_TOTALS[action]
        assert len(set(edges)) == len(edges)
        assert all(allowed[idx[u], idx[v]] for u, v in edges), action
        assert ("goal_in_sight_t1", "reward") in edges
        assert all(len(e.rationale) > 10 for e in expert_edges(action))
    # physics: only actions that move towards something can crash into it
    crash = {a: {u for u, v in e if v == "reward" and u.endswith("_t")} for a, e in dags.items()}
    assert crash["forward"] == {"depth_center_t"}
    assert crash["backward"] == crash["turn_left"] == crash["turn_right"] == set()
    assert "altitude_t" in crash["descend"]
    assert expert_edges(3) == expert_edges("right")
    with pytest.raises(ValueError, match="action"):
        expert_edges("hover")
    with pytest.raises(ValueError, match="schema lacks"):
        expert_dags(VariableSchema((Variable("a", ("x", "y")),)))


def test_transition_data_grows_and_windows():
    data = TransitionData(n_actions=3, initial_capacity=2)
    total = 0
    for i in range(20):
        s = torch.full((7, 9), i % 2, dtype=torch.long)
        data.add(s, torch.tensor([0, 0, 0, 1, 1, 0, 0]), s, torch.arange(7) - 3.0)
        total += 7
    assert data.counts().tolist() == [100, 40, 0] and len(data) == total
    rows = data.rows(0)
    assert rows.shape == (100, 19) and rows.dtype == np.int8
    np.testing.assert_array_equal(rows[:5, -1], [0, 0, 0, 1, 1])  # rewards -3, -2, -1, 2, 3
    assert data.rows(2).shape == (0, 19)
    windowed = TransitionData(n_actions=1, max_rows=10, initial_capacity=4)
    for i in range(5):
        s = torch.full((4, 9), i % 2, dtype=torch.long)
        windowed.add(s, torch.zeros(4, dtype=torch.long), s, torch.zeros(4))
    assert windowed.rows(0).shape[0] == 10
    np.testing.assert_array_equal(windowed.rows(0)[-4:, 0], [0, 0, 0, 0])  # newest batch (i = 4)
    np.testing.assert_array_equal(windowed.rows(0)[:6, 0], [0, 0, 1, 1, 1, 1])
    with pytest.raises(ValueError, match="batch size"):
        data.add(torch.zeros(2, 9, dtype=torch.long), torch.zeros(3, dtype=torch.long),
                 torch.zeros(2, 9, dtype=torch.long), torch.zeros(2))


def test_compare_dags_and_shd():
    ref = [("a_t", "a_t1"), ("b_t", "b_t1"), ("a_t1", "reward"), ("b_t1", "reward")]
    learned = [("a_t", "a_t1"), ("b_t1", "b_t"), ("c_t", "reward"), ("a_t1", "reward")]
    c = compare_dags(learned, ref)
    # common: a_t->a_t1, a_t1->reward; reversed: b; missing: b_t1->reward; extra: c_t->reward
    assert (c.common, c.n_learned, c.n_reference, c.shd) == (2, 4, 4, 3)
    assert c.mb_precision == pytest.approx(1 / 2) and c.mb_recall == pytest.approx(1 / 2)
    assert shd(ref, ref) == 0 and shd([], ref) == 4
    assert compare_dags(ref, ref).similarity == 1.0


def test_table_5_1_writer(tmp_path):
    expert = expert_dags()
    first = {a: e[:3] for a, e in expert.items()}
    last = {a: e[:5] + [("altitude_t", "reward")] for a, e in expert.items()}
    rows = table_5_1(expert, first, last)
    assert [r["action"] for r in rows] == list(ACTION_NAMES)
    left = rows[ACTION_NAMES.index("left")]
    assert (left["expert_edges"], left["first_common"], left["last_common"], left["last_edges"]) == (17, 3, 5, 6)
    assert left["best_similarity"] == pytest.approx(5 / 17)
    md, cv = write_table_5_1(rows, tmp_path / "table_5_1")
    lines = md.read_text().splitlines()
    assert len(lines) == 2 + 8 and "| left | 17 | 3/3 | 5/6 |" in md.read_text()
    with open(cv) as f:
        back = list(csv.DictReader(f))
    assert back[2]["action"] == "left" and int(back[2]["last_edges"]) == 6


@pytest.mark.parametrize("suffix", [".xmlbif", ".json"])
def test_save_load_round_trip(tmp_path, suffix):
    edges = expert_dags()["turn_right"]
    cbn = fit_cbn(edges, random_cbn(edges, seed=0).sample(300, seed=0), prior=0.5)
    path = save_cbn(cbn, tmp_path / f"turn_right{suffix}")
    back = load_cbn(path)
    assert set(back.edges) == set(cbn.edges)
    np.testing.assert_allclose(back.reward_table(), cbn.reward_table(), atol=1e-9)
    for n in NODES:
        assert set(back.parents[n]) == set(cbn.parents[n])
    with pytest.raises(ValueError, match="suffix"):
        save_cbn(cbn, tmp_path / "x.pkl")


def test_draw_writes_png(tmp_path):
    from matplotlib.image import imread

    path = tmp_path / "forward.png"
    edges = expert_dags()["forward"]
    fig = draw_cbn(edges, path=path, title="forward", highlight=edges[:2])
    img = imread(path)
    assert img.ndim == 3 and img.shape[0] > 300 and img.shape[1] > 600
    assert img[..., :3].std() > 0.05  # not blank
    ax = fig.axes[0]
    assert len(ax.patches) >= len(edges)  # one arrow per edge
    with pytest.raises(ValueError, match="not in the schema"):
        draw_cbn([("x", "reward")])
