"""Train the YOLOv8n heliport detector (thesis sec. 4.2) offline on rendered images.

Renders the dataset if the data folder has none (:mod:`torchrl_causal.perception.dataset`),
trains ``yolov8n.yaml`` from scratch (no pretrained weights, ``amp=False``,
``plots=False``, no network access), copies the best weights (optimizer stripped,
fp16) to the package's weights folder with a JSON sidecar, and evaluates on the
held-out test split at the data's resolution: precision / recall (at the
GoalMeter's 0.7 rule, IoU 0.5) and mAP50, beside the thesis's 0.943 / 0.902,
plus CPU ms per frame.

Usage::

    python recipes/train_detector.py --data data/perception --n-train 1100 --n-val 160 \\
        --n-test 320 --epochs 50 --imgsz 320 --threads 1
    python recipes/train_detector.py --data data/perception --resume   # continue last.pt
    python recipes/train_detector.py --data data/perception --evaluate-only --weights W.pt

Checkpoints: ``<project>/<name>/weights/last.pt`` after every epoch (``--resume``
continues it).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
THESIS = {"precision": 0.943, "recall": 0.902}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="dataset root (rendered here if missing)")
    p.add_argument("--n-train", type=int, default=1100)
    p.add_argument("--n-val", type=int, default=160)
    p.add_argument("--n-test", type=int, default=320)
    p.add_argument("--image-size", type=int, nargs=2, default=(240, 320), metavar=("H", "W"))
    p.add_argument("--data-seed", type=int, default=0, help="seed of the rendered views")
    p.add_argument("--layout-seed", type=int, default=0)
    p.add_argument("--epochs", type=int, default=50)
    p.add_argument("--imgsz", type=int, default=320)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--seed", type=int, default=0, help="training seed")
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    p.add_argument("--fraction", type=float, default=1.0, help="share of the train images used")
    p.add_argument("--patience", type=int, default=100)
    p.add_argument(
        "--nbs", type=int, default=None,
        help="nominal batch size (default: --batch, i.e. one optimizer step per batch; "
        "ultralytics' own default 64 accumulates 4 batches of 16, too few steps on a CPU budget)",
    )
    p.add_argument("--close-mosaic", type=int, default=4, help="last epochs without mosaic")
    p.add_argument("--warmup-epochs", type=float, default=1.0)
    p.add_argument("--project", default=str(ROOT / "runs" / "detector"))
    p.add_argument("--name", default="goal_yolov8n")
    p.add_argument("--resume", action="store_true", help="continue <project>/<name>/weights/last.pt")
    p.add_argument(
        "--out",
        default=str(ROOT / "torchrl_causal" / "perception" / "weights" / "goal_yolov8n.pt"),
        help="where the best weights go ('' = do not copy)",
    )
    p.add_argument(
        "--init", default=None,
        help="start from these weights (a checkpoint this recipe made) instead of yolov8n.yaml",
    )
    p.add_argument("--evaluate-only", action="store_true")
    p.add_argument(
        "--finalize", action="store_true",
        help="skip training: copy and evaluate <project>/<name>'s best weights",
    )
    p.add_argument(
        "--calibrate-only", action="store_true",
        help="fit the Platt calibration of --weights (default: the shipped ones) on the val "
             "split, store it in their sidecar and re-evaluate",
    )
    p.add_argument("--weights", default=None,
                   help="weights to evaluate (--evaluate-only) or calibrate (--calibrate-only)")
    p.add_argument(
        "--extra-data", action="append", default=[], metavar="ROOT",
        help="another dataset root written by `python -m torchrl_causal.perception.dataset` "
             "(e.g. close-ups: --goal-distance 0.3 1.2), repeatable: its train images join "
             "training, its val views the calibration; its test split is reported apart",
    )
    p.add_argument("--config-dir", default=str(ROOT / ".yolo_config"))
    p.add_argument("--bench-reps", type=int, default=20, help="repetitions of the CPU timing")
    a = p.parse_args(argv)
    for name in ("n_train", "n_val", "epochs", "batch", "threads"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(a, name)}")
    if a.imgsz < 32 or a.imgsz % 32:
        p.error(f"--imgsz must be a multiple of 32, got {a.imgsz}")
    if not 0 < a.fraction <= 1:
        p.error(f"--fraction must be in (0, 1], got {a.fraction}")
    for extra in a.extra_data:
        if not ((Path(extra) / "yolo" / "data.yaml").is_file()
                and (Path(extra) / "meta.json").is_file()):
            p.error(f"--extra-data {extra!r} is not a dataset root (no yolo/data.yaml and "
                    "meta.json): write one with `python -m torchrl_causal.perception.dataset`")
    return a


def data_yaml(a) -> Path:
    """The data.yaml ultralytics trains on: the dataset's own, or -- with --extra-data --
    one whose train split lists every root's train images (val and test: the dataset's)."""
    own = Path(a.data).resolve() / "yolo" / "data.yaml"
    if not a.extra_data:
        return own
    roots = [Path(a.data).resolve()] + [Path(e).resolve() for e in a.extra_data]
    train = ", ".join(json.dumps(str(r / "yolo" / "images" / "train")) for r in roots)
    y = Path(a.data).resolve() / "yolo"
    path = Path(a.project).resolve() / f"{a.name}_data.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"path: {y}\ntrain: [{train}]\nval: {y / 'images' / 'val'}\n"
                    f"test: {y / 'images' / 'test'}\nnc: 1\nnames: [\"heliport\"]\n")
    return path


def ensure_data(a) -> dict:
    from torchrl_causal.perception.dataset import write_datasets

    root = Path(a.data)
    meta_path = root / "meta.json"
    if (root / "yolo" / "data.yaml").is_file() and meta_path.is_file():
        return json.loads(meta_path.read_text())
    print(f"rendering the dataset into {root}", flush=True)
    return write_datasets(
        root, n_train=a.n_train, n_val=a.n_val, n_test=a.n_test, seed=a.data_seed,
        image_size=tuple(a.image_size), layout_seed=a.layout_seed,
    )


def train(a) -> Path:
    """Runs (or resumes) ultralytics training; returns the run folder."""
    from torchrl_causal.perception.yolo import ultralytics_offline

    ultralytics_offline()
    from ultralytics import YOLO

    run = Path(a.project) / a.name
    last = run / "weights" / "last.pt"
    if a.resume:
        if not last.is_file():
            raise FileNotFoundError(f"--resume: {last} does not exist")
        YOLO(str(last)).train(resume=True)
        return run
    model = YOLO(a.init if a.init else "yolov8n.yaml")
    model.train(
        data=str(data_yaml(a)),
        epochs=a.epochs,
        imgsz=a.imgsz,
        batch=a.batch,
        device="cpu",
        workers=0,
        pretrained=a.init if a.init else False,  # only ever this recipe's own weights
        amp=False,
        plots=False,
        seed=a.seed,
        deterministic=True,
        project=str(Path(a.project).resolve()),
        name=a.name,
        exist_ok=True,
        fraction=a.fraction,
        patience=a.patience,
        nbs=a.nbs or a.batch,
        close_mosaic=a.close_mosaic,
        warmup_epochs=a.warmup_epochs,
        verbose=False,
    )
    return run


def _views84(root: Path, split: str, n: int) -> list:
    """Views ``0 .. n-1`` of a dataset root's ``split`` rendered again at 84 x 84."""
    from torchrl_causal.perception.dataset import render_views

    meta = json.loads((root / "meta.json").read_text())
    options = dict(meta.get("view_options", {}))
    if options.get("video_path") is not None:  # meta.json holds the path's settings
        from torchrl_causal.perception.video_path import VideoPath

        options["video_path"] = VideoPath.from_dict(options["video_path"],
                                                    seed=int(meta.get("seed", 0)))
    return list(render_views(split, n, seed=int(meta.get("seed", 0)), image_size=84,
                             layout_seed=int(meta.get("layout_seed", 0)), **options))


def calibrate(weights: Path, data_root: Path, meta: dict, extra=()) -> tuple[dict, dict]:
    """Platt calibrations of the detector's scores (see
    :func:`torchrl_causal.perception.yolo.fit_calibration`): one fitted on the val split at
    the data's resolution, one on the same val views rendered at 84 x 84 (the DQN's camera;
    used for frames whose longer side is at most 128 px). ``extra`` dataset roots add
    their val views to both."""
    from torchrl_causal.perception.dataset import load_views
    from torchrl_causal.perception.yolo import YoloGoalDetector, fit_calibration

    det = YoloGoalDetector(weights, calibration=None)
    val, val84 = [], []
    primary_small = None
    for root in (data_root, *map(Path, extra)):
        views = load_views(root, "val")
        small = max(views[0].rgb.shape[:2]) <= 128
        if primary_small is None:
            primary_small = small
        elif small and not primary_small:  # an extra dataset rendered small already
            val84 += views
            continue
        val += views
        val84 += _views84(root, "val", len(views))
    h, w = val[0].rgb.shape[:2]
    fits = []
    for name, views, extra in (("large", val, {"fit_on": f"val split ({len(val)} views) at {h}x{w}"}),
                               ("small", val84, {"max_side": 128, "fit_on": f"the same val views "
                                                 f"({len(val84)}) rendered at 84x84"})):
        try:
            fit = {**fit_calibration(det, views), **extra}
            print(f"calibration ({name}): a={fit['a']:.4f} b={fit['b']:.4f} ({fit['n']} "
                  f"detections, {fit['positives']} correct)")
        except ValueError as e:  # e.g. a barely trained model that detects nothing
            print(f"calibration ({name}) not fitted, raw scores are used: {e}")
            fit = None
        fits.append(fit)
    return fits[0], fits[1]


def evaluate(weights: Path, data_root: Path, *, threads: int, reps: int = 20, imgsz: int = 320,
             extra=()) -> dict:
    """Held-out metrics at the data's resolution, ultralytics' own test-split figures and CPU ms;
    with ``extra`` dataset roots, their test splits too (at their resolution and at 84 x 84)."""
    from torchrl_causal.perception.dataset import evaluate_detector, load_views
    from torchrl_causal.perception.yolo import YoloGoalDetector

    det = YoloGoalDetector(weights, imgsz=int(imgsz))
    views = load_views(data_root, "test")
    ours = evaluate_detector(det, views, conf_threshold=0.7, batch_size=16)
    # ultralytics' validator on the test split (P/R at its best-F1 confidence, mAP50)
    from ultralytics import YOLO

    r = YOLO(str(weights)).val(
        data=str(data_root.resolve() / "yolo" / "data.yaml"), split="test", imgsz=det.imgsz,
        batch=16, device="cpu", plots=False, verbose=False, workers=0,
        project=str(ROOT / "runs" / "detector_eval"), exist_ok=True,
    )
    ul = {
        "precision": float(r.box.mp), "recall": float(r.box.mr),
        "map50": float(r.box.map50), "map50_95": float(r.box.map),
    }
    # CPU ms per frame: batch 1 and 16 at the data's resolution, batch 1 at 84 x 84
    torch.set_num_threads(threads)
    frames = torch.from_numpy(np.stack([v.rgb for v in views[:16]]))
    small = torch.nn.functional.interpolate(
        frames.permute(0, 3, 1, 2).float(), size=(84, 84), mode="bilinear", antialias=True
    ).round().clamp(0, 255).byte().permute(0, 2, 3, 1).contiguous()

    def ms(x, reps):
        det(x)  # warm-up
        t0 = time.perf_counter()
        for _ in range(reps):
            det(x)
        return 1e3 * (time.perf_counter() - t0) / (reps * x.shape[0])

    timing = {
        "threads": threads,
        "ms_per_frame_b1": ms(frames[:1], reps),
        "ms_per_frame_b16": ms(frames, max(1, reps // 6)),
        "ms_per_frame_84x84_b1": ms(small[:1], reps),
    }
    # the test views rendered at 84 x 84 (the DQN's camera)
    ours84 = evaluate_detector(det, _views84(data_root, "test", len(views)), conf_threshold=0.7)
    keys = ("precision", "recall", "map50", "image_accuracy")
    extra_test = {}
    for root in map(Path, extra):
        ev = load_views(root, "test")
        full = evaluate_detector(det, ev, conf_threshold=0.7)
        small = evaluate_detector(det, _views84(root, "test", len(ev)), conf_threshold=0.7)
        extra_test[str(root)] = {"full": {k: full[k] for k in keys},
                                 "84x84": {k: small[k] for k in keys}}
    raw = evaluate_detector(YoloGoalDetector(weights, imgsz=int(imgsz), calibration=None), views,
                            conf_threshold=0.7, batch_size=16)
    return {
        "calibration": None if det.calibration is None else list(det.calibration),
        "test_rule07": ours,
        "test_rule07_raw_scores": {k: raw[k] for k in ("precision", "recall", "image_accuracy")},
        "test_rule07_84x84": {k: ours84[k] for k in keys},
        **({"extra_test_rule07": extra_test} if extra_test else {}),
        "test_ultralytics": ul,
        "cpu": timing,
        "thesis": THESIS,
    }


def main(argv=None):
    a = parse_args(argv)
    torch.set_num_threads(a.threads)
    os.environ.setdefault("YOLO_CONFIG_DIR", a.config_dir)
    t0 = time.time()
    meta = ensure_data(a)
    data_root = Path(a.data)
    if a.evaluate_only:
        weights = Path(a.weights or a.out)
        from torchrl_causal.perception.yolo import load_sidecar

        imgsz = load_sidecar(weights).get("imgsz", a.imgsz)
        metrics = evaluate(weights, data_root, threads=a.threads, reps=a.bench_reps, imgsz=imgsz,
                           extra=a.extra_data)
        print(json.dumps(metrics, indent=1))
        return metrics
    if a.calibrate_only:
        from torchrl_causal.perception.yolo import DEFAULT_WEIGHTS, load_sidecar

        weights = Path(a.weights) if a.weights else DEFAULT_WEIGHTS
        sidecar = load_sidecar(weights)
        sidecar["calibration"], sidecar["calibration_small"] = calibrate(
            weights, data_root, meta, a.extra_data)
        sidecar["calibration_command"] = "python recipes/train_detector.py " + " ".join(
            shlex.quote(x) for x in (sys.argv[1:] if argv is None else argv))
        weights.with_suffix(".json").write_text(json.dumps(sidecar, indent=1) + "\n")
        metrics = evaluate(weights, data_root, threads=a.threads, reps=a.bench_reps,
                           imgsz=sidecar.get("imgsz", a.imgsz), extra=a.extra_data)
        # the CPU timing of the training run stays (calibration changes no cost)
        metrics.pop("cpu", None)
        sidecar["metrics"] = {**sidecar.get("metrics", {}), **metrics}
        weights.with_suffix(".json").write_text(json.dumps(sidecar, indent=1) + "\n")
        print(json.dumps(metrics["test_rule07"]))
        return sidecar
    run = Path(a.project) / a.name
    if not a.finalize:
        run = train(a)
    best = run / "weights" / "best.pt"
    if not best.is_file():
        best = run / "weights" / "last.pt"
    train_s = time.time() - t0
    sidecar = {
        "model": "yolov8n",
        "task": "detect",
        "names": ["heliport"],
        "command": "python recipes/train_detector.py "
        + " ".join(
            shlex.quote(x) for x in (sys.argv[1:] if argv is None else argv) if x != "--finalize"
        ),
        "seed": a.seed,
        "data": meta,
        "extra_data": [json.loads((Path(e) / "meta.json").read_text()) for e in a.extra_data],
        "epochs": a.epochs,
        "imgsz": a.imgsz,
        "batch": a.batch,
        "nbs": a.nbs or a.batch,
        "threads": a.threads,
        "fraction": a.fraction,
        "init": a.init,
        "train_wall_s": None if a.finalize else round(train_s, 1),
        "torch": torch.__version__,
    }
    if a.init:
        prev = Path(a.init).parents[1] / "torchrl_causal_metrics.json"
        if prev.is_file():
            sidecar["init_command"] = json.loads(prev.read_text()).get("command")
        init_sidecar = Path(a.init).with_suffix(".json")
        if init_sidecar.is_file():  # the chain of fine-tunes stays on record, stage by stage
            sidecar["init_sidecar"] = json.loads(init_sidecar.read_text())
    try:
        import ultralytics

        sidecar["ultralytics"] = ultralytics.__version__
    except ImportError:  # pragma: no cover
        pass
    out = Path(a.out) if a.out else run / "weights" / "goal_yolov8n.pt"
    # the weights and their sidecar first (an interrupted evaluation loses nothing)
    if a.out:
        import shutil

        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(best, out)
        print(f"weights: {out} ({out.stat().st_size / 1e6:.1f} MB)")
    else:
        out = best
    sidecar["calibration"], sidecar["calibration_small"] = calibrate(out, data_root, meta,
                                                                     a.extra_data)
    if a.out:  # the detector reads its calibration from the sidecar
        out.with_suffix(".json").write_text(json.dumps(sidecar, indent=1) + "\n")
    metrics = evaluate(out, data_root, threads=a.threads, reps=a.bench_reps, imgsz=a.imgsz,
                       extra=a.extra_data)
    sidecar["metrics"] = metrics
    if a.out:
        out.with_suffix(".json").write_text(json.dumps(sidecar, indent=1) + "\n")
    (run / "torchrl_causal_metrics.json").write_text(json.dumps(sidecar, indent=1) + "\n")
    m = metrics["test_rule07"]
    print(
        f"held-out test ({m['n_views']} views, {m['n_positives']} positives): "
        f"precision {m['precision']:.3f} recall {m['recall']:.3f} mAP50 {m['map50']:.3f} "
        f"(thesis: precision 0.943 recall 0.902); "
        f"CPU {metrics['cpu']['ms_per_frame_b1']:.1f} ms/frame"
    )
    return sidecar


if __name__ == "__main__":
    main()
