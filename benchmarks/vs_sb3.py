"""Stable-Baselines3's DQN beside this library's ``DQNLoop``: speed and sample efficiency.

Both train the same DQN on the same observations -- the thesis scene's nine
continuous features (``causal_features``, from the project's own feature
stack; SB3 reads them through :class:`~torchrl_causal.envs.gym_registration.DroneNavGymEnv`
wrapped around the very TorchRL env the recipe builds) -- with the same
Q-network (two dense ReLU layers of 256 on the features divided by the same
per-feature scale, a linear head), Huber loss, plain (not double) DQN targets,
no reward scaling, Adam (same learning rate and eps), gradient-norm clip 10,
replay ratio (``updates_per_frame`` 0.25 -> SB3 ``train_freq`` 4; the loop collects
batches of 4 frames, then takes its one gradient step, as SB3 does; ``--train-freq N``
makes both collect N frames, then take N x 0.25 gradient steps), batch size, replay
size, ``learning_starts``, hard target sync (SB3 counts it in env steps: the
recipe's gradient steps / replay ratio) and linear epsilon-greedy exploration
(uniformly random actions until ``learning_starts`` in both: SB3's rule, the loop's
``collector.init_random_frames``; the epsilon schedule counts those frames in both).
``DQNLoop`` runs as the recipe ``dqn_features`` with ``features.image=false``
(no CBN, no gate).

Figures (one JSON object each):

* ``frames_per_second``: each library trains ``--speed-frames`` frames with no
  evaluation, the runs alternated ``--repeats`` times in this one process;
  the medians and their ratio (target of the "thesis protocol" issue:
  ``DQNLoop`` >= SB3). More runs per repeat (``--arms``, default all):
  ``dqnloop_dqnloss``, the loop
  with TorchRL's own ``DQNLoss`` (``loss.stateful=false``) instead of its
  ``StatefulDQNLoss`` (the same numbers bit for bit, with per-call parameter swaps);
  ``dqnloop_sequential_acting``, the loop acting through ``TensorDictSequential(actor,
  explorer)`` (``collector.fused_acting=false``) instead of its ``EGreedyQValuePolicy``
  (the same actions bit for bit); ``dqnloop_fused_adam``, the loop with PyTorch's
  fused Adam kernel (``optim.fused=auto``) instead of its default path; and
  ``sb3_fused_adam``, SB3 with its Adam fused too (``optimizer_kwargs``), the fair
  partner of the fused loop.
  ``paired_*``: the per-repeat ratios, their geometric mean and its 95 % interval
  (the runs of one repeat are back to back, so a slow spell of the machine slows both);
* ``first_success`` (per library): over ``--seeds``, the frames of the first
  periodic greedy evaluation (``--eval-every`` frames, ``--eval-episodes``
  episodes on the thesis scene) that reaches the goal, within ``--frames``;
  and the final greedy success. Target: not worse than SB3 within the CIs.
* with ``--overheads N``, where the loop's time goes beside SB3's:
  ``stepping`` (random actions for N frames, alternated ``--repeats`` times: the
  gym-style step SB3 drives, TorchRL's ``step_and_maybe_reset`` loop, the collector with
  4-frame batches, and the same collector with the images dropped by an
  ``ExcludeTransform``) and ``update`` (milliseconds per gradient step, 4 x N/4 steps:
  TorchRL's ``DQNLoss`` update with Adam single-tensor / ``foreach`` / ``fused``, the loop's
  ``StatefulDQNLoss``, and the
  same network, batch, Huber loss, clip and Adam written as plain PyTorch).
* with ``--calls N``, ``calls_per_frame``: each library trains N frames once while a
  ``sys.setprofile`` hook counts every Python-level function call (C built-ins included)
  in the loop's ``DQNLoop.run`` / SB3's ``learn``; the counts per frame, in total, by
  phase (the env's step, acting, storing, the update, the rest), by the package a
  function lives in, the functions the loop calls most more often than SB3 and each
  library's most called functions in its ``rest`` phase. A count does not depend on how
  busy the machine is, so it shows where the loop does more work than SB3 where timings
  on a noisy machine cannot.

::

    python benchmarks/vs_sb3.py                               # speed + 3 seeds x 12,000 frames
    python benchmarks/vs_sb3.py --seeds 0 --frames 4000 --speed-frames 1000   # a quick look
    python benchmarks/vs_sb3.py --seeds --speed-frames 0 --overheads 1200     # overheads only
    python benchmarks/vs_sb3.py --seeds --arms dqnloop_fused_adam sb3_fused_adam --repeats 9  # 4 runs a repeat
    python benchmarks/vs_sb3.py --seeds --speed-frames 0 --calls 2000         # calls per frame only

Needs the ``bench`` extra (``pip install -e '.[bench]'``: stable-baselines3).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))


#: The speed figure's runs: ``DQNLoop`` as the recipe runs it, three variants of it (each with
#: one implementation choice changed), SB3's DQN as it comes and with its Adam fused.
SPEED_ARMS = ("dqnloop", "dqnloop_dqnloss", "dqnloop_sequential_acting", "dqnloop_fused_adam",
              "sb3", "sb3_fused_adam")


def recipe_config(frames: int, seed: int, eval_every: int, eval_episodes: int, out: Path,
                  extra=(), train_freq: int = 4):
    """The ``dqn_features`` recipe on the nine features alone, set up as the SB3 run is
    (``train_freq``: frames collected between two optimisation phases, in both)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from omegaconf import OmegaConf

    GlobalHydra.instance().clear()
    with initialize_config_dir(version_base=None, config_dir=str(ROOT / "recipes" / "config")):
        cfg = compose("base", [
            "variant=dqn_features", "features.image=false", "features.inputs=[causal_features]",
            "features.history=0", "loss.double_dqn=false", "loss.reward_scale=1.0",
            "loss.function=huber", "optim.name=adam", "loss.updates_per_frame=0.25",
            # SB3 collects train_freq steps (default 4 = 1 / replay ratio), then takes
            # train_freq x replay ratio gradient steps: the loop collects batches of that
            # size, then optimises the same
            f"collector.frames_per_batch={train_freq}",
            f"collector.total_frames={frames}", f"seed={seed}", "threads=1", "progress=false",
            f"eval.interval_frames={eval_every}", f"eval.episodes={eval_episodes}",
            f"eval.final_episodes={eval_episodes}", "eval.keep_best=false",
            "env.eval_layouts=[thesis]", "outputs.videos=0", "outputs.draw_cbns=false",
            "checkpoint.interval_frames=0", "logger.backend=none", f"output_dir={out}",
            *extra])
    # SB3 acts uniformly at random until learning_starts (no Q-network call, the epsilon
    # schedule still counting those steps); the loop does the same with init_random_frames
    if not any(e.startswith("collector.init_random_frames=") for e in extra):
        OmegaConf.update(cfg, "collector.init_random_frames", int(cfg.loss.learning_starts))
    return cfg


def run_dqnloop(cfg) -> dict:
    """``recipes/train.py``'s ``train`` on ``cfg``: frames/s and the periodic evaluations."""
    import train as train_recipe

    with contextlib.redirect_stdout(io.StringIO()):
        summary = train_recipe.train(cfg)
    out = Path(cfg.output_dir)
    evals = []
    if (out / "eval.csv").exists():
        import pandas as pd

        df = pd.read_csv(out / "eval.csv")
        evals = [(int(r.frames), float(r.success_rate)) for r in df.itertuples()]
    final = summary.get("final_eval", {}).get("thesis", {}).get("success_rate")
    return {"fps": float(summary["loop_frames_per_second"]), "evals": evals, "final": final}


def sb3_schedule(cfg) -> tuple[int, int]:
    """SB3's ``(train_freq, gradient_steps)`` for the loop's config: the loop's batch
    (``collector.frames_per_batch``) and its updates per batch (x ``updates_per_frame``).

    Raises:
        ValueError: the batch does not make a whole number (>= 1) of gradient steps.
    """
    upf = float(cfg.loss.updates_per_frame)
    train_freq = int(cfg.collector.frames_per_batch)
    gradient_steps = round(train_freq * upf)
    if gradient_steps < 1 or abs(gradient_steps - train_freq * upf) > 1e-9:
        raise ValueError(f"--train-freq {train_freq} x updates_per_frame {upf:g} must be a whole "
                         "number (>= 1) of gradient steps per collection phase")
    return train_freq, gradient_steps


def sb3_model(cfg, env, seed: int, fused: bool = False):
    """SB3's DQN with the recipe's settings and the same Q-network (``fused``: its Adam
    with PyTorch's fused kernel, as the recipe's ``optim.fused=auto``; SB3's default, like
    the recipe's, is PyTorch's default path)."""
    import gymnasium as gym
    import torch
    from stable_baselines3 import DQN
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

    from torchrl_causal.pretrained.policy import FEATURE_SCALES

    scale = torch.tensor(FEATURE_SCALES["causal_features"], dtype=torch.float32)

    class ScaledFeatures(BaseFeaturesExtractor):
        """``causal_features / scale``, as ``FeatureQNet`` divides them."""

        def __init__(self, observation_space: gym.spaces.Dict):
            super().__init__(observation_space, features_dim=len(scale))
            self.register_buffer("scale", scale.clone())

        def forward(self, obs):
            return obs["causal_features"].float() / self.scale

    upf = float(cfg.loss.updates_per_frame)
    train_freq, gradient_steps = sb3_schedule(cfg)
    frames = int(cfg.collector.total_frames)
    return DQN(
        "MultiInputPolicy", env, learning_rate=float(cfg.optim.lr),
        buffer_size=int(cfg.buffer.size), learning_starts=int(cfg.loss.learning_starts),
        batch_size=int(cfg.buffer.batch_size), gamma=float(cfg.loss.gamma),
        train_freq=(train_freq, "step"), gradient_steps=gradient_steps,
        # SB3 counts the sync in env steps: the recipe's gradient steps / replay ratio
        target_update_interval=round(int(cfg.loss.target_update_interval) / upf),
        exploration_initial_eps=float(cfg.exploration.eps_init),
        exploration_final_eps=float(cfg.exploration.eps_end),
        exploration_fraction=min(1.0, float(cfg.exploration.annealing_frames) / frames),
        max_grad_norm=float(cfg.loss.max_grad_norm), seed=seed, device="cpu", verbose=0,
        policy_kwargs=dict(net_arch=[256, 256], activation_fn=torch.nn.ReLU,
                           features_extractor_class=ScaledFeatures,
                           optimizer_kwargs=dict(eps=float(cfg.optim.eps),
                                                 **({"fused": True} if fused else {}))),
    )


def sb3_env(cfg):
    """The recipe's own TorchRL env (thesis scene + feature stack) as a gymnasium env."""
    import recipe_utils as ru
    import train as train_recipe

    from torchrl_causal.envs.gym_registration import DroneNavGymEnv

    env = train_recipe.build_env(cfg, ru.VARIANTS[cfg.variant], "thesis", "cpu")
    return DroneNavGymEnv(env=env, obs_keys=["causal_features"])


def greedy_success(model, env, episodes: int) -> float:
    wins = 0
    for _ in range(episodes):
        obs, _ = env.reset()
        done = False
        info = {}
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, term, trunc, info = env.step(int(action))
            done = term or trunc
        wins += bool(info.get("reached"))
    return wins / episodes


def run_sb3(cfg, seed: int, eval_every: int, eval_episodes: int, fused: bool = False) -> dict:
    from stable_baselines3.common.callbacks import BaseCallback

    import torch

    torch.set_num_threads(1)
    env, eval_env = sb3_env(cfg), sb3_env(cfg)
    model = sb3_model(cfg, env, seed, fused=fused)
    frames = int(cfg.collector.total_frames)
    evals = []

    class Evaluate(BaseCallback):
        def _on_step(self) -> bool:
            if eval_every and self.num_timesteps % eval_every == 0:
                evals.append((self.num_timesteps, greedy_success(self.model, eval_env,
                                                                 eval_episodes)))
            return True

    t0 = time.perf_counter()
    model.learn(total_timesteps=frames, callback=Evaluate())
    seconds = time.perf_counter() - t0
    final = greedy_success(model, eval_env, eval_episodes)
    env.close()
    eval_env.close()
    return {"fps": frames / seconds, "evals": evals, "final": final}


def stepping_fps(cfg, frames: int) -> dict:
    """Frames/s of random actions on the recipe's env: the gym-style step SB3 drives, the
    env's own ``step_and_maybe_reset`` loop, and the loop's collector (4-frame batches),
    with and without the images (``ExcludeTransform`` after the feature stack)."""
    import recipe_utils as ru
    import train as train_recipe
    from torchrl.collectors import Collector
    from torchrl.envs import ExcludeTransform, TransformedEnv

    def make():
        return train_recipe.build_env(cfg, ru.VARIANTS[cfg.variant], "thesis", "cpu")

    def timed(fn):
        t0 = time.perf_counter()
        fn()
        return round(frames / (time.perf_counter() - t0), 1)

    def gym_steps():
        env = sb3_env(cfg)
        env.reset(seed=0)
        for _ in range(frames):
            _, _, term, trunc, _ = env.step(env.action_space.sample())
            if term or trunc:
                env.reset()
        env.close()

    def env_steps():
        env = make()
        td = env.reset()
        for _ in range(frames):
            _, td = env.step_and_maybe_reset(env.rand_action(td))
        env.close()

    def collector(exclude: bool):
        env = make()
        if exclude:
            env = TransformedEnv(env, ExcludeTransform("pixels", "depth"), auto_unwrap=False)
        c = Collector(env, None, frames_per_batch=4, total_frames=frames, track_traj_ids=False)
        for _ in c:
            pass
        c.shutdown()

    return {"gym_step": timed(gym_steps), "env_step_and_maybe_reset": timed(env_steps),
            "collector_4": timed(lambda: collector(False)),
            "collector_4_no_images": timed(lambda: collector(True))}


def update_ms(cfg, updates: int) -> dict:
    """Milliseconds per gradient step on one 32-row batch of real transitions: TorchRL's
    ``DQNLoss`` with Adam single-tensor / ``foreach`` / ``fused``, the loop's
    ``StatefulDQNLoss`` (the same loss without per-call parameter swaps) with Adam
    single-tensor, and plain PyTorch."""
    import warnings

    import recipe_utils as ru
    import torch
    import train as train_recipe
    from torchrl.objectives import DQNLoss

    from torchrl_causal.pretrained.policy import FEATURE_SCALES

    variant = ru.VARIANTS[cfg.variant]
    env = train_recipe.build_env(cfg, variant, "thesis", "cpu")
    actor, _, _ = train_recipe.build_agent(cfg, variant, env, "cpu")
    # the loop owns the target sync, not the loss: TorchRL's warning about it is noise here
    warnings.filterwarnings("ignore", message="No target network updater")
    stateful, optim = train_recipe.build_loss(cfg, actor, env)
    functional = DQNLoss(actor, loss_function=ru.LOSS_FUNCTIONS[cfg.loss.function],
                         delay_value=True, double_dqn=cfg.loss.double_dqn,
                         action_space=env.action_spec_unbatched)
    functional.make_value_estimator(gamma=cfg.loss.gamma)
    n = int(cfg.buffer.batch_size)
    batch = env.rollout(n, break_when_any_done=False).exclude(
        "pixels", "depth", ("next", "pixels"), ("next", "depth"))
    env.close()
    params = [p for p in stateful.parameters() if p.requires_grad]
    group = optim.param_groups[0]
    clip = float(cfg.loss.max_grad_norm)

    def timed(step):
        for _ in range(20):
            step()
        t0 = time.perf_counter()
        for _ in range(updates):
            step()
        return round((time.perf_counter() - t0) / updates * 1e3, 3)

    out = {}
    for name, loss, kw in (("dqnloss_adam_single", functional, {"foreach": False}),
                           ("stateful_dqnloss_adam_single", stateful, {"foreach": False}),
                           ("dqnloss_adam_foreach", functional, {"foreach": True}),
                           ("dqnloss_adam_fused", functional, {"fused": True})):
        opt = torch.optim.Adam(params, lr=group["lr"], eps=group["eps"], **kw)

        def step(opt=opt, loss=loss):
            value = loss(batch)["loss"]
            opt.zero_grad()
            value.backward()
            torch.nn.utils.clip_grad_norm_(params, clip)
            opt.step()
        out[name] = timed(step)

    def mlp():
        return torch.nn.Sequential(torch.nn.Linear(9, 256), torch.nn.ReLU(),
                                   torch.nn.Linear(256, 256), torch.nn.ReLU(),
                                   torch.nn.Linear(256, 8))
    net, target = mlp(), mlp()
    opt = torch.optim.Adam(net.parameters(), lr=group["lr"], eps=group["eps"], foreach=False)
    scale = torch.tensor(FEATURE_SCALES["causal_features"], dtype=torch.float32)
    x, x2 = batch["causal_features"] / scale, batch["next", "causal_features"] / scale
    a, r = batch["action"].reshape(-1, 1), batch["next", "reward"].reshape(-1)
    d = batch["next", "terminated"].reshape(-1).float()
    gamma = float(cfg.loss.gamma)

    def plain():
        with torch.no_grad():
            y = r + gamma * (1 - d) * target(x2).max(1).values
        value = torch.nn.functional.smooth_l1_loss(net(x).gather(1, a).squeeze(1), y)
        opt.zero_grad()
        value.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), clip)
        opt.step()
    out["plain_torch_adam_single"] = timed(plain)
    return out


def _package(path: str) -> str:
    """The package a Python function lives in: a site-packages top-level name,
    ``torchrl_causal`` or ``python`` (the standard library and the rest)."""
    if "site-packages/" in path:
        return path.split("site-packages/")[-1].split("/")[0].removesuffix(".py")
    return "torchrl_causal" if "torchrl_causal" in path else "python"


class _CallCounter:
    """Counts every Python-level function call (``sys.setprofile``'s ``call`` and
    ``c_call`` events) by the phase it runs under and the function (with its package). A
    phase is the innermost method :meth:`label` wrapped that is running (``rest`` outside
    them). The counts by phase and by package are sums of ``calls``."""

    def __init__(self):
        self.stack = ["rest"]
        self.calls = collections.Counter()  # (phase, package, function)

    def _event(self, frame, event, arg):
        if event == "call":
            code = frame.f_code
            package = _package(code.co_filename)
            self.calls[self.stack[-1], package,
                       f"{package}:{Path(code.co_filename).name}:{code.co_name}"] += 1
        elif event == "c_call":
            self.calls[self.stack[-1], "builtins (C)",
                       f"C:{getattr(arg, '__qualname__', repr(arg))}"] += 1

    def by(self, field: int, phase: str | None = None) -> collections.Counter:
        """The counts summed by phase (0), package (1) or function (2), of one phase or all."""
        out = collections.Counter()
        for key, n in self.calls.items():
            if phase is None or key[0] == phase:
                out[key[field]] += n
        return out

    def label(self, owner, name: str, phase: str):
        """``mock.patch`` of ``owner.name`` that runs it under ``phase``."""
        from unittest import mock

        fn, stack = getattr(owner, name), self.stack

        def wrapped(*args, **kwargs):
            stack.append(phase)
            try:
                return fn(*args, **kwargs)
            finally:
                stack.pop()

        return mock.patch.object(owner, name, wrapped)

    @contextlib.contextmanager
    def counting(self):
        sys.setprofile(self._event)
        try:
            yield self
        finally:
            sys.setprofile(None)


def call_counts(cfg, frames: int, top: int = 12) -> dict:
    """Python function calls per frame while each library trains ``frames`` frames, by
    phase, by package and by function: the loop's ``DQNLoop.run`` (no evaluation in it)
    and SB3's ``learn`` (env and model built before). Phases: ``env`` (the TorchRL env's
    ``step`` / ``reset``, which both libraries drive), ``acting`` (the policy, or the random
    action before ``learning_starts``), ``update`` (the loop's ``_optimise``; SB3's
    ``train``: sampling, loss, optimiser); the loop's ``step_mdp`` (the next step's input,
    in ``step_and_maybe_reset``), ``postproc`` (the collector's scan of each batch for
    private keys) and ``store`` (``_ingest``: buffer write and episode rows); SB3's
    ``gym_wrapper`` (``DroneNavGymEnv`` around the env); and ``rest`` (the collector's or
    SB3's own bookkeeping between them: the loop's stacking of each batch, SB3's buffer
    write). ``sys.setprofile`` sees the calling thread only: the loop must run serially
    (``collector.overlap=false``, the recipe's default)."""
    from unittest import mock

    if cfg.collector.get("overlap", False):
        raise ValueError("calls per frame count one thread: run with collector.overlap=false")

    import train as train_recipe
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
    from stable_baselines3.dqn import DQN
    from torchrl.collectors import Collector
    from torchrl.envs import EnvBase
    from torchrl.envs.utils import _StepMDP

    from torchrl_causal.envs.gym_registration import DroneNavGymEnv
    from torchrl_causal.modules import EGreedyQValuePolicy
    from torchrl_causal.training import DQNLoop

    def env_phases(c):
        return [c.label(EnvBase, "step", "env"), c.label(EnvBase, "reset", "env"),
                c.label(EnvBase, "rand_action", "acting")]

    loop = _CallCounter()
    run = DQNLoop.run

    def counted_run(self, *args, **kwargs):
        with loop.counting():
            return run(self, *args, **kwargs)

    with contextlib.ExitStack() as stack:
        for patch in (*env_phases(loop), loop.label(EGreedyQValuePolicy, "forward", "acting"),
                      loop.label(DQNLoop, "_ingest", "store"),
                      loop.label(DQNLoop, "_optimise", "update"),
                      loop.label(_StepMDP, "__call__", "step_mdp"),
                      loop.label(Collector, "_postproc", "postproc")):
            stack.enter_context(patch)
        stack.enter_context(contextlib.redirect_stdout(io.StringIO()))
        stack.enter_context(mock.patch.object(DQNLoop, "run", counted_run))
        train_recipe.train(cfg)
    sb3 = _CallCounter()
    env = sb3_env(cfg)
    model = sb3_model(cfg, env, int(cfg.seed))
    with contextlib.ExitStack() as stack:
        for patch in (*env_phases(sb3), sb3.label(OffPolicyAlgorithm, "_sample_action", "acting"),
                      sb3.label(DQN, "train", "update"),
                      sb3.label(DroneNavGymEnv, "step", "gym_wrapper"),
                      sb3.label(DroneNavGymEnv, "reset", "gym_wrapper")):
            stack.enter_context(patch)
        with sb3.counting():
            model.learn(total_timesteps=frames)
    env.close()

    def per(counter):
        return {k: round(v / frames, 1) for k, v in counter.most_common() if v / frames >= 0.05}

    def phase_top(counter, phase):
        return [[f, round(n / frames, 1)] for f, n in counter.by(2, phase).most_common(top)]

    lt, st = sum(loop.calls.values()), sum(sb3.calls.values())
    lf, sf = loop.by(2), sb3.by(2)
    extra = sorted(set(lf) | set(sf), key=lambda k: (sf[k] - lf[k], k))[:top]  # ties by name
    return {"dqnloop_total": round(lt / frames, 1), "sb3_total": round(st / frames, 1),
            "ratio_dqnloop_over_sb3": round(lt / max(1, st), 3),
            "dqnloop_by_phase": per(loop.by(0)), "sb3_by_phase": per(sb3.by(0)),
            "dqnloop_by_package": per(loop.by(1)), "sb3_by_package": per(sb3.by(1)),
            "dqnloop_more_than_sb3": [[k, round(lf[k] / frames, 1), round(sf[k] / frames, 1)]
                                      for k in extra if lf[k] > sf[k]],
            "dqnloop_top_in_rest": phase_top(loop, "rest"),
            "dqnloop_top_in_store": phase_top(loop, "store"),
            "sb3_top_in_rest": phase_top(sb3, "rest")}


def paired_ratio(ours, theirs) -> dict:
    """Per-repeat ratios ``ours[i] / theirs[i]`` (the runs of one repeat ran back to back,
    so a slow spell of the machine slows both), their geometric mean and its 95 % Student-t
    interval (on the log ratios; ``None`` with one repeat)."""
    import numpy as np
    from results import mean_ci95

    ratios = [o / t for o, t in zip(ours, theirs)]
    logs = np.log(np.asarray(ratios, dtype=float))
    mean, half = mean_ci95(logs[:, None])
    ci = (None if len(ratios) < 2 else
          [round(math.exp(mean[0] - half[0]), 3), round(math.exp(mean[0] + half[0]), 3)])
    return {"per_repeat": [round(r, 3) for r in ratios],
            "geomean": round(math.exp(mean[0]), 3), "ci95": ci}


def first_success(evals) -> int | None:
    return next((f for f, s in evals if s > 0), None)


def mean_ci(values):
    """Mean and 95 % t half-width (recipes/results.py's ``mean_ci95``; 0 for one value)."""
    import numpy as np
    from results import mean_ci95

    values = [v for v in values if v is not None]
    if not values:
        return None, None
    if len(values) == 1:
        return float(values[0]), 0.0
    mean, half = mean_ci95(np.asarray(values, dtype=float)[:, None])
    return float(mean[0]), float(half[0])


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=12000, help="frames per sample-efficiency run")
    p.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2])
    p.add_argument("--eval-every", type=int, default=1000)
    p.add_argument("--eval-episodes", type=int, default=3)
    p.add_argument("--speed-frames", type=int, default=3000,
                   help="frames per speed run (no evaluation); 0 skips the speed figure")
    p.add_argument("--repeats", type=int, default=2, help="speed runs per library, alternated")
    p.add_argument("--overheads", type=int, default=0,
                   help="frames per stepping run of the overheads figures (0: skip them)")
    p.add_argument("--calls", type=int, default=0,
                   help="frames per library of the calls-per-frame figure (0: skip it)")
    p.add_argument("--arms", nargs="+", default=list(SPEED_ARMS), metavar="ARM",
                   help=f"the speed figure's runs, each repeat (default: all of {SPEED_ARMS}; "
                        "dqnloop and sb3 always run)")
    p.add_argument("--train-freq", type=int, default=4,
                   help="frames collected between two optimisation phases, in both libraries "
                        "(the loop's collector.frames_per_batch, SB3's train_freq); each phase "
                        "takes train_freq x updates_per_frame gradient steps (default 4: SB3's "
                        "default, one step at the recipe's 0.25)")
    p.add_argument("--override", action="append", default=[],
                   help="a recipe override for every run of both libraries (repeatable), "
                        "e.g. loss.learning_starts=200")
    a = p.parse_args(argv)
    bad = [arm for arm in a.arms if arm not in SPEED_ARMS]
    if bad:
        p.error(f"--arms: unknown {bad}; choose from {SPEED_ARMS}")
    a.arms = sorted({"dqnloop", "sb3", *a.arms}, key=SPEED_ARMS.index)
    for name in ("frames", "eval_every", "eval_episodes", "repeats"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(a, name)}")
    for name in ("speed_frames", "overheads", "calls"):
        if getattr(a, name) < 0:
            p.error(f"--{name.replace('_', '-')} must be >= 0, got {getattr(a, name)}")
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        p.error("stable-baselines3 is not installed: pip install -e '.[bench]'")
    if a.train_freq < 1:
        p.error(f"--train-freq must be >= 1, got {a.train_freq}")
    with tempfile.TemporaryDirectory(prefix="vs_sb3_probe_") as tmp:
        try:
            sb3_schedule(recipe_config(1000, 0, 0, 1, Path(tmp), a.override, a.train_freq))
        except ValueError as e:
            p.error(str(e))
    import torch

    torch.set_num_threads(1)
    rows = []
    tf = a.train_freq
    with tempfile.TemporaryDirectory(prefix="vs_sb3_") as tmp:
        if a.speed_frames:
            # beside them, the loop with TorchRL's own DQNLoss (loss.stateful=false: the same
            # numbers with per-call parameter swaps) and the loop acting through
            # TensorDictSequential(actor, explorer) (collector.fused_acting=false: the same
            # actions, three tensordict modules a call)
            variants = {"dqnloop": [], "dqnloop_dqnloss": ["loss.stateful=false"],
                        "dqnloop_sequential_acting": ["collector.fused_acting=false"],
                        "dqnloop_fused_adam": ["optim.fused=auto"]}
            variants = {k: v for k, v in variants.items() if k in a.arms}
            sb3_arms = {k: k == "sb3_fused_adam" for k in ("sb3", "sb3_fused_adam")
                        if k in a.arms}
            fps = {k: [] for k in (*variants, *sb3_arms)}
            starts = min(1000, a.speed_frames // 3)
            for r in range(a.repeats):
                # eval.episodes=0: the loop's timed part then holds no greedy episodes
                # (it evaluates once when the budget ends); SB3's timed learn() holds none
                cfgs = {name: recipe_config(a.speed_frames, 0, 0, 1,
                                            Path(tmp) / f"speed{r}_{name}",
                                            [f"loss.learning_starts={starts}", "eval.episodes=0",
                                             *extra, *a.override], tf)
                        for name, extra in variants.items()}
                for name, cfg in cfgs.items():
                    fps[name].append(run_dqnloop(cfg)["fps"])
                for name, fused in sb3_arms.items():
                    fps[name].append(run_sb3(cfgs["dqnloop"], 0, 0, 1, fused=fused)["fps"])
            med = {k: statistics.median(v) for k, v in fps.items()}
            rows.append({"bench": "vs_sb3", "figure": "frames_per_second",
                         "frames": a.speed_frames, "repeats": a.repeats, "train_freq": tf,
                         **{k: [round(v, 1) for v in fps[k]] for k in fps},
                         **{f"{k}_median": round(v, 1) for k, v in med.items()},
                         **{f"ratio_{k}_over_{b}": round(med[k] / med[b], 3)
                            for k in variants for b in sb3_arms},
                         **{f"paired_{k}_over_{b}": paired_ratio(fps[k], fps[b])
                            for k in variants for b in sb3_arms},
                         **{f"paired_dqnloop_over_{k}": paired_ratio(fps["dqnloop"], fps[k])
                            for k in variants if k != "dqnloop" and "dqnloop" in variants}})
            print(json.dumps(rows[-1]), flush=True)
        if a.overheads:
            cfg = recipe_config(a.overheads, 0, 0, 1, Path(tmp) / "overheads", a.override, tf)
            runs = [stepping_fps(cfg, a.overheads) for _ in range(a.repeats)]
            rows.append({"bench": "vs_sb3", "figure": "stepping", "frames": a.overheads,
                         "unit": "frames/s", **{k: [r[k] for r in runs] for k in runs[0]}})
            print(json.dumps(rows[-1]), flush=True)
            rows.append({"bench": "vs_sb3", "figure": "update", "unit": "ms",
                         "updates": max(1, a.overheads // 4), "batch": int(cfg.buffer.batch_size),
                         **update_ms(cfg, max(1, a.overheads // 4))})
            print(json.dumps(rows[-1]), flush=True)
        if a.calls:
            starts = min(1000, a.calls // 3)
            cfg = recipe_config(a.calls, 0, 0, 1, Path(tmp) / "calls",
                                [f"loss.learning_starts={starts}", "eval.episodes=0",
                                 "eval.final_episodes=0", *a.override], tf)
            rows.append({"bench": "vs_sb3", "figure": "calls_per_frame", "frames": a.calls,
                         "unit": "Python function calls per frame",
                         **call_counts(cfg, a.calls)})
            print(json.dumps(rows[-1]), flush=True)
        results = {"dqnloop": [], "sb3": []}
        for seed in a.seeds:
            cfg = recipe_config(a.frames, seed, a.eval_every, a.eval_episodes,
                                Path(tmp) / f"seed{seed}", a.override, tf)
            results["dqnloop"].append(run_dqnloop(cfg))
            results["sb3"].append(run_sb3(cfg, seed, a.eval_every, a.eval_episodes))
        for lib, runs in results.items():
            if not runs:
                continue
            firsts = [first_success(r["evals"]) for r in runs]
            m, h = mean_ci([f if f is not None else a.frames for f in firsts])
            fm, fh = mean_ci([r["final"] for r in runs])
            rows.append({"bench": "vs_sb3", "figure": "first_success", "library": lib,
                         "frames": a.frames, "seeds": a.seeds,
                         "first_greedy_success_frames": firsts,
                         "first_success_mean": m, "first_success_ci95": h,
                         "final_success": [r["final"] for r in runs],
                         "final_success_mean": fm, "final_success_ci95": fh,
                         "frames_per_second": [round(r["fps"], 1) for r in runs]})
            print(json.dumps(rows[-1]), flush=True)
    return rows


if __name__ == "__main__":
    main()
