"""Thesis Algorithm 1: the DQN training loop, with a CBN gate and the causal-learning hook.

:class:`DQNLoop` runs Alg. 1 for any TorchRL env with a categorical action
spec, any Q-network in a :class:`~torchrl.modules.QValueActor`, and any
explorer that steps an epsilon (:class:`~torchrl_causal.modules.CBNGate` for
the causal variants, :class:`~torchrl.modules.EGreedyModule` for the plain
DQN). Per collected frame it

1. acts: the actor proposes, the explorer (gate) explores, vetoes or replaces
   (Alg. 3 / 4), and the gate's epsilon is annealed;
2. stores the transition in a :class:`~torchrl.data.TensorDictReplayBuffer`
   whose transform (a :class:`~torchrl_causal.data.CausalLearningHook`) feeds
   the causal learner and relearns the CBNs every ``k`` frames (Alg. 2);
3. takes ``updates_per_frame`` minibatch steps of :class:`~torchrl.objectives.DQNLoss`
   (by default its swap-free form, :class:`~torchrl_causal.training.StatefulDQNLoss`)
   and syncs the target network (:class:`~torchrl.objectives.HardUpdate`);
4. evaluates the greedy policy every ``eval_interval_frames`` and writes a
   checkpoint every ``checkpoint_interval_frames`` (at an episode end).

What a run folder (``output_dir``) holds: ``episodes.csv`` (reward, length,
success, crash, epsilon, relearns and the gate's branch shares of every
training episode), ``eval.csv``, ``relearns.csv``, ``checkpoints/last.pt``
(+ the replay buffer of that checkpoint) and, at the end, ``model.pt`` and
``explorer.pt`` (the final policy: the actor's and the explorer's states).

**Exact resume.** ``run(resume=True)`` continues from ``checkpoints/last.pt``
and produces the same run as an uninterrupted one -- also after a
``kill -9`` at any moment: checkpoints are written atomically (the buffer to a
new folder, then ``last.pt`` by rename), the CSVs are cut back to the
checkpoint's rows, and right after every checkpoint both runs reseed and
reset the env. This holds with ``hook.background=False``; with a batched env
(``SerialEnv`` / ``ParallelEnv``, ``batch_size=(num_envs,)``) checkpoints
come at batch ends and cut the episodes in flight, in the uninterrupted run as
in the resumed one.

**Overlap** (``LoopConfig.overlap=True``, opt-in): a worker thread collects
the next batch while the main thread optimises on the last one; the acting
copy of the Q-network lags the learner by one batch. Runs stay deterministic
and resume exactly (see :doc:`/training`). The collector acts
under ``torch.inference_mode`` in both modes.

See :doc:`/training` for a walk-through and :doc:`/tutorial_gridnav` for a measured example.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import random
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from torchrl_causal.data.checkpoint import install_filled_rows_checkpointer
from torchrl_causal.modules.acting import acting_policy
from torchrl_causal.training.evaluation import OUTCOME_KEYS, evaluate, seed_transforms
from torchrl_causal.training.optim import dqn_optimizer
from torchrl_causal.training.records import EpisodeCSV, atomic_save, rng_state, set_rng_state

__all__ = ["DQNLoop", "LoopConfig", "RUN_FILES"]

#: Files and folders of a run folder, relative to it.
RUN_FILES = {
    "episodes": "episodes.csv",
    "eval": "eval.csv",
    "relearns": "relearns.csv",
    "checkpoint": "checkpoints/last.pt",
    "buffer": "checkpoints/buffer",  # + _<n>: the replay buffer of checkpoint n
    "model": "model.pt",  # the final policy's actor (Q-network) state
    "explorer": "explorer.pt",  # ... and its explorer's (the CBN gate with its tables)
}
LOSS_FUNCTIONS = ("l2", "smooth_l1", "l1")
_GATE_BRANCHES = ("explored", "consulted", "vetoed", "replaced")


@dataclass
class LoopConfig:
    """Settings of :class:`DQNLoop` (the defaults are the library's tested ones).

    Args:
        total_frames: training frames (env steps), an upper bound.
        total_episodes: stop after this many training episodes (``None``: no limit).
        frames_per_batch: env steps per collector batch (1: the thesis's DQN).
        init_random_frames: uniformly random frames collected first (counted in the budget).
        buffer_size: replay memory, in frames (the default buffer only).
        batch_size: minibatch size.
        learning_starts: frames stored before the first gradient step.
        updates_per_frame: gradient steps per collected frame (the replay ratio, > 0).
        target_update_interval: gradient steps between hard target-network updates.
        gamma: discount (the default loss only).
        loss_function: ``"smooth_l1"`` (Huber), ``"l2"`` (thesis) or ``"l1"`` (the default loss only).
        double_dqn: Double DQN targets (the default loss only).
        lr: Adam learning rate (the default optimiser only).
        max_grad_norm: gradient-norm clip (``None``: no clip).
        reward_scale: rewards are multiplied by this inside the loss only.
        eval_interval_frames: frames between greedy evaluations (0: only at the end).
        eval_episodes: episodes of a periodic evaluation (0: none).
        eval_fixed_seed: every periodic evaluation replays the same episodes
            (one fixed seed: a fixed validation set, so ``keep_best`` compares
            policies on equal terms) instead of new ones each time.
        final_eval_episodes: episodes per evaluation env after training (0: none).
        eval_max_steps: step limit of an evaluation episode (``None``: the env's
            ``max_steps``, else 1000).
        keep_best: end with the best periodic evaluation's snapshot (ties go to
            the later one) instead of the last weights.
        checkpoint_interval_frames: frames between checkpoints, written at the
            next episode end (0: only at the end).
        stop_after_frames: stop, as if killed, after the first checkpoint at or
            past this frame (``None``: run to the end).
        keep_final_buffer: keep a copy of the replay buffer in the finished run's
            checkpoint, so the run can be extended later (default False: a
            finished run keeps none, and its disk holds one buffer at most -- a
            memmap storage's own files). Mid-run checkpoints write the buffer's
            filled rows only, file to file
            (:class:`~torchrl_causal.data.FilledRowsCheckpointer`, installed on
            a storage that has TorchRL's default checkpointer).
        seed: seeds torch, NumPy, Python, the env, its transforms and the evaluations.
        overlap: collect the next batch in a worker thread while the main thread
            optimises on the last one (opt-in; see :class:`DQNLoop`). The acting
            policy then lags the learner by one batch: a semantic change against
            thesis Alg. 1, deterministic and exactly resumable like the default.
        device: where the network, the buffer samples and the gate run
            (the env stays where it is).
        progress: show a tqdm bar.
        fused_acting: the collector acts with
            :class:`~torchrl_causal.modules.EGreedyQValuePolicy` (the actor and
            explorer computed on tensors) where the actor is a ``QValueActor`` and
            the explorer an ``EGreedyModule``; the same actions bit for bit as
            ``TensorDictSequential(actor, explorer)``, which ``False`` uses
            (implementation choice, kept for side-by-side timing).

    Raises:
        ValueError: naming the field and its value, for a bad setting.

    Example:
        >>> LoopConfig(total_frames=5000).updates_per_frame
        0.5
        >>> LoopConfig(updates_per_frame=0)
        Traceback (most recent call last):
        ...
        ValueError: Invalid LoopConfig.updates_per_frame=0: expected a number > 0 (gradient steps per frame)
    """

    total_frames: int = 20_000
    total_episodes: int | None = None
    frames_per_batch: int = 1
    init_random_frames: int = 0
    buffer_size: int = 20_000
    batch_size: int = 32
    learning_starts: int = 1000
    updates_per_frame: float = 0.5
    target_update_interval: int = 250
    gamma: float = 0.95
    loss_function: str = "smooth_l1"
    double_dqn: bool = True
    lr: float = 3e-4
    max_grad_norm: float | None = 10.0
    reward_scale: float = 1.0
    eval_interval_frames: int = 2000
    eval_episodes: int = 5
    eval_fixed_seed: bool = False
    final_eval_episodes: int = 20
    eval_max_steps: int | None = None
    keep_best: bool = True
    checkpoint_interval_frames: int = 3000
    stop_after_frames: int | None = None
    keep_final_buffer: bool = False
    seed: int = 0
    device: str = "cpu"
    progress: bool = False
    overlap: bool = False
    fused_acting: bool = True

    def __post_init__(self):
        def bad(name, expected):
            raise ValueError(
                f"Invalid LoopConfig.{name}={getattr(self, name)!r}: expected {expected}"
            )

        def is_int(v):
            return isinstance(v, int) and not isinstance(v, bool)

        def is_num(v):
            return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

        for name in ("total_frames", "frames_per_batch", "buffer_size", "batch_size",
                     "target_update_interval"):
            if not (is_int(getattr(self, name)) and getattr(self, name) > 0):
                bad(name, "an int > 0")
        for name in ("init_random_frames", "learning_starts", "eval_interval_frames",
                     "eval_episodes", "final_eval_episodes", "checkpoint_interval_frames", "seed"):
            if not (is_int(getattr(self, name)) and getattr(self, name) >= 0):
                bad(name, "an int >= 0")
        for name in ("total_episodes", "stop_after_frames", "eval_max_steps"):
            v = getattr(self, name)
            if v is not None and not (is_int(v) and v > 0):
                bad(name, "None or an int > 0")
        if not (is_num(self.updates_per_frame) and self.updates_per_frame > 0):
            bad("updates_per_frame", "a number > 0 (gradient steps per frame)")
        if not (is_num(self.gamma) and 0 <= self.gamma <= 1):
            bad("gamma", "a discount in [0, 1]")
        if not (is_num(self.lr) and self.lr > 0):
            bad("lr", "a number > 0")
        if not (is_num(self.reward_scale) and self.reward_scale > 0):
            bad("reward_scale", "a number > 0")
        if self.max_grad_norm is not None and not (is_num(self.max_grad_norm)
                                                   and self.max_grad_norm > 0):
            bad("max_grad_norm", "None or a number > 0")
        if self.loss_function not in LOSS_FUNCTIONS:
            bad("loss_function", f"one of {LOSS_FUNCTIONS}")
        for name in ("double_dqn", "keep_best", "progress", "keep_final_buffer", "overlap",
                     "eval_fixed_seed", "fused_acting"):
            if not isinstance(getattr(self, name), bool):
                bad(name, "True or False")
        try:
            dev = torch.device(self.device)
        except (RuntimeError, TypeError):
            bad("device", "'cpu' or 'cuda' (or 'cuda:<index>')")
        if dev.type not in ("cpu", "cuda"):
            bad("device", "'cpu' or 'cuda' (or 'cuda:<index>')")
        if dev.type == "cuda" and not torch.cuda.is_available():
            bad("device", "'cpu' on this machine (torch.cuda.is_available() is False)")
        if self.learning_starts >= self.total_frames:
            bad("learning_starts", f"fewer frames than total_frames={self.total_frames} "
                "(no gradient step would run)")
        updates = int((self.total_frames - self.learning_starts) * self.updates_per_frame)
        if self.target_update_interval > updates:
            bad("target_update_interval",
                f"at most the run's {updates} gradient steps ((total_frames - learning_starts) "
                "x updates_per_frame): the target network would never be updated")


class _NoRecords:
    """Stands in for :class:`EpisodeCSV` when a loop has no run folder."""

    def __init__(self):
        self.n_rows = 0

    def write(self, row):
        self.n_rows += 1

    def truncate(self, n_rows):
        self.n_rows = n_rows


class _ForwardTimer:
    """Wall time spent in a module's forward calls (forward pre/post hooks)."""

    def __init__(self, module):
        self.seconds = 0.0
        self._t0 = 0.0
        self._handles = [
            module.register_forward_pre_hook(self._pre),
            module.register_forward_hook(self._post),
        ]

    def _pre(self, *_):
        self._t0 = time.perf_counter()

    def _post(self, *_):
        self.seconds += time.perf_counter() - self._t0

    def remove(self):
        for h in self._handles:
            h.remove()


def _check_categorical(env) -> int:
    from torchrl.data import Categorical, OneHot

    spec = env.action_spec_unbatched
    if not isinstance(spec, (Categorical, OneHot)):
        raise ValueError(
            f"DQNLoop needs an env with a categorical action spec (Categorical or OneHot), "
            f"got {type(spec).__name__}: {spec}"
        )
    return int(spec.space.n)


def _peak_rss_mb() -> float | None:
    """This process's peak resident memory (MiB), where the OS reports it."""
    try:
        import resource
    except ImportError:  # pragma: no cover - not on Windows
        return None
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(kb / 1024.0, 1)


def _collect(batches):
    """The collector's next batch, acted under ``torch.inference_mode``.

    The Collector already acts under ``no_grad``; inference mode also skips
    version counting and view tracking: 8 % less time per collected frame of the
    thesis scene (8.61 -> 7.91 ms, cbn_v2, measured A/B interleaved). The
    batch's tensors are inference tensors; the loop only reads them (the replay
    buffer copies them into its storage).
    """
    with torch.inference_mode():
        return next(batches)


def _storage_device(replay_buffer) -> torch.device:
    """Where a replay buffer's storage samples its indices (its generator's device)."""
    dev = getattr(getattr(replay_buffer, "_storage", None), "device", None)
    try:
        return torch.device(dev) if dev not in (None, "auto") else torch.device("cpu")
    except (RuntimeError, TypeError):
        return torch.device("cpu")


def _num_envs(env) -> int:
    shape = tuple(env.batch_size)
    if len(shape) > 1:
        raise ValueError(f"DQNLoop takes an env with batch_size () or (num_envs,), got {shape}")
    return shape[0] if shape else 1


class DQNLoop:
    """Thesis Algorithm 1 for any env: collect, gate, store, learn CBNs, update, evaluate.

    See the module docs for what each step does, what the run folder holds and
    why resume is exact.

    Args:
        env: the training env (TorchRL ``EnvBase``) with a categorical action
            spec; for a gated run it writes the schema's ``causal_state``
            (e.g. through :class:`~torchrl_causal.transforms.Discretize`).
        actor: a :class:`~torchrl.modules.QValueActor` (writes ``action_value``
            and a greedy ``action``).
        explorer: the module placed after the actor: a
            :class:`~torchrl_causal.modules.CBNGate` or an
            :class:`~torchrl.modules.EGreedyModule` (anything with ``step(n)``).
        config: a :class:`LoopConfig` (default: ``LoopConfig()``).
        hook: the :class:`~torchrl_causal.data.CausalLearningHook` that feeds
            the causal learner (``None`` for a plain DQN). Appended to the
            replay buffer's transforms (unless the buffer already has it).
        loss: a :class:`~torchrl.objectives.DQNLoss` (default: a
            :class:`~torchrl_causal.training.StatefulDQNLoss`, the same loss bit for bit,
            built on ``actor`` from the config's ``loss_function``, ``double_dqn``, ``gamma``).
        optimizer: over ``loss.parameters()`` (default: Adam with ``config.lr``; pass
            ``dqn_optimizer(loss.parameters(), lr=..., fused=None)`` for PyTorch's fused
            kernel: :func:`~torchrl_causal.training.dqn_optimizer`).
        replay_buffer: a :class:`~torchrl.data.TensorDictReplayBuffer` (default:
            ``LazyTensorStorage(config.buffer_size)`` on ``config.device``).
        eval_envs: ``{name: env or zero-argument factory}``; the first is
            evaluated periodically (and decides ``keep_best``), all of them
            after training. ``None``: no evaluation.
        output_dir: the run folder (``None``: nothing is written; no resume).
        logger: a TorchRL logger (``log_scalar``), optional.
        store_keys: keys kept in the replay buffer (default: the actor's inputs
            at ``t`` and ``t+1``, the action, reward, done and terminated flags,
            and the hook's causal states).
        outcome_keys: overrides of :data:`~torchrl_causal.training.evaluation.OUTCOME_KEYS`
            (which ``("next", key)`` means success, crash, out of bounds).
        guards: modules placed after the explorer when acting, in collection and
            evaluation (e.g. :class:`~torchrl_causal.modules.LoopGuard`).

    Raises:
        ValueError: an env whose action spec is not categorical; a config that is not a
            :class:`LoopConfig`.

    Example:
        A CBN-gated DQN on CartPole, the pole angle and velocity discretised by
        a schema of your own:

        >>> import tempfile, torch
        >>> from torchrl.envs import GymEnv, TransformedEnv
        >>> from torchrl.modules import MLP, QValueActor
        >>> from torchrl_causal.causal import CausalLearner
        >>> from torchrl_causal.data import CausalLearningHook
        >>> from torchrl_causal.modules import CBNGate
        >>> from torchrl_causal.schema import Variable, VariableSchema
        >>> from torchrl_causal.training import DQNLoop, LoopConfig
        >>> from torchrl_causal.transforms import Discretize
        >>> schema = VariableSchema((
        ...     Variable("angle", ("left", "upright", "right"), bins=(-0.05, 0.05),
        ...              source="observation", index=2),
        ...     Variable("spin", ("left", "still", "right"), bins=(-0.3, 0.3),
        ...              source="observation", index=3)))
        >>> env = TransformedEnv(GymEnv("CartPole-v1"), Discretize(schema=schema))
        >>> actor = QValueActor(MLP(out_features=2, num_cells=[64]), in_keys=["observation"],
        ...                     spec=env.action_spec)
        >>> gate = CBNGate("v2", annealing_num_steps=500, seed=0)
        >>> hook = CausalLearningHook(CausalLearner(schema, n_actions=2), k=200, gates=[gate])
        >>> loop = DQNLoop(env, actor, gate, hook=hook, output_dir=tempfile.mkdtemp(),
        ...                config=LoopConfig(total_frames=600, learning_starts=200,
        ...                                  target_update_interval=50, eval_interval_frames=0,
        ...                                  final_eval_episodes=0, seed=0))
        >>> summary = loop.run()
        >>> summary["frames"], summary["n_relearns"] >= 2
        (600, True)
    """

    def __init__(
        self,
        env,
        actor,
        explorer,
        *,
        config: LoopConfig | None = None,
        hook=None,
        loss=None,
        optimizer: torch.optim.Optimizer | None = None,
        replay_buffer=None,
        eval_envs: Mapping[str, Any] | None = None,
        output_dir: str | Path | None = None,
        logger=None,
        store_keys: Sequence | None = None,
        outcome_keys: Mapping[str, str] | None = None,
        guards: Sequence = (),
    ):
        from tensordict.nn import TensorDictSequential
        from torchrl.objectives import HardUpdate

        from .loss import StatefulDQNLoss

        config = LoopConfig() if config is None else config
        if not isinstance(config, LoopConfig):
            raise ValueError(f"config must be a LoopConfig, got {type(config).__name__}")
        self.config = cfg = config
        self.n_actions = _check_categorical(env)
        self.num_envs = _num_envs(env)
        self.env, self.actor, self.explorer, self.hook = env, actor, explorer, hook
        self.guards = list(guards)
        self.policy = TensorDictSequential(actor, explorer, *self.guards)
        self.device = torch.device(cfg.device)
        if loss is None:
            loss = StatefulDQNLoss(actor, loss_function=cfg.loss_function, delay_value=True,
                                   double_dqn=cfg.double_dqn,
                                   action_space=env.action_spec_unbatched)
            loss.make_value_estimator(gamma=cfg.gamma)
        self.loss = loss
        self.optimizer = optimizer or dqn_optimizer(loss.parameters(), lr=cfg.lr)
        self.updater = HardUpdate(loss, value_network_update_interval=cfg.target_update_interval)
        self.output_dir = Path(output_dir).expanduser().resolve() if output_dir else None
        self.paths = ({k: self.output_dir / v for k, v in RUN_FILES.items()}
                      if self.output_dir else None)
        if replay_buffer is None:
            from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

            replay_buffer = TensorDictReplayBuffer(
                storage=LazyTensorStorage(cfg.buffer_size, device=self.device),
                batch_size=cfg.batch_size,
            )
        # mid-run checkpoints write the buffer's filled rows, file to file (TorchRL's
        # default copies the full capacity through memory maps: 2x a memmap buffer)
        install_filled_rows_checkpointer(replay_buffer)
        present = getattr(replay_buffer, "_transform", None) or []
        if hook is not None and not any(t is hook for t in present):
            replay_buffer.append_transform(hook)  # once, also when the buffer already has it
        self.replay_buffer = replay_buffer
        self._acting_actor, self._rb_rng, self._synced_at = None, None, None
        # the collector acts with the same policy, computed on tensors where the actor is a
        # QValueActor and the explorer an EGreedyModule (the same actions bit for bit)
        act = acting_policy if cfg.fused_acting else TensorDictSequential
        self.collector_policy = act(actor, explorer, *self.guards)
        self._loss_forward = loss
        if cfg.overlap:
            # TorchRL's LossModule.forward sets the process-global exploration type
            # (DETERMINISTIC) while it runs: beside a worker thread whose explorer reads
            # that global, the loop calls the loss's own forward (for a DQN loss on a
            # feed-forward Q-network, the same arithmetic)
            raw = getattr(type(loss).forward, "__wrapped__", None)
            if raw is not None:
                self._loss_forward = functools.partial(raw, loss)
            # the worker thread acts with its own copy of the Q-network (the main
            # thread updates the learner's in place meanwhile) and the buffer samples
            # with its own generator (the worker may draw from the global RNG)
            self._acting_actor = copy.deepcopy(actor).requires_grad_(False)
            self.collector_policy = act(self._acting_actor, explorer, *self.guards)
            self._rb_rng = torch.Generator(device=_storage_device(replay_buffer))
            replay_buffer.set_rng(self._rb_rng)
        self.eval_envs = dict(eval_envs or {})
        self.logger = logger
        self.outcome_keys = {**OUTCOME_KEYS, **(outcome_keys or {})}
        self.store_keys = list(store_keys) if store_keys is not None else self._default_keys()
        prefix = getattr(explorer, "diagnostics_prefix", None)
        self.gate_keys = [f"{prefix}{b}" for b in _GATE_BRANCHES] if prefix else []
        self.best: dict | None = None
        self._collector = None
        self.state = {
            "frames": 0, "episodes": 0, "updates": 0, "update_budget": 0.0,
            "next_eval": cfg.eval_interval_frames or math.inf,
            "next_ckpt": cfg.checkpoint_interval_frames or math.inf,
            "n_ckpt": 0, "n_relearns": 0, "n_evals": 0, "successes": [],
            "time_extend": 0.0, "time_train": 0.0, "time_collect": 0.0,
            "time_collect_worker": 0.0,
        }
        self._episodes = [self._new_episode() for _ in range(self.num_envs)]

    # ------------------------------------------------------------------ set-up
    def _default_keys(self) -> list:
        keys = []
        for k in getattr(self.actor, "in_keys", []):
            keys += [k, ("next", k) if isinstance(k, str) else ("next", *k)]
        keys += ["action", ("next", "reward"), ("next", "done"), ("next", "terminated")]
        if self.hook is not None:
            keys += [self.hook.causal_state_key, self.hook.next_causal_state_key]
        unique = []
        for k in keys:
            if k not in unique:
                unique.append(k)
        return unique

    def _new_episode(self) -> dict:
        return {"reward": 0.0, "length": 0, "gate": {k: 0.0 for k in self.gate_keys}}

    def _records(self):
        if self.paths is None:
            return _NoRecords(), _NoRecords(), _NoRecords()
        self.paths["checkpoint"].parent.mkdir(parents=True, exist_ok=True)
        gate_cols = [f"gate_frac_{b}" for b in _GATE_BRANCHES] if self.gate_keys else []
        episodes = EpisodeCSV(
            self.paths["episodes"],
            ["episode", "frames", "reward", "length", "success", "crash", "out_of_bounds",
             "epsilon", "n_relearns"] + gate_cols,
        )
        evals = EpisodeCSV(
            self.paths["eval"],
            ["frames", "episodes", "layout", "success_rate", "mean_reward", "collisions",
             "out_of_bounds", "mean_length", "steps_to_goal", "spl", "oracle_steps"],
        )
        relearns = EpisodeCSV(self.paths["relearns"], ["relearn", "frames", "episode"])
        return episodes, evals, relearns

    def _eval_env(self, name):
        env = self.eval_envs[name]
        if callable(env) and not hasattr(env, "rollout"):
            env = self.eval_envs[name] = env()
        return env

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Everything a resumed run needs (but the replay buffer, saved beside it)."""
        c = self._collector
        return {
            "loop": dict(self.state),
            "episodes": copy.deepcopy(self._episodes),
            "loss": self.loss.state_dict(),
            "optim": self.optimizer.state_dict(),
            "updater_counter": self.updater.counter,
            "explorer": self.explorer.state_dict(),
            "hook": self.hook.state_dict() if self.hook is not None else None,
            "collector": ({k: v for k, v in c.state_dict().items()
                           if k in ("frames", "iter", "traj_pool")} if c is not None else None),
            "logger": (self.logger.state_dict()
                       if self.logger is not None and hasattr(self.logger, "state_dict") else None),
            "rows": {name: rec.n_rows for name, rec in zip(
                ("episodes", "eval", "relearns"), self._recs)},
            "rng": rng_state(),
            "best": self.best,
            "config": dataclasses.asdict(self.config),
            "acting_actor": (self._acting_actor.state_dict()
                             if self._acting_actor is not None else None),
            "buffer_rng": self._rb_rng.get_state() if self._rb_rng is not None else None,
        }

    def _save_checkpoint(self, final: bool = False) -> None:
        # The buffer goes to a new folder; last.pt (written atomically after it)
        # names it, and older folders are removed only then: a kill at any point
        # leaves a consistent last.pt + buffer pair. A finished run's checkpoint
        # keeps no copy of the buffer unless keep_final_buffer is set.
        if self.paths is None:
            return
        name = None
        if not final or self.config.keep_final_buffer:
            buffer_dir = self.paths["buffer"].with_name(f"buffer_{self.state['n_ckpt']}")
            self.replay_buffer.dumps(buffer_dir)
            name = buffer_dir.name
        atomic_save({**self.state_dict(), "buffer_dir": name}, self.paths["checkpoint"])
        for old in self.paths["buffer"].parent.glob("buffer_*"):
            if old.is_dir() and old.name != name and old.name != "buffer_storage":
                shutil.rmtree(old, ignore_errors=True)

    def _load_checkpoint(self) -> None:
        ckpt = torch.load(self.paths["checkpoint"], weights_only=False)
        finished = ckpt["loop"]["frames"] >= self.config.total_frames
        if ckpt.get("buffer_dir") is None and not finished:
            raise ValueError(  # a finished run extended to a larger budget
                f"Cannot resume from {self.paths['checkpoint']}: the run finished and its final "
                "checkpoint keeps no replay buffer (LoopConfig.keep_final_buffer=False); start a "
                "new run, or set keep_final_buffer=True to extend finished runs later"
            )
        # a run that finished training but was stopped before its final evaluation
        # ended (its summary never written): everything but the buffer is restored,
        # and run() goes straight to the final evaluation
        self._resumed_finished = ckpt.get("buffer_dir") is None
        was_overlap = ckpt.get("config", {}).get("overlap", False)
        if was_overlap != self.config.overlap:
            raise ValueError(
                f"Cannot resume from {self.paths['checkpoint']} with LoopConfig.overlap="
                f"{self.config.overlap}: the run was written with overlap={was_overlap} "
                "(resume with the same setting)"
            )
        self.state.update(ckpt["loop"])
        self._episodes = ckpt["episodes"]
        self.loss.load_state_dict(ckpt["loss"])
        self.optimizer.load_state_dict(ckpt["optim"])
        self.updater.counter = ckpt["updater_counter"]
        self.explorer.load_state_dict(ckpt["explorer"])
        if ckpt.get("buffer_dir") is not None:
            self.replay_buffer.loads(self.paths["checkpoint"].parent / ckpt["buffer_dir"])
        if self.hook is not None:
            self.hook.load_state_dict(ckpt["hook"])
        if ckpt["collector"] is not None:
            self._collector.load_state_dict(ckpt["collector"], strict=False)
        # episodes in flight at the checkpoint are dropped: right after a checkpoint
        # the uninterrupted run resets the envs too (_restart_collector)
        self._episodes = [self._new_episode() for _ in range(self.num_envs)]
        for rec, name in zip(self._recs, ("episodes", "eval", "relearns")):
            rec.truncate(ckpt["rows"][name])
        if self.logger is not None and ckpt["logger"] is not None and hasattr(
                self.logger, "load_state_dict"):
            self.logger.load_state_dict(ckpt["logger"])
        set_rng_state(ckpt["rng"])
        if self._acting_actor is not None:
            self._acting_actor.load_state_dict(ckpt["acting_actor"])
            self._synced_at = None
            self._rb_rng.set_state(ckpt["buffer_rng"])
            self.replay_buffer.set_rng(self._rb_rng)
        self.best = ckpt["best"]

    def _restart_collector(self) -> None:
        # With one env, checkpoints fall on episode ends. Right after one (in the
        # uninterrupted run as in the resumed one) the env is reseeded and reset,
        # so both runs continue from the same state; with several envs the
        # episodes in flight are cut there, in both runs alike.
        self._episodes = [self._new_episode() for _ in range(self.num_envs)]
        seed = self.config.seed * 7919 + 104729 * self.state["n_ckpt"]
        self._collector.set_seed(seed)
        seed_transforms(self.env, seed)
        with torch.inference_mode():  # the collector's buffers are inference tensors
            self._collector.reset()

    # ------------------------------------------------------------------ steps
    def _record_episodes(self, batch, n_envs: int, steps: int) -> bool:
        """Running sums -> one ``episodes.csv`` row per finished episode.

        ``batch`` holds ``n_envs * steps`` frames laid out as ``[envs, time]`` (any
        shape of that many elements in that order: only the few keys read here
        are reshaped, never the whole tensordict); steps are taken in collection
        order (time, then env). Returns True when every env's last step ended an
        episode.
        """
        st, nxt = self.state, batch["next"]
        frames0 = st["frames"] - n_envs * steps
        done = nxt["done"].reshape(n_envs, steps).tolist()
        rewards = nxt["reward"].reshape(n_envs, steps).tolist()
        gates = {k: batch[k].reshape(n_envs, steps).float().tolist() for k in self.gate_keys}
        raw = {c: nxt.get(key, None) for c, key in self.outcome_keys.items()}
        flags = {c: (v.reshape(n_envs, steps, -1).any(-1).tolist() if v is not None else None)
                 for c, v in raw.items()}
        for t in range(steps):
            for e in range(n_envs):
                ep = self._episodes[e]
                ep["reward"] += rewards[e][t]
                ep["length"] += 1
                for k in self.gate_keys:
                    ep["gate"][k] += gates[k][e][t]
                if not done[e][t]:
                    continue
                st["episodes"] += 1
                outcome = {c: bool(v[e][t]) if v is not None else False for c, v in flags.items()}
                st["successes"] = (st["successes"] + [int(outcome["success"])])[-50:]
                row = {"episode": st["episodes"], "frames": frames0 + (t + 1) * n_envs,
                       "reward": ep["reward"], "length": ep["length"], **outcome,
                       "epsilon": float(self.explorer.eps), "n_relearns": st["n_relearns"]}
                for k, b in zip(self.gate_keys, _GATE_BRANCHES):
                    row[f"gate_frac_{b}"] = ep["gate"][k] / ep["length"]
                self._recs[0].write(row)
                self._last_reward = ep["reward"]
                if self.logger is not None:
                    self.logger.log_scalar("train/episode_reward", ep["reward"], step=st["frames"])
                    self.logger.log_scalar("train/success", float(outcome["success"]),
                                           step=st["frames"])
                self._episodes[e] = self._new_episode()
        return all(row[-1] for row in done)

    def _optimise(self, n: int) -> None:
        """``updates_per_frame`` minibatch DQN steps per new frame, then target syncs."""
        cfg, st, rb = self.config, self.state, self.replay_buffer
        if len(rb) < max(cfg.learning_starts, cfg.batch_size):
            return
        st["update_budget"] += n * cfg.updates_per_frame
        while st["update_budget"] >= 1.0:
            st["update_budget"] -= 1.0
            sample = rb.sample(cfg.batch_size).to(self.device)
            if cfg.reward_scale != 1.0:  # the loss sees scaled rewards; the env's stay as defined
                sample.set(("next", "reward"), sample.get(("next", "reward")) * cfg.reward_scale)
            loss_td = self._loss_forward(sample)
            loss_td["loss"].backward()
            if cfg.max_grad_norm is not None:
                torch.nn.utils.clip_grad_norm_(self.loss.parameters(), cfg.max_grad_norm)
            self.optimizer.step()
            self.optimizer.zero_grad(set_to_none=True)
            self.updater.step()
            st["updates"] += 1
            if self.logger is not None and st["updates"] % 100 == 0:
                self.logger.log_scalar("train/loss", float(loss_td["loss"].detach()),
                                       step=st["frames"])

    def _ingest(self, batch) -> tuple[int, bool]:
        """A collected batch: frames, epsilon step, buffer (+ hook: Alg. 2), episode rows.

        Returns the batch's frame count and whether it ends at an episode end
        (always True with several envs: checkpoints then cut episodes in flight).
        """
        st = self.state
        n = batch.numel()  # laid out [envs, time]
        st["frames"] += n
        self.explorer.step(n)  # the gate's (or egreedy's) epsilon schedule
        t0 = time.perf_counter()
        # only the stored keys are flattened: reshaping the whole batch (images, depth,
        # every feature, twice with "next") cost more than the buffer write itself
        stored = batch.select(*self.store_keys)
        self.replay_buffer.extend(stored if stored.ndim == 1 else stored.reshape(-1))  # + hook
        st["time_extend"] += time.perf_counter() - t0
        if self.hook is not None and self.hook.learner.n_relearns > st["n_relearns"]:
            st["n_relearns"] = self.hook.learner.n_relearns
            self._recs[2].write({"relearn": st["n_relearns"], "frames": st["frames"],
                                 "episode": st["episodes"] + 1})
        at_episode_end = self._record_episodes(batch, self.num_envs, n // self.num_envs) \
            or self.num_envs > 1
        return n, at_episode_end

    def _finished(self) -> bool:
        cfg, st = self.config, self.state
        return st["frames"] >= cfg.total_frames or st["episodes"] >= (cfg.total_episodes
                                                                      or math.inf)

    def _after_update(self, n: int, at_episode_end: bool, pbar) -> tuple[bool, bool]:
        """Progress, periodic evaluation, checkpoint. Returns (end the loop, stopped early)."""
        cfg, st = self.config, self.state
        if pbar is not None:
            pbar.update(n)
            sr = np.mean(st["successes"]) if st["successes"] else float("nan")
            pbar.set_postfix(ep=st["episodes"], reward=f"{self._last_reward:.1f}",
                             success=f"{sr:.2f}", eps=f"{float(self.explorer.eps):.2f}",
                             refresh=False)
        finished = self._finished()
        if st["frames"] >= st["next_eval"] or finished:
            self._periodic_eval()
            while st["next_eval"] <= st["frames"]:
                st["next_eval"] += cfg.eval_interval_frames or math.inf
        if (st["frames"] >= st["next_ckpt"] and at_episode_end) or finished:
            st["n_ckpt"] += 1
            while st["next_ckpt"] <= st["frames"]:
                st["next_ckpt"] += cfg.checkpoint_interval_frames or math.inf
            self._save_checkpoint(final=finished)
            if not finished:
                self._restart_collector()
            if (cfg.stop_after_frames is not None and not finished
                    and st["frames"] >= cfg.stop_after_frames):
                return True, True
        return finished, False

    def _run_serial(self, collector, pbar) -> bool:
        """Alg. 1 as the thesis has it: collect a batch, store it, optimise, repeat."""
        st = self.state
        batches = iter(collector)
        while True:
            t_last = time.perf_counter()
            batch = _collect(batches)
            st["time_collect"] += time.perf_counter() - t_last
            n, at_episode_end = self._ingest(batch)
            t0 = time.perf_counter()
            self._optimise(n)
            st["time_train"] += time.perf_counter() - t0
            end, stopped_early = self._after_update(n, at_episode_end, pbar)
            if end:
                return stopped_early

    def _must_drain(self, at_episode_end: bool) -> bool:
        """Whether the batch just stored is followed by an evaluation, a checkpoint or the end.

        The pipeline then collects nothing ahead: evaluations use the explorer and
        the global exploration mode, and checkpoints reseed and reset the env,
        with the worker idle.
        """
        cfg, st = self.config, self.state
        if self._finished():
            return True
        if st["frames"] >= st["next_eval"] and cfg.eval_episodes > 0 and self.eval_envs:
            return True
        return st["frames"] >= st["next_ckpt"] and at_episode_end

    def _sync_acting(self) -> None:
        """The acting copy takes the learner's Q-network weights (when they changed)."""
        if self._synced_at != self.state["updates"]:
            self._acting_actor.load_state_dict(self.actor.state_dict())
            self._synced_at = self.state["updates"]

    def _run_overlapped(self, collector, pbar) -> bool:
        """A two-stage pipeline: a worker thread collects batch i+1 while this thread
        optimises on batch i.

        Per batch i: (a) wait for batch i from the worker; (b) store it (the hook
        relearns and swaps the gate's tables here, while the worker is idle);
        (c) copy the learner's weights into the acting copy and step epsilon
        (done in (b)); (d) start the worker on batch i+1 -- unless an evaluation,
        a checkpoint or the end follows batch i (then the pipeline drains);
        (e) optimise for batch i's frames. Batch i+1 is thus collected with the
        weights from before batch i's updates: the acting policy lags one batch.
        The worker alone draws from the global RNG (explorer, random frames,
        env); the buffer samples with its own generator, so runs are
        deterministic and resume exactly.
        """
        from concurrent.futures import ThreadPoolExecutor

        st = self.state
        batches = iter(collector)

        def collect():
            t0 = time.perf_counter()
            batch = _collect(batches)
            return batch, time.perf_counter() - t0

        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="DQNLoop-collector")
        future = None
        try:
            future = pool.submit(collect)
            while True:
                t0 = time.perf_counter()
                batch, worker_seconds = future.result()  # (a)
                future = None
                st["time_collect"] += time.perf_counter() - t0
                st["time_collect_worker"] += worker_seconds
                n, at_episode_end = self._ingest(batch)  # (b), epsilon step
                del batch
                self._sync_acting()  # (c)
                if not self._must_drain(at_episode_end):
                    future = pool.submit(collect)  # (d)
                t0 = time.perf_counter()
                self._optimise(n)  # (e), beside (d)
                st["time_train"] += time.perf_counter() - t0
                end, stopped_early = self._after_update(n, at_episode_end, pbar)
                if end:
                    return stopped_early
                if future is None:  # drained for an evaluation / checkpoint
                    future = pool.submit(collect)
        finally:
            if future is not None:  # an error here: let the worker finish its batch
                try:
                    future.result()
                except Exception:  # noqa: BLE001 - the main thread's error is raised
                    pass
            pool.shutdown(wait=True)

    def _periodic_eval(self) -> None:
        cfg, st = self.config, self.state
        if cfg.eval_episodes == 0 or not self.eval_envs:
            return
        st["n_evals"] += 1
        name = next(iter(self.eval_envs))
        n = 1 if cfg.eval_fixed_seed else st["n_evals"]  # fixed: the first evaluation's episodes
        res = evaluate(self.policy, self._eval_env(name), cfg.eval_episodes,
                       seed=cfg.seed * 1009 + 31 * n, outcome_keys=self.outcome_keys,
                       max_steps=cfg.eval_max_steps)
        self._recs[1].write({"frames": st["frames"], "episodes": st["episodes"], "layout": name,
                             **res})
        if self.logger is not None:
            for key, val in res.items():
                self.logger.log_scalar(f"eval_{name}/{key}", val, step=st["frames"])
        # keep_best: higher greedy success wins; ties go to the later policy
        if cfg.keep_best and (self.best is None
                              or res["success_rate"] >= self.best["result"]["success_rate"]):
            self.best = {"frames": st["frames"], "result": res,
                         "actor": copy.deepcopy(self.actor.state_dict()),
                         "explorer": copy.deepcopy(self.explorer.state_dict())}

    def final_evaluation(self) -> dict:
        """``final_eval_episodes`` greedy episodes on every evaluation env: ``{name: result}``.

        The episodes' own records (outcomes, steps, SPL and, over a ``DroneNavEnv``,
        the flown paths) are kept in ``self.final_episodes[name]``."""
        cfg, out = self.config, {}
        if cfg.final_eval_episodes == 0:
            return out
        self.final_episodes = {}
        for i, name in enumerate(self.eval_envs):
            out[name] = evaluate(self.policy, self._eval_env(name), cfg.final_eval_episodes,
                                 seed=10_000_019 + cfg.seed * 1009 + i,
                                 outcome_keys=self.outcome_keys, max_steps=cfg.eval_max_steps,
                                 per_episode=True)
            # per-episode records (paths, oracle plans) stay on the loop: flight maps
            self.final_episodes[name] = out[name].pop("episodes")
        return out

    # ------------------------------------------------------------------ run
    def run(self, resume: bool = False) -> dict:
        """Trains (or, with ``resume=True``, continues from the run folder's checkpoint).

        Returns:
            The run summary: ``frames``, ``episodes``, ``updates``, ``n_relearns``,
            ``stopped_early``, timings (``loop_seconds``, ``loop_frames_per_second``,
            ``optimisation_seconds``, ``collection_seconds``,
            ``causal_learning_seconds``, ``gating_seconds``), ``peak_rss_mb`` (the
            process's peak resident memory) and, when the run
            finished, ``final_eval`` and ``selected_frames`` (``keep_best``).

        Raises:
            ValueError: ``resume=True`` without a checkpoint in ``output_dir``.
        """
        from torchrl.collectors import Collector

        cfg, st = self.config, self.state
        if resume and (self.paths is None or not self.paths["checkpoint"].is_file()):
            where = self.paths["checkpoint"] if self.paths else "nowhere (output_dir=None)"
            raise ValueError(f"Cannot resume: there is no checkpoint at {where}")
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        random.seed(cfg.seed)
        self.env.set_seed(cfg.seed)
        seed_transforms(self.env, cfg.seed)
        self._collector = collector = Collector(
            self.env, self.collector_policy, frames_per_batch=cfg.frames_per_batch, total_frames=-1,
            init_random_frames=cfg.init_random_frames or None, device=self.device,
            # the policy is feed-forward: the collector must not add env transforms
            auto_register_policy_transforms=False,
            # episodes are cut by the done flags; trajectory ids are not read (and cost
            # about 0.15 ms a frame)
            track_traj_ids=False,
            # the loop reads each batch (buffer copy, episode rows) before asking for the
            # next one, so the collector's own tensordict is handed out, not a clone of
            # it (about 0.15 ms a frame less; the same runs, bit for bit)
            return_same_td=True,
        )
        self._recs = self._records()
        if not resume:
            # a fresh run replaces the folder's records: rows of an earlier start cut
            # short before its first checkpoint would otherwise stay ahead of this run's
            for rec in self._recs:
                rec.truncate(0)
        if cfg.overlap:  # a resumed run loads both from its checkpoint
            self._rb_rng.manual_seed(cfg.seed * 1_000_003 + 12_345)
            self._synced_at = None
            self._sync_acting()
        self._resumed_finished = False
        if resume:
            self._load_checkpoint()
            if not self._resumed_finished:
                self._restart_collector()
        hook = self.hook
        pbar = None
        if cfg.progress:
            from tqdm import tqdm

            pbar = tqdm(total=cfg.total_frames, initial=st["frames"], unit="frame",
                        dynamic_ncols=True, mininterval=1.0)
        gate_timer = _ForwardTimer(self.explorer) if hook is not None else None
        causal0 = hook.stats["add_seconds"] + hook.stats["relearn_seconds"] if hook else 0.0
        frames0, t_start = st["frames"], time.perf_counter()
        self._last_reward = float("nan")
        stopped_early = False
        try:
            if self._resumed_finished:
                pass  # trained already: only the final evaluation is left
            elif cfg.overlap:
                stopped_early = self._run_overlapped(collector, pbar)
            else:
                stopped_early = self._run_serial(collector, pbar)
        finally:
            if pbar is not None:
                pbar.close()
            collector.shutdown()
            if gate_timer is not None:
                gate_timer.remove()
        wall = time.perf_counter() - t_start
        summary = {
            "frames": st["frames"], "episodes": st["episodes"], "updates": st["updates"],
            "n_relearns": st["n_relearns"], "stopped_early": stopped_early,
            "output_dir": str(self.output_dir) if self.output_dir else None,
            # timings of this session's loop (a resumed run counts its own part)
            "loop_seconds": wall,
            "loop_frames_per_second": (st["frames"] - frames0) / wall if wall > 0 else None,
            "optimisation_seconds": st["time_train"],
            # policy (incl. gate) + env + features; with overlap: the main thread's wait
            "collection_seconds": st["time_collect"],
            # with overlap: the worker thread's time collecting (beside the optimisation)
            "worker_collection_seconds": st["time_collect_worker"],
            "causal_learning_seconds": (hook.stats["add_seconds"] + hook.stats["relearn_seconds"]
                                        - causal0) if hook is not None else 0.0,
            "gating_seconds": gate_timer.seconds if gate_timer is not None else 0.0,
            "peak_rss_mb": _peak_rss_mb(),
        }
        if stopped_early:
            return summary
        if self.best is not None:  # keep_best: the best periodic evaluation's snapshot
            self.actor.load_state_dict(self.best["actor"])
            self.explorer.load_state_dict(self.best["explorer"])
            summary["selected_frames"] = self.best["frames"]
        # the final policy as evaluated (the explorer's random state before the evaluation)
        explorer_state = copy.deepcopy(self.explorer.state_dict())
        summary["final_eval"] = self.final_evaluation()
        if self.paths is not None:
            torch.save(self.actor.state_dict(), self.paths["model"])
            torch.save(explorer_state, self.paths["explorer"])
            summary["model"] = str(self.paths["model"])
        return summary

