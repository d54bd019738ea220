"""``recipes/train_depth.py`` on a working-resolution cache (``make_cache.py``), on a GPU box.

::

    python benchmarks/gpu_depth/train_cached.py --cache .devrun/cache -- \\
        --data depth_vp depth_close --device cuda --loss log-berhu --batch-size 32 \\
        --lr 3e-3 --epochs 100 --widths 32 64 96 160 224 --decoder 160 96 64 32 \\
        --n-test-84 0 --reach-poses 0 --out /tmp/w/wider.pt --run-dir /tmp/runs/wider

Everything after ``--`` is ``train_depth.py``'s own command line; ``--data`` names the
cached roots by folder name. The training loop, its checkpoints and the weights file are
``train_depth.py``'s. Three things differ, all forced by what a GPU box can be sent:

* the data come from the cache, already at the working resolution;
* the 84-row low-resolution copies (``--lowres-prob``) are re-made from the 96 x 128
  working images (96 x 128 -> 84 x 112 -> 96 x 128) rather than from the 240 x 320
  renders, so they carry less aliasing;
* the held-out evaluation is skipped (the box has no test files): give the weights their
  figures and arrival calibration afterwards on the CPU with
  ``python recipes/train_depth.py --evaluate-only W --data ROOTS... --out W2``.
"""

from __future__ import annotations

import json
import lzma
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "recipes"))

import train_depth  # noqa: E402


def cached_loader(cache: Path):
    """A stand-in for ``train_depth.load_split`` that reads ``cache/<root>/<split>_*.npy.xz``."""

    def load(path, work_height, limit=None, chunk=200):
        root, split = Path(path).parent.parent.name, Path(path).stem
        info = json.loads((cache / root / "cache.json").read_text())
        with lzma.open(cache / root / f"{split}_full.npy.xz") as f:
            full = torch.from_numpy(np.load(f))
        with lzma.open(cache / root / f"{split}_depth.npy.xz") as f:
            dep = torch.from_numpy(np.load(f))
        if info["work_height"] != work_height:
            raise ValueError(f"the cache of {root} is at {info['work_height']} rows, not --work-height {work_height}")
        if limit is not None:
            full, dep = full[:limit], dep[:limit]
        low = torch.empty_like(full)
        h, w = full.shape[-2:]
        low_size = (84, max(1, round(84 * w / h)))
        for s in range(0, len(full), chunk):
            low[s : s + chunk] = train_depth.lowres_roundtrip(full[s : s + chunk].float(), low_size, (h, w))
        return {"full": full, "low": low, "depth": dep, "image_size": tuple(info["image_size"]), "n": len(full)}

    return load


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--cache" not in argv or "--" not in argv:
        raise SystemExit("usage: train_cached.py --cache DIR -- <train_depth.py options>")
    cache = Path(argv[argv.index("--cache") + 1])
    rest = argv[argv.index("--") + 1 :]
    if "--data" not in rest:
        raise SystemExit("train_depth.py's options need --data (the cached roots' folder names)")
    # --data names cached roots; train_depth.py checks for files, so each gets empty stand-ins
    i = rest.index("--data") + 1
    stand_in = Path("/tmp/train_cached_roots")
    while i < len(rest) and not rest[i].startswith("--"):
        name = Path(rest[i]).name
        if not (cache / name / "cache.json").is_file():
            raise SystemExit(f"--data {rest[i]}: no cache at {cache / name}")
        d = stand_in / name / "depth"
        d.mkdir(parents=True, exist_ok=True)
        for split in ("train", "val", "test"):
            (d / f"{split}.npz").touch()
        if (cache / name / "meta.json").is_file():
            (d.parent / "meta.json").write_text((cache / name / "meta.json").read_text())
        rest[i] = str(stand_in / name)
        i += 1
    train_depth.load_split = cached_loader(cache)
    train_depth.evaluate_depth = lambda *a, **k: {"skipped": "evaluate with train_depth.py --evaluate-only"}
    train_depth.time_estimator = lambda *a, **k: float("nan")
    torch.backends.cudnn.benchmark = True
    return train_depth.main(rest)


if __name__ == "__main__":
    main()
