"""benchmarks/generalisation.py: real evaluations of a shipped policy, gate on/off, paired rows."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import generalisation as gb  # noqa: E402


def test_shipped_thesis_policy_rows_with_the_gate_on_and_off(tmp_path):
    out = tmp_path / "rows.jsonl"
    rows = gb.main(["--pretrained", "thesis", "--episodes", "2", "--settings", "thesis",
                    "--gate-off", "--no-oracle", "--control", "cbn_v2/gate_off",
                    "--out", str(out)])
    runs = [r for r in rows if r["figure"] == "run"]
    assert [r["variant"] for r in runs] == ["cbn_v2", "cbn_v2/gate_off"]
    assert all(r["episodes"] == 2 and r["setting"] == "thesis" for r in runs)
    assert runs[0]["success_rate"] == 1.0  # the thesis policy flies its scene, gate on
    # the thesis scene starts with the goal in view: no hidden-start episodes to split off
    assert runs[0]["goal_hidden_at_start"] == 0
    assert runs[0]["success_goal_hidden"] is None and runs[0]["success_goal_visible"] == 1.0
    paired = [r for r in rows if r["figure"] == "paired"]
    assert len(paired) == 1 and paired[0]["n_pairs"] == 1
    assert paired[0]["verdict"] == "cannot be told apart"  # one pair: no interval
    assert len(out.read_text().strip().splitlines()) == len(rows)


def _row(variant, seed, success, setting="heldout"):
    return {"figure": "run", "variant": variant, "seed": seed, "training_scene": "train",
            "setting": setting, "success_rate": success, "spl": success, "crash_rate": 0.0}


def test_paired_rows_say_helps_hurts_or_cannot_be_told_apart():
    rows = [_row("dqn_features", s, 0.5) for s in range(5)]
    rows += [_row("cbn_v2", s, 0.7 + 0.01 * s) for s in range(5)]  # clearly higher
    rows += [_row("cbn_defined", s, 0.3 - 0.01 * s) for s in range(5)]  # clearly lower
    rows += [_row("cbn_p", s, 0.5 + (0.2 if s % 2 else -0.2)) for s in range(5)]
    verdicts = {r["variant"]: r["verdict"] for r in gb.paired_rows(rows, "dqn_features")}
    assert verdicts == {"cbn_v2": "helps", "cbn_defined": "hurts",
                        "cbn_p": "cannot be told apart"}
    var = {r["variant"]: r for r in gb.variant_rows(rows, 0.9)}
    assert var["cbn_v2"]["n_seeds"] == 5 and var["cbn_v2"]["seeds_at_target"] == 0
    assert var["cbn_v2"]["success_ci95"][0] < 0.72 < var["cbn_v2"]["success_ci95"][1]


def test_bad_input_is_named():
    with pytest.raises(SystemExit):
        gb.main(["--runs", "/nonexistent/run*"])
    with pytest.raises(SystemExit):
        gb.main(["--episodes", "0"])


def test_loop_guard_rows_fly_the_same_episodes_with_the_guard_appended(tmp_path):
    """--loop-guard adds a row with a LoopGuard appended to a run that acts without one
    (the generalist's run as trained); a policy that has one already gets no second."""
    import shutil

    from omegaconf import OmegaConf

    from torchrl_causal.pretrained import policy_dir

    run = tmp_path / "seed1"
    shutil.copytree(policy_dir("generalist"), run)
    cfg = OmegaConf.load(run / "config.yaml")
    cfg.features.loop_guard = False
    OmegaConf.save(cfg, run / "config.yaml")
    rows = gb.main(["--runs", str(run), "--pretrained", "generalist", "--episodes", "2",
                    "--settings", "heldout", "--loop-guard", "--no-oracle"])
    runs = [r for r in rows if r["figure"] == "run"]
    assert [(r["name"], r["variant"]) for r in runs] == [
        ("seed1", "cbn_v2"), ("seed1", "cbn_v2/loop_guard"), ("pretrained:generalist", "cbn_v2")]
    assert all(r["episodes"] == 2 and r["setting"] == "heldout" for r in runs)
    # the guarded row and the shipped (guarded) policy fly the same episodes identically
    assert runs[1]["success_rate"] == runs[2]["success_rate"]
    assert runs[1]["mean_length"] == runs[2]["mean_length"]
    # the split by the goal's visibility at the start counts the same episodes in every row
    assert len({r["goal_hidden_at_start"] for r in runs}) == 1
    assert runs[0]["goal_hidden_at_start"] in (0, 1, 2)


def test_goal_prior_rows_fly_the_same_episodes_with_a_guessed_hidden_goal():
    rows = gb.main(["--pretrained", "generalist", "--episodes", "2", "--settings", "heldout",
                    "--goal-prior", "4", "--no-oracle"])
    runs = [r for r in rows if r["figure"] == "run"]
    assert [r["variant"] for r in runs] == ["cbn_v2", "cbn_v2/prior4"]
    assert runs[0]["goal_hidden_at_start"] == runs[1]["goal_hidden_at_start"]
    # a goal in view at the start is flown identically: the prior only fills in a hidden one
    if runs[0]["goal_hidden_at_start"] == 0:
        assert runs[0]["mean_length"] == runs[1]["mean_length"]
    for bad in ("0", "-1", "nan", "12"):
        with pytest.raises(SystemExit):
            gb.main(["--pretrained", "generalist", "--goal-prior", bad])


def test_goal_search_rows_fly_the_same_episodes_with_a_search_for_a_hidden_goal():
    rows = gb.main(["--pretrained", "generalist", "--episodes", "3", "--settings", "heldout",
                    "--goal-search", "4", "--no-oracle"])
    runs = [r for r in rows if r["figure"] == "run"]
    assert [r["variant"] for r in runs] == ["cbn_v2", "cbn_v2/search4"]
    assert runs[0]["goal_hidden_at_start"] == runs[1]["goal_hidden_at_start"]
    assert runs[0]["episodes"] == runs[1]["episodes"] == 3
    for bad in ("0", "-1", "nan", "12"):
        with pytest.raises(SystemExit):
            gb.main(["--pretrained", "generalist", "--goal-search", bad])


def test_fence_and_revisit_rows_fly_the_same_episodes_with_the_options_added(tmp_path):
    """--geofence / --revisit-guard add rows to a run that flies without them (the generalist
    as shipped before them); the shipped generalist, which has both, flies as the last row."""
    import shutil

    from omegaconf import OmegaConf

    from torchrl_causal.pretrained import policy_dir

    run = tmp_path / "seed1"
    shutil.copytree(policy_dir("generalist"), run)
    cfg = OmegaConf.load(run / "config.yaml")
    cfg.features.revisit_guard = False
    cfg.features.ego_map = {"flank_margin": 0.3}
    OmegaConf.save(cfg, run / "config.yaml")
    rows = gb.main(["--runs", str(run), "--pretrained", "generalist", "--episodes", "2",
                    "--settings", "heldout", "--geofence", "--revisit-guard", "--no-oracle"])
    runs = [r for r in rows if r["figure"] == "run"]
    assert [(r["name"], r["variant"]) for r in runs] == [
        ("seed1", "cbn_v2"), ("seed1", "cbn_v2/fence"), ("seed1", "cbn_v2/fence/revisit"),
        ("pretrained:generalist", "cbn_v2"), ("pretrained:generalist", "cbn_v2/fence")]
    assert len({r["goal_hidden_at_start"] for r in runs}) == 1
    assert all(r["episodes"] == 2 for r in runs)
    # the fence keeps every flight inside the arena
    assert all(r["out_of_bounds"] == 0 for r in runs[1:])
    # the options added by the benchmark fly as the shipped policy that has them
    assert runs[2]["success_rate"] == runs[3]["success_rate"]
    assert runs[2]["mean_length"] == runs[3]["mean_length"]
