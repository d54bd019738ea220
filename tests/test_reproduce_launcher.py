"""``recipes/reproduce.py`` through hydra launchers: a tiny two-run grid through
submitit's real local executor and through joblib (real training jobs, run folders,
aggregated figures), finished runs skipped, the launcher errors, the wall-time
estimate and ``checkpoint.resume=auto``."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))

import recipe_utils as ru  # noqa: E402
import reproduce  # noqa: E402

#: ~150 frames per run, one final greedy episode on the thesis scene.
TINY = [
    "collector.total_frames=150", "env.max_steps=50", "causal.k=60", "loss.learning_starts=40",
    "loss.updates_per_frame=0.125", "loss.target_update_interval=10", "buffer.size=200",
    "buffer.batch_size=8", "exploration.annealing_frames=100", "eval.interval_frames=0",
    "eval.episodes=1", "eval.final_episodes=1", "env.eval_layouts=[thesis]",
    "checkpoint.interval_frames=0", "progress=false", "threads=1", "outputs.draw_cbns=false",
    "outputs.videos=0",
]
FIGURES = ["fig5_3_k_sweep.png", "fig5_4_variants.png", "success_k_sweep.png",
           "success_variants.png"]


@pytest.fixture(autouse=True)
def _mujoco_gl(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))


def _check_grid(root: Path, runs: list[Path], out: dict) -> None:
    for run in runs:
        summary = json.loads((run / "summary.json").read_text())
        assert summary["frames"] == 150 and Path(summary["output_dir"]) == run
        assert len(pd.read_csv(run / "episodes.csv")) == summary["episodes"] >= 2
    assert sorted(Path(f).name for f in out["figures"]) == FIGURES
    for name in FIGURES:
        assert (root / "figures" / name).read_bytes()[:4] == b"\x89PNG"
    assert (root / "tables" / "summary.md").exists()


def _needs(module: str):
    return pytest.mark.skipif(importlib.util.find_spec(module) is None,
                              reason=f"{module} not installed (pip install -e '.[cluster]')")


@_needs("hydra_plugins.hydra_submitit_launcher")
def test_two_run_grid_through_submitit_local(tmp_path, capsys):
    root = tmp_path / "grid"
    args = ["--launcher", "submitit_local", "--jobs", "2", "--variants", "cbn_v2", "--seeds",
            "2", "--k", "200", "--no-estimate", "--root", str(root), *TINY]
    out = reproduce.main(args)
    runs = [root / "variants" / "cbn_v2" / f"seed_{s}" for s in (0, 1)]
    _check_grid(root, runs, out)
    assert "2 runs via --launcher=submitit_local" in capsys.readouterr().out
    assert list((root / "variants" / ".submitit").iterdir())  # submitit's job logs
    table = (root / "tables" / "summary.md").read_text()
    assert "| CBN-DQN V2 | 2 |" in table
    # started again: both runs are finished, nothing is launched
    reproduce.main(args)
    printed = capsys.readouterr().out
    assert printed.count("done already") == 2 and "runs via" not in printed


@_needs("hydra_plugins.hydra_joblib_launcher")
def test_two_run_grid_through_joblib(tmp_path):
    root = tmp_path / "grid"
    # one multirun of two runs, side by side in joblib's two workers (the k sweep's own
    # multirun goes through the same code; the Ray test below runs one)
    out = reproduce.main(["--launcher", "joblib", "--jobs", "2", "--variants", "dqn_image",
                          "cbn_v2", "--seeds", "1", "--k", "200", "--no-estimate",
                          "--root", str(root), *TINY])
    runs = [root / "variants" / v / "seed_0" for v in ("dqn_image", "cbn_v2")]
    _check_grid(root, runs, out)
    # --export: the records alone (no checkpoint or model) redraw the same tables
    rec = tmp_path / "records"
    reproduce.main(["--aggregate-only", "--root", str(root), "--export", str(rec)])
    assert sorted(p.name for p in (rec / "variants" / "dqn_image" / "seed_0").iterdir()) == [
        "config.yaml", "episodes.csv", "eval.csv", "relearns.csv", "summary.json", "tables"]
    assert not list(rec.rglob("*.pt"))
    reproduce.main(["--aggregate-only", "--root", str(rec)])
    assert (rec / "tables" / "summary.md").read_text() == \
        (root / "tables" / "summary.md").read_text()
    with pytest.raises(ValueError, match=r"--export=.*inside --root"):
        reproduce.main(["--aggregate-only", "--root", str(root), "--export",
                        str(root / "x")])


def test_unknown_launcher_is_named_before_any_work(tmp_path):
    root = tmp_path / "never"
    with pytest.raises(ValueError, match=r"--launcher='bogus'.*joblib"):
        reproduce.main(["--launcher", "bogus", "--root", str(root)])
    assert not root.exists()


def test_missing_plugin_is_named_before_any_work(tmp_path, monkeypatch):
    # as if Ray were not installed (it is, in dev): the launcher's module cannot be found
    monkeypatch.setitem(reproduce.LAUNCHERS, "ray",
                        reproduce.Launcher("ray", "ray_is_not_installed_here", "ray", "ray"))
    root = tmp_path / "never"
    with pytest.raises(ValueError, match=r"--launcher=ray: ray is not installed \(pip install "
                                         r"ray, or pip install -e '\.\[ray\]'\)"):
        reproduce.main(["--launcher", "ray", "--root", str(root)])
    assert not root.exists()


def test_bad_jobs_are_named(tmp_path):
    with pytest.raises(ValueError, match=r"--jobs=0"):
        reproduce.main(["--jobs", "0", "--dry-run", "--root", str(tmp_path)])
    with pytest.raises(ValueError, match=r"--jobs=2: --launcher=basic"):
        reproduce.main(["--launcher", "basic", "--jobs", "2", "--dry-run", "--root",
                        str(tmp_path)])


def test_estimate_wall_time():
    est = reproduce.estimate_wall_time
    assert est(frames=1000, runs=4, jobs=2, fps=50.0) == pytest.approx(2 * 20.0)
    assert est(frames=1000, runs=5, jobs=2, fps=50.0, overhead_s=5) == pytest.approx(3 * 25.0)
    assert est(frames=1000, runs=3, jobs=8, fps=50.0) == pytest.approx(20.0)  # one wave
    assert est(frames=1000, runs=0, jobs=2, fps=50.0) == 0.0
    with pytest.raises(ValueError, match="fps"):
        est(frames=1000, runs=2, jobs=1, fps=0.0)
    with pytest.raises(ValueError, match="--jobs=0"):
        est(frames=1000, runs=2, jobs=0, fps=10.0)
    line = reproduce.estimate_line(20000, 12, 2, 41.2, 8.0)
    assert line.startswith("Estimated wall time for 12 runs x 20000 frames on 2 parallel "
                           "jobs: 49.3 min (warm-up: 41.2 frames/s")
    assert reproduce.format_duration(90) == "90 s"
    assert reproduce.format_duration(600) == "10.0 min"


def test_dry_run_prints_multiruns_and_formula(tmp_path, capsys):
    assert reproduce.main(["--mode", "reduced", "--jobs", "2", "--dry-run",
                           "--root", str(tmp_path)]) == {}
    printed = capsys.readouterr().out
    # 7 variants (the five of the thesis and the two no-CBN controls) x 2 seeds + k sweep 3 x 2
    assert "Estimated wall time for 20 runs x 2000 frames on 2 parallel jobs: " \
           "ceil(20 / 2) x (2000 / fps" in printed
    assert "14 runs via --launcher=joblib" in printed and "6 runs via --launcher=joblib" in printed
    assert "hydra.launcher.n_jobs=2" in printed and "checkpoint.resume=auto" in printed
    assert not list(tmp_path.rglob("summary.json"))


def test_groups_split_the_grid_across_machines(tmp_path, capsys):
    """--groups k_sweep launches only Fig. 5.3's other k values (the k = 200 runs are the
    cbn_v2 variant runs, launched with --groups variants)."""
    assert reproduce.main(["--mode", "full", "--seeds", "2", "--groups", "k_sweep",
                           "--dry-run", "--root", str(tmp_path)]) == {}
    printed = capsys.readouterr().out
    assert "6 runs via --launcher=joblib" in printed and "causal.k=100,400,600" in printed
    assert "variants/" not in printed and "variant=cbn_v2" in printed
    # seed-major: a grid cut short still holds every k's first seeds
    assert printed.index("seed=0,1") < printed.index("causal.k=100,400,600")
    plan = reproduce.run_plan(tmp_path, "full", 2, ["cbn_v2", "dqn_image"], [100, 200],
                              groups=["variants"])
    assert [(r.group, r.value, r.seed) for r in plan] == [
        ("variants", "cbn_v2", 0), ("variants", "cbn_v2", 1),
        ("variants", "dqn_image", 0), ("variants", "dqn_image", 1)]
    with pytest.raises(SystemExit):
        reproduce.main(["--groups", "figures", "--dry-run", "--root", str(tmp_path)])


def test_grids_skip_finished_runs_and_cap_submitit_local(tmp_path):
    plan = reproduce.run_plan(tmp_path, "reduced", 3, ["cbn_v2", "dqn_image"], [100, 200])
    done = {(tmp_path / "variants" / "dqn_image" / "seed_1")}
    pending = [r for r in plan if r.run_dir not in done]
    grids = reproduce.sweeps(pending, "joblib", 2)
    assert sorted((g, tuple(v), tuple(s)) for g, v, s in grids) == sorted([
        ("variants", ("cbn_v2",), (0, 1, 2)), ("variants", ("dqn_image",), (0, 2)),
        ("k_sweep", (100,), (0, 1, 2))])
    capped = reproduce.sweeps(pending, "submitit_local", 2)
    assert all(len(v) * len(s) <= 2 for _, v, s in capped)
    assert sum(len(v) * len(s) for _, v, s in capped) == len(pending)
    # a later override replaces the mode's
    merged = reproduce.merge_overrides(["a.b=1", "c=2"], ["a.b=3"])
    assert merged == ["c=2", "a.b=3"]


def _cfg(name: str, overrides: list[str]):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(reproduce.CONFIG_DIR), version_base=None):
        return compose(config_name=name, overrides=overrides)


def test_checkpoint_resume_auto(tmp_path):
    cfg = _cfg("cbn_v2", ["checkpoint.resume=auto"])
    ru.validate_config(cfg, tmp_path)  # auto without a checkpoint: a fresh start
    assert ru.resolve_resume(cfg, tmp_path) is False
    ckpt = tmp_path / ru.RUN_LAYOUT["checkpoint"]
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"x")
    assert ru.resolve_resume(cfg, tmp_path) is True
    assert ru.resolve_resume(_cfg("cbn_v2", ["checkpoint.resume=false"]), tmp_path) is False
    with pytest.raises(ValueError, match="checkpoint.resume='sometimes'"):
        ru.validate_config(_cfg("cbn_v2", ["checkpoint.resume=sometimes"]), tmp_path)


@_needs("ray")
def test_two_run_grid_through_a_real_local_ray_instance(tmp_path, capsys):
    """--launcher ray starts a real local Ray instance (2 CPUs), runs each run as a Ray
    task, and the run folders and aggregated figures are there afterwards."""
    import ray

    assert not ray.is_initialized()
    root = tmp_path / "grid"
    args = ["--launcher", "ray", "--jobs", "2", "--variants", "dqn_image",
            "--seeds", "1", "--k", "200", "100", "--no-estimate", "--root", str(root), *TINY]
    out = reproduce.main(args)
    runs = [root / "variants" / "dqn_image" / "seed_0", root / "k_sweep" / "k_100" / "seed_0"]
    _check_grid(root, runs, out)
    # the sweep's k wins over TINY's causal.k=60
    assert json.loads((runs[1] / "summary.json").read_text())["k"] == 100
    printed = capsys.readouterr().out
    assert "Ray: 2 runs on 2 CPUs, 1 node(s)" in printed
    assert printed.count("finished on ") == 2
    for run in runs:  # each task's own log beside its run folder
        assert (run.parent / "seed_0.ray.log").stat().st_size > 0
    assert not ray.is_initialized()  # the instance it started is shut down


def test_ray_options_need_the_ray_launcher(tmp_path):
    with pytest.raises(ValueError, match="--ray-address"):
        reproduce.main(["--launcher", "joblib", "--ray-address", "auto", "--root",
                        str(tmp_path), "--no-estimate"])
    with pytest.raises(ValueError, match="--cpus-per-run"):
        reproduce.main(["--launcher", "basic", "--cpus-per-run", "0", "--root",
                        str(tmp_path), "--no-estimate"])


def _write_run_config(run_dir, overrides, variant):
    from omegaconf import OmegaConf

    run_dir.mkdir(parents=True)
    cfg = reproduce.compose_run_config(overrides, variant)
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg))


def test_ray_tasks_go_seed_major(tmp_path, capsys):
    """--launcher ray submits one task per run, every configuration's seed 0 before any
    seed 1 (as the multiruns do), so a grid cut short holds the first seeds of all."""
    assert reproduce.main(["--mode", "full", "--seeds", "2", "--launcher", "ray",
                           "--variants", "cbn_p", "cbn_pn", "--groups", "variants",
                           "--dry-run", "--no-estimate", "--root", str(tmp_path)]) == {}
    tasks = [line for line in capsys.readouterr().out.splitlines()
             if line.startswith("Ray task:")]
    order = [(re.search(r"--config-name (\S+)", t)[1], re.search(r" seed=(\d)", t)[1])
             for t in tasks]
    assert order == [("cbn_p", "0"), ("cbn_pn", "0"), ("cbn_p", "1"), ("cbn_pn", "1")]


def test_root_of_another_config_is_refused_before_any_job(tmp_path, capsys):
    """A --root holding runs of another mode/preset is named before the warm-up or any job;
    runs that differ only in where they ran (device, threads) are the grid's own."""
    full = reproduce.MODES["full"]["overrides"]
    _write_run_config(tmp_path / "variants" / "cbn_p" / "seed_0",
                      [*full, "seed=0", "device=cuda", "threads=1", "progress=false"], "cbn_p")
    assert reproduce.main(["--mode", "full", "--seeds", "1", "--variants", "cbn_p",
                           "--groups", "variants", "--dry-run", "--no-estimate",
                           "--root", str(tmp_path)]) == {}
    assert "resumes" not in capsys.readouterr().out  # a config only, no checkpoint
    # a run made before env.noise existed (no such key) is the grid's own, a noisy one is not
    from omegaconf import OmegaConf

    old = tmp_path / "variants" / "cbn_pn" / "seed_0"
    _write_run_config(old, [*full, "seed=0"], "cbn_pn")
    cfg = OmegaConf.load(old / "config.yaml")
    del cfg.env["noise"]
    (old / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    assert reproduce.main(["--mode", "full", "--seeds", "1", "--variants", "cbn_pn",
                           "--groups", "variants", "--dry-run", "--no-estimate",
                           "--root", str(tmp_path)]) == {}
    # nor do runs that computed the same numbers another way (TorchRL's own DQNLoss, acting
    # through TensorDictSequential)
    _write_run_config(tmp_path / "variants" / "cbn_v2" / "seed_0",
                      [*full, "seed=0", "loss.stateful=false", "collector.fused_acting=false"],
                      "cbn_v2")
    assert reproduce.main(["--mode", "full", "--seeds", "1", "--variants", "cbn_v2",
                           "--groups", "variants", "--dry-run", "--no-estimate",
                           "--root", str(tmp_path)]) == {}
    noisy = tmp_path / "noisy"
    _write_run_config(noisy / "variants" / "cbn_v2" / "seed_0",
                      [*full, "seed=0", "env.noise=tello"], "cbn_v2")
    with pytest.raises(ValueError, match="env.noise: 'tello' there, 'none' in this grid"):
        reproduce.main(["--mode", "full", "--seeds", "1", "--variants", "cbn_v2",
                        "--groups", "variants", "--dry-run", "--no-estimate",
                        "--root", str(noisy)])
    _write_run_config(tmp_path / "k_sweep" / "k_400" / "seed_0",
                      [*reproduce.MODES["reduced"]["overrides"], "causal.k=400"], "cbn_v2")
    with pytest.raises(ValueError, match=r"--root=.*k_400/seed_0 holds a run of another "
                                         r"config \(.*collector.total_frames: 2000 there, "
                                         r"140000 in this grid"):
        reproduce.main(["--mode", "full", "--seeds", "1", "--k", "400", "--dry-run",
                        "--root", str(tmp_path)])
    with pytest.raises(ValueError, match="env.reward: 'progress' there, 'thesis'"):
        reproduce.main(["--mode", "full", "--seeds", "1", "--variants", "cbn_p",
                        "--groups", "variants", "--dry-run", "--root", str(tmp_path),
                        "preset=thesis"])


def test_a_second_separator_among_the_overrides_is_dropped(tmp_path, capsys):
    """A wrapper adding its overrides after the caller's (benchmarks/gpu_box.sh) passes a
    second '--': it separates, it is not an override for hydra."""
    assert reproduce.main(["--mode", "reduced", "--seeds", "1", "--groups", "k_sweep",
                           "--k", "100", "--dry-run", "--root", str(tmp_path), "--",
                           "env.max_steps=30", "--", "threads=1"]) == {}
    printed = capsys.readouterr().out
    assert "env.max_steps=30" in printed and "threads=1" in printed
    assert " -- " not in printed.replace("' -- '", "")


def test_repair_records_drops_the_rows_of_earlier_starts(tmp_path, capsys):
    """--repair-records keeps each CSV from its last start when the earlier rows are a copy."""
    full = reproduce.MODES["full"]["overrides"]
    run = tmp_path / "variants" / "cbn_v2" / "seed_0"
    _write_run_config(run, [*full, "seed=0"], "cbn_v2")
    rows = [f"{i},{10 * i},{i / 10}" for i in range(1, 6)]
    (run / "episodes.csv").write_text("episode,frames,reward\n" + "\n".join(rows[:2] + rows) + "\n")
    (run / "eval.csv").write_text("frames,episodes,layout,success_rate\n5000,3,thesis,0\n"
                                  "5000,3,thesis,0\n10000,5,thesis,1\n")
    (run / "relearns.csv").write_text("relearn,frames,episode\n1,200,2\n2,400,4\n")
    assert reproduce.main(["--mode", "full", "--seeds", "1", "--variants", "cbn_v2",
                           "--groups", "variants", "--dry-run", "--no-estimate",
                           "--repair-records", "--root", str(tmp_path)]) == {}
    assert "Records repaired" in capsys.readouterr().out
    assert (run / "episodes.csv").read_text().splitlines() == ["episode,frames,reward", *rows]
    assert (run / "eval.csv").read_text().splitlines()[1:] == ["5000,3,thesis,0",
                                                               "10000,5,thesis,1"]
    assert len((run / "relearns.csv").read_text().splitlines()) == 3  # nothing to drop
    assert reproduce.repair_records(tmp_path) == {}  # idempotent
    # an earlier start that logged other episodes is not a copy: refused, file untouched
    text = "episode,frames,reward\n1,10,0.5\n" + "\n".join(rows) + "\n"
    (run / "episodes.csv").write_text(text)
    with pytest.raises(ValueError, match=r"--repair-records: .*episodes.csv rows 1-1 are not"):
        reproduce.repair_records(tmp_path)
    assert (run / "episodes.csv").read_text() == text
