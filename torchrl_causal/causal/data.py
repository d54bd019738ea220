"""Per-action transition storage for causal learning (thesis Alg. 2, line 1).

Every transition is stored, integer-coded, as one row of the action's DBN
table: the nine codes at ``t``, the nine codes at ``t+1`` and the reward class
(``1`` = positive iff the environment reward is ``>= 0``, ``0`` = negative),
in the column order of :meth:`~torchrl_causal.schema.VariableSchema.node_names`.
Rows live in a numpy array per action that doubles its capacity when full
(amortised O(1) appends, no DataFrame rebuilt per step); :meth:`TransitionData.rows`
returns a view of the filled part.

Example:
    >>> import torch
    >>> from torchrl_causal.causal.data import TransitionData
    >>> data = TransitionData(n_actions=8)
    >>> s = torch.zeros(3, 9, dtype=torch.long)
    >>> data.add(s, torch.tensor([0, 0, 5]), s, torch.tensor([-9.0, 1.0, 3.0]))
    >>> data.counts().tolist()
    [2, 0, 0, 0, 0, 1, 0, 0]
    >>> data.rows(0)[:, -1].tolist()
    [0, 1]
"""

from __future__ import annotations

import numpy as np
import torch

from torchrl_causal.schema import DEFAULT_SCHEMA, VariableSchema

__all__ = ["TransitionData"]


def _to_numpy(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


class TransitionData:
    """Growing, integer-coded transition tables, one per action.

    Args:
        n_actions: number of actions.
        schema: the variable schema of ``state_t`` / ``state_t1``.
        initial_capacity: rows allocated per action before the first growth.
        max_rows: keep only the newest ``max_rows`` rows per action (a sliding
            window); ``None`` keeps everything.

    Example:
        >>> import torch
        >>> d = TransitionData(n_actions=2, initial_capacity=1)
        >>> s = torch.ones(5, 9, dtype=torch.long)
        >>> d.add(s, torch.zeros(5, dtype=torch.long), s, torch.ones(5))
        >>> d.rows(0).shape
        (5, 19)
    """

    def __init__(
        self,
        n_actions: int = 8,
        schema: VariableSchema = DEFAULT_SCHEMA,
        *,
        initial_capacity: int = 1024,
        max_rows: int | None = None,
    ):
        if not isinstance(n_actions, int) or n_actions < 1:
            raise ValueError(f"n_actions must be a positive int, got {n_actions!r}")
        if initial_capacity < 1:
            raise ValueError(f"initial_capacity must be >= 1, got {initial_capacity!r}")
        if max_rows is not None and max_rows < 1:
            raise ValueError(f"max_rows must be None or >= 1, got {max_rows!r}")
        self.schema = schema
        self.n_actions = n_actions
        self.max_rows = max_rows
        self.n_cols = 2 * len(schema) + 1
        self.dtype = np.int8 if max(schema.cardinalities) <= 127 else np.int32
        self._cards = np.asarray(schema.cardinalities)
        self._buf = [np.zeros((initial_capacity, self.n_cols), self.dtype) for _ in range(n_actions)]
        self._n = np.zeros(n_actions, dtype=np.int64)
        self.total_added = 0

    def add(self, state_t, action, state_t1, reward) -> None:
        """Append a batch of transitions.

        Args:
            state_t: int codes ``[N, n_vars]``.
            action: action indices ``[N]`` (or ``[N, 1]``).
            state_t1: int codes ``[N, n_vars]``.
            reward: env rewards ``[N]`` (or ``[N, 1]``); class positive iff ``>= 0``.
        """
        s0 = _to_numpy(state_t).reshape(-1, len(self.schema))
        s1 = _to_numpy(state_t1).reshape(-1, len(self.schema))
        a = _to_numpy(action).reshape(-1).astype(np.int64)
        r = _to_numpy(reward).reshape(-1)
        n = s0.shape[0]
        if not (s1.shape[0] == a.shape[0] == r.shape[0] == n):
            raise ValueError(
                f"state_t, action, state_t1 and reward must have the same batch size, got "
                f"{s0.shape[0]}, {a.shape[0]}, {s1.shape[0]}, {r.shape[0]}"
            )
        if n == 0:
            return
        if a.min() < 0 or a.max() >= self.n_actions:
            raise ValueError(f"action must be in [0, {self.n_actions}), got values {np.unique(a).tolist()}")
        for name, s in (("state_t", s0), ("state_t1", s1)):
            if (s < 0).any() or (s >= self._cards).any():
                raise ValueError(f"{name} has codes outside the schema cardinalities {tuple(self._cards)}")
        rows = np.concatenate([s0, s1, (r >= 0)[:, None]], axis=1).astype(self.dtype)
        for act in np.unique(a):
            self._append(int(act), rows[a == act])
        self.total_added += n

    def _append(self, act: int, rows: np.ndarray) -> None:
        n, m = int(self._n[act]), rows.shape[0]
        buf = self._buf[act]
        if self.max_rows is not None and n + m > self.max_rows:
            keep = max(self.max_rows - m, 0)
            buf[:keep] = buf[n - keep : n].copy()
            rows = rows[-self.max_rows :]
            n, m = keep, rows.shape[0]
        if n + m > buf.shape[0]:
            cap = max(2 * buf.shape[0], n + m)
            new = np.zeros((cap, self.n_cols), self.dtype)
            new[:n] = buf[:n]
            self._buf[act] = buf = new
        buf[n : n + m] = rows
        self._n[act] = n + m

    def rows(self, action: int) -> np.ndarray:
        """The filled rows of one action, ``[n, 2 * n_vars + 1]`` (a view)."""
        return self._buf[action][: self._n[action]]

    def counts(self) -> np.ndarray:
        """Rows stored per action, ``[n_actions]``."""
        return self._n.copy()

    def __len__(self) -> int:
        return int(self._n.sum())

    def state_dict(self) -> dict:
        """Compact, checkpointable copy (filled rows only)."""
        return {
            "rows": [torch.from_numpy(self.rows(a).copy()) for a in range(self.n_actions)],
            "total_added": self.total_added,
        }

    def load_state_dict(self, sd: dict) -> None:
        rows = sd["rows"]
        if len(rows) != self.n_actions:
            raise ValueError(f"state dict holds {len(rows)} actions, expected {self.n_actions}")
        for a, r in enumerate(rows):
            r = _to_numpy(r).astype(self.dtype).reshape(-1, self.n_cols)
            self._buf[a] = np.zeros((max(len(r), 1), self.n_cols), self.dtype)
            self._buf[a][: len(r)] = r
            self._n[a] = len(r)
        self.total_added = int(sd.get("total_added", len(self)))
