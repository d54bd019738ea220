"""Does the CBN gate change learning? Five variants and an ablation on the grid world, many seeds, in minutes.

Trains, with :class:`torchrl_causal.training.DQNLoop`, a DQN on
``torchrl_causal/GridNav-v0`` (:class:`~torchrl_causal.envs.GridNavEnv`, whose
causal structure is known) with:

* ``dqn`` -- no gate (epsilon-greedy, :class:`~torchrl.modules.EGreedyModule`);
* ``expert`` -- the expert CBNs (:func:`~torchrl_causal.envs.gridnav_expert_dags`,
  CPTs fitted from data at every relearn) and the V2 gate (Alg. 4);
* ``p`` / ``pn`` / ``v2`` -- learned CBNs (Alg. 2) with the gate of Alg. 3
  (P, PN) or Alg. 4 (V2);
* ``dqn_v2eps`` -- an ablation: no gate, epsilon scaled by ``1 - 0.7``. Once
  its CBNs know every action, Alg. 4 takes the (vetoed) greedy action with
  probability 0.7 and only the rest of the time is epsilon-greedy, so its
  effective epsilon is ``0.3 x epsilon``; this variant has that exploration
  without any CBN;

for ``--seeds`` seeds each, and prints one JSON object per variant:

* ``episodes_to_threshold`` -- per seed, the training episodes until the success
  rate of the last ``--window`` training episodes first reaches
  ``--threshold`` (null if never), with ``median`` and the number of seeds
  that got there;
* ``final_greedy_success`` -- mean and 95% CI over seeds of the greedy policy's
  success over ``--eval-episodes`` episodes after training (gate on);
* ``train_success`` / ``train_crash`` -- share of all training episodes;
* ``gate_vetoed`` / ``gate_replaced`` -- share of training steps where the
  gate vetoed / replaced the DQN's action; ``wall_seconds`` per run.

``--plot`` writes the mean training-success curves (95% CI bands) to a PNG.

Usage::

    python benchmarks/gridnav.py                       # 6 variants x 10 seeds
    python benchmarks/gridnav.py --variants dqn v2 --seeds 3 --frames 3000
    python benchmarks/gridnav.py --plot docs/_static/results/gridnav_success.png
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recipes"))
import results  # noqa: E402  (recipes/results.py: the CI helper the figures share)

VARIANTS = ("dqn", "expert", "p", "pn", "v2", "dqn_v2eps")
#: The V2 gate's consult probability (thesis ProbCausalModel, CBNGate's default).
PROB_CAUSAL_MODEL = 0.7


#: The grid world of the benchmark: the default 7x7 map, the goal in its top-right corner.
ENV_OPTIONS = {"goal": (0, 6)}


def build_loop(variant: str, seed: int, frames: int, output_dir=None, **overrides):
    """The DQNLoop of one grid-world run (the tutorial's code, in one place)."""
    import torch
    from torchrl.modules import MLP, EGreedyModule, QValueActor

    from torchrl_causal.causal import CausalLearner
    from torchrl_causal.data import CausalLearningHook
    from torchrl_causal.envs import (GRIDNAV_ACTIONS, GRIDNAV_SCHEMA, gridnav_expert_dags,
                                     make_gridnav_env)
    from torchrl_causal.modules import CBNGate
    from torchrl_causal.training import DQNLoop, LoopConfig

    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    torch.manual_seed(seed)
    env = make_gridnav_env(seed=seed, **ENV_OPTIONS)
    n_obs = env.observation_spec["observation"].shape[-1]
    actor = QValueActor(MLP(in_features=n_obs, out_features=4, num_cells=[64, 64]),
                        in_keys=["observation"], spec=env.action_spec)
    scale = 1.0 - PROB_CAUSAL_MODEL if variant == "dqn_v2eps" else 1.0
    eps = dict(eps_init=1.0 * scale, eps_end=0.05 * scale, annealing_num_steps=frames // 2)
    hook = None
    if variant in ("dqn", "dqn_v2eps"):
        explorer = EGreedyModule(env.action_spec, **eps)
    else:
        explorer = CBNGate("v2" if variant == "expert" else variant, seed=seed,
                           prob_causal_model=PROB_CAUSAL_MODEL, **eps)
        learner = CausalLearner(GRIDNAV_SCHEMA, 4, action_names=GRIDNAV_ACTIONS,
                                mode="defined" if variant == "expert" else "learned",
                                expert_dags=gridnav_expert_dags())
        hook = CausalLearningHook(learner, k=200, gates=[explorer])
    config = dict(total_frames=frames, learning_starts=200, updates_per_frame=0.5,
                  target_update_interval=100, gamma=0.9, lr=1e-3, buffer_size=frames,
                  eval_interval_frames=0, eval_episodes=0, final_eval_episodes=50,
                  checkpoint_interval_frames=0, keep_best=False, seed=seed)
    config.update(overrides)
    return DQNLoop(env, actor, explorer, hook=hook, config=LoopConfig(**config),
                   output_dir=output_dir,
                   eval_envs={"gridnav": lambda: make_gridnav_env(seed=seed + 10_000, **ENV_OPTIONS)})


def episodes_to_threshold(success, window: int, threshold: float):
    """First training episode at which the mean success of the last ``window`` reaches ``threshold``."""
    for i in range(window, len(success) + 1):
        if sum(success[i - window:i]) / window >= threshold:
            return i
    return None


def run_one(variant: str, seed: int, frames: int, window: int, threshold: float) -> dict:
    import pandas as pd
    import torch

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        summary = build_loop(variant, seed, frames, output_dir=tmp).run()
        wall = time.perf_counter() - t0
        eps = pd.read_csv(Path(tmp) / "episodes.csv")
    success = eps["success"].astype(int).tolist()
    return {
        "variant": variant, "seed": seed, "wall_seconds": wall,
        "episodes": len(success),
        "episodes_to_threshold": episodes_to_threshold(success, window, threshold),
        "final_greedy_success": summary["final_eval"]["gridnav"]["success_rate"],
        "success": success, "crash": eps["crash"].astype(int).tolist(),
        "gate_vetoed": float((eps.get("gate_frac_vetoed", 0) * eps["length"]).sum()
                             / eps["length"].sum()),
        "gate_replaced": float((eps.get("gate_frac_replaced", 0) * eps["length"]).sum()
                               / eps["length"].sum()),
    }


def mean_ci95(values) -> tuple[float, float]:
    """Mean over seeds and the half-width of its 95 % CI (the recipes' :func:`results.mean_ci95`;
    0 for one seed)."""
    mean, half = results.mean_ci95(np.asarray(values, dtype=float)[:, None])
    return float(mean[0]), (0.0 if len(values) == 1 else float(half[0]))


def aggregate(runs, window: int, threshold: float) -> dict:
    reached = [r["episodes_to_threshold"] for r in runs]
    got = [e for e in reached if e is not None]
    fin_m, fin_ci = mean_ci95([r["final_greedy_success"] for r in runs])
    n_eps = sum(len(r["success"]) for r in runs)
    return {
        "variant": runs[0]["variant"], "seeds": [r["seed"] for r in runs],
        "threshold": threshold, "window": window,
        "episodes_to_threshold": reached,
        "episodes_to_threshold_median": statistics.median(got) if got else None,
        "seeds_reaching_threshold": len(got),
        "final_greedy_success_mean": fin_m, "final_greedy_success_ci95": fin_ci,
        "train_success": sum(map(sum, (r["success"] for r in runs))) / n_eps,
        "train_crash": sum(map(sum, (r["crash"] for r in runs))) / n_eps,
        "gate_vetoed": statistics.fmean(r["gate_vetoed"] for r in runs),
        "gate_replaced": statistics.fmean(r["gate_replaced"] for r in runs),
        "wall_seconds": statistics.fmean(r["wall_seconds"] for r in runs),
    }


def plot(by_variant: dict, path: Path, window: int) -> None:
    """Mean moving success (``window`` episodes) per variant over training episodes, 95% CI."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for variant, runs in by_variant.items():
        n = min(len(r["success"]) for r in runs)
        curves = np.array([np.convolve(r["success"][:n], np.ones(window) / window, "valid")
                           for r in runs])
        x = np.arange(window, n + 1)
        m, half = results.mean_ci95(curves)
        half = np.nan_to_num(half)  # one seed: no band
        ax.plot(x, m, label=f"{variant} ({len(runs)} seeds)")
        ax.fill_between(x, m - half, m + half, alpha=0.2)
    ax.set_xlabel("training episode")
    ax.set_ylabel(f"success (moving mean of {window})")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    ax.set_title("GridNav-v0: training success, mean and 95% CI over seeds")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    p.add_argument("--seeds", type=int, default=10, help="seeds 0..N-1 per variant")
    p.add_argument("--frames", type=int, default=4000, help="training frames per run")
    p.add_argument("--window", type=int, default=20)
    p.add_argument("--threshold", type=float, default=0.8)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--plot", type=Path, default=None)
    p.add_argument("--json-out", type=Path, default=None, help="also write the objects here")
    args = p.parse_args(argv)
    if args.seeds < 1 or args.frames < 500 or args.jobs < 1 or not 0 < args.threshold <= 1:
        p.error(f"need --seeds >= 1, --frames >= 500, --jobs >= 1, 0 < --threshold <= 1; got "
                f"{args.seeds}, {args.frames}, {args.jobs}, {args.threshold}")
    jobs = [(v, s) for v in args.variants for s in range(args.seeds)]
    with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn")) as ex:
        runs = list(ex.map(run_one, *zip(*jobs), *[[x] * len(jobs) for x in
                                                    (args.frames, args.window, args.threshold)]))
    by_variant = {v: [r for r in runs if r["variant"] == v] for v in args.variants}
    lines = []
    for v, rs in by_variant.items():
        obj = aggregate(rs, args.window, args.threshold)
        obj["frames"] = args.frames
        lines.append(json.dumps(obj))
        print(lines[-1], flush=True)
    if args.json_out:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        args.json_out.write_text("\n".join(lines) + "\n")
    if args.plot:
        plot(by_variant, args.plot, args.window)
    return 0


if __name__ == "__main__":
    sys.exit(main())
