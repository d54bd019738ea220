"""``LoopConfig.overlap``: collection in a worker thread beside the optimisation.

The exact-resume tests of the default path (``tests/test_training.py``) are run
again here with ``overlap=True`` (their helpers are reused, not copied): a run
killed with SIGKILL and resumed, and a run stopped and resumed on batched grid
worlds, must equal the uninterrupted overlapped run bit for bit.
"""

from __future__ import annotations

import threading

import pandas as pd
import pytest
import torch

import test_training as tt
from torchrl_causal.training import LoopConfig


def _overlapped(make):
    """``make`` with ``overlap=True`` added to its options."""
    return lambda *args, **kwargs: make(*args, overlap=True, **kwargs)


def test_overlap_sigkill_then_resume_equals_an_uninterrupted_run(tmp_path, monkeypatch):
    """CartPole, CBN-gated: the default path's kill test, with overlap=True in every run."""
    worker = tt._worker
    monkeypatch.setattr(tt, "_worker", lambda out, *extra: worker(out, *extra, "--overlap"))
    tt.test_sigkill_at_a_random_moment_then_resume_equals_an_uninterrupted_run(tmp_path)
    for run in ("whole", "killed"):
        ckpt = torch.load(tmp_path / run / "checkpoints" / "last.pt", weights_only=False)
        assert ckpt["config"]["overlap"] is True
        assert ckpt["acting_actor"] is not None and ckpt["buffer_rng"] is not None


def test_overlap_is_deterministic_and_resumes_exactly_on_batched_grid_worlds(
        tmp_path, monkeypatch):
    """Grid world, 3 envs in a SerialEnv: the default path's stop + resume test with
    overlap=True, plus a second uninterrupted run from the same seed."""
    monkeypatch.setattr(tt, "_gridnav_loop", _overlapped(tt._gridnav_loop))
    tt.test_batched_envs_train_record_every_episode_and_resume_exactly(tmp_path)
    opts = dict(num_envs=3, frames_per_batch=6, checkpoint_interval_frames=240,
                final_eval_episodes=10)
    again = tt._gridnav_loop(tmp_path / "again", 900, **opts)
    threads = set()
    step = again.env.step

    def step_and_note_thread(td):
        threads.add(threading.get_ident())
        return step(td)

    again.env.step = step_and_note_thread
    summary = again.run()
    # the env was stepped in the worker thread only, and the worker collected
    # beside the optimisation
    assert threads and threading.get_ident() not in threads
    assert summary["worker_collection_seconds"] > 0
    for name in ("episodes.csv", "eval.csv"):
        a = (tmp_path / "whole" / name).read_text()
        assert a == (tmp_path / "again" / name).read_text(), name
    ma = torch.load(tmp_path / "whole" / "model.pt")
    mb = torch.load(tmp_path / "again" / "model.pt")
    assert all(torch.equal(ma[k], mb[k]) for k in ma)


def test_overlap_acts_with_the_weights_of_one_batch_before(monkeypatch):
    """The acting copy holds the learner's weights from before the last batch's updates."""
    from torchrl_causal.training.loop import DQNLoop as Loop

    loop = tt._gridnav_loop(None, 600, overlap=True, final_eval_episodes=0,
                            frames_per_batch=4, updates_per_frame=1.0, learning_starts=100)
    seen = []
    sync = Loop._sync_acting

    def spy(self):
        before = [p.clone() for p in self._acting_actor.parameters()]
        sync(self)
        seen.append((self.state["updates"], before,
                     [p.clone() for p in self.actor.parameters()]))

    monkeypatch.setattr(Loop, "_sync_acting", spy)
    loop.run()
    # from the second sync on, what the worker acted with is what the learner had at
    # the sync before: one batch (4 frames, 4 updates) older than the learner
    lagged = 0
    for (u0, _, learner0), (u1, acting1, _) in zip(seen, seen[1:]):
        assert all(torch.equal(a, b) for a, b in zip(acting1, learner0))
        lagged += u1 > u0
    assert lagged > 100
    assert all(torch.equal(a, b) for a, b in zip(loop._acting_actor.parameters(),
                                                 seen[-1][2]))


def test_drone_env_renders_the_same_frames_from_a_worker_thread():
    """An env reset in the main thread and stepped in another renders what one stepped
    in the main thread renders (SceneRenderer builds a GL context for that thread)."""
    from torchrl_causal.envs import DroneNavEnv

    actions = [0, 2, 2, 4, 1, 3, 0, 0, 5, 6]

    def fly(env, td, out):
        for a in actions:
            td = env.step(td.set("action", torch.tensor(a)))["next"]
            out.append(td["pixels"].clone())  # (+ the goal mask's pass, inside step)

    ref_env, env = DroneNavEnv(seed=3), DroneNavEnv(seed=3)
    ref = [ref_env.reset()["pixels"].clone()]
    fly(ref_env, ref_env.reset(), ref)
    got = [env.reset()["pixels"].clone()]
    worker = threading.Thread(target=fly, args=(env, env.reset(), got))  # reset here,
    worker.start()  # stepped there
    worker.join()
    assert len(ref) == len(got) == len(actions) + 1
    assert all(torch.equal(a, b) for a, b in zip(ref, got))
    assert len({int(f.long().sum()) for f in got}) > 3  # the view changed as it flew
    # back in the main thread (its own context again), with a new layout on reset
    for e in (ref_env, env):
        e.set_seed(5)
    assert torch.equal(ref_env.reset()["pixels"], env.reset()["pixels"])
    ref_env.close()
    env.close()


def test_overlap_bad_input_is_named(tmp_path):
    with pytest.raises(ValueError, match=r"LoopConfig\.overlap='yes'.*True or False"):
        LoopConfig(overlap="yes")
    opts = dict(checkpoint_interval_frames=200, final_eval_episodes=0, keep_final_buffer=True)
    tt._gridnav_loop(tmp_path / "run", 400, stop_after_frames=200, **opts).run()
    with pytest.raises(ValueError, match=r"LoopConfig\.overlap=True.*written with overlap=False"):
        tt._gridnav_loop(tmp_path / "run", 400, overlap=True, **opts).run(resume=True)
    assert len(pd.read_csv(tmp_path / "run" / "episodes.csv")) > 0  # nothing was cut


def test_recipe_option_collector_overlap(tmp_path):
    """``collector.overlap`` reaches the loop; a bad value is named before any build; a
    short drone run (dqn_image: pixels, the thesis CNN) trains with it."""
    import test_recipes as tr

    out = tmp_path / "bad"
    with pytest.raises(ValueError, match=r"Invalid option collector\.overlap='maybe'"):
        tr.train.train(tr._cfg("dqn_image", [f"output_dir={out}", "collector.overlap=maybe"]))
    assert not (out / "config.yaml").exists()
    cfg = tr._cfg("dqn_image", [
        f"output_dir={tmp_path / 'run'}", "collector.overlap=true", "collector.total_frames=100",
        "loss.learning_starts=50", "loss.target_update_interval=10", "eval.interval_frames=0",
        "eval.final_episodes=0", "env.eval_layouts=[thesis]", "env.max_steps=40",
        "checkpoint.interval_frames=0", "logger.backend=none", "progress=false",
        "outputs.draw_cbns=false", "outputs.videos=0", "threads=1"])
    assert tr.train.loop_config(cfg, tr.ru.VARIANTS["dqn_image"]).overlap is True
    summary = tr.train.train(cfg)
    assert summary["frames"] == 100 and summary["updates"] > 0
    assert summary["worker_collection_seconds"] > 0
