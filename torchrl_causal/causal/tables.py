"""Compiled reward tables: the only thing the gate needs from a learned CBN.

After each relearn, P(reward | state at t) of every action's network is
evaluated once for every joint state at t and stored as a dense table; at
each step the gate indexes it in batch (no inference on the hot path).

Example:
    >>> import torch
    >>> from torchrl_causal.schema import DEFAULT_SCHEMA
    >>> from torchrl_causal.causal.tables import RewardTables
    >>> p = torch.full((8, DEFAULT_SCHEMA.n_states), 0.5)
    >>> known = torch.tensor([True] * 7 + [False])
    >>> tables = RewardTables(p, known, DEFAULT_SCHEMA)
    >>> p_pos, p_neg, known = tables.lookup(torch.zeros(4, 9, dtype=torch.long))
    >>> p_pos.shape, p_neg.shape, known.shape
    (torch.Size([4, 8]), torch.Size([4, 8]), torch.Size([4, 8]))
"""

from __future__ import annotations

import torch

from torchrl_causal.schema import DEFAULT_SCHEMA, Variable, VariableSchema

__all__ = ["RewardTables"]


class RewardTables:
    """P(reward = positive | state_t) per action, for every joint state at t.

    Args:
        p_pos: float tensor ``[n_actions, schema.n_states]``; row ``a`` is
            P(positive | s, a) indexed by :meth:`VariableSchema.state_index`.
        known: bool tensor ``[n_actions]``; False where the action's model is
            unknown (too little or degenerate data): the gate abstains there.
        schema: the variable schema the states are coded with.

    P(negative) is ``1 - p_pos`` (the reward node is binary).

    Example:
        >>> import torch
        >>> t = RewardTables(torch.rand(8, 1728), torch.ones(8, dtype=torch.bool))
        >>> t.n_actions
        8
    """

    def __init__(
        self,
        p_pos: torch.Tensor,
        known: torch.Tensor,
        schema: VariableSchema = DEFAULT_SCHEMA,
    ):
        p_pos = torch.as_tensor(p_pos, dtype=torch.float32)
        known = torch.as_tensor(known, dtype=torch.bool)
        if p_pos.ndim != 2 or p_pos.shape[1] != schema.n_states:
            raise ValueError(
                f"p_pos must have shape [n_actions, {schema.n_states}], got {tuple(p_pos.shape)}"
            )
        if known.shape != (p_pos.shape[0],):
            raise ValueError(
                f"known must have shape [{p_pos.shape[0]}], got {tuple(known.shape)}"
            )
        if p_pos.numel() and (p_pos.min() < 0 or p_pos.max() > 1 or p_pos.isnan().any()):
            raise ValueError("p_pos must hold probabilities in [0, 1]")
        self.p_pos = p_pos
        self.known = known
        self.schema = schema
        self._strides = torch.tensor(schema.strides(), dtype=torch.int64, device=p_pos.device)
        # state-major copies for the hot path: one gather gives [..., n_actions] directly
        self._pos_by_state = p_pos.T.contiguous()
        self._neg_by_state = (1.0 - p_pos).T.contiguous()

    @property
    def n_actions(self) -> int:
        return self.p_pos.shape[0]

    @property
    def p_neg(self) -> torch.Tensor:
        return 1.0 - self.p_pos

    def to(self, device) -> "RewardTables":
        return RewardTables(self.p_pos.to(device), self.known.to(device), self.schema)

    def lookup(self, causal_state: torch.Tensor):
        """Batched lookup.

        Args:
            causal_state: int codes ``[..., n_vars]``.

        Returns:
            ``(p_pos [..., A], p_neg [..., A], known [..., A])``.
        """
        if causal_state.device != self._strides.device:
            return self.to(causal_state.device).lookup(causal_state)
        codes = causal_state if causal_state.dtype == torch.int64 else causal_state.long()
        if codes.device.type == "cpu":
            idx = codes.matmul(self._strides)  # one kernel for the mixed-radix index
        else:
            idx = (codes * self._strides).sum(-1)
        known = self.known.expand(*idx.shape, self.n_actions)
        return self._pos_by_state[idx], self._neg_by_state[idx], known

    def state_dict(self) -> dict:
        """The tables and their schema as plain tensors, strings and lists."""
        return {
            "p_pos": self.p_pos.cpu(),
            "known": self.known.cpu(),
            "schema": [[v.name, list(v.labels), v.description] for v in self.schema],
        }

    @classmethod
    def from_state_dict(cls, sd: dict, schema: VariableSchema | None = None) -> "RewardTables":
        """Rebuild tables from :meth:`state_dict`.

        Args:
            sd: the state dict.
            schema: the schema to code states with; ``None`` takes the one
                stored in ``sd`` (:data:`~torchrl_causal.schema.DEFAULT_SCHEMA`
                for a state dict written without one).

        Example:
            >>> import torch
            >>> from torchrl_causal.schema import Variable, VariableSchema
            >>> s = VariableSchema((Variable("a", ("lo", "hi")),))
            >>> t = RewardTables(torch.rand(4, 2), torch.ones(4, dtype=torch.bool), s)
            >>> RewardTables.from_state_dict(t.state_dict()).schema == s
            True
        """
        if schema is None:
            stored = sd.get("schema")
            schema = (
                DEFAULT_SCHEMA
                if stored is None
                else VariableSchema(tuple(Variable(n, tuple(labels), d) for n, labels, d in stored))
            )
        return cls(sd["p_pos"], sd["known"], schema)
