"""The training loop as a library part (:mod:`torchrl_causal.training`), tested from the outside."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from torchrl_causal.training import DQNLoop, EpisodeCSV, LoopConfig, rng_state, set_rng_state

ROOT = Path(__file__).resolve().parents[1]
WORKER = ROOT / "tests" / "kill_resume_worker.py"


def test_episode_csv_truncates_on_resume(tmp_path):
    path = tmp_path / "episodes.csv"
    log = EpisodeCSV(path, ["episode", "reward", "success"])
    for i in range(5):
        log.write({"episode": i + 1, "reward": float(i) * 1.5, "success": i % 2 == 0})
    again = EpisodeCSV(path, ["episode", "reward", "success"])
    assert again.n_rows == 5
    again.truncate(3)
    again.write({"episode": 4, "reward": -9.0, "success": False})
    df = pd.read_csv(path)
    assert df["episode"].tolist() == [1, 2, 3, 4]
    assert df["reward"].tolist() == [0.0, 1.5, 3.0, -9.0]
    assert df["success"].tolist() == [1, 0, 1, 0]
    with pytest.raises(ValueError, match="columns"):
        EpisodeCSV(path, ["episode", "other"])


def test_rng_state_roundtrip():
    import torch

    state = rng_state()
    a = (torch.rand(3), np.random.rand(3))
    set_rng_state(state)
    b = (torch.rand(3), np.random.rand(3))
    assert torch.equal(a[0], b[0]) and np.array_equal(a[1], b[1])


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("total_frames", 0, "LoopConfig.total_frames=0"),
        ("updates_per_frame", -1.0, "LoopConfig.updates_per_frame=-1.0"),
        ("loss_function", "mse", "LoopConfig.loss_function='mse'"),
        ("gamma", 1.5, "LoopConfig.gamma=1.5"),
        ("learning_starts", 5000, "LoopConfig.learning_starts=5000"),
        ("target_update_interval", 10**6, "LoopConfig.target_update_interval=1000000"),
        ("eval_max_steps", 0, "LoopConfig.eval_max_steps=0"),
        ("device", "tpu", "LoopConfig.device='tpu'"),
    ],
)
def test_loop_config_rejects_bad_values(field, value, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(".", r"\.")):
        LoopConfig(**{"total_frames": 4000, field: value})


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the no-CUDA message")
def test_loop_config_rejects_cuda_without_cuda():
    with pytest.raises(ValueError, match="LoopConfig.device='cuda'.*is_available"):
        LoopConfig(device="cuda")


def test_loop_rejects_continuous_action_spec():
    from torchrl.envs import GymEnv
    from torchrl.modules import EGreedyModule

    env = GymEnv("Pendulum-v1")
    with pytest.raises(ValueError, match="categorical action spec.*Bounded"):
        DQNLoop(env, torch.nn.Identity(), EGreedyModule(env.action_spec))
    with pytest.raises(ValueError, match="must be a LoopConfig"):
        from torchrl.envs import GymEnv as G

        cart = G("CartPole-v1")
        DQNLoop(cart, torch.nn.Identity(), EGreedyModule(cart.action_spec), config={"a": 1})


def test_resume_without_checkpoint_is_a_clear_error(tmp_path):
    sys.path.insert(0, str(WORKER.parent))
    import kill_resume_worker

    loop = kill_resume_worker.build_loop(tmp_path / "run", frames=600)
    with pytest.raises(ValueError, match="no checkpoint at .*last.pt"):
        loop.run(resume=True)


def _worker(out: Path, *extra: str) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, str(WORKER), str(out), *extra], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _finish(proc: subprocess.Popen, timeout: float = 300) -> str:
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err[-3000:]
    return out


def test_sigkill_at_a_random_moment_then_resume_equals_an_uninterrupted_run(tmp_path):
    """A run killed with SIGKILL mid-run and resumed ends exactly as a run never killed."""
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    ref = _worker(whole)  # the uninterrupted run, beside the one that gets killed
    victim = _worker(killed)
    ckpt = killed / "checkpoints" / "last.pt"
    deadline = time.monotonic() + 240
    while not ckpt.exists():
        assert victim.poll() is None, "the run ended before its first checkpoint"
        assert time.monotonic() < deadline, "no checkpoint within 240 s"
        time.sleep(0.05)
    delay = random.Random(int(time.time())).uniform(0.0, 3.0)  # a random moment
    time.sleep(delay)
    assert victim.poll() is None, f"the run finished before the kill ({delay:.2f} s after ckpt 1)"
    victim.send_signal(signal.SIGKILL)
    victim.wait(timeout=30)
    assert victim.returncode == -signal.SIGKILL
    # what the kill left is a consistent checkpoint: last.pt loads and names its buffer, or,
    # on a machine fast enough to end training within the delay, it is the final checkpoint
    # (no buffer kept) of a run killed in its final evaluation, which resume then runs
    state = torch.load(ckpt, weights_only=False)
    frames_at_kill = state["loop"]["frames"]
    if state["buffer_dir"] is None:
        assert frames_at_kill >= 1200
    else:
        assert (ckpt.parent / state["buffer_dir"]).is_dir()
        assert 0 < frames_at_kill < 1200
    _finish(_worker(killed, "--resume"))
    _finish(ref)
    for name in ("episodes.csv", "eval.csv", "relearns.csv"):
        a, b = (whole / name).read_text(), (killed / name).read_text()
        assert a == b, f"{name} differs after a kill at frame >= {frames_at_kill} (+{delay:.2f} s)"
    assert len(pd.read_csv(whole / "episodes.csv")) > 30
    ma, mb = torch.load(whole / "model.pt"), torch.load(killed / "model.pt")
    assert ma.keys() == mb.keys()
    assert all(torch.equal(ma[k], mb[k]) for k in ma)
    assert not list((killed / "checkpoints").glob("*.tmp"))


def _gridnav_loop(out, frames, *, num_envs=1, variant="expert", seed=0, **overrides):
    """The benchmark's grid-world loop, on ``num_envs`` envs in a ``SerialEnv``."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import gridnav
    from torchrl.envs import SerialEnv

    from torchrl_causal.envs import make_gridnav_env

    torch.set_num_threads(1)
    base = gridnav.build_loop(variant, seed, frames, output_dir=out, **overrides)
    if num_envs == 1:
        return base
    env = SerialEnv(num_envs, lambda: make_gridnav_env(seed=seed, **gridnav.ENV_OPTIONS))
    return DQNLoop(env, base.actor, base.explorer, hook=base.hook, config=base.config,
                   output_dir=out, eval_envs=base.eval_envs)


def test_batched_envs_train_record_every_episode_and_resume_exactly(tmp_path):
    opts = dict(num_envs=3, frames_per_batch=6, checkpoint_interval_frames=240,
                final_eval_episodes=10)
    whole = _gridnav_loop(tmp_path / "whole", 900, **opts).run()
    part = _gridnav_loop(tmp_path / "part", 900, stop_after_frames=400, **opts).run()
    assert part["stopped_early"] and part["frames"] == 480
    resumed = _gridnav_loop(tmp_path / "part", 900, **opts).run(resume=True)
    assert whole["frames"] == resumed["frames"] == 900
    assert whole["peak_rss_mb"] > 50  # the process's peak memory is reported
    a = pd.read_csv(tmp_path / "whole" / "episodes.csv")
    b = pd.read_csv(tmp_path / "part" / "episodes.csv")
    pd.testing.assert_frame_equal(a, b)
    # every step of a recorded episode is in it: lengths add up to at most the frames,
    # episodes end in order of collection, and each ends in exactly one outcome
    assert a["length"].sum() <= 900 and a["frames"].is_monotonic_increasing
    outcome = a["success"] + a["crash"]
    assert ((outcome == 1) | (a["length"] == 50)).all()
    ma = torch.load(tmp_path / "whole" / "model.pt")
    mb = torch.load(tmp_path / "part" / "model.pt")
    assert all(torch.equal(ma[k], mb[k]) for k in ma)
    assert whole["final_eval"]["gridnav"] == resumed["final_eval"]["gridnav"]


def test_gate_changes_learning_on_the_grid_world(tmp_path):
    """What Alg. 4 says, measured: with the expert CBN the gate vetoes moves into
    walls, so training crashes less than with no gate, from the same seeds. The
    gate acts on the DQN's own actions (not the epsilon-random ones), so the gap
    is widest in the second half of training, once epsilon has annealed
    (measured: crash rate 0.12 without the gate, 0.04 with it)."""
    crash, late, veto = {}, {}, []
    for variant in ("dqn", "expert"):
        crash[variant], late[variant] = [], []
        for seed in (0, 1, 2):
            out = tmp_path / f"{variant}_{seed}"
            _gridnav_loop(out, 1200, variant=variant, seed=seed, final_eval_episodes=0).run()
            eps = pd.read_csv(out / "episodes.csv")
            crash[variant].append(eps["crash"].mean())
            late[variant].append(eps[eps["frames"] > 600]["crash"].mean())
            if variant == "expert":
                veto.append((eps["gate_frac_vetoed"] * eps["length"]).sum() / eps["length"].sum())
    assert np.mean(crash["expert"]) < np.mean(crash["dqn"]) - 0.05, crash
    assert all(e < 0.6 * d for e, d in zip(late["expert"], late["dqn"])), late
    assert all(v > 0.005 for v in veto), veto


def test_hook_already_on_the_buffer_is_not_added_twice(tmp_path):
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    base = _gridnav_loop(tmp_path / "a", 600)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(600), transform=base.hook)
    loop = DQNLoop(base.env, base.actor, base.explorer, hook=base.hook, replay_buffer=rb,
                   config=base.config)
    assert sum(t is base.hook for t in loop.replay_buffer._transform) == 1
    loop = DQNLoop(base.env, base.actor, base.explorer, hook=base.hook, config=base.config)
    assert sum(t is base.hook for t in loop.replay_buffer._transform) == 1


def test_a_fresh_start_replaces_the_records_of_an_earlier_start(tmp_path):
    """A run cut short before its first checkpoint, then started again in its folder (a
    grid's checkpoint.resume=auto does this), records the second start only."""
    opts = dict(checkpoint_interval_frames=10_000, final_eval_episodes=2)
    clean = _gridnav_loop(tmp_path / "clean", 400, **opts).run()
    cut = _gridnav_loop(tmp_path / "again", 400, stop_after_frames=150, **opts)
    cut.run()
    (tmp_path / "again" / "checkpoints" / "last.pt").unlink()  # killed before a checkpoint
    assert len(pd.read_csv(tmp_path / "again" / "episodes.csv")) > 0
    again = _gridnav_loop(tmp_path / "again", 400, **opts).run()
    assert clean["frames"] == again["frames"] == 400
    for name in ("episodes.csv", "eval.csv", "relearns.csv"):
        pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "clean" / name),
                                      pd.read_csv(tmp_path / "again" / name))


def test_finished_run_keeps_no_second_copy_of_the_buffer(tmp_path):
    opts = dict(checkpoint_interval_frames=200, final_eval_episodes=0)
    _gridnav_loop(tmp_path / "lean", 600, **opts).run()
    ckpt = tmp_path / "lean" / "checkpoints"
    assert torch.load(ckpt / "last.pt", weights_only=False)["buffer_dir"] is None
    assert not [p for p in ckpt.iterdir() if p.name.startswith("buffer_")]
    # the same budget: only the final evaluation is left, which resuming runs
    again = _gridnav_loop(tmp_path / "lean", 600, **opts).run(resume=True)
    assert again["frames"] == 600 and "final_eval" in again
    # a larger one would need the buffer it did not keep
    with pytest.raises(ValueError, match="finished.*keep_final_buffer"):
        _gridnav_loop(tmp_path / "lean", 800, **opts).run(resume=True)
    # keep_final_buffer: the finished run can be extended with a larger budget
    _gridnav_loop(tmp_path / "kept", 600, keep_final_buffer=True, **opts).run()
    state = torch.load(tmp_path / "kept" / "checkpoints" / "last.pt", weights_only=False)
    assert (tmp_path / "kept" / "checkpoints" / state["buffer_dir"]).is_dir()
    more = _gridnav_loop(tmp_path / "kept", 800, keep_final_buffer=True, buffer_size=600,
                         **opts).run(resume=True)
    assert more["frames"] == 800
