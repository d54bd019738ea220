"""Memory and time of a replay-buffer checkpoint, TorchRL's checkpointer against ours.

The thesis protocol keeps 100k transitions (84x84x3 uint8 pixels plus the next
pixels, about 4.2 GB) in a memory-mapped ``LazyMemmapStorage``. This script
fills such a buffer with the real transition layout of the ``cbn_v2`` recipe
(one real rollout of the thesis scene, its rows repeated with fresh pixel
noise), then times ``rb.dumps`` (a mid-run checkpoint) and ``rb.loads`` (a
resume into a fresh buffer) with:

* ``torchrl`` -- TorchRL's default ``TensorStorageCheckpointer``
  (``TensorDict.memmap(copy_existing=True)`` of the full capacity);
* ``filled_rows`` -- :class:`torchrl_causal.data.FilledRowsCheckpointer`
  (the filled rows only, kernel-side file copies), which ``DQNLoop`` installs.

Every case runs in its own process. Prints one JSON object per case::

    {"figure": "checkpoint", "storage": "memmap", "checkpointer": "filled_rows",
     "capacity": 100000, "rows": 10000, "dumps_s": ..., "loads_s": ...,
     "dumps_peak_rss_mb": ..., "dumps_peak_anon_mb": ..., "dumps_peak_file_mb": ...,
     "rss_before_mb": ..., "disk_mb": ..., "exact": true}

``*_peak_*`` are the peaks of the process's ``VmRSS`` / ``RssAnon`` /
``RssFile + RssShmem`` sampled every 2 ms during the call; ``rss_before_mb`` is
``VmRSS`` just before it (the filled buffer's own pages included);
``disk_mb`` the blocks the checkpoint occupies on disk; ``exact`` whether the
resumed buffer equals the saved one row for row.

Usage::

    python benchmarks/checkpoint_memory.py [--capacity 100000] [--rows 10000 100000]
        [--storage memmap ram] [--dir DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))


def _status_mb() -> dict:
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "RssAnon", "RssFile", "RssShmem"):
                out[key] = int(value.split()[0]) / 1024.0
    return out


class _Peak:
    """Samples /proc/self/status in a thread while the block runs."""

    def __enter__(self):
        self.peak = {"VmRSS": 0.0, "RssAnon": 0.0, "file": 0.0}
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def _run(self):
        while not self._stop.is_set():
            s = _status_mb()
            self.peak["VmRSS"] = max(self.peak["VmRSS"], s["VmRSS"])
            self.peak["RssAnon"] = max(self.peak["RssAnon"], s["RssAnon"])
            self.peak["file"] = max(self.peak["file"], s["RssFile"] + s.get("RssShmem", 0.0))
            time.sleep(0.002)

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()


def _disk_mb(path: Path) -> float:
    return sum(p.stat().st_blocks * 512 for p in path.rglob("*") if p.is_file()) / 2**20


def _template():
    """One real rollout of the cbn_v2 recipe's env (random actions), with the keys
    ``DQNLoop`` stores for it (the actor's inputs at t and t+1, action, reward,
    done, terminated: about 42.5 KB a transition)."""
    import torch
    from hydra import compose, initialize_config_dir

    import recipe_utils as ru
    import train as recipe

    with tempfile.TemporaryDirectory() as tmp:
        with initialize_config_dir(config_dir=recipe.CONFIG_DIR, version_base=None):
            cfg = compose(config_name="cbn_v2", overrides=[f"output_dir={tmp}"])
    env = recipe.build_env(cfg, ru.VARIANTS["cbn_v2"], "thesis", "cpu")
    torch.manual_seed(0)
    keys = []
    for k in ("pixels", "causal_state"):
        keys += [k, ("next", k)]
    keys += ["action", ("next", "reward"), ("next", "done"), ("next", "terminated")]
    return env.rollout(32, break_when_any_done=False).select(*keys)


def child(args) -> dict:
    import torch
    from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer

    from torchrl_causal.data import FilledRowsCheckpointer

    work = Path(args.dir)
    template = _template()

    def make(scratch):
        if args.storage == "memmap":
            storage = LazyMemmapStorage(args.capacity, scratch_dir=scratch)
        else:
            storage = LazyTensorStorage(args.capacity)
        checkpointer = FilledRowsCheckpointer() if args.checkpointer == "filled_rows" else None
        rb = TensorDictReplayBuffer(storage=storage, batch_size=32, checkpointer=checkpointer)
        assert type(rb._storage.checkpointer).__name__ == (
            "FilledRowsCheckpointer" if checkpointer else "TensorStorageCheckpointer")
        return rb

    rb = make(work / "storage")
    g = torch.Generator().manual_seed(1)
    chunk = 1000
    for start in range(0, args.rows, chunk):
        n = min(chunk, args.rows - start)
        batch = template[torch.arange(n) % template.shape[0]].clone()
        for key in ("pixels", ("next", "pixels")):
            px = batch.get(key)
            batch.set(key, torch.randint(0, 256, px.shape, generator=g, dtype=torch.uint8))
        rb.extend(batch)
    ckpt = work / "ckpt"
    before = _status_mb()["VmRSS"]
    with _Peak() as peak:
        t0 = time.perf_counter()
        rb.dumps(ckpt)
        dumps_s = time.perf_counter() - t0
    rb2 = make(work / "storage2")
    with _Peak() as lpeak:
        t0 = time.perf_counter()
        rb2.loads(ckpt)
        loads_s = time.perf_counter() - t0
    idx = torch.randint(0, args.rows, (512,), generator=g)
    exact = len(rb2) == len(rb) and bool((rb2[idx] == rb[idx]).all())
    return {
        "figure": "checkpoint", "storage": args.storage, "checkpointer": args.checkpointer,
        "capacity": args.capacity, "rows": args.rows,
        "dumps_s": round(dumps_s, 2), "loads_s": round(loads_s, 2),
        "rss_before_mb": round(before, 1),
        "dumps_peak_rss_mb": round(peak.peak["VmRSS"], 1),
        "dumps_peak_anon_mb": round(peak.peak["RssAnon"], 1),
        "dumps_peak_file_mb": round(peak.peak["file"], 1),
        "loads_peak_rss_mb": round(lpeak.peak["VmRSS"], 1),
        "disk_mb": round(_disk_mb(ckpt), 1), "exact": exact,
    }


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--capacity", type=int, default=100_000)
    p.add_argument("--rows", type=int, nargs="+", default=[10_000, 100_000])
    p.add_argument("--storage", nargs="+", default=["memmap"], choices=["memmap", "ram"])
    p.add_argument("--checkpointers", nargs="+", default=["torchrl", "filled_rows"],
                   choices=["torchrl", "filled_rows"])
    p.add_argument("--dir", default=None, help="scratch folder (default: a temporary one)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--checkpointer", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    for rows in args.rows:
        if not 0 < rows <= args.capacity:
            p.error(f"--rows {rows} must be in [1, --capacity {args.capacity}]")
    if args.child:
        args.storage, args.rows = args.storage[0], args.rows[0]
        print(json.dumps(child(args)), flush=True)
        return
    base = Path(args.dir or tempfile.mkdtemp(prefix="ckpt_bench_"))
    for storage in args.storage:
        for rows in args.rows:
            for name in args.checkpointers:
                work = base / f"{storage}_{rows}_{name}"
                shutil.rmtree(work, ignore_errors=True)
                work.mkdir(parents=True)
                cmd = [sys.executable, __file__, "--child", "--storage", storage,
                       "--checkpointer", name, "--capacity", str(args.capacity),
                       "--rows", str(rows), "--dir", str(work)]
                out = subprocess.run(cmd, capture_output=True, text=True)
                shutil.rmtree(work, ignore_errors=True)
                if out.returncode:
                    raise SystemExit(f"{' '.join(cmd)} failed:\n{out.stderr[-3000:]}")
                print(out.stdout.strip().splitlines()[-1], flush=True)
    if args.dir is None:
        shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
