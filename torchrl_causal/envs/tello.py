"""``TelloEnv``: the real drone (DJI Tello, through ``djitellopy``) as a TorchRL ``EnvBase``, with safety.

The env speaks the same language as :class:`~torchrl_causal.envs.DroneNavEnv`:
the action is ``Categorical(8)`` in :data:`~torchrl_causal.schema.ACTION_NAMES`
order, mapped to the Tello SDK's ``forward/back/left/right/up/down <cm>`` and
``ccw/cw <deg>`` with the env's step sizes (``step_size`` 0.25 m -> 25 cm,
the Tello's minimum is 20 cm; ``turn_deg`` 15); the observation has the keys the
RGB-only feature stack (:func:`~torchrl_causal.transforms.make_causal_transforms`)
reads: ``pixels`` uint8 ``[H, W, 3]`` (the decoded video frame, centre-cropped to
the aspect of ``image_size`` and resized), ``depth`` float32 ``[H, W]`` (metres,
from ``depth_estimator``), ``altitude`` ``[1]`` (the state's ``tof``, m),
``goal_in_sight`` / ``goal_distance`` / ``goal_angle`` (the
:class:`~torchrl_causal.perception.goal.GoalMeter` of ``detector``, as in
:class:`DroneNavEnv`), ``goal_box`` ``[4]`` (the detector's box in pixels of
``image_size``, zeros when the goal is not in sight; ``DroneNavEnv``'s key of
the same name, from which :class:`~torchrl_causal.transforms.EgoMap` reads the
goal's elevation), ``battery`` ``[1]`` (%), and the outcome flags
``crashed`` / ``reached`` / ``out_of_bounds``.

Perception is pluggable and RGB-only: ``detector`` is any
:class:`~torchrl_causal.perception.goal.GoalDetector` and ``depth_estimator``
any callable ``uint8 [B, H, W, 3] -> float32 [B, H, W]`` (metres). Against the
:class:`~torchrl_causal.envs.tello_emulator.TelloEmulator` the simulator's
ground truth can stand in for both (``emu.sim_detector()``,
``emu.sim_depth_estimator()``; a simulation-only test aid).

Outcomes (no ground truth on a real drone): ``crashed`` when a move is answered
``error Motor stop`` (the Tello's reply when a collision stopped it) or the
drone is found on the ground; ``reached`` when
its :class:`~torchrl_causal.envs.reach.ReachRule` says so (distance, bearing, the
height sensor against the goal's height); ``out_of_bounds`` when a move would
leave the geofence or the height limits (the move is then **not** sent) or the
measured height leaves them. Reward: :mod:`~torchrl_causal.envs.rewards` on
the detector's measurement (``"thesis"``, the default, uses nothing else;
``"progress"`` uses the measured goal distance before and after the step while
the goal is in sight, 0 progress otherwise).

Safety is enforced here, not in scripts (see :doc:`/tello`): battery floors
before take-off and in flight, a geofence in the take-off frame (dead reckoning
of the executed moves) and height limits, command timeouts with retries (moves
are retried only after an explicit ``error`` reply, never after a timeout, when
they may have run), stale replies flushed before each command, a keepalive
while idle in the air, landing at the end of every episode, on any exception
(``KeyboardInterrupt`` included), on :meth:`TelloEnv.close` and at interpreter
exit, ``emergency`` only if landing fails, and ``dry_run`` that prints the
commands instead of sending them.

Example:
    >>> import torch
    >>> from torchrl_causal.envs.tello import TelloEnv
    >>> from torchrl_causal.perception.goal import SimGoalDetector
    >>> class NoGoal(SimGoalDetector):
    ...     def detect(self, pixels, depth=None, **_):
    ...         return torch.zeros(len(pixels), 0, 4), torch.zeros(len(pixels), 0)
    >>> env = TelloEnv(dry_run=True, detector=NoGoal(), verbose=False,
    ...                depth_estimator=lambda p: torch.full(p.shape[:3], 3.0))
    >>> td = env.reset()
    >>> td = env.step(td.set("action", torch.tensor(0)))
    >>> env.sent[-2:], td["next", "reward"].item()
    (['takeoff', 'forward 25'], -9.0)
    >>> env.close(); env.sent[-1]
    'land'
"""

from __future__ import annotations

import atexit
import logging
import math
import threading
import time
import types
import weakref
from typing import Callable

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded
from torchrl.envs import EnvBase

from ..perception.arrival import segment_distance
from ..perception.goal import GoalDetector, GoalMeter, horizontal_fov
from ..perception.video_path import crop_resize
from ..schema import ACTION_NAMES
from .reach import BoardPlaneOffset, FinalApproach, ReachRule
from .rewards import StepOutcome, make_reward
from .specs import navigation_specs

__all__ = ["TelloEnv", "TelloError", "TelloCommandError", "TelloSafetyError", "TelloVideoError",
           "ACTION_COMMANDS"]

LOGGER = logging.getLogger("torchrl_causal.tello")

#: SDK command word of each action, in :data:`~torchrl_causal.schema.ACTION_NAMES` order.
ACTION_COMMANDS: tuple[str, ...] = tuple(
    {"forward": "forward", "backward": "back", "left": "left", "right": "right", "ascend": "up",
     "descend": "down", "turn_left": "ccw", "turn_right": "cw"}[n] for n in ACTION_NAMES)

_OPEN_ENVS: "weakref.WeakSet[TelloEnv]" = weakref.WeakSet()


def _land_all_at_exit():  # pragma: no cover - runs at interpreter exit
    for env in list(_OPEN_ENVS):
        try:
            env.land(reason="interpreter exit")
        except Exception as e:  # noqa: BLE001
            LOGGER.error("atexit landing failed: %r", e)


atexit.register(_land_all_at_exit)


class TelloError(RuntimeError):
    """Base class of the errors of :class:`TelloEnv` (the drone is landed when they propagate).

    Example:
        >>> try:
        ...     raise TelloSafetyError("battery 12 % is below the take-off floor 30 %")
        ... except TelloError as err:
        ...     print(type(err).__name__, "-", err)
        TelloSafetyError - battery 12 % is below the take-off floor 30 %
    """


class TelloCommandError(TelloError):
    """A command failed after its retries (the message names the command and the last reply).

    Example:
        >>> issubclass(TelloCommandError, TelloError), issubclass(TelloCommandError, RuntimeError)
        (True, True)
    """


class TelloSafetyError(TelloError):
    """A safety rule refused to fly (e.g. battery below the take-off floor).

    Example:
        >>> str(TelloSafetyError("height 2.6 m above max_height=2.5"))
        'height 2.6 m above max_height=2.5'
    """


class TelloVideoError(TelloError):
    """No fresh video frame within ``frame_timeout``.

    Example:
        >>> issubclass(TelloVideoError, TelloError)
        True
    """


def _check_geofence(geofence, origin):
    """``(geofence or None, origin)`` as floats; the take-off point must lie inside."""
    if (not isinstance(origin, (tuple, list)) or len(origin) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                       and math.isfinite(v) for v in origin)):
        raise ValueError(f"geofence_origin must be (x, y, yaw_deg), three finite numbers, "
                         f"got {origin!r}")
    origin = tuple(float(v) for v in origin)
    if geofence is None:
        return None, origin
    ox, oy = origin[:2]
    if (not isinstance(geofence, (tuple, list)) or len(geofence) != 4
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                       for v in geofence)
            or not (geofence[0] < ox < geofence[2] and geofence[1] < oy < geofence[3])):
        raise ValueError("geofence must be None or (x_min, y_min, x_max, y_max) around the "
                         f"take-off point {(ox, oy)} (x_min < x < x_max, y_min < y < y_max), "
                         f"got {geofence!r}")
    return tuple(float(v) for v in geofence), origin


def _num(name, value, low=None, strict=False):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if strict else value >= low
    if not ok:
        cond = "" if low is None else f" {'>' if strict else '>='} {low}"
        raise ValueError(f"{name} must be a finite number{cond}, got {value!r}")
    return float(value)


def _keep_host_registered(tello) -> None:
    """Makes this ``djitellopy.Tello``'s ``end()`` (which its ``__del__`` calls) leave the
    drone's entry in djitellopy's process-wide ``drones`` table.

    That entry holds the reply queue and the state records that *every* ``Tello`` object
    of the address reads. djitellopy's ``end()`` deletes it, so an old object collected
    after a new one was made for the same drone (``env = TelloEnv(Tello())`` run twice in
    a notebook, or two flights in one process) broke the new one: its next command or
    state read raised ``KeyError`` (the host), in the air. Other objects are left alone.
    """
    import djitellopy.tello as dt

    if not isinstance(tello, dt.Tello) or "end" in vars(tello):
        return
    plain_end = type(tello).end

    def end(self):
        entry = dt.drones.get(self.address[0])
        try:
            plain_end(self)
        finally:
            if entry is not None:
                dt.drones.setdefault(self.address[0], entry)

    tello.end = types.MethodType(end, tello)


class TelloEnv(EnvBase):
    """A DJI Tello (or a :class:`~torchrl_causal.envs.tello_emulator.TelloEmulator`) as a TorchRL env.

    Unbatched (``batch_size=[]``). The drone is connected, switched to video and
    taken off at the first :meth:`reset`; every episode ends landed.

    Args:
        tello: a ``djitellopy.Tello`` (e.g. ``TelloEmulator.client()``); None:
            ``djitellopy.Tello(host)`` (a real drone) unless ``dry_run``.
        host: the drone's address when ``tello`` is None.
        detector: a :class:`~torchrl_causal.perception.goal.GoalDetector` (RGB only).
        depth_estimator: callable ``uint8 [B, H, W, 3] -> float32 [B, H, W]`` (m).
        image_size: ``int`` or ``(height, width)`` of ``pixels``/``depth`` (>= 32).
        fov_deg: vertical field of view of the (cropped) camera image (deg):
            60 for the emulator's default camera, about 55.6 for a real Tello
            (82.6 deg diagonal, 4:3).
        step_size: metres per move action (>= 0.20, the Tello's minimum).
        turn_deg: degrees per turn action (1..360).
        max_steps: truncation horizon.
        max_depth: depth clip (m).
        reward: ``"thesis"`` (default), ``"progress"`` or a callable of a
            :class:`~torchrl_causal.envs.rewards.StepOutcome`.
        confidence_threshold: detector score needed for ``goal_in_sight``.
        reach_rule: a :class:`~torchrl_causal.envs.reach.ReachRule`: when the
            measured goal counts as reached (default: ``ReachRule()`` with the
            depth estimator's own calibrated range, its ``reach_distance``, when
            it has one (the shipped MonoDepth does), else 0.45 m; goal in sight
            within it and 30 deg; give it ``goal_height`` to check the height
            sensor too, as ``fly_tello.py`` does).
        arrival_head: a :class:`~torchrl_causal.perception.arrival.GoalOffsetEstimator`
            (or any callable: uint8 frames ``[B, H, W, 3]`` -> ``[B, 2]`` offsets
            ``(ahead, lateral)`` in m from the goal point): the rule's ``goal_offset``
            is then read from the camera frame by this learned head (3-D with the
            height sensor's difference, to the segment since the last step's
            estimate) instead of the depth map's board plane; needs a ``reach_rule``
            with ``max_goal_offset`` (docs/tello.rst, "A learned arrival head"). A
            :class:`~torchrl_causal.envs.reach.BoardPlaneOffset` reads the same offset
            from the depth map's board plane instead (any board the rule's
            ``board_width`` describes; docs/tello.rst, "The board plane as the head").
        arrival_fusion: with ``arrival_head``, average the head's ``(ahead, lateral)``
            over consecutive asked steps whose moves did not move the drone across the
            floor (turns, climbs, refused moves): the drone is where it was, so the
            estimates of one place are fused (docs/tello.rst, "Fused over turns").
        climb_reading: with ``arrival_head``, where a climb or descent (no move across the
            floor) puts the step's segment: ``"both"`` (default) between the head's reading
            before the move and the one after it, wherever they lie; ``"nearer"`` at one
            place across the floor, the reading taken nearer the goal point's height (the
            head's training range), swept vertically between the two heights. In the
            2,800 headline emulated episodes with the two-faced board, 31 of the 80 false
            "reached" fired on such a step, its two readings a median 0.30 m apart across
            the floor. With a printed, blank-backed board and ``"nearer"``, 973 of 1,000
            emulated episodes on twenty fresh seeds agreed with the simulator, 0.973
            [0.961, 0.981]; with the two-faced board 982 of 1,000, 0.982 [0.972, 0.989]
            (docs/tello.rst, "Climbs that read a new place"). ``fly_tello.py`` flies
            ``"nearer"`` by default wherever the view head flies (``--climb-reading
            auto``; docs/tello.rst, "The climb reading made the default").
        final_approach: with ``arrival_head``, a
            :class:`~torchrl_causal.envs.reach.FinalApproach` (or its ``radius`` in m):
            when the head puts the goal point within that radius and the rule has not
            fired, the env flies the last leg itself (one SDK ``go x y z speed`` to the
            estimated goal point) within the same step and observes again
            (docs/tello.rst, "A final approach"); None (default): never.
        lost_board: with ``arrival_head``, what a board the detector has just lost
            (within ``hold_radius``) gives for one step: ``"hold"`` (default) asks the
            head on the frame without the detection; ``"carry"`` reads no frame and
            carries the head's last estimate by the drone's dead-reckoned move since,
            turned into the board's frame by ``final_approach``'s fitted heading (needs
            ``final_approach``; docs/tello.rst, "Carrying a lost board"); ``"ask"``
            needs a head that says whether the board is in view
            (:attr:`~torchrl_causal.perception.arrival.GoalOffsetEstimator.in_view`):
            after the head has read the board within ``hold_radius``, it is asked on
            every following frame, with or without a detection, for as long as it says
            the board is in view and within that radius, and a frame it declines gives
            no estimate (docs/tello.rst, "A head that can decline").
        hold_radius: with ``arrival_head``, how near the goal point (m, the head's
            last estimate with the board in sight) a board the detector then loses is
            still held for one step; None (default): twice the rule's
            ``max_goal_offset`` (0.4 m at the 0.2 m rule), or 1.0 m with
            ``lost_board="ask"``. A lower threshold shrinks
            that default below a ``final_approach`` radius, so a board lost after an
            approach from farther out is not held (docs/tello.rst, "The hold and the
            threshold").
        segment_slack: with ``arrival_head``, how much farther apart (m) the head's two
            estimates that bound a step's segment may lie than the drone flew across the
            floor between them. Farther apart, they cannot both be right, and a segment
            drawn between them can sweep through the goal sphere that the drone never
            entered: the step then counts at its current estimate (with the height
            sensor's sweep of a climb) alone. None (default): every segment counts
            (docs/tello.rst, "A head that can decline").
        height_margin: with ``arrival_head``, keep the simulator's sphere for the height:
            the rule's ``max_goal_offset`` is then the head's horizontal bound with this
            margin (m) added back for the height sensor, so a step counts when, along its
            segment, ``sqrt((h + margin)^2 + dz^2) - margin <= max_goal_offset`` (``h``: the
            head's horizontal distance, ``dz``: the height sensor's), and the head is asked
            while ``|dz| <= max_goal_offset + margin``. None (default): the 3-D distance
            with ``dz`` is bounded by ``max_goal_offset`` itself (docs/tello.rst, "A head
            that can decline").
        height_approach: with ``arrival_head`` and ``final_approach``, the head is asked
            also where the height sensor alone puts the drone outside the rule's
            ``max_goal_offset`` (so the rule cannot fire there) but within this height (m)
            of the goal point, and the final approach may then fly the vertical leg too: a
            drone hovering over (or under) the goal point is brought to its height instead
            of being left there. None (default): the head is not asked there, and a drone
            0.13-0.2 m above the goal point is inside the simulator's sphere but never
            told it has arrived. Flown at 0.3 m on twelve emulated seeds it traded missed
            arrivals for false "reached" at equal agreement, so it is off by default
            (docs/tello.rst, "The vertical leg").
        mirror_check: with a learned ``arrival_head`` that has ``estimate_mirrored``
            (:class:`~torchrl_causal.perception.arrival.GoalOffsetEstimator`), ask it on the
            frame and on its mirror image: the estimate is the mean of the two, and a frame
            whose two sideways readings lie more than this (m) apart gives nothing, as a
            frame the head declines does. None (default): one reading of the frame
            (docs/tello.rst, "Asking the head twice").
        look_around: with a learned ``arrival_head``, a turn (deg, 1-45): where the head
            puts the step's segment within ``look_around_radius`` of the goal point, the
            drone turns this far right, then as far left of its heading, then back, asking
            the head at each of the two turned views (with the same checks: the in-view
            output, ``mirror_check``), and the rule decides again on the mean of the
            readings at that place (the head reads the board's frame, whatever the yaw).
            The head's errors at one place differ enough between views 12 deg apart that
            their mean halved the rule's false firings on rendered poses
            (docs/tello.rst, "Looking around before landing"); ``look_arounds`` counts
            the steps it looked around. None (default): one view.
        look_around_radius: the segment distance (m) within which ``look_around`` looks
            (default 0.2, the simulator's sphere; at least the rule's ``max_goal_offset``).
        geofence: ``(x_min, y_min, x_max, y_max)`` (m) in the fence's frame (by
            default the take-off frame: x forward, y left at take-off), checked on
            the dead-reckoned position before each move; None: no geofence.
        geofence_origin: the take-off pose ``(x, y, yaw_deg)`` in the fence's frame
            (default ``(0, 0, 0)``: the fence is given in the take-off frame). An
            emulated layout's arena is a rectangle of the world frame, and its drone
            may start turned: ``fly_tello.py`` passes the arena and the start pose
            (:meth:`set_geofence` changes both between episodes).
        min_height: lowest allowed height (m) for a descend and for the measured height.
        max_height: highest allowed height (m).
        min_battery_takeoff: battery (%) needed to take off.
        min_battery: the episode is truncated (and the drone landed) below this.
        command_timeout: seconds to wait for a reply (whole seconds, djitellopy's unit).
        takeoff_timeout: seconds to wait for ``takeoff``/``land``.
        retries: extra attempts of a failed command.
        frame_timeout: seconds to wait for a fresh video frame after a move.
        fresh_frames: frames decoded after a move's reply before observing
            (covers the frames already in flight).
        settle_s: extra wait after a move before observing (s); a real
            Tello's video lags 0.3 s or more.
        keepalive_s: send ``keepalive`` when no command went out for this long
            while flying (the Tello lands after 15 s); None: off.
        before_takeoff: called as ``before_takeoff(env)`` in every
            :meth:`reset` before the take-off, e.g. ``emu.reset_world`` or a
            prompt to carry the drone back to the start.
        emergency_on_failure: send ``emergency`` (motors off) when landing fails.
        dry_run: print the commands instead of sending them (black frames).
        verbose: in ``dry_run``, print the commands (else only log them).
        device: device of the output tensors.

    Attributes:
        sent: every command sent (or printed), in order.
        flying: whether the env believes the drone is in the air.
        last_frame: the last decoded video frame (RGB, full size) observed.
        approaches: how many final approaches (``go`` commands) this env has flown.

    Example:
        >>> import torch
        >>> from torchrl_causal.perception.goal import SimGoalDetector
        >>> env = TelloEnv(dry_run=True, detector=SimGoalDetector(), verbose=False,
        ...                depth_estimator=lambda p: torch.ones(p.shape[:3]))
        >>> env.action_spec.n, env.observation_spec["pixels"].shape
        (8, torch.Size([84, 84, 3]))
        >>> env.close()
    """

    batch_locked = True

    def __init__(
        self,
        tello=None,
        *,
        host: str = "192.168.10.1",
        detector: GoalDetector,
        depth_estimator: Callable[[torch.Tensor], torch.Tensor],
        image_size: int | tuple[int, int] = 84,
        fov_deg: float = 60.0,
        step_size: float = 0.25,
        turn_deg: float = 15.0,
        max_steps: int = 200,
        max_depth: float = 10.0,
        reward="thesis",
        confidence_threshold: float = 0.7,
        reach_rule: ReachRule | None = None,
        arrival_head: Callable | None = None,
        arrival_fusion: bool = False,
        climb_reading: str = "both",
        final_approach: FinalApproach | float | None = None,
        hold_radius: float | None = None,
        lost_board: str = "hold",
        segment_slack: float | None = None,
        height_margin: float | None = None,
        height_approach: float | None = None,
        mirror_check: float | None = None,
        look_around: float | None = None,
        look_around_radius: float = 0.2,
        geofence: tuple[float, float, float, float] | None = (-2.0, -3.0, 5.0, 3.0),
        geofence_origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
        min_height: float = 0.2,
        max_height: float = 2.5,
        min_battery_takeoff: float = 20.0,
        min_battery: float = 10.0,
        command_timeout: int = 7,
        takeoff_timeout: int = 20,
        retries: int = 2,
        frame_timeout: float = 3.0,
        fresh_frames: int = 2,
        settle_s: float = 0.0,
        keepalive_s: float | None = 5.0,
        before_takeoff: Callable | None = None,
        emergency_on_failure: bool = True,
        dry_run: bool = False,
        verbose: bool = True,
        device=None,
    ):
        if not isinstance(detector, GoalDetector):
            raise ValueError(f"detector must be a GoalDetector, got {detector!r}")
        if not callable(depth_estimator):
            raise ValueError(f"depth_estimator must be a callable, got {depth_estimator!r}")
        if isinstance(image_size, (int, np.integer)) and not isinstance(image_size, bool):
            image_size = (int(image_size), int(image_size))
        if (not isinstance(image_size, (tuple, list)) or len(image_size) != 2
                or not all(isinstance(v, (int, np.integer)) and v >= 32 for v in image_size)):
            raise ValueError(f"image_size must be an int or (height, width), each >= 32, "
                             f"got {image_size!r}")
        if not (isinstance(fov_deg, (int, float)) and 0 < fov_deg < 180):
            raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg!r}")
        _num("step_size", step_size)
        if not 0.2 <= step_size <= 5.0:
            raise ValueError(f"step_size must be in [0.2, 5.0] m (Tello moves 20-500 cm), "
                             f"got {step_size!r}")
        _num("turn_deg", turn_deg)
        if not 1 <= round(turn_deg) <= 360:
            raise ValueError(f"turn_deg must be in [1, 360], got {turn_deg!r}")
        if not isinstance(max_steps, int) or isinstance(max_steps, bool) or max_steps < 1:
            raise ValueError(f"max_steps must be an int >= 1, got {max_steps!r}")
        _num("max_depth", max_depth, 0, strict=True)
        self.reward_fn = make_reward(reward)
        if not (isinstance(confidence_threshold, (int, float)) and 0 <= confidence_threshold <= 1):
            raise ValueError(f"confidence_threshold must be in [0, 1], got {confidence_threshold!r}")
        if reach_rule is None:  # the depth model's own calibrated range, if it has one
            d = getattr(depth_estimator, "reach_distance", None)
            reach_rule = ReachRule() if d is None else ReachRule(max_distance=float(d))
        if not isinstance(reach_rule, ReachRule):
            raise ValueError(f"reach_rule must be a ReachRule or None, got {reach_rule!r}")
        if arrival_head is not None and not callable(arrival_head):
            raise ValueError(f"arrival_head must be a callable or None, got {arrival_head!r}")
        if arrival_head is not None and reach_rule.max_goal_offset is None:
            raise ValueError("arrival_head needs a reach_rule with max_goal_offset (the "
                             "distance to the goal point it estimates is compared with it), "
                             f"got {reach_rule!r}")
        if isinstance(final_approach, (int, float)) and not isinstance(final_approach, bool):
            final_approach = FinalApproach(radius=float(final_approach))
        if final_approach is not None and not isinstance(final_approach, FinalApproach):
            raise ValueError(f"final_approach must be a FinalApproach, a radius (m) or None, "
                             f"got {final_approach!r}")
        if final_approach is not None and arrival_head is None:
            raise ValueError("final_approach flies to the arrival head's estimate of the goal "
                             "point: it needs an arrival_head")
        geofence, geofence_origin = _check_geofence(geofence, geofence_origin)
        _num("min_height", min_height, 0)
        _num("max_height", max_height, 0, strict=True)
        if not min_height < max_height:
            raise ValueError(f"need min_height < max_height, got {min_height!r}, {max_height!r}")
        for name, v in (("min_battery_takeoff", min_battery_takeoff), ("min_battery", min_battery)):
            _num(name, v, 0)
            if v > 100:
                raise ValueError(f"{name} must be in [0, 100], got {v!r}")
        for name, v in (("command_timeout", command_timeout), ("takeoff_timeout", takeoff_timeout)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{name} must be an int >= 1 (seconds), got {v!r}")
        if not isinstance(retries, int) or isinstance(retries, bool) or retries < 0:
            raise ValueError(f"retries must be an int >= 0, got {retries!r}")
        _num("frame_timeout", frame_timeout, 0, strict=True)
        if not isinstance(fresh_frames, int) or fresh_frames < 0:
            raise ValueError(f"fresh_frames must be an int >= 0, got {fresh_frames!r}")
        _num("settle_s", settle_s, 0)
        if keepalive_s is not None:
            _num("keepalive_s", keepalive_s, 0, strict=True)
        if before_takeoff is not None and not callable(before_takeoff):
            raise ValueError(f"before_takeoff must be None or a callable, got {before_takeoff!r}")

        super().__init__(device=device if device is not None else "cpu", batch_size=torch.Size([]))
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.fov_deg = float(fov_deg)
        self.step_cm = int(round(step_size * 100))
        self.turn = int(round(turn_deg))
        self.step_size = self.step_cm / 100.0
        self.turn_deg = float(self.turn)
        self.max_steps = int(max_steps)
        self.max_depth = float(max_depth)
        self.reach_rule = reach_rule
        if hold_radius is not None:
            if arrival_head is None:
                raise ValueError(f"hold_radius={hold_radius!r} holds the arrival head's board: "
                                 "it needs arrival_head")
            hold_radius = _num("hold_radius", hold_radius, 0, strict=True)
        self.hold_radius = hold_radius
        for name, value, does in (("segment_slack", segment_slack, "checks the arrival head's "
                                   "segments"),
                                  ("height_margin", height_margin, "widens the arrival head's "
                                   "rule"),
                                  ("mirror_check", mirror_check, "asks the arrival head twice")):
            if value is not None:
                if arrival_head is None:
                    raise ValueError(f"{name}={value!r} {does}: it needs arrival_head")
                value = _num(name, value, 0)
            setattr(self, name, value)
        if height_approach is not None:
            if final_approach is None:
                raise ValueError(f"height_approach={height_approach!r} lets the final approach "
                                 "fly the vertical leg: it needs final_approach (and "
                                 "arrival_head)")
            height_approach = _num("height_approach", height_approach, 0, strict=True)
        self.height_approach = height_approach
        if mirror_check is not None and not callable(getattr(arrival_head, "estimate_mirrored",
                                                             None)):
            raise ValueError(f"mirror_check={mirror_check!r} asks the arrival head on the frame "
                             "and its mirror image: it needs a learned head with "
                             f"estimate_mirrored (GoalOffsetEstimator), got "
                             f"{type(arrival_head).__name__}")
        if lost_board not in ("hold", "carry", "ask"):
            raise ValueError(f"lost_board must be 'hold', 'carry' or 'ask', got {lost_board!r}")
        if lost_board == "ask" and not getattr(arrival_head, "in_view", False):
            raise ValueError("lost_board='ask' asks the arrival head without the detector: it "
                             "needs a head that says whether the board is in view "
                             "(train_arrival.py --in-view-share), got "
                             f"{type(arrival_head).__name__}")
        if lost_board == "carry" and final_approach is None:
            raise ValueError("lost_board='carry' turns the dead-reckoned move into the board's "
                             "frame with final_approach's fitted heading: it needs "
                             "final_approach")
        self.lost_board = lost_board
        if look_around is not None:
            if arrival_head is None or isinstance(arrival_head, BoardPlaneOffset):
                raise ValueError(f"look_around={look_around!r} asks the arrival head at turned "
                                 "views: it needs a head that reads frames, got "
                                 f"{type(arrival_head).__name__}")
            look_around = _num("look_around", look_around, 1)
            if look_around > 45:
                raise ValueError(f"look_around={look_around!r}: a turn of 1-45 deg keeps the "
                                 "board in view")
            look_around = int(round(look_around))
            look_around_radius = _num("look_around_radius", look_around_radius, 0, strict=True)
            if look_around_radius < (self.reach_rule.max_goal_offset or 0.0):
                raise ValueError(f"look_around_radius={look_around_radius!r} is below the "
                                 "rule's max_goal_offset "
                                 f"({self.reach_rule.max_goal_offset!r}): it would look only "
                                 "at some of the places where the rule fires")
        self.look_around, self.look_around_radius = look_around, look_around_radius
        self.look_arounds = 0
        if not isinstance(arrival_fusion, bool):
            raise ValueError(f"arrival_fusion must be a bool, got {arrival_fusion!r}")
        if climb_reading not in ("both", "nearer"):
            raise ValueError(f"climb_reading must be 'both' or 'nearer', got {climb_reading!r}")
        if climb_reading == "nearer":
            if arrival_head is None or isinstance(arrival_head, BoardPlaneOffset):
                raise ValueError("climb_reading='nearer' keeps one of the arrival head's two "
                                 "readings around a climb: it needs a head that reads frames, "
                                 f"got {type(arrival_head).__name__}")
            if arrival_fusion:
                raise ValueError("climb_reading='nearer' and arrival_fusion=True both decide "
                                 "where a climb's readings put the drone: choose one")
        self.climb_reading = climb_reading
        self.arrival_head = arrival_head
        self._plane = isinstance(arrival_head, BoardPlaneOffset)  # read from depth, not frames
        self.arrival_fusion = arrival_fusion
        self.final_approach = final_approach
        self.approaches = 0
        self._world = np.zeros(2)  # dead reckoning turned by the IMU's yaw (final approach)
        self._yaw = 0.0  # the IMU's yaw (rad, counter-clockwise) at the last observation
        self._forget_arrival()
        self.geofence, self.geofence_origin = geofence, geofence_origin
        self.min_height = float(min_height)
        self.max_height = float(max_height)
        self.min_battery_takeoff = float(min_battery_takeoff)
        self.min_battery = float(min_battery)
        self.command_timeout = int(command_timeout)
        self.takeoff_timeout = int(takeoff_timeout)
        self.retries = int(retries)
        self.frame_timeout = float(frame_timeout)
        self.fresh_frames = int(fresh_frames)
        self.settle_s = float(settle_s)
        self.keepalive_s = None if keepalive_s is None else float(keepalive_s)
        self.before_takeoff = before_takeoff
        self.emergency_on_failure = bool(emergency_on_failure)
        self.dry_run = bool(dry_run)
        self.verbose = bool(verbose)
        self.detector = detector
        self.depth_estimator = depth_estimator
        h, w = self.image_size
        self.hfov_deg = horizontal_fov(self.fov_deg, h, w)
        self.goal_meter = GoalMeter(detector, hfov_deg=self.hfov_deg,
                                    confidence_threshold=float(confidence_threshold),
                                    max_depth=self.max_depth)
        self._make_specs()

        if tello is None and not self.dry_run:
            from djitellopy import Tello

            tello = Tello(host=host, retry_count=1)
        if tello is not None:
            _keep_host_registered(tello)
        self.tello = tello
        self.sent: list[str] = []
        self.last_frame: np.ndarray | None = None
        self.flying = False
        self._connected = False
        self._closed = False
        self._frame_reader = None
        self._lock = threading.RLock()
        self._last_command = time.monotonic()
        self._odom = (0.0, 0.0, 0.0, 0.0)  # x fwd, y left, z, yaw (rad) in the take-off frame
        self._steps = 0
        self._last_move = (0.0, 0.0, 0.0)
        self._prev_distance: float | None = None
        self._state_since = None  # the state record when the last move's reply came
        self._keepalive_stop = threading.Event()
        self._keepalive_thread = None
        _OPEN_ENVS.add(self)

    # ------------------------------------------------------------------ specs
    def _make_specs(self):
        specs = navigation_specs(
            self.image_size, self.max_depth, self.device,
            battery=lambda h, w, dev: Bounded(0.0, 100.0, shape=(1,), dtype=torch.float32,
                                              device=dev),
            # the detector's box, as DroneNavEnv's goal_box: EgoMap reads the goal's
            # elevation from its vertical place
            goal_box=lambda h, w, dev: Bounded(0.0, float(max(h, w)), shape=(4,),
                                               dtype=torch.float32, device=dev),
        )
        for name, spec in specs.items():
            setattr(self, name, spec)

    @property
    def arrival_estimate(self) -> tuple[float, float, float] | None:
        """The arrival head's ``(ahead, lateral, dz)`` (m, the board's frame, from the goal
        point) on the last observed frame, or None where it was not asked (read-only;
        ``fly_tello.py --log-steps`` records it)."""
        est = self._prev_offset
        return None if est is None else tuple(float(v) for v in est)

    # ------------------------------------------------------------------ commands
    def action_command(self, action: int) -> str:
        """The SDK command of ``action``, e.g. ``action_command(0) == "forward 25"``."""
        word = ACTION_COMMANDS[int(action)]
        return f"{word} {self.turn if word in ('cw', 'ccw') else self.step_cm}"

    def _flush(self):
        try:
            self.tello.get_own_udp_object()["responses"].clear()
        except (KeyError, AttributeError):
            pass

    def _send(self, cmd: str, timeout: int | None = None, *, retry_on_timeout: bool = True,
              retries: int | None = None) -> str | None:
        """Sends ``cmd``; returns the reply (``None``: no reply and not retried).

        Retries after an ``error`` reply, and after a timeout when
        ``retry_on_timeout``; ``error Motor stop`` and ``error Not flying``
        (the drone is down) are returned at once.

        Raises:
            TelloCommandError: every attempt failed.
        """
        timeout = int(timeout or self.command_timeout)
        retries = self.retries if retries is None else int(retries)
        with self._lock:
            self.sent.append(cmd)
            self._last_command = time.monotonic()
            if self.dry_run:
                if self.verbose:
                    print(f"[dry-run] {cmd}", flush=True)
                LOGGER.info("[dry-run] %s", cmd)
                return "ok"
            reply = None
            for attempt in range(retries + 1):
                self._flush()  # a late reply of an earlier command must not answer this one
                reply = self.tello.send_command_with_return(cmd, timeout=timeout)
                self._last_command = time.monotonic()
                if reply.startswith("Aborting command"):
                    LOGGER.warning("Tello: no reply to %r within %d s (attempt %d/%d)", cmd,
                                   timeout, attempt + 1, retries + 1)
                    if not retry_on_timeout:
                        return None
                    continue
                low = reply.lower()
                if "motor stop" in low or "not flying" in low:
                    return reply  # final: the drone is down
                if "ok" in low or (cmd.endswith("?") and "error" not in low):
                    return reply
                LOGGER.warning("Tello: %r answered %r (attempt %d/%d)", cmd, reply, attempt + 1,
                               retries + 1)
            raise TelloCommandError(
                f"Tello command {cmd!r} failed after {retries + 1} attempt(s); last reply: {reply!r}")

    def _state(self) -> dict:
        if self.dry_run:
            return {"tof": int(round(self._odom[2] * 100)), "h": int(round(self._odom[2] * 100)),
                    "bat": 100}
        return dict(self.tello.get_own_udp_object().get("state") or {})

    def _state_record(self):
        """The last state record object (djitellopy makes a new one per message)."""
        if self.dry_run:
            return None
        try:
            return self.tello.get_own_udp_object().get("state")
        except (KeyError, AttributeError):
            return None

    def battery(self) -> float:
        """The battery level (%) from the state stream (or ``battery?``)."""
        st = self._state()
        if "bat" in st:
            return float(st["bat"])
        return float(int(self._send("battery?")))

    # ------------------------------------------------------------------ flight
    def _connect(self):
        if self._connected:
            return
        self._send("command")
        if not self.dry_run:
            t0 = time.monotonic()
            while not self._state() and time.monotonic() - t0 < self.command_timeout:
                time.sleep(0.05)
            if not self._state():
                raise TelloCommandError("no state message from the Tello after 'command' "
                                        f"within {self.command_timeout} s")
            self._send("streamon")
            self.tello.stream_on = True
            self._frame_reader = self._open_video()
        self._connected = True
        if self.keepalive_s is not None and not self.dry_run:
            self._keepalive_thread = threading.Thread(target=self._keepalive_loop, daemon=True,
                                                      name="tello-keepalive")
            self._keepalive_thread.start()

    def _keepalive_loop(self):
        while not self._keepalive_stop.wait(0.2):
            if not self.flying or time.monotonic() - self._last_command < self.keepalive_s:
                continue
            if not self._lock.acquire(blocking=False):
                continue
            try:
                self._send("keepalive", timeout=1, retries=0, retry_on_timeout=False)
            except TelloError as e:
                LOGGER.warning("Tello keepalive failed: %s", e)
            finally:
                self._lock.release()

    def land(self, reason: str = "episode end") -> None:
        """Lands if flying (``emergency`` as the last resort when landing fails)."""
        if not self.flying:
            return
        LOGGER.info("Tello: landing (%s)", reason)
        try:
            self._send("land", timeout=self.takeoff_timeout)
        except TelloError as e:
            if self.emergency_on_failure:
                LOGGER.error("Tello: landing failed (%s); sending 'emergency' (motors off)", e)
                with self._lock:
                    self.sent.append("emergency")
                    if not self.dry_run:
                        self.tello.send_command_without_return("emergency")
            else:
                LOGGER.error("Tello: landing failed (%s); the drone may still be flying", e)
                raise
        finally:
            self.flying = False
            if self.tello is not None:
                self.tello.is_flying = False

    def _takeoff(self):
        bat = self.battery()
        if bat < self.min_battery_takeoff:
            raise TelloSafetyError(f"battery {bat:.0f}% is below min_battery_takeoff "
                                   f"{self.min_battery_takeoff:.0f}%: not taking off")
        self.flying = True  # from here on, any failure lands
        self._send("takeoff", timeout=self.takeoff_timeout)
        st = self._airborne_state(self._state_record())
        z = st.get("tof", 0) / 100.0 if st else 1.0
        self._odom = (0.0, 0.0, z if not self.dry_run else 1.0, 0.0)

    def _airborne_state(self, at_reply) -> dict:
        """The state once the take-off's ``ok`` has come: the first record sent after
        ``at_reply`` (the record current at the reply) that shows the drone in the air
        (``h > 0``), waiting up to ``command_timeout``; the latest record if none comes.
        The record current at the reply may predate the take-off (``h: 0``, ``tof`` the
        ground's) when the state stream is slow or the machine busy; read from it, the
        dead-reckoned height sat on the ground and the first move was refused as below
        ``min_height``."""
        if not self.dry_run and not self._await_state(at_reply, self.command_timeout,
                                                       airborne=True):
            LOGGER.warning("Tello: no state record of the drone in the air within %d s of "
                           "the take-off; reading the last one", self.command_timeout)
        return self._state()

    def _await_state(self, since, timeout: float, airborne: bool = False) -> bool:
        """Waits up to ``timeout`` s for a state record other than ``since`` (djitellopy
        makes one per message), showing the drone in the air (``h > 0``) if ``airborne``;
        returns whether one came."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            record = self._state_record()
            if record is not since and (not airborne or float((record or {}).get("h", 0)) > 0):
                return True
            time.sleep(0.005)
        return False

    def _open_video(self):
        from .tello_video import TelloFrameReader

        try:
            return TelloFrameReader.open(self.tello)
        except Exception as e:  # djitellopy's TelloException, PyAV's errors
            raise TelloVideoError(f"cannot open the Tello's video stream: {e}") from e

    # ------------------------------------------------------------------ observation
    def _fresh_frame(self, since) -> np.ndarray:
        if self.dry_run:
            self.last_frame = np.zeros((*self.image_size, 3), np.uint8)
            return self.last_frame
        if self.settle_s:
            time.sleep(self.settle_s)
        reader = self._frame_reader
        if not reader.alive:  # the stream ended (a dropped link): open it again, once
            LOGGER.warning("Tello video: the decoder stopped (%r); reopening the stream", reader.error)
            reader = self._frame_reader = self._open_video()
        seen, last = 0, since
        t0 = time.monotonic()
        while seen < max(1, self.fresh_frames):
            frame = reader.frame
            if frame is not last:
                seen += 1
                last = frame
                continue
            if time.monotonic() - t0 > self.frame_timeout:
                raise TelloVideoError(f"no fresh video frame from the Tello within "
                                      f"{self.frame_timeout:g} s (video stalled?)")
            time.sleep(0.005)
        self.last_frame = np.asarray(last)
        return self.last_frame

    def preprocess(self, frame: np.ndarray) -> torch.Tensor:
        """A decoded RGB frame ``[H0, W0, 3]`` -> ``pixels`` uint8 ``image_size``: centre crop
        to the target aspect, then an antialiased bilinear resize."""
        return crop_resize(frame, self.image_size)

    def measure_frame(self, frame: np.ndarray, altitude: float | None = None) -> dict:
        """The goal measurement of one decoded frame, and whether the reach rule fires.

        For calibrating the :class:`~torchrl_causal.envs.reach.ReachRule` on a real
        drone held (motors off) at known places in front of the board
        (docs/tello.rst, "Field guide"): ``{"in_sight", "distance", "angle", "box",
        "reached", "goal_offset"}`` (``goal_offset``: the rule's estimate of the
        drone's distance to the goal point, when the rule uses one, else None);
        ``altitude`` (m) defaults to the rule's goal height.

        Example:
            >>> import numpy as np, torch
            >>> from torchrl_causal.perception.goal import GoalDetector
            >>> class Centre(GoalDetector):  # "sees" the goal filling the middle of the view
            ...     def detect(self, pixels, depth=None, **_):
            ...         return torch.tensor([[[20.0, 20.0, 64.0, 64.0]]]), torch.tensor([[0.9]])
            >>> env = TelloEnv(dry_run=True, detector=Centre(), verbose=False,
            ...                depth_estimator=lambda p: torch.full(p.shape[:3], 0.4))
            >>> m = env.measure_frame(np.zeros((720, 960, 3), np.uint8))
            >>> m["in_sight"], round(m["distance"], 2), m["reached"]
            (True, 0.4, True)
            >>> env.close()
        """
        pixels = self.preprocess(frame)
        self._forget_arrival()  # one frame alone: no segment
        depth = torch.as_tensor(self.depth_estimator(pixels.unsqueeze(0)), dtype=torch.float32)
        depth = depth.reshape(1, *self.image_size).clamp(0.0, self.max_depth)
        meas = self.goal_meter(pixels.unsqueeze(0), depth)
        in_sight = bool(meas.in_sight[0])
        out = {"in_sight": in_sight,
               "distance": float(meas.distance[0]) if in_sight else float("nan"),
               "angle": float(meas.angle[0]) if in_sight else 0.0,
               "box": [float(v) for v in meas.box[0].tolist()]}
        rule = self.reach_rule
        alt = altitude if altitude is not None else (rule.goal_height or 0.0)
        out["goal_offset"] = self._goal_offset(in_sight, depth[0], out["box"], alt, frame,
                                               out["distance"])
        out["reached"] = rule(in_sight=in_sight, distance=out["distance"], angle=out["angle"],
                              box=out["box"], width=self.image_size[1], altitude=alt,
                              goal_offset=out["goal_offset"])
        return out

    def _forget_arrival(self) -> None:
        """Drops what the arrival rule carries from step to step (a new episode, or one
        frame measured alone)."""
        self._prev_offset = None  # the arrival head's last (ahead, lateral, dz), for the segment
        self._prev_seen = False  # that estimate came with the board in the detector's sight
        self._prev_world = None  # the dead-reckoned (x, y) where that estimate was read
        self._prev_dz = None  # the height sensor's offset from the goal height, last step
        self._prev_sighted = False  # the detector saw the board within range, last step
        self._fused = None  # (sum of (ahead, lateral), count) of the head's looks at one place
        self._asked = None  # this step's head segment (start, end), for look_around
        self._rule_args = None  # the reach rule's inputs of this step, but the offset
        if self.final_approach is not None:
            self.final_approach.reset()
        if getattr(self, "_plane", False):
            self.arrival_head.reset()

    def _goal_offset(self, in_sight: bool, depth, box, altitude: float,
                     frame=None, distance: float | None = None) -> float | None:
        """The reach rule's goal-point offset estimate (only when the rule uses it): from
        the arrival head on ``frame`` when there is one, else from the depth map. The head
        is asked only within the rule's range (``distance``) and when the height sensor does
        not already put the drone outside ``max_goal_offset`` (where it was trained); the
        3-D segment starts at the last step's estimate only if that one was asked too.

        A board the detector loses right after the head was asked with it in sight and
        put the drone within twice ``max_goal_offset`` of the goal point (there the board
        fills the view and the detector's recall falls) is still the board in front: the
        head is asked for that one step more, never for two in a row without a
        detection. A climb or descent (no move across the floor) sweeps the
        heights between two steps: the height sensor's gate then looks at the nearest
        of them, the segment runs vertically from the last height, and a board sighted
        within range one step before is held even if the head was not asked there."""
        if self.arrival_head is not None:
            rule = self.reach_rule
            prev, self._prev_offset = self._prev_offset, None
            # held only near the goal point (within twice the rule's radius), where the
            # board fills the view and the detector loses it; farther out a lost board is
            # one the camera turned or flew away from, and the head, asked on a frame
            # without it, read "at the goal point" 0.5-0.9 m off it (docs/tello.rst)
            ask = self.lost_board == "ask"  # the head says itself whether it sees the board
            hold = ((1.0 if ask else 2 * rule.max_goal_offset) if self.hold_radius is None
                    else self.hold_radius)
            held = (prev is not None and (self._prev_seen or ask)
                    and float(np.linalg.norm(prev)) <= hold)
            self._prev_seen = False
            dz = (altitude - rule.goal_height) if rule.goal_height is not None else 0.0
            # a climb or a descent without a move across the floor sweeps the heights
            # between the last step's and this one's: it may have crossed the goal's
            dz_prev, self._prev_dz = self._prev_dz, dz
            climbed = (dz_prev is not None and bool(self._last_move[2])
                       and not any(self._last_move[:2]))
            # a climb or descent does not turn the camera away: a board sighted within
            # range one step before (even where the height sensor kept the head from being
            # asked) is held too
            sighted, self._prev_sighted = self._prev_sighted, in_sight and (
                distance is None or distance <= rule.max_distance)
            held = held or (climbed and sighted)
            plane = self._plane
            if plane:  # the depth map's board plane: the box of this frame, none held
                held = False
            if held and not in_sight and self.lost_board == "carry" and prev is not None:
                return self._carried(prev, dz)
            if (frame is None and not plane) or (not in_sight and not held) or (
                    in_sight and distance is not None and not distance <= rule.max_distance):
                return None
            if plane:  # read every frame in range: its memory keeps the last view's edge
                look = self.arrival_head(
                    depth.cpu().numpy(), box, self.hfov_deg, board_width=rule.board_width,
                    goal_standoff=rule.goal_standoff, pose=(*self._world, self._yaw))
            nearest = abs(dz)
            if climbed:
                nearest = 0.0 if dz_prev * dz <= 0 else min(abs(dz_prev), abs(dz))
            margin = self.height_margin or 0.0
            if nearest > rule.max_goal_offset + margin and not (  # the height sensor alone:
                    self.height_approach is not None  # outside, unless the vertical leg is
                    and nearest <= self.height_approach):  # flown (the rule cannot fire)
                return nearest
            if plane:
                if look is None:
                    return None
            else:
                look = self._read_head(frame)
                if look is None:
                    return None
            if self.final_approach is not None:
                self.final_approach.record(self._world, look)
            stayed = prev is not None and not any(self._last_move[:2])  # no move across
            if self.arrival_fusion and stayed and self._fused is not None:
                total, n = self._fused
                self._fused = (total + look, n + 1)
                look = self._fused[0] / self._fused[1]
                prev = np.array([look[0], look[1], prev[2]])  # one place, fused: no segment
            else:
                self._fused = (look.copy(), 1)
            cur = np.array([look[0], look[1], dz])
            if prev is None and climbed:  # the same place, swept from the last height
                prev = np.array([look[0], look[1], dz_prev])
            elif climbed and self.climb_reading == "nearer":  # one place across the floor:
                near = prev if abs(prev[2]) <= abs(dz) else cur  # read nearer the goal height
                prev, cur = (np.array([near[0], near[1], prev[2]]),
                             np.array([near[0], near[1], dz]))
            if prev is not None and self.segment_slack is not None and float(
                    np.linalg.norm(cur[:2] - prev[:2])) > math.hypot(
                    *self._last_move[:2]) + self.segment_slack:  # the two cannot both be right
                prev = np.array([cur[0], cur[1], prev[2]])
            self._prev_offset, self._prev_seen = cur, in_sight
            self._prev_world = self._world.copy()
            start = cur if prev is None else prev
            offset = self._segment_offset(start, cur)
            self._asked = (start, cur, offset)  # look_around reads this step's segment again
            return offset
        if not in_sight or self.reach_rule.max_goal_offset is None:
            return None
        return self.reach_rule.goal_offset(depth.cpu().numpy(), box, self.hfov_deg,
                                           moved=self._last_move, altitude=altitude)

    def _segment_offset(self, start, cur) -> float:
        """The rule's offset along the segment ``start`` -> ``cur`` (``(ahead, lateral,
        dz)`` each), with ``height_margin`` for the head's horizontal error only."""
        margin = self.height_margin or 0.0
        if margin:  # the margin for the head's horizontal error only, along the segment
            pts = start[None] + np.linspace(0.0, 1.0, 41)[:, None] * (cur - start)[None]
            return float((np.sqrt((np.hypot(pts[:, 0], pts[:, 1]) + margin) ** 2
                                  + pts[:, 2] ** 2) - margin).min())
        return segment_distance(start, cur)

    def _read_head(self, frame):
        """The learned arrival head's ``(ahead, lateral)`` on one frame, or None where it
        declines (``lost_board="ask"``: its in-view output under 0.5) or is unsure
        (``mirror_check``: the frame's and its mirror image's sideways readings too far
        apart)."""
        frame = np.asarray(frame)[None]
        ask = self.lost_board == "ask"
        if not ask and self.mirror_check is None:
            return np.asarray(self.arrival_head(frame), float).reshape(-1)[:2]
        spread = None
        if self.mirror_check is not None:  # the frame and its mirror image
            look, p_view, spread = self.arrival_head.estimate_mirrored(frame)
        else:
            look, p_view = self.arrival_head.estimate(frame)
        if ask and float(p_view[0]) < 0.5:  # the head declines: no board it can read
            return None
        if spread is not None and float(spread[0]) > self.mirror_check:
            return None  # the two readings disagree: the head is unsure
        return np.asarray(look, float).reshape(-1)[:2]

    def _look_around(self, obs):
        """``look_around``: turns right, left and back at the step's place, asks the head at
        the two turned views and decides the step's arrival again on the mean of the
        readings. Returns ``(obs, crashed)`` (``obs["reached"]`` replaced)."""
        start, cur, _ = self._asked
        one_place = start is cur  # the head was not asked the step before: no segment
        looks, t = [cur[:2]], self.look_around
        for turn, read in ((-t, True), (2 * t, True), (-t, False)):  # cw t, ccw 2t, cw t
            cmd = f"{'ccw' if turn > 0 else 'cw'} {abs(turn)}"
            target = self._moved_pose(0.0, 0.0, 0.0, math.radians(turn))
            since, crashed = self._fly(cmd, target, (0.0, 0.0, 0.0))
            if crashed:
                obs["crashed"][0], obs["reached"][0] = True, False
                return obs, True
            if read:
                look = self._read_head(self._fresh_frame(since))
                if look is not None:
                    looks.append(look)
        self.look_arounds += 1
        mean = np.mean(looks, axis=0)
        cur = np.array([mean[0], mean[1], cur[2]])
        if one_place:
            start = cur
        offset = self._segment_offset(start, cur)
        args = self._rule_args
        if args is None:  # a board held just after the detector lost it
            reached = offset <= self.reach_rule.max_goal_offset
        else:
            reached = self.reach_rule(**args, goal_offset=offset)
        obs["reached"][0] = bool(reached)
        self._prev_offset = cur  # the next step's segment starts at the better reading
        self._last_move = (0.0, 0.0, 0.0)
        return obs, False

    def _carried(self, prev, dz: float) -> float | None:
        """``lost_board="carry"``: the segment from the head's last estimate ``prev`` to
        that estimate moved by the dead-reckoned displacement since it was read, turned
        into the board's frame by the final approach's fitted heading (None without
        one). Nothing is stored: a second step without the board gives nothing."""
        if self._prev_world is None:
            return None
        moved = self.final_approach.carried(prev, self._world - self._prev_world)
        return None if moved is None else segment_distance(prev, np.array([*moved, dz]))

    def _observe(self, frame_since, crashed=False, out_of_bounds=False) -> dict:
        frame = self._fresh_frame(frame_since)
        pixels = self.preprocess(frame)
        depth = torch.as_tensor(self.depth_estimator(pixels.unsqueeze(0)), dtype=torch.float32)
        depth = depth.reshape(1, *self.image_size).clamp(0.0, self.max_depth)
        meas = self.goal_meter(pixels.unsqueeze(0), depth)
        in_sight = bool(meas.in_sight[0])
        dist = float(meas.distance[0]) if in_sight else 0.0
        angle = float(meas.angle[0]) if in_sight else 0.0
        if self.final_approach is not None and self._state_since is not None:
            # the approach turns its dead reckoning by the IMU's yaw: a state record sent
            # before the move ended may hold the yaw before a turn
            self._await_state(self._state_since, timeout=0.5)
        self._state_since = None
        st = self._state()
        alt = float(st.get("tof", st.get("h", 0))) / 100.0 if st else 0.0
        bat = float(st.get("bat", 0.0)) if st else 0.0
        # the Tello's yaw is clockwise-positive degrees; without one, the commanded yaw
        self._yaw = -math.radians(float(st["yaw"])) if st and "yaw" in st else self._odom[3]
        box = meas.box[0].tolist()
        self._asked = None
        offset = None if crashed else self._goal_offset(in_sight, depth[0], box, alt, frame,
                                                        dist)
        if not in_sight and offset is not None:  # the arrival head held a board just lost
            reached = offset <= self.reach_rule.max_goal_offset  # (no offset when crashed)
            self._rule_args = None
        else:
            self._rule_args = dict(in_sight=in_sight, distance=dist, angle=angle, box=box,
                                   width=self.image_size[1], altitude=alt)
            reached = not crashed and self.reach_rule(**self._rule_args, goal_offset=offset)
        f = torch.from_numpy(np.array([in_sight, crashed, reached, out_of_bounds], dtype=np.bool_))
        s = torch.from_numpy(np.array([alt, bat, dist, angle], dtype=np.float32))
        goal_box = torch.tensor(box if in_sight else [0.0] * 4, dtype=torch.float32)
        goal_box = goal_box.clamp(0.0, float(max(self.image_size)))
        return {"pixels": pixels, "depth": depth[0], "altitude": s[0:1], "battery": s[1:2],
                "goal_box": goal_box,
                "goal_in_sight": f[0:1], "goal_distance": s[2:3], "goal_angle": s[3:4],
                "crashed": f[1:2], "reached": f[2:3], "out_of_bounds": f[3:4]}

    def _current_frame(self):
        return None if self._frame_reader is None else self._frame_reader.frame

    # ------------------------------------------------------------------ EnvBase
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        if self._closed:
            raise TelloError("TelloEnv is closed")
        try:
            self._connect()
            self.land(reason="reset")
            if self.before_takeoff is not None:
                self.before_takeoff(self)
            self._takeoff()
            self._steps = 0
            self._prev_distance = None
            self._last_move = (0.0, 0.0, 0.0)
            self._world = np.zeros(2)
            self._forget_arrival()
            obs = self._observe(self._current_frame())
        except BaseException as e:
            self.land(reason=f"exception in reset: {e!r}")
            raise
        self._prev_distance = float(obs["goal_distance"]) if bool(obs["goal_in_sight"]) else None
        false = torch.zeros(1, dtype=torch.bool)
        obs.update(done=false, terminated=false.clone(), truncated=false.clone())
        return TensorDict(obs, batch_size=torch.Size([])).to(self.device)

    def _predicted(self, action: int):
        fwd = left = up = dyaw = 0.0
        name = ACTION_NAMES[action]
        s = self.step_size
        fwd = {"forward": s, "backward": -s}.get(name, 0.0)
        left = {"left": s, "right": -s}.get(name, 0.0)
        up = {"ascend": s, "descend": -s}.get(name, 0.0)
        dyaw = {"turn_left": 1.0, "turn_right": -1.0}.get(name, 0.0) * math.radians(self.turn)
        return self._moved_pose(fwd, left, up, dyaw)

    def _moved_pose(self, fwd: float, left: float, up: float, dyaw: float = 0.0):
        """The dead-reckoned pose after a move ``(forward, left, up)`` (m) in the drone's
        frame and a turn ``dyaw`` (rad)."""
        x, y, z, yaw = self._odom
        c, sn = math.cos(yaw), math.sin(yaw)
        return (x + c * fwd - sn * left, y + sn * fwd + c * left, z + up, yaw + dyaw)

    def _fly(self, cmd: str, target, move) -> tuple[object, bool]:
        """Sends the move ``cmd`` (an action's or the final approach's) and books it:
        ``target`` the dead-reckoned pose after it, ``move`` its ``(right, forward, up)``.
        Returns ``(since, crashed)``: the frame to count fresh frames from (the reply's;
        frames decoded while the move ran may show the drone before it ended, more of
        them under load) and whether the drone answered that it is down."""
        reply = self._send(cmd, retry_on_timeout=False)
        since = self._current_frame()
        self._state_since = self._state_record()
        if reply is not None and ("motor stop" in reply.lower()
                                  or "not flying" in reply.lower()):
            self.flying = False
            self.tello.is_flying = False
            LOGGER.warning("Tello: %r answered %r: crash", cmd, reply)
            return since, True
        self._odom = target
        self._last_move = tuple(move)
        self._dead_reckon(self._last_move)
        return since, False

    def _move_in_camera_frame(self, action: int) -> tuple[float, float, float]:
        """The move of ``action``, ``(right, forward, up)`` in m (the reach rule's
        swept segment)."""
        name, s = ACTION_NAMES[action], self.step_size
        return ({"right": s, "left": -s}.get(name, 0.0),
                {"forward": s, "backward": -s}.get(name, 0.0),
                {"ascend": s, "descend": -s}.get(name, 0.0))

    def _dead_reckon(self, move) -> None:
        """Adds a flown move ``(right, forward, up)`` to the final approach's dead
        reckoning, turned by the IMU's yaw before the move."""
        c, s = math.cos(self._yaw), math.sin(self._yaw)
        fwd, left = move[1], -move[0]
        self._world = self._world + np.array([c * fwd - s * left, s * fwd + c * left])

    def _approach(self, go, obs):
        """Flies the final approach ``go = (forward, left, up)`` (cm) and observes again;
        returns ``(obs, crashed)`` (``obs`` unchanged when the geofence refuses it)."""
        fwd, left, up = (v / 100.0 for v in go)
        target = self._moved_pose(fwd, left, up)
        if not self._inside(target):
            LOGGER.warning("Tello: final approach %s refused, it would leave the geofence/height "
                           "limits", go)
            return obs, False
        self._last_move = (0.0, 0.0, 0.0)  # until the move is flown
        self.approaches += 1
        since, crashed = self._fly(f"go {go[0]} {go[1]} {go[2]} {self.final_approach.speed}",
                                   target, (-left, fwd, up))
        return self._observe(since, crashed=crashed), crashed

    def set_geofence(self, geofence, origin=(0.0, 0.0, 0.0), max_height: float | None = None):
        """Replaces the geofence (and the height limit), e.g. between episodes: the
        arguments of ``geofence``, ``geofence_origin`` and ``max_height``, checked as there.

        Example:
            >>> import torch
            >>> from torchrl_causal.envs.tello import TelloEnv
            >>> from torchrl_causal.perception.goal import SimGoalDetector
            >>> env = TelloEnv(dry_run=True, detector=SimGoalDetector(), verbose=False,
            ...                depth_estimator=lambda p: torch.ones(p.shape[:3]))
            >>> # an arena of the world frame; the drone takes off at (0.2, -2.0), turned 30 deg
            >>> env.set_geofence((-1.2, -3.0, 6.0, 3.0), origin=(0.2, -2.0, 30.0), max_height=2.9)
            >>> env._inside((1.0, 0.0, 1.0, 0.0)), env._inside((0.0, -1.5, 1.0, 0.0))
            (True, False)
            >>> env.close()
        """
        geofence, origin = _check_geofence(geofence, origin)
        if max_height is not None:
            _num("max_height", max_height, 0, strict=True)
            if not self.min_height < max_height:
                raise ValueError(f"need min_height < max_height, got {self.min_height!r}, "
                                 f"{max_height!r}")
            self.max_height = float(max_height)
        self.geofence, self.geofence_origin = geofence, origin

    def _inside(self, pose) -> bool:
        x, y, z, _ = pose
        if not self.min_height <= z <= self.max_height:
            return False
        if self.geofence is None:
            return True
        ox, oy, oyaw = self.geofence_origin
        c, s = math.cos(math.radians(oyaw)), math.sin(math.radians(oyaw))
        x, y = ox + c * x - s * y, oy + s * x + c * y  # the take-off frame -> the fence's
        x0, y0, x1, y1 = self.geofence
        return x0 <= x <= x1 and y0 <= y <= y1

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = int(tensordict.get("action"))
        try:
            if not self.flying:
                raise TelloError("step() while landed: call reset() first")
            self._steps += 1
            target = self._predicted(action)
            self._last_move = (0.0, 0.0, 0.0)  # until the move is flown
            crashed = out_of_bounds = False
            since = self._current_frame()
            if not self._inside(target):
                out_of_bounds = True
                LOGGER.warning("Tello: %r refused, it would leave the geofence/height limits "
                               "(dead-reckoned target x=%.2f y=%.2f z=%.2f)",
                               self.action_command(action), *target[:3])
            else:
                since, crashed = self._fly(self.action_command(action), target,
                                           self._move_in_camera_frame(action))
            obs = self._observe(since, crashed=crashed, out_of_bounds=out_of_bounds)
            if (self.final_approach is not None and not crashed and not out_of_bounds
                    and not bool(obs["reached"]) and self._prev_offset is not None):
                go = self.final_approach.plan(self._prev_offset, self._yaw,
                                              threshold=self.reach_rule.max_goal_offset)
                if go is not None:
                    obs, crashed = self._approach(go, obs)
            if (self.look_around is not None and not crashed and not out_of_bounds
                    and self._asked is not None and self._asked[2] <= self.look_around_radius):
                obs, crashed = self._look_around(obs)
            st = self._state()
            if not crashed and not self.dry_run and st and st.get("h", 1) == 0:
                crashed = True  # on the ground without having been told to land
                self.flying = False
                obs["crashed"][0] = True
                obs["reached"][0] = False
                LOGGER.warning("Tello: the drone is on the ground (state h=0): counted as a crash")
            alt = float(obs["altitude"])
            if not crashed and self.flying and not self.dry_run and not (
                    self.min_height - 0.1 <= alt <= self.max_height + 0.1):
                out_of_bounds = True
                obs["out_of_bounds"][0] = True
                LOGGER.warning("Tello: measured height %.2f m outside [%g, %g]", alt,
                               self.min_height, self.max_height)
            in_sight = bool(obs["goal_in_sight"])
            dist = float(obs["goal_distance"])
            before = self._prev_distance if (in_sight and self._prev_distance is not None) else dist
            reward = self.reward_fn(StepOutcome(
                crashed=crashed, reached=bool(obs["reached"]), out_of_bounds=out_of_bounds,
                in_sight=in_sight, goal_distance=dist, goal_angle=float(obs["goal_angle"]),
                distance_before=before, distance_after=dist))
            self._prev_distance = dist if in_sight else None
            low_battery = float(obs["battery"]) < self.min_battery and not self.dry_run
            if low_battery:
                LOGGER.warning("Tello: battery %.0f%% below min_battery %.0f%%: ending the episode",
                               float(obs["battery"]), self.min_battery)
            terminated = crashed or bool(obs["reached"]) or out_of_bounds
            truncated = not terminated and (self._steps >= self.max_steps or low_battery)
            if terminated or truncated:
                self.land(reason="episode end")
        except BaseException as e:
            self.land(reason=f"exception in step: {e!r}")
            raise
        obs["reward"] = torch.tensor([reward], dtype=torch.float32)
        ends = torch.tensor([terminated, truncated, terminated or truncated])
        obs.update(terminated=ends[0:1], truncated=ends[1:2], done=ends[2:3])
        return TensorDict(obs, batch_size=torch.Size([])).to(self.device)

    def _set_seed(self, seed: int | None) -> None:
        self._seed = seed

    # ------------------------------------------------------------------ closing
    def close(self, *, raise_if_closed: bool = True):
        """Lands, switches the video off and stops the keepalive (idempotent)."""
        if not self._closed:
            self._closed = True
            try:
                self.land(reason="close")
            finally:
                self._keepalive_stop.set()
                if self._connected and not self.dry_run:
                    try:
                        self._send("streamoff", timeout=1, retries=0)
                    except TelloError as e:
                        LOGGER.warning("Tello: streamoff failed: %s", e)
                    if self._frame_reader is not None:
                        self._frame_reader.stop()
                if self.tello is not None:
                    self.tello.stream_on = False
                    self.tello.is_flying = False
                    self.tello.background_frame_read = None
                _OPEN_ENVS.discard(self)
        try:
            super().close(raise_if_closed=False)
        except TypeError:  # pragma: no cover - older signature
            super().close()

    def __enter__(self) -> "TelloEnv":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
