"""``ReachRule``: a drone with only a camera (and a height sensor) decides that it has arrived.

:class:`~torchrl_causal.envs.DroneNavEnv` knows the drone's pose and ends an
episode ``reached`` when the drone passes within ``reach_radius`` (0.2 m) of the
goal point, 0.47 m in front of the board's centre. A real Tello has no pose:
:class:`~torchrl_causal.envs.TelloEnv` asks a :class:`ReachRule` after every
step, from what it measures:

* ``distance``: the detector's goal distance (the range from the *camera* to the
  board along the ray through the box centre). The camera sits
  ``camera_offset`` (0.125 m) in front of the drone's centre, so at the goal
  point the board is 0.47 - 0.125 = 0.345 m away; ``max_distance`` 0.55 (the
  old rule) fires with the drone's centre 0.2 m short of the goal point, on the
  sphere's surface;
* ``angle``: the bearing of the box centre;
* ``altitude``: the height sensor (the Tello's ``tof``) against
  ``goal_height``, the goal point's height above the floor (the board centre's
  height; ``None``: not checked). The board fills the view near the goal, so
  the image no longer shows a vertical offset, the height sensor does;
* ``full_width``: near the goal point the 1.0 m board fills the image's width
  (both sides of the box at the image border); a box with one side inside the
  image means the drone is beside the board.

The thresholds were chosen by measurement (docs/tello.rst, "An arrival rule
that agrees with the simulator").

Example:
    >>> rule = ReachRule(max_distance=0.45, goal_height=1.0, max_height_offset=0.12)
    >>> rule(in_sight=True, distance=0.40, angle=2.0, box=(0, 0, 84, 84), width=84, altitude=1.05)
    True
    >>> rule(in_sight=True, distance=0.40, angle=2.0, box=(0, 0, 84, 84), width=84, altitude=1.30)
    False
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

__all__ = ["ReachRule"]


def _finite(name, value, low=None, high=None, strict_low=False):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if strict_low else value >= low
    if ok and high is not None:
        ok = value <= high
    if not ok:
        rng = f" in {'(' if strict_low else '['}{low}, {high}]" if high is not None else (
            f" {'>' if strict_low else '>='} {low}" if low is not None else "")
        raise ValueError(f"ReachRule.{name} must be a finite number{rng}, got {value!r}")


@dataclass(frozen=True)
class ReachRule:
    """When :class:`~torchrl_causal.envs.TelloEnv` declares ``reached``.

    Args:
        max_distance: the goal in sight within this measured distance (m) of the
            camera (0.05-3; default 0.45: the drone's centre about 0.1 m short of
            the goal point; the old 0.55 fired on the sphere's surface).
        min_distance: ... and not closer than this (m; default 0).
        max_angle: ... and its bearing within this angle (deg, 0-90).
        goal_height: the goal point's height above the floor (m), compared with
            the measured ``altitude``; ``None`` (default): not checked.
        max_height_offset: allowed ``|altitude - goal_height|`` (m, 0.01-1).
        full_width: the goal's box must touch both side borders of the image
            (the board fills the view's width).

    Example:
        >>> ReachRule().max_distance, ReachRule().goal_height
        (0.45, None)
        >>> ReachRule(max_distance=-1)
        Traceback (most recent call last):
        ...
        ValueError: ReachRule.max_distance must be a finite number in (0.05, 3.0], got -1
    """

    max_distance: float = 0.45
    min_distance: float = 0.0
    max_angle: float = 30.0
    goal_height: float | None = None
    max_height_offset: float = 0.15
    full_width: bool = False

    def __post_init__(self):
        _finite("max_distance", self.max_distance, 0.05, 3.0, strict_low=True)
        _finite("min_distance", self.min_distance, 0.0, self.max_distance)
        _finite("max_angle", self.max_angle, 0.0, 90.0, strict_low=True)
        if self.goal_height is not None:
            _finite("goal_height", self.goal_height, 0.0, 10.0, strict_low=True)
        _finite("max_height_offset", self.max_height_offset, 0.01, 1.0)
        if not isinstance(self.full_width, bool):
            raise ValueError(f"ReachRule.full_width must be a bool, got {self.full_width!r}")

    def __call__(self, *, in_sight: bool, distance: float, angle: float, box, width: int,
                 altitude: float) -> bool:
        """Whether the drone has arrived, from one step's measurements."""
        if not in_sight or not math.isfinite(distance):
            return False
        if not self.min_distance <= distance <= self.max_distance:
            return False
        if abs(angle) > self.max_angle:
            return False
        if self.goal_height is not None and abs(altitude - self.goal_height) > \
                self.max_height_offset:
            return False
        if self.full_width:
            x0, _, x1, _ = (float(v) for v in box)
            if x0 > 0.5 or x1 < width - 0.5:
                return False
        return True

    def to_dict(self) -> dict:
        """The rule's options (for ``summary.json``)."""
        return asdict(self)
