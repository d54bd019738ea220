"""Expert ("defined") causal Bayesian networks, one per action (thesis sec. 4.3).

Each action's network is a two-slice dynamic Bayesian network over the nine
scene variables at ``t`` and ``t+1`` plus the binary ``reward`` node (see
:mod:`torchrl_causal.schema`). Edges only go forward in time: ``t -> t+1``,
``t -> reward`` and ``t+1 -> reward``; there are no same-slice edges, so an
expert network lives in the same search space as the learned ones and the two
can be compared edge by edge (thesis Table 5.1).

The edges come from what each action physically changes (the thesis's figures
are images that are not available, only their edge totals in Table 5.1 are):

* every action shares a *goal core* of six edges: the goal's visibility,
  distance and bearing persist over one small move (three ``t -> t+1`` edges),
  and the reward sign is decided by whether the goal is seen, how far and at
  which angle (three ``t+1 -> reward`` edges: ``100 - d - |angle|`` when seen,
  ``-9`` when not, ``+1000`` on reaching it);
* translations (forward, backward, left, right) move obstacles through the five
  depth sections and can crash into what is close in the direction of motion
  (``depth_* (t) -> reward``); the camera cannot see behind, so backward has no
  crash edge;
* ascend / descend shift the image vertically and change the altitude band;
  descending close to the ground crashes;
* turns rotate in place: no crash edge, but the goal's bearing moves by one
  step (15 deg, the width of the ``good`` band), so bearing at ``t`` decides
  whether the goal stays in view.

The edge totals follow Table 5.1 (forward 14, backward 14, left 17, right 17,
ascend 14, descend 14, turn left 16, turn right 17). Every edge carries a
one-line rationale (:func:`expert_edges`), rendered in the user guide.

Example:
    >>> from torchrl_causal.causal.expert import expert_dags
    >>> dags = expert_dags()
    >>> {a: len(e) for a, e in dags.items()}["left"]
    17
    >>> ("goal_in_sight_t1", "reward") in dags["forward"]
    True
"""

from __future__ import annotations

from typing import NamedTuple

from torchrl_causal.schema import ACTION_NAMES, DEFAULT_SCHEMA, REWARD_NODE, T1_SUFFIX, T_SUFFIX, VariableSchema

__all__ = ["ExpertEdge", "expert_edges", "expert_dags", "TABLE_5_1_TOTALS"]

#: Edge totals of the defined CBNs in thesis Table 5.1.
TABLE_5_1_TOTALS: dict[str, int] = {
    "forward": 14,
    "backward": 14,
    "left": 17,
    "right": 17,
    "ascend": 14,
    "descend": 14,
    "turn_left": 16,
    "turn_right": 17,
}


class ExpertEdge(NamedTuple):
    """One edge of an expert CBN with the reason it is there.

    Example:
        >>> e = ExpertEdge("altitude_t", "altitude_t1", "climbing changes the altitude band")
        >>> e.source, e.target
        ('altitude_t', 'altitude_t1')
    """

    source: str
    target: str
    rationale: str


R = REWARD_NODE


def _t(v: str) -> str:
    return v + T_SUFFIX


def _t1(v: str) -> str:
    return v + T1_SUFFIX


def _core() -> list[tuple[str, str, str]]:
    return [
        (_t("goal_in_sight"), _t1("goal_in_sight"), "a goal in view stays in view over one small move"),
        (_t("goal_distance"), _t1("goal_distance"), "one step changes the goal distance by at most 0.25 m"),
        (_t("goal_angle"), _t1("goal_angle"), "the goal's bearing changes gradually over one move"),
        (_t1("goal_in_sight"), R, "reward is 100 - d - |angle| if the goal is seen, -9 if not"),
        (_t1("goal_distance"), R, "a close goal means the +1000 reach bonus, a far one a larger distance penalty"),
        (_t1("goal_angle"), R, "a large bearing lowers 100 - d - |angle|"),
    ]


def _persist(sections, why) -> list[tuple[str, str, str]]:
    return [(_t(s), _t1(s), why) for s in sections]


_ALL_SECTIONS = (
    "depth_center",
    "depth_top_left",
    "depth_top_right",
    "depth_bottom_left",
    "depth_bottom_right",
)


def _forward():
    return _core() + _persist(
        _ALL_SECTIONS, "moving ahead brings the obstacles of this section closer"
    ) + [
        (_t("depth_center"), R, "an obstacle close ahead is hit when moving forward (-1000)"),
        (_t("goal_angle"), _t1("goal_in_sight"), "an off-axis goal leaves the field of view as the drone approaches"),
        (_t("goal_in_sight"), _t1("goal_distance"), "the goal distance is only measured while the goal is seen"),
    ]


def _backward():
    return _core() + _persist(
        _ALL_SECTIONS, "moving back pushes the obstacles of this section further away"
    ) + [
        (_t("goal_distance"), _t1("goal_in_sight"), "a far goal shrinks below the detector's size when backing off"),
        (_t("goal_in_sight"), _t1("goal_distance"), "the goal distance is only measured while the goal is seen"),
        (_t("goal_distance"), _t1("goal_angle"), "backing off from a near goal pulls its bearing towards the centre"),
    ]


def _lateral(side: str, other: str):
    # side = the direction of motion ("left" / "right"); the image content shifts towards `other`.
    return _core() + [
        (_t(f"depth_top_{side}"), _t1(f"depth_top_{side}"), f"side-stepping {side} approaches obstacles on the {side}"),
        (_t(f"depth_bottom_{side}"), _t1(f"depth_bottom_{side}"), f"side-stepping {side} approaches obstacles on the {side}"),
        (_t("depth_center"), _t1(f"depth_top_{other}"), f"what is ahead slides to the {other} of the image"),
        (_t("depth_center"), _t1(f"depth_bottom_{other}"), f"what is ahead slides to the {other} of the image"),
        (_t(f"depth_top_{side}"), _t1("depth_center"), f"what is on the {side} slides to the centre of the image"),
        (_t(f"depth_bottom_{side}"), _t1("depth_center"), f"what is on the {side} slides to the centre of the image"),
        (_t(f"depth_top_{side}"), R, f"a close obstacle on the {side} is hit when side-stepping (-1000)"),
        (_t(f"depth_bottom_{side}"), R, f"a close obstacle on the {side} is hit when side-stepping (-1000)"),
        (_t("goal_angle"), _t1("goal_in_sight"), f"a goal far to the {other} leaves the view when stepping {side}"),
        (_t("goal_distance"), _t1("goal_angle"), "the same lateral step turns the bearing of a near goal more"),
        (_t("goal_in_sight"), _t1("goal_distance"), "the goal distance is only measured while the goal is seen"),
    ]


def _ascend():
    return _core() + [
        (_t("altitude"), _t1("altitude"), "climbing raises the altitude band"),
        (_t("altitude"), _t1("goal_in_sight"), "climbing above the board takes the goal out of the camera's view"),
        (_t("depth_top_left"), _t1("depth_top_left"), "obstacles above-ahead get closer to the camera when climbing"),
        (_t("depth_top_right"), _t1("depth_top_right"), "obstacles above-ahead get closer to the camera when climbing"),
        (_t("depth_center"), _t1("depth_bottom_left"), "what is ahead slides to the bottom of the image"),
        (_t("depth_center"), _t1("depth_bottom_right"), "what is ahead slides to the bottom of the image"),
        (_t("depth_top_left"), R, "a close obstacle above-ahead is hit when climbing (-1000)"),
        (_t("depth_top_right"), R, "a close obstacle above-ahead is hit when climbing (-1000)"),
    ]


def _descend():
    return _core() + [
        (_t("altitude"), _t1("altitude"), "descending lowers the altitude band"),
        (_t("altitude"), R, "descending while close to the ground hits the floor (-1000)"),
        (_t("depth_bottom_left"), _t1("depth_bottom_left"), "obstacles below-ahead get closer when descending"),
        (_t("depth_bottom_right"), _t1("depth_bottom_right"), "obstacles below-ahead get closer when descending"),
        (_t("depth_center"), _t1("depth_top_left"), "what is ahead slides to the top of the image"),
        (_t("depth_center"), _t1("depth_top_right"), "what is ahead slides to the top of the image"),
        (_t("depth_bottom_left"), R, "a close obstacle below-ahead is hit when descending (-1000)"),
        (_t("depth_bottom_right"), R, "a close obstacle below-ahead is hit when descending (-1000)"),
    ]


def _turn(side: str, other: str, extra: bool):
    edges = _core() + [
        (_t("goal_angle"), _t1("goal_in_sight"), f"a goal far to the {other} leaves the view when turning {side}"),
        (_t("depth_center"), _t1(f"depth_top_{other}"), f"turning {side} shifts what is ahead to the {other}"),
        (_t("depth_center"), _t1(f"depth_bottom_{other}"), f"turning {side} shifts what is ahead to the {other}"),
        (_t(f"depth_top_{side}"), _t1("depth_center"), f"turning {side} brings the {side} side to the centre"),
        (_t(f"depth_bottom_{side}"), _t1("depth_center"), f"turning {side} brings the {side} side to the centre"),
        (_t(f"depth_top_{side}"), _t1(f"depth_top_{side}"), f"the {side} sections keep part of what they saw"),
        (_t(f"depth_bottom_{side}"), _t1(f"depth_bottom_{side}"), f"the {side} sections keep part of what they saw"),
        (_t("goal_in_sight"), _t1("goal_distance"), "the goal distance is only measured while the goal is seen"),
        (_t("goal_in_sight"), _t1("goal_angle"), "the bearing is only measured (else 'good') while the goal is seen"),
        (_t("goal_angle"), _t1("goal_distance"), "a goal turned out of view has no distance ('not_visible')"),
    ]
    if extra:
        edges.append(
            (_t("goal_distance"), _t1("goal_in_sight"), "a small, far goal is lost first when its image moves to the border")
        )
    return edges


_BUILDERS = {
    "forward": _forward,
    "backward": _backward,
    "left": lambda: _lateral("left", "right"),
    "right": lambda: _lateral("right", "left"),
    "ascend": _ascend,
    "descend": _descend,
    "turn_left": lambda: _turn("left", "right", extra=False),
    "turn_right": lambda: _turn("right", "left", extra=True),
}


def expert_edges(action: str | int, schema: VariableSchema = DEFAULT_SCHEMA) -> list[ExpertEdge]:
    """The expert edges of one action, each with its rationale.

    Args:
        action: an action name of :data:`~torchrl_causal.schema.ACTION_NAMES` or its index.
        schema: the variable schema; it must contain the variables the edges name.

    Returns:
        list of :class:`ExpertEdge`.

    Example:
        >>> from torchrl_causal.causal.expert import expert_edges
        >>> expert_edges("descend")[7].rationale
        'descending while close to the ground hits the floor (-1000)'
    """
    if isinstance(action, int):
        if not 0 <= action < len(ACTION_NAMES):
            raise ValueError(f"action index must be in [0, {len(ACTION_NAMES)}), got {action}")
        action = ACTION_NAMES[action]
    if action not in _BUILDERS:
        raise ValueError(f"action must be one of {list(ACTION_NAMES)}, got {action!r}")
    edges = [ExpertEdge(*e) for e in _BUILDERS[action]()]
    nodes = set(schema.node_names())
    missing = {n for e in edges for n in e[:2]} - nodes
    if missing:
        raise ValueError(
            f"schema lacks the variables the expert CBN of {action!r} uses: {sorted(missing)}"
        )
    return edges


def expert_dags(schema: VariableSchema = DEFAULT_SCHEMA) -> dict[str, list[tuple[str, str]]]:
    """The expert DAG of every action, as edge lists keyed by action name.

    Args:
        schema: the variable schema (default :data:`~torchrl_causal.schema.DEFAULT_SCHEMA`).

    Returns:
        ``{action_name: [(source, target), ...]}`` in :data:`~torchrl_causal.schema.ACTION_NAMES` order.

    Example:
        >>> from torchrl_causal.causal.expert import expert_dags
        >>> list(expert_dags())[:2]
        ['forward', 'backward']
    """
    return {a: [(e.source, e.target) for e in expert_edges(a, schema)] for a in ACTION_NAMES}
