"""Training throughput against this machine's limit, side by side in one run.

Prints one JSON object per figure:

* ``{"figure": "limit", ...}`` -- the parts of a training frame timed alone, in
  this run: one env step of the thesis scene (``env_step_ms``, 84x84 RGB-D,
  kinematic), the causal feature stack on it (``features_ms``), acting -- the
  thesis Q-network plus the CBN gate -- on 1 and on ``--envs`` observations
  (``acting_ms_1``, ``acting_ms_N``), and one minibatch DQN update of the thesis
  network (``update_ms``, batch 32: forward, backward, optimiser step, target
  sync). A frame cannot cost less than ``env + features + acting / envs +
  replay_ratio x update``: ``limit_fps`` for each replay ratio and env count
  (a run's own limit uses the gradient steps per frame it took: none before
  ``loss.learning_starts``);
* ``{"figure": "fps", ...}`` -- one per variant (``dqn_image``, ``cbn_v2``) x
  replay ratio (``--ratios``, default 0.25 and 1) x env count (1 and
  ``--envs``) x ``collector.overlap`` off / on (``--overlap``, default both,
  run back to back): frames per second of ``recipes/train.py``'s loop
  (:class:`torchrl_causal.training.DQNLoop`) and ``share_of_limit``
  (target >= 0.7 at replay ratio 0.25; the limit is that of the serial loop);
* ``{"figure": "overlap_gain", ...}`` -- per variant x ratio x env count:
  fps with overlap on / off (``ratio_on_off``);
* ``{"figure": "causal_overhead", ...}`` -- over the ``cbn_v2`` runs: the
  share of loop wall time spent in causal learning (the replay-buffer hook:
  adding transitions, relearning every k frames) and in the gate's forward
  (target: together <= 0.03), over the runs without overlap;
* with ``--levers``, ``{"figure": "lever", ...}`` -- the CPU levers timed
  against the loop's own code, A/B interleaved: acting under
  ``torch.inference_mode``, the thesis CNN in channels-last, ``torch.compile``
  of the Q-network (``ratio`` = lever / baseline time; < 1 helps).

Every run uses the same frames, seed and options (thesis scene, k = 200, no
evaluation, no checkpoints). The machine is shared and noisy: compare figures
of one invocation only.

Usage::

    python benchmarks/training.py [--frames 1000] [--envs 4] [--ratios 0.25 1] [--threads N]
        [--overlap off|on|both] [--single-env-only] [--levers] [--device cuda]

``--device cuda`` puts the Q-network, the buffer samples, the gate and the timed
update on the GPU (the recipe's ``device=cuda``; the simulator and the feature
stack stay on the CPU); device work is synchronised before each timing.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402

import train as recipe  # noqa: E402


def _cfg(variant: str, overrides: list[str]):
    with initialize_config_dir(config_dir=recipe.CONFIG_DIR, version_base=None):
        return compose(config_name=variant, overrides=overrides)


def _sync() -> None:
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()  # time the device's work, not its queueing


def _median_ms(fn, n: int, warmup: int = 5) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(n):
        _sync()
        t0 = time.perf_counter()
        fn()
        _sync()
        times.append(time.perf_counter() - t0)
    return 1000.0 * float(np.median(times))


def measure_limit(n_envs: int, steps: int = 200, device: str = "cpu") -> dict:
    """Each part of a training frame timed alone (median ms); the network, the gate and
    the update on ``device``, the simulator and the features on the CPU."""
    import recipe_utils as ru
    from tensordict.nn import TensorDictSequential
    from torchrl.envs.utils import step_mdp

    with tempfile.TemporaryDirectory() as tmp:
        cfg = _cfg("cbn_v2", [f"output_dir={tmp}"])
    variant = ru.VARIANTS["cbn_v2"]
    env = recipe.build_env(cfg, variant, "thesis", "cpu")
    base = env.base_env
    rng = np.random.default_rng(0)

    def stepper(e):
        state = {"td": e.reset()}

        def step():
            td = state["td"].set("action", torch.tensor(int(rng.integers(8))))
            out = e.step(td)
            state["td"] = e.reset() if bool(out["next", "done"]) else step_mdp(out)

        return step

    full_ms = _median_ms(stepper(env), steps)
    base_ms = _median_ms(stepper(base), steps)
    actor, gate, hook = recipe.build_agent(cfg, variant, env, device)
    policy = TensorDictSequential(actor, gate)
    obs = env.reset()
    acting = {}
    for n in sorted({1, n_envs}):
        batch = obs.expand(n).clone() if n > 1 else obs

        def act(b=batch):  # the observation goes to the device, as in the collector
            with torch.no_grad():
                policy(b.clone(False).to(device))

        acting[n] = _median_ms(act, steps)
    loss, optim = recipe.build_loss(cfg, actor, env)
    rollout = env.rollout(40, lambda td: policy(td.to(device)).to("cpu"),
                          break_when_any_done=False)
    sample = rollout[torch.randint(0, 40, (cfg.buffer.batch_size,))].to(device)
    from torchrl.objectives import HardUpdate

    updater = HardUpdate(loss, value_network_update_interval=cfg.loss.target_update_interval)

    def update():
        out = loss(sample.clone(False))
        out["loss"].backward()
        torch.nn.utils.clip_grad_norm_(loss.parameters(), cfg.loss.max_grad_norm)
        optim.step()
        optim.zero_grad(set_to_none=True)
        updater.step()

    update_ms = _median_ms(update, 30)
    return {"env_step_ms": base_ms, "features_ms": max(full_ms - base_ms, 0.0),
            "acting_ms": acting, "update_ms": update_ms}


def _interleaved(variants: dict, reps: int, calls: int) -> dict:
    """Median ms per call of each variant, A/B/... interleaved ``reps`` times
    (each rep: the median of ``calls`` calls), so load changes hit all alike."""
    for fn in variants.values():  # warm-up
        for _ in range(3):
            fn()
    out = {name: [] for name in variants}
    for _ in range(reps):
        for name, fn in variants.items():
            out[name].append(_median_ms(fn, calls, warmup=0))
    return {name: float(np.median(v)) for name, v in out.items()}


def measure_concurrency(env, policy, update, steps: int = 150, updates: int = 15,
                        reps: int = 3) -> dict:
    """Do env steps + acting (one thread) and updates (another) run side by side?

    Times ``steps`` env steps with acting alone, ``updates`` updates alone, and
    both at once in two threads (what ``overlap`` does), ``reps`` times
    interleaved. ``overlap_efficiency`` = (alone_sum - together) / min(alone):
    1 when the two fully overlap (MuJoCo and torch release the GIL and a core
    is free), 0 when they serialise.
    """
    import threading

    from torchrl.envs.utils import step_mdp

    state = {"td": env.reset()}

    def collect():
        for _ in range(steps):
            with torch.no_grad():
                td = policy(state["td"].clone(False))
            out = env.step(td)
            state["td"] = env.reset() if bool(out["next", "done"]) else step_mdp(out)

    def learn():
        for _ in range(updates):
            update()

    def timed(fn):
        t0 = time.perf_counter()
        fn()
        return time.perf_counter() - t0

    def both():
        worker = threading.Thread(target=collect)
        worker.start()
        learn()
        worker.join()

    res = {"collect": [], "learn": [], "both": []}
    for _ in range(reps):
        res["collect"].append(timed(collect))
        res["learn"].append(timed(learn))
        res["both"].append(timed(both))
    c, u, b = (float(np.median(res[k])) for k in ("collect", "learn", "both"))
    return {"figure": "concurrency", "env_steps": steps, "updates": updates,
            "collect_alone_s": round(c, 3), "updates_alone_s": round(u, 3),
            "together_s": round(b, 3), "serial_sum_s": round(c + u, 3),
            "overlap_efficiency": round((c + u - b) / min(c, u), 3),
            "torch_threads": torch.get_num_threads(), "cpu_count": os.cpu_count()}


def measure_levers(reps: int = 7, calls: int = 20, compile_net: bool = True) -> list[dict]:
    """The CPU levers of issue 9, each against the loop's own code, side by side.

    * ``inference_mode``: acting (thesis CNN + 9 features + CBN gate, 1 obs) under
      ``torch.inference_mode`` against ``torch.no_grad`` (the Collector's);
    * ``channels_last``: the thesis CNN's weights in channels-last memory format,
      for acting and for one batch-32 update;
    * ``compile``: ``torch.compile`` of the Q-network, for acting and the update
      (plus the one-off compile seconds).

    Returns one figure per lever with ``ratio`` = lever time / baseline time
    (< 1: the lever helps).
    """
    import copy

    import recipe_utils as ru
    from tensordict.nn import TensorDictSequential

    with tempfile.TemporaryDirectory() as tmp:
        cfg = _cfg("cbn_v2", [f"output_dir={tmp}"])
    variant = ru.VARIANTS["cbn_v2"]
    env = recipe.build_env(cfg, variant, "thesis", "cpu")
    actor, gate, _ = recipe.build_agent(cfg, variant, env, "cpu")
    policy = TensorDictSequential(actor, gate)
    rollout = env.rollout(64, policy, break_when_any_done=False)
    obs = env.reset()
    sample = rollout[torch.randint(0, 64, (cfg.buffer.batch_size,))]

    def acting(pol, ctx):
        def fn():
            with ctx():
                pol(obs.clone(False))
        return fn

    def updating(act):
        loss, optim = recipe.build_loss(cfg, act, env)

        def fn():
            out = loss(sample.clone(False))
            out["loss"].backward()
            optim.step()
            optim.zero_grad(set_to_none=True)
        return fn

    figures = [measure_concurrency(env, policy, updating(copy.deepcopy(actor)))]
    t = _interleaved({"no_grad": acting(policy, torch.no_grad),
                      "inference_mode": acting(policy, torch.inference_mode)}, reps, calls)
    figures.append({"figure": "lever", "lever": "inference_mode", "part": "acting_1",
                    "baseline_ms": round(t["no_grad"], 3), "lever_ms": round(t["inference_mode"], 3),
                    "ratio": round(t["inference_mode"] / t["no_grad"], 3)})
    # ... and per frame of a Collector (env step + features + acting), as DQNLoop
    # collects (it acts under inference mode: torchrl_causal.training.loop._collect)
    from torchrl.collectors import Collector

    collector = Collector(env, policy, frames_per_batch=1, total_frames=-1,
                          auto_register_policy_transforms=False)
    batches = iter(collector)

    def frame(ctx):
        def fn():
            with ctx():
                next(batches)
        return fn

    t = _interleaved({"no_grad": frame(torch.no_grad),
                      "inference_mode": frame(torch.inference_mode)}, reps, calls * 5)
    collector.shutdown()
    figures.append({"figure": "lever", "lever": "inference_mode", "part": "collector_frame",
                    "baseline_ms": round(t["no_grad"], 3), "lever_ms": round(t["inference_mode"], 3),
                    "ratio": round(t["inference_mode"] / t["no_grad"], 3)})
    cl_actor = copy.deepcopy(actor)
    cl_actor.module.to(memory_format=torch.channels_last)
    cl_policy = TensorDictSequential(cl_actor, gate)
    t = _interleaved({"base": acting(policy, torch.no_grad),
                      "lever": acting(cl_policy, torch.no_grad)}, reps, calls)
    u = _interleaved({"base": updating(copy.deepcopy(actor)),
                      "lever": updating(cl_actor)}, reps, max(calls // 4, 5))
    for part, res in (("acting_1", t), ("update_32", u)):
        figures.append({"figure": "lever", "lever": "channels_last", "part": part,
                        "baseline_ms": round(res["base"], 3), "lever_ms": round(res["lever"], 3),
                        "ratio": round(res["lever"] / res["base"], 3)})
    if compile_net:
        from torchrl_causal.modules import ThesisQNet

        co_actor = copy.deepcopy(actor)
        for m in co_actor.modules():  # the TensorDictModule around the Q-network
            if isinstance(getattr(m, "module", None), ThesisQNet):
                m.module = torch.compile(m.module)
        co_policy = TensorDictSequential(co_actor, gate)
        t0 = time.perf_counter()
        co_update = updating(co_actor)
        with torch.no_grad():
            co_policy(obs.clone(False))
        co_update()
        compile_s = time.perf_counter() - t0
        t = _interleaved({"base": acting(policy, torch.no_grad),
                          "lever": acting(co_policy, torch.no_grad)}, reps, calls)
        u = _interleaved({"base": updating(copy.deepcopy(actor)), "lever": co_update},
                         reps, max(calls // 4, 5))
        for part, res in (("acting_1", t), ("update_32", u)):
            figures.append({"figure": "lever", "lever": "torch.compile", "part": part,
                            "baseline_ms": round(res["base"], 3),
                            "lever_ms": round(res["lever"], 3),
                            "ratio": round(res["lever"] / res["base"], 3),
                            "compile_seconds": round(compile_s, 1)})
    return figures


def limit_fps(parts: dict, ratio: float, n_envs: int) -> float:
    """The most frames per second a loop can reach here: nothing but the parts.

    ``ratio`` is the gradient steps per frame actually taken (a run takes none
    before ``loss.learning_starts``)."""
    ms = (parts["env_step_ms"] + parts["features_ms"] + parts["acting_ms"][n_envs] / n_envs
          + ratio * parts["update_ms"])
    return 1000.0 / ms


def run(variant: str, frames: int, ratio: float, n_envs: int, out: Path,
        threads: int | None, overlap: bool = False, device: str = "cpu") -> dict:
    overrides = [
        f"output_dir={out}", f"collector.total_frames={frames}", "eval.episodes=0",
        "eval.final_episodes=0", "eval.keep_best=false", "checkpoint.interval_frames=0",
        "outputs.draw_cbns=false", "outputs.videos=0", "logger.backend=none", "progress=false",
        "loss.learning_starts=200", "loss.target_update_interval=50",
        f"exploration.annealing_frames={frames}", f"loss.updates_per_frame={ratio}",
        f"env.num_envs={n_envs}", f"collector.frames_per_batch={n_envs}",
        f"collector.overlap={str(overlap).lower()}", f"device={device}",
    ]
    if threads:
        overrides.append(f"threads={threads}")
    return recipe.train(_cfg(variant, overrides))


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=int, default=1000, help="frames per run")
    p.add_argument("--envs", type=int, default=4, help="env count of the batched runs")
    p.add_argument("--ratios", type=float, nargs="+", default=[0.25, 1.0],
                   help="replay ratios (gradient steps per frame)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--overlap", choices=("off", "on", "both"), default="both",
                   help="collector.overlap of the fps runs (both: off and on, paired)")
    p.add_argument("--single-env-only", action="store_true",
                   help="skip the --envs runs (1 env only)")
    p.add_argument("--device", default="cpu",
                   help="where the network, the buffer samples and the gate run (cpu, cuda, "
                        "cuda:N; the simulator stays on the CPU)")
    p.add_argument("--levers", action="store_true",
                   help="also time the CPU levers (inference mode, channels-last, torch.compile)")
    args = p.parse_args(argv)
    if args.frames < 400:
        p.error(f"Invalid option --frames={args.frames}: expected >= 400 (k = 200)")
    if args.envs < 2:
        p.error(f"Invalid option --envs={args.envs}: expected >= 2 (1 env is always measured)")
    if any(r <= 0 for r in args.ratios):
        p.error(f"Invalid option --ratios={args.ratios}: replay ratios must be > 0")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        p.error(f"Invalid option --device={args.device}: CUDA is not available on this machine")
    if not (args.device == "cpu" or args.device.startswith("cuda")):
        p.error(f"Invalid option --device={args.device}: expected cpu, cuda or cuda:N")
    if args.threads:
        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    figures = []

    def emit(obj):
        figures.append(obj)
        print(json.dumps(obj), flush=True)

    parts = measure_limit(args.envs, device=args.device)
    env_counts = (1,) if args.single_env_only else (1, args.envs)
    overlaps = {"off": (False,), "on": (True,), "both": (False, True)}[args.overlap]
    emit({
        "figure": "limit", "env_step_ms": round(parts["env_step_ms"], 3),
        "features_ms": round(parts["features_ms"], 3),
        "acting_ms_1": round(parts["acting_ms"][1], 3),
        f"acting_ms_{args.envs}": round(parts["acting_ms"][args.envs], 3),
        "update_ms": round(parts["update_ms"], 3),
        "limit_fps": {f"ratio_{r}_envs_{n}": round(limit_fps(parts, r, n), 2)
                      for r in args.ratios for n in env_counts},
        "device": args.device,
        "gpu": torch.cuda.get_device_name(args.device) if args.device.startswith("cuda") else None,
        "threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
        "python": platform.python_version(), "torch": torch.__version__,
    })
    causal = {"wall": 0.0, "causal": 0.0, "gating": 0.0, "relearns": 0}
    paired = {}
    with tempfile.TemporaryDirectory() as tmp:
        i = 0
        for ratio in args.ratios:
            for n in env_counts:
                for variant, overlap in [(v, o) for v in ("dqn_image", "cbn_v2")
                                         for o in overlaps]:
                    i += 1
                    s = run(variant, args.frames, ratio, n, Path(tmp) / str(i), args.threads,
                            overlap, args.device)
                    fps = s["frames"] / s["loop_seconds"]
                    # the limit of this run: its own gradient steps per frame (none
                    # are taken before loss.learning_starts)
                    lim = limit_fps(parts, s["updates"] / s["frames"], n)
                    emit({"figure": "fps", "variant": variant, "replay_ratio": ratio,
                          "num_envs": n, "overlap": overlap, "frames": s["frames"],
                          "updates": s["updates"], "fps": round(fps, 2),
                          "limit_fps": round(lim, 2), "share_of_limit": round(fps / lim, 3),
                          "target_share_of_limit": 0.7 if ratio == 0.25 else None,
                          "optimisation_share": round(s["optimisation_seconds"]
                                                      / s["loop_seconds"], 3),
                          "collection_share": round(s["collection_seconds"]
                                                    / s["loop_seconds"], 3),
                          "worker_collection_share": round(s["worker_collection_seconds"]
                                                           / s["loop_seconds"], 3)})
                    paired[(variant, ratio, n, overlap)] = fps
                    if overlap and (variant, ratio, n, False) in paired:
                        off = paired[(variant, ratio, n, False)]
                        emit({"figure": "overlap_gain", "variant": variant,
                              "replay_ratio": ratio, "num_envs": n, "fps_off": round(off, 2),
                              "fps_on": round(fps, 2), "ratio_on_off": round(fps / off, 3)})
                    if variant == "cbn_v2" and not overlap:
                        causal["wall"] += s["loop_seconds"]
                        causal["causal"] += s["causal_learning_seconds"]
                        causal["gating"] += s["gating_seconds"]
                        causal["relearns"] += s["n_relearns"]
    emit({
        "figure": "causal_overhead", "runs": len(args.ratios) * len(env_counts),
        "overlap": False,
        "relearns": causal["relearns"],
        "causal_learning_share": round(causal["causal"] / causal["wall"], 4),
        "gating_share": round(causal["gating"] / causal["wall"], 4),
        "causal_overhead_share": round((causal["causal"] + causal["gating"]) / causal["wall"], 4),
        "target_causal_overhead_share": 0.03,
        "total_seconds": round(time.perf_counter() - t0, 1),
    })
    if args.levers:
        for fig in measure_levers():
            emit(fig)
    return figures


if __name__ == "__main__":
    main()
