"""Discretisation of the nine scene variables (thesis sec. 4.2-4.3).

The continuous values and their codes, per variable of
:data:`~torchrl_causal.schema.DEFAULT_SCHEMA` (thresholds are the fields of
:class:`Thresholds`; the defaults are the thesis's):

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
:class:`~torchrl_causal.perception.goal.GoalMeter`'s job.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, MultiCategorical, Unbounded
from torchrl.envs.transforms import Transform

from torchrl_causal.schema import DEFAULT_SCHEMA

__all__ = ["Thresholds", "Discretize"]


@dataclass(frozen=True)
class Thresholds:
    """Discretisation thresholds (thesis sec. 4.2 defaults).

    Args:
        depth_close: a section is ``close`` when its min depth is ``<=`` this (m).
        goal_close: the goal is ``close`` when its distance is ``<=`` this (m).
        angle_good: the angle is ``good`` when ``|angle| <=`` this (deg).
        altitude_low: ``close_ground`` below this altitude (m).
        altitude_high: ``far_ground`` above this altitude (m).

    Example:
        >>> Thresholds().angle_good, Thresholds(depth_close=0.8).depth_close
        (15.0, 0.8)
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


class Discretize(Transform):
    """Writes the nine variables, continuous and discretised.

    Reads the five section depths (``depth_sections`` ``[..., 5]``, from
    :class:`~torchrl_causal.transforms.DepthSections`), ``goal_in_sight``,
    ``goal_distance``, ``goal_angle`` (``[..., 1]``, from the env's goal
    measurement or :class:`~torchrl_causal.transforms.GoalFeatures`) and
    ``altitude`` (``[..., 1]``), and writes

    * ``causal_features``: ``float32 [..., 9]``, the continuous values in schema
      order (finite always);
    * ``causal_state``: ``int64 [..., 9]``, the codes, with a
      :class:`~torchrl.data.MultiCategorical` spec of the schema's cardinalities.

    See the module docs for the table of codes, the not-in-sight rule and
    input sanitising. On another env whose altitude (or any input) has another
    key, pass the key here or rename it with TorchRL's ``RenameTransform``.

    Args:
        thresholds: a :class:`Thresholds` (default: the thesis's).
        max_depth: sensor range in metres (clip for depths and goal distance).
        depth_key, in_sight_key, distance_key, angle_key, altitude_key: input keys.
        features_key, state_key: output keys.

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
    """

    def __init__(
        self,
        thresholds: Thresholds | None = None,
        *,
        max_depth: float = 10.0,
        depth_key="depth_sections",
        in_sight_key="goal_in_sight",
        distance_key="goal_distance",
        angle_key="goal_angle",
        altitude_key="altitude",
        features_key="causal_features",
        state_key="causal_state",
    ):
        if thresholds is None:
            thresholds = Thresholds()
        if not isinstance(thresholds, Thresholds):
            raise ValueError(f"thresholds must be a Thresholds instance, got {thresholds!r}")
        if not (math.isfinite(max_depth) and max_depth > 0):
            raise ValueError(f"max_depth must be a positive finite number, got {max_depth!r}")
        super().__init__(
            in_keys=[depth_key, in_sight_key, distance_key, angle_key, altitude_key],
            out_keys=[features_key, state_key],
        )
        self.thresholds = thresholds
        self.max_depth = float(max_depth)
        self.schema = DEFAULT_SCHEMA
        self._const: dict = {}

    def _constants(self, device):
        const = self._const.get(device)
        if const is None:
            th, md, big = self.thresholds, self.max_depth, 1e30
            inf = float("inf")
            # columns: [depth x5, in_sight, distance, angle, altitude]
            lo = [0.0] * 5 + [0.0, 0.0, -90.0, -big]
            hi = [md] * 5 + [1.0, md, 90.0, big]
            nan_fill = [md] * 5 + [0.0, md, 0.0, 0.0]
            keep_unseen = [True] * 5 + [False, False, False, True]
            # code = sum_k weight_k * (x > edge_k) + bias
            edges = [[th.depth_close, inf]] * 5 + [
                [0.5, inf],
                [th.goal_close, inf],
                [th.angle_good, -th.angle_good],
                [th.altitude_low, th.altitude_high],
            ]
            # ">= e" is "> nextafter(e, -inf)", taken in float32 (the features' dtype)
            strict = [[False, False]] * 7 + [[False, True], [True, False]]
            weights = [[1, 1]] * 7 + [[1, -2], [1, 1]]  # angle: (x > a) + 2 * (x < -a)
            bias_seen = [0] * 7 + [2, 0]
            bias_unseen = [0] * 6 + [2, 2, 0]  # distance -> not_visible
            f32 = dict(dtype=torch.float32, device=device)
            i64 = dict(dtype=torch.int64, device=device)
            const = self._const[device] = (
                torch.tensor(lo, **f32),
                torch.tensor(hi, **f32),
                torch.tensor(nan_fill, **f32),
                torch.tensor(keep_unseen, dtype=torch.bool, device=device),
                torch.where(
                    torch.tensor(strict, device=device),
                    torch.nextafter(torch.tensor(edges, **f32), torch.tensor(-inf, **f32)),
                    torch.tensor(edges, **f32),
                ),
                torch.tensor(weights, **i64),
                torch.tensor(bias_seen, **i64),
                torch.tensor(bias_unseen, **i64),
            )
        return const

    def discretize(self, depth, in_sight, distance, angle, altitude):
        """Tensors in (shapes ``[..., 5]`` and ``[..., 1]``) -> ``(features, codes)`` ``[..., 9]``."""
        batch = depth.shape[:-1]
        lo, hi, nan_fill, keep_unseen, edges, weights, bias_seen, bias_unseen = self._constants(
            depth.device
        )
        if in_sight.dtype != torch.bool:
            in_sight = in_sight > 0.5
        col = (*batch, 1)
        if in_sight.shape != col:
            in_sight = in_sight.reshape(col)
        cols = [depth, in_sight.to(torch.float32)]
        for v in (distance, angle, altitude):
            cols.append(v if v.shape == col else v.reshape(col))
        x = torch.cat(cols, -1)  # promotes to float32 (or float64 inputs' dtype)
        if x.dtype != torch.float32:
            x = x.to(torch.float32)
        x = torch.where(x == x, x, nan_fill).clamp(lo, hi)  # x != x only for NaN
        features = x * (in_sight | keep_unseen)
        codes = ((features.unsqueeze(-1) > edges) * weights).sum(-1) + torch.where(
            in_sight, bias_seen, bias_unseen
        )
        return features, codes

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        features, codes = self.discretize(*(next_tensordict.get(k) for k in self.in_keys))
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
