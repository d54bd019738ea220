"""Working-resolution cache of MonoDepth training data, small enough to carry to a GPU box.

::

    python benchmarks/gpu_depth/make_cache.py outputs/depth_vp outputs/depth_close \\
        --out .devrun/cache

For each data set root (``ROOT/depth/{train,val}.npz``, rendered by
``python -m torchrl_causal.perception.dataset``) it runs ``recipes/train_depth.py``'s own
``load_split`` (the resize to the working resolution that training does first) and
stores the full-width working images (uint8) and depth (float16) as xz-compressed
``.npy`` files, with the root's ``meta.json``. At 96 x 128 the two camera-path sets
(4,000 training + 400 validation views) take 37 MB against 270 MB of ``.npz``: the
device tool carries at most 64 MiB with the working tree.

Not cached: the 84-row low-resolution copies (``train_cached.py`` re-makes them from the
working images) and the test splits (held-out figures are computed afterwards on the
CPU with ``recipes/train_depth.py --evaluate-only``).
"""

from __future__ import annotations

import argparse
import json
import lzma
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "recipes"))

from train_depth import load_split  # noqa: E402


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("roots", nargs="+", type=Path, help="data set roots (ROOT/depth/*.npz)")
    p.add_argument("--out", type=Path, required=True, help="cache folder")
    p.add_argument("--work-height", type=int, default=96)
    a = p.parse_args(argv)
    for r in a.roots:
        for split in ("train", "val"):
            if not (r / "depth" / f"{split}.npz").is_file():
                p.error(f"{r}: {r / 'depth' / (split + '.npz')} not found")
    for r in a.roots:
        dst = a.out / r.name
        dst.mkdir(parents=True, exist_ok=True)
        if (r / "meta.json").is_file():
            shutil.copy(r / "meta.json", dst / "meta.json")
        info = {"work_height": a.work_height, "source": str(r), "n": {}}
        for split in ("train", "val"):
            d = load_split(r / "depth" / f"{split}.npz", a.work_height)
            for key in ("full", "depth"):
                with lzma.open(dst / f"{split}_{key}.npy.xz", "wb", preset=6) as f:
                    np.save(f, d[key].numpy())
            info["image_size"], info["n"][split] = list(d["image_size"]), d["n"]
            print(f"{r.name} {split}: {d['n']} views", flush=True)
        (dst / "cache.json").write_text(json.dumps(info, indent=1) + "\n")


if __name__ == "__main__":
    main()
