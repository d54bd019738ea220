"""How far can one frame tell the depth of a near surface? One JSON object per figure.

::

    python benchmarks/depth_ambiguity.py > depth_ambiguity.jsonl

MonoDepth misses abs rel <= 0.10 within 1 m on obstacle close-ups (docs/perception.rst).
This script asks whether any single-frame estimator could meet it there. The scenes
are lit by one directional light and a directional headlight, without shadows, and
60 % of the random layouts' obstacles are plain (one colour, no texture; the rest carry
a checker of a fixed metric size). A plane's image under such light depends on its
orientation and colour, not on its distance. Moving the camera back along its axis
scales the depth map by a factor and leaves the image unchanged wherever the plane
fills the view.

Two figures:

* ``twins``: a plain box face filling the view, rendered at 0.25-1.0 m, square-on and
  turned 25 deg (``DroneNavEnv``, 240 x 320, no camera path). It prints the largest
  pixel difference between the renders of one colour and orientation, and MonoDepth's
  median reading at each distance.
* ``near_by_surface``: 200 held-out obstacle close-ups (seed 601, the same views as
  ``depth_floor_scale.py``) and 200 views of the usual mix (seed 602), through the Tello
  camera path. Each near pixel (true depth <= 1 m) is labelled by the surface it shows
  (plain obstacle, checker obstacle, board, other) from a segmentation render of the
  same pose. It prints MonoDepth's abs rel per surface and the share of near pixels.
  For the views a plain obstacle fills (>= 98 % of the pixels: nothing else in the
  image), the frame does not depend on the distance. Since the views' distance is drawn
  independently of the direction they look in, no estimator can do better on those
  pixels, on average, than the best single scale ``a`` for the whole set:
  ``min_a mean |a / d - 1|`` over their near pixels, with ``d`` each view's own
  distance (:func:`best_constant_abs_rel`). That floor, times the share of near pixels
  in such views, bounds the near abs rel of any single-frame estimator from below.

Results: docs/perception.rst, "What one frame cannot tell".
"""

from __future__ import annotations

import json
import math
import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchrl_causal.envs.drone import DroneNavEnv  # noqa: E402
from torchrl_causal.envs.layouts import Layout, Obstacle  # noqa: E402
from torchrl_causal.perception.dataset import _quat, render_views  # noqa: E402
from torchrl_causal.perception.depth import MonoDepth  # noqa: E402
from torchrl_causal.perception.video_path import VideoPath  # noqa: E402

H, W = 240, 320
FILLED = 0.98  # share of a view's pixels on one plain obstacle for "nothing else in view"
KINDS = (("obstacle close-ups", dict(obstacle_frac=1.0, goal_absent_frac=0.0), 601),
         ("usual mix", {}, 602))


def best_constant_abs_rel(distances, weights) -> tuple[float, float]:
    """``(a, min_a sum_i w_i |a / d_i - 1| / sum_i w_i)``: the best single scale for views
    whose images do not depend on their distances ``d_i`` (weights: their near pixels).

    The objective is convex and piecewise linear in ``a``, so its minimum lies at one of
    the ``d_i`` (a weighted median of ``d`` with weights ``w / d``).

    Example:
        >>> a, floor = best_constant_abs_rel([0.5, 1.0], [1, 1])
        >>> round(a, 2), round(floor, 3)   # reading 1.0: 0.5 off at 0.5 m, exact at 1 m
        (1.0, 0.5)
    """
    d = np.asarray(distances, float)
    w = np.asarray(weights, float)
    if d.size == 0:
        return float("nan"), float("nan")
    costs = [(float(np.sum(w * np.abs(a / d - 1.0)) / w.sum()), float(a)) for a in d]
    cost, a = min(costs)
    return a, cost


def _pose(env: DroneNavEnv, x, y, z, yaw, pitch=0.0, roll=0.0):
    qa = env.ids.qpos_adr
    env.data.qpos[qa:qa + 3] = (x, y, z)
    env.data.qpos[qa + 3:qa + 7] = _quat(yaw, pitch, roll)
    obs = env._observe(False, False)
    return obs["pixels"].numpy().copy(), obs["depth"].numpy().copy()


def twin_frames(rgb, turn_deg: float, distances, image_size=(H, W)):
    """RGB frames ``[N, H, W, 3]`` and depths ``[N, H, W]`` of one plain box face of colour
    ``rgb`` filling the view, the camera ``distances`` metres from it along its axis and
    turned ``turn_deg`` off the face's normal (``DroneNavEnv``'s own scene and lights).

    Example:
        >>> f, d = twin_frames((0.5, 0.3, 0.2), 0.0, (0.3, 0.6), image_size=(48, 64))
        >>> int(abs(f[0].astype(int) - f[1].astype(int)).max()) <= 1   # the same image
        True
    """
    # a plain face 3 m wide and 4 m tall at x = 3, facing -x: it fills the view from 1 m
    wall = Obstacle(center=(3.2, 0.0, 2.0), half_size=(0.2, 1.5, 2.0),
                    rgba=(*(float(v) for v in rgb), 1.0))
    lay = Layout(name="twin", arena=(-2.0, -3.0, 5.0, 3.0), height=3.5,
                 start_pos=(0.0, 0.0, 1.0), start_yaw_deg=0.0, goal_center=(-1.5, 2.5, 1.0),
                 goal_yaw_deg=0.0, goal_size=(0.8, 0.6), obstacles=(wall,))
    env = DroneNavEnv(lay, image_size=tuple(image_size), seed=0)
    env.reset()
    ahead = float(env.model.cam_pos[env.ids.camera][0])  # the camera ahead of the body
    frames, depths = [], []
    try:
        for d in distances:
            c, s = math.cos(math.radians(turn_deg)), math.sin(math.radians(turn_deg))
            f, dep = _pose(env, 3.0 - (d + ahead) * c, -(d + ahead) * s, 1.2, turn_deg)
            frames.append(f)
            depths.append(dep)
    finally:
        env.close()
    return np.stack(frames), np.stack(depths)


def twins(est: MonoDepth) -> list[dict]:
    out = []
    rng = np.random.default_rng(5)
    distances = (0.25, 0.35, 0.5, 0.7, 1.0)
    for _ in range(4):
        rgb = tuple(float(v) for v in rng.uniform(0.1, 0.9, size=3))
        for turn in (0.0, 25.0):
            frames, depths = twin_frames(rgb, turn, distances)
            pred = est(torch.from_numpy(frames)).numpy()
            diff = int(np.abs(frames[1:].astype(int) - frames[0].astype(int)).max())
            row = {"figure": "twins", "colour": [round(v, 3) for v in rgb], "turn_deg": turn,
                   "camera_distance_m": list(distances),
                   "true_median_m": [round(float(np.median(t)), 3) for t in depths],
                   "max_pixel_diff": diff,
                   "monodepth_median_m": [round(float(np.median(p)), 3) for p in pred],
                   "abs_rel": [round(float(np.mean(np.abs(p - t) / t)), 3)
                               for p, t in zip(pred, depths)]}
            print(json.dumps(row), flush=True)
            out.append(row)
    return out


def _surfaces(env: DroneNavEnv) -> tuple[list[int], list[int]]:
    plain, checker = [], []
    for k, o in enumerate(env.layout.obstacles):
        gid = mujoco.mj_name2id(env.model, mujoco.mjtObj.mjOBJ_GEOM, f"obstacle{k}")
        (plain if o.pattern == "plain" else checker).append(int(gid))
    return plain, checker


def near_by_surface(est: MonoDepth, n: int) -> list[dict]:
    out = []
    env = DroneNavEnv("random", split="heldout", layout_seed=0, image_size=(H, W), seed=0)
    try:
        for kind, kw, seed in KINDS:
            views = list(render_views("test", n, seed=seed, video_path=VideoPath(seed=seed), **kw))
            p = np.concatenate([est(torch.from_numpy(np.stack([v.rgb for v in views[s:s + 32]])))
                                .numpy() for s in range(0, len(views), 32)])
            err = {c: [0.0, 0] for c in ("plain", "checker", "board", "other")}
            filled_d, filled_w, filled_err = [], [], []
            near_total = 0
            current = None
            for i, v in enumerate(views):
                if v.layout_index != current:
                    env.layout_index = v.layout_index
                    env._load(env._select_layout())
                    current = v.layout_index
                    plain, checker = _surfaces(env)
                x, y, z, yaw, pitch, roll = v.pose
                _, depth = _pose(env, x, y, z, yaw, pitch, roll)
                if not np.allclose(depth, v.depth, atol=1e-3):
                    raise RuntimeError(f"view {i}: the segmentation render is not the view's pose")
                m_plain = env._renderer.geom_mask(plain)
                m_check = env._renderer.geom_mask(checker)
                m_board = env._renderer.geom_mask(env.ids.goal_geoms)
                t = v.depth
                near = (t > 0) & (t <= 1.0)
                rel = np.abs(p[i] - t) / np.maximum(t, 1e-6)
                near_total += int(near.sum())
                for c, m in (("plain", m_plain), ("checker", m_check), ("board", m_board),
                             ("other", ~(m_plain | m_check | m_board))):
                    sel = near & m
                    err[c][0] += float(rel[sel].sum())
                    err[c][1] += int(sel.sum())
                if m_plain.mean() >= FILLED and near.sum() > 0:
                    filled_d.append(float(np.median(t[near])))
                    filled_w.append(int(near.sum()))
                    filled_err.append(float(rel[near].sum()))
            a, floor = best_constant_abs_rel(filled_d, filled_w)
            filled_pixels = int(sum(filled_w))
            share = filled_pixels / max(near_total, 1)
            row = {"figure": "near_by_surface", "views": kind, "seed": seed, "n_views": len(views),
                   "near_pixels": near_total,
                   "share_of_near_pixels": {c: round(e[1] / max(near_total, 1), 4)
                                            for c, e in err.items()},
                   "monodepth_abs_rel_near": {c: round(e[0] / e[1], 4) if e[1] else None
                                              for c, e in err.items()},
                   "monodepth_abs_rel_near_all": round(sum(e[0] for e in err.values())
                                                       / max(near_total, 1), 4),
                   "filled_plain_views": len(filled_d),
                   "filled_plain_share_of_near_pixels": round(share, 4),
                   "filled_plain_monodepth_abs_rel": (round(sum(filled_err) / filled_pixels, 4)
                                                      if filled_pixels else None),
                   "filled_plain_best_scale_m": round(a, 3) if filled_d else None,
                   "filled_plain_floor_abs_rel": round(floor, 4) if filled_d else None,
                   "any_estimator_near_abs_rel_at_least": (round(floor * share, 4)
                                                           if filled_d else None)}
            print(json.dumps(row), flush=True)
            out.append(row)
    finally:
        env.close()
    return out


def main(n: int = 200) -> list[dict]:
    torch.set_num_threads(1)
    est = MonoDepth.load()
    return twins(est) + near_by_surface(est, n)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 200)
