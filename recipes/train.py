"""Train one paper variant (thesis sec. 5.2) with TorchRL: ``python recipes/train.py``.

The default config is ``cbn_v2`` (CBN-DQN V2, k = 200) on the thesis scene with
a short budget; pick another variant with ``--config-name``::

    python recipes/train.py                                   # cbn_v2, short budget
    python recipes/train.py --config-name dqn_image seed=3
    python recipes/train.py -m --config-name cbn_v2 seed=0,1,2 causal.k=100,200,400,600
    python recipes/train.py output_dir=outputs/cbn_v2/<run> checkpoint.resume=true

This script is configuration and composition only. It builds
:class:`torchrl_causal.envs.DroneNavEnv` with
:func:`torchrl_causal.transforms.make_causal_transforms`,
:class:`torchrl_causal.modules.ThesisQNet` in a :class:`torchrl.modules.QValueActor`,
:class:`torchrl_causal.modules.CBNGate` (or :class:`torchrl.modules.EGreedyModule`
for the image-only DQN), a :class:`torchrl_causal.causal.CausalLearner` fed by a
:class:`torchrl_causal.data.CausalLearningHook`, and hands them to
:class:`torchrl_causal.training.DQNLoop` -- thesis Algorithm 1, with its
evaluation, checkpoints and exact resume. See ``docs/recipes.rst``.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import sys
import time
from pathlib import Path
from typing import Any

# before anything imports mujoco; also for jobs a hydra launcher (joblib, submitit,
# Ray) starts, which do not run this file as __main__
os.environ.setdefault("MUJOCO_GL", "egl")

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parent))

import recipe_utils as ru  # noqa: E402
from torchrl_causal.schema import ACTION_NAMES  # noqa: E402
from torchrl_causal.pretrained import policy_guards  # noqa: E402
import results  # noqa: E402

CONFIG_DIR = str(Path(__file__).resolve().parent / "config")
# ``${or_else:a,b}``: a unless it is null/empty, else b (used for hydra.run.dir).
OmegaConf.register_new_resolver("or_else", lambda a, b: a if a else b, replace=True)


# --------------------------------------------------------------------------- build
def build_env(cfg: DictConfig, variant: ru.Variant, scene: str, device: str, num_envs: int = 1):
    """DroneNavEnv on ``scene`` -- ``num_envs`` of them in a ``SerialEnv`` (or a
    ``ParallelEnv`` with ``env.parallel=true``) -- plus the causal feature stack
    for CBN variants (applied to the batch)."""
    import functools

    from torchrl.envs import ParallelEnv, SerialEnv

    from torchrl_causal.envs import DroneNavEnv

    make = functools.partial(
        DroneNavEnv, **ru.SCENES[scene], image_size=cfg.env.image_size,
        max_steps=cfg.env.max_steps, reward=cfg.env.reward, seed=cfg.seed, device=device,
        **OmegaConf.to_container(cfg.env.options, resolve=True),
        **ru.NOISE_PRESETS[cfg.env.get("noise", "none")])
    if num_envs == 1:
        env = make()
    else:
        env = (ParallelEnv if cfg.env.parallel else SerialEnv)(num_envs, make, device=device)
    return with_features(cfg, variant, env)


def with_features(cfg: DictConfig, variant: ru.Variant, env):
    """``env`` with the run's policy transforms (the causal feature stack
    ``features.options``, and for ``features.history > 0`` the action history),
    as :func:`policy_spec` describes them; ``env`` itself for the image-only DQN."""
    from torchrl_causal.pretrained import with_policy_features

    return with_policy_features(policy_spec(cfg, variant), env, seed=cfg.seed)


def policy_spec(cfg: DictConfig, variant: ru.Variant, provenance: dict | None = None):
    """The run's :class:`~torchrl_causal.pretrained.PolicySpec`: what the policy reads
    (``features.inputs``, ``features.history``) and how its explorer is built. The
    recipe builds its agent from it and saves it as ``policy.json``."""
    from torchrl_causal.pretrained import PolicySpec

    eps = ru.exploration_kwargs(cfg, variant)
    features = cfg.get("features", {})
    inputs = list(features.get("inputs", ["causal_state"])) if variant.features else []
    return PolicySpec(
        image_size=cfg.env.image_size, n_actions=len(ACTION_NAMES), inputs=inputs,
        history=int(features.get("history", 0)) if variant.features else 0,
        frames=int(features.get("frames", 0)) if variant.features else 0,
        features=OmegaConf.to_container(cfg.features.options, resolve=True),
        explorer="egreedy" if variant.causal_mode is None else "cbn_gate",
        gate_mode=ru.gate_mode(cfg, variant), prob_causal_model=cfg.gate.prob_causal_model,
        threshold=cfg.gate.threshold, eps_init=eps["eps_init"], eps_end=eps["eps_end"],
        annealing_frames=eps["annealing_num_steps"], provenance=provenance or {},
        image=bool(features.get("image", True)) if variant.features else True,
        ego_map=_plain(features.get("ego_map", {})) if variant.features else {},
        shield=bool(features.get("shield", False)) if variant.features else False,
        loop_guard=bool(features.get("loop_guard", False)) if variant.features else False,
        revisit_guard=bool(features.get("revisit_guard", False)) if variant.features else False,
        goal_search=float(features.get("goal_search", 0.0) or 0.0) if variant.features else 0.0,
    )


def _plain(node) -> dict:
    """A config node (or a plain dict, from a run folder written before the key existed)
    as a dict."""
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) \
        else dict(node or {})


def random_frames(cfg: DictConfig, variant: ru.Variant) -> int:
    """Uniformly random frames collected first: ``collector.init_random_frames``, plus,
    for ``cbn_defined``, the ``causal.warmup_frames`` that fit the expert CPTs
    (counted in the frame budget)."""
    extra = cfg.causal.warmup_frames if variant.causal_mode == "defined" else 0
    return cfg.collector.init_random_frames + extra


def build_agent(cfg: DictConfig, variant: ru.Variant, env, device: str):
    """Q-network actor, explorer (CBN gate, Alg. 3/4, or epsilon-greedy), causal hook (or None),
    built from :func:`policy_spec` by :func:`torchrl_causal.pretrained.build_policy`."""
    from torchrl_causal.pretrained import build_policy

    actor, explorer = build_policy(policy_spec(cfg, variant), env.action_spec_unbatched,
                                   device=device, seed=cfg.seed)
    if variant.causal_mode is None:
        return actor, explorer, None

    from torchrl_causal.causal import CausalLearner
    from torchrl_causal.data import CausalLearningHook

    learner = CausalLearner(n_actions=len(ACTION_NAMES), mode=variant.causal_mode,
                            backend=cfg.causal.backend,
                            **OmegaConf.to_container(cfg.causal.options, resolve=True))
    # cbn_defined: the first relearn (fitting the expert CBNs' CPTs) comes at the
    # end of the random warm-up, which the loop runs first
    warmup = random_frames(cfg, variant)
    hook = CausalLearningHook(learner, k=cfg.causal.k, gates=[explorer],
                              background=cfg.causal.background,
                              first_relearn=warmup if variant.causal_mode == "defined" and warmup
                              else None)
    return actor, explorer, hook


def build_buffer(cfg: DictConfig, scratch: Path, device: str = "cpu"):
    """Replay memory: on ``device`` (RAM or GPU), or a memmap on disk above
    ``buffer.memmap_above`` (samples are then moved to ``device``)."""
    from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer

    if cfg.buffer.size > cfg.buffer.memmap_above:
        # existsok: a resumed run reuses its own scratch files (the checkpoint overwrites them)
        storage = LazyMemmapStorage(cfg.buffer.size, scratch_dir=cfg.buffer.scratch_dir or scratch,
                                    existsok=True)
    else:
        storage = LazyTensorStorage(cfg.buffer.size, device=device)
    return TensorDictReplayBuffer(storage=storage, batch_size=cfg.buffer.batch_size)


def build_loss(cfg: DictConfig, actor, env):
    """The DQN loss (TorchRL's ``DQNLoss``; with ``loss.stateful``, the default, the same
    loss bit for bit without per-call parameter swaps:
    :class:`~torchrl_causal.training.StatefulDQNLoss`) + its value estimator, and the
    optimiser the preset names (:func:`~torchrl_causal.training.dqn_optimizer`; Adam fused
    where it runs, ``optim.fused``)."""
    from torchrl.objectives import DQNLoss

    from torchrl_causal.training import StatefulDQNLoss, dqn_optimizer

    cls = StatefulDQNLoss if cfg.loss.get("stateful", True) else DQNLoss
    loss = cls(actor, loss_function=ru.LOSS_FUNCTIONS[cfg.loss.function], delay_value=True,
               double_dqn=cfg.loss.double_dqn, action_space=env.action_spec_unbatched)
    loss.make_value_estimator(gamma=cfg.loss.gamma)
    optim = dqn_optimizer(loss.parameters(), cfg.optim.name, lr=cfg.optim.lr, eps=cfg.optim.eps,
                          alpha=cfg.optim.alpha, fused=ru.optim_fused(cfg))
    return loss, optim


def _dotlist(overrides) -> list[str]:
    """``load_policy``'s overrides as OmegaConf's dotlist: Hydra's append prefix (``+key=v``,
    ``++key=v``) is dropped, since a dotlist adds missing keys anyway (left in, it would
    silently set a key named ``+key``); anything that is not ``key=value`` is refused."""
    out = []
    for o in overrides:
        if not isinstance(o, str) or "=" not in o or o.lstrip("+").startswith(("~", "=")):
            raise ValueError(f"Invalid override {o!r} for load_policy: expected 'key=value' "
                             "(Hydra's '+key=value' is accepted; deleting a key is not)")
        out.append(o.lstrip("+"))
    return out


def load_policy(run_dir, *, overrides=(), scene: str | None = None, device: str = "cpu",
                env=None):
    """The trained policy of a finished run folder, rebuilt by this recipe's builders.

    The Q-network comes from ``model.pt`` (the final policy, ``eval.keep_best``'s
    choice) and the explorer (the CBN gate with its compiled tables, or
    epsilon-greedy) from ``explorer.pt`` (runs older than that file: from the
    checkpoint's snapshot of the same policy). ``config.yaml``, ``model.pt`` and
    ``explorer.pt`` are all a policy needs: copy those three to share one.

    Args:
        run_dir: a run folder written by :func:`train`.
        overrides: config overrides applied to the run's ``config.yaml``, e.g.
            ``["features.options.perception=rgb"]`` to fly the policy on
            features from the RGB image alone. Keys the config lacks are
            added; Hydra's ``+key=value`` is accepted as the same.
        scene: the env's scene (default: the run's training scene); ignored
            when ``env`` is given.
        device: the device of the networks, the gate and the env outputs.
        env: an env to act in instead (it must write the keys the policy
            reads: ``pixels`` and, for CBN variants, ``causal_state``).

    Returns:
        ``(policy, env, cfg)``: a ``TensorDictSequential(actor, explorer)``, the
        env and the run's config.

    Raises:
        FileNotFoundError: the folder has no ``config.yaml``, ``model.pt``, or
            neither ``explorer.pt`` nor a checkpoint (the run did not finish).
        ValueError: an override that is not ``key=value``.
    """
    from tensordict.nn import TensorDictSequential

    run_dir = Path(run_dir)
    files = {"config": run_dir / "config.yaml", "model": run_dir / ru.RUN_LAYOUT["model"],
             "explorer": run_dir / ru.RUN_LAYOUT["explorer"]}
    if not files["explorer"].is_file():
        files["explorer"] = run_dir / ru.RUN_LAYOUT["checkpoint"]
    for what, path in files.items():
        if not path.is_file():
            raise FileNotFoundError(
                f"run_dir={str(run_dir)!r} has no {what} file {str(path)!r}: is it a finished "
                "run folder of recipes/train.py?")
    cfg = OmegaConf.merge(OmegaConf.load(files["config"]),
                          OmegaConf.from_dotlist(_dotlist(overrides)))
    cfg.device = device
    variant = ru.VARIANTS[cfg.variant]
    if env is None:
        env = build_env(cfg, variant, scene or cfg.env.layout, device)
    actor, explorer, _ = build_agent(cfg, variant, env, device)
    actor.load_state_dict(torch.load(files["model"], map_location=device, weights_only=False))
    state = torch.load(files["explorer"], map_location=device, weights_only=False)
    if files["explorer"].name != "explorer.pt":  # a checkpoint: its snapshot of the final policy
        state = state["best"]["explorer"] if state.get("best") else state["explorer"]
    explorer.load_state_dict(state)
    return TensorDictSequential(actor, explorer, *policy_guards(policy_spec(cfg, variant))), env, cfg


def teach(cfg: DictConfig, env, actor, hook, out: Path) -> list[dict] | None:
    """The teacher phase (``teacher.rounds > 0``): DAgger from the shortest-path oracle
    (:class:`torchrl_causal.training.imitation.OracleImitation`) before the DQN phase.

    Its transitions also go through the causal hook (one relearn on all of them), so
    a CBN variant's gate is active when the DQN phase starts. The result (actor and
    causal state, the per-round table ``imitation.csv``) is saved as
    ``checkpoints/imitation.pt``; a resumed run loads it instead of teaching again.
    """
    if not cfg.teacher.rounds:
        return None
    from torchrl_causal.training.imitation import ImitationConfig, OracleImitation
    from torchrl_causal.training.records import EpisodeCSV

    ckpt = out / "checkpoints" / "imitation.pt"
    if ckpt.is_file():
        state = torch.load(ckpt, map_location=cfg.device, weights_only=False)
        actor.load_state_dict(state["actor"])
        if hook is not None and state.get("hook") is not None:
            hook.load_state_dict(state["hook"])
        return state["history"]
    t = cfg.teacher
    imitation = OracleImitation(env, actor, ImitationConfig(
        rounds=t.rounds, episodes_per_round=t.episodes_per_round, beta_decay=t.beta_decay,
        updates_per_frame=t.updates_per_frame, batch_size=cfg.buffer.batch_size, lr=t.lr,
        margin=t.margin, td_weight=t.td_weight, max_expansions=t.max_expansions,
        planner_weight=t.get("planner_weight", 1.2), clearance=t.get("clearance", 0.0),
        teacher_actions=list(t.actions) if t.get("actions") else None,
        seed=cfg.seed, progress=cfg.progress), device=cfg.device)
    rows = EpisodeCSV(out / "imitation.csv", [
        "round", "beta", "frames", "labelled", "agreement", "success_rate", "crash_rate",
        "crash_near_goal_rate", "loss",
        "collect_seconds", "train_seconds", "teacher_replans"])
    rows.truncate(0)  # an interrupted teacher phase starts again from round 0
    history = imitation.run(on_round=rows.write)  # imitation.csv grows round by round
    if hook is not None:  # the CBNs learn from the teacher phase's flights (one relearn)
        before = hook.learner.n_relearns
        hook.inv(imitation.buffer[:])
        if hook.learner.n_relearns == before:  # the write crossed no multiple of k
            hook.relearn()
    ckpt.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"actor": actor.state_dict(), "history": history,
                "hook": hook.state_dict() if hook is not None else None}, ckpt)
    return history


def loop_config(cfg: DictConfig, variant: ru.Variant):
    """The recipe's options as a :class:`~torchrl_causal.training.LoopConfig`."""
    from torchrl_causal.training import LoopConfig

    return LoopConfig(
        total_frames=cfg.collector.total_frames, total_episodes=cfg.collector.total_episodes,
        frames_per_batch=cfg.collector.frames_per_batch,
        init_random_frames=random_frames(cfg, variant), batch_size=cfg.buffer.batch_size,
        learning_starts=cfg.loss.learning_starts, updates_per_frame=cfg.loss.updates_per_frame,
        target_update_interval=cfg.loss.target_update_interval,
        max_grad_norm=cfg.loss.max_grad_norm, reward_scale=ru.reward_scale(cfg),
        eval_interval_frames=cfg.eval.interval_frames, eval_episodes=cfg.eval.episodes,
        final_eval_episodes=cfg.eval.final_episodes, keep_best=cfg.eval.keep_best,
        checkpoint_interval_frames=cfg.checkpoint.interval_frames,
        stop_after_frames=cfg.checkpoint.stop_after_frames, seed=cfg.seed, device=cfg.device,
        progress=cfg.progress, overlap=cfg.collector.get("overlap", False),
        eval_fixed_seed=cfg.eval.get("fixed_episodes", False),
        fused_acting=cfg.collector.get("fused_acting", True),
    )


def make_logger(cfg: DictConfig, log_dir: Path):
    if cfg.logger.backend == "none":
        return None
    from torchrl.record.loggers import get_logger

    kwargs = {}
    if cfg.logger.backend == "wandb":
        kwargs["wandb_kwargs"] = {"project": cfg.logger.project, "dir": str(log_dir)}
    try:
        return get_logger(cfg.logger.backend, str(log_dir), cfg.variant, **kwargs)
    except ImportError as err:
        raise ValueError(
            f"Invalid option logger.backend={cfg.logger.backend!r}: its package is not "
            f"installed ({err}); use logger.backend=csv"
        ) from None


def resolve_output_dir(cfg: DictConfig) -> Path:
    if cfg.get("output_dir"):
        return Path(cfg.output_dir).expanduser().resolve()
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir).resolve()
    raise ValueError("Invalid option output_dir=None: give a run folder when not run by hydra.")


# --------------------------------------------------------------------------- train
def train(cfg: DictConfig) -> dict:
    """Runs (or resumes) one training run and writes its run folder.

    Args:
        cfg: a config composed from ``recipes/config`` (hydra or
            :func:`hydra.compose`).

    Returns:
        The run summary (also written to ``summary.json``).
    """
    from torchrl_causal.training import DQNLoop

    out = resolve_output_dir(cfg)
    variant = ru.validate_config(cfg, out)  # every bad option fails here, before any build
    resume = ru.resolve_resume(cfg, out)  # checkpoint.resume: true | false | auto
    paths = ru.prepare_run_dir(out)
    if not resume:
        cfg_plain = OmegaConf.to_container(cfg, resolve=False)
        cfg_plain.pop("hydra", None)
        paths["config"].write_text(OmegaConf.to_yaml(OmegaConf.create(cfg_plain)))
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)

    # Alg. 1, l. 1-3: the env, the Q-network, the gate and the causal learner
    env = build_env(cfg, variant, cfg.env.layout, cfg.device, num_envs=cfg.env.num_envs)
    actor, explorer, hook = build_agent(cfg, variant, env, cfg.device)
    if hook is not None:  # causal.transfer_from: start from saved CBNs, the gate acts from frame 0
        ru.transfer_cbns(cfg, hook.learner, hook.gates)
    loss, optim = build_loss(cfg, actor, env)
    teacher = teach(cfg, env, actor, hook, out)
    # evaluation scenes, built when first used; the first is evaluated periodically
    eval_envs = {scene: (lambda s=scene: build_env(cfg, variant, s, cfg.device))
                 for scene in ru.eval_scenes(cfg)}  # the selection scene first
    loop = DQNLoop(
        env, actor, explorer, config=loop_config(cfg, variant), hook=hook, loss=loss,
        optimizer=optim, eval_envs=eval_envs, output_dir=out,
        replay_buffer=build_buffer(cfg, paths["buffer"].parent / "buffer_storage", cfg.device),
        logger=make_logger(cfg, paths["logs"]),
        guards=policy_guards(policy_spec(cfg, variant)),
    )
    # Alg. 1, l. 4-20: collect, gate, store (+ relearn every k), update, sync, evaluate
    summary = {"variant": cfg.variant, "seed": cfg.seed, "k": cfg.causal.k,
               **loop.run(resume=resume),
               "plots_dir": str(paths["plots"])}
    if summary["stopped_early"]:
        print(f"Stopped after {summary['frames']} frames (checkpoint.stop_after_frames); resume "
              f"with output_dir={out} checkpoint.resume=true")
        return summary
    if not cfg.buffer.scratch_dir and not loop.config.keep_final_buffer:
        # a finished run's checkpoint keeps no buffer: its memmap scratch files (up to
        # ~1 GB) go, so a grid of finished runs holds records, not buffers
        shutil.rmtree(paths["buffer"].parent / "buffer_storage", ignore_errors=True)
    if teacher:
        summary["teacher"] = {
            "rounds": len(teacher), "frames": int(sum(r["frames"] for r in teacher)),
            "labelled": int(sum(r["labelled"] for r in teacher)),
            "seconds": float(sum(r["collect_seconds"] + r["train_seconds"] for r in teacher)),
            "last_round": teacher[-1]}
    summary.update(write_outputs(cfg, variant, paths, hook))
    summary["flight_maps"] = [str(p) for p in draw_flight_maps(loop, paths["plots"])]
    if cfg.outputs.get("videos", 0):
        summary["videos"] = record_videos(cfg, variant, loop.policy, out / "videos")
    spec = policy_spec(cfg, variant, provenance={
        "run": str(out), "variant": cfg.variant, "seed": cfg.seed,
        "frames": summary["frames"],
        "teacher_frames": summary.get("teacher", {}).get("frames", 0),
        "final_eval": summary.get("final_eval", {})})
    (out / "policy.json").write_text(spec.to_json())
    paths["summary"].write_text(json.dumps(summary, indent=2, default=str))
    return summary


def write_outputs(cfg, variant, paths, hook) -> dict:
    """CBNs (+ drawings), plots and Table 5.1 into the run folder."""
    out: dict[str, Any] = {}
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


def draw_flight_maps(loop, folder: Path, max_maps: int = 12) -> list[Path]:
    """``plots/flight_map_<scene>.png``: the final greedy episodes of each evaluation
    scene from above (up to ``max_maps`` per scene), coloured by outcome, the oracle's
    plans dashed."""
    from torchrl_causal.training.flightmap import plot_flight_maps

    out = []
    for scene, episodes in getattr(loop, "final_episodes", {}).items():
        eps = [e for e in episodes if e.get("path")][:max_maps]
        if eps:
            out.append(plot_flight_maps(eps, folder / f"flight_map_{scene}.png",
                                        suptitle=f"final greedy episodes: {scene}"))
    return out


def record_videos(cfg: DictConfig, variant: ru.Variant, policy, folder: Path) -> dict:
    """``videos/<scene>.mp4``: greedy episodes of the final policy, onboard camera beside a
    chase view (:func:`torchrl_causal.training.video.record_episodes`) -- one on the thesis
    scene and ``outputs.videos`` on held-out layouts. Only evaluation episodes: the
    training flights are never recorded."""
    from torchrl_causal.training.video import record_episodes

    out = {}
    for scene, episodes in (("thesis", 1), ("heldout", int(cfg.outputs.videos))):
        t0 = time.perf_counter()
        env = build_env(cfg, variant, scene, cfg.device)
        res = record_episodes(policy, env, episodes, seed=cfg.seed * 7919 + 17,
                              path=folder / f"{scene}.mp4", spl=False)
        out[scene] = {"video": str(res["video"]), "episodes": episodes,
                      "success_rate": res["success_rate"],
                      "seconds": round(time.perf_counter() - t0, 2)}
        env.close()
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
    main()
