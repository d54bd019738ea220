"""The replay-buffer hook that feeds causal learning (thesis Alg. 1 lines 7-9, Alg. 2).

:meth:`torchrl.data.ReplayBuffer.extend` (and ``add``) pass every batch of
transitions through the buffer transform's inverse before storing it, so a
buffer transform sees exactly what is stored -- the natural place to append
each transition to the causal learner's data and to relearn every ``k``
frames. The hook leaves the data unchanged.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
    >>> from torchrl_causal.causal import CausalLearner
    >>> from torchrl_causal.data import CausalLearningHook
    >>> from torchrl_causal.modules import CBNGate
    >>> gate = CBNGate("v2")
    >>> hook = CausalLearningHook(CausalLearner(), k=100, gates=[gate])
    >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), batch_size=32)
    >>> rb.append_transform(hook)  # doctest: +ELLIPSIS
    TensorDictReplayBuffer(...)
    >>> g = torch.Generator().manual_seed(0)
    >>> s = torch.randint(0, 2, (100, 9), generator=g)
    >>> td = TensorDict(
    ...     causal_state=s, action=torch.randint(0, 8, (100,), generator=g),
    ...     next=TensorDict(causal_state=s.roll(1, 0), reward=torch.randn(100, 1, generator=g),
    ...                     batch_size=[100]),
    ...     batch_size=[100])
    >>> _ = rb.extend(td)
    >>> hook.frames, hook.learner.n_relearns, gate.tables is hook.learner.tables
    (100, 1, True)
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import wait as futures_wait
from typing import Iterable

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.envs.transforms import Transform

__all__ = ["CausalLearningHook"]


class CausalLearningHook(Transform):
    """Replay-buffer transform that appends stored transitions to a causal learner.

    On every write to the buffer (:meth:`~torchrl.data.ReplayBuffer.extend`,
    ``add``, ``__setitem__``) the hook reads, for every stored transition,
    ``causal_state`` (t), ``action``, ``("next", "causal_state")`` (t+1) and
    ``("next", "reward")``, and calls ``learner.add(state_t, action, state_t1,
    reward)``. Each time the number of stored frames crosses a multiple of
    ``k`` it calls ``learner.relearn()`` (warm-started from the previous models
    by the learner) and pushes the new
    :class:`~torchrl_causal.causal.tables.RewardTables` to every registered
    gate via ``gate.set_tables``. At most one relearn is triggered per write:
    with writes larger than ``k`` frames, relearns happen once per write. The
    data passes through unchanged; sampling is not affected.

    With ``background=True`` the relearn runs in a worker thread and the write
    returns at once: transitions stored meanwhile are queued and added to the
    learner when the relearn finishes; the worker swaps the new tables into the
    gates (one reference assignment, so a gate call sees either the old or the
    new tables, never a mix); a boundary crossed while a relearn is in flight
    starts another one as soon as it finishes. Errors raised in the worker are
    re-raised on the next write or :meth:`wait`. The relearn shares the GIL with
    collection, so the gain depends on how much of the learner's time is spent
    in numpy / torch kernels.

    Checkpointing goes through ``nn.Module``'s extra state, so
    :meth:`state_dict` / :meth:`load_state_dict` of the hook -- and of a
    replay buffer that holds it (``rb.state_dict()``) -- carry the frame
    counter and the learner's full state (data, models, tables). Saving waits
    for an in-flight relearn first. Loading pushes the restored tables to the
    gates.

    Args:
        learner: the :class:`~torchrl_causal.causal.CausalLearner` (or any object
            with its ``add`` / ``relearn`` / ``tables`` / ``state_dict`` /
            ``load_state_dict`` contract); ``None`` builds a default
            ``CausalLearner()``.
        k: relearn every ``k`` stored frames (thesis: 200).
        gates: gates (objects with ``set_tables``) to receive new tables.
        background: relearn in a worker thread (collection does not wait).

    Keyword Args:
        causal_state_key: discretised state at t (``"causal_state"``).
        action_key: the executed action (``"action"``), integer or one-hot.
        next_causal_state_key: state at t+1 (``("next", "causal_state")``).
        reward_key: the env reward (``("next", "reward")``); the learner turns it
            into the reward class (positive iff ``>= 0``).
        mask_key: optional boolean key marking valid transitions (a collector's
            ``("collector", "mask")`` with ``split_trajs=True``); used when present.
        first_relearn: stored frames before the first relearn (default ``k``);
            later relearns fall on multiples of ``k``. E.g. the end of a random
            warm-up that fits an expert CBN's CPTs before training.

    Example:
        >>> from torchrl_causal.causal import CausalLearner
        >>> hook = CausalLearningHook(CausalLearner(), k=200, background=True)
        >>> hook.frames, hook.k
        (0, 200)
        >>> hook.close()
    """

    def __init__(
        self,
        learner=None,
        k: int = 200,
        gates: Iterable = (),
        background: bool = False,
        *,
        causal_state_key: NestedKey = "causal_state",
        action_key: NestedKey = "action",
        next_causal_state_key: NestedKey = ("next", "causal_state"),
        reward_key: NestedKey = ("next", "reward"),
        mask_key: NestedKey | None = ("collector", "mask"),
        first_relearn: int | None = None,
    ):
        if isinstance(k, bool) or not isinstance(k, int) or k <= 0:
            raise ValueError(f"k must be a positive int, got {k!r}")
        if first_relearn is not None and (
            isinstance(first_relearn, bool) or not isinstance(first_relearn, int) or first_relearn <= 0
        ):
            raise ValueError(f"first_relearn must be None or a positive int, got {first_relearn!r}")
        if not isinstance(background, bool):
            raise ValueError(f"background must be a bool, got {background!r}")
        gates = list(gates)
        for g in gates:
            if not hasattr(g, "set_tables"):
                raise ValueError(f"gates must have a set_tables method, got {type(g).__name__}")
        super().__init__(in_keys=[], out_keys=[])
        if learner is None:
            from torchrl_causal.causal import CausalLearner

            learner = CausalLearner()
        for attr in ("add", "relearn", "state_dict", "load_state_dict"):
            if not callable(getattr(learner, attr, None)):
                raise ValueError(
                    f"learner must provide {attr}() (the CausalLearner contract), "
                    f"got {type(learner).__name__}"
                )
        # plain attributes: not nn.Modules, not part of the module tree
        self.__dict__["learner"] = learner
        self.__dict__["_gates"] = gates
        self.k = k
        self.background = background
        self.causal_state_key = causal_state_key
        self.action_key = action_key
        self.next_causal_state_key = next_causal_state_key
        self.reward_key = reward_key
        self.mask_key = mask_key
        self.frames = 0
        self._next_relearn = k if first_relearn is None else first_relearn
        self.relearn_seconds = 0.0
        self.add_seconds = 0.0
        self.last_relearn_seconds = 0.0
        self.__dict__["_executor"] = None
        self.__dict__["_future"] = None
        self.__dict__["_pending"] = []
        self.__dict__["_requested"] = False

    # ------------------------------------------------------------------ gates
    @property
    def gates(self) -> tuple:
        """The registered gates."""
        return tuple(self._gates)

    def register_gate(self, gate) -> None:
        """Register a gate; it receives the current tables at once if there are any."""
        if not hasattr(gate, "set_tables"):
            raise ValueError(f"gate must have a set_tables method, got {type(gate).__name__}")
        if gate not in self._gates:
            self._gates.append(gate)
        tables = getattr(self.learner, "tables", None)
        if tables is not None:
            gate.set_tables(tables)

    def _push(self, tables) -> None:
        for g in self._gates:
            g.set_tables(tables)

    # ------------------------------------------------------------------ stats
    @property
    def relearning(self) -> bool:
        """Whether a background relearn is in flight."""
        f = self._future
        return f is not None and not f.done()

    @property
    def stats(self) -> dict:
        """Counters: frames, relearns, seconds spent adding and relearning."""
        return {
            "frames": self.frames,
            "n_relearns": int(getattr(self.learner, "n_relearns", 0)),
            "add_seconds": self.add_seconds,
            "relearn_seconds": self.relearn_seconds,
            "last_relearn_seconds": self.last_relearn_seconds,
        }

    # ------------------------------------------------------------------ transform API
    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict

    forward = _call

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        batch = self._extract(tensordict)
        self._collect_finished()
        n = batch[1].shape[0]
        if n:
            if self.relearning:
                self._pending.append(batch)
            else:
                self._add(batch)
            self.frames += n
        if self.frames >= self._next_relearn:
            self._next_relearn = (self.frames // self.k + 1) * self.k
            self._trigger()
        return tensordict

    def _extract(self, td: TensorDictBase):
        keys = (self.causal_state_key, self.action_key, self.next_causal_state_key, self.reward_key)
        vals = []
        for key in keys:
            v = td.get(key, None)
            if v is None:
                raise KeyError(
                    f"CausalLearningHook: key {key!r} not found in the data written to the "
                    f"replay buffer (keys: {list(td.keys(True, True))})"
                )
            vals.append(v)
        s, a, s1, r = vals
        n_vars = s.shape[-1]
        s = s.reshape(-1, n_vars)
        s1 = s1.reshape(-1, n_vars)
        n = s.shape[0]
        if a.numel() != n:  # one-hot actions
            a = a.reshape(n, -1).long().argmax(-1)
        a = a.reshape(n).long()
        r = r.reshape(n).float()
        if self.mask_key is not None:
            mask = td.get(self.mask_key, None)
            if mask is not None and mask.numel() == n and not mask.all():
                mask = mask.reshape(n).bool()
                s, a, s1, r = s[mask], a[mask], s1[mask], r[mask]
        return (
            s.detach().long().cpu(),
            a.detach().cpu(),
            s1.detach().long().cpu(),
            r.detach().cpu(),
        )

    # ------------------------------------------------------------------ relearning
    def _relearn_now(self):
        t0 = time.perf_counter()
        tables = self.learner.relearn()
        dt = time.perf_counter() - t0
        self.last_relearn_seconds = dt
        self.relearn_seconds += dt
        if tables is None:
            tables = getattr(self.learner, "tables", None)
        self._push(tables)
        return tables

    def _trigger(self) -> None:
        if not self.background:
            self._relearn_now()
            return
        if self.relearning:
            self._requested = True
            return
        if self._executor is None:
            self.__dict__["_executor"] = ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="causal-relearn"
            )
        self.__dict__["_future"] = self._executor.submit(self._relearn_now)

    def _add(self, batch) -> None:
        t0 = time.perf_counter()
        self.learner.add(*batch)
        self.add_seconds += time.perf_counter() - t0

    def _flush_pending(self) -> None:
        pending, self.__dict__["_pending"] = self._pending, []
        if pending:
            self._add([torch.cat(parts) for parts in zip(*pending)])

    def _collect_finished(self) -> None:
        f = self._future
        if f is None or not f.done():
            return
        self.__dict__["_future"] = None
        self._flush_pending()
        f.result()  # re-raise a worker error here, in the collecting thread
        if self._requested:
            self.__dict__["_requested"] = False
            self._trigger()

    def wait(self) -> None:
        """Block until no relearn is in flight or requested, and queued data is added."""
        while self._future is not None:
            futures_wait([self._future])
            self._collect_finished()
        self._flush_pending()

    def relearn(self):
        """Relearn now (synchronously), push the tables to the gates and return them."""
        self.wait()
        return self._relearn_now()

    def close(self) -> None:
        """Wait for the background worker and shut it down."""
        try:
            self.wait()
        finally:
            ex = self._executor
            self.__dict__["_executor"] = None
            if ex is not None:
                ex.shutdown(wait=True)

    # ------------------------------------------------------------------ checkpointing
    def get_extra_state(self) -> dict:
        self.wait()
        return {
            "frames": self.frames,
            "next_relearn": self._next_relearn,
            "k": self.k,
            "learner": self.learner.state_dict(),
        }

    def set_extra_state(self, state: dict) -> None:
        self.wait()
        self.learner.load_state_dict(state["learner"])
        self.frames = int(state["frames"])
        self._next_relearn = int(state["next_relearn"])
        if int(state.get("k", self.k)) != self.k:
            # keep the configured k; realign the next boundary to it
            self._next_relearn = (self.frames // self.k + 1) * self.k
        tables = getattr(self.learner, "tables", None)
        if tables is not None:
            self._push(tables)

    def __getstate__(self):
        self.wait()
        state = super().__getstate__()  # Transform's: the container weakref is resolved
        state["_executor"] = None
        state["_future"] = None
        return state

    def extra_repr(self) -> str:
        return f"k={self.k}, background={self.background}, frames={self.frames}"
