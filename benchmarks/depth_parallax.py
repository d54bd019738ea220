"""Depth from a forward move's expansion (dense optical flow) against MonoDepth, near the drone.

::

    python benchmarks/depth_parallax.py                 # 240 x 320 and 84 x 84, 120 moves each

A forward move of ``b`` metres turns a pixel at radius ``r1`` from the image centre into one at
``r2``; the surface's depth after the move is ``b * r1 / (r2 - r1)``. This script flies
``DroneNavEnv`` on held-out random layouts with the Tello's move noise (0.05 m on the moved
axis), takes 0-2 random turns and one forward move per episode, computes OpenCV's DIS optical
flow (``PRESET_MEDIUM``) from the frame after the move back to the frame before, and compares,
over the pixels within 1 m, the flow's depth (where the flow is radial and expanding), MonoDepth's
and their minimum. One JSON object per image size: ``abs_rel_near_*`` (mean over views),
``close_read_far_*`` (share of pixels truly within 0.6 m read beyond 0.75 m) and
``flow_cover_near`` (share of near pixels with a flow depth). Results: docs/perception.rst,
"Depth from the drone's own motion".
"""

from __future__ import annotations

import json
import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchrl_causal.envs import DroneNavEnv  # noqa: E402
from torchrl_causal.envs.control import TELLO_MOVE_NOISE  # noqa: E402
from torchrl_causal.perception.depth import MonoDepth  # noqa: E402

STEP = 0.25  # DroneNavEnv's move (m)


def flow_depth(before: np.ndarray, after: np.ndarray, dis) -> tuple[np.ndarray, np.ndarray]:
    """``(depth after the move, valid mask)`` from two RGB frames of a forward move of STEP."""
    h, w = after.shape[:2]
    g1, g2 = (cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in (before, after))
    flow = dis.calc(g2, g1, None)  # where each pixel of the later frame was before
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    x2, y2 = xx - (w - 1) / 2, yy - (h - 1) / 2
    r2 = np.hypot(x2, y2)
    r1 = np.hypot(x2 + flow[..., 0], y2 + flow[..., 1])
    dr = r2 - r1
    mag = np.hypot(flow[..., 0], flow[..., 1])
    radial = -(x2 * flow[..., 0] + y2 * flow[..., 1]) / np.maximum(r2 * mag, 1e-6)
    valid = (r2 > 0.15 * min(h, w)) & (dr > 0.5) & (radial > 0.8)
    return np.clip(np.where(valid, STEP * r1 / np.maximum(dr, 1e-6), np.inf), 0.05, 10.0), valid


def measure(h: int, w: int, n: int, seed: int = 11) -> dict:
    est = MonoDepth.load()
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    env = DroneNavEnv("random", split="heldout", image_size=(h, w), seed=seed, **TELLO_MOVE_NOISE)
    rng = np.random.default_rng(0)
    err = {k: [] for k in ("mono", "flow", "fused")}
    far = {k: [0, 0] for k in err}
    cover, moves = [], 0
    while moves < n:
        td = env.reset()
        for _ in range(int(rng.integers(0, 3))):
            td = env.step(td.set("action", torch.tensor(int(rng.choice([6, 7])))))["next"]
            if bool(td["done"]):
                break
        if bool(td["done"]):
            continue
        before = td["pixels"].numpy().copy()  # the renderer reuses its buffer
        td = env.step(td.set("action", torch.tensor(0)))["next"]
        if bool(td["done"]):
            continue
        moves += 1
        after, depth = td["pixels"].numpy().copy(), td["depth"].numpy().reshape(h, w)
        zf, valid = flow_depth(before, after, dis)
        mono = est(torch.from_numpy(after)).numpy()
        near = (depth > 0) & (depth <= 1.0)
        if near.sum() < 30:
            continue
        cover.append(float(valid[near].mean()))
        for k, z, m in (("mono", mono, near), ("flow", zf, near & valid),
                        ("fused", np.where(valid, np.minimum(mono, zf), mono), near)):
            if m.sum() > 10:
                err[k].append(float(np.mean(np.abs(z[m] - depth[m]) / depth[m])))
            c = (depth > 0) & (depth <= 0.6) & (valid if k == "flow" else True)
            far[k][0] += int((z[c] > 0.75).sum())
            far[k][1] += int(c.sum())
    return {"figure": "depth_parallax", "image_size": [h, w], "moves": moves,
            "views_with_near": len(cover), "flow_cover_near": round(float(np.mean(cover)), 3),
            **{f"abs_rel_near_{k}": round(float(np.mean(v)), 3) for k, v in err.items()},
            **{f"close_read_far_{k}": round(v[0] / max(v[1], 1), 4) for k, v in far.items()}}


def main(argv=None) -> list[dict]:
    torch.set_num_threads(1)
    n = int((argv or sys.argv[1:] or [120])[0])
    out = []
    for h, w in ((240, 320), (84, 84)):
        out.append(measure(h, w, n))
        print(json.dumps(out[-1]), flush=True)
    return out


if __name__ == "__main__":
    main()
