"""The nine causal state variables of the thesis (sec. 4.2-4.3), in one place.

Every part of the library that speaks about the discretised scene -- the
:class:`~torchrl_causal.transforms.Discretize` transform, the causal learner,
the expert CBNs, the gate -- reads names, cardinalities and category labels
from a :class:`VariableSchema`. The default one, :data:`DEFAULT_SCHEMA`, is the
thesis's:

==================== ===== ==========================================
variable             card. categories (code order)
==================== ===== ==========================================
depth_center         2     close (<= 0.5 m), far
depth_top_left       2     close, far
depth_top_right      2     close, far
depth_bottom_left    2     close, far
depth_bottom_right   2     close, far
goal_in_sight        2     no, yes
goal_distance        3     close (<= 0.5 m), far, not_visible
goal_angle           3     good (-15..15 deg), far_left (> 15), far_right (< -15)
altitude             3     close_ground (< 0.5 m), good, far_ground (> 1.5 m)
==================== ===== ==========================================

While the goal is not in sight, ``goal_distance`` takes its third category
``not_visible`` (there is no distance to measure) and ``goal_angle`` takes
``good`` (the continuous angle is reported as 0 deg): the angle is only
meaningful together with ``goal_in_sight``, which every expert CBN gives it as
a co-parent of the reward. There are ``2**6 * 3**3 = 1728`` joint states with
this schema; code never hard-codes it and reads :attr:`VariableSchema.n_states`.

The dynamic Bayesian networks of the causal package use the node names
``"<var>_t"``, ``"<var>_t1"`` and ``"reward"`` (see :meth:`VariableSchema.node_names`).

Example:
    >>> from torchrl_causal.schema import DEFAULT_SCHEMA
    >>> DEFAULT_SCHEMA.names[0], DEFAULT_SCHEMA.cardinalities[-1]
    ('depth_center', 3)
    >>> DEFAULT_SCHEMA.n_states
    1728
    >>> DEFAULT_SCHEMA.state_index([[0, 0, 0, 0, 0, 1, 1, 2, 1]]).tolist()
    [43]
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

__all__ = [
    "Variable",
    "VariableSchema",
    "DEFAULT_SCHEMA",
    "ACTION_NAMES",
    "REWARD_NODE",
    "REWARD_LABELS",
]

#: Public, ordered action names; index ``i`` is action ``i`` of every env and gate.
ACTION_NAMES: tuple[str, ...] = (
    "forward",
    "backward",
    "left",
    "right",
    "ascend",
    "descend",
    "turn_left",
    "turn_right",
)

#: Name of the reward node in every per-action DBN.
REWARD_NODE = "reward"
#: Category labels of the reward node: code 0 = negative (env reward < 0), 1 = positive (>= 0).
REWARD_LABELS: tuple[str, ...] = ("negative", "positive")

T_SUFFIX = "_t"
T1_SUFFIX = "_t1"


@dataclass(frozen=True)
class Variable:
    """One discrete state variable.

    Args:
        name: identifier, used for keys and DBN node names.
        labels: category labels; code ``i`` means ``labels[i]``.
        description: one line for docs and plots.

    Example:
        >>> v = Variable("altitude", ("close_ground", "good", "far_ground"))
        >>> v.cardinality
        3
    """

    name: str
    labels: tuple[str, ...]
    description: str = ""

    def __post_init__(self):
        if not self.name.isidentifier():
            raise ValueError(f"Variable name must be an identifier, got {self.name!r}")
        if len(self.labels) < 2:
            raise ValueError(
                f"Variable {self.name!r} needs at least 2 labels, got {self.labels!r}"
            )

    @property
    def cardinality(self) -> int:
        return len(self.labels)


@dataclass(frozen=True)
class VariableSchema:
    """An ordered set of discrete variables: the layout of ``causal_state``.

    Args:
        variables: the variables, in the order of the last dim of ``causal_state``.

    Example:
        >>> s = VariableSchema((Variable("a", ("lo", "hi")), Variable("b", ("x", "y", "z"))))
        >>> s.n_states, s.cardinalities
        (6, (2, 3))
        >>> s.node_names()
        ['a_t', 'b_t', 'a_t1', 'b_t1', 'reward']
    """

    variables: tuple[Variable, ...]
    _index: dict = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        names = [v.name for v in self.variables]
        if len(set(names)) != len(names):
            raise ValueError(f"Duplicate variable names in schema: {names}")
        if not names:
            raise ValueError("A VariableSchema needs at least one variable")
        object.__setattr__(self, "_index", {n: i for i, n in enumerate(names)})

    def __len__(self) -> int:
        return len(self.variables)

    def __iter__(self):
        return iter(self.variables)

    def __getitem__(self, name: str) -> Variable:
        return self.variables[self.index(name)]

    def index(self, name: str) -> int:
        """Position of variable ``name`` in ``causal_state``."""
        try:
            return self._index[name]
        except KeyError:
            raise KeyError(
                f"Unknown variable {name!r}; schema has {list(self._index)}"
            ) from None

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.variables)

    @property
    def cardinalities(self) -> tuple[int, ...]:
        return tuple(v.cardinality for v in self.variables)

    @property
    def n_states(self) -> int:
        """Number of joint states at one time slice."""
        return int(np.prod(self.cardinalities))

    def node_names(self) -> list[str]:
        """DBN node names: the t slice, the t+1 slice, then ``"reward"``."""
        return (
            [n + T_SUFFIX for n in self.names]
            + [n + T1_SUFFIX for n in self.names]
            + [REWARD_NODE]
        )

    def node_cardinalities(self) -> dict[str, int]:
        """Cardinality of every DBN node."""
        out = {n + T_SUFFIX: c for n, c in zip(self.names, self.cardinalities)}
        out.update({n + T1_SUFFIX: c for n, c in zip(self.names, self.cardinalities)})
        out[REWARD_NODE] = len(REWARD_LABELS)
        return out

    def node_labels(self) -> dict[str, list[str]]:
        """Category labels of every DBN node (used for pgmpy ``state_names``)."""
        out = {}
        for v in self.variables:
            out[v.name + T_SUFFIX] = list(v.labels)
            out[v.name + T1_SUFFIX] = list(v.labels)
        out[REWARD_NODE] = list(REWARD_LABELS)
        return out

    def strides(self) -> tuple[int, ...]:
        """Mixed-radix strides: ``index = sum(code[i] * strides[i])`` (C order)."""
        strides, acc = [], 1
        for c in reversed(self.cardinalities):
            strides.append(acc)
            acc *= c
        return tuple(reversed(strides))

    def state_index(self, codes) -> torch.Tensor:
        """Flat joint-state index of integer codes ``[..., n_vars]`` (C order).

        Works on tensors, arrays and nested lists; returns an ``int64`` tensor
        of shape ``[...]``.
        """
        codes = torch.as_tensor(codes)
        if codes.shape[-1] != len(self):
            raise ValueError(
                f"Expected codes with last dim {len(self)}, got shape {tuple(codes.shape)}"
            )
        strides = torch.tensor(self.strides(), dtype=torch.int64, device=codes.device)
        return (codes.long() * strides).sum(-1)

    def all_states(self) -> np.ndarray:
        """Every joint state as integer codes, shape ``[n_states, n_vars]``, in index order."""
        grids = np.meshgrid(*[np.arange(c) for c in self.cardinalities], indexing="ij")
        return np.stack([g.reshape(-1) for g in grids], axis=-1).astype(np.int64)


DEFAULT_SCHEMA = VariableSchema(
    (
        Variable("depth_center", ("close", "far"), "min depth, centre section"),
        Variable("depth_top_left", ("close", "far"), "min depth, top-left section"),
        Variable("depth_top_right", ("close", "far"), "min depth, top-right section"),
        Variable("depth_bottom_left", ("close", "far"), "min depth, bottom-left section"),
        Variable("depth_bottom_right", ("close", "far"), "min depth, bottom-right section"),
        Variable("goal_in_sight", ("no", "yes"), "goal detected with confidence > 0.7"),
        Variable(
            "goal_distance", ("close", "far", "not_visible"), "depth inside the goal's box"
        ),
        Variable("goal_angle", ("good", "far_left", "far_right"), "bearing of the goal's box"),
        Variable("altitude", ("close_ground", "good", "far_ground"), "barometric altitude"),
    )
)
