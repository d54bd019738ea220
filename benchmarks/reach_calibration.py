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

This is how ``TelloEnv``'s 0.45 m default compares with a depth model's own
best threshold (docs/tello.rst, "Which model, measured").
"""

from __future__ import annotations

import argparse
import json
import math
import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only


def sweep(poses: int, seed: int, depth_weights=None) -> list[dict]:
    """One row per pose: distance to the goal point, goal in sight, measured goal distance."""
    import numpy as np
    import torch
    from tensordict import TensorDict

    from torchrl_causal.envs import DroneNavEnv
    from torchrl_causal.perception.dataset import _quat
    from torchrl_causal.perception.depth import MonoDepth
    from torchrl_causal.transforms import make_causal_transforms

    env = DroneNavEnv("thesis", image_size=(240, 320), seed=0)
    env.reset()
    lay = env.layout
    gp, gc = np.array(lay.goal_point()), np.array(lay.goal_center)
    normal = (gp - gc)[:2] / np.linalg.norm((gp - gc)[:2])
    side = np.array([-normal[1], normal[0]])
    stack = make_causal_transforms(env, perception="rgb",
                                   depth_estimator=MonoDepth.load(depth_weights))
    rng = np.random.default_rng(seed)
    qa = env.ids.qpos_adr
    rows = []
    for _ in range(poses):
        ahead, lat = rng.uniform(-0.35, 0.45), rng.uniform(-0.25, 0.25)
        yaw = math.degrees(math.atan2(-normal[1], -normal[0])) + rng.uniform(-15, 15)
        xy = gp[:2] + ahead * normal + lat * side
        env.data.qpos[qa:qa + 3] = (xy[0], xy[1], gp[2])
        env.data.qpos[qa + 3:qa + 7] = _quat(yaw, 0.0, 0.0)
        obs = env._observe(False, False)
        with torch.no_grad():
            td = stack(TensorDict(dict(obs.items()), []).unsqueeze(0))[0]
        rows.append({"to_goal_point_m": float(math.hypot(ahead, lat)),
                     "in_sight": bool(td["goal_in_sight"].item()),
                     "measured_m": float(td["goal_distance"].item())})
    env.close()
    return rows


def thresholds(rows, grid) -> list[dict]:
    inside = [r for r in rows if r["in_sight"] and r["to_goal_point_m"] <= 0.2]
    outside = [r for r in rows if r["in_sight"] and r["to_goal_point_m"] > 0.2]
    out = []
    for t in grid:
        fin = sum(r["measured_m"] <= t for r in inside) / max(1, len(inside))
        fout = sum(r["measured_m"] <= t for r in outside) / max(1, len(outside))
        out.append({"threshold_m": round(t, 3), "fire_inside": round(fin, 3),
                    "fire_outside": round(fout, 3), "youden": round(fin - fout, 3),
                    "n_inside": len(inside), "n_outside": len(outside)})
    return out


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--poses", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--depth-weights", default=None, help="MonoDepth weights (default: shipped)")
    a = p.parse_args(argv)
    if a.poses < 1:
        p.error(f"--poses must be >= 1, got {a.poses}")
    if a.depth_weights is not None and not os.path.isfile(a.depth_weights):
        p.error(f"--depth-weights {a.depth_weights!r}: no such file")
    import torch

    torch.set_num_threads(1)
    rows = thresholds(sweep(a.poses, a.seed, a.depth_weights),
                      [x / 100 for x in range(28, 52)])
    for r in rows:
        print(json.dumps({"bench": "reach_calibration", "figure": "threshold",
                          "depth_weights": a.depth_weights or "shipped", **r}), flush=True)
    best = max(rows, key=lambda r: (r["youden"], -r["threshold_m"]))
    best = {"bench": "reach_calibration", "figure": "best", "depth_weights":
            a.depth_weights or "shipped", "poses": a.poses, "seed": a.seed, **best}
    print(json.dumps(best), flush=True)
    return rows + [best]


if __name__ == "__main__":
    main()
