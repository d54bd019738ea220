"""Train one paper variant (thesis sec. 5.2) with TorchRL: ``python recipes/train.py``.

The default config is ``cbn_v2`` (CBN-DQN V2, k = 200) on the thesis scene with
a short budget; pick another variant with ``--config-name``::

    python recipes/train.py                                   # cbn_v2, short budget
    python recipes/train.py --config-name dqn_image seed=3
    python recipes/train.py -m --config-name cbn_v2 seed=0,1,2 causal.k=100,200,400,600
    python recipes/train.py output_dir=outputs/cbn_v2/<run> checkpoint.resume=true

The script composes library parts only: :class:`torchrl_causal.envs.DroneNavEnv`
with :func:`torchrl_causal.transforms.make_causal_transforms`,
:class:`torchrl_causal.modules.ThesisQNet` in a :class:`torchrl.modules.QValueActor`,
:class:`torchrl_causal.modules.CBNGate` (or :class:`torchrl.modules.EGreedyModule`
for the image-only DQN), a :class:`torchrl.data.TensorDictReplayBuffer` whose
transform is :class:`torchrl_causal.data.CausalLearningHook`, TorchRL's
:class:`~torchrl.collectors.Collector`, :class:`~torchrl.objectives.DQNLoss` and
:class:`~torchrl.objectives.HardUpdate`. See ``docs/recipes.rst``.
"""

from __future__ import annotations

import copy
import json
import math
import os
import random
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parent))

import recipe_utils as ru  # noqa: E402
import results  # noqa: E402

CONFIG_DIR = str(Path(__file__).resolve().parent / "config")
# ``${or_else:a,b}``: a unless it is null/empty, else b (used for hydra.run.dir).
OmegaConf.register_new_resolver("or_else", lambda a, b: a if a else b, replace=True)

#: Keys kept in the replay buffer (pixels stay uint8); everything else is dropped.
STORE_KEYS = ("pixels", "action", ("next", "pixels"), ("next", "reward"),
              ("next", "done"), ("next", "terminated"))
CAUSAL_STORE_KEYS = ("causal_state", ("next", "causal_state"))


# --------------------------------------------------------------------------- build
def build_env(cfg: DictConfig, variant: ru.Variant, scene: str, device: str):
    """DroneNavEnv on ``scene`` (+ the causal feature stack for CBN variants)."""
    from torchrl.envs import TransformedEnv

    from torchrl_causal.envs import DroneNavEnv

    env = DroneNavEnv(
        **ru.SCENES[scene],
        image_size=cfg.env.image_size,
        max_steps=cfg.env.max_steps,
        reward=cfg.env.reward,
        seed=cfg.seed,
        device=device,
        **OmegaConf.to_container(cfg.env.options, resolve=True),
    )
    if variant.features:
        from torchrl_causal.transforms import make_causal_transforms

        options = OmegaConf.to_container(cfg.features.options, resolve=True)
        options.setdefault("seed", cfg.seed)
        env = TransformedEnv(env, make_causal_transforms(env, **options))
    return env


def random_frames(cfg: DictConfig, variant: ru.Variant) -> int:
    """Uniformly random frames collected first: ``collector.init_random_frames``, plus,
    for ``cbn_defined``, the ``causal.warmup_frames`` that fit the expert CPTs
    (counted in the frame budget)."""
    extra = cfg.causal.warmup_frames if variant.causal_mode == "defined" else 0
    return cfg.collector.init_random_frames + extra


def build_agent(cfg: DictConfig, variant: ru.Variant, env, device: str):
    """Actor, explorer (gate or epsilon-greedy), policy, causal hook (or None)."""
    from tensordict.nn import TensorDictSequential
    from torchrl.modules import EGreedyModule, QValueActor

    from torchrl_causal.modules import CBNGate, ThesisQNet

    n_actions = env.action_spec.space.n
    net = ThesisQNet(
        n_actions,
        n_features=env.observation_spec["causal_state"].shape[-1] if variant.features else 0,
        image_size=(cfg.env.image_size, cfg.env.image_size),
        device=device,
    )
    in_keys = ["pixels", "causal_state"] if variant.features else ["pixels"]
    actor = QValueActor(net, in_keys=in_keys, spec=env.action_spec)
    hook = None
    if variant.causal_mode is None:
        explorer = EGreedyModule(
            env.action_spec,
            eps_init=cfg.exploration.eps_init,
            eps_end=cfg.exploration.eps_end,
            annealing_num_steps=cfg.exploration.annealing_frames,
        )
    else:
        from torchrl_causal.causal import CausalLearner
        from torchrl_causal.data import CausalLearningHook

        explorer = CBNGate(
            ru.gate_mode(cfg, variant),
            prob_causal_model=cfg.gate.prob_causal_model,
            threshold=cfg.gate.threshold,
            eps_init=cfg.exploration.eps_init,
            eps_end=cfg.exploration.eps_end,
            annealing_num_steps=cfg.exploration.annealing_frames,
            seed=cfg.seed,
            device=device,
        )
        learner = CausalLearner(
            n_actions=n_actions,
            mode=variant.causal_mode,
            backend=cfg.causal.backend,
            **OmegaConf.to_container(cfg.causal.options, resolve=True),
        )
        # cbn_defined: the first relearn (fitting the expert CBNs' CPTs) comes
        # at the end of the random warm-up, which the collector runs first
        warmup = random_frames(cfg, variant)
        hook = CausalLearningHook(
            learner,
            k=cfg.causal.k,
            gates=[explorer],
            background=cfg.causal.background,
            first_relearn=warmup if variant.causal_mode == "defined" and warmup else None,
        )
    policy = TensorDictSequential(actor, explorer)
    return actor, explorer, policy, hook


def build_buffer(cfg: DictConfig, hook, scratch: Path, device: str = "cpu"):
    """Replay memory: on ``device`` (RAM or GPU), or a memmap on disk above
    ``buffer.memmap_above`` (samples are then moved to ``device``)."""
    from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer

    if cfg.buffer.size > cfg.buffer.memmap_above:
        storage = LazyMemmapStorage(cfg.buffer.size, scratch_dir=cfg.buffer.scratch_dir or scratch)
    else:
        storage = LazyTensorStorage(cfg.buffer.size, device=device)
    rb = TensorDictReplayBuffer(storage=storage, batch_size=cfg.buffer.batch_size)
    if hook is not None:
        rb.append_transform(hook)
    return rb


def make_logger(cfg: DictConfig, log_dir: Path, state: dict | None):
    if cfg.logger.backend == "none":
        return None
    from torchrl.record.loggers import get_logger

    kwargs = {}
    if cfg.logger.backend == "wandb":
        kwargs["wandb_kwargs"] = {"project": cfg.logger.project, "dir": str(log_dir)}
    try:
        return get_logger(cfg.logger.backend, str(log_dir), cfg.variant, state_dict=state, **kwargs)
    except ImportError as err:
        raise ValueError(
            f"Invalid option logger.backend={cfg.logger.backend!r}: its package is not "
            f"installed ({err}); use logger.backend=csv"
        ) from None


# --------------------------------------------------------------------------- loop pieces
class EpisodeTracker:
    """Per-env running sums turned into one CSV row per finished episode."""

    def __init__(self, gate_keys: list[str]):
        self.gate_keys = gate_keys
        self.reset()

    def reset(self):
        self.reward, self.length = 0.0, 0
        self.gate = {k: 0.0 for k in self.gate_keys}

    def state_dict(self):
        return {"reward": self.reward, "length": self.length, "gate": dict(self.gate)}

    def load_state_dict(self, sd):
        self.reward, self.length, self.gate = sd["reward"], sd["length"], dict(sd["gate"])


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


def _flag(td, key) -> bool:
    val = td.get(key, None)
    return bool(val.any()) if val is not None else False


def seed_transforms(env, seed: int) -> None:
    """Reseeds the env's transforms that sample (``DepthSections``' pixel draws): TorchRL's
    ``env.set_seed`` does not reach them, and their streams must restart with the env's
    so that a resumed run and an evaluation do not depend on what ran before."""
    from torchrl.envs import Compose

    transform = getattr(env, "transform", None)
    transforms = list(transform) if isinstance(transform, Compose) else [transform]
    for t in transforms:
        if t is not None and hasattr(t, "set_seed"):
            t.set_seed(int(seed))


@torch.no_grad()
def evaluate(policy, env, episodes: int, seed: int) -> dict:
    """Greedy episodes (epsilon 0; the gate still applies): success rate, reward, collisions."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    env.set_seed(seed)
    seed_transforms(env, seed)
    rewards, successes, crashes, exits, lengths = [], [], [], [], []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(episodes):
            td = env.rollout(env_max_steps(env), policy, break_when_any_done=True)
            nxt = td["next"]
            rewards.append(float(nxt["reward"].sum()))
            lengths.append(td.numel())
            successes.append(_flag(nxt, "reached"))
            crashes.append(_flag(nxt, "crashed"))
            exits.append(_flag(nxt, "out_of_bounds"))
    to_goal = [n for n, ok in zip(lengths, successes) if ok]
    return {
        "success_rate": float(np.mean(successes)),
        "mean_reward": float(np.mean(rewards)),
        "collisions": int(np.sum(crashes)),
        "out_of_bounds": int(np.sum(exits)),
        "mean_length": float(np.mean(lengths)),
        "steps_to_goal": float(np.mean(to_goal)) if to_goal else float("nan"),
    }


def env_max_steps(env) -> int:
    base = getattr(env, "base_env", env)
    return int(getattr(base, "max_steps", 200))


# --------------------------------------------------------------------------- train
def resolve_output_dir(cfg: DictConfig) -> Path:
    if cfg.get("output_dir"):
        return Path(cfg.output_dir).expanduser().resolve()
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir).resolve()
    raise ValueError("Invalid option output_dir=None: give a run folder when not run by hydra.")


def train(cfg: DictConfig) -> dict:
    """Runs (or resumes) one training run and writes its run folder.

    Args:
        cfg: a config composed from ``recipes/config`` (hydra or
            :func:`hydra.compose`).

    Returns:
        The run summary (also written to ``summary.json``).
    """
    out = resolve_output_dir(cfg)
    variant = ru.validate_config(cfg, out)  # every bad option fails here, before any build
    cfg_plain = OmegaConf.to_container(cfg, resolve=False)
    cfg_plain.pop("hydra", None)
    paths = ru.prepare_run_dir(out)
    resume = bool(cfg.checkpoint.resume)
    if not resume:
        paths["config"].write_text(OmegaConf.to_yaml(OmegaConf.create(cfg_plain)))

    from torchrl.collectors import Collector
    from torchrl.objectives import DQNLoss, HardUpdate

    device = cfg.device
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)

    env = build_env(cfg, variant, cfg.env.layout, device)
    actor, explorer, policy, hook = build_agent(cfg, variant, env, device)
    rb = build_buffer(cfg, hook, paths["buffer"].parent / "buffer_storage", device)
    loss = DQNLoss(actor, loss_function=ru.LOSS_FUNCTIONS[cfg.loss.function], delay_value=True,
                   double_dqn=cfg.loss.double_dqn, action_space=env.action_spec)
    loss.make_value_estimator(gamma=cfg.loss.gamma)
    reward_scale = ru.reward_scale(cfg)
    if cfg.optim.name == "adam":
        optim = torch.optim.Adam(loss.parameters(), lr=cfg.optim.lr, eps=cfg.optim.eps)
    else:
        optim = torch.optim.RMSprop(
            loss.parameters(), lr=cfg.optim.lr, eps=cfg.optim.eps, alpha=cfg.optim.alpha
        )
    updater = HardUpdate(loss, value_network_update_interval=cfg.loss.target_update_interval)

    init_random = random_frames(cfg, variant)
    collector = Collector(
        env,
        policy,
        frames_per_batch=cfg.collector.frames_per_batch,
        total_frames=-1,
        init_random_frames=init_random or None,
        device=device,
        # the policy is feed-forward: the collector must not add env transforms
        auto_register_policy_transforms=False,
    )
    store_keys = list(STORE_KEYS) + (list(CAUSAL_STORE_KEYS) if variant.features else [])
    gate_keys = (
        ["gate_explored", "gate_consulted", "gate_vetoed", "gate_replaced"]
        if variant.causal_mode
        else []
    )
    ep_csv = ru.EpisodeCSV(
        paths["episodes"],
        ["episode", "frames", "reward", "length", "success", "crash", "out_of_bounds", "epsilon",
         "n_relearns"]
        + [k.replace("gate_", "gate_frac_") for k in gate_keys],
    )
    eval_csv = ru.EpisodeCSV(
        paths["eval"],
        ["frames", "episodes", "layout", "success_rate", "mean_reward", "collisions",
         "out_of_bounds", "mean_length", "steps_to_goal"],
    )
    rel_csv = ru.EpisodeCSV(paths["relearns"], ["relearn", "frames", "episode"])
    eval_envs = {lay: None for lay in cfg.env.eval_layouts}

    eval_every = cfg.eval.interval_frames or math.inf  # 0 = only at the end
    ckpt_every = cfg.checkpoint.interval_frames or math.inf

    # ---- state of the loop (all of it is checkpointed)
    st = {
        "frames": 0, "episodes": 0, "updates": 0, "update_budget": 0.0,
        "next_eval": eval_every, "next_ckpt": ckpt_every,
        "n_ckpt": 0, "n_relearns": 0, "n_evals": 0, "successes": [],
        "time_extend": 0.0, "time_train": 0.0, "time_collect": 0.0,
    }
    tracker = EpisodeTracker(gate_keys)
    logger_state = None
    best = None  # eval.keep_best: the best periodic evaluation's snapshot

    def restart_collector():
        # Checkpoints fall on episode ends. Right after one (in the uninterrupted
        # run as in the resumed one) the env is reseeded and reset, so both runs
        # continue from the same state: see docs/recipes.rst, "Resume".
        seed = int(cfg.seed) * 7919 + 104729 * st["n_ckpt"]
        collector.set_seed(seed)
        seed_transforms(env, seed)
        collector.reset()

    def save_checkpoint() -> None:
        # the buffer goes to a new folder; last.pt (written atomically after it)
        # names it, and older folders are removed only then: a kill at any point
        # leaves a consistent last.pt + buffer pair.
        buffer_dir = paths["buffer"].with_name(f"buffer_{st['n_ckpt']}")
        rb.dumps(buffer_dir)
        ru.atomic_save({**state_dict(), "buffer_dir": buffer_dir.name}, paths["checkpoint"])
        for old in paths["buffer"].parent.glob("buffer_*"):
            if old.is_dir() and old.name != buffer_dir.name and old.name != "buffer_storage":
                shutil.rmtree(old, ignore_errors=True)

    def state_dict() -> dict:
        return {
            "loop": dict(st),
            "tracker": tracker.state_dict(),
            "loss": loss.state_dict(),
            "optim": optim.state_dict(),
            "updater_counter": updater.counter,
            "explorer": explorer.state_dict(),
            "hook": hook.state_dict() if hook is not None else None,
            "collector": {k: v for k, v in collector.state_dict().items()
                          if k in ("frames", "iter", "traj_pool")},
            "logger": logger.state_dict() if logger is not None else None,
            "rows": {"episodes": ep_csv.n_rows, "eval": eval_csv.n_rows,
                     "relearns": rel_csv.n_rows},
            "rng": ru.rng_state(),
            "best": best,
        }

    if resume:
        ckpt = torch.load(paths["checkpoint"], weights_only=False)
        st.update(ckpt["loop"])
        tracker.load_state_dict(ckpt["tracker"])
        loss.load_state_dict(ckpt["loss"])
        optim.load_state_dict(ckpt["optim"])
        updater.counter = ckpt["updater_counter"]
        explorer.load_state_dict(ckpt["explorer"])
        rb.loads(paths["checkpoint"].parent / ckpt["buffer_dir"])
        if hook is not None:
            hook.load_state_dict(ckpt["hook"])
        collector.load_state_dict(ckpt["collector"], strict=False)  # frames, iter, traj ids
        if tracker.length:  # a final checkpoint may fall mid-episode: that episode is dropped
            tracker.reset()
        ep_csv.truncate(ckpt["rows"]["episodes"])
        eval_csv.truncate(ckpt["rows"]["eval"])
        rel_csv.truncate(ckpt["rows"]["relearns"])
        logger_state = ckpt["logger"]
        ru.set_rng_state(ckpt["rng"])
        best = ckpt.get("best")
        restart_collector()
    logger = make_logger(cfg, paths["logs"], logger_state)

    total_frames = cfg.collector.total_frames
    total_episodes = cfg.collector.total_episodes or math.inf
    stop_after = cfg.checkpoint.stop_after_frames
    pbar = None
    if cfg.progress:
        from tqdm import tqdm

        pbar = tqdm(total=total_frames, initial=st["frames"], desc=cfg.variant,
                    unit="frame", dynamic_ncols=True, mininterval=1.0)
    stopped_early = False
    gate_timer = _ForwardTimer(explorer) if hook is not None else None
    frames_at_start = st["frames"]
    causal_at_start = (hook.stats["add_seconds"] + hook.stats["relearn_seconds"]
                       if hook is not None else 0.0)
    t_start = time.perf_counter()
    last_reward = float("nan")

    t_last = time.perf_counter()
    for batch in collector:
        st["time_collect"] += time.perf_counter() - t_last
        batch = batch.reshape(-1)
        n = batch.numel()
        st["frames"] += n
        explorer.step(n)
        t0 = time.perf_counter()
        # the collector yields a fresh copy each batch: the storage copies it once more
        rb.extend(batch.select(*store_keys))
        st["time_extend"] += time.perf_counter() - t0
        if hook is not None and hook.learner.n_relearns > st["n_relearns"]:
            st["n_relearns"] = hook.learner.n_relearns
            rel_csv.write({"relearn": st["n_relearns"], "frames": st["frames"],
                           "episode": st["episodes"] + 1})
        # ---- episodes
        nxt = batch["next"]
        done = nxt["done"].reshape(n)
        for i in range(n):
            tracker.reward += float(nxt["reward"][i])
            tracker.length += 1
            for k in gate_keys:
                tracker.gate[k] += float(batch[k][i])
            if done[i]:
                st["episodes"] += 1
                success = bool(nxt["reached"][i].any())
                st["successes"] = (st["successes"] + [int(success)])[-50:]
                row = {
                    "episode": st["episodes"], "frames": st["frames"] - (n - 1 - i),
                    "reward": tracker.reward, "length": tracker.length,
                    "success": success, "crash": bool(nxt["crashed"][i].any()),
                    "out_of_bounds": bool(nxt["out_of_bounds"][i].any()),
                    "epsilon": float(explorer.eps), "n_relearns": st["n_relearns"],
                }
                for k in gate_keys:
                    row[k.replace("gate_", "gate_frac_")] = tracker.gate[k] / tracker.length
                ep_csv.write(row)
                last_reward = tracker.reward
                if logger is not None:
                    logger.log_scalar("train/episode_reward", tracker.reward, step=st["frames"])
                    logger.log_scalar("train/success", float(success), step=st["frames"])
                tracker.reset()
        # ---- optimisation
        t0 = time.perf_counter()
        if len(rb) >= max(cfg.loss.learning_starts, cfg.buffer.batch_size):
            st["update_budget"] += n * cfg.loss.updates_per_frame
            while st["update_budget"] >= 1.0:
                st["update_budget"] -= 1.0
                sample = rb.sample().to(device)
                if reward_scale != 1.0:  # the loss sees scaled rewards; the env's stay as defined
                    sample.set(("next", "reward"), sample.get(("next", "reward")) * reward_scale)
                loss_td = loss(sample)
                loss_td["loss"].backward()
                torch.nn.utils.clip_grad_norm_(loss.parameters(), cfg.loss.max_grad_norm)
                optim.step()
                optim.zero_grad(set_to_none=True)
                updater.step()
                st["updates"] += 1
                if logger is not None and st["updates"] % 100 == 0:
                    logger.log_scalar("train/loss", float(loss_td["loss"].detach()), step=st["frames"])
        st["time_train"] += time.perf_counter() - t0
        if pbar is not None:
            pbar.update(n)
            sr = np.mean(st["successes"]) if st["successes"] else float("nan")
            pbar.set_postfix(ep=st["episodes"], reward=f"{last_reward:.0f}",
                             success=f"{sr:.2f}", eps=f"{float(explorer.eps):.2f}",
                             refresh=False)
        # ---- evaluation, checkpoint, stop
        finished = st["frames"] >= total_frames or st["episodes"] >= total_episodes
        if st["frames"] >= st["next_eval"] or finished:
            res = _run_evals(cfg, variant, policy, eval_envs, eval_csv, st, logger, device)
            if cfg.eval.keep_best and res is not None and _better(res, best and best["result"]):
                best = {"frames": st["frames"], "result": res,
                        "actor": copy.deepcopy(actor.state_dict()),
                        "explorer": copy.deepcopy(explorer.state_dict())}
            while st["next_eval"] <= st["frames"]:
                st["next_eval"] += eval_every
        at_episode_end = bool(done[-1])
        if (st["frames"] >= st["next_ckpt"] and at_episode_end) or finished:
            st["n_ckpt"] += 1
            while st["next_ckpt"] <= st["frames"]:
                st["next_ckpt"] += ckpt_every
            save_checkpoint()
            if not finished:
                restart_collector()
            if stop_after is not None and st["frames"] >= stop_after and not finished:
                stopped_early = True
                break
        if finished:
            break
        t_last = time.perf_counter()
    if pbar is not None:
        pbar.close()
    collector.shutdown()
    wall = time.perf_counter() - t_start

    if gate_timer is not None:
        gate_timer.remove()
    summary = {
        "variant": cfg.variant, "seed": cfg.seed, "k": cfg.causal.k,
        "frames": st["frames"], "episodes": st["episodes"], "updates": st["updates"],
        "n_relearns": st["n_relearns"], "stopped_early": stopped_early,
        "output_dir": str(out), "plots_dir": str(paths["plots"]),
        # timings of this session's training loop (a resumed run counts its own part)
        "loop_seconds": wall,
        "loop_frames_per_second": (st["frames"] - frames_at_start) / wall if wall > 0 else None,
        "optimisation_seconds": st["time_train"],
        "collection_seconds": st["time_collect"],  # policy (incl. gate) + env + features
        "causal_learning_seconds": (hook.stats["add_seconds"] + hook.stats["relearn_seconds"]
                                    - causal_at_start) if hook is not None else 0.0,
        "gating_seconds": gate_timer.seconds if gate_timer is not None else 0.0,
    }
    if stopped_early:
        print(f"Stopped after {st['frames']} frames (checkpoint.stop_after_frames); resume with "
              f"output_dir={out} checkpoint.resume=true")
        return summary
    if best is not None:
        # eval.keep_best: the final policy is the best periodic evaluation's snapshot
        actor.load_state_dict(best["actor"])
        explorer.load_state_dict(best["explorer"])
        summary["selected_frames"] = best["frames"]
    summary["final_eval"] = final_evaluation(cfg, variant, policy, eval_envs, device)
    summary.update(write_outputs(cfg, variant, paths, actor, hook))
    paths["summary"].write_text(json.dumps(summary, indent=2, default=str))
    return summary


def _run_evals(cfg, variant, policy, eval_envs, eval_csv, st, logger, device) -> dict | None:
    """Periodic greedy evaluation (``eval.episodes``) on the training layout; returns its result."""
    if cfg.eval.episodes == 0:
        return None
    st["n_evals"] += 1
    # periodic evaluations run on the training layout only (the held-out split is
    # evaluated once, after training, by final_evaluation)
    layout = cfg.env.layout
    if eval_envs.get(layout) is None:
        eval_envs[layout] = build_env(cfg, variant, layout, device)
    res = evaluate(policy, eval_envs[layout], cfg.eval.episodes,
                   seed=int(cfg.seed) * 1009 + 31 * st["n_evals"])
    eval_csv.write({"frames": st["frames"], "episodes": st["episodes"], "layout": layout, **res})
    if logger is not None:
        for key, val in res.items():
            logger.log_scalar(f"eval_{layout}/{key}", val, step=st["frames"])
    return res


def _better(res: dict, best: dict | None) -> bool:
    """Higher greedy success wins; ties go to the later (longer-trained) policy."""
    return best is None or res["success_rate"] >= best["success_rate"]


def final_evaluation(cfg, variant, policy, eval_envs, device) -> dict:
    """``eval.final_episodes`` greedy episodes per evaluation layout (the headline figures)."""
    out = {}
    if cfg.eval.final_episodes == 0:
        return out
    for i, layout in enumerate(eval_envs):
        if eval_envs[layout] is None:
            eval_envs[layout] = build_env(cfg, variant, layout, device)
        out[layout] = evaluate(policy, eval_envs[layout], cfg.eval.final_episodes,
                               seed=10_000_019 + int(cfg.seed) * 1009 + i)
    return out


def write_outputs(cfg, variant, paths, actor, hook) -> dict:
    """Final model, CBNs (+ drawings), plots and Table 5.1 into the run folder."""
    out: dict[str, Any] = {}
    torch.save(actor.state_dict(), paths["model"])
    out["model"] = str(paths["model"])
    out["plots"] = [str(p) for p in results.plot_run(paths["model"].parent)]
    if hook is not None and hook.learner.n_relearns > 0:
        from torchrl_causal.causal import expert_dags, table_5_1, write_table_5_1

        learner = hook.learner
        learner.save(paths["cbns"] / "last")
        out["cbns"] = str(paths["cbns"])
        expert = expert_dags(learner.schema)
        last = learner.history_dags(-1)
        first = learner.first_searched_dags() if variant.causal_mode == "learned" else None
        if cfg.outputs.draw_cbns:
            out["cbn_drawings"] = [
                str(p) for p in draw_cbns(last, expert, paths["cbns"] / "last", "last")
            ]
            if first is not None:
                out["cbn_drawings"] += [
                    str(p) for p in draw_cbns(first, expert, paths["cbns"] / "first", "first")
                ]
        if first is not None:
            rows = table_5_1(expert, first, last)
            md, _ = write_table_5_1(rows, paths["tables"] / "table_5_1")
            out["table_5_1"] = str(md)
    return out


def draw_cbns(dags: dict, expert: dict, folder: Path, tag: str) -> list[Path]:
    """One PNG per action (edges shared with the ``expert`` (defined) CBN drawn thick)."""
    from torchrl_causal.causal import draw_cbn

    import matplotlib

    matplotlib.use("Agg")
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, edges in dags.items():
        p = folder / f"{name}.png"
        shared = set(map(tuple, edges)) & set(map(tuple, expert.get(name, [])))
        draw_cbn(edges, path=p, title=f"{name} ({tag} CBN, {len(edges)} edges)",
                 highlight=shared, dpi=90)
        paths.append(p)
    return paths


@hydra.main(version_base=None, config_path="config", config_name="cbn_v2")
def main(cfg: DictConfig) -> None:
    summary = train(cfg)
    if not summary.get("stopped_early"):
        for layout, res in summary.get("final_eval", {}).items():
            print(f"Greedy success on {layout}: {res['success_rate']:.2f} "
                  f"({cfg.eval.final_episodes} episodes; collisions {res['collisions']}, "
                  f"geofence exits {res['out_of_bounds']}, mean length {res['mean_length']:.1f})")
        print(f"Run folder: {summary['output_dir']}")
        print(f"Plots: {summary['plots_dir']}")
        if "table_5_1" in summary:
            print(f"Table 5.1: {summary['table_5_1']}")


if __name__ == "__main__":
    os.environ.setdefault("MUJOCO_GL", "egl")
    main()
