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

Each variable may also carry the rule that discretises it from a continuous
input (:class:`Variable`'s ``bins``, ``source``, ...): the thesis's thresholds
are :data:`DEFAULT_SCHEMA`'s rules (:func:`thesis_schema` builds them for other
thresholds), and :class:`~torchrl_causal.transforms.Discretize` applies the
rules of any schema.

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

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch

__all__ = [
    "Variable",
    "VariableSchema",
    "DEFAULT_SCHEMA",
    "DEFAULT_CLIP",
    "thesis_schema",
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


_ON_EDGE = ("below", "above")
#: Default clip of a binned value: only infinities are made finite.
DEFAULT_CLIP: tuple[float, float] = (-1e30, 1e30)


def _canonical_key(key, what: str, name: str):
    """A NestedKey as ``str`` or a tuple of at least two ``str``."""
    if isinstance(key, str) and key:
        return key
    if isinstance(key, tuple) and key and all(isinstance(k, str) and k for k in key):
        return key[0] if len(key) == 1 else key
    raise ValueError(f"Variable {name!r}: {what} must be a key (str or tuple of str), got {key!r}")


_F32_MAX = float(np.finfo(np.float32).max)


def _finite(value, what: str, name: str) -> float:
    """A number that is finite in float32, the precision values are compared in."""
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not math.isfinite(value)
        or abs(value) > _F32_MAX
    ):
        raise ValueError(
            f"Variable {name!r}: {what} must be a finite (float32) number, got {value!r}"
        )
    return float(value)


def _rule(**kw):
    """A keyword-only field of the discretisation rule (not compared, not hashed)."""
    return field(compare=False, kw_only=True, **kw)


@dataclass(frozen=True)
class Variable:
    """One discrete state variable, and optionally the rule that discretises it.

    Without ``bins`` the input already holds the code: a bool flag, an integer
    code, or a number that is rounded (halves down) to the nearest code; codes
    out of range are clipped, and the continuous feature is the code. With
    ``bins`` a continuous input is binned:

    1. read ``tensordict[source][..., index]`` as float32 (a NaN counts as
       ``nan_as``), clip it into ``clip``: that is the variable's continuous
       feature;
    2. its bin is the number of edges below it: an edge with ``on_edge="below"``
       counts when ``value > edge`` (a value on the edge stays in the bin
       below), one with ``"above"`` when ``value >= edge``;
    3. bin ``i`` has category code ``codes[i]`` (default: the categories in
       order);
    4. where the ``valid`` flag is false, the code is the ``missing`` category
       and the continuous feature is 0.

    Edges are compared in float32. The thesis's rules read: depth close iff
    ``<= 0.5`` is ``bins=(0.5,)`` (``on_edge="below"``); altitude close_ground
    ``< 0.5``, good ``0.5..1.5``, far_ground ``> 1.5`` is ``bins=(0.5, 1.5),
    on_edge=("above", "below")``; see :func:`thesis_schema` for all nine.

    The rule fields are keyword-only and take no part in equality or hashing:
    two schemas with the same names, labels and descriptions are equal whatever
    their rules (the causal components only ever see the codes).

    Args:
        name: identifier, used for keys and DBN node names.
        labels: category labels; code ``i`` means ``labels[i]`` (also
            :attr:`categories`).
        description: one line for docs and plots.
        bins: strictly increasing, finite bin edges; ``len(labels)`` must be
            ``len(bins) + 1`` (or ``len(bins) + 2`` when ``missing`` is a category
            that no bin produces). ``None``: the input is already a code.
        on_edge: ``"below"`` (default) or ``"above"``, for all edges or one per edge.
        codes: the category of each bin, lowest bin first, as codes or labels;
            each binned category exactly once.
        source: input key (default: ``name``).
        index: element of the source's last dim (default 0, a ``[..., 1]`` key).
        clip: ``(low, high)``, finite, the range of the continuous feature
            (default :data:`DEFAULT_CLIP`, which only makes infinities finite).
        nan_as: what a NaN input counts as (default 0.0).
        valid: key of a ``[..., 1]`` flag (a bool, or a number: true when ``> 0.5``;
            NaN is false); needs ``missing``.
        missing: the category where the ``valid`` flag is false.

    Raises:
        ValueError: naming the variable, for a bad name, labels or rule (e.g.
            categories that do not match the bins, unsorted bins, ``codes`` that
            are not a permutation).

    Example:
        >>> v = Variable("altitude", ("close_ground", "good", "far_ground"))
        >>> v.cardinality, v.categories[0], v.bins
        (3, 'close_ground', None)
        >>> v = Variable("angle", ("good", "far_left", "far_right"), bins=(-15, 15),
        ...              on_edge=("above", "below"), codes=("far_right", "good", "far_left"))
        >>> v.bin_codes, v.edge_sides
        ((2, 0, 1), ('above', 'below'))
        >>> Variable("altitude", ("low", "high"), bins=(0.5, 1.5))
        Traceback (most recent call last):
        ...
        ValueError: Variable 'altitude': 2 categories ('low', 'high') do not match bins (0.5, 1.5), which make 3 bins; need 3 categories, or 4 with a `missing` category that no bin produces
    """

    name: str
    labels: tuple[str, ...]
    description: str = ""
    bins: tuple[float, ...] | None = _rule(default=None)
    on_edge: str | tuple[str, ...] | None = _rule(default=None)
    codes: tuple[int | str, ...] | None = _rule(default=None)
    source: str | tuple[str, ...] | None = _rule(default=None)
    index: int = _rule(default=0)
    clip: tuple[float, float] | None = _rule(default=None)
    nan_as: float = _rule(default=0.0)
    valid: str | tuple[str, ...] | None = _rule(default=None)
    missing: str | None = _rule(default=None)

    def __post_init__(self):
        name = self.name
        if not isinstance(name, str) or not name.isidentifier():
            raise ValueError(f"Variable name must be an identifier, got {name!r}")
        labels = tuple(self.labels)
        if len(labels) < 2:
            raise ValueError(f"Variable {name!r} needs at least 2 labels, got {self.labels!r}")
        if len(set(labels)) != len(labels):
            raise ValueError(f"Variable {name!r} has duplicate labels {labels!r}")
        set_ = lambda attr, value: object.__setattr__(self, attr, value)  # noqa: E731
        set_("labels", labels)
        if self.source is not None:
            set_("source", _canonical_key(self.source, "source", name))
        if isinstance(self.index, bool) or not isinstance(self.index, int) or self.index < 0:
            raise ValueError(f"Variable {name!r}: index must be an int >= 0, got {self.index!r}")
        set_("nan_as", _finite(self.nan_as, "nan_as", name))
        if (self.valid is None) != (self.missing is None):
            raise ValueError(
                f"Variable {name!r}: valid and missing go together, got "
                f"valid={self.valid!r}, missing={self.missing!r}"
            )
        if self.valid is not None:
            set_("valid", _canonical_key(self.valid, "valid", name))
            if self.missing not in labels:
                raise ValueError(
                    f"Variable {name!r}: missing={self.missing!r} is not one of its "
                    f"categories {labels!r}"
                )
        if self.bins is None:
            for attr in ("on_edge", "codes", "clip"):
                if getattr(self, attr) is not None:
                    raise ValueError(
                        f"Variable {name!r}: {attr}={getattr(self, attr)!r} needs bins "
                        "(without bins the input is already a code)"
                    )
            return
        self._check_bins(set_)

    def _check_bins(self, set_):
        name, labels = self.name, self.labels
        try:
            bins = tuple(self.bins)
        except TypeError:
            raise ValueError(f"Variable {name!r}: bins must be a tuple of numbers, got {self.bins!r}") from None
        if not bins:
            raise ValueError(f"Variable {name!r}: bins must hold at least one edge, got {self.bins!r}")
        bins = tuple(_finite(b, f"every bin edge (bins={self.bins!r})", name) for b in bins)
        if any(a >= b for a, b in zip(bins, bins[1:])):
            raise ValueError(f"Variable {name!r}: bins {bins!r} must be strictly increasing")
        as_f32 = [np.float32(b) for b in bins]
        if any(a >= b for a, b in zip(as_f32, as_f32[1:])):
            raise ValueError(
                f"Variable {name!r}: bins {bins!r} must be strictly increasing in float32, "
                "the precision values are compared in"
            )
        set_("bins", bins)
        n_bins = len(bins) + 1
        if len(labels) == n_bins:
            binned = tuple(range(n_bins))
        elif self.missing is not None and len(labels) == n_bins + 1:
            binned = tuple(i for i, c in enumerate(labels) if c != self.missing)
        else:
            raise ValueError(
                f"Variable {name!r}: {len(labels)} categories {labels!r} do not match bins "
                f"{bins!r}, which make {n_bins} bins; need {n_bins} categories, or "
                f"{n_bins + 1} with a `missing` category that no bin produces"
            )
        on_edge = "below" if self.on_edge is None else self.on_edge
        if isinstance(on_edge, str):
            on_edge = (on_edge,) * len(bins)
        on_edge = tuple(on_edge) if isinstance(on_edge, (tuple, list)) else ()
        if len(on_edge) != len(bins) or any(e not in _ON_EDGE for e in on_edge):
            raise ValueError(
                f"Variable {name!r}: on_edge must be 'below' or 'above', or one of them per "
                f"edge of bins {bins!r}, got {self.on_edge!r}"
            )
        set_("_edge_sides", on_edge)
        if self.codes is None:
            codes = binned
        else:
            codes = tuple(
                labels.index(c) if isinstance(c, str) and c in labels else c
                for c in (self.codes if isinstance(self.codes, (tuple, list)) else (None,))
            )
            ok = all(isinstance(c, int) and not isinstance(c, bool) for c in codes)
            if not ok or len(codes) != n_bins or sorted(codes) != list(binned):
                raise ValueError(
                    f"Variable {name!r}: codes {self.codes!r} must give each of the {n_bins} "
                    f"bins of {bins!r} one of the categories "
                    f"{tuple(labels[i] for i in binned)!r} (codes {binned!r}), each exactly once"
                )
        set_("_bin_codes", codes)
        if not isinstance(self.on_edge, (str, type(None))):
            set_("on_edge", tuple(self.on_edge))
        if self.codes is not None:
            set_("codes", tuple(self.codes))
        if self.clip is not None:
            clip = tuple(self.clip) if isinstance(self.clip, (tuple, list)) else (self.clip,)
            if len(clip) != 2:
                raise ValueError(f"Variable {name!r}: clip must be (low, high), got {self.clip!r}")
            clip = tuple(_finite(c, f"clip {self.clip!r}", name) for c in clip)
            if clip[0] > clip[1]:
                raise ValueError(f"Variable {name!r}: clip {clip!r} needs low <= high")
            set_("clip", clip)

    @property
    def cardinality(self) -> int:
        return len(self.labels)

    @property
    def categories(self) -> tuple[str, ...]:
        """The category labels, in code order (same as :attr:`labels`)."""
        return self.labels

    @property
    def bin_codes(self) -> tuple[int, ...] | None:
        """The category code of each bin, lowest bin first (``codes`` resolved; None without bins)."""
        return getattr(self, "_bin_codes", None)

    @property
    def edge_sides(self) -> tuple[str, ...] | None:
        """``on_edge`` for each edge (``"below"`` / ``"above"``; None without bins)."""
        return getattr(self, "_edge_sides", None)

    @property
    def source_key(self):
        """The input key the value is read from: ``source``, else ``name``."""
        return self.name if self.source is None else self.source


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
        object.__setattr__(self, "variables", tuple(self.variables))
        for v in self.variables:
            if not isinstance(v, Variable):
                raise ValueError(f"A VariableSchema holds Variable instances, got {v!r}")
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

    def replace(self, name: str, **changes) -> "VariableSchema":
        """A copy with variable ``name`` changed (``dataclasses.replace`` of it).

        Example:
            >>> s = DEFAULT_SCHEMA.replace("altitude", bins=(0.3, 2.0))
            >>> s["altitude"].bins, DEFAULT_SCHEMA["altitude"].bins
            ((0.3, 2.0), (0.5, 1.5))
        """
        i = self.index(name)
        variables = list(self.variables)
        variables[i] = dataclasses.replace(variables[i], **changes)
        return VariableSchema(tuple(variables))

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


def thesis_schema(
    *,
    depth_close: float = 0.5,
    goal_close: float = 0.5,
    angle_good: float = 15.0,
    altitude_low: float = 0.5,
    altitude_high: float = 1.5,
    max_depth: float = 10.0,
) -> VariableSchema:
    """The thesis's nine variables with their discretisation rules (sec. 4.2).

    :data:`DEFAULT_SCHEMA` is ``thesis_schema()``; other thresholds give a
    schema equal to it (same variables and labels) with other bins. The inputs
    are those of :class:`~torchrl_causal.transforms.Discretize`:
    ``depth_sections`` ``[..., 5]`` and ``goal_in_sight`` / ``goal_distance`` /
    ``goal_angle`` / ``altitude`` ``[..., 1]``.

    ==================== ============================================================
    variable             rule
    ==================== ============================================================
    depth_* (5)          ``depth_sections[..., k]``, ``bins=(depth_close,)``,
                         ``clip=(0, max_depth)``, ``nan_as=max_depth``
    goal_in_sight        the flag itself (no bins)
    goal_distance        ``bins=(goal_close,)``, ``clip=(0, max_depth)``,
                         ``nan_as=max_depth``; ``not_visible`` where not in sight
    goal_angle           ``bins=(-angle_good, angle_good)``, ``on_edge=("above",
                         "below")``, ``codes=("far_right", "good", "far_left")``,
                         ``clip=(-90, 90)``; ``good`` where not in sight
    altitude             ``bins=(altitude_low, altitude_high)``,
                         ``on_edge=("above", "below")``, NaN counts as 0 m
    ==================== ============================================================

    Args:
        depth_close, goal_close, angle_good, altitude_low, altitude_high: the
            thresholds (see :class:`~torchrl_causal.transforms.Thresholds`).
        max_depth: the sensor range (m): clip, and NaN value, of the depths and
            the goal distance.

    Example:
        >>> s = thesis_schema(angle_good=20.0)
        >>> s["goal_angle"].bins, s["altitude"].bins
        ((-20.0, 20.0), (0.5, 1.5))
        >>> s == DEFAULT_SCHEMA  # same variables, other bins
        True
    """
    md = max_depth
    depth = dict(source="depth_sections", bins=(depth_close,), clip=(0.0, md), nan_as=md)
    sections = ("center", "top_left", "top_right", "bottom_left", "bottom_right")
    where = ("centre", "top-left", "top-right", "bottom-left", "bottom-right")
    in_sight = dict(valid="goal_in_sight")
    return VariableSchema(
        tuple(
            Variable(f"depth_{s}", ("close", "far"), f"min depth, {w} section", index=k, **depth)
            for k, (s, w) in enumerate(zip(sections, where))
        )
        + (
            Variable("goal_in_sight", ("no", "yes"), "goal detected with confidence > 0.7"),
            Variable(
                "goal_distance",
                ("close", "far", "not_visible"),
                "depth inside the goal's box",
                bins=(goal_close,),
                clip=(0.0, md),
                nan_as=md,
                missing="not_visible",
                **in_sight,
            ),
            Variable(
                "goal_angle",
                ("good", "far_left", "far_right"),
                "bearing of the goal's box",
                bins=(-angle_good, angle_good),
                on_edge=("above", "below"),
                codes=("far_right", "good", "far_left"),
                clip=(-90.0, 90.0),
                missing="good",
                **in_sight,
            ),
            Variable(
                "altitude",
                ("close_ground", "good", "far_ground"),
                "barometric altitude",
                bins=(altitude_low, altitude_high),
                on_edge=("above", "below"),
            ),
        )
    )


#: The thesis's nine variables and rules: ``thesis_schema()``.
DEFAULT_SCHEMA = thesis_schema()
