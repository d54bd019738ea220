"""Discretisation of schema variables into ``causal_state`` (thesis sec. 4.2-4.3).

:class:`Discretize` applies the rules that the variables of a
:class:`~torchrl_causal.schema.VariableSchema` carry (bins, input key,
clipping, a validity flag; see :class:`~torchrl_causal.schema.Variable`). Its
default schema, :data:`~torchrl_causal.schema.DEFAULT_SCHEMA`, holds the
thesis's nine variables; their thresholds are the fields of :class:`Thresholds`
(the defaults are the thesis's):

===================== ================================ ===========================================
variable              continuous value                 code
===================== ================================ ===========================================
depth_* (5 sections)  section minimum, m               0 close (``<= depth_close``), 1 far
goal_in_sight         0.0 / 1.0                        0 no, 1 yes
goal_distance         m; 0.0 when not in sight         0 close (``<= goal_close``), 1 far,
                                                       2 not_visible (goal not in sight)
goal_angle            deg, positive left; 0.0 when     0 good (``|angle| <= angle_good``),
                      not in sight                     1 far_left (``> angle_good``),
                                                       2 far_right (``< -angle_good``)
altitude              m                                0 close_ground (``< altitude_low``),
                                                       1 good, 2 far_ground (``> altitude_high``)
===================== ================================ ===========================================

Not in sight: the goal distance takes ``not_visible`` (there is nothing to
measure) and the angle takes ``good`` with a continuous 0 deg, so an unseen goal
never looks like a goal "far to the left/right".

Sanitising (inputs from any source never produce NaN/inf or an out-of-range
code): a NaN section depth counts as ``max_depth`` (nothing seen), depths are
clipped to ``[0, max_depth]`` (``+inf`` -> ``max_depth``, ``-inf`` -> 0); a NaN
goal distance counts as ``max_depth`` and a NaN angle as 0 deg; distance is
clipped to ``[0, max_depth]``, angle to ``[-90, 90]``; a NaN altitude counts as
0 m (the conservative "close to the ground"). ``goal_in_sight`` is taken as
given (a non-bool flag counts as in sight when ``> 0.5``); dropping goals
without a valid measurement is the
:class:`~torchrl_causal.perception.goal.GoalMeter`'s job. In a schema of your
own the same happens per variable: a NaN counts as its ``nan_as``, the value is
clipped into its ``clip`` (by default only infinities are made finite), and a
variable without bins takes its input as the code (clipped to the valid codes).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, MultiCategorical, Unbounded
from torchrl.envs.transforms import Transform

from torchrl_causal.schema import DEFAULT_CLIP, VariableSchema, thesis_schema

__all__ = ["Thresholds", "Discretize"]

_DEFAULT_MAX_DEPTH = 10.0
# keyword of Discretize -> the default schema's input key it replaces
_KEY_ARGS = {
    "depth_key": "depth_sections",
    "in_sight_key": "goal_in_sight",
    "distance_key": "goal_distance",
    "angle_key": "goal_angle",
    "altitude_key": "altitude",
}
@dataclass(frozen=True)
class Thresholds:
    """Discretisation thresholds of the default schema (thesis sec. 4.2 defaults).

    A convenience for :func:`~torchrl_causal.schema.thesis_schema`:
    ``Discretize(Thresholds(...))`` discretises with
    ``Thresholds(...).to_schema(max_depth)``, the thesis's nine variables with
    these thresholds.

    Args:
        depth_close: a section is ``close`` when its min depth is ``<=`` this (m).
        goal_close: the goal is ``close`` when its distance is ``<=`` this (m).
        angle_good: the angle is ``good`` when ``|angle| <=`` this (deg).
        altitude_low: ``close_ground`` below this altitude (m).
        altitude_high: ``far_ground`` above this altitude (m).

    Example:
        >>> Thresholds().angle_good, Thresholds(depth_close=0.8).depth_close
        (15.0, 0.8)
        >>> Thresholds(angle_good=20.0).to_schema()["goal_angle"].bins
        (-20.0, 20.0)
    """

    depth_close: float = 0.5
    goal_close: float = 0.5
    angle_good: float = 15.0
    altitude_low: float = 0.5
    altitude_high: float = 1.5

    def __post_init__(self):
        for name, value in asdict(self).items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"threshold {name} must be a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in ("depth_close", "goal_close", "angle_good"):
            if getattr(self, name) <= 0:
                raise ValueError(f"threshold {name} must be > 0, got {getattr(self, name)!r}")
        if not 0 <= self.altitude_low < self.altitude_high:
            raise ValueError(
                "thresholds need 0 <= altitude_low < altitude_high, got "
                f"altitude_low={self.altitude_low!r}, altitude_high={self.altitude_high!r}"
            )

    def to_schema(self, max_depth: float = _DEFAULT_MAX_DEPTH) -> VariableSchema:
        """The default schema with these thresholds (and sensor range ``max_depth``, m)."""
        return thesis_schema(**asdict(self), max_depth=max_depth)


class Discretize(Transform):
    """Writes the variables of a schema, continuous and discretised.

    Reads, for each variable of ``schema``, ``tensordict[source][..., index]``
    (and its ``valid`` flag) and writes

    * ``causal_features``: ``float32 [..., n_vars]``, the sanitised continuous
      values in schema order (finite always; the code itself for a variable
      without bins);
    * ``causal_state``: ``int64 [..., n_vars]``, the codes, with a
      :class:`~torchrl.data.MultiCategorical` spec of the schema's
      cardinalities; the labels are ``transform.schema[name].categories``.

    Every source is ``[..., d]``: the batch dims, then the value(s) (``d = 1``
    for a scalar such as ``altitude``). The default schema reads the five
    section depths (``depth_sections`` ``[..., 5]``, from
    :class:`~torchrl_causal.transforms.DepthSections`), ``goal_in_sight``,
    ``goal_distance``, ``goal_angle`` (``[..., 1]``, from the env's goal
    measurement or :class:`~torchrl_causal.transforms.GoalFeatures``) and
    ``altitude`` (``[..., 1]``). See the module docs for the table of codes,
    the not-in-sight rule and input sanitising.

    Args:
        thresholds: a :class:`Thresholds` for the default schema (default: the
            thesis's); not with ``schema``.
        schema: a :class:`~torchrl_causal.schema.VariableSchema` whose variables
            carry their rules (default:
            :data:`~torchrl_causal.schema.DEFAULT_SCHEMA`, built from
            ``thresholds`` and ``max_depth``).
        max_depth: sensor range in metres (clip for depths and goal distance)
            of the default schema (default 10.0); not with ``schema``.
        depth_key, in_sight_key, distance_key, angle_key, altitude_key: the keys
            to read instead of ``"depth_sections"``, ``"goal_in_sight"``,
            ``"goal_distance"``, ``"goal_angle"``, ``"altitude"`` (wherever the
            schema uses them as a ``source`` or ``valid`` key); other keys can be
            renamed with TorchRL's ``RenameTransform``.
        features_key, state_key: output keys.

    Raises:
        ValueError: bad options; at call time, a source whose shape does not
            fit the batch, naming the variable.
        KeyError: at call time, an input key that is missing, naming it and
            the variables that read it.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> td = TensorDict({
        ...     "depth_sections": torch.tensor([0.3, 5.0, 5.0, 0.5, 9.0]),
        ...     "goal_in_sight": torch.tensor([True]),
        ...     "goal_distance": torch.tensor([2.0]),
        ...     "goal_angle": torch.tensor([-20.0]),
        ...     "altitude": torch.tensor([1.0]),
        ... }, [])
        >>> Discretize()(td)["causal_state"].tolist()
        [0, 1, 1, 0, 1, 1, 1, 2, 1]
        >>> td["goal_in_sight"] = torch.tensor([False])
        >>> Discretize()(td)["causal_state"][5:8].tolist()
        [0, 2, 0]

        A schema of your own (here: a cart's position and a pole angle, both
        read from one ``observation`` vector):

        >>> from torchrl_causal.schema import Variable, VariableSchema
        >>> schema = VariableSchema((
        ...     Variable("cart", ("left", "centre", "right"), bins=(-1.0, 1.0),
        ...              source="observation", index=0),
        ...     Variable("pole", ("upright", "falling"), bins=(0.1,),
        ...              source="observation", index=2),
        ... ))
        >>> t = Discretize(schema=schema)
        >>> obs = TensorDict(observation=torch.tensor([[1.5, 0.0, 0.05, 0.0]]), batch_size=[1])
        >>> t(obs)["causal_state"].tolist(), t.schema["cart"].categories[2]
        ([[2, 0]], 'right')
    """

    def __init__(
        self,
        thresholds: Thresholds | None = None,
        *,
        schema: VariableSchema | None = None,
        max_depth: float | None = None,
        depth_key="depth_sections",
        in_sight_key="goal_in_sight",
        distance_key="goal_distance",
        angle_key="goal_angle",
        altitude_key="altitude",
        features_key="causal_features",
        state_key="causal_state",
    ):
        if thresholds is not None and not isinstance(thresholds, Thresholds):
            hint = " (pass a schema as schema=...)" if isinstance(thresholds, VariableSchema) else ""
            raise ValueError(f"thresholds must be a Thresholds instance, got {thresholds!r}{hint}")
        if max_depth is not None and not (
            isinstance(max_depth, (int, float)) and math.isfinite(max_depth) and max_depth > 0
        ):
            raise ValueError(f"max_depth must be a positive finite number, got {max_depth!r}")
        if schema is None:
            thresholds = Thresholds() if thresholds is None else thresholds
            max_depth = _DEFAULT_MAX_DEPTH if max_depth is None else float(max_depth)
            schema = thresholds.to_schema(max_depth)
        elif not isinstance(schema, VariableSchema):
            raise ValueError(f"schema must be a VariableSchema, got {schema!r}")
        elif thresholds is not None or max_depth is not None:
            raise ValueError(
                "thresholds and max_depth build the default schema; with schema=..., give "
                "its variables their bins and clip instead (see thesis_schema)"
            )
        rename = {}
        for arg, value in zip(
            _KEY_ARGS, (depth_key, in_sight_key, distance_key, angle_key, altitude_key)
        ):
            if value != _KEY_ARGS[arg]:
                rename[_KEY_ARGS[arg]] = value
        used = {v.source_key for v in schema} | {v.valid for v in schema}
        for arg, value in zip(
            _KEY_ARGS, (depth_key, in_sight_key, distance_key, angle_key, altitude_key)
        ):
            if value != _KEY_ARGS[arg] and _KEY_ARGS[arg] not in used:
                raise ValueError(
                    f"{arg}={value!r} replaces the key {_KEY_ARGS[arg]!r}, which no variable "
                    "of the schema reads (set the variable's source instead)"
                )
        in_keys, readers = [], {}
        sources, valids = [], []
        for v in schema:
            src = rename.get(v.source_key, v.source_key)
            valid = None if v.valid is None else rename.get(v.valid, v.valid)
            sources.append(src)
            valids.append(valid)
            for key in (src, valid):
                if key is not None and key not in in_keys:
                    in_keys.append(key)
                if key is not None:
                    readers.setdefault(key, []).append(v.name)
        super().__init__(in_keys=in_keys, out_keys=[features_key, state_key])
        self.schema = schema
        self.thresholds = thresholds
        self.max_depth = max_depth
        self._readers = readers
        # runs of variables reading consecutive elements of one source: (in_keys pos, start, stop, names)
        segments = []
        for v, src in zip(schema, sources):
            pos = in_keys.index(src)
            last = segments[-1] if segments else None
            if last is not None and last[0] == pos and last[2] == v.index:
                segments[-1] = (pos, last[1], v.index + 1, last[3] + (v.name,))
            else:
                segments.append((pos, v.index, v.index + 1, (v.name,)))
        self._segments = segments
        # per valid key: (in_keys pos, which variables it gates)
        self._valids = [
            (in_keys.index(key), tuple(k == key for k in valids))
            for key in dict.fromkeys(k for k in valids if k is not None)
        ]
        self._is_code = tuple(v.bins is None for v in schema)
        # a code variable's feature is its code: a float input may not be one (0.7 -> 1),
        # nor is a gated one's 0 where its flag is false (the missing code is)
        self._code_pos = tuple(
            {seg[0] for seg in segments for name in seg[3] if schema[name].bins is None}
        )
        self._code_gated = any(v.bins is None and v.valid is not None for v in schema)
        self._const: dict = {}

    def _constants(self, device):
        const = self._const.get(device)
        if const is None:
            inf = float("inf")
            lo, hi, nan_fill, edges, above, luts, missing = [], [], [], [], [], [], []
            for v in self.schema:
                nan_fill.append(v.nan_as)
                if v.bins is None:  # a code: count the edges k + 0.5 below it
                    lo.append(0.0)
                    hi.append(float(v.cardinality - 1))
                    edges.append([k + 0.5 for k in range(v.cardinality - 1)])
                    above.append([False] * (v.cardinality - 1))
                    luts.append(list(range(v.cardinality)))
                else:
                    clip = DEFAULT_CLIP if v.clip is None else v.clip
                    lo.append(clip[0])
                    hi.append(clip[1])
                    edges.append(list(v.bins))
                    above.append([e == "above" for e in v.edge_sides])
                    luts.append(list(v.bin_codes))
                missing.append(0 if v.missing is None else v.labels.index(v.missing))
            width = max(len(e) for e in edges)
            # Sorted edges: the comparisons "x > edge" that hold are the first `bin` ones, so
            # codes[bin] = codes[0] + sum_k (codes[k+1] - codes[k]) * (x > edge_k).
            weights = [[b - a for a, b in zip(lut, lut[1:])] for lut in luts]
            unit = all(w == 1 for ws in weights for w in ws)
            # pad with +inf: values are finite after clipping, so "> inf" never counts
            edges = [e + [inf] * (width - len(e)) for e in edges]
            above = [a + [False] * (width - len(a)) for a in above]
            weights = [w + [0] * (width - len(w)) for w in weights]
            f32 = dict(dtype=torch.float32, device=device)
            i64 = dict(dtype=torch.int64, device=device)
            edges = torch.tensor(edges, **f32)
            # "x >= e" is "x > nextafter(e, -inf)", taken in float32 (the features' dtype)
            edges = torch.where(
                torch.tensor(above, device=device),
                torch.nextafter(edges, torch.tensor(-inf, **f32)),
                edges,
            )
            bias = torch.tensor([lut[0] for lut in luts], **i64)
            weights = torch.tensor(weights, **i64)
            # where a flag is false the features are 0, which makes a known sum of weights
            at_zero = ((torch.zeros(len(luts), 1, **f32) > edges) * weights).sum(-1)
            const = self._const[device] = (
                torch.tensor(lo, **f32),
                torch.tensor(hi, **f32),
                torch.tensor(nan_fill, **f32),
                edges,
                None if unit else weights,
                None if not bias.any() else bias,
                bias,
                torch.tensor(missing, **i64) - at_zero,
                [torch.tensor([not u for u in uses], dtype=torch.bool, device=device)
                 for _, uses in self._valids],
                torch.tensor(self._is_code, dtype=torch.bool, device=device),
            )
        return const

    @staticmethod
    def _fit(t, batch, start, stop, what):
        """``t[..., start:stop]`` of a ``[*batch, d]`` source (or a ``[*batch]`` one, one column)."""
        shape = t.shape
        if shape and shape[:-1] == batch and stop <= shape[-1]:
            return t if (start == 0 and stop == shape[-1]) else t[..., start:stop]
        if stop - start == 1 and start == 0 and t.numel() == batch.numel():
            return t.reshape(*batch, 1)
        what = what if isinstance(what, str) else f"variable(s) {what}"
        raise ValueError(
            f"Discretize: {what} needs a source of shape [*batch, >= {stop}] with batch "
            f"{list(batch)} (from the first variable's source), got shape {list(shape)}"
        )

    def discretize(self, *inputs):
        """The input tensors, in ``in_keys`` order -> ``(features, codes)`` ``[..., n_vars]``."""
        if len(inputs) != len(self.in_keys):
            raise ValueError(
                f"discretize expects {len(self.in_keys)} tensors for {self.in_keys}, got {len(inputs)}"
            )
        lo, hi, nan_fill, edges, weights, bias, bias_ok, bias_not_ok, ungated, is_code = (
            self._constants(inputs[0].device)
        )
        fit, f32 = self._fit, torch.float32
        first = inputs[self._segments[0][0]]
        batch = first.shape[:-1] if first.ndim else first.shape
        cols = []
        for pos, start, stop, names in self._segments:
            t = fit(inputs[pos], batch, start, stop, names)
            cols.append(t if t.dtype == f32 else t.to(f32))
        x = cols[0] if len(cols) == 1 else torch.cat(cols, -1)
        x = torch.where(x == x, x, nan_fill).clamp(lo, hi)  # x != x only for NaN
        ok = None
        for (pos, uses), not_uses in zip(self._valids, ungated):
            flag = inputs[pos]
            if flag.dtype != torch.bool:
                flag = flag > 0.5  # NaN is False
            term = fit(flag, batch, 0, 1, f"the valid flag {self.in_keys[pos]!r}") | not_uses
            ok = term if ok is None else ok & term
        features = x if ok is None else x * ok
        above = features.unsqueeze(-1) > edges
        codes = (above if weights is None else above * weights).sum(-1)
        if ok is not None:
            codes = codes + torch.where(ok, bias_ok, bias_not_ok)
        elif bias is not None:
            codes = codes + bias
        code_features = self._code_gated
        for pos in self._code_pos:
            code_features = code_features or inputs[pos].is_floating_point()
        if code_features:
            features = torch.where(is_code, codes.to(f32), features)
        return features, codes

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        inputs = [next_tensordict.get(k, None) for k in self.in_keys]
        if any(t is None for t in inputs):
            key = next(k for k, t in zip(self.in_keys, inputs) if t is None)
            keys = sorted(map(str, next_tensordict.keys(True, True)))
            raise KeyError(
                f"Discretize: the input has no key {key!r}, read by variable(s) "
                f"{self._readers[key]} of the schema; it has {keys}"
            )
        features, codes = self.discretize(*inputs)
        next_tensordict.set(self.out_keys[0], features)
        next_tensordict.set(self.out_keys[1], codes)
        return next_tensordict

    forward = _call

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase):
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        shape = (*observation_spec.shape, len(self.schema))
        device = observation_spec.device
        observation_spec[self.out_keys[0]] = Unbounded(
            shape=shape, dtype=torch.float32, device=device
        )
        observation_spec[self.out_keys[1]] = MultiCategorical(
            nvec=list(self.schema.cardinalities), shape=shape, dtype=torch.int64, device=device
        )
        return observation_spec
