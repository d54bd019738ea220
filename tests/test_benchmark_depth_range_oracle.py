"""benchmarks/depth_range_oracle.py: MonoDepth with the simulator's depth below T, paired arms."""

import json
import math

import pytest
import torch
from torchrl.envs import TransformedEnv

from tests._scripts import load_script
from torchrl_causal.envs import DroneNavEnv
from torchrl_causal.transforms import EstimatedDepth

oracle = load_script("benchmarks/depth_range_oracle.py", "depth_range_oracle")


def test_the_truth_replaces_the_estimate_below_t_only():
    true = torch.tensor([0.3, 0.9, 1.5, 4.0])
    est = torch.tensor([1.0, 1.0, 1.0, 1.0])
    assert oracle.oracle_depth(true, est, 0.0).tolist() == [1.0, 1.0, 1.0, 1.0]
    assert oracle.oracle_depth(true, est, 1.0).tolist() == pytest.approx([0.3, 0.9, 1.0, 1.0])
    assert oracle.oracle_depth(true, est, math.inf).tolist() == pytest.approx(true.tolist())
    for bad in (-0.5, math.nan, "1", True):
        with pytest.raises(ValueError, match="below"):
            oracle.oracle_depth(true, est, bad)
    with pytest.raises(ValueError, match="shape"):
        oracle.oracle_depth(true, est[:2], 1.0)


def test_on_a_real_env_the_estimate_keeps_the_simulators_depth_below_t():
    base = DroneNavEnv(seed=0)
    sim = base.reset()["depth"]
    env = TransformedEnv(DroneNavEnv(seed=0), EstimatedDepth(lambda px: torch.full(px.shape[:-1], 2.5)))
    assert torch.all(env.reset()["depth"] == 2.5)  # outside the block: the estimate alone
    with oracle.truth_below(1.5):
        got = env.reset()["depth"]
    near = sim < 1.5
    assert near.any() and (~near).any()  # the thesis start sees both
    assert torch.allclose(got[near], sim[near]) and torch.all(got[~near] == 2.5)
    assert torch.all(env.reset()["depth"] == 2.5)  # the transform is itself again
    with pytest.raises(ValueError, match="below"):
        with oracle.truth_below(-1.0):
            pass


def test_pairing_counts_the_discordant_episodes():
    a, b = [1, 1, 0, 1, 0, 1], [1, 0, 0, 0, 1, 1]
    p = oracle.paired(a, b)
    assert (p["gains"], p["losses"]) == (2, 1)
    assert p["paired_difference"] == pytest.approx(1 / 6, abs=1e-4)
    lo, hi = p["paired_ci95"]
    assert lo < p["paired_difference"] < hi
    with pytest.raises(ValueError, match="same"):
        oracle.paired([1], [1, 0])
    rows = [{"below": t, "seed": s, "success_per_episode": e}
            for t, s, e in ((0.0, 1, [1, 0]), (0.0, 2, [0, 0]), (math.inf, 1, [1, 1]),
                            (math.inf, 2, [1, 0]))]
    first, best = oracle.pooled(rows)
    assert (first["arm"], best["arm"]) == ("below=0", "below=inf")
    assert (first["success"], first["n"], first["paired_difference"]) == (0.25, 4, 0.0)
    assert (best["success"], best["gains"], best["losses"]) == (0.75, 2, 0)
    assert best["ci95"][0] < 0.75 < best["ci95"][1]  # its own Wilson interval, kept apart
    with pytest.raises(ValueError, match="twice"):
        oracle.pooled(rows + rows[:1])
    weighted = dict(rows[0], depth_weights="/x/cand.pt")
    assert oracle.pooled(rows[:2] + [weighted, dict(weighted, seed=2)])[1]["arm"] == \
        "below=0, depth=cand.pt"


def test_pool_pairs_arms_from_several_runs(tmp_path, capsys):
    a = tmp_path / "a.jsonl"
    b = tmp_path / "b.jsonl"
    a.write_text(json.dumps({"figure": "depth_range_oracle", "arm": "below=0", "below": 0.0,
                             "seed": 3, "success_per_episode": [0, 1, 0, 1]}) + "\n")
    b.write_text(json.dumps({"figure": "depth_range_oracle", "arm": "below=1", "below": 1.0,
                             "seed": 3, "success_per_episode": [1, 1, 0, 1]}) + "\n"
                 + json.dumps({"figure": "depth_range_oracle_pooled"}) + "\n")
    out = oracle.main(["--pool", str(a), str(b)])
    assert [o["arm"] for o in out] == ["below=0", "below=1"]
    assert (out[1]["gains"], out[1]["losses"], out[1]["success"]) == (1, 0, 0.75)
    printed = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert printed == out


def test_bad_options_are_named_before_any_flight(capsys):
    for argv, word in ((["--below", "-1"], "--below"), (["--below", "x"], "--below"),
                       (["--ego-map", "max_range"], "--ego-map"),
                       (["--episodes", "0"], "--episodes"),
                       (["--depth-weights", "/nonexistent.pt"], "--depth-weights"),
                       (["--pool", "/nonexistent.jsonl"], "--pool")):
        with pytest.raises(SystemExit):
            oracle.main(argv)
        assert word in capsys.readouterr().err
