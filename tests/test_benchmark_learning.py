"""benchmarks/learning.py: aggregation of run folders (no training).

Synthetic run folders with the files ``recipes/train.py`` writes
(``summary.json``, ``config.yaml``, ``episodes.csv``, ``eval.csv``) and known
numbers; checks :func:`aggregate` exactly and the ``--from-runs`` command line.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
from scipy import stats
from _scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "learning.py"

bl = load_script("benchmarks/learning.py", "bench_learning")

EP_COLS = ("episode,frames,reward,length,success,crash,out_of_bounds,epsilon,n_relearns,"
           "gate_frac_explored,gate_frac_consulted,gate_frac_vetoed,gate_frac_replaced")
EVAL_COLS = ("frames,episodes,layout,success_rate,mean_reward,collisions,out_of_bounds,"
             "mean_length,steps_to_goal")


def _eval_result(success):
    return {"success_rate": success, "mean_reward": 12.5, "collisions": 1, "out_of_bounds": 0,
            "mean_length": 40.0, "steps_to_goal": 35.0 if success > 0 else float("nan")}


def make_run(folder: Path, variant: str, seed: int, final: float, heldout: float,
             episodes: list[tuple[int, int, int]], evals: list[tuple[int, str, float]],
             loop_seconds: float, frames: int = 1200, preset: str = "default") -> Path:
    """A finished run folder. ``episodes``: (success, crash, out_of_bounds) per training
    episode; ``evals``: (frames, layout, success_rate) per eval.csv row."""
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(
        f"variant: {variant}\nseed: {seed}\npreset_name: {preset}\n"
        f"collector:\n  total_frames: {frames}\n  total_episodes: null\n"
        f"env:\n  layout: thesis\n  eval_layouts:\n  - thesis\n  - heldout\n")
    rows, f = [EP_COLS], 0
    for i, (succ, crash, oob) in enumerate(episodes):
        length = 30 + 7 * i
        f += length
        reward = 150.0 if succ else -80.5
        rows.append(f"{i},{f},{reward},{length},{succ},{crash},{oob},0.8125,{i // 2},"
                    "0.3,0.4,0.05,0.02")
    (folder / "episodes.csv").write_text("\n".join(rows) + "\n")
    rows = [EVAL_COLS]
    for fr, layout, sr in evals:
        stg = "nan" if sr == 0 else "33.5"
        rows.append(f"{fr},{fr // 40},{layout},{sr},-20.25,1,0,44.5,{stg}")
    (folder / "eval.csv").write_text("\n".join(rows) + "\n")
    summary = {
        "variant": variant, "seed": seed, "k": 200, "frames": frames, "episodes": len(episodes),
        "updates": 450, "n_relearns": 5, "stopped_early": False, "output_dir": str(folder),
        "plots_dir": str(folder / "plots"), "loop_seconds": loop_seconds,
        "loop_frames_per_second": frames / loop_seconds, "optimisation_seconds": 10.0,
        "collection_seconds": 20.0, "causal_learning_seconds": 1.5, "gating_seconds": 0.5,
        "final_eval": {"thesis": _eval_result(final), "heldout": _eval_result(heldout)},
        "model": str(folder / "model.pt"),
    }
    # json.dumps writes NaN as train.py does (steps_to_goal of a run without success)
    (folder / "summary.json").write_text(json.dumps(summary, indent=2))
    return folder


@pytest.fixture
def runs(tmp_path):
    out = tmp_path / "bench"
    a = make_run(
        out / "cbn_v2" / "seed_0", "cbn_v2", 0, final=0.95, heldout=0.5,
        episodes=[(0, 1, 0), (0, 0, 1), (1, 0, 0), (1, 0, 0)],
        evals=[(600, "thesis", 0.0), (600, "heldout", 1.0),
               (1200, "thesis", 1.0), (1200, "heldout", 0.0)],
        loop_seconds=100.0)
    b = make_run(
        out / "cbn_v2" / "seed_1", "cbn_v2", 1, final=0.6, heldout=0.25,
        episodes=[(0, 1, 0), (0, 1, 0), (0, 0, 0), (1, 0, 0), (0, 0, 1), (1, 0, 0)],
        evals=[(600, "thesis", 0.0), (600, "heldout", 0.0),
               (1200, "thesis", 0.0), (1200, "heldout", 0.0)],
        loop_seconds=140.0)
    c = make_run(
        out / "dqn_image" / "seed_0", "dqn_image", 0, final=0.2, heldout=0.0,
        episodes=[(0, 1, 0), (1, 0, 0)],
        evals=[(600, "thesis", 0.5), (1200, "thesis", 0.0)],
        loop_seconds=50.0)
    return out, [a, b], [c]


def test_aggregate_two_seeds(runs):
    _, cbn, _ = runs
    res = bl.aggregate(cbn)
    assert res["variant"] == "cbn_v2" and res["preset"] == "default" and res["frames"] == 1200
    assert res["n_seeds"] == 2 and res["seeds"] == [0, 1] and res["n_unfinished"] == 0
    assert res["final_success"] == [0.95, 0.6]
    assert res["final_success_mean"] == pytest.approx(0.775)
    sd = math.sqrt(((0.95 - 0.775) ** 2 + (0.6 - 0.775) ** 2) / 1)
    assert res["final_success_ci95"] == pytest.approx(stats.t.ppf(0.975, 1) * sd / math.sqrt(2))
    assert res["seeds_at_0_9"] == 1
    # seed 0: first thesis row with success > 0 is at 1200 (the heldout row at 600 does not count)
    assert res["frames_to_first_greedy_success"] == [1200, None]
    assert res["frames_to_first_greedy_success_median"] == 1200.0
    # 10 training episodes: 3 crashes, 2 out of bounds, 4 successes
    assert res["train_episodes"] == 10
    assert res["train_crash_rate"] == pytest.approx(0.3)
    assert res["train_out_of_bounds_rate"] == pytest.approx(0.2)
    assert res["train_success_rate"] == pytest.approx(0.4)
    assert res["wall_seconds"] == pytest.approx(120.0)
    assert res["final_success_heldout_mean"] == pytest.approx(0.375)
    json.dumps(res, allow_nan=False)  # strict JSON


def test_aggregate_one_seed_and_unfinished(runs, tmp_path):
    _, _, dqn = runs
    unfinished = tmp_path / "bench" / "dqn_image" / "seed_1"
    (unfinished / "checkpoints").mkdir(parents=True)
    res = bl.aggregate(dqn + [unfinished])
    assert res["n_seeds"] == 1 and res["n_unfinished"] == 1
    assert res["final_success_mean"] == pytest.approx(0.2) and res["final_success_ci95"] == 0.0
    assert res["frames_to_first_greedy_success"] == [600]
    assert res["train_crash_rate"] == pytest.approx(0.5)


def test_aggregate_rejects_mixed_or_empty(runs, tmp_path):
    _, cbn, dqn = runs
    with pytest.raises(ValueError, match="several variants"):
        bl.aggregate(cbn + dqn)
    with pytest.raises(ValueError, match="no finished run"):
        bl.aggregate([tmp_path / "nothing"])


def test_run_overrides_extra_replaces_same_key(tmp_path):
    ov = bl.run_overrides(tmp_path, 3, 5000, "thesis", 7, False,
                          ["eval.final_episodes=9", "buffer.size=100"])
    assert f"output_dir={tmp_path}" in ov and "seed=3" in ov and "preset=thesis" in ov
    assert "env.eval_layouts=[thesis]" in ov and "collector.total_frames=5000" in ov
    assert "eval.final_episodes=9" in ov and "eval.final_episodes=7" not in ov
    assert "buffer.size=100" in ov
    assert "env.eval_layouts=[thesis,heldout]" in bl.run_overrides(tmp_path, 0, 1, "default",
                                                                   1, True)


def test_from_runs_prints_one_line_per_variant(runs):
    out, _, _ = runs
    env = dict(os.environ, MUJOCO_GL="egl")
    proc = subprocess.run([sys.executable, str(SCRIPT), "--from-runs", "--out", str(out)],
                          capture_output=True, text=True, env=env, timeout=120, check=True)
    lines = proc.stdout.strip().splitlines()
    # every other variant has no run folder: only these two, in --variants order
    rows = [json.loads(line) for line in lines]
    assert [r["variant"] for r in rows] == ["dqn_image", "cbn_v2"]
    assert rows[1]["n_seeds"] == 2 and rows[1]["final_success_mean"] == pytest.approx(0.775)
    assert rows[0]["frames_to_first_greedy_success_median"] == 600.0
    saved = [json.loads(line) for line in (out / "learning.jsonl").read_text().splitlines()]
    assert saved == rows
    assert not (out / "cbn_p").exists()  # nothing was trained
