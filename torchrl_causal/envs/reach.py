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
  image means the drone is beside the board;
* ``max_goal_offset``: the drone's estimated horizontal distance to the goal
  point (:func:`goal_point_offset`): the board's plane fitted to the depth
  inside the box gives the board's facing; the board's centre is the midpoint of
  its two side edges, or one edge plus half the ``board_width``, when an edge
  is in view (the box centre's ray when the board fills the view); the goal
  point lies ``goal_standoff`` in front of it. Range and bearing alone cannot
  tell the goal point from a place beside it when the board is seen at an angle
  (random layouts turn it up to 30 deg), this can.

:class:`BoardPlaneOffset` reads that estimate as an arrival head does, in the
board's frame, so that :class:`~torchrl_causal.envs.TelloEnv` can take the
segment between two steps' estimates and fly a :class:`FinalApproach` on any board
the depth map shows (docs/tello.rst, "The board plane as the head").

The thresholds were chosen by measurement (docs/tello.rst, "An arrival rule
that agrees with the simulator"). ``max_distance`` depends on the depth model:
:func:`calibrate_reach_distance` finds a model's own threshold (a pose sweep at
the thesis board), ``recipes/train_depth.py`` stores it in the weights it writes,
and :class:`~torchrl_causal.envs.TelloEnv` uses it when given no rule.

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

import numpy as np

__all__ = ["ReachRule", "FinalApproach", "BoardPlaneOffset", "calibrate_reach_distance",
           "goal_point_offset"]


def _board_line(depth, box, hfov_deg: float, board_width: float | None,
                max_residual: float | None = None):
    """The board's centre and normal (towards the camera) in the camera's horizontal plane
    (``(x right, z forward)``, m), and how many of its side edges are in view, from the
    per-column median z-depth inside ``box``; None when too few columns are valid or the
    board is seen edge-on (:func:`goal_point_offset`).

    With ``max_residual`` (m) two checks more: None when more than a fifth of the columns'
    depths lie farther than that from their fitted line (something in front of the board,
    or not a board; the line is refitted to the others: a board seen at an angle leaves
    background in the thin columns at its far end), and a side of the box is not taken for the board's edge when the image just
    beyond it is nearer than the board there (an obstacle hides the board's end)."""
    d_ = np.asarray(depth, dtype=np.float64)
    H, W = d_.shape
    x0, y0, x1, y1 = (int(round(float(v))) for v in box)
    x0, x1 = max(0, x0), min(W, x1)
    y0, y1 = max(0, y0), min(H, y1)
    if x1 - x0 < 3 or y1 - y0 < 1:
        return None
    f = (W / 2) / math.tan(math.radians(hfov_deg) / 2)
    cols = np.arange(x0, x1)
    block = d_[y0:y1, x0:x1]
    block = np.where(np.isfinite(block) & (block > 0), block, np.nan)
    with np.errstate(all="ignore"):
        z = np.nanmedian(block, axis=0) if np.isfinite(block).any() else np.full(len(cols), np.nan)
    ok = np.isfinite(z)
    if ok.sum() < 3:
        return None
    cols, z = cols[ok], z[ok]
    pts = np.stack([z * (cols + 0.5 - W / 2) / f, z], 1)
    c = pts.mean(0)
    _, _, vt = np.linalg.svd(pts - c)
    if max_residual is not None:  # the columns off the line: at most a fifth, then refit
        keep = np.abs((pts - c) @ vt[1]) <= max_residual
        if keep.mean() < 0.8 or keep.sum() < 3:
            return None
        c = pts[keep].mean(0)
        _, _, vt = np.linalg.svd(pts[keep] - c)
    along = vt[0] if vt[0][0] >= 0 else -vt[0]  # along the board, towards the image's right
    normal = np.array([-along[1], along[0]])
    if normal[1] > 0:  # towards the camera
        normal = -normal

    def on_board(col):  # where the ray through a pixel column meets the board's line
        ray = np.array([(col - W / 2) / f, 1.0])
        t, _ = np.linalg.solve(np.stack([ray, -along], 1), c)
        return t * ray

    left_in, right_in = x0 > 0, x1 < W
    if max_residual is not None:  # an edge with something nearer just beyond it is hidden
        def hidden(lo, hi, col):
            out = d_[y0:y1, max(0, lo):min(W, hi)]
            out = out[np.isfinite(out) & (out > 0)]
            if out.size == 0:
                return False
            try:
                board_z = float(on_board(col)[1])
            except np.linalg.LinAlgError:
                return False
            return float(np.median(out)) < board_z - 2 * max_residual - 0.02

        left_in = left_in and not hidden(x0 - 3, x0, x0)
        right_in = right_in and not hidden(x1, x1 + 3, x1)
    try:
        if left_in and right_in:
            centre, edges = (on_board(x0) + on_board(x1)) / 2, 2
        elif left_in and board_width is not None:
            centre, edges = on_board(x0) + along * board_width / 2, 1
        elif right_in and board_width is not None:
            centre, edges = on_board(x1) - along * board_width / 2, 1
        else:
            centre, edges = on_board((x0 + x1) / 2), 0
    except np.linalg.LinAlgError:  # a ray along the board's line: seen edge-on
        return None
    return centre, normal, edges


def goal_point_offset(depth, box, hfov_deg: float, *, goal_standoff: float = 0.45,
                      board_width: float | None = 1.0, camera_offset: float = 0.125,
                      moved=(0.0, 0.0), height_offset: float = 0.0):
    """The drone's horizontal distance to the goal point, seen from one depth map.

    Fits the board's plane (a line in the camera's horizontal plane) to the
    per-column median z-depth inside ``box``; the board's centre is the midpoint
    of its two side edges when both are in view, one edge plus ``board_width``/2
    along the board when one is (``board_width`` None: the box centre's ray),
    else (the board fills the view's width) where the box centre's ray meets the
    plane. The goal point is ``goal_standoff`` in front of that centre, along
    the plane's normal; the drone's centre is ``camera_offset`` behind the camera.
    With ``moved``, the distance is to the segment the drone's centre has just
    flown (as the simulator judges a pass through the goal sphere), not to its
    end only: 0.25 m moves can step over a 0.2 m sphere's centre. With
    ``height_offset`` (the goal point's height above the drone's centre, from a
    height sensor) the distance is 3-D, as the simulator's sphere is.

    Args:
        depth: z-depth map ``[H, W]`` (m; array or tensor).
        box: the goal's box ``(x0, y0, x1, y1)`` in pixels.
        hfov_deg: the camera's horizontal field of view (deg).
        goal_standoff: goal point in front of the board's face (m).
        board_width: the board's width (m), or None.
        camera_offset: camera in front of the drone's centre (m).
        moved: the last move of the drone's centre, ``(right, forward)`` or
            ``(right, forward, up)`` in the camera's current frame (m);
            ``(0, 0)``: the point itself.
        height_offset: the goal point's height above the drone's centre (m).

    Returns:
        ``(offset_m, facing_deg)``: the distance, and the angle between the
        camera's axis and the board's normal (0: square on); ``(nan, nan)`` when
        the box holds too few valid columns.

    Example:
        >>> import numpy as np
        >>> depth = np.full((84, 84), 0.345)   # the board square on, filling the view, 0.345 m away
        >>> off, facing = goal_point_offset(depth, (0, 0, 84, 84), hfov_deg=60.0)
        >>> round(off, 3), round(facing, 1)    # |0.345 + 0.125 - 0.45|: 2 cm behind the goal point
        (0.02, 0.0)
        >>> depth = np.full((84, 84), 0.2)     # 0.125 m past it, having just flown 0.25 m forward
        >>> round(goal_point_offset(depth, (0, 0, 84, 84), 60.0)[0], 3)
        0.125
        >>> round(goal_point_offset(depth, (0, 0, 84, 84), 60.0, moved=(0.0, 0.25))[0], 3)
        0.0
    """
    line = _board_line(depth, box, hfov_deg, board_width)
    if line is None:
        return (float("nan"), float("nan"))
    centre, normal, _ = line
    goal = np.append(centre + goal_standoff * normal, float(height_offset))
    end = np.array([0.0, -camera_offset, 0.0])
    mv = np.zeros(3)
    mv[: len(moved)] = np.asarray(moved, dtype=np.float64)
    start = end - mv
    seg = end - start
    t = float(np.clip((goal - start) @ seg / max(float(seg @ seg), 1e-12), 0.0, 1.0))
    offset = float(np.linalg.norm(goal - (start + t * seg)))
    facing = float(math.degrees(math.atan2(-normal[0], -normal[1]))) + 0.0  # no -0.0
    return offset, facing


def _finite(name, value, low=None, high=None, strict_low=False, owner="ReachRule"):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if strict_low else value >= low
    if ok and high is not None:
        ok = value <= high
    if not ok:
        rng = f" in {'(' if strict_low else '['}{low}, {high}]" if high is not None else (
            f" {'>' if strict_low else '>='} {low}" if low is not None else "")
        raise ValueError(f"{owner}.{name} must be a finite number{rng}, got {value!r}")


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
        max_goal_offset: the estimated distance (m) from the drone's centre
            (the segment of its last move) to the goal point
            (:func:`goal_point_offset`) must be at most this; with a
            ``goal_height`` it is 3-D (the height sensor's difference included)
            and replaces ``max_height_offset``; ``None`` (default): not checked.
        board_width: the board's width (m; the thesis board: 1.0), for
            ``max_goal_offset``.
        goal_standoff: the goal point in front of the board's face (m; the
            thesis scene and the random layouts: 0.45), for ``max_goal_offset``.

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
    max_goal_offset: float | None = None
    board_width: float = 1.0
    goal_standoff: float = 0.45

    def __post_init__(self):
        _finite("max_distance", self.max_distance, 0.05, 3.0, strict_low=True)
        _finite("min_distance", self.min_distance, 0.0, self.max_distance)
        _finite("max_angle", self.max_angle, 0.0, 90.0, strict_low=True)
        if self.goal_height is not None:
            _finite("goal_height", self.goal_height, 0.0, 10.0, strict_low=True)
        _finite("max_height_offset", self.max_height_offset, 0.01, 1.0)
        if not isinstance(self.full_width, bool):
            raise ValueError(f"ReachRule.full_width must be a bool, got {self.full_width!r}")
        if self.max_goal_offset is not None:
            _finite("max_goal_offset", self.max_goal_offset, 0.02, 2.0)
        _finite("board_width", self.board_width, 0.1, 5.0)
        _finite("goal_standoff", self.goal_standoff, 0.0, 3.0)

    def goal_offset(self, depth, box, hfov_deg: float, camera_offset: float = 0.125,
                    moved=(0.0, 0.0), altitude: float | None = None) -> float:
        """:func:`goal_point_offset` with this rule's board (the distance only); 3-D
        when the rule has a ``goal_height`` and ``altitude`` is given."""
        dz = (self.goal_height - altitude
              if self.goal_height is not None and altitude is not None else 0.0)
        return goal_point_offset(depth, box, hfov_deg, goal_standoff=self.goal_standoff,
                                 board_width=self.board_width, camera_offset=camera_offset,
                                 moved=moved, height_offset=dz)[0]

    def __call__(self, *, in_sight: bool, distance: float, angle: float, box, width: int,
                 altitude: float, goal_offset: float | None = None) -> bool:
        """Whether the drone has arrived, from one step's measurements
        (``goal_offset``: :meth:`goal_offset`'s estimate, needed when
        ``max_goal_offset`` is set; a missing or non-finite one never fires)."""
        if not in_sight or not math.isfinite(distance):
            return False
        if not self.min_distance <= distance <= self.max_distance:
            return False
        if abs(angle) > self.max_angle:
            return False
        # with an offset estimate the height is inside it (3-D, as the sphere)
        if self.goal_height is not None and self.max_goal_offset is None and \
                abs(altitude - self.goal_height) > self.max_height_offset:
            return False
        if self.full_width:
            x0, _, x1, _ = (float(v) for v in box)
            if x0 > 0.5 or x1 < width - 0.5:
                return False
        if self.max_goal_offset is not None and not (
                goal_offset is not None and math.isfinite(goal_offset)
                and goal_offset <= self.max_goal_offset):
            return False
        return True

    def to_dict(self) -> dict:
        """The rule's options (for ``summary.json``)."""
        return asdict(self)


class FinalApproach:
    """The last leg flown by the drone itself: from the arrival head's estimate to the goal point.

    Near the goal a policy that turns back and forth at the sphere's edge (0.2-0.4 m
    from the goal point, where the head's few centimetres of error decide the verdict)
    neither arrives nor crashes until it does (docs/tello.rst, "A final approach").
    When the head puts the goal point within ``radius`` (and the rule has not fired),
    :class:`~torchrl_causal.envs.TelloEnv` sends one Tello SDK ``go x y z speed`` to
    the estimated goal point and observes again.

    The head reads ``(ahead, lateral)`` in the *board's* frame; the move is in the
    drone's. The angle between the two comes from the episode's own history: each
    head estimate is stored with the drone's dead-reckoned position (its executed
    moves, turned by the height sensor's companion, the IMU's yaw), and the rotation
    that best maps the dead-reckoned displacements onto the head's displacements
    (2-D Procrustes over every pair at least ``min_baseline`` apart) is the board's
    heading in the drone's odometry frame. Without such a pair there is no approach.

    The SDK refuses a ``go`` whose three components are all within -20..20 cm: such a
    move is lengthened along its own line to 21 cm on its largest axis, so it flies
    through the estimated goal point and a little beyond (the simulator and the
    arrival rule's segment both count the pass).

    Args:
        radius: the head's 3-D distance to the goal point (m) within which the drone
            flies the last leg itself (0.05-1.0).
        min_baseline: the shortest dead-reckoned displacement (m) between two
            estimates whose pair is used for the heading.
        speed: the ``go`` speed (cm/s, the SDK's 10-100).

    Example:
        >>> import math
        >>> fa = FinalApproach(radius=0.4)
        >>> fa.record((0.0, 0.0), (0.8, 0.0))     # the board ahead, square on
        >>> fa.record((0.5, 0.0), (0.3, 0.0))     # flew 0.5 m forward: 0.5 m nearer
        >>> fa.plan((0.3, 0.0, 0.0), yaw=0.0)     # 30 cm forward to the goal point
        (30, 0, 0)
        >>> fa.plan((0.3, 0.1, 0.0), yaw=math.radians(90))  # 0.1 m to its right, turned left
        (10, -30, 0)
        >>> fa.plan((0.1, 0.05, -0.05), yaw=0.0)  # all within 20 cm: lengthened
        (21, 11, 10)
        >>> fa.plan((0.6, 0.0, 0.0), yaw=0.0) is None   # beyond the radius
        True
    """

    def __init__(self, radius: float = 0.4, *, min_baseline: float = 0.15, speed: int = 30):
        for name, v, lo, hi in (("radius", radius, 0.05, 1.0),
                                ("min_baseline", min_baseline, 0.01, 2.0)):
            if not (isinstance(v, (int, float)) and not isinstance(v, bool)
                    and math.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"FinalApproach.{name} must be a number in [{lo}, {hi}] m, "
                                 f"got {v!r}")
        if not (isinstance(speed, int) and not isinstance(speed, bool) and 10 <= speed <= 100):
            raise ValueError(f"FinalApproach.speed must be an int in [10, 100] cm/s (the "
                             f"Tello SDK's go), got {speed!r}")
        self.radius = float(radius)
        self.min_baseline = float(min_baseline)
        self.speed = int(speed)
        self.reset()

    def reset(self) -> None:
        """Forgets the episode's estimates (a new episode)."""
        self._history: list[tuple[np.ndarray, np.ndarray]] = []

    def record(self, position, estimate) -> None:
        """Stores one head estimate ``(ahead, lateral)`` (m, the board's frame) with the
        drone's dead-reckoned ``(x, y)`` (m, the odometry frame) where it was read."""
        self._history.append((np.asarray(position, float)[:2].copy(),
                              np.asarray(estimate, float)[:2].copy()))

    def heading(self) -> float | None:
        """The rotation (rad) from the odometry frame to the board's, or None (no pair of
        estimates ``min_baseline`` apart)."""
        cross = dot = 0.0
        h = self._history
        for i in range(len(h)):
            for j in range(i + 1, len(h)):
                dw, dp = h[j][0] - h[i][0], h[j][1] - h[i][1]
                if float(np.hypot(*dw)) < self.min_baseline:
                    continue
                cross += dw[0] * dp[1] - dw[1] * dp[0]
                dot += dw @ dp
        if cross == 0.0 and dot == 0.0:
            return None
        return math.atan2(cross, dot)

    def carried(self, estimate, displacement):
        """``estimate`` ``(ahead, lateral)`` moved by the dead-reckoned ``displacement``
        ``(dx, dy)`` (m, the odometry frame) since it was read, turned into the board's
        frame by :meth:`heading`; None without a heading.

        Example:
            >>> fa = FinalApproach()
            >>> fa.record((0.0, 0.0), (0.8, 0.0)); fa.record((0.5, 0.0), (0.3, 0.0))
            >>> [round(float(v), 2) for v in fa.carried((0.3, 0.0), (0.25, 0.0))]
            [0.05, 0.0]
        """
        alpha = self.heading()
        if alpha is None:
            return None
        c, s = math.cos(alpha), math.sin(alpha)
        dx, dy = (float(v) for v in displacement[:2])
        return np.array([estimate[0] + c * dx - s * dy, estimate[1] + s * dx + c * dy])

    def plan(self, estimate, yaw: float, threshold: float = 0.0):
        """The ``go`` of the last leg, ``(forward, left, up)`` in whole cm, or None.

        Args:
            estimate: the head's ``(ahead, lateral, dz)`` (m; ``dz``: the drone above
                the goal point, from the height sensor).
            yaw: the drone's yaw (rad, counter-clockwise) in the odometry frame.
            threshold: no approach at or within this distance (the rule's own
                ``max_goal_offset``: it would have fired).
        """
        est = np.asarray(estimate, float).reshape(-1)
        if est.shape != (3,) or not np.isfinite(est).all():
            return None
        dist = float(np.linalg.norm(est))
        if dist > self.radius or dist <= threshold:
            return None
        alpha = self.heading()
        if alpha is None:
            return None
        ca, sa = math.cos(-alpha), math.sin(-alpha)
        vx, vy = -est[0], -est[1]  # to the goal point, in the board's frame
        wx, wy = ca * vx - sa * vy, sa * vx + ca * vy  # ... in the odometry frame
        cy, sy = math.cos(yaw), math.sin(yaw)
        move = np.array([cy * wx + sy * wy, -sy * wx + cy * wy, -est[2]]) * 100.0
        big = float(np.abs(move).max())
        if big < 1e-9:
            return None
        if big < 20.5:  # the SDK's go needs one axis beyond 20 cm: fly through the point
            move *= 21.0 / big
        return tuple(int(round(float(v))) for v in move)


class BoardPlaneOffset:
    """The depth map's board plane as an arrival head: ``(ahead, lateral)`` from the goal point.

    :class:`~torchrl_causal.envs.TelloEnv` takes it as its ``arrival_head``
    (``fly_tello.py --arrival-head depth``). It reads what :func:`goal_point_offset`
    reads (the board's plane fitted to the depth inside the goal's box, its side
    edges, the rule's ``board_width`` and ``goal_standoff``) but returns the drone's
    place in the *board's* frame, as :class:`~torchrl_causal.perception.arrival.GoalOffsetEstimator`
    does: ``ahead`` > 0 farther from the board than the goal point, ``lateral`` > 0 to
    the right seen facing the board. So the head's machinery applies to any board the
    depth map shows (random layouts' boards of any width, where the learned head was
    not trained): the segment between two steps' estimates, both in the board's
    frame, is the path the drone really flew, not the commanded move, and
    :class:`FinalApproach` can fly the last leg.

    Once the board fills the view (no side edge in view) one frame no longer shows
    where along the board the drone is. With ``memory`` the lateral place is then
    carried on from the last view with an edge by the drone's dead-reckoned moves
    since (``pose``: the odometry ``(x, y, yaw)``, yaw in rad counter-clockwise),
    turned into that view's board frame; the range to the board's plane is always
    the current frame's. Without ``memory``, or ``max_age`` steps after the last
    edge, the box centre's ray is taken (:func:`goal_point_offset`'s choice).

    Two checks keep what is not the board's plane out: when more than a fifth of the
    box's columns lie more than ``max_residual`` from their fitted line there is no
    estimate (an obstacle in front of part of the board, a sliver of board at the
    image's border; the line is refitted to the rest), and a side of
    the box with something nearer just beyond it is not the board's edge (an obstacle
    hides the board's end there).

    A sliver of board (a box narrower than ``min_width`` of the image) and a board
    seen nearly edge-on (its normal more than ``max_facing`` off the camera's axis) give
    no estimate either: a few columns at a grazing angle fix neither the plane nor the
    edge (the drone beside the board, in its plane, read as in front of it).

    Args:
        memory: carry the lateral place over views without an edge.
        max_age: how many views without an edge a remembered lateral place lasts.
        max_residual: how far (m) a column's depth may lie from the fitted line
            (0.001-1; default 0.03, for a depth map as exact as the simulator's).
        min_width: the narrowest box (a fraction of the image's width, 0-1) read.
        max_facing: the largest angle (deg, 1-90) between the camera's axis and the
            board's normal read.

    Example:
        >>> import numpy as np
        >>> head = BoardPlaneOffset()
        >>> depth = np.full((84, 84), 1.0)          # a 1 m board, square on, 1 m ahead
        >>> box = (20, 0, 64, 84)                   # ... both of its side edges in view
        >>> ahead, lat = head(depth, box, 60.0, board_width=1.0, goal_standoff=0.45,
        ...                   pose=(0.0, 0.0, 0.0))
        >>> round(float(ahead), 3), round(float(lat), 3)   # 1 + 0.125 - 0.45 m in front
        (0.675, 0.0)
        >>> # 0.5 m forward and 0.2 m to the right: the board now fills the view
        >>> ahead, lat = head(np.full((84, 84), 0.5), (0, 0, 84, 84), 60.0, board_width=1.0,
        ...                   goal_standoff=0.45, pose=(0.5, -0.2, 0.0))
        >>> round(float(ahead), 3), round(float(lat), 3)   # the lateral place remembered
        (0.175, 0.2)
    """

    def __init__(self, memory: bool = True, max_age: int = 8, max_residual: float = 0.03,
                 min_width: float = 0.25, max_facing: float = 70.0):
        _finite("max_residual", max_residual, 0.001, 1.0, owner="BoardPlaneOffset")
        _finite("min_width", min_width, 0.0, 1.0, owner="BoardPlaneOffset")
        _finite("max_facing", max_facing, 1.0, 90.0, owner="BoardPlaneOffset")
        if not isinstance(memory, bool):
            raise ValueError(f"BoardPlaneOffset.memory must be a bool, got {memory!r}")
        if not (isinstance(max_age, int) and not isinstance(max_age, bool) and max_age >= 0):
            raise ValueError(f"BoardPlaneOffset.max_age must be an int >= 0, got {max_age!r}")
        self.memory = memory
        self.max_age = max_age
        self.max_residual = float(max_residual)
        self.min_width = float(min_width)
        self.max_facing = float(max_facing)
        self.reset()

    def reset(self) -> None:
        """Forgets the last view with an edge (a new episode)."""
        self._fix = None  # (odometry xy, lateral, the board's side direction in odometry)
        self._age = 0

    def __call__(self, depth, box, hfov_deg: float, *, board_width: float = 1.0,
                 goal_standoff: float = 0.45, camera_offset: float = 0.125, pose=None):
        """``np.array([ahead, lateral])`` (m), or None (too few valid depth columns in
        ``box``, or the board seen edge-on)."""
        width = np.asarray(depth).shape[-1]
        if float(box[2]) - float(box[0]) < self.min_width * width:
            return None
        line = _board_line(depth, box, hfov_deg, board_width, self.max_residual)
        if line is None:
            return None
        centre, normal, edges = line
        if abs(math.degrees(math.atan2(-normal[0], -normal[1]))) > self.max_facing:
            return None
        side = np.array([-normal[1], normal[0]])  # the drone's right, facing the board
        v = np.array([0.0, -camera_offset]) - (centre + goal_standoff * normal)
        ahead, lateral = float(v @ normal), float(v @ side)
        if pose is None or not self.memory:
            return np.array([ahead, lateral])
        x, y, yaw = (float(p) for p in pose)
        c, s = math.cos(yaw), math.sin(yaw)
        # a camera-frame vector (right, forward) in the odometry frame
        side_w = np.array([side[1] * c + side[0] * s, side[1] * s - side[0] * c])
        if edges > 0:
            self._fix, self._age = (np.array([x, y]), lateral, side_w), 0
        elif self._fix is not None and self._age < self.max_age:
            self._age += 1
            xy0, lat0, side0 = self._fix
            lateral = lat0 + float((np.array([x, y]) - xy0) @ side0)
        return np.array([ahead, lateral])


def calibrate_reach_distance(depth_estimator=None, *, poses: int = 200, seed: int = 0,
                             thresholds=None, detector=None) -> dict:
    """The ``max_distance`` at which a depth model's goal distance best says "arrived".

    The drone is placed at ``poses`` random poses in front of the thesis
    scene's board (along its normal from 0.35 m nearer to 0.45 m farther than
    the goal point, up to 0.25 m sideways, yaw within 15 deg of facing it; plain
    240 x 320 renders) and the RGB stack (the detector + ``depth_estimator``)
    measures ``goal_distance``, the range :class:`ReachRule` compares with
    ``max_distance``. For each threshold: the share of poses inside
    :class:`~torchrl_causal.envs.DroneNavEnv`'s 0.2 m goal sphere where the
    rule would fire (``fire_inside``) and the share outside it
    (``fire_outside``); the best threshold has the largest difference (Youden's
    J; ties: the smaller threshold).

    Args:
        depth_estimator: a :class:`~torchrl_causal.perception.MonoDepth` or any
            ``uint8 [B, H, W, 3] -> depth [B, H, W]`` callable (None: the
            shipped MonoDepth).
        poses: how many poses (>= 10).
        seed: the poses' seed.
        thresholds: the candidate thresholds (m; default 0.28-0.51 in 1 cm steps).
        detector: the goal detector (None: the shipped YOLOv8).

    Returns:
        ``{"max_distance", "youden", "fire_inside", "fire_outside", "n_inside",
        "n_outside", "poses", "seed", "thresholds": [one row per threshold]}``.

    Example:
        >>> cal = calibrate_reach_distance(poses=10)   # the shipped detector and MonoDepth
        >>> rule = ReachRule(max_distance=cal["max_distance"])
        >>> 0.28 <= rule.max_distance <= 0.51, len(cal["thresholds"])
        (True, 24)
    """
    if not (isinstance(poses, int) and poses >= 10):
        raise ValueError(f"poses must be an int >= 10, got {poses!r}")
    grid = [x / 100 for x in range(28, 52)] if thresholds is None else [float(t) for t in thresholds]
    if not grid:
        raise ValueError("thresholds must not be empty")
    for t in grid:
        _finite("max_distance", t, 0.05, 3.0, strict_low=True)
    return dict(_threshold_table(_reach_sweep(depth_estimator, detector, poses, seed), grid),
                poses=poses, seed=seed)


def _threshold_table(rows, grid) -> dict:
    """Where a threshold on ``measured_m`` fires, inside and outside the 0.2 m sphere
    (poses without the goal in sight left out), and the best one (Youden's J)."""
    inside = [r for r in rows if r["in_sight"] and r["to_goal_point_m"] <= 0.2]
    outside = [r for r in rows if r["in_sight"] and r["to_goal_point_m"] > 0.2]
    table = []
    for t in grid:
        fin = sum(r["measured_m"] <= t for r in inside) / max(1, len(inside))
        fout = sum(r["measured_m"] <= t for r in outside) / max(1, len(outside))
        table.append({"threshold_m": round(t, 3), "fire_inside": round(fin, 3),
                      "fire_outside": round(fout, 3), "youden": round(fin - fout, 3)})
    best = max(table, key=lambda r: (r["youden"], -r["threshold_m"]))
    return {"max_distance": best["threshold_m"], "youden": best["youden"],
            "fire_inside": best["fire_inside"], "fire_outside": best["fire_outside"],
            "n_inside": len(inside), "n_outside": len(outside), "thresholds": table}


def _reach_sweep(depth_estimator, detector, poses: int, seed: int) -> list[dict]:
    """One row per pose: distance to the goal point, goal in sight, measured goal distance."""
    import torch
    from tensordict import TensorDict

    from ..perception.dataset import _quat
    from ..perception.depth import MonoDepth
    from ..transforms import make_causal_transforms
    from .drone import DroneNavEnv

    env = DroneNavEnv("thesis", image_size=(240, 320), seed=0)
    try:
        env.reset()
        lay = env.layout
        gp, gc = np.array(lay.goal_point()), np.array(lay.goal_center)
        normal = (gp - gc)[:2] / np.linalg.norm((gp - gc)[:2])
        side = np.array([-normal[1], normal[0]])
        stack = make_causal_transforms(
            env, perception="rgb", detector=detector,
            depth_estimator=MonoDepth.load() if depth_estimator is None else depth_estimator)
        rng = np.random.default_rng(seed)
        qa = env.ids.qpos_adr
        rows = []
        for _ in range(poses):
            ahead, lat = rng.uniform(-0.35, 0.45), rng.uniform(-0.25, 0.25)
            yaw = math.degrees(math.atan2(-normal[1], -normal[0])) + rng.uniform(-15, 15)
            xy = gp[:2] + ahead * normal + lat * side
            env.data.qpos[qa:qa + 3] = (xy[0], xy[1], gp[2])
            env.data.qpos[qa + 3:qa + 7] = _quat(yaw, 0.0, 0.0)
            obs = env._observe(False, False)
            with torch.no_grad():
                td = stack(TensorDict(dict(obs.items()), []).unsqueeze(0))[0]
            rows.append({"to_goal_point_m": float(math.hypot(ahead, lat)),
                         "in_sight": bool(td["goal_in_sight"].item()),
                         "measured_m": float(td["goal_distance"].item())})
    finally:
        env.close()
    return rows
