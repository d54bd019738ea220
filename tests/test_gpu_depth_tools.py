"""benchmarks/gpu_depth: MonoDepth trained from a working-resolution cache (what a GPU box
is sent), then given its held-out figures on the CPU with train_depth.py --evaluate-only.
Runs on the CPU here (--device cpu); the same scripts ran on an H200 (docs/perception.rst)."""

import json
import lzma

import numpy as np
import pytest
import torch

from torchrl_causal.perception.dataset import write_datasets
from torchrl_causal.perception.depth import MonoDepth
from _scripts import load_script


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("gd") / "tiny"
    write_datasets(root, n_train=16, n_val=4, n_test=4, seed=3, image_size=(60, 80), progress=False)
    return root


def test_cache_is_train_depths_own_resize_and_trains(data, tmp_path, capsys):
    make_cache = load_script("benchmarks/gpu_depth/make_cache.py")
    train_cached = load_script("benchmarks/gpu_depth/train_cached.py")
    train_depth = load_script("recipes/train_depth.py")
    cache = tmp_path / "cache"
    make_cache.main([str(data), "--out", str(cache)])
    ref = train_depth.load_split(data / "depth" / "train.npz", 96)
    with lzma.open(cache / "tiny" / "train_full.npy.xz") as f:
        assert torch.equal(torch.from_numpy(np.load(f)), ref["full"])
    with lzma.open(cache / "tiny" / "train_depth.npy.xz") as f:
        assert torch.equal(torch.from_numpy(np.load(f)), ref["depth"])
    info = json.loads((cache / "tiny" / "cache.json").read_text())
    assert info["image_size"] == [60, 80] and info["n"] == {"train": 16, "val": 4}
    loaded = train_cached.cached_loader(cache)(data / "depth" / "train.npz", 96)
    assert loaded["image_size"] == (60, 80) and torch.equal(loaded["full"], ref["full"])
    assert loaded["low"].shape == ref["low"].shape  # re-made from the working images
    assert (loaded["low"].float() - ref["low"].float()).abs().mean() < 8

    w = tmp_path / "w.pt"
    train_cached.main(["--cache", str(cache), "--", "--data", "tiny", "--device", "cpu", "--epochs", "1",
                       "--batch-size", "8", "--widths", "8", "8", "8", "8", "8", "--decoder", "8", "8", "8", "8",
                       "--n-test-84", "0", "--reach-poses", "0", "--no-progress", "--out", str(w),
                       "--run-dir", str(tmp_path / "run")])
    side = json.loads(w.with_suffix(".json").read_text())
    assert side["epochs"] == 1 and side["device"] == "cpu" and side["data"]["counts"]["train"] == 16
    assert all("skipped" in m for m in side["metrics"].values())
    out = train_depth.main(["--data", str(data), "--evaluate-only", str(w), "--out", str(tmp_path / "e.pt"),
                            "--n-test-84", "0", "--reach-poses", "0"])
    assert set(out["metrics"]) == {"test_60x80", "val_60x80"} and out["metrics"]["test_60x80"]["abs_rel"] > 0
    e = MonoDepth.load(tmp_path / "e.pt")
    assert e.meta["metrics"] == out["metrics"] and e.meta["epochs"] == 1
    with pytest.raises(SystemExit, match="no cache"):
        train_cached.main(["--cache", str(cache), "--", "--data", "missing"])
