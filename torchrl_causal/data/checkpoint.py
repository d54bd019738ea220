"""Replay-buffer checkpoints that copy only the filled rows, file to file.

TorchRL's default :class:`~torchrl.data.TensorStorageCheckpointer` saves a
``TensorStorage`` with ``TensorDict.memmap(path, copy_existing=True)``: every
leaf is copied at its full *capacity* through memory maps of both the source and
the new file. For the thesis protocol's buffer (100k frames of 84x84x3 uint8
pixels plus the next pixels, about 4.2 GB) one mid-run checkpoint then maps
8 GB of file pages into the process (measured peak RSS 9 GB) and writes 4.2 GB
to disk even when a few thousand rows are filled.

:class:`FilledRowsCheckpointer` writes the same on-disk format (``rb.loads`` and
TorchRL's own checkpointer can read it), but

* copies only the rows ``[0, len(storage))`` -- the rows a round-robin writer has
  filled -- and leaves the rest of each file a sparse hole;
* copies memory-mapped leaves (``LazyMemmapStorage``) with ``os.copy_file_range``,
  so the bytes move inside the kernel and never enter the process's memory;
* writes in-RAM leaves (``LazyTensorStorage``, also on CUDA) in bounded chunks
  with plain file writes, never through a memory map;
* loads the same way back into the live storage.

:class:`~torchrl_causal.training.DQNLoop` installs it on the replay buffer's
storage when that storage still has TorchRL's default checkpointer.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.memmap import MemoryMappedTensor
from torchrl.data import TensorStorageCheckpointer

__all__ = ["FilledRowsCheckpointer", "install_filled_rows_checkpointer"]

_CHUNK_BYTES = 64 << 20  # bound on the bytes staged in RAM per write


def _filename(t) -> str | None:
    """The file behind a memory-mapped leaf; None for RAM / CUDA / anonymous maps."""
    if not isinstance(t, MemoryMappedTensor):
        return None
    try:
        name = t.filename
    except RuntimeError:  # a memory map without a file (LazyMemmapStorage, no scratch_dir)
        return None
    return str(name) if name else None


def _row_bytes(t: torch.Tensor) -> int:
    """Bytes of one row (one index of the leading dimension) of a contiguous tensor."""
    return t[0].numel() * t.element_size() if t.shape[0] else 0


def _copy_file_prefix(src: str, dst: str, nbytes: int) -> None:
    """Copies the first ``nbytes`` of ``src`` over the start of ``dst`` (kernel side)."""
    with open(src, "rb") as fin, open(dst, "r+b") as fout:
        done = 0
        while done < nbytes:
            try:
                n = os.copy_file_range(fin.fileno(), fout.fileno(), nbytes - done, done, done)
            except OSError:  # e.g. across file systems on old kernels: plain reads
                fin.seek(done)
                fout.seek(done)
                n = fout.write(fin.read(min(_CHUNK_BYTES, nbytes - done)))
            if n == 0:
                raise OSError(f"short copy from {src} to {dst}: {done} of {nbytes} bytes")
            done += n


def _write_rows(src: torch.Tensor, dst: str, rows: int) -> None:
    """Writes ``src[:rows]`` (any device) to the start of the raw file ``dst``."""
    if rows == 0:
        return
    row_bytes = max(1, _row_bytes(src))
    step = max(1, _CHUNK_BYTES // row_bytes)
    with open(dst, "r+b") as fout:
        for start in range(0, rows, step):
            chunk = src[start:min(rows, start + step)]
            chunk = chunk.detach().to("cpu").contiguous()
            fout.write(memoryview(chunk.view(torch.uint8).reshape(-1).numpy()))


def _read_rows(src: str, dst: torch.Tensor, rows: int) -> None:
    """Reads the first ``rows`` rows of the raw file ``src`` into ``dst[:rows]``."""
    if rows == 0:
        return
    row_bytes = _row_bytes(dst)
    step = max(1, _CHUNK_BYTES // max(1, row_bytes))
    with open(src, "rb") as fin:
        for start in range(0, rows, step):
            stop = min(rows, start + step)
            buf = bytearray(fin.read((stop - start) * row_bytes))
            chunk = torch.frombuffer(buf, dtype=torch.uint8).view(dst.dtype)
            dst[start:stop].copy_(chunk.reshape(dst[start:stop].shape))


def _leaf_pairs(a: TensorDictBase, b: TensorDictBase):
    keys = sorted(a.keys(include_nested=True, leaves_only=True), key=str)
    for key in keys:
        yield key, a.get(key), b.get(key)


class FilledRowsCheckpointer(TensorStorageCheckpointer):
    """A ``TensorStorage`` checkpointer that writes only the filled rows.

    Same files as :class:`~torchrl.data.TensorStorageCheckpointer` (a memory-mapped
    ``TensorDict`` of the storage's full shape plus ``storage_metadata.json``), so
    either can read what the other wrote; the rows past ``len(storage)`` are left
    as sparse holes. Memory-mapped storages are copied by the kernel
    (``os.copy_file_range``), so a checkpoint of a 4 GB ``LazyMemmapStorage`` does
    not raise the process's resident memory; in-RAM and CUDA storages are written
    in 64 MB chunks. Storages holding a bare tensor or a pytree, or with save /
    load hooks, fall back to TorchRL's behaviour.

    The rows ``[0, len)`` are the filled ones for the round-robin writers a
    ``TensorDictReplayBuffer`` uses; a writer that fills rows out of order (a
    prioritised max-value writer) must keep TorchRL's checkpointer. Storages
    with ``ndim > 1`` fall back to TorchRL's behaviour too.

    Example:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyMemmapStorage, TensorDictReplayBuffer
        >>> from torchrl_causal.data import FilledRowsCheckpointer
        >>> rb = TensorDictReplayBuffer(storage=LazyMemmapStorage(1000), batch_size=4,
        ...                             checkpointer=FilledRowsCheckpointer())
        >>> _ = rb.extend(TensorDict({"obs": torch.arange(30.).view(10, 3)}, [10]))
        >>> d = tempfile.mkdtemp()
        >>> rb.dumps(d)
        >>> rb2 = TensorDictReplayBuffer(storage=LazyMemmapStorage(1000), batch_size=4,
        ...                              checkpointer=FilledRowsCheckpointer())
        >>> rb2.loads(d)
        >>> type(rb2._storage.checkpointer).__name__
        'FilledRowsCheckpointer'
        >>> len(rb2), bool((rb2[:10]["obs"] == rb[:10]["obs"]).all())
        (10, True)
    """

    def _plain(self, storage) -> bool:
        data = getattr(storage, "_storage", None)
        return bool(
            self._save_hooks or self._load_hooks
            or getattr(storage, "ndim", 1) != 1  # multi-dim storages fill rows differently
            # a bare tensor or a pytree (an uninitialized storage holds None)
            or (data is not None and not isinstance(data, TensorDictBase))
        )

    def dumps(self, storage, path) -> None:
        """Saves the filled rows of ``storage`` under ``path`` (a new or empty folder)."""
        if not storage.initialized:
            raise RuntimeError("Cannot save a non-initialized storage.")
        if self._plain(storage):
            return super().dumps(storage, path)
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        src_td = storage._storage
        rows = int(storage._len)
        # the destination files: same structure and meta.json, full capacity, sparse
        dst_td = src_td.memmap_like(path, existsok=True)
        for key, src, dst in _leaf_pairs(src_td, dst_td):
            dst_file = _filename(dst)
            if dst_file is None:
                raise RuntimeError(f"leaf {key!r} of the saved storage has no file")
            src_file = _filename(src)
            if src_file is not None and src.is_contiguous():
                _copy_file_prefix(src_file, dst_file, rows * _row_bytes(src))
            else:
                _write_rows(src, dst_file, rows)
        del dst_td
        with open(path / "storage_metadata.json", "w") as file:
            json.dump({"metadata": {}, "is_pytree": False, "len": storage._len}, file)

    def loads(self, storage, path) -> None:
        """Loads a checkpoint written by this class or by TorchRL's checkpointer."""
        path = Path(path)
        meta = json.loads((path / "storage_metadata.json").read_text())
        if self._plain(storage) or meta.get("is_pytree"):
            return super().loads(storage, path)
        rows = int(meta["len"])
        saved = TensorDict.load_memmap(path)
        if not storage.initialized:
            storage._init(saved[0])
        dst_td = storage._storage
        if dst_td.shape != saved.shape:
            raise ValueError(
                f"the checkpoint at {path} holds a storage of shape {tuple(saved.shape)}, the "
                f"buffer's storage has shape {tuple(dst_td.shape)} (same buffer_size needed)"
            )
        for key, src, dst in _leaf_pairs(saved, dst_td):
            src_file = _filename(src)
            dst_file = _filename(dst)
            if dst_file is not None and dst.is_contiguous():
                _copy_file_prefix(src_file, dst_file, rows * _row_bytes(src))
            else:
                _read_rows(src_file, dst, rows)
        del saved
        storage._len = rows


def install_filled_rows_checkpointer(replay_buffer) -> bool:
    """Gives ``replay_buffer``'s storage a :class:`FilledRowsCheckpointer`.

    Only where the storage still has TorchRL's default
    :class:`~torchrl.data.TensorStorageCheckpointer`, without hooks (a
    checkpointer chosen or configured by the user is kept). Returns whether it
    was installed.

    Example:
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl_causal.data import install_filled_rows_checkpointer
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100))
        >>> install_filled_rows_checkpointer(rb)
        True
    """
    if getattr(replay_buffer, "_initialized", True) is False:  # delayed init: set at init
        if replay_buffer._init_checkpointer is not None:
            return False
        replay_buffer._init_checkpointer = FilledRowsCheckpointer()
        return True
    storage = getattr(replay_buffer, "_storage", None)
    current = getattr(storage, "checkpointer", None)
    if (type(current) is not TensorStorageCheckpointer
            or current._save_hooks or current._load_hooks):  # chosen or configured by the user
        return False
    storage.checkpointer = FilledRowsCheckpointer()
    return True
