"""Train the monocular depth network (:class:`torchrl_causal.perception.depth.MonoDepth`).

Trains the small FCRN-style network with the BerHu loss on the RGB / metric
depth pairs rendered by ``python -m torchrl_causal.perception.dataset``
(``DATA/depth/{train,val,test}.npz``), keeps the weights of the epoch with the
best validation abs rel, writes them (float16) and a JSON sidecar (command,
seed, data, epochs, held-out metrics, CPU timings), and prints the held-out
test metrics (abs rel, RMSE, delta < 1.25) as one JSON object: on the test
split at the data set's size (240x320, the reference camera) and on held-out
views rendered at the DQN's 84x84.

The shipped weights (7.7 M parameters, log BerHu) are made by ``make depth-weights`` in
two stages: 100 epochs from scratch on two camera-path data sets (video frames and board
close-ups)::

    python recipes/train_depth.py --data outputs/depth_vp outputs/depth_close --loss log-berhu \
        --epochs 100 --lr 3e-3 --batch-size 32 --widths 32 64 96 160 224 \
        --decoder 160 96 64 32 --device cuda --out outputs/depth_base.pt

(about 6 minutes on an H200, about 5 hours on one CPU core with ``--device cpu``), then a
fine-tune that adds obstacle close-ups (``--obstacle-frac 1``)::

    python recipes/train_depth.py --data outputs/depth_vp outputs/depth_close outputs/depth_obst \
        --init outputs/depth_base.pt --loss log-berhu --epochs 6 --lr 5e-4 --batch-size 16

(about 14 minutes on two CPU cores). The first stage of the file shipped was trained on an
H200 from a working-resolution cache of the same data (``benchmarks/gpu_depth/``) and
evaluated here with ``--evaluate-only``; its sidecar records every command, the first
stage's under ``init_sidecar``.
``--evaluate-only W`` alone prints W's held-out figures on ``--data`` and writes
nothing; with ``--out W2`` it also writes the weights there with the figures. (Until
2026-12-08 ``--out`` defaulted to the package's file here too, so evaluating the shipped
weights on another set replaced their recorded figures.)

Checkpoints go to ``--run-dir`` after every epoch (``last.pt``); ``--resume``
continues an interrupted run from there (same options).

Training augmentations (the network must serve 240x320 and 84x84 views, see
:mod:`torchrl_causal.perception.depth`): random horizontal crops of 96 or 128
working columns (an 84x84 view is a centre crop of a 4:3 view at the same
angular scale), horizontal flips, a low-resolution round trip (the image
rendered at 84 rows, then scaled up to the working 96) and colour jitter.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from torchrl_causal.perception.depth import (
    DEFAULT_WEIGHTS,
    FCRN,
    MonoDepth,
    berhu_loss,
    depth_metrics,
    evaluate_depth,
    read_sidecar,
    working_size,
)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, nargs="+",
                   help="data set root(s) (each holds depth/{train,val,test}.npz; several "
                        "roots are trained on together and tested one by one)")
    p.add_argument("--init", default=None,
                   help="fine-tune: start from these MonoDepth weights (their network "
                        "replaces --widths/--decoder)")
    p.add_argument("--out", default=None,
                   help="weights file to write (+ .json sidecar; default: the package's shipped "
                        "MonoDepth file; with --evaluate-only: none, the figures are only printed)")
    p.add_argument("--run-dir", default="outputs/depth_run", help="checkpoints and history")
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR/last.pt")
    p.add_argument("--epochs", type=int, default=12)
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--loss", choices=("berhu", "log-berhu"), default="berhu",
                   help="BerHu on depth (m; the shipped weights) or on log depth (relative "
                        "errors: near pixels weigh as much as far ones)")
    p.add_argument("--weight-decay", type=float, default=1e-4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch threads (1: one CPU core)")
    p.add_argument("--device", default="cpu",
                   help="where the network trains: cpu, cuda or cuda:N (the batches are built "
                        "on the CPU; the held-out evaluation and timings run on the CPU)")
    p.add_argument("--work-height", type=int, default=96)
    p.add_argument("--widths", type=int, nargs=5, default=[16, 24, 32, 64, 96])
    p.add_argument("--decoder", type=int, nargs=4, default=[64, 32, 24, 16])
    p.add_argument("--crop-widths", type=int, nargs="+", default=[96, 128])
    p.add_argument("--lowres-prob", type=float, default=0.3)
    p.add_argument("--limit-train", type=int, default=None, help="use the first N training pairs")
    p.add_argument("--limit-eval", type=int, default=None, help="evaluate on the first N pairs")
    p.add_argument("--n-test-84", type=int, default=300, help="held-out 84x84 views to evaluate (0: none)")
    p.add_argument("--reach-poses", type=int, default=200,
                   help="calibrate the arrival rule's range threshold for the new weights on "
                        "this many poses at the thesis board, stored in the weights as "
                        "reach_calibration (TelloEnv's default; 0: not calibrated)")
    p.add_argument("--stop-after", type=int, default=None,
                   help="stop (checkpointed, no weights written) after this many epochs; --resume continues")
    p.add_argument("--evaluate-only", default=None, metavar="WEIGHTS",
                   help="train nothing: evaluate these weights (trained elsewhere, e.g. on a GPU "
                        "box) on the held-out sets of --data, calibrate their arrival range, and "
                        "print the figures; with --out, also write the weights with the figures "
                        "there (the training record in the weights is kept)")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    for name in ("epochs", "batch_size", "threads"):
        if getattr(a, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(a, name)}")
    if not a.lr > 0:
        raise ValueError(f"--lr must be > 0, got {a.lr}")
    if not (a.device == "cpu" or re.fullmatch(r"cuda(:\d+)?", a.device)):
        raise ValueError(f"--device must be cpu, cuda or cuda:N, got {a.device!r}")
    if a.device != "cpu" and not torch.cuda.is_available():
        raise ValueError(f"--device {a.device!r}: CUDA is not available on this machine")
    if a.work_height < 32 or a.work_height % 32:
        raise ValueError(f"--work-height must be a multiple of 32, got {a.work_height}")
    if any(c < 32 or c % 32 for c in a.crop_widths):
        raise ValueError(f"--crop-widths must be multiples of 32, got {a.crop_widths}")
    if not 0.0 <= a.lowres_prob <= 1.0:
        raise ValueError(f"--lowres-prob must be in [0, 1], got {a.lowres_prob}")
    for root in a.data:
        for split in ("train", "val", "test"):
            f = Path(root) / "depth" / f"{split}.npz"
            if not f.is_file():
                raise ValueError(
                    f"--data {root!r}: {f} not found; render it with "
                    f"python -m torchrl_causal.perception.dataset --out {root} --n-train N --n-val N --n-test N"
                )
    if a.evaluate_only is not None and not Path(a.evaluate_only).is_file():
        raise ValueError(f"--evaluate-only {a.evaluate_only!r}: no such weights file")
    if a.out is None and a.evaluate_only is None:  # training writes the package's file
        a.out = str(DEFAULT_WEIGHTS)
    if a.init is not None and not Path(a.init).is_file():
        raise ValueError(f"--init {a.init!r}: no such weights file")
    if a.reach_poses != 0 and a.reach_poses < 10:
        raise ValueError(f"--reach-poses must be 0 (no calibration) or >= 10, got {a.reach_poses}")
    return a


def concat_splits(parts: list[dict]) -> dict:
    """Several :func:`load_split` results (same image size) as one."""
    if len(parts) == 1:
        return parts[0]
    sizes = {tuple(p["image_size"]) for p in parts}
    if len(sizes) > 1:
        raise ValueError(f"--data roots have different image sizes {sorted(sizes)}")
    return {"full": torch.cat([p["full"] for p in parts]), "low": torch.cat([p["low"] for p in parts]),
            "depth": torch.cat([p["depth"] for p in parts]), "image_size": parts[0]["image_size"],
            "n": sum(p["n"] for p in parts)}


# ----------------------------------------------------------------------------- data


def lowres_roundtrip(x: torch.Tensor, low_size, size) -> torch.Tensor:
    """Float images ``[N, 3, H, W]`` (0-255) rendered at ``low_size`` -- resized without
    antialiasing, like a direct low-resolution render -- and scaled back up to ``size``, as uint8."""
    lo = F.interpolate(x, size=low_size, mode="bilinear", align_corners=False)
    lo = F.interpolate(lo, size=size, mode="bilinear", align_corners=False)
    return lo.round().clamp(0, 255).to(torch.uint8)


def load_split(path: Path, work_height: int, limit: int | None = None, chunk: int = 200) -> dict:
    """Reads an ``.npz`` and resizes it once to the working resolution.

    Returns ``full`` (uint8 ``[N, 3, h, w]``, antialiased), ``low`` (the same
    image rendered at 84 rows -- resized without antialiasing, like a direct
    low-resolution render -- and scaled back up to ``h``) and ``depth``
    (float16 ``[N, h, w]``, area-averaged metres).
    """
    with np.load(path) as data:
        rgb, depth = data["rgb"], data["depth"]
        if limit is not None:
            rgb, depth = rgb[:limit], depth[:limit]
    N, H, W = rgb.shape[:3]
    h, w = working_size(H, W, work_height)
    low_size = (84, max(1, round(84 * W / H)))
    full = torch.empty((N, 3, h, w), dtype=torch.uint8)
    low = torch.empty_like(full)
    dep = torch.empty((N, h, w), dtype=torch.float16)
    for s in range(0, N, chunk):
        x = torch.from_numpy(rgb[s : s + chunk]).permute(0, 3, 1, 2).float()
        f = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
        full[s : s + chunk] = f.round().clamp(0, 255).to(torch.uint8)
        low[s : s + chunk] = lowres_roundtrip(x, low_size, (h, w))
        d = torch.from_numpy(depth[s : s + chunk].astype(np.float32)).unsqueeze(1)
        dep[s : s + chunk] = F.interpolate(d, size=(h, w), mode="area")[:, 0].half()
    return {"full": full, "low": low, "depth": dep, "image_size": (H, W), "n": N}


def make_batch(data: dict, idx: torch.Tensor, g: torch.Generator, crop_widths, lowres_prob):
    """An augmented batch: (float RGB ``[B, 3, h, cw]`` in [0, 1], depth ``[B, 1, h, cw]``)."""
    B = len(idx)
    w = data["full"].shape[-1]
    widths = [c for c in crop_widths if c <= w] or [w]
    cw = widths[int(torch.randint(len(widths), (), generator=g))]
    x0 = torch.randint(0, w - cw + 1, (B,), generator=g)
    use_low = torch.rand(B, generator=g) < lowres_prob
    flip = torch.rand(B, generator=g) < 0.5
    bright = 0.75 + 0.5 * torch.rand(B, 1, 1, 1, generator=g)
    contrast = 0.8 + 0.4 * torch.rand(B, 1, 1, 1, generator=g)
    gain = 0.92 + 0.16 * torch.rand(B, 3, 1, 1, generator=g)
    xs, ds = [], []
    for k in range(B):
        i, a = int(idx[k]), int(x0[k])
        img = (data["low"] if use_low[k] else data["full"])[i, :, :, a : a + cw]
        dep = data["depth"][i, :, a : a + cw]
        if flip[k]:
            img, dep = img.flip(-1), dep.flip(-1)
        xs.append(img)
        ds.append(dep)
    x = torch.stack(xs).float().div_(255.0)
    mean = x.mean((1, 2, 3), keepdim=True)
    x = ((x - mean) * contrast + mean) * bright * gain
    return x.clamp_(0.0, 1.0), torch.stack(ds).float().unsqueeze(1)


@torch.no_grad()
def validate(net: FCRN, data: dict, batch_size: int = 32) -> dict:
    """Metrics at the working resolution on the un-augmented full-width images
    (computed on the CPU, the network run where its parameters are)."""
    net.eval()
    device = next(net.parameters()).device
    total: dict = {}
    for s in range(0, data["n"], batch_size):
        x = data["full"][s : s + batch_size].float().div_(255.0)
        pred = net(x.to(device))[:, 0].float().cpu()
        for k, v in depth_metrics(pred, data["depth"][s : s + batch_size].float(), max_depth=net.max_depth).items():
            total[k] = total.get(k, 0) + v
    n, nn_ = total.pop("n_images"), max(total.pop("n_images_in_range"), 1)
    nc = max(total.pop("n_images_near"), 1)
    return {k: v / (nn_ if k.endswith("_in_range") else nc if k.endswith("_near") else n)
            for k, v in total.items()}


# ----------------------------------------------------------------------------- timing


def time_estimator(est: MonoDepth, size, batch: int, repeats: int = 5) -> float:
    """Median wall milliseconds per frame of ``est`` on random ``size`` images at ``batch``."""
    g = torch.Generator().manual_seed(0)
    px = torch.randint(0, 256, (batch, *size, 3), dtype=torch.uint8, generator=g)
    est(px)  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        est(px)
        times.append(time.perf_counter() - t0)
    return 1000.0 * float(np.median(times)) / batch


# ----------------------------------------------------------------------------- main


def heldout_figures(est: MonoDepth, a, roots: list[Path], data_meta: dict, image_size) -> tuple:
    """The held-out figures of ``est``: (metrics per test set, CPU ms per frame, the
    arrival range's calibration or None), as written into the sidecar."""
    root = roots[0]
    metrics = {
        "test_{}x{}".format(*image_size): evaluate_depth(
            est, root / "depth" / "test.npz", limit=a.limit_eval),
        "val_{}x{}".format(*image_size): evaluate_depth(
            est, root / "depth" / "val.npz", limit=a.limit_eval),
    }
    for r in roots[1:]:  # each further root's own test split, by its folder name
        metrics["test_{}x{}_{}".format(*image_size, r.name)] = evaluate_depth(
            est, r / "depth" / "test.npz", limit=a.limit_eval)
    if a.n_test_84 > 0:
        from torchrl_causal.perception.dataset import render_views

        views = render_views(
            "test", a.n_test_84, seed=int(data_meta.get("seed", 0)) + 1, image_size=(84, 84),
            layout_seed=int(data_meta.get("layout_seed", 0)),
        )
        metrics["test_84x84"] = evaluate_depth(est, views)
    timing = {
        f"{h}x{w}_batch{b}": round(time_estimator(est, (h, w), b), 2)
        for (h, w) in ((240, 320), (84, 84))
        for b in (1, 16)
    }
    reach = None
    if a.reach_poses > 0:
        from torchrl_causal.envs.reach import calibrate_reach_distance

        print(f"calibrating the arrival rule's range on {a.reach_poses} poses ...", flush=True)
        reach = calibrate_reach_distance(est, poses=a.reach_poses, seed=0)
        reach["command"] = (f"calibrate_reach_distance(est, poses={a.reach_poses}, seed=0) "
                            "(benchmarks/reach_calibration.py)")
    return metrics, timing, reach


def _rounded(metrics: dict) -> dict:
    """Metrics as the sidecar stores them (floats to 4 decimals)."""
    return {k: {kk: (round(vv, 4) if isinstance(vv, float) else vv) for kk, vv in m.items()}
            for k, m in metrics.items()}


def _command(argv) -> str:
    """This invocation as a shell command line (for the sidecar)."""
    return "python " + " ".join(
        shlex.quote(x) for x in [sys.argv[0], *(argv if argv is not None else sys.argv[1:])])


def _atomic_save(obj, path: Path):
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def evaluate_only(a, argv, roots: list[Path], data_meta: dict) -> dict:
    """``--evaluate-only``: the held-out figures of weights trained elsewhere, printed, and
    with ``--out`` written with them (their training record kept, the figures and this
    command added). Without ``--out`` nothing is written: evaluating the shipped weights on
    another set never replaces the package's file or its recorded figures."""
    est = MonoDepth.load(a.evaluate_only)
    record = dict(est.meta)
    history = read_sidecar(a.evaluate_only).get("history")
    with np.load(roots[0] / "depth" / "test.npz") as d:
        image_size = tuple(d["rgb"].shape[1:3])
    metrics, timing, reach = heldout_figures(est, a, roots, data_meta, image_size)
    record.update(
        metrics=_rounded(metrics), ms_per_frame_cpu=timing, reach_calibration=reach,
        evaluated_by=_command(argv),
        evaluated_with_torch=str(torch.__version__),
    )
    result = {"weights": None, "evaluated": str(a.evaluate_only), "metrics": record["metrics"],
              "ms_per_frame_cpu": timing}
    if a.out is not None:
        out = est.save(a.out, meta=record)
        out.with_suffix(".json").write_text(json.dumps({**record, "history": history}, indent=1)
                                            + "\n")
        result.update(weights=str(out), bytes=out.stat().st_size)
    print(json.dumps(result))
    return result


def main(argv=None) -> dict:
    a = parse_args(argv)
    torch.set_num_threads(a.threads)
    torch.manual_seed(a.seed)
    roots = [Path(r) for r in a.data]
    root = roots[0]
    metas = [json.loads((r / "meta.json").read_text()) if (r / "meta.json").is_file() else {}
             for r in roots]
    data_meta = metas[0]
    # a fine-tune's parent, read before --out may overwrite it (the shipped weights' chain)
    parent = ({k: v for k, v in read_sidecar(a.init).items() if k != "history"}
              if a.init is not None else None)
    if a.evaluate_only is not None:
        return evaluate_only(a, argv, roots, data_meta)
    run_dir = Path(a.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)

    t_load = time.perf_counter()
    train = concat_splits([load_split(r / "depth" / "train.npz", a.work_height, a.limit_train)
                           for r in roots])
    val = concat_splits([load_split(r / "depth" / "val.npz", a.work_height, a.limit_eval)
                         for r in roots])
    print(f"data: {train['n']} train, {val['n']} val pairs of {train['image_size']} "
          f"-> working {tuple(train['full'].shape[-2:])} ({time.perf_counter() - t_load:.1f} s)", flush=True)

    if a.init is not None:  # fine-tuning: the starting weights bring their network
        net = MonoDepth.load(a.init).net
        net.float()
    else:
        net = FCRN(widths=tuple(a.widths), decoder=tuple(a.decoder))
    device = torch.device(a.device)
    net.to(device)
    steps_per_epoch = max(1, train["n"] // a.batch_size)
    total_steps = steps_per_epoch * a.epochs
    opt = torch.optim.AdamW(net.parameters(), lr=a.lr, weight_decay=a.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=a.lr, total_steps=total_steps, pct_start=0.1)
    g = torch.Generator().manual_seed(a.seed)
    state = {"epoch": 0, "best": None, "best_state": None, "history": [], "train_seconds": 0.0}

    last = run_dir / "last.pt"
    if a.resume and last.is_file():
        ck = torch.load(last, map_location="cpu", weights_only=False)
        keys = ("data", "epochs", "batch_size", "lr", "seed", "widths", "decoder", "work_height",
                "limit_train", "init", "loss")
        # checkpoints written before --loss existed trained BerHu on depth
        diff = [k for k in keys if ck["args"].get(k, "berhu" if k == "loss" else None) != vars(a)[k]]
        if diff:
            raise ValueError(f"--resume: {last} was made with other options {diff}; use the same ones")
        net.load_state_dict(ck["net"])
        opt.load_state_dict(ck["opt"])
        sched.load_state_dict(ck["sched"])
        g.set_state(ck["gen"])
        torch.set_rng_state(ck["torch_rng"])
        state = ck["state"]
        print(f"resumed from {last} after epoch {state['epoch']}", flush=True)

    bar = None
    if not a.no_progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=total_steps, initial=state["epoch"] * steps_per_epoch, desc="train_depth", unit="step")
    for epoch in range(state["epoch"], a.epochs):
        net.train()
        t0 = time.perf_counter()
        perm = torch.randperm(train["n"], generator=g)
        losses = []
        for s in range(steps_per_epoch):
            idx = perm[s * a.batch_size : (s + 1) * a.batch_size]
            x, y = make_batch(train, idx, g, a.crop_widths, a.lowres_prob)
            x, y = x.to(device, non_blocking=True), y.to(device, non_blocking=True)
            loss = berhu_loss(net(x), y, log=a.loss == "log-berhu")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            losses.append(float(loss.detach()))
            if bar is not None:
                bar.update(1)
                bar.set_postfix(epoch=epoch + 1, loss=f"{np.mean(losses[-50:]):.3f}")
        v = validate(net, val)
        rec = {"epoch": epoch + 1, "loss": float(np.mean(losses)), "seconds": time.perf_counter() - t0,
               **{f"val_{k}": v[k] for k in ("abs_rel", "rmse", "delta1", "abs_rel_in_range")}}
        state["history"].append(rec)
        state["train_seconds"] += rec["seconds"]
        if state["best"] is None or v["abs_rel"] < state["best"]["val_abs_rel"]:
            state["best"] = rec
            state["best_state"] = {k: t.detach().cpu().clone() for k, t in net.state_dict().items()}
        state["epoch"] = epoch + 1
        _atomic_save(
            {"args": vars(a), "net": net.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
             "gen": g.get_state(), "torch_rng": torch.get_rng_state(), "state": state},
            last,
        )
        msg = json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in rec.items()})
        (bar.write if bar is not None else print)(msg)
        with open(run_dir / "history.jsonl", "a") as f:
            f.write(msg + "\n")
        if a.stop_after is not None and state["epoch"] >= a.stop_after and state["epoch"] < a.epochs:
            if bar is not None:
                bar.close()
            print(f"stopped after epoch {state['epoch']} (--stop-after); continue with --resume", flush=True)
            return {"stopped_after": state["epoch"], "checkpoint": str(last)}
    if bar is not None:
        bar.close()

    # ------------------------------------------------------------------ held-out evaluation
    net.cpu().load_state_dict(state["best_state"])
    est = MonoDepth(net, work_height=a.work_height)
    metrics, timing, reach = heldout_figures(est, a, roots, data_meta, train["image_size"])
    sidecar = {
        "name": "monodepth",
        "command": _command(argv),
        "seed": a.seed,
        "init": a.init,
        "init_sidecar": parent,
        "data": {
            "root": str(root),
            "roots": [str(r) for r in roots],
            "root_meta": [m.get("view_options") for m in metas],
            "counts": (data_meta.get("counts", {"train": train["n"], "val": val["n"]})
                       if len(roots) == 1 else {"train": train["n"], "val": val["n"]}),
            "image_size": list(train["image_size"]),
            "layout_seed": data_meta.get("layout_seed"),
            "data_seed": data_meta.get("seed"),
            "limit_train": a.limit_train,
            "dataset_commands": [m.get("command") for m in metas],
            "dataset_command": data_meta.get("command") or (
                f"python -m torchrl_causal.perception.dataset --out {root} "
                + " ".join(f"--n-{k} {v}" for k, v in data_meta["counts"].items())
                + f" --seed {data_meta.get('seed')} --layout-seed {data_meta.get('layout_seed')} "
                + "--image-size {} {}".format(*train["image_size"])
                if "counts" in data_meta else None
            ),
            "test_84x84": (
                f"render_views('test', {a.n_test_84}, seed={int(data_meta.get('seed', 0)) + 1}, "
                f"image_size=(84, 84), layout_seed={int(data_meta.get('layout_seed', 0))})"
                if a.n_test_84 > 0 else None
            ),
        },
        "epochs": a.epochs,
        "best_epoch": state["best"]["epoch"],
        "batch_size": a.batch_size,
        "lr": a.lr,
        "loss": a.loss,
        "work_height": a.work_height,
        "network": dict(net.config),
        "parameters": sum(p.numel() for p in net.parameters()),
        "train_seconds": round(state["train_seconds"], 1),
        "threads": a.threads,
        "device": a.device,
        "metrics": _rounded(metrics),
        "ms_per_frame_cpu": timing,
        "reach_calibration": reach,
        "torch": str(torch.__version__),
        "history": state["history"],
    }
    out = est.save(a.out, meta={k: v for k, v in sidecar.items() if k != "history"})
    out.with_suffix(".json").write_text(json.dumps(sidecar, indent=1) + "\n")
    result = {"weights": str(out), "bytes": out.stat().st_size, "metrics": sidecar["metrics"],
              "ms_per_frame_cpu": timing}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
