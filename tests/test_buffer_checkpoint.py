"""Replay-buffer checkpoints that write only the filled rows (:mod:`torchrl_causal.data.checkpoint`).

Real TorchRL buffers (RAM and memory-mapped storages), real files, the real
training loop; memory is read from ``/proc/self/status``.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import pandas as pd
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import (LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer,
                          TensorStorageCheckpointer)

from torchrl_causal.data import FilledRowsCheckpointer, install_filled_rows_checkpointer
from torchrl_causal.training import DQNLoop

ROOT = Path(__file__).resolve().parents[1]


def _batch(n: int, start: int, px: int = 16) -> TensorDict:
    g = torch.Generator().manual_seed(start)
    return TensorDict({
        "pixels": torch.randint(0, 256, (n, 3, px, px), generator=g, dtype=torch.uint8),
        "causal_state": torch.randint(0, 4, (n, 9), generator=g),
        "action": torch.arange(start, start + n) % 8,
        "next": {"pixels": torch.randint(0, 256, (n, 3, px, px), generator=g, dtype=torch.uint8),
                 "reward": torch.randn(n, 1, generator=g),
                 "done": torch.zeros(n, 1, dtype=torch.bool)},
    }, [n])


def _buffer(kind: str, capacity: int, scratch: Path | None, checkpointer=None):
    storage = (LazyMemmapStorage(capacity, scratch_dir=scratch) if kind == "memmap"
               else LazyTensorStorage(capacity))
    return TensorDictReplayBuffer(storage=storage, batch_size=8, checkpointer=checkpointer)


def _disk_bytes(path: Path) -> int:
    return sum(p.stat().st_blocks * 512 for p in path.rglob("*") if p.is_file())


@pytest.mark.parametrize("kind", ["memmap", "ram"])
@pytest.mark.parametrize("written", [37, 250])  # part-filled, and wrapped (capacity 100)
def test_round_trip_is_exact_and_continues_alike(tmp_path, kind, written):
    rb = _buffer(kind, 100, tmp_path / "s1", FilledRowsCheckpointer())
    for start in range(0, written, 25):
        rb.extend(_batch(min(25, written - start), start))
    rb.dumps(tmp_path / "ckpt")
    back = _buffer(kind, 100, tmp_path / "s2", FilledRowsCheckpointer())
    back.loads(tmp_path / "ckpt")
    assert len(back) == len(rb) == min(written, 100)
    assert (back[:len(rb)] == rb[:len(rb)]).all()
    # the writer's cursor came back too: the next writes land on the same rows
    rb.extend(_batch(30, 1000))
    back.extend(_batch(30, 1000))
    assert (back[:len(rb)] == rb[:len(rb)]).all()
    # and the same generator draws the same minibatch from both
    rb.set_rng(torch.Generator().manual_seed(3))
    back.set_rng(torch.Generator().manual_seed(3))
    assert (rb.sample() == back.sample()).all()


def test_part_filled_checkpoint_writes_only_its_rows(tmp_path):
    rb = _buffer("memmap", 2000, tmp_path / "s", FilledRowsCheckpointer())
    rb.extend(_batch(100, 0, px=32))
    rb.dumps(tmp_path / "ours")
    plain = _buffer("memmap", 2000, tmp_path / "s_plain")
    plain.extend(_batch(100, 0, px=32))
    plain.dumps(tmp_path / "torchrl")
    ours, theirs = _disk_bytes(tmp_path / "ours"), _disk_bytes(tmp_path / "torchrl")
    row = 2 * 3 * 32 * 32  # the two pixel frames dominate a row
    assert ours < 200 * row < theirs / 5, (ours, theirs)


@pytest.mark.parametrize("writer_is_ours", [True, False])
def test_reads_and_is_read_by_torchrls_checkpointer(tmp_path, writer_is_ours):
    mine, theirs = FilledRowsCheckpointer(), TensorStorageCheckpointer()
    rb = _buffer("memmap", 64, tmp_path / "a", mine if writer_is_ours else theirs)
    rb.extend(_batch(40, 0))
    rb.dumps(tmp_path / "ckpt")
    back = _buffer("ram", 64, None, theirs if writer_is_ours else mine)
    back.loads(tmp_path / "ckpt")
    assert len(back) == 40 and (back[:40] == rb[:40]).all()


def test_resume_into_a_buffer_of_another_size_is_a_clear_error(tmp_path):
    rb = _buffer("memmap", 64, tmp_path / "a", FilledRowsCheckpointer())
    rb.extend(_batch(10, 0))
    rb.dumps(tmp_path / "ckpt")
    small = _buffer("memmap", 32, tmp_path / "b", FilledRowsCheckpointer())
    small.extend(_batch(1, 0))
    with pytest.raises(ValueError, match="shape.*buffer_size"):
        small.loads(tmp_path / "ckpt")


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS")


def _peak_rise_mb(fn) -> float:
    """How far the process's resident memory rises above its level before ``fn``."""
    before, peak, stop = _rss_mb(), [0.0], threading.Event()

    def watch():
        while not stop.is_set():
            peak[0] = max(peak[0], _rss_mb())
            time.sleep(0.002)

    t = threading.Thread(target=watch)
    t.start()
    try:
        fn()
    finally:
        stop.set()
        t.join()
    return max(peak[0], _rss_mb()) - before


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc (Linux)")
def test_memmap_checkpoint_does_not_map_a_second_copy(tmp_path):
    """A full 300 MB memory-mapped buffer: TorchRL's checkpointer raises the
    process's resident memory by about the buffer's size (both files mapped),
    ours by almost nothing (the kernel copies the file); resuming likewise."""
    capacity, px = 1500, 128  # 2 x 3 x 128 x 128 uint8 = 98 KB a row: 147 MB of pixels
    results = {}
    for name, ckpt in (("torchrl", None), ("ours", FilledRowsCheckpointer())):
        rb = _buffer("memmap", capacity, tmp_path / f"s_{name}", ckpt)
        for start in range(0, capacity, 250):
            rb.extend(_batch(250, start, px=px))
        dump = _peak_rise_mb(lambda: rb.dumps(tmp_path / f"ckpt_{name}"))
        back = _buffer("memmap", capacity, tmp_path / f"r_{name}", ckpt)
        load = _peak_rise_mb(lambda: back.loads(tmp_path / f"ckpt_{name}"))
        assert (back[::97] == rb[::97]).all()
        results[name] = (dump, load)
        del rb, back
    assert results["torchrl"][0] > 100, results  # the measurement sees a second copy
    assert results["ours"][0] < 20 and results["ours"][1] < 20, results


def test_loop_installs_it_and_resumes_a_wrapped_memmap_buffer_exactly(tmp_path):
    """A grid-world run whose memmap buffer (300 rows) wraps three times, stopped
    at a mid-run checkpoint and resumed, ends exactly as the run never stopped."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import gridnav

    torch.set_num_threads(1)
    opts = dict(checkpoint_interval_frames=240, final_eval_episodes=5, buffer_size=300)

    def loop(out, **extra):
        base = gridnav.build_loop("expert", 0, 900, output_dir=out, **opts, **extra)
        rb = TensorDictReplayBuffer(
            storage=LazyMemmapStorage(300, scratch_dir=out / "scratch", existsok=True),
            batch_size=base.config.batch_size)
        return DQNLoop(base.env, base.actor, base.explorer, hook=base.hook,
                       config=base.config, replay_buffer=rb, output_dir=out,
                       eval_envs=base.eval_envs)

    whole = loop(tmp_path / "whole")
    assert isinstance(whole.replay_buffer._storage.checkpointer, FilledRowsCheckpointer)
    whole = whole.run()
    part = loop(tmp_path / "part", stop_after_frames=500).run()
    assert part["stopped_early"] and part["frames"] < 900
    resumed = loop(tmp_path / "part").run(resume=True)
    assert whole["frames"] == resumed["frames"] == 900
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "whole" / "episodes.csv"),
                                  pd.read_csv(tmp_path / "part" / "episodes.csv"))
    ma = torch.load(tmp_path / "whole" / "model.pt")
    mb = torch.load(tmp_path / "part" / "model.pt")
    assert all(torch.equal(ma[k], mb[k]) for k in ma)


def test_a_checkpointer_the_user_chose_is_kept():
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10))
    assert install_filled_rows_checkpointer(rb) is True
    assert isinstance(rb._storage.checkpointer, FilledRowsCheckpointer)
    hooked = TensorStorageCheckpointer()
    hooked.register_save_hook(lambda data, path: data)  # TorchRL's, configured by the user
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10), checkpointer=hooked)
    assert install_filled_rows_checkpointer(rb) is False
    assert rb._storage.checkpointer is hooked
    custom = type("MyCheckpointer", (TensorStorageCheckpointer,), {})()
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10), checkpointer=custom)
    assert install_filled_rows_checkpointer(rb) is False
    assert rb._storage.checkpointer is custom
