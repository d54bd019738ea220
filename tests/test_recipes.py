"""Recipe plumbing: config validation (bad input fails before training), run-folder
CSV/plot/table helpers and the reproduce plan. Fast: no environment is built.
End-to-end runs of every variant and the resume test are in test_recipes_smoke.py."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))

import recipe_utils as ru  # noqa: E402
import reproduce  # noqa: E402
import results  # noqa: E402
import train  # noqa: E402


def _cfg(name="cbn_v2", overrides=()):
    with initialize_config_dir(config_dir=train.CONFIG_DIR, version_base=None):
        return compose(config_name=name, overrides=list(overrides))


@pytest.mark.parametrize("name", sorted(ru.VARIANTS))
def test_every_variant_config_is_valid(name, tmp_path):
    cfg = _cfg(name, [f"output_dir={tmp_path}"])
    v = ru.validate_config(cfg, tmp_path)
    assert v.name == name == cfg.variant
    # default preset: progress reward, Huber, Double DQN, Adam (docs/recipes.rst, "Presets")
    assert cfg.preset_name == "default" and cfg.env.reward == "progress"
    assert cfg.loss.function == "huber" and cfg.loss.double_dqn and cfg.optim.name == "adam"
    assert ru.reward_scale(cfg) == 1.0
    # the thesis preset keeps every value sec. 5.1 states
    th = _cfg(name, [f"output_dir={tmp_path}", "preset=thesis"])
    ru.validate_config(th, tmp_path)
    assert th.preset_name == "thesis" and th.env.reward == "thesis"
    assert th.loss.gamma == 0.9 and th.optim.lr == 0.00025 and th.optim.eps == 1e-8
    assert th.optim.name == "rmsprop" and th.loss.function == "l2" and not th.loss.double_dqn
    assert th.loss.updates_per_frame == 1.0 and ru.reward_scale(th) == 1.0
    assert ru.reward_scale(_cfg(name, ["env.reward=thesis"])) == 0.01  # auto scale
    assert cfg.gate.prob_causal_model == 0.7 and cfg.gate.threshold == 0.75
    assert cfg.causal.k == 200 and cfg.env.image_size == 84 and cfg.env.max_steps == 200
    expected_gate = {"cbn_p": "p", "cbn_pn": "pn", "cbn_v2": "v2", "cbn_defined": "v2"}
    assert ru.gate_mode(cfg, v) == expected_gate.get(name)


@pytest.mark.parametrize(
    "override, needle",
    [
        ("variant=cbn_q", "variant='cbn_q'"),
        ("causal.k=0", "causal.k=0"),
        ("causal.k=-5", "causal.k=-5"),
        ("gate.threshold=1.5", "gate.threshold=1.5"),
        ("gate.prob_causal_model=-0.1", "gate.prob_causal_model=-0.1"),
        ("exploration.eps_end=2", "exploration.eps_end=2"),
        ("gate.mode=pnx", "gate.mode='pnx'"),
        ("collector.total_frames=0", "collector.total_frames=0"),
        ("env.reward=bogus", "env.reward='bogus'"),
        ("loss.function=l1", "loss.function='l1'"),
        ("optim.name=sgd", "optim.name='sgd'"),
        ("optim.fused=yes", "optim.fused='yes'"),
        ("optim.fused=1", "optim.fused=1"),
        ("preset=thesis optim.fused=true", "optim.fused=True"),
        ("loss.reward_scale=-1", "loss.reward_scale=-1"),
        ("eval.keep_best=3", "eval.keep_best=3"),
        ("loss.learning_starts=20000", "loss.learning_starts=20000"),
        ("loss.target_update_interval=100000", "loss.target_update_interval=100000"),
        ("device=tpu", "device='tpu'"),
        ("logger.backend=mlflowx", "logger.backend='mlflowx'"),
        ("checkpoint.resume=true", "checkpoint.resume"),
        ("env.num_envs=0", "env.num_envs=0"),
        ("loss.updates_per_frame=0", "loss.updates_per_frame=0"),
        ("env.num_envs=3", "collector.frames_per_batch=1"),
        ("env.parallel=maybe", "env.parallel='maybe'"),
        ("env.noise=windy", "env.noise='windy'"),
        ("+env.options.yaw_noise_std_deg=1.0", "env.options.yaw_noise_std_deg"),
    ],
)
def test_bad_input_fails_before_training(override, needle, tmp_path):
    out = tmp_path / "run"
    # the noise preset beside an option it sets itself is a clash
    extra = ["env.noise=tello"] if override.startswith("+env.options") else []
    cfg = _cfg("cbn_v2", [f"output_dir={out}", *override.split(" "), *extra])
    with pytest.raises(ValueError, match="Invalid option") as err:
        train.train(cfg)
    assert needle in str(err.value)
    # nothing of a run was written: the error came before any build
    assert not (out / "config.yaml").exists() and not (out / "episodes.csv").exists()


def test_logger_backend_must_be_installed(tmp_path):
    import importlib.util

    for backend in ("tensorboard", "wandb"):
        cfg = _cfg("cbn_v2", [f"output_dir={tmp_path}", f"logger.backend={backend}"])
        if importlib.util.find_spec(backend) is None:
            with pytest.raises(ValueError, match=f"logger.backend='{backend}'.*not installed"):
                ru.validate_config(cfg, tmp_path)
        else:
            assert ru.validate_config(cfg, tmp_path).name == "cbn_v2"


def test_unwritable_output_dir(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    cfg = _cfg("dqn_image", [f"output_dir={blocker / 'run'}"])
    with pytest.raises(ValueError, match="output_dir=.*cannot be written"):
        train.train(cfg)


def test_cli_reports_bad_input_and_unknown_variant(tmp_path):
    env = dict(os.environ, HYDRA_FULL_ERROR="1")
    r = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "train.py"), "causal.k=0",
         f"output_dir={tmp_path}"],
        capture_output=True, text=True, env=env, timeout=120,
    )
    assert r.returncode != 0
    assert "Invalid option causal.k=0" in r.stderr
    r = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "train.py"), "--config-name", "cbn_x"],
        capture_output=True, text=True, env=env, timeout=120,
    )
    assert r.returncode != 0 and "cbn_x" in r.stderr


def test_moving_average_and_seed_bands(tmp_path):
    ma = results.moving_average([0, 10, 20, 30], 2)
    np.testing.assert_allclose(ma, [0, 5, 15, 25])
    stacked = results.stack_curves([[1, 2, 3], [4]])
    assert stacked.shape == (2, 3) and np.isnan(stacked[1, 1])
    rng = np.random.default_rng(0)
    groups = {"a": [rng.normal(size=80).tolist() for _ in range(3)], "b": [list(range(60))]}
    png = results.plot_reward_curves(groups, 20, tmp_path / "f.png", vlines={"a": [10]})
    assert png.stat().st_size > 5000 and png.read_bytes()[:4] == b"\x89PNG"


def test_bands_need_three_seeds_and_success_bounds_are_cut(tmp_path, monkeypatch):
    """A group gets its 95 % band from three seeds on (two seeds: t = 12.7, the band would
    hide the rest); a success band's bounds are cut to [0, 1] one by one, not narrowed."""
    import matplotlib.axes

    bands = []
    orig = matplotlib.axes.Axes.fill_between
    monkeypatch.setattr(matplotlib.axes.Axes, "fill_between",
                        lambda self, x, lo, hi, **kw: bands.append((lo, hi)) or orig(
                            self, x, lo, hi, **kw))
    rng = np.random.default_rng(0)
    three = [(rng.uniform(size=60) < 0.1).astype(float).tolist() for _ in range(3)]
    two = [(rng.uniform(size=60) < 0.5).astype(float).tolist() for _ in range(2)]
    results.plot_reward_curves({"three": three, "two": two}, 20, tmp_path / "s.png",
                               ylabel="success")
    assert len(bands) == 1  # the three-seed group only
    lo, hi = bands[0]
    mean, half = results.mean_ci95(results.stack_curves(
        [results.moving_average(s, 20) for s in three]))
    np.testing.assert_allclose(lo, np.clip(mean - half, 0, 1))
    np.testing.assert_allclose(hi, np.clip(mean + half, 0, 1))
    assert (hi > 2 * mean).any()  # near 0 the upper bound keeps its width
    bands.clear()
    results.plot_reward_curves({"three": three, "two": two}, 20, tmp_path / "s2.png",
                               ylabel="success", min_band_seeds=2)
    assert len(bands) == 2


def test_reproduce_plan_covers_protocol(tmp_path):
    plan = reproduce.run_plan(tmp_path, "full", 3, list(ru.VARIANTS), [100, 200, 400, 600])
    assert len(plan) == len(ru.VARIANTS) * 3 + 3 * 3  # variants (controls too) + k sweep
    run = {r.run_dir: r for r in plan}[tmp_path / "variants" / "cbn_pn" / "seed_2"]
    argv = run.argv(reproduce.MODES["full"]["overrides"])
    assert argv[:3] == ["--config-name", "cbn_pn", "seed=2"]
    assert "collector.total_episodes=700" in argv
    # the run's own seed and k win over the same keys among the extra overrides
    k_run = next(r for r in plan if r.group == "k_sweep" and r.value == 400 and r.seed == 1)
    argv = k_run.argv(["causal.k=60", "seed=9", "env.max_steps=50"])
    assert argv == ["--config-name", "cbn_v2", "seed=1", "causal.k=400",
                    f"output_dir={k_run.run_dir}", "env.max_steps=50"]
    ks = sorted({r.value for r in plan if r.group == "k_sweep"})
    assert ks == [100, 400, 600]
    with pytest.raises(ValueError, match="--seeds=0"):
        reproduce.main(["--seeds", "0", "--dry-run", "--root", str(tmp_path)])


def test_unknown_preset_is_named():
    with pytest.raises(Exception, match="bogus"):
        _cfg("cbn_v2", ["preset=bogus"])


def test_tello_noise_preset_reaches_the_env():
    """``env.noise=tello`` trains and evaluates under the emulated Tello's move noise."""
    from torchrl_causal.envs import TELLO_MOVE_NOISE

    for noise, expected in (("none", (0.0, 0.0)), ("tello", (0.05, 3.0))):
        cfg = _cfg("dqn_image", [f"env.noise={noise}"])
        env = train.build_env(cfg, ru.VARIANTS["dqn_image"], "thesis", "cpu")
        assert (env.position_noise_std, env.yaw_noise_std_deg) == expected
        env.close()
    assert TELLO_MOVE_NOISE == {"position_noise_std": 0.05, "yaw_noise_std_deg": 3.0}


def test_ordering_calls_a_pair_only_with_three_seeds_a_side(tmp_path):
    """tables/ordering.md: ranked by mean; a pair is told apart where its Welch interval
    excludes 0, and not called at all below three seeds on a side."""
    finals = {"A": pd.DataFrame({"eval_success_thesis": [1.0, 0.95, 0.9]}),
              "B": pd.DataFrame({"eval_success_thesis": [0.0, 0.1, 0.05]}),
              "C": pd.DataFrame({"eval_success_thesis": [0.9, 0.0, 0.5]}),
              "D": pd.DataFrame({"eval_success_thesis": [1.0, 1.0]})}
    text = reproduce._write_ordering(finals, tmp_path / "ordering.md").read_text()
    ranks = [line.split(" | ")[1] for line in text.splitlines() if line.startswith("| ") and
             line.split(" | ")[0] in ("| 1", "| 2", "| 3", "| 4")]
    assert ranks == ["D", "A", "C", "B"]
    rows = {tuple(line.split(" | ")[:2]): line for line in text.splitlines()
            if line.startswith("| ") and (" | [" in line or "n/a" in line)}
    assert rows[("| A", "B")].endswith("| yes |")
    assert rows[("| A", "C")].endswith("| no |")  # C's spread covers A
    assert rows[("| D", "A")].endswith("| n/a (< 3 seeds) |")  # two seeds: no verdict
