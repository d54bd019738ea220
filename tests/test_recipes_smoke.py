"""End-to-end smoke runs of recipes/train.py (real MuJoCo env, real causal learner)
and the exact-resume test. Budgets are tiny: a few hundred frames per run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ROOT / "recipes" / "train.py"

TINY = [
    "collector.total_frames=240",
    "env.max_steps=60",
    "causal.k=80",
    "causal.warmup_frames=40",
    "loss.learning_starts=48",
    "loss.updates_per_frame=0.125",
    "loss.target_update_interval=10",
    "buffer.size=300",
    "buffer.batch_size=8",
    "exploration.annealing_frames=200",
    "eval.interval_frames=0",
    "eval.episodes=1",
    "eval.final_episodes=1",
    "checkpoint.interval_frames=100",
    "progress=false",
    "threads=1",
    "++causal.options.min_rows=10",
    # the final videos take seconds a run; dqn_image's end-to-end run records them
    "outputs.videos=0",
]


def _run(args, timeout=300):
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), HYDRA_FULL_ERROR="1")
    r = subprocess.run([sys.executable, str(TRAIN), *args], capture_output=True, text=True,
                       env=env, timeout=timeout, cwd=ROOT)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return r


def _train_here(name, overrides):
    """``recipes/train.py --config-name name overrides`` in this process: the same run
    without an interpreter's start-up (about 10 s of CPU, which the suite's time counts)."""
    import test_recipes as tr

    return tr.train.train(tr._cfg(name, overrides))


@pytest.mark.parametrize("variant", ["dqn_image", "cbn_defined", "cbn_p", "cbn_pn", "cbn_v2"])
def test_variant_runs_end_to_end(variant, tmp_path):
    out = tmp_path / variant
    # evaluation at intervals is exercised by one variant (the code is shared)
    every = ["eval.interval_frames=120"] if variant == "cbn_v2" else []
    # the default recipe's videos (one thesis-scene and outputs.videos held-out episodes)
    # are recorded by one variant (the code is shared)
    videos = ["outputs.videos=1"] if variant == "dqn_image" else []
    # the CBN drawings (16 figures, about 6 s) are drawn by one variant (the code is shared)
    drawings = [] if variant == "cbn_v2" else ["outputs.draw_cbns=false"]
    args = [f"output_dir={out}", *TINY, *every, *videos, *drawings]
    if variant == "dqn_image":  # the command line, as a user runs it
        r = _run(["--config-name", variant, *args])
        assert f"Plots: {out / 'plots'}" in r.stdout
    else:  # the same run in this process
        assert _train_here(variant, args)["plots_dir"] == str(out / "plots")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["variant"] == variant and summary["frames"] == 240
    eps = pd.read_csv(out / "episodes.csv")
    assert len(eps) == summary["episodes"] >= 3
    assert (eps["length"] <= 60).all() and eps["frames"].is_monotonic_increasing
    assert set(eps["success"]) <= {0, 1} and set(eps["crash"]) <= {0, 1}
    # a truncated episode ends at 60 steps; a crash/reach/geofence exit earlier
    ended_early = eps["length"] < 60
    assert ((eps["success"] + eps["crash"] + eps["out_of_bounds"])[ended_early] == 1).all()
    ev = pd.read_csv(out / "eval.csv")
    assert sorted(set(ev["layout"])) == ["thesis"]  # periodic evaluations: training layout
    assert sorted(summary["final_eval"]) == ["heldout", "thesis"]  # final: every eval layout
    assert summary["selected_frames"] in set(ev["frames"])  # eval.keep_best
    assert sorted(set(ev["frames"])) == ([120, 240] if variant == "cbn_v2" else [240])
    assert ev["success_rate"].between(0, 1).all()
    for name in ("reward_ma20.png", "reward_ma50.png", "success_ma50.png"):
        assert (out / "plots" / name).read_bytes()[:4] == b"\x89PNG"
    assert (out / "checkpoints" / "last.pt").is_file()
    model = torch.load(out / "model.pt")
    dense = [v for k, v in model.items() if "dense" in k and k.endswith("weight")][0]
    n_features = 0 if variant == "dqn_image" else 9
    assert dense.shape[1] == 64 * 7 * 7 + n_features  # Fig. 5.1 vs Fig. 5.2
    if variant == "dqn_image":
        assert "gate_frac_consulted" not in eps and not list((out / "cbns").iterdir())
        import av

        for scene in ("thesis", "heldout"):
            assert summary["videos"][scene]["episodes"] == 1
            with av.open(str(out / "videos" / f"{scene}.mp4")) as video:
                stream = video.streams.video[0]
                assert stream.codec_context.name == "h264"
                assert sum(1 for _ in video.decode(stream)) >= 2
        return
    assert not (out / "videos").exists()
    rel = pd.read_csv(out / "relearns.csv")
    assert len(rel) >= 2 and summary["n_relearns"] == len(rel)
    assert eps["gate_frac_consulted"].between(0, 1).all()
    # once tables exist the gate consults the CBN on some steps
    assert eps["gate_frac_consulted"].iloc[-1] > 0 or eps["gate_frac_consulted"].sum() > 0
    learned = json.loads((out / "cbns" / "last" / "learner.json").read_text())
    assert len(learned["actions"]) == 8
    assert len(list((out / "cbns" / "last").glob("*.xmlbif"))) == 8
    assert len(list((out / "cbns" / "last").glob("*.png"))) == (8 if drawings == [] else 0)
    if variant == "cbn_defined":
        from torchrl_causal.causal import expert_dags

        expert = expert_dags()
        for name, info in learned["actions"].items():
            assert sorted(map(tuple, info["edges"])) == sorted(map(tuple, expert[name]))
    else:
        table = (out / "tables" / "table_5_1.md").read_text()
        assert table.count("\n| ") == 8 and "| forward | 14 |" in table
        assert len(list((out / "cbns" / "first").glob("*.png"))) == (8 if drawings == [] else 0)


def test_recipe_trains_on_several_envs(tmp_path):
    """``env.num_envs=2``: two drones in a SerialEnv per collector batch, the
    feature stack on the batch, every episode of both recorded."""
    out = tmp_path / "two"
    _train_here("cbn_v2", [f"output_dir={out}", *TINY, "env.num_envs=2",
                           "collector.frames_per_batch=2", "env.eval_layouts=[thesis]",
                           "outputs.draw_cbns=false"])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 240 and summary["n_relearns"] >= 2
    eps = pd.read_csv(out / "episodes.csv")
    assert len(eps) == summary["episodes"] >= 3
    assert eps["length"].sum() <= 240 and (eps["length"] <= 60).all()
    ended_early = eps["length"] < 60
    assert ((eps["success"] + eps["crash"] + eps["out_of_bounds"])[ended_early] == 1).all()


def test_resume_continues_exactly(tmp_path):
    """Stop a run after its first checkpoint, resume it, compare with an uninterrupted run."""
    full, cut = tmp_path / "full", tmp_path / "cut"
    args = ["--config-name", "cbn_v2", *TINY, "seed=3", "collector.total_frames=280",
            "checkpoint.interval_frames=90", "eval.interval_frames=100",
            "env.eval_layouts=[thesis]", "outputs.draw_cbns=false",
            "buffer.memmap_above=100"]  # the replay memory on disk, as in full-size runs
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), HYDRA_FULL_ERROR="1")
    procs = [
        subprocess.Popen([sys.executable, str(TRAIN), *args, f"output_dir={full}"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env),
        subprocess.Popen([sys.executable, str(TRAIN), *args, f"output_dir={cut}",
                          "checkpoint.stop_after_frames=90"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env),
    ]
    for p in procs:
        stdout, stderr = p.communicate(timeout=300)
        assert p.returncode == 0, stdout[-2000:] + stderr[-3000:]
    assert "checkpoint.resume=true" in stdout  # the stopped run says how to resume
    stopped = pd.read_csv(cut / "episodes.csv")
    assert 0 < len(stopped) < len(pd.read_csv(full / "episodes.csv"))
    assert not (cut / "summary.json").exists()
    assert (cut / "checkpoints" / "buffer_storage").is_dir()  # the memmap a resume reuses
    # reproduce.py --status over a grid holding a finished run, a stopped one and two never
    # started: read from the folders, nothing trained
    import shutil

    sys.path.insert(0, str(ROOT / "recipes"))
    import reproduce

    grid = tmp_path / "status"
    shutil.copytree(full, grid / "variants" / "cbn_v2" / "seed_0")
    shutil.copytree(cut, grid / "variants" / "cbn_v2" / "seed_1")
    rows = reproduce.main(["--status", "--root", str(grid), "--groups", "variants",
                           "--variants", "cbn_v2", "dqn_image", "--seeds", "2"])["status"]
    assert [(r["run"], r["state"]) for r in rows] == [
        ("variants/cbn_v2/seed_0", "finished"), ("variants/cbn_v2/seed_1", "started"),
        ("variants/dqn_image/seed_0", "not started"), ("variants/dqn_image/seed_1", "not started")]
    assert rows[1]["episodes"] == len(stopped) and rows[1]["checkpoint"]
    assert rows[1]["frames"] == int(stopped["frames"].iloc[-1]) < rows[0]["frames"] == 280
    assert rows[0]["thesis_success"] is not None and rows[2]["episodes"] == 0
    assert not (grid / "figures").exists()  # --status draws and trains nothing
    _run([*args, f"output_dir={cut}", "checkpoint.resume=true"])

    for name in ("episodes.csv", "relearns.csv", "eval.csv"):
        a, b = pd.read_csv(full / name), pd.read_csv(cut / name)
        pd.testing.assert_frame_equal(a, b, obj=name)
    assert len(pd.read_csv(full / "relearns.csv")) >= 2
    for run in (full, cut):  # finished: the memmap scratch files are gone
        assert not (run / "checkpoints" / "buffer_storage").exists()
    ma, mb = torch.load(full / "model.pt"), torch.load(cut / "model.pt")
    assert ma.keys() == mb.keys()
    for k in ma:
        assert torch.equal(ma[k], mb[k]), k
    la = json.loads((full / "cbns" / "last" / "learner.json").read_text())
    lb = json.loads((cut / "cbns" / "last" / "learner.json").read_text())
    assert la == lb
    sa = json.loads((full / "summary.json").read_text())
    sb = json.loads((cut / "summary.json").read_text())
    for key in ("frames", "episodes", "updates", "n_relearns"):
        assert sa[key] == sb[key], key

    # stopped during its final evaluation (trained, summary not yet written): resuming
    # only evaluates -- the same final figures, no frame trained again
    episodes_before = (full / "episodes.csv").read_text()
    (full / "summary.json").unlink()
    _train_here("cbn_v2", [*args[2:], f"output_dir={full}", "checkpoint.resume=true"])
    again = json.loads((full / "summary.json").read_text())
    assert again["final_eval"] == sa["final_eval"]
    assert again["frames"] == sa["frames"] and again["updates"] == sa["updates"]
    assert (full / "episodes.csv").read_text() == episodes_before

    # reproduce.py's aggregation over real run folders (two seeds of one variant)
    root = tmp_path / "repro"
    shutil.copytree(full, root / "variants" / "cbn_v2" / "seed_0")
    shutil.copytree(cut, root / "variants" / "cbn_v2" / "seed_1")
    out = reproduce.aggregate(root)
    names = sorted(Path(f).name for f in out["figures"])
    assert names == ["fig5_3_k_sweep.png", "fig5_4_variants.png", "success_k_sweep.png",
                     "success_variants.png"]
    summary_md = (root / "tables" / "summary.md").read_text()
    assert "| CBN-DQN V2 | 2 |" in summary_md and "eval_success_thesis" in summary_md
    assert (root / "tables" / "table_5_1_seed_3.md").exists()  # both copies ran seed 3
    # Table 5.1 over the two runs: each action's row counts both, with a t half-width
    t51 = (root / "tables" / "table_5_1.md").read_text()
    own = pd.read_csv(full / "tables" / "table_5_1.csv")
    first = own.iloc[0]
    assert f"| {first['action']} | 2 | {first['expert_edges']:.2f} +- 0.00 |" in t51
    t51_csv = pd.read_csv(root / "tables" / "table_5_1.csv")  # the same rows, for the docs
    assert list(t51_csv["action"]) == list(own["action"]) and (t51_csv["seeds"] == 2).all()
    assert t51_csv["expert_edges"].iloc[0] == f"{first['expert_edges']:.2f} +- 0.00"
    # the measured ordering: one ranked block per evaluation layout set, a pair row only
    # between different runs (one variant here: no pair)
    ordering = (root / "tables" / "ordering.md").read_text()
    assert "#### thesis" in ordering and "| 1 | CBN-DQN V2 | 2 |" in ordering
    # the k sweep ranked the same way (here the two cbn_v2 runs are its only k)
    k = json.loads((full / "summary.json").read_text())["k"]
    ordering_k = (root / "tables" / "ordering_k.md").read_text()
    assert "#### thesis" in ordering_k and f"| 1 | CBN-DQN V2 k={k} | 2 |" in ordering_k
    # --verify: the first three episodes re-trained here match the record row for row; a
    # record altered in its second episode is caught there (one re-run checks both)
    altered = tmp_path / "altered"
    shutil.copytree(full, altered)
    eps = pd.read_csv(altered / "episodes.csv")
    eps.loc[1, "reward"] += 1.0
    eps.to_csv(altered / "episodes.csv", index=False)
    least = reproduce.min_verify_frames(altered)  # 48 + 10 / 0.125 in this config
    assert least == 128
    with pytest.raises(ValueError, match="--verify-frames=100"):
        reproduce.verify_run(altered, frames=100)
    check = reproduce.verify_run(altered, frames=max(int(eps.loc[2, "frames"]), least))
    assert check["episodes_compared"] >= 3
    assert check["identical"] == check["episodes_compared"] - 1
    assert check["first_difference"] == int(eps.loc[1, "episode"])
    with pytest.raises(ValueError, match="--verify"):
        reproduce.main(["--verify", str(altered), str(tmp_path / "nothing")])
    # the grid's time: both runs' loop seconds, summed
    secs = sum(json.loads((d / "summary.json").read_text())["loop_seconds"] for d in (full, cut))
    assert out["grid_time"]["variants"]["runs"] == 2
    assert out["grid_time"]["variants"]["loop_hours"] == round(secs / 3600.0, 2)
    assert "| variants | 2 |" in (root / "tables" / "grid_time.md").read_text()


def test_load_policy_reproduces_the_final_evaluation(tmp_path):
    """recipes/train.py:load_policy rebuilds the finished run's policy (Q-network + gate with
    its CBN tables): re-running the final evaluation's first episode gives the same reward."""
    sys.path.insert(0, str(ROOT / "recipes"))
    import train as recipe

    from torchrl_causal.training import evaluate

    out = tmp_path / "run"
    _train_here("cbn_v2", [f"output_dir={out}", *TINY, "seed=3"])
    summary = json.loads((out / "summary.json").read_text())
    assert (out / "explorer.pt").is_file()
    seed = 10_000_019 + 3 * 1009  # the final evaluation seeds scene i with 10_000_019 + seed * 1009 + i
    expected = summary["final_eval"]["thesis"]["mean_reward"]
    policy, env, cfg = recipe.load_policy(out, scene="thesis")
    assert cfg.seed == 3 and policy[1].tables is not None  # the gate has its tables
    assert evaluate(policy, env, episodes=1, seed=seed)["mean_reward"] == pytest.approx(expected,
                                                                                        abs=1e-4)
    # a run folder without explorer.pt (older runs): the checkpoint's snapshot is used
    (out / "explorer.pt").unlink()
    policy, _, _ = recipe.load_policy(out, env=env)
    assert evaluate(policy, env, episodes=1, seed=seed)["mean_reward"] == pytest.approx(expected,
                                                                                        abs=1e-4)
    env.close()
    # Hydra's append prefix is the same override (a dotlist would have set a key '+env')
    _, env, cfg = recipe.load_policy(out, overrides=["+env.noise=tello", "++eval.episodes=7"])
    assert cfg.env.noise == "tello" and cfg.eval.episodes == 7 and "+env" not in cfg
    env.close()
    for bad in ("~env.noise", "env.noise", "=tello"):
        with pytest.raises(ValueError, match="Invalid override"):
            recipe.load_policy(out, overrides=[bad])
    with pytest.raises(FileNotFoundError, match="model"):
        (out / "model.pt").unlink()
        recipe.load_policy(out)
