"""Run records and checkpoint files: what makes a training run resumable after ``kill -9``.

* :class:`EpisodeCSV` -- an append-only CSV (one row per episode, evaluation or
  relearn) that is cut back to a checkpoint's row count on resume;
* :func:`atomic_save` -- ``torch.save`` to a temporary file, then an atomic
  rename, so a kill never leaves half a checkpoint;
* :func:`rng_state` / :func:`set_rng_state` -- Python, NumPy and torch RNGs.

Example:
    >>> import tempfile, torch
    >>> from pathlib import Path
    >>> from torchrl_causal.training import EpisodeCSV, atomic_save
    >>> d = Path(tempfile.mkdtemp())
    >>> csv = EpisodeCSV(d / "episodes.csv", ["episode", "reward"])
    >>> csv.write({"episode": 1, "reward": 0.5}); csv.write({"episode": 2, "reward": -1.0})
    >>> csv.truncate(1); csv.n_rows
    1
    >>> atomic_save({"frames": 10}, d / "last.pt"); torch.load(d / "last.pt")["frames"]
    10
"""

from __future__ import annotations

import csv
import os
import random
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch

__all__ = ["EpisodeCSV", "atomic_save", "rng_state", "set_rng_state"]


class EpisodeCSV:
    """Append-only CSV with a fixed header, flushed after every row.

    On resume the file is cut back to the rows that existed when the
    checkpoint was written (:meth:`truncate`), so rows written after the last
    checkpoint by an interrupted run (even a half-written last line) do not
    appear twice.

    Args:
        path: the CSV file (created with its header when missing or empty).
        columns: the header.

    Raises:
        ValueError: the file exists with another header.

    Example:
        >>> import tempfile
        >>> from pathlib import Path
        >>> p = Path(tempfile.mkdtemp()) / "eval.csv"
        >>> rows = EpisodeCSV(p, ["frames", "success_rate"])
        >>> rows.write({"frames": 2000, "success_rate": 0.4})
        >>> p.read_text().splitlines()
        ['frames,success_rate', '2000,0.4']
    """

    def __init__(self, path: str | os.PathLike, columns: Sequence[str]):
        self.path = Path(path)
        self.columns = list(columns)
        self.n_rows = 0
        if self.path.exists() and self.path.stat().st_size > 0:
            with open(self.path, newline="") as f:
                rows = list(csv.reader(f))
            if rows and rows[0] != self.columns:
                raise ValueError(f"{self.path} has columns {rows[0]}, expected {self.columns}")
            self.n_rows = max(len(rows) - 1, 0)
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "w", newline="") as f:
                csv.writer(f).writerow(self.columns)

    def truncate(self, n_rows: int) -> None:
        """Keeps the header and the first ``n_rows`` rows."""
        with open(self.path, newline="") as f:
            rows = list(csv.reader(f))
        with open(self.path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(self.columns)
            w.writerows(rows[1 : n_rows + 1])
        self.n_rows = min(n_rows, max(len(rows) - 1, 0))

    def write(self, row: Mapping[str, Any]) -> None:
        """Appends one row (missing columns are left empty)."""
        with open(self.path, "a", newline="") as f:
            csv.writer(f).writerow([_fmt(row.get(c, "")) for c in self.columns])
        self.n_rows += 1


def _fmt(x: Any) -> Any:
    if isinstance(x, torch.Tensor):
        x = x.item()
    if isinstance(x, (bool, np.bool_)):
        return int(x)
    if isinstance(x, float):
        return f"{x:.6g}"
    return x


def rng_state() -> dict:
    """The global RNG states of Python, NumPy and torch.

    Example:
        >>> import torch
        >>> state = rng_state(); a = torch.rand(2)
        >>> set_rng_state(state); torch.equal(a, torch.rand(2))
        True
    """
    return {
        "python": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": torch.get_rng_state(),
    }


def set_rng_state(state: Mapping) -> None:
    """Restores what :func:`rng_state` returned.

    Example:
        >>> import numpy as np
        >>> state = rng_state(); a = np.random.rand()
        >>> set_rng_state(state); a == np.random.rand()
        True
    """
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])


def atomic_save(obj: Any, path: str | os.PathLike) -> None:
    """``torch.save`` to a temporary file, fsync, then rename: a kill never leaves half a file.

    Example:
        >>> import tempfile, torch
        >>> from pathlib import Path
        >>> path = Path(tempfile.mkdtemp()) / "last.pt"
        >>> atomic_save({"step": 3}, path); torch.load(path)["step"], path.with_suffix(".pt.tmp").exists()
        (3, False)
    """
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "wb") as f:
        torch.save(obj, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
