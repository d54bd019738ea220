"""Rewards of :class:`~torchrl_causal.envs.DroneNavEnv`: the default ``"progress"`` and the thesis's.

A reward is a callable ``reward(outcome) -> float`` of one :class:`StepOutcome`
(what happened in a step). Two are built in, selected by the env's ``reward``
option (:data:`REWARDS`):

* :class:`ProgressReward` (``"progress"``, the default): ``+10`` on reaching the
  goal, ``-10`` on a crash or on leaving the flight volume, else the progress
  made towards the goal point in metres (``d_before - d_after``, simulator
  ground truth) minus a step cost of ``0.01``. The progress term is a
  potential difference, so it sums to ``d_start - d_end`` over an episode
  whatever the path: it guides without creating a loop worth repeating. The
  step cost makes hovering slightly worse than moving on, while keeping
  hovering for 200 steps (``-2``) better than crashing (``-10``).
* :class:`ThesisReward` (``"thesis"``, thesis sec. 5.1, exactly): ``+1000`` on
  reaching, ``-1000`` on a crash, else ``100 - goal_distance - |goal_angle|``
  while the goal is recognised and ``-9`` while it is not. Leaving the flight
  volume is scored as a crash (the thesis's scene has no such boundary).

Why the default is not the thesis's reward (``docs/envs.rst``, "Reward"): the
thesis pays about ``+90`` for *every* step the goal is in view, so hovering in
view is worth nearly as much as reaching the goal when discounted (``gamma =
0.9``: 888 against 948 for the 12-step path, measured in the env) and nearly
nine times more over an undiscounted 200-step episode (17,784 against 2,017).
A DQN trained on it learns to hover (the thesis noted that "the network learns to do nothing").
Under :class:`ProgressReward` the discounted return orders reach > hover >
crash for any ``gamma`` in (0, 1), and so does the undiscounted episode return.

**Reward classes of the CBN.** The causal learner's reward node is positive
iff the env reward is ``>= 0`` (:class:`~torchrl_causal.causal.CausalLearner`).
Under ``"progress"`` that means "the step moved the
drone at least 1 cm closer to the goal point, or reached it"; under
``"thesis"`` it means "the goal is in view (or reached)", the thesis's
binarisation.

Example:
    >>> r = ProgressReward()
    >>> r(StepOutcome(reached=True))
    10.0
    >>> round(r(StepOutcome(distance_before=2.0, distance_after=1.75)), 2)
    0.24
    >>> ThesisReward()(StepOutcome(in_sight=True, goal_distance=2.0, goal_angle=-5.0))
    93.0
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["REWARDS", "StepOutcome", "ProgressReward", "ThesisReward", "make_reward"]

#: Names accepted by ``DroneNavEnv(reward=...)``; the first is the default.
REWARDS: tuple[str, ...] = ("progress", "thesis")


@dataclass(frozen=True)
class StepOutcome:
    """What one env step did, as the reward sees it.

    Args:
        crashed: the drone touched something.
        reached: the drone's centre came within ``reach_radius`` of the goal point.
        out_of_bounds: the drone's centre left the flight volume (geofence).
        in_sight: the goal is recognised after the step (``goal_in_sight``).
        goal_distance: measured distance to the goal (m; 0 when not in sight).
        goal_angle: measured angle to the goal (deg; 0 when not in sight).
        distance_before: true distance of the drone's centre to the goal point
            before the step (m).
        distance_after: the same after the step (m).

    Example:
        >>> StepOutcome(crashed=True).failed
        True
    """

    crashed: bool = False
    reached: bool = False
    out_of_bounds: bool = False
    in_sight: bool = False
    goal_distance: float = 0.0
    goal_angle: float = 0.0
    distance_before: float = 0.0
    distance_after: float = 0.0

    @property
    def failed(self) -> bool:
        """A crash or a geofence exit (and not a reach)."""
        return (self.crashed or self.out_of_bounds) and not self.reached


def _number(name, value, positive=False):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or (positive and value <= 0):
        need = "a finite number > 0" if positive else "a finite number"
        raise ValueError(f"{name} must be {need}, got {value!r}")
    return float(value)


class ProgressReward:
    """The default reward: reach bonus, failure penalty, progress minus a step cost.

    Args:
        reach: reward for reaching the goal (terminal).
        fail: reward for a crash or a geofence exit (terminal).
        progress_per_m: reward per metre of progress towards the goal point.
        step_cost: subtracted on every non-terminal step.

    Example:
        >>> ProgressReward()(StepOutcome(out_of_bounds=True))
        -10.0
        >>> ProgressReward()(StepOutcome(distance_before=1.0, distance_after=1.0))
        -0.01
    """

    name = "progress"

    def __init__(
        self,
        reach: float = 10.0,
        fail: float = -10.0,
        progress_per_m: float = 1.0,
        step_cost: float = 0.01,
    ):
        self.reach = _number("reach", reach)
        self.fail = _number("fail", fail)
        self.progress_per_m = _number("progress_per_m", progress_per_m)
        self.step_cost = _number("step_cost", step_cost)
        if self.step_cost < 0:
            raise ValueError(f"step_cost must be >= 0, got {step_cost!r}")
        if not self.fail < 0 < self.reach:
            raise ValueError(f"need fail < 0 < reach, got fail={fail!r}, reach={reach!r}")

    def __call__(self, o: StepOutcome) -> float:
        if o.reached:
            return self.reach
        if o.failed:
            return self.fail
        return self.progress_per_m * (o.distance_before - o.distance_after) - self.step_cost

    def __repr__(self) -> str:
        return (f"ProgressReward(reach={self.reach}, fail={self.fail}, "
                f"progress_per_m={self.progress_per_m}, step_cost={self.step_cost})")


class ThesisReward:
    """The thesis's reward (sec. 5.1), exactly; a geofence exit counts as a crash.

    Args:
        reach: reward for reaching the goal (thesis: 1000).
        crash: reward for a crash (thesis: -1000).
        in_view: base of the in-view term ``in_view - distance - |angle|`` (thesis: 100).
        not_in_view: reward while the goal is not recognised (thesis: -9).

    Example:
        >>> ThesisReward()(StepOutcome(in_sight=False))
        -9.0
        >>> ThesisReward()(StepOutcome(crashed=True, in_sight=True))
        -1000.0
    """

    name = "thesis"

    def __init__(
        self,
        reach: float = 1000.0,
        crash: float = -1000.0,
        in_view: float = 100.0,
        not_in_view: float = -9.0,
    ):
        self.reach = _number("reach", reach)
        self.crash = _number("crash", crash)
        self.in_view = _number("in_view", in_view)
        self.not_in_view = _number("not_in_view", not_in_view)

    def __call__(self, o: StepOutcome) -> float:
        if o.failed:
            return self.crash
        if o.reached:
            return self.reach
        if o.in_sight:
            return self.in_view - o.goal_distance - abs(o.goal_angle)
        return self.not_in_view

    def __repr__(self) -> str:
        return (f"ThesisReward(reach={self.reach}, crash={self.crash}, "
                f"in_view={self.in_view}, not_in_view={self.not_in_view})")


def make_reward(reward) -> ProgressReward | ThesisReward:
    """A reward from its name (:data:`REWARDS`) or a callable (returned as is).

    Raises:
        ValueError: an unknown name, naming the accepted ones.

    Example:
        >>> make_reward("thesis").name
        'thesis'
    """
    if callable(reward):
        return reward
    if reward == "progress":
        return ProgressReward()
    if reward == "thesis":
        return ThesisReward()
    raise ValueError(f"reward must be one of {REWARDS} or a callable, got {reward!r}")
