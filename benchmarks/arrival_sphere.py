"""One frame inside the goal sphere, facing the board: does the camera path see it and read it?

::

    python benchmarks/arrival_sphere.py [N]      # default 120 frames

Renders ``N`` frames from poses inside the simulator's 0.2 m sphere around the goal
point of held-out random rooms (the printed 1.0 x 0.8 m board, 10 frames per room,
height within 0.08 m of the goal point, yaw within 15 deg of facing the board, roll
and pitch within 3 deg), each through the Tello camera path (``VideoPath``, 320 x 240
stream), and measures each with a dry-run :class:`~torchrl_causal.envs.TelloEnv`
with what ``fly_tello.py``'s defaults fly in such rooms (the shipped detector, MonoDepth and
random-rooms arrival head; the rule at 0.13 m within 1 m, written out here). Prints one JSON object: how
many frames the detector saw the board in, how many MonoDepth put beyond the rule's
1 m, how many the head was asked on, and the head's error on the distance from the
goal point (one frame each: ``TelloEnv.measure_frame``, no segment). Results:
docs/tello.rst, "Step by step at the goal".
"""

from __future__ import annotations

import json
import math
import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only

import numpy as np  # noqa: E402
import torch  # noqa: E402


def main(n: int = 120, seed: int = 11) -> dict:
    from torchrl_causal.envs import DroneNavEnv, TelloEnv
    from torchrl_causal.envs.reach import ReachRule
    from torchrl_causal.perception.arrival import ROOMS_WEIGHTS, GoalOffsetEstimator
    from torchrl_causal.perception.dataset import _quat
    from torchrl_causal.perception.depth import MonoDepth
    from torchrl_causal.perception.video_path import VideoPath
    from torchrl_causal.perception.yolo import YoloGoalDetector

    if not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be an int >= 1, got {n!r}")
    torch.set_num_threads(1)
    rule = ReachRule(max_distance=1.0, max_goal_offset=0.13, board_width=1.0,
                     goal_standoff=0.45, max_height_offset=0.12, goal_height=1.0)
    tenv = TelloEnv(dry_run=True, detector=YoloGoalDetector(), depth_estimator=MonoDepth.load(),
                    arrival_head=GoalOffsetEstimator.load(ROOMS_WEIGHTS), reach_rule=rule,
                    image_size=(84, 84), fov_deg=60.0, verbose=False)
    path = VideoPath(stream_size=(240, 320), seed=5)
    rng = np.random.default_rng(seed)
    rows, env = [], None
    try:
        for i in range(n):
            if i % 10 == 0:  # a new room
                if env is not None:
                    env.close()
                env = DroneNavEnv("random", split="heldout", goal_size=(1.0, 0.8),
                                  image_size=(240, 320), seed=0,
                                  layout_index=int(rng.integers(0, 1_000_000)))
                env.reset()
                lay = env.layout
                gp, normal = np.array(lay.goal_point()), lay.goal_normal()[:2]
                side = np.array([-normal[1], normal[0]])
                facing = math.degrees(math.atan2(-normal[1], -normal[0]))
            for _ in range(1000):  # inside the sphere, clear of obstacles and the room's edge
                r, a = 0.19 * math.sqrt(rng.uniform()), rng.uniform(0, 2 * math.pi)
                ahead, lat, dz = r * math.cos(a), r * math.sin(a), rng.uniform(-0.08, 0.08)
                xy = gp[:2] + ahead * normal + lat * side
                x0, y0, x1, y1 = lay.arena
                if (x0 + 0.3 <= xy[0] <= x1 - 0.3 and y0 + 0.3 <= xy[1] <= y1 - 0.3
                        and all(float(o.footprint_distance(*xy)) >= 0.3 for o in lay.obstacles)):
                    break
            qa = env.ids.qpos_adr
            env.data.qpos[qa:qa + 3] = (xy[0], xy[1], gp[2] + dz)
            env.data.qpos[qa + 3:qa + 7] = _quat(facing + rng.uniform(-15, 15),
                                                 rng.uniform(-3, 3), rng.uniform(-3, 3))
            frame = path(np.asarray(env._observe(False, False)["pixels"]).copy())
            m = tenv.measure_frame(frame, altitude=1.0 + dz)
            rows.append((m["in_sight"], m["in_sight"] and m["distance"] > 1.0,
                         m["goal_offset"], math.sqrt(ahead ** 2 + lat ** 2 + dz ** 2)))
    finally:
        if env is not None:
            env.close()
        tenv.close()
        path.close()
    err = [abs(off - true) for _, _, off, true in rows if off is not None]
    fig = {"figure": "arrival_sphere", "frames": n, "seed": seed,
           "in_sight": sum(r[0] for r in rows), "monodepth_beyond_1m": sum(r[1] for r in rows),
           "head_asked": len(err),
           "distance_err_median_m": round(float(np.median(err)), 4) if err else None,
           "distance_err_p90_m": round(float(np.percentile(err, 90)), 4) if err else None}
    print(json.dumps(fig), flush=True)
    return fig


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 120)
