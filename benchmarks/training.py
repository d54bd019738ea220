"""Training throughput: ``dqn_image`` vs ``cbn_v2`` side by side, and the causal overhead.

Runs ``recipes/train.py``'s :func:`train` four times in this process, with the
same frames, seed and options (thesis scene, k = 200, one gradient step every 4
frames, batch 32, no evaluation, no checkpoints), in the order ``dqn_image``,
``cbn_v2``, ``cbn_v2``, ``dqn_image``, and prints one JSON line (sums over the
two runs of each variant):

* ``fps_dqn_image`` / ``fps_cbn_v2``: frames per second of the training loop
  (collection + replay buffer + optimisation);
* ``causal_learning_share``: share of ``cbn_v2``'s loop wall time spent in
  causal learning (the replay-buffer hook: adding transitions to the learner
  and relearning every k frames);
* ``gating_share``: share spent in the CBN gate's forward (it also does the
  epsilon-greedy draw that ``EGreedyModule`` does for ``dqn_image``);
* ``causal_overhead_share``: the sum of the two; target <= 0.05;
* ``optimisation_share_*`` / ``collection_share_*``: where the rest goes
  (gradient steps; policy + env + feature transforms).

The runs are sequential on a shared machine: compare the fps of runs
measured in the same invocation only.

Usage::

    python benchmarks/training.py [--frames 1000] [--threads N]
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
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))

import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402

import train as recipe  # noqa: E402


def run(variant: str, frames: int, out: Path, threads: int | None) -> dict:
    overrides = [
        f"output_dir={out / variant}",
        f"collector.total_frames={frames}",
        "eval.episodes=0",
        "checkpoint.interval_frames=0",
        "outputs.draw_cbns=false",
        "logger.backend=none",
        "progress=false",
        "loss.learning_starts=200",
        f"exploration.annealing_frames={frames}",
    ]
    if threads:
        overrides.append(f"threads={threads}")
    with initialize_config_dir(config_dir=recipe.CONFIG_DIR, version_base=None):
        cfg = compose(config_name=variant, overrides=overrides)
    return recipe.train(cfg)


def _sum(summaries: list[dict]) -> dict:
    keys = ("frames", "n_relearns", "loop_seconds", "optimisation_seconds",
            "collection_seconds", "causal_learning_seconds", "gating_seconds")
    return {k: sum(s[k] for s in summaries) for k in keys}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=int, default=1000, help="frames per run")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    args = p.parse_args(argv)
    if args.frames < 400:
        raise ValueError(f"Invalid option --frames={args.frames}: expected >= 400 (k = 200)")
    t0 = time.perf_counter()
    runs: dict[str, list[dict]] = {"dqn_image": [], "cbn_v2": []}
    with tempfile.TemporaryDirectory() as tmp:
        # A B B A order, so a change of machine load hits both variants alike
        for i, variant in enumerate(("dqn_image", "cbn_v2", "cbn_v2", "dqn_image")):
            runs[variant].append(run(variant, args.frames, Path(tmp) / str(i), args.threads))
    dqn, cbn = _sum(runs["dqn_image"]), _sum(runs["cbn_v2"])
    wall = cbn["loop_seconds"]
    causal = cbn["causal_learning_seconds"] / wall
    gating = cbn["gating_seconds"] / wall
    result = {
        "benchmark": "training",
        "frames_per_variant": dqn["frames"],
        "fps_dqn_image": round(dqn["frames"] / dqn["loop_seconds"], 2),
        "fps_cbn_v2": round(cbn["frames"] / wall, 2),
        "cbn_v2_relearns": cbn["n_relearns"],
        "causal_learning_share": round(causal, 4),
        "gating_share": round(gating, 4),
        "causal_overhead_share": round(causal + gating, 4),
        "target_causal_overhead_share": 0.05,
        "optimisation_share_dqn_image": round(dqn["optimisation_seconds"] / dqn["loop_seconds"], 4),
        "optimisation_share_cbn_v2": round(cbn["optimisation_seconds"] / wall, 4),
        "collection_share_dqn_image": round(dqn["collection_seconds"] / dqn["loop_seconds"], 4),
        "collection_share_cbn_v2": round(cbn["collection_seconds"] / wall, 4),
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "total_seconds": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
