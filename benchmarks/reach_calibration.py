"""Where the RGB stack's goal distance should trigger "reached": a pose sweep at the thesis board.

The drone is placed at ``--poses`` random poses in front of the thesis scene's
board (along its normal from 0.35 m nearer to 0.45 m farther than the goal
point, up to 0.25 m sideways, yaw within 15 deg of facing it; plain 240 x 320
renders), and the RGB stack (YOLOv8 + MonoDepth, or ``--depth-weights``)
measures ``goal_distance`` -- the range :class:`~torchrl_causal.envs.ReachRule`
compares with ``max_distance``. For each threshold: the share of poses inside
the 0.2 m goal sphere where the rule would fire (``fire_inside``) and the share
outside it (``fire_outside``); the threshold with the largest difference
(Youden's J) is printed last. One JSON object per figure::

    python benchmarks/reach_calibration.py [--poses 200] [--depth-weights W.pt]

The sweep is :func:`torchrl_causal.envs.reach.calibrate_reach_distance`, the
one ``recipes/train_depth.py`` stores in the weights it writes and ``TelloEnv``
uses by default (docs/tello.rst, "A depth model needs its own threshold").
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--poses", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--depth-weights", default=None, help="MonoDepth weights (default: shipped)")
    a = p.parse_args(argv)
    if a.poses < 10:
        p.error(f"--poses must be >= 10, got {a.poses}")
    if a.depth_weights is not None and not os.path.isfile(a.depth_weights):
        p.error(f"--depth-weights {a.depth_weights!r}: no such file")
    import torch

    torch.set_num_threads(1)
    from torchrl_causal.envs.reach import calibrate_reach_distance
    from torchrl_causal.perception.depth import MonoDepth

    est = MonoDepth.load(a.depth_weights)
    cal = calibrate_reach_distance(est, poses=a.poses, seed=a.seed)
    name = a.depth_weights or "shipped"
    counts = {"n_inside": cal["n_inside"], "n_outside": cal["n_outside"]}
    rows = [{"bench": "reach_calibration", "figure": "threshold", "depth_weights": name,
             **r, **counts} for r in cal["thresholds"]]
    best = next(r for r in cal["thresholds"] if r["threshold_m"] == cal["max_distance"])
    stored = est.reach_distance
    rows.append({"bench": "reach_calibration", "figure": "best", "depth_weights": name,
                 "poses": a.poses, "seed": a.seed, **best, **counts,
                 "stored_max_distance": stored})
    for r in rows:
        print(json.dumps(r), flush=True)
    return rows


if __name__ == "__main__":
    main()
