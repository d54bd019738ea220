"""benchmarks/vs_sb3.py: SB3's DQN and DQNLoop train the same Q-network on the same
observations; a tiny real run of both prints both figures."""

from __future__ import annotations

import importlib.util
import os

import pytest
from _scripts import load_script

pytestmark = pytest.mark.skipif(importlib.util.find_spec("stable_baselines3") is None,
                                reason="stable-baselines3 not installed (the bench extra)")


def _bench():
    return load_script("benchmarks/vs_sb3.py")


def test_same_network_and_settings_on_both_sides(tmp_path, monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))
    bench = _bench()
    cfg = bench.recipe_config(800, 0, 0, 1, tmp_path / "run")
    env = bench.sb3_env(cfg)
    model = bench.sb3_model(cfg, env, 0)
    q = model.q_net
    linears = [m for m in q.modules() if m.__class__.__name__ == "Linear"]
    assert [(m.in_features, m.out_features) for m in linears] == [(9, 256), (256, 256), (256, 8)]
    assert model.train_freq.frequency == 4 and model.gradient_steps == 1  # 0.25 updates/frame
    assert model.target_update_interval == 250 * 4 and model.batch_size == 32
    assert model.learning_starts == cfg.loss.learning_starts
    assert not model.policy.optimizer.defaults["fused"]  # SB3 as it comes: PyTorch's default
    fused = bench.sb3_model(cfg, env, 0, fused=True)  # the arm beside the loop's fused Adam
    assert fused.policy.optimizer.defaults["fused"] is True
    assert fused.policy.optimizer.defaults["eps"] == model.policy.optimizer.defaults["eps"]
    env.close()


@pytest.mark.parametrize("train_freq, updates", [(8, 2), (16, 4)])
def test_a_longer_collection_phase_on_both_sides(tmp_path, monkeypatch, train_freq, updates):
    """``--train-freq N``: the loop collects N frames a batch and SB3 N steps a phase, and
    each then takes N x 0.25 gradient steps; the target sync stays 250 gradient steps."""
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))
    bench = _bench()
    cfg = bench.recipe_config(800, 0, 0, 1, tmp_path / "run", train_freq=train_freq)
    assert cfg.collector.frames_per_batch == train_freq
    env = bench.sb3_env(cfg)
    model = bench.sb3_model(cfg, env, 0)
    assert model.train_freq.frequency == train_freq and model.gradient_steps == updates
    assert model.target_update_interval == 250 * 4
    env.close()


def test_a_collection_phase_of_part_of_an_update_is_named(tmp_path, capsys):
    bench = _bench()
    with pytest.raises(ValueError, match="--train-freq 6 x updates_per_frame 0.25"):
        bench.sb3_schedule(bench.recipe_config(800, 0, 0, 1, tmp_path / "run", train_freq=6))
    for bad, says in (("6", "--train-freq 6 x updates_per_frame 0.25 must be a whole"),
                      ("0", "--train-freq must be >= 1, got 0")):
        with pytest.raises(SystemExit):
            bench.main(["--train-freq", bad, "--speed-frames", "0"])
        assert says in capsys.readouterr().err


def test_tiny_run_prints_both_figures(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))
    rows = _bench().main(["--seeds", "0", "--frames", "300", "--eval-every", "150",
                          "--eval-episodes", "1", "--speed-frames", "300", "--repeats", "1",
                          "--override", "loss.learning_starts=100",
                          "--override", "loss.target_update_interval=10",
                          "--override", "exploration.annealing_frames=200",
                          "--override", "env.max_steps=40"])
    speed = rows[0]
    assert speed["figure"] == "frames_per_second" and speed["dqnloop_median"] > 0 < speed["sb3_median"]
    for name in ("dqnloop_dqnloss", "dqnloop_sequential_acting", "dqnloop_fused_adam"):
        assert speed[f"{name}_median"] > 0 and len(speed[name]) == speed["repeats"]
        assert len(speed[f"paired_dqnloop_over_{name}"]["per_repeat"]) == speed["repeats"]
    assert speed["sb3_fused_adam_median"] > 0
    assert len(speed["paired_dqnloop_over_sb3_fused_adam"]["per_repeat"]) == 1
    paired = speed["paired_dqnloop_over_sb3"]
    # one repeat: its ratio is the medians' (from the unrounded frames/s)
    assert paired["per_repeat"] == [speed["ratio_dqnloop_over_sb3"]] == [paired["geomean"]]
    assert paired["ci95"] is None  # one repeat: no interval
    libs = {r["library"]: r for r in rows[1:]}
    assert set(libs) == {"dqnloop", "sb3"}
    for r in libs.values():
        assert len(r["final_success"]) == 1 and 0.0 <= r["final_success"][0] <= 1.0
    with pytest.raises(SystemExit):
        _bench().main(["--frames", "0"])
    with pytest.raises(SystemExit):
        _bench().main(["--arms", "sb3_turbo"])
    err = capsys.readouterr().err
    assert "--arms: unknown ['sb3_turbo']" in err


def test_paired_ratio():
    p = _bench().paired_ratio([2.0, 4.0, 3.0], [1.0, 2.0, 3.0])
    assert p["per_repeat"] == [2.0, 2.0, 1.0]
    assert p["geomean"] == round(4 ** (1 / 3), 3)
    lo, hi = p["ci95"]
    assert lo < p["geomean"] < hi


def test_overheads_figures(tmp_path, monkeypatch):
    """--overheads times the stepping paths and the update paths on the recipe's env."""
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))
    rows = _bench().main(["--seeds", "--speed-frames", "0", "--overheads", "40",
                          "--repeats", "1", "--override", "env.max_steps=15"])
    stepping, update = rows
    assert stepping["figure"] == "stepping" and update["figure"] == "update"
    for key in ("gym_step", "env_step_and_maybe_reset", "collector_4", "collector_4_no_images"):
        assert len(stepping[key]) == 1 and stepping[key][0] > 0
    for key in ("dqnloss_adam_single", "dqnloss_adam_foreach", "dqnloss_adam_fused",
                "stateful_dqnloss_adam_single",
                "plain_torch_adam_single"):
        assert 0 < update[key] < 1000
    with pytest.raises(SystemExit):
        _bench().main(["--overheads", "-1"])


def test_calls_per_frame_figure(tmp_path, monkeypatch):
    """--calls counts the Python calls of each library's training alone, by package."""
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))
    (row,) = _bench().main(["--seeds", "--speed-frames", "0", "--calls", "60",
                            "--override", "env.max_steps=15",
                            "--override", "loss.target_update_interval=5"])
    assert row["figure"] == "calls_per_frame" and row["frames"] == 60
    loop, sb3 = row["dqnloop_by_package"], row["sb3_by_package"]
    # each side's own code ran, and only it: SB3 is not in the loop's count, nor the loop's
    # collector in SB3's (both step the same TorchRL env, so torchrl is in both)
    assert loop["tensordict"] > 0 and "stable_baselines3" not in loop
    assert sb3["stable_baselines3"] > 0 and sb3["gymnasium"] > 0
    assert abs(row["dqnloop_total"] - sum(loop.values())) < 1.0  # rounded per package
    assert row["ratio_dqnloop_over_sb3"] > 0
    # every labelled phase ran, on the side that has it
    assert {"env", "acting", "update", "store", "step_mdp", "postproc"} <= set(
        row["dqnloop_by_phase"])
    assert {"env", "acting", "update", "gym_wrapper"} <= set(row["sb3_by_phase"])
    assert "step_mdp" not in row["sb3_by_phase"] and "gym_wrapper" not in row["dqnloop_by_phase"]
    assert abs(sum(row["sb3_by_phase"].values()) - row["sb3_total"]) < 1.0
    for name, ours, theirs in row["dqnloop_more_than_sb3"]:
        assert ours > theirs, name
    with pytest.raises(SystemExit):
        _bench().main(["--calls", "-5"])
