"""Perception from images: cost and held-out accuracy of the RGB-only feature stack.

Prints one JSON object per figure (``{"bench": "perception", "figure": ..., ...}``):

* ``detector_ms`` / ``depth_ms`` / ``rgb_stack_ms``: CPU milliseconds per frame
  of the shipped YOLOv8 goal detector, the shipped ``MonoDepth`` and the whole
  RGB-only stack (``make_causal_transforms(perception="rgb")``: depth, goal,
  sections, discretisation) at batch 1 and 16, on 240x320 (the reference camera)
  and 84x84 (the DQN's frames); median of ``--repeats`` calls after a warm-up;
* ``detector_heldout``: precision / recall (the thesis's 0.7 rule, IoU >= 0.5)
  and mAP50 on views of held-out layouts, beside the thesis's 0.943 / 0.902;
* ``depth_heldout``: abs rel, RMSE and delta < 1.25 on the same views;
* ``detector_camera_path`` / ``depth_camera_path``: the same figures on views
  that went through the Tello camera path (``VideoPath``: rendered at 960x720,
  exposure / blur / noise jitter, H.264 at the emulator's settings, cropped and
  resized as ``TelloEnv`` does) and on plain renders of the same poses, near
  (goal views 0.25-1 m from the board) and far (1-9 m), and on obstacle
  close-ups (``distance: "obstacle"``, 0.25-1.5 m from an obstacle's surface:
  the detector's ``false_sight_rate``, a goal seen where there is none, is the
  figure there), at 240x320 and 84x84;
  depth adds ``abs_rel_near`` / ``delta1_near`` over the pixels within 1 m
  (targets: P/R >= 0.943 / 0.902; near delta1 >= 0.9, abs rel <= 0.10);
* ``feature_agreement``: per variable, the share of held-out 84x84 views where
  the RGB-only stack's category equals the ground-truth stack's (target >= 0.9);
* ``policy_flight`` (with ``--run``): greedy success of a trained run's policy
  (trained on ground-truth features) on its training scene with ground-truth
  (``sim``) and with RGB-only (``rgb``) features, with 95 % Wilson intervals;
  ``--noise`` adds the env's move and turn noise so episodes differ.

Held-out views are rendered here (``render_views("test", ...)``: layouts of the
held-out split, never used to train either model), deterministic from ``--seed``.

Run: ``python benchmarks/perception.py [--views 300] [--run outputs/make_train]
[--episodes 20] [--threads 2]``
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
THESIS_DETECTOR = {"precision": 0.943, "recall": 0.902}
VFOV_DEG = 60.0  # DroneNavEnv's default vertical field of view (the views' camera)


def rgb_stack(h: int, w: int, detector, depth):
    """The RGB-only feature stack for views of ``h x w`` pixels."""
    from torchrl_causal.perception import horizontal_fov
    from torchrl_causal.transforms import make_causal_transforms

    return make_causal_transforms(perception="rgb", detector=detector, depth_estimator=depth,
                                  hfov_deg=horizontal_fov(VFOV_DEG, h, w), seed=0)


def emit(figure: str, **values) -> dict:
    row = {"bench": "perception", "figure": figure, **values}
    print(json.dumps(row), flush=True)
    return row


def median_ms(fn, frames: int, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times) / frames


def bench_costs(views_by_size: dict, detector, depth, repeats: int) -> None:
    from tensordict import TensorDict

    for (h, w), views in views_by_size.items():
        px_all = torch.from_numpy(np.stack([v.rgb for v in views]))
        stack = rgb_stack(h, w, detector, depth)
        for batch in (1, 16):
            px = px_all[:batch]
            td = TensorDict({"pixels": px, "altitude": torch.ones(batch, 1)}, [batch])
            emit("detector_ms", image_size=[h, w], batch=batch,
                 ms_per_frame=round(median_ms(lambda: detector(px), batch, repeats), 2))
            emit("depth_ms", image_size=[h, w], batch=batch,
                 ms_per_frame=round(median_ms(lambda: depth(px), batch, repeats), 2))
            emit("rgb_stack_ms", image_size=[h, w], batch=batch,
                 ms_per_frame=round(median_ms(lambda: stack(td.clone()), batch, repeats), 2))


def bench_accuracy(views_by_size: dict, detector, depth) -> None:
    from torchrl_causal.perception.dataset import evaluate_detector
    from torchrl_causal.perception.depth import evaluate_depth

    for (h, w), views in views_by_size.items():
        det = evaluate_detector(detector, views)
        emit("detector_heldout", image_size=[h, w], n_views=det["n_views"],
             n_positives=det["n_positives"], precision=round(det["precision"], 4),
             recall=round(det["recall"], 4), map50=round(det["map50"], 4),
             image_accuracy=round(det["image_accuracy"], 4),
             thesis_precision=THESIS_DETECTOR["precision"], thesis_recall=THESIS_DETECTOR["recall"])
        dep = evaluate_depth(depth, views)
        emit("depth_heldout", image_size=[h, w], n_views=dep["n_images"],
             abs_rel=round(dep["abs_rel"], 4), rmse=round(dep["rmse"], 4),
             delta1=round(dep["delta1"], 4), abs_rel_in_range=round(dep["abs_rel_in_range"], 4),
             delta1_in_range=round(dep["delta1_in_range"], 4))


def bench_camera_path(detector, depth, n: int, seed: int) -> None:
    """Plain vs camera-path views, near vs far, at both sizes (see the docstring)."""
    from torchrl_causal.perception.dataset import evaluate_detector, render_views
    from torchrl_causal.perception.depth import evaluate_depth
    from torchrl_causal.perception.video_path import VideoPath

    # near / far: views of the board; obstacle: close-ups of obstacles (the detector's hard
    # negatives: its false_sight_rate is a goal seen where there is none)
    ranges = {"near": (0.25, 1.0), "far": (1.0, 9.0), "obstacle": (0.25, 1.5)}
    for size in ((240, 320), (84, 84)):
        for rng_name, dist in ranges.items():
            for path in ("plain", "video"):
                kind = (dict(obstacle_frac=1.0, obstacle_distance=dist) if rng_name == "obstacle"
                        else dict(start_frac=0.0, goal_distance=dist))
                views = list(render_views(
                    "test", n, seed=seed + 7, image_size=size, goal_absent_frac=0.0,
                    video_path=VideoPath(seed=seed) if path == "video" else None, **kind))
                det = evaluate_detector(detector, views)
                r4 = lambda v: None if v != v else round(v, 4)  # noqa: E731  (NaN: no such views)
                emit("detector_camera_path", image_size=list(size), distance=rng_name,
                     distance_m=list(dist), frames=path, n_views=det["n_views"],
                     n_positives=det["n_positives"], precision=r4(det["precision"]),
                     recall=r4(det["recall"]), map50=r4(det["map50"]),
                     false_sight_rate=r4(det["false_sight_rate"]),
                     thesis_precision=THESIS_DETECTOR["precision"],
                     thesis_recall=THESIS_DETECTOR["recall"])
                dep = evaluate_depth(depth, views)
                near = {k: (round(dep[k], 4) if dep[k] is not None else None)
                        for k in ("abs_rel_near", "delta1_near")}
                emit("depth_camera_path", image_size=list(size), distance=rng_name,
                     distance_m=list(dist), frames=path, n_views=dep["n_images"],
                     abs_rel=round(dep["abs_rel"], 4), delta1=round(dep["delta1"], 4),
                     abs_rel_in_range=round(dep["abs_rel_in_range"], 4),
                     n_views_near=dep["n_images_near"], **near)


def bench_agreement(views, detector, depth) -> dict:
    from torchrl_causal.perception import horizontal_fov
    from torchrl_causal.perception.agreement import feature_agreement

    h, w = views[0].rgb.shape[:2]
    res = feature_agreement(views, rgb_stack(h, w, detector, depth), seed=0,
                            hfov_deg=horizontal_fov(VFOV_DEG, h, w))
    return emit("feature_agreement", image_size=[h, w], n_views=res["n"],
                per_variable={k: round(v, 4) for k, v in res["per_variable"].items()},
                all_nine=round(res["all_nine"], 4),
                min_variable=round(min(res["per_variable"].values()), 4),
                confusion=res["confusion"])


def bench_flight(run: Path, episodes: int, noise: bool, seed: int) -> None:
    sys.path.insert(0, str(ROOT / "recipes"))
    import train as recipe
    from results import wilson

    from torchrl_causal.training import evaluate

    extra = ["env.noise=tello"] if noise else []
    for perception in ("sim", "rgb"):
        policy, env, cfg = recipe.load_policy(
            run, overrides=[f"features.options.perception={perception}", *extra])
        t0 = time.perf_counter()
        res = evaluate(policy, env, episodes=episodes, seed=seed)
        k = int(round(res["success_rate"] * episodes))
        lo, hi = wilson(k, episodes)
        emit("policy_flight", run=str(run), scene=cfg.env.layout, perception=perception,
             noise=noise, episodes=episodes, success_rate=res["success_rate"],
             ci95=[round(lo, 3), round(hi, 3)], collisions=res["collisions"],
             out_of_bounds=res["out_of_bounds"], mean_length=res["mean_length"],
             seconds=round(time.perf_counter() - t0, 1))
        env.close()


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--views", type=int, default=300, help="held-out views per image size")
    p.add_argument("--seed", type=int, default=123, help="seed of the held-out views")
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--run", default=None, help="a finished run folder of recipes/train.py")
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--noise", action="store_true", help="policy flight with move/turn noise")
    p.add_argument("--skip", nargs="*", default=(),
                   choices=("costs", "accuracy", "camera_path", "agreement", "flight"))
    p.add_argument("--depth-weights", default=None,
                   help="MonoDepth weights to measure (default: the shipped ones)")
    p.add_argument("--detector-weights", default=None,
                   help="YOLO goal-detector weights to measure (default: the shipped ones)")
    p.add_argument("--path-views", type=int, default=100,
                   help="views per (size, distance, plain/video) set of the camera-path figures")
    a = p.parse_args(argv)
    if a.views < 16:
        p.error(f"--views must be >= 16, got {a.views}")
    if a.run is not None and not Path(a.run).is_dir():
        p.error(f"--run {a.run!r} is not a folder")
    if a.threads:
        torch.set_num_threads(a.threads)

    from torchrl_causal.perception.dataset import render_views
    from torchrl_causal.perception.depth import MonoDepth
    from torchrl_causal.perception.yolo import YoloGoalDetector

    detector = (YoloGoalDetector() if a.detector_weights is None
                else YoloGoalDetector(weights=a.detector_weights))
    depth = MonoDepth.load(a.depth_weights)
    emit("setup", threads=torch.get_num_threads(), views=a.views, seed=a.seed,
         depth_weights=a.depth_weights or "shipped", detector_weights=a.detector_weights or "shipped")
    views = {size: list(render_views("test", a.views, seed=a.seed, image_size=size))
             for size in ((240, 320), (84, 84))}
    if "costs" not in a.skip:
        bench_costs(views, detector, depth, a.repeats)
    if "accuracy" not in a.skip:
        bench_accuracy(views, detector, depth)
    if "camera_path" not in a.skip:
        bench_camera_path(detector, depth, a.path_views, a.seed)
    if "agreement" not in a.skip:
        bench_agreement(views[(84, 84)], detector, depth)
    if a.run is not None and "flight" not in a.skip:
        bench_flight(Path(a.run), a.episodes, a.noise, a.seed)


if __name__ == "__main__":
    main()
