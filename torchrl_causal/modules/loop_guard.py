"""``LoopGuard``: a deterministic policy never repeats a two-move loop.

A greedy policy over features that do not change when it moves back and forth
(the goal memory, the map's clearance in a masked corner) can alternate two
opposite moves for ever: forward / backward, left / right, turn left / turn
right. The generalist's held-out timeouts were of this kind (docs/results.rst,
"The generalist, five seeds"). With the last four actions in the observation
(:class:`~torchrl_causal.transforms.ActionHistory`), ``A, inv(A), A, inv(A)``
brings the drone back to where it was, with the same history: taking ``A``
once more repeats a state already seen twice, and a deterministic policy in a
deterministic world then loops until the step limit.

:class:`LoopGuard` is placed after the actor (and the gate, if any). When the
chosen action would repeat such a loop, it takes the best *other* allowed
action by the Q-values; otherwise it passes the action through. It needs no
pose, only the action history, so it works on a real drone too.

:class:`RevisitGuard` breaks cycles of any length: it reads, from
:class:`~torchrl_causal.transforms.VisitMemory`, which actions were already
taken from the dead-reckoned pose the drone is at, and prefers an untried one.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from ..schema import ACTION_NAMES

__all__ = ["LoopGuard", "RevisitGuard", "INVERSE_ACTIONS"]

#: The move that undoes each action, in :data:`~torchrl_causal.schema.ACTION_NAMES` order.
INVERSE_ACTIONS: tuple[int, ...] = tuple(
    ACTION_NAMES.index(b) for b in ("backward", "forward", "right", "left", "descend", "ascend",
                                    "turn_right", "turn_left"))


def _check_int(name: str, value, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ValueError(f"{name} must be an int >= {low}, got {value!r}")


def _action_index(guard, tensordict: TensorDictBase) -> torch.Tensor:
    """The chosen action as an index (a guard cannot read a one-hot or float action)."""
    action = tensordict.get(guard.action_key)
    if action.is_floating_point() or action.shape[-1:] == (guard.n_actions,) and \
            action.dtype == torch.bool:
        raise ValueError(f"{type(guard).__name__} needs an action index, got {action.dtype} "
                         f"{tuple(action.shape)}")
    return action


class LoopGuard(TensorDictModuleBase):
    """Replaces an action that would repeat a two-move loop by the best other one.

    Reads ``action_history`` (``[..., length * n_actions]``, one-hot, most
    recent first, as :class:`~torchrl_causal.transforms.ActionHistory` writes
    it; ``length >= 4``), the chosen ``action`` (an index) and the Q-values
    (``action_value``). If the last four actions were ``A, inv(A), A, inv(A)``
    (oldest first) and the chosen action is ``A``, it writes the allowed action
    with the highest Q-value other than ``A`` (``action_mask``, if given,
    says which are allowed; if no other is allowed the action stays).
    Otherwise the action is unchanged. ``loop_guard_fired`` (bool) records
    where it intervened.

    Args:
        n_actions: size of the action space.
        inverse: for each action, the index of the action that undoes it
            (default :data:`INVERSE_ACTIONS`, the drone's eight moves).
        history_key, action_key, action_value_key: the keys read.
        action_mask_key: the allowed actions (bool ``[..., n_actions]``), or None.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> guard = LoopGuard()
        >>> hist = torch.zeros(4, 8)
        >>> hist[[0, 1, 2, 3], [1, 0, 1, 0]] = 1   # backward, forward, backward, forward
        >>> td = TensorDict({"action_history": hist.flatten(), "action": torch.tensor(0),
        ...                  "action_value": torch.tensor([5., 4., 1., 3., 0., 0., 0., 0.])}, [])
        >>> guard(td)["action"].item(), td["loop_guard_fired"].item()   # not forward again
        (1, True)
    """

    def __init__(self, n_actions: int = 8, inverse=INVERSE_ACTIONS, *,
                 history_key="action_history", action_key="action",
                 action_value_key="action_value", action_mask_key=None):
        super().__init__()
        _check_int("n_actions", n_actions, 2)
        inverse = tuple(int(i) for i in inverse)
        if len(inverse) != n_actions or any(not 0 <= i < n_actions for i in inverse) or \
                any(inverse[i] == i for i in range(n_actions)):
            raise ValueError(f"inverse must give, for each of the {n_actions} actions, another "
                             f"action index; got {inverse!r}")
        self.n_actions = n_actions
        self.register_buffer("inverse", torch.tensor(inverse, dtype=torch.long))
        self.history_key, self.action_key = history_key, action_key
        self.action_value_key, self.action_mask_key = action_value_key, action_mask_key
        self.in_keys = [history_key, action_key, action_value_key] + (
            [action_mask_key] if action_mask_key is not None else [])
        self.out_keys = [action_key, "loop_guard_fired"]

    def loops(self, history: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Where ``action`` would repeat ``A, inv(A), A, inv(A)`` (bool, the batch shape)."""
        n = self.n_actions
        if history.shape[-1] % n or history.shape[-1] // n < 4:
            raise ValueError(f"{self.history_key} must hold >= 4 one-hot blocks of "
                             f"{n} actions, got {history.shape[-1]} values")
        blocks = history.reshape(*history.shape[:-1], -1, n)[..., :4, :]
        taken = blocks.sum(-1) > 0.5                       # the step had an action
        h = blocks.argmax(-1)                              # [..., 4], most recent first
        inv = self.inverse.to(h.device)
        return (taken.all(-1) & (action == h[..., 1]) & (h[..., 0] == inv[h[..., 1]])
                & (h[..., 2] == h[..., 0]) & (h[..., 3] == h[..., 1]))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = _action_index(self, tensordict)
        q = tensordict.get(self.action_value_key)
        fire = self.loops(tensordict.get(self.history_key), action)
        allowed = torch.ones_like(q, dtype=torch.bool)
        if self.action_mask_key is not None:
            allowed = tensordict.get(self.action_mask_key).bool().expand_as(q).clone()
        allowed.scatter_(-1, action.unsqueeze(-1).long(), False)
        fire = fire & allowed.any(-1)
        low = -math.inf if q.is_floating_point() else torch.iinfo(q.dtype).min
        other = q.masked_fill(~allowed, low).argmax(-1)
        tensordict.set(self.action_key, torch.where(fire, other.to(action.dtype), action))
        tensordict.set("loop_guard_fired", fire)
        return tensordict


class RevisitGuard(TensorDictModuleBase):
    """Never repeats an action from a pose it was already taken from, while another is untried.

    :class:`LoopGuard` breaks two-move loops from the action history. A cycle
    of any length brings the drone back to a pose it has flown from before;
    :class:`~torchrl_causal.transforms.VisitMemory` counts the actions already
    taken from the pose the drone is at (``visit_counts``). Where the chosen
    action has been taken from here ``repeats`` times or more and an allowed
    action has been taken fewer times than it, :class:`RevisitGuard` takes the
    least-tried allowed action, the best of them by Q-value -- a depth-first
    search's rule (Tremaux's): every way out of a pose is tried before one is
    taken again. Otherwise the action is unchanged. ``revisit_guard_fired``
    (bool) records where it intervened.

    Args:
        n_actions: size of the action space.
        repeats: how many times an action may be taken from one pose before the
            guard prefers a less-tried one (1: never twice while another way is
            untried).
        counts_key, action_key, action_value_key: the keys read.
        action_mask_key: the allowed actions (bool ``[..., n_actions]``), or None.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> guard = RevisitGuard()
        >>> td = TensorDict({"visit_counts": torch.tensor([1., 0, 0, 0, 0, 0, 1, 0]),
        ...                  "action": torch.tensor(0),
        ...                  "action_value": torch.tensor([5., 4., 1., 3., 0., 0., 2., 0.])}, [])
        >>> guard(td)["action"].item(), td["revisit_guard_fired"].item()  # backward: untried
        (1, True)
    """

    def __init__(self, n_actions: int = 8, repeats: int = 1, *, counts_key="visit_counts",
                 action_key="action", action_value_key="action_value", action_mask_key=None):
        super().__init__()
        _check_int("n_actions", n_actions, 2)
        _check_int("RevisitGuard repeats", repeats, 1)
        self.n_actions, self.repeats = n_actions, repeats
        self.counts_key, self.action_key = counts_key, action_key
        self.action_value_key, self.action_mask_key = action_value_key, action_mask_key
        self.in_keys = [counts_key, action_key, action_value_key] + (
            [action_mask_key] if action_mask_key is not None else [])
        self.out_keys = [action_key, "revisit_guard_fired"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = _action_index(self, tensordict)
        q = tensordict.get(self.action_value_key).float()
        counts = tensordict.get(self.counts_key).float().expand_as(q)
        allowed = torch.ones_like(q, dtype=torch.bool)
        if self.action_mask_key is not None:
            allowed = tensordict.get(self.action_mask_key).bool().expand_as(q)
        inf = torch.tensor(math.inf, device=q.device)
        chosen = counts.gather(-1, action.unsqueeze(-1).long()).squeeze(-1)
        least = torch.where(allowed, counts, inf).amin(-1)
        fire = (chosen >= self.repeats) & (least < chosen)
        candidates = allowed & (counts == least.unsqueeze(-1))
        other = q.masked_fill(~candidates, -math.inf).argmax(-1)
        tensordict.set(self.action_key, torch.where(fire, other.to(action.dtype), action))
        tensordict.set("revisit_guard_fired", fire)
        return tensordict
