"""benchmarks/gridnav.py: episodes to threshold, aggregation and the curve figure (no training;
the training side is exercised by tests/test_training.py through ``build_loop``)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import gridnav  # noqa: E402


def test_episodes_to_threshold():
    assert gridnav.episodes_to_threshold([0, 0, 1, 1, 1, 1], window=4, threshold=0.75) == 5
    assert gridnav.episodes_to_threshold([0, 1, 0, 1], window=2, threshold=1.0) is None


def _run(variant, seed, success, final):
    return {"variant": variant, "seed": seed, "success": success, "crash": [1 - s for s in success],
            "episodes_to_threshold": gridnav.episodes_to_threshold(success, 2, 1.0),
            "final_greedy_success": final, "gate_vetoed": 0.01, "gate_replaced": 0.0,
            "wall_seconds": 2.0}


def test_aggregate_and_plot(tmp_path):
    runs = [_run("v2", 0, [0, 1, 1, 1], 1.0), _run("v2", 1, [0, 0, 0, 1], 0.8)]
    out = gridnav.aggregate(runs, window=2, threshold=1.0)
    assert out["episodes_to_threshold"] == [3, None] and out["seeds_reaching_threshold"] == 1
    assert out["final_greedy_success_mean"] == pytest.approx(0.9)
    # Student t, 1 dof: 12.706 x sd(0.1414) / sqrt(2)
    assert out["final_greedy_success_ci95"] == pytest.approx(12.706 * 0.1, rel=1e-3)
    assert out["train_success"] == pytest.approx(4 / 8) and out["train_crash"] == pytest.approx(4 / 8)
    gridnav.plot({"v2": runs, "dqn": [_run("dqn", 0, [0, 0, 1, 0], 0.0)]}, tmp_path / "c.png", 2)
    assert (tmp_path / "c.png").read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(ValueError, match="variant must be one of"):
        gridnav.build_loop("bogus", 0, 1000)
