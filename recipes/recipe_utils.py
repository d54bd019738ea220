"""Plumbing shared by the training recipe and ``reproduce.py``.

Nothing here is method logic: the environment, features, Q-network, gate,
causal learner and replay-buffer hook all come from :mod:`torchrl_causal`.
This module only holds what a training *script* needs around them:

* :data:`VARIANTS` -- the five paper variants and the two no-CBN controls,
  and what each one switches on;
* :func:`validate_config` -- every bad option is rejected with a
  ``ValueError`` naming it, before anything heavy is built;
* :func:`exploration_kwargs`, :func:`eval_scenes`, :func:`transfer_cbns` --
  the explorer's epsilon schedule, the evaluation scenes (the selection scene
  first) and the transfer of saved CBNs into the causal learner;
* :func:`prepare_run_dir` -- the run-folder layout (:data:`RUN_LAYOUT`: the
  training loop's :data:`~torchrl_causal.training.RUN_FILES` plus the recipe's
  plots, tables, CBNs and summary).

The training loop itself (Alg. 1, checkpoints, exact resume) is
:class:`torchrl_causal.training.DQNLoop`.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import torch

from torchrl_causal.envs.control import TELLO_MOVE_NOISE
from torchrl_causal.envs.rewards import REWARDS  # ``env.reward`` names: the env's own
from torchrl_causal.training import OPTIMIZERS, RUN_FILES

__all__ = [
    "Variant",
    "VARIANTS",
    "GATE_MODES",
    "PRESETS",
    "REWARDS",
    "LOSS_FUNCTIONS",
    "reward_scale",
    "SCENES",
    "LOGGER_BACKENDS",
    "RUN_LAYOUT",
    "validate_config",
    "resolve_resume",
    "check_writable",
    "gate_mode",
    "exploration_kwargs",
    "selection_scene",
    "eval_scenes",
    "transfer_source",
    "transfer_cbns",
    "prepare_run_dir",
]


@dataclass(frozen=True)
class Variant:
    """What a paper variant switches on.

    Args:
        name: the variant's name (also its config file name).
        features: concatenate the nine causal features before the dense layer
            (thesis Fig. 5.2) instead of the image-only network (Fig. 5.1).
        causal_mode: ``None`` (no CBN), ``"learned"`` or ``"defined"``
            (expert structures, CPTs fitted from data).
        default_gate: the gate algorithm the variant uses by default.
        label: the legend label used in the thesis's Fig. 5.4.
        v2_epsilon: (variants without a CBN) scale epsilon by
            ``1 - gate.prob_causal_model``: the random-action probability V2
            (Alg. 4) effectively has, since it acts greedily with probability
            ``prob_causal_model`` and epsilon-greedily otherwise.
    """

    name: str
    features: bool
    causal_mode: str | None
    default_gate: str | None
    label: str
    v2_epsilon: bool = False


#: The five variants of thesis sec. 5.2 / Fig. 5.4, then two controls without a
#: CBN on the same Fig. 5.2 network and feature stack: plain epsilon-greedy, and
#: epsilon-greedy with V2's effective epsilon.
VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("dqn_image", False, None, None, "DQN (image only)"),
        Variant("cbn_defined", True, "defined", "v2", "DQN + defined CBN"),
        Variant("cbn_p", True, "learned", "p", "CBN-DQN P"),
        Variant("cbn_pn", True, "learned", "pn", "CBN-DQN PN"),
        Variant("cbn_v2", True, "learned", "v2", "CBN-DQN V2"),
        Variant("dqn_features", True, None, None, "DQN (image + features)"),
        Variant("dqn_features_v2eps", True, None, None, "DQN (image + features), V2 epsilon",
                v2_epsilon=True),
    )
}
GATE_MODES = ("p", "pn", "v2")
#: Scene names of the ``env.layout`` / ``env.eval_layouts`` options -> DroneNavEnv arguments.
SCENES = {
    "thesis": {"layout": "thesis"},  # the thesis scene (Fig. 2.3)
    "train": {"layout": "random", "split": "train"},  # random layouts, training split
    "heldout": {"layout": "random", "split": "heldout"},  # random layouts never trained on
    # validation: random layouts of the training split from another world (layout_seed 1;
    # training uses 0), for eval.select_layout -- selection never sees held-out layouts
    "val": {"layout": "random", "split": "train", "layout_seed": 1},
}
#: ``env.noise`` presets -> DroneNavEnv options (``tello``: the emulated Tello's move
#: noise, :data:`torchrl_causal.envs.control.TELLO_MOVE_NOISE`).
NOISE_PRESETS = {"none": {}, "tello": TELLO_MOVE_NOISE}
LOGGER_BACKENDS = ("csv", "tensorboard", "wandb", "none")
#: ``preset`` names (config group ``recipes/config/preset``).
PRESETS = ("default", "thesis")
#: ``loss.function`` -> the ``loss_function`` of :class:`torchrl.objectives.DQNLoss`.
LOSS_FUNCTIONS = {"huber": "smooth_l1", "l2": "l2"}
#: ``loss.reward_scale: null`` -> the scale for each reward (keeps TD targets O(1..10)).
AUTO_REWARD_SCALE = {"progress": 1.0, "thesis": 0.01}

#: Files and folders of a run folder, relative to it.
RUN_LAYOUT = {
    **RUN_FILES,  # episodes.csv, eval.csv, relearns.csv, checkpoints/, model.pt
    "config": "config.yaml",
    "logs": "logs",
    "plots": "plots",
    "tables": "tables",
    "cbns": "cbns",
    "summary": "summary.json",
}


def _get(cfg: Mapping, dotted: str, default: Any = None) -> Any:
    node: Any = cfg
    for part in dotted.split("."):
        if node is None or part not in node:
            return default
        node = node[part]
    return node


def optim_fused(cfg: Mapping) -> bool | None:
    """``optim.fused`` as :func:`~torchrl_causal.training.dqn_optimizer` takes it: ``auto``
    -> ``None``, else the bool. A stored config from before the key trained on PyTorch's
    default path, so its absence reads ``False``, the default."""
    fused = _get(cfg, "optim.fused", False)
    return None if fused == "auto" else fused


def _require(cond: bool, option: str, value: Any, expected: str) -> None:
    if not cond:
        raise ValueError(f"Invalid option {option}={value!r}: expected {expected}.")


def check_writable(path: str | os.PathLike) -> Path:
    """Creates ``path`` if needed and proves a file can be written in it.

    Raises:
        ValueError: naming the option ``output_dir`` when it is not writable.
    """
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".write_probe_"):
            pass
    except OSError as err:
        raise ValueError(
            f"Invalid option output_dir={str(path)!r}: the folder cannot be written ({err})."
        ) from None
    return path


def validate_config(cfg: Mapping, output_dir: str | os.PathLike) -> Variant:
    """Checks every option a run needs before anything is built.

    Args:
        cfg: the (hydra / OmegaConf or plain dict) run config.
        output_dir: the run folder the config resolves to.

    Returns:
        The :class:`Variant` the config selects.

    Raises:
        ValueError: for an unknown variant or gate mode, ``causal.k <= 0``,
            probabilities outside [0, 1], non-positive budgets, an unknown
            logger, ``checkpoint.resume=true`` without a checkpoint (or a
            value other than true / false / auto), an ``eval.select_layout``
            that is not among ``env.eval_layouts`` or is held out (keep_best
            must not select on held-out layouts), an ``env.options`` key a
            scene sets itself, a ``causal.transfer_from`` folder that is
            missing, holds no CBN files or CBNs of another schema, or is given
            to a variant without a CBN, or an unwritable output folder. The
            message names the option and value.
    """
    variant = _get(cfg, "variant")
    _require(variant in VARIANTS, "variant", variant, f"one of {sorted(VARIANTS)}")
    v = VARIANTS[variant]
    for key in ("gate.prob_causal_model", "gate.threshold", "exploration.eps_init",
                "exploration.eps_end", "loss.gamma"):
        val = _get(cfg, key)
        _require(
            isinstance(val, (int, float)) and not isinstance(val, bool) and 0.0 <= val <= 1.0,
            key, val, "a probability in [0, 1]",
        )
    k = _get(cfg, "causal.k")
    _require(isinstance(k, int) and not isinstance(k, bool) and k > 0,
             "causal.k", k, "an integer > 0 (frames between relearns)")
    for key in ("collector.total_frames", "collector.frames_per_batch", "buffer.size",
                "buffer.batch_size", "loss.target_update_interval",
                "exploration.annealing_frames", "env.max_steps", "env.image_size"):
        val = _get(cfg, key)
        _require(isinstance(val, int) and not isinstance(val, bool) and val > 0,
                 key, val, "an integer > 0")
    for key in ("collector.init_random_frames", "loss.learning_starts",
                "eval.interval_frames", "eval.episodes", "checkpoint.interval_frames",
                "causal.warmup_frames"):
        val = _get(cfg, key)
        _require(isinstance(val, int) and not isinstance(val, bool) and val >= 0,
                 key, val, "an integer >= 0")
    upf = _get(cfg, "loss.updates_per_frame")
    _require(isinstance(upf, (int, float)) and not isinstance(upf, bool) and upf > 0,
             "loss.updates_per_frame", upf, "a number > 0 (the replay ratio: gradient steps "
             "per collected frame)")
    n_envs = _get(cfg, "env.num_envs", 1)
    _require(isinstance(n_envs, int) and not isinstance(n_envs, bool) and n_envs >= 1,
             "env.num_envs", n_envs, "an integer >= 1")
    fpb = _get(cfg, "collector.frames_per_batch")
    if isinstance(fpb, int) and fpb > 0:
        _require(fpb % n_envs == 0, "collector.frames_per_batch", fpb,
                 f"a multiple of env.num_envs={n_envs} (each batch steps every env alike), "
                 f"e.g. collector.frames_per_batch={n_envs}")
    noise = _get(cfg, "env.noise", "none")
    _require(noise in NOISE_PRESETS, "env.noise", noise, f"one of {sorted(NOISE_PRESETS)}")
    both = sorted(set(NOISE_PRESETS[noise]) & set(_get(cfg, "env.options") or {}))
    if both:
        raise ValueError(f"Invalid option env.noise={noise!r}: the preset sets "
                         f"env.options.{both[0]} itself; drop env.options.{both[0]} or use "
                         "env.noise=none.")
    overlap = _get(cfg, "collector.overlap", False)
    _require(isinstance(overlap, bool), "collector.overlap", overlap,
             "true (collect beside the optimisation, in a worker thread) or false")
    par = _get(cfg, "env.parallel", False)
    _require(isinstance(par, bool), "env.parallel", par, "true (ParallelEnv) or false (SerialEnv)")
    lr = _get(cfg, "optim.lr")
    _require(isinstance(lr, (int, float)) and lr > 0, "optim.lr", lr, "a number > 0")
    gate_mode = _get(cfg, "gate.mode")
    _require(gate_mode is None or gate_mode in GATE_MODES, "gate.mode", gate_mode,
             f"null or one of {GATE_MODES}")
    episodes = _get(cfg, "collector.total_episodes")
    _require(episodes is None or (isinstance(episodes, int) and episodes > 0),
             "collector.total_episodes", episodes, "null or an integer > 0")
    device = _get(cfg, "device")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        dev = None
    _require(dev is not None and dev.type in ("cpu", "cuda"), "device", device,
             "'cpu' or 'cuda' (or 'cuda:<index>')")
    _require(dev.type == "cpu" or torch.cuda.is_available(), "device", device,
             "'cpu' on this machine (torch.cuda.is_available() is False)")
    preset = _get(cfg, "preset_name")
    _require(preset in PRESETS, "preset", preset, f"one of {PRESETS}")
    reward = _get(cfg, "env.reward")
    _require(reward in REWARDS, "env.reward", reward, f"one of {REWARDS}")
    fn = _get(cfg, "loss.function")
    _require(fn in LOSS_FUNCTIONS, "loss.function", fn, f"one of {sorted(LOSS_FUNCTIONS)}")
    opt = _get(cfg, "optim.name")
    _require(opt in OPTIMIZERS, "optim.name", opt, f"one of {OPTIMIZERS}")
    fused = _get(cfg, "optim.fused", False)  # absent: a config from before the key
    _require(fused == "auto" or isinstance(fused, bool), "optim.fused", fused,
             "auto (Adam's fused kernel where it runs), true or false")
    _require(not (fused is True and opt == "rmsprop"), "optim.fused", fused,
             "auto or false with optim.name=rmsprop (PyTorch's RMSprop has no fused kernel)")
    kb = _get(cfg, "eval.keep_best")
    _require(isinstance(kb, bool), "eval.keep_best", kb, "true or false")
    fe = _get(cfg, "eval.final_episodes")
    _require(isinstance(fe, int) and not isinstance(fe, bool) and fe >= 0,
             "eval.final_episodes", fe, "an integer >= 0")
    dd = _get(cfg, "loss.double_dqn")
    _require(isinstance(dd, bool), "loss.double_dqn", dd, "true or false")
    rs = _get(cfg, "loss.reward_scale")
    _require(rs is None or (isinstance(rs, (int, float)) and not isinstance(rs, bool) and rs > 0),
             "loss.reward_scale", rs, "null (auto) or a number > 0")
    _check_can_learn(cfg)
    scene = _get(cfg, "env.layout")
    _require(scene in SCENES, "env.layout", scene, f"one of {sorted(SCENES)}")
    for scene in _get(cfg, "env.eval_layouts") or []:
        _require(scene in SCENES, "env.eval_layouts", scene, f"scenes among {sorted(SCENES)}")
    _check_scenes(cfg)
    _check_transfer(cfg, v)
    _check_teacher(cfg)
    logger = _get(cfg, "logger.backend")
    _require(logger in LOGGER_BACKENDS, "logger.backend", logger, f"one of {LOGGER_BACKENDS}")
    package = {"tensorboard": "tensorboard", "wandb": "wandb"}.get(logger)
    if package is not None:
        import importlib.util

        _require(importlib.util.find_spec(package) is not None, "logger.backend", logger,
                 f"an installed logger, but the {package!r} package is not installed "
                 f"(pip install -e '.[{package}]', or use logger.backend=csv)")
    stop = _get(cfg, "checkpoint.stop_after_frames")
    _require(stop is None or (isinstance(stop, int) and stop > 0),
             "checkpoint.stop_after_frames", stop, "null or an integer > 0")
    out = check_writable(output_dir)
    resume = _get(cfg, "checkpoint.resume")
    _require(isinstance(resume, bool) or resume == "auto", "checkpoint.resume", resume,
             "true, false or auto (resume when the run folder holds a checkpoint)")
    if resume is True:
        ckpt = out / RUN_LAYOUT["checkpoint"]
        _require(ckpt.is_file(), "checkpoint.resume", True,
                 f"an existing checkpoint, but {str(ckpt)!r} does not exist "
                 "(point output_dir at the folder of the run to resume)")
    return v


def resolve_resume(cfg: Mapping, output_dir: str | os.PathLike) -> bool:
    """Whether a run resumes: ``checkpoint.resume`` (``true`` / ``false``), or for
    ``auto`` whether ``output_dir`` holds a checkpoint (``reproduce.py`` sets ``auto``
    for every job of a grid, so interrupted runs resume and new ones start).
    """
    resume = _get(cfg, "checkpoint.resume")
    if resume == "auto":
        return (Path(output_dir) / RUN_LAYOUT["checkpoint"]).is_file()
    return bool(resume)


def reward_scale(cfg: Mapping) -> float:
    """``loss.reward_scale``, or for ``null`` the scale of the reward in use (:data:`AUTO_REWARD_SCALE`)."""
    scale = _get(cfg, "loss.reward_scale")
    if scale is None:
        return AUTO_REWARD_SCALE[_get(cfg, "env.reward")]
    return float(scale)


def _check_can_learn(cfg: Mapping) -> None:
    """Settings that cannot learn by construction: a clear error before any work.

    * ``loss.learning_starts >= collector.total_frames``: no gradient step ever;
    * a ``loss.target_update_interval`` longer than the run's gradient steps:
      the target network is never copied, so no value ever propagates.
    """
    total = _get(cfg, "collector.total_frames")
    starts = _get(cfg, "loss.learning_starts")
    if not (isinstance(total, int) and isinstance(starts, int)):
        return  # reported by the type checks
    _require(starts < total, "loss.learning_starts", starts,
             f"fewer frames than collector.total_frames={total} (no gradient step would run)")
    upf = _get(cfg, "loss.updates_per_frame")
    interval = _get(cfg, "loss.target_update_interval")
    if isinstance(upf, (int, float)) and upf > 0 and isinstance(interval, int):
        updates = int((total - starts) * upf)
        _require(interval <= updates, "loss.target_update_interval", interval,
                 f"at most the run's {updates} gradient steps ((collector.total_frames - "
                 f"loss.learning_starts) x loss.updates_per_frame): the target network would "
                 f"never be updated")


def _check_scenes(cfg: Mapping) -> None:
    """``eval.select_layout``, ``eval.fixed_episodes`` and ``env.options`` against the scenes."""
    layouts = list(_get(cfg, "env.eval_layouts") or [])
    sel = _get(cfg, "eval.select_layout")
    _require(sel is None or sel in layouts, "eval.select_layout", sel,
             f"null (the first of env.eval_layouts) or one of env.eval_layouts={layouts}")
    chosen = selection_scene(cfg)
    if chosen is not None and SCENES[chosen].get("split") == "heldout" and (
            sel is not None or _get(cfg, "eval.keep_best")):
        raise ValueError(
            f"Invalid option eval.select_layout={sel!r}: the selection scene {chosen!r} holds "
            "held-out layouts, and keep_best must not select on held-out layouts; select a "
            "scene of the training split, e.g. eval.select_layout=val with val in "
            "env.eval_layouts.")
    fixed = _get(cfg, "eval.fixed_episodes", False)
    _require(isinstance(fixed, bool), "eval.fixed_episodes", fixed,
             "true (the same episodes at every periodic evaluation) or false")
    options = _get(cfg, "env.options") or {}
    for scene in dict.fromkeys([_get(cfg, "env.layout"), *layouts]):
        for key, value in SCENES[scene].items():
            _require(key not in options, f"env.options.{key}", options.get(key),
                     f"unset: the scene {scene!r} sets {key}={value!r} itself")


def _check_teacher(cfg: Mapping) -> None:
    """``teacher.*`` (the DAgger phase) and ``features.inputs`` / ``features.history``."""
    rounds = _get(cfg, "teacher.rounds", 0)
    _require(isinstance(rounds, int) and not isinstance(rounds, bool) and rounds >= 0,
             "teacher.rounds", rounds, "an integer >= 0 (0: no teacher phase)")
    history = _get(cfg, "features.history", 0)
    _require(isinstance(history, int) and not isinstance(history, bool) and history >= 0,
             "features.history", history, "an integer >= 0 (0: no action history)")
    inputs = list(_get(cfg, "features.inputs", None) or ["causal_state"])
    allowed = ("causal_state", "causal_features", "action_history", "feature_history",
               "goal_memory", "map_clearance", "ego_map")
    for key in inputs:
        _require(key in allowed, "features.inputs", inputs, f"keys among {allowed}")
    shield = _get(cfg, "features.shield", False)
    _require(not shield or bool({"goal_memory", "map_clearance", "ego_map"} & set(inputs)),
             "features.shield", shield,
             "false unless features.inputs has an EgoMap input (goal_memory, map_clearance, "
             "ego_map)")
    loop_guard = _get(cfg, "features.loop_guard", False)
    _require(not loop_guard or history >= 4, "features.loop_guard", loop_guard,
             "false unless features.history >= 4 (LoopGuard reads the last four actions)")
    revisit_guard = _get(cfg, "features.revisit_guard", False)
    _require(isinstance(revisit_guard, bool) and (not revisit_guard or bool(
        {"goal_memory", "map_clearance", "ego_map"} & set(inputs))), "features.revisit_guard",
        revisit_guard, "false unless features.inputs has an EgoMap input (the guard reads its "
        "dead-reckoned pose)")
    goal_search = _get(cfg, "features.goal_search", 0.0)
    _require(isinstance(goal_search, (int, float)) and not isinstance(goal_search, bool)
             and math.isfinite(goal_search) and goal_search >= 0
             and (goal_search == 0 or bool({"goal_memory", "map_clearance", "ego_map"}
                                           & set(inputs))),
             "features.goal_search", goal_search,
             "0 (off) or a distance > 0 (m) with an EgoMap input in features.inputs")
    _require(not ("ego_map" in inputs and _get(cfg, "features.image", True)), "features.image",
             _get(cfg, "features.image", True), "false when ego_map is an input (MapQNet)")
    _require(("action_history" in inputs) == (history > 0), "features.inputs", inputs,
             f"action_history listed exactly when features.history > 0 "
             f"(features.history={history})")
    frames = _get(cfg, "features.frames", 0)
    _require(isinstance(frames, int) and not isinstance(frames, bool) and frames >= 0
             and frames != 1, "features.frames", frames, "0 (none) or an integer >= 2")
    _require(("feature_history" in inputs) == (frames > 0), "features.inputs", inputs,
             f"feature_history listed exactly when features.frames > 0 "
             f"(features.frames={frames})")
    if not rounds:
        return
    for key in ("teacher.episodes_per_round", "teacher.max_expansions"):
        val = _get(cfg, key)
        _require(isinstance(val, int) and not isinstance(val, bool) and val >= 1, key, val,
                 "an integer >= 1")
    for key in ("teacher.updates_per_frame", "teacher.lr"):
        val = _get(cfg, key)
        _require(isinstance(val, (int, float)) and not isinstance(val, bool) and val > 0, key,
                 val, "a number > 0")
    for key in ("teacher.margin", "teacher.td_weight"):
        val = _get(cfg, key)
        _require(isinstance(val, (int, float)) and not isinstance(val, bool) and val >= 0, key,
                 val, "a number >= 0")
    acts = _get(cfg, "teacher.actions")
    if acts is not None:
        from torchrl_causal.schema import ACTION_NAMES

        bad = [a for a in acts if a not in ACTION_NAMES]
        _require(not bad and len(acts) > 0, "teacher.actions", list(acts),
                 f"null or a non-empty list of actions among {ACTION_NAMES}")
    clearance = _get(cfg, "teacher.clearance", 0.0)
    _require(isinstance(clearance, (int, float)) and not isinstance(clearance, bool)
             and 0 <= clearance <= 0.5, "teacher.clearance", clearance, "metres in [0, 0.5]")
    weight = _get(cfg, "teacher.planner_weight", 1.2)
    _require(isinstance(weight, (int, float)) and not isinstance(weight, bool) and weight >= 1,
             "teacher.planner_weight", weight, "a number >= 1 (1: optimal A*)")
    beta = _get(cfg, "teacher.beta_decay")
    _require(isinstance(beta, (int, float)) and 0 <= beta <= 1, "teacher.beta_decay", beta,
             "a number in [0, 1]")
    _require(_get(cfg, "env.num_envs", 1) == 1, "env.num_envs", _get(cfg, "env.num_envs"),
             "1 with teacher.rounds > 0 (the oracle teacher flies one unbatched env)")
    execution = (_get(cfg, "env.options") or {}).get("execution", "kinematic")
    _require(execution == "kinematic", "env.options.execution", execution,
             "kinematic with teacher.rounds > 0 (the oracle plans kinematic moves)")


def _check_transfer(cfg: Mapping, variant: Variant) -> None:
    """``causal.transfer_from`` / ``causal.transfer_relearn``: the CBN files are read here."""
    relearn = _get(cfg, "causal.transfer_relearn", True)
    _require(isinstance(relearn, bool), "causal.transfer_relearn", relearn,
             "true (keep relearning from the transferred CBNs) or false (frozen)")
    src = _get(cfg, "causal.transfer_from")
    if src is None:
        return
    _require(isinstance(src, str) and bool(src), "causal.transfer_from", src,
             "null or the path of a run folder or of a folder of CBN (XMLBIF) files")
    _require(variant.causal_mode is not None, "causal.transfer_from", src,
             f"null for variant={variant.name}, which has no CBN to transfer into "
             "(use a cbn_* variant)")
    from torchrl_causal.causal.io import load_cbn_folder
    from torchrl_causal.schema import ACTION_NAMES, DEFAULT_SCHEMA

    try:
        load_cbn_folder(transfer_source(cfg), DEFAULT_SCHEMA, ACTION_NAMES)
    except ValueError as err:
        raise ValueError(_transfer_error(src, err)) from None


def _transfer_error(src: Any, err: Exception) -> str:
    return (f"Invalid option causal.transfer_from={src!r}: {err} (expected a run folder of a "
            "CBN variant, whose cbns/last holds its CBNs, or a folder of XMLBIF files)")


def exploration_kwargs(cfg: Mapping, variant: Variant) -> dict:
    """The epsilon schedule of the explorer (:class:`~torchrl.modules.EGreedyModule`
    or the CBN gate): ``eps_init``, ``eps_end`` and ``annealing_num_steps`` from
    ``exploration.*``; for a ``v2_epsilon`` variant (``dqn_features_v2eps``)
    ``eps_init`` and ``eps_end`` are scaled by ``1 - gate.prob_causal_model``.
    """
    scale = 1.0 - float(_get(cfg, "gate.prob_causal_model")) if variant.v2_epsilon else 1.0
    return dict(eps_init=float(_get(cfg, "exploration.eps_init")) * scale,
                eps_end=float(_get(cfg, "exploration.eps_end")) * scale,
                annealing_num_steps=int(_get(cfg, "exploration.annealing_frames")))


def selection_scene(cfg: Mapping) -> str | None:
    """The scene of the periodic evaluations that ``eval.keep_best`` selects on:
    ``eval.select_layout``, or when null the first of ``env.eval_layouts``."""
    layouts = list(_get(cfg, "env.eval_layouts") or [])
    return _get(cfg, "eval.select_layout") or (layouts[0] if layouts else None)


def eval_scenes(cfg: Mapping) -> list[str]:
    """``env.eval_layouts`` with :func:`selection_scene` first (the training loop
    evaluates the first evaluation env periodically and keeps the best on it)."""
    layouts = list(_get(cfg, "env.eval_layouts") or [])
    first = selection_scene(cfg)
    return [first] + [s for s in layouts if s != first] if first is not None else []


def transfer_source(cfg: Mapping) -> Path | None:
    """The folder of CBN files ``causal.transfer_from`` names: a run folder's
    ``cbns/last`` when it has one, else the folder itself; ``None`` when unset."""
    src = _get(cfg, "causal.transfer_from")
    if src is None:
        return None
    path = Path(str(src)).expanduser()
    run_cbns = path / RUN_LAYOUT["cbns"] / "last"
    return run_cbns if run_cbns.is_dir() else path


def transfer_cbns(cfg: Mapping, learner, gates=()) -> bool:
    """Starts ``learner`` from the CBNs of ``causal.transfer_from``
    (:meth:`~torchrl_causal.causal.CausalLearner.transfer`; ``causal.transfer_relearn``:
    keep relearning from them, or frozen) and hands the tables to ``gates``, so
    the gate is active from the first frame.

    Returns:
        Whether CBNs were transferred (``False`` when ``causal.transfer_from`` is null).

    Raises:
        ValueError: naming ``causal.transfer_from`` and its path, for a folder
            that cannot be transferred (see :func:`validate_config`).
    """
    folder = transfer_source(cfg)
    if folder is None:
        return False
    try:
        tables = learner.transfer(folder, relearn=_get(cfg, "causal.transfer_relearn", True))
    except ValueError as err:
        raise ValueError(_transfer_error(_get(cfg, "causal.transfer_from"), err)) from None
    for gate in gates:
        gate.set_tables(tables)
    return True


def gate_mode(cfg: Mapping, variant: Variant) -> str | None:
    """The gate algorithm of a run: ``gate.mode`` or, when null, the variant's own."""
    if variant.causal_mode is None:
        return None
    return _get(cfg, "gate.mode") or variant.default_gate


def prepare_run_dir(output_dir: str | os.PathLike) -> dict[str, Path]:
    """Creates the run folder's sub-folders; returns :data:`RUN_LAYOUT` as absolute paths."""
    root = Path(output_dir)
    paths = {name: root / rel for name, rel in RUN_LAYOUT.items()}
    for name in ("logs", "plots", "tables", "cbns"):
        paths[name].mkdir(parents=True, exist_ok=True)
    paths["checkpoint"].parent.mkdir(parents=True, exist_ok=True)
    return paths
