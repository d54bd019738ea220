"""``TelloEmulator``: a DJI Tello that speaks the Tello SDK over UDP, flown in a :class:`DroneNavEnv`.

Software in the loop for the real-drone path: the exact client code that flies
a Tello (``djitellopy``, unmodified, or any Tello SDK client) talks to this
emulator over real UDP sockets on a loopback address, and sees the MuJoCo scene
of :class:`~torchrl_causal.envs.DroneNavEnv` as a raw H.264 stream.

What it emulates (Tello SDK 2.0/3.0, see :doc:`/tello`):

* **commands** on ``(host, command_port)``: ``command``, ``takeoff``, ``land``,
  ``emergency``, ``streamon``/``streamoff``, ``up/down/left/right/forward/back
  <20..500 cm>``, ``cw/ccw <1..360 deg>``, ``go x y z speed`` (x forward, y left,
  z up, -500..500 cm, not all three within 20 cm; 10..100 cm/s), ``rc a b c d``
  (no reply), ``stop``,
  ``keepalive``, ``speed <cm/s>``, ``port <state> <video>``, ``setfps``,
  ``setbitrate``, ``setresolution``, the read commands ``battery?``,
  ``speed?``, ``time?``, ``height?``, ``tof?``, ``temp?``, ``attitude?``,
  ``baro?``, ``wifi?``, ``sdk?``, ``sn?``. Replies are ``ok``, ``error ...`` or
  a value; a move's ``ok`` comes when the motion has finished (the motion is
  animated in the video at ``speed`` and ``turn_rate``, sped up by
  ``time_scale``); commands received during a motion wait for it.
* **state** (the SDK's text record, non-EDU fields) at ``state_hz`` (10 Hz) to
  the client's address on ``state_port``: ``tof``/``h`` are the drone's height
  above the floor in cm (``h`` is 0 on the ground), ``yaw`` is clockwise
  positive from the take-off heading, ``bat`` drains with flight time.
* **video** after ``streamon``: the onboard camera rendered at ``video_size``
  and ``fps``, encoded by PyAV's libx264 (``ultrafast``, ``zerolatency``, a
  keyframe with SPS/PPS every ``gop`` frames and at every ``streamon``), sent as raw Annex-B H.264 in
  1460-byte datagrams (a frame's last datagram shorter) to ``video_port``.
* **safety behaviour of the real drone**: it lands by itself after
  ``auto_land_s`` (15 s) without any command, and when the battery reaches
  ``auto_land_battery``; a take-off below ``min_takeoff_battery`` is refused;
  a collision stops the motors (the move's reply is ``error Motor stop``, the
  drone drops to the floor).
* **faults** (:class:`TelloFaults`, each one an option, changeable while the
  emulator runs): dropped or delayed replies, ``error`` replies, video stalls
  and corrupt video datagrams, ``error No valid imu``; low battery through the
  ``battery`` option; a client that disappears is answered by the auto-land.

Ports default to free ones (the emulator binds ``host:0``) and are exposed as
attributes; ``host`` defaults to a fresh ``127.0.0.x`` address per emulator, so
several emulators in one process (djitellopy keeps one reply queue per host
address) and in parallel test processes never collide. :meth:`TelloEmulator.client`
returns a ``djitellopy.Tello`` already pointed at the emulator.

All MuJoCo work (motion, rendering, encoding) happens in one simulation
thread, which owns the OpenGL context. :meth:`TelloEmulator.sim_detector` and
:meth:`TelloEmulator.sim_depth_estimator` answer from that thread's current
render: **they are simulation-only test aids** standing in for the RGB-only
detector and monocular depth model, never something a real drone offers.

Command line (fly it with any Tello client)::

    python -m torchrl_causal.envs.tello_emulator --host 127.0.0.2 --command-port 8889

Example:
    >>> from torchrl_causal.envs.tello_emulator import TelloEmulator
    >>> import socket
    >>> with TelloEmulator(fps=5, time_scale=20.0) as emu:
    ...     s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.settimeout(2.0)
    ...     for cmd in (b"command", b"battery?", b"takeoff", b"forward 50"):
    ...         _ = s.sendto(cmd, emu.address); print(s.recvfrom(64)[0].decode())
    ...     round(emu.pose()[0], 2), emu.flying
    ok
    100
    ok
    ok
    (0.5, True)
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import heapq
import itertools
import logging
import math
import os
import queue
import signal
import socket
import threading
import time
from typing import Any, Callable

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from ..perception.goal import GoalDetector, SimGoalDetector  # noqa: E402
from ..perception.video_path import yuv420p_frame  # noqa: E402

__all__ = ["TelloEmulator", "TelloFaults", "DATAGRAM_SIZE", "free_udp_port", "djitellopy_ports"]

LOGGER = logging.getLogger("torchrl_causal.tello_emulator")

#: Size of the video datagrams of a Tello (a frame's last one is shorter).
DATAGRAM_SIZE = 1460
_MOVES = {"forward": (1, 0, 0), "back": (-1, 0, 0), "left": (0, 1, 0), "right": (0, -1, 0),
          "up": (0, 0, 1), "down": (0, 0, -1)}
_host_counter = itertools.count(2)
_host_lock = threading.Lock()


def _next_host() -> str:
    with _host_lock:
        n = next(_host_counter)
    return f"127.0.{(n // 254) % 256}.{n % 254 + 1}" if n >= 254 else f"127.0.0.{n}"


def free_udp_port(host: str = "") -> int:
    """A UDP port that is free on ``host`` right now (bind to port 0, read it, close).

    Example:
        >>> 0 < free_udp_port("127.0.0.1") < 65536
        True
    """
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind((host, 0))
        return int(s.getsockname()[1])
    finally:
        s.close()


def djitellopy_ports() -> tuple[int, int]:
    """djitellopy's process-wide ``(control, state)`` client ports, chosen free if not yet bound.

    djitellopy binds one command socket and one state socket per process, at its
    first ``Tello()``, on ``Tello.CONTROL_UDP_PORT`` and ``Tello.STATE_UDP_PORT``
    (class attributes), and never closes them. Before that first instance this
    sets both to free ports (unless a caller already changed them from the
    defaults 8889/8890); afterwards it returns the ports in use.

    Example:
        >>> control, state = djitellopy_ports()
        >>> control != state
        True
    """
    from djitellopy import Tello, tello as tello_mod

    if not getattr(tello_mod, "threads_initialized", False):
        if Tello.CONTROL_UDP_PORT == 8889 and Tello.STATE_UDP_PORT == 8890:
            Tello.CONTROL_UDP_PORT = free_udp_port()
            state = free_udp_port()
            while state == Tello.CONTROL_UDP_PORT:  # pragma: no cover - vanishingly rare
                state = free_udp_port()
            Tello.STATE_UDP_PORT = state
    return int(Tello.CONTROL_UDP_PORT), int(Tello.STATE_UDP_PORT)


@dataclasses.dataclass
class TelloFaults:
    """Injected faults of a :class:`TelloEmulator`; every field can be changed while it runs.

    Args:
        drop_reply_prob: probability that a reply is not sent (the command
            is still executed).
        reply_delay_s: extra delay of every reply (s, wall clock).
        error_prob: probability that a command (other than ``command``,
            ``land``, ``emergency``, ``rc``) is answered ``error`` and not executed.
        no_valid_imu: ``takeoff`` and every motion command answer
            ``error No valid imu`` (seen on real drones in poor light).
        video_stalled: no video datagram is sent while True.
        corrupt_video_prob: probability that a video datagram gets a few
            random bytes overwritten.
        battery_drain_scale: multiplies the battery drain rate.

    Example:
        >>> TelloFaults(drop_reply_prob=0.5).drop_reply_prob
        0.5
    """

    drop_reply_prob: float = 0.0
    reply_delay_s: float = 0.0
    error_prob: float = 0.0
    no_valid_imu: bool = False
    video_stalled: bool = False
    corrupt_video_prob: float = 0.0
    battery_drain_scale: float = 1.0

    def __post_init__(self):
        for name in ("drop_reply_prob", "error_prob", "corrupt_video_prob"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
                raise ValueError(f"{name} must be in [0, 1], got {v!r}")
        for name in ("reply_delay_s", "battery_drain_scale"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")


@dataclasses.dataclass
class _Motion:
    kind: str  # "move" | "takeoff" | "land"
    delta: tuple  # (forward, left, up, yaw_deg)
    duration: float  # wall seconds
    reply_to: Any
    t0: float = 0.0
    done_frac: float = 0.0
    start_z: float = 0.0


class _SimGoalDetector(GoalDetector):
    """Answers from the emulator's current render (simulation only, a test aid)."""

    def __init__(self, emu: "TelloEmulator", min_pixels: int):
        self.emu = emu
        self.inner = SimGoalDetector(min_pixels)

    def detect(self, pixels, depth=None, **_):
        pixels = torch.as_tensor(pixels)
        B, H, W = pixels.shape[0], pixels.shape[1], pixels.shape[2]
        _, _, box, count = self.emu._aux(H, W)
        gt_box = torch.tensor([box] * B, dtype=torch.float32)
        gt_pixels = torch.full((B,), float(count))
        return self.inner.detect(pixels, gt_box=gt_box, gt_pixels=gt_pixels)


def _check_number(name, value, *, low=None, allow_equal=True, integer=False):
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    ok = ok and math.isfinite(float(value))
    if ok and integer:
        ok = float(value) == int(value)
    if ok and low is not None:
        ok = float(value) >= low if allow_equal else float(value) > low
    if not ok:
        need = "an int" if integer else "a finite number"
        if low is not None:
            need += f" {'>=' if allow_equal else '>'} {low}"
        raise ValueError(f"{name} must be {need}, got {value!r}")


class TelloEmulator:
    """A Tello SDK server (commands, state, H.264 video) flying a :class:`DroneNavEnv`.

    Use it as a context manager (or call :meth:`start` / :meth:`close`). The
    drone starts landed at the layout's start position; ``takeoff`` lifts it to
    ``takeoff_height`` (default: the layout's start height, so a flight starts
    where a :class:`DroneNavEnv` episode starts).

    Args:
        host: address to bind (default: a fresh ``127.0.0.x``).
        command_port: command port (0: a free one; see :attr:`command_port`).
        state_port: where the state is sent (on the client's address); the
            SDK's ``port`` command and :meth:`client` change it.
        video_port: where the video is sent (on the client's address).
        env_options: keyword arguments of the :class:`DroneNavEnv` behind it
            (``layout``, ``layout_seed``, ``execution``...); ``image_size``
            is set from ``video_size``.
        video_size: ``(height, width)`` of the video, e.g. ``(240, 320)``
            (default) or the real drone's ``(720, 960)``; each >= 32 and even.
        fps: video frame rate.
        gop: frames between keyframes (each with SPS/PPS).
        bitrate: encoder bit rate (bit/s).
        state_hz: state messages per second.
        speed: move speed (m/s of emulated time; the SDK's ``speed`` command
            changes it, in cm/s).
        turn_rate: rotation speed (deg/s of emulated time).
        takeoff_s: duration of a take-off and of a landing (emulated s).
        time_scale: emulated seconds per wall-clock second for motions (> 1
            flies faster than real time; tests use 10-50).
        takeoff_height: height after ``takeoff`` (m); None: the layout's start height.
        battery: battery level at start (%).
        battery_drain_per_min: % per emulated minute while flying (a Tello
            flies about 13 min on a charge).
        min_takeoff_battery: ``takeoff`` below this level answers ``error``.
        auto_land_battery: the drone lands by itself at this level.
        auto_land_s: the drone lands after this many wall seconds without a
            command (Tello: 15 s); None: never.
        rc_speed: speed (m/s) of an ``rc`` stick at 100.
        rc_yaw_rate: yaw rate (deg/s) of an ``rc`` yaw stick at 100.
        faults: a :class:`TelloFaults` (or a dict of its fields).
        seed: seeds the fault draws and the env.

    Attributes:
        host, command_port: the SDK address; :attr:`address` is the pair.
        state_port, video_port: current targets on the client's address.
        faults: the live :class:`TelloFaults`.
        log: recent events (``collections.deque`` of strings), also logged
            on the ``torchrl_causal.tello_emulator`` logger.

    Example:
        >>> with TelloEmulator(fps=5) as emu:
        ...     emu.host.startswith("127."), emu.command_port > 0, emu.flying
        (True, True, False)
    """

    def __init__(
        self,
        host: str | None = None,
        *,
        command_port: int = 0,
        state_port: int = 8890,
        video_port: int = 11111,
        env_options: dict | None = None,
        video_size: tuple[int, int] = (240, 320),
        fps: float = 30.0,
        gop: int = 15,
        bitrate: int = 1_000_000,
        state_hz: float = 10.0,
        speed: float = 1.0,
        turn_rate: float = 90.0,
        takeoff_s: float = 2.0,
        time_scale: float = 1.0,
        takeoff_height: float | None = None,
        battery: float = 100.0,
        battery_drain_per_min: float = 7.0,
        min_takeoff_battery: float = 10.0,
        auto_land_battery: float = 5.0,
        auto_land_s: float | None = 15.0,
        rc_speed: float = 1.0,
        rc_yaw_rate: float = 90.0,
        faults: TelloFaults | dict | None = None,
        seed: int = 0,
    ):
        if host is not None and not isinstance(host, str):
            raise ValueError(f"host must be a string address or None, got {host!r}")
        for name, value in (("command_port", command_port), ("state_port", state_port),
                            ("video_port", video_port)):
            _check_number(name, value, low=0, integer=True)
            if value > 65535:
                raise ValueError(f"{name} must be in [0, 65535], got {value!r}")
        if (not isinstance(video_size, (tuple, list)) or len(video_size) != 2
                or not all(isinstance(v, (int, np.integer)) and v >= 32 and v % 2 == 0
                           for v in video_size)):
            raise ValueError(
                f"video_size must be a (height, width) pair of even ints >= 32, got {video_size!r}")
        _check_number("fps", fps, low=0, allow_equal=False)
        _check_number("gop", gop, low=1, integer=True)
        _check_number("bitrate", bitrate, low=10_000, integer=True)
        _check_number("state_hz", state_hz, low=0, allow_equal=False)
        for name, value in (("speed", speed), ("turn_rate", turn_rate), ("takeoff_s", takeoff_s),
                            ("time_scale", time_scale), ("rc_speed", rc_speed),
                            ("rc_yaw_rate", rc_yaw_rate)):
            _check_number(name, value, low=0, allow_equal=False)
        if takeoff_height is not None:
            _check_number("takeoff_height", takeoff_height, low=0, allow_equal=False)
        for name, value in (("battery", battery), ("min_takeoff_battery", min_takeoff_battery),
                            ("auto_land_battery", auto_land_battery)):
            _check_number(name, value, low=0)
            if value > 100:
                raise ValueError(f"{name} must be in [0, 100], got {value!r}")
        _check_number("battery_drain_per_min", battery_drain_per_min, low=0)
        if auto_land_s is not None:
            _check_number("auto_land_s", auto_land_s, low=0, allow_equal=False)
        if faults is None:
            faults = TelloFaults()
        elif isinstance(faults, dict):
            faults = TelloFaults(**faults)
        elif not isinstance(faults, TelloFaults):
            raise ValueError(f"faults must be a TelloFaults, a dict or None, got {faults!r}")
        env_options = dict(env_options or {})
        if "image_size" in env_options:
            raise ValueError("env_options must not set image_size: it is video_size")
        self._env_options = env_options
        self.host = host if host is not None else _next_host()
        self._command_port_opt = int(command_port)
        self.command_port = int(command_port)
        self.state_port = int(state_port)
        self.video_port = int(video_port)
        self.video_size = (int(video_size[0]), int(video_size[1]))
        self.fps = float(fps)
        self.gop = int(gop)
        self.bitrate = int(bitrate)
        self.state_hz = float(state_hz)
        self.speed = float(speed)
        self.turn_rate = float(turn_rate)
        self.takeoff_s = float(takeoff_s)
        self.time_scale = float(time_scale)
        self.takeoff_height = None if takeoff_height is None else float(takeoff_height)
        self.battery = float(battery)
        self.battery_drain_per_min = float(battery_drain_per_min)
        self.min_takeoff_battery = float(min_takeoff_battery)
        self.auto_land_battery = float(auto_land_battery)
        self.auto_land_s = None if auto_land_s is None else float(auto_land_s)
        self.rc_speed = float(rc_speed)
        self.rc_yaw_rate = float(rc_yaw_rate)
        self.faults = faults
        self.seed = int(seed)
        self.log: collections.deque[str] = collections.deque(maxlen=500)

        self._rng = np.random.default_rng(seed)
        self._sock: socket.socket | None = None
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._inbox: queue.Queue = queue.Queue()
        self._calls: queue.Queue = queue.Queue()
        self._client_ip: str | None = None
        # simulation state (owned by the sim thread; read-only snapshots elsewhere)
        self.sdk_mode = False
        self.flying = False
        self.streaming = False
        self.crashed = False
        self.reached = False
        self.closest_goal_m = math.inf  # closest approach to the goal point since take-off
        self.land_offset_m: tuple | None = None  # drone - goal point (m) at the land command
        self.crash_at: tuple | None = None  # the drone's (x, y, z) at its collision (m)
        self._pose = (0.0, 0.0, 0.0, 0.0)
        self._motion: _Motion | None = None
        self._pending: collections.deque = collections.deque()
        self._rc = (0.0, 0.0, 0.0, 0.0)
        self._last_command = time.monotonic()
        self._flight_time = 0.0
        self._takeoff_yaw = 0.0
        self._state_version = 0
        self.frames_sent = 0
        self._force_keyframe = False
        self.datagrams_sent = 0
        self.frame_times: collections.deque = collections.deque(maxlen=10_000)
        self.commands_received = 0

    # ------------------------------------------------------------------ life cycle
    @property
    def address(self) -> tuple[str, int]:
        """``(host, command_port)``: where a client sends its commands."""
        return (self.host, self.command_port)

    def start(self) -> "TelloEmulator":
        """Binds the command socket, starts the threads and waits until the scene is ready."""
        if self._sock is not None:
            return self
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((self.host, self._command_port_opt))
        except OSError as e:
            sock.close()
            raise OSError(f"TelloEmulator cannot bind {self.host}:{self._command_port_opt}: {e}") from e
        sock.settimeout(0.05)
        self._sock = sock
        self.command_port = int(sock.getsockname()[1])
        self._stop.clear()
        for target, name in ((self._receive_loop, "rx"), (self._sim_loop, "sim")):
            t = threading.Thread(target=target, name=f"tello-emu-{name}-{self.host}", daemon=True)
            t.start()
            self._threads.append(t)
        if not self._ready.wait(60.0) or self._error is not None:
            err = self._error
            self.close()
            raise RuntimeError(f"TelloEmulator failed to start: {err!r}") from err
        self._event(f"listening on {self.host}:{self.command_port}")
        return self

    def close(self) -> None:
        """Stops the threads and closes the socket (idempotent)."""
        self._stop.set()
        for t in self._threads:
            t.join(timeout=10.0)
        self._threads = []
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> "TelloEmulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass

    def _event(self, text: str, level: int = logging.INFO) -> None:
        self.log.append(text)
        LOGGER.log(level, "[%s] %s", self.host, text)

    # ------------------------------------------------------------------ clients
    def set_client_ports(self, state_port: int | None = None, video_port: int | None = None):
        """Changes where state and video go (on the client's address), like the SDK's ``port``."""
        if state_port is not None:
            self.state_port = int(state_port)
        if video_port is not None:
            self.video_port = int(video_port)

    def client(self, retry_count: int = 1, video_port: int | None = None):
        """A ``djitellopy.Tello`` pointed at this emulator (not yet connected).

        Sets djitellopy's process-wide ports first (:func:`djitellopy_ports`),
        tells the emulator where the client's state and video sockets are, and
        sets the client's ``address`` to the emulator's command port. Its ``end()``
        (and so its collection) leaves djitellopy's per-address entry in place, so an
        old client collected later does not break a newer one (as ``TelloEnv`` does
        with any ``Tello`` it is given).

        Args:
            retry_count: djitellopy's attempts per control command.
            video_port: the client's video port (default: a free one).
        """
        from djitellopy import Tello

        _, state = djitellopy_ports()
        vport = int(video_port) if video_port is not None else free_udp_port()
        self.set_client_ports(state_port=state, video_port=vport)
        tello = Tello(host=self.host, retry_count=int(retry_count), vs_udp=vport)
        tello.address = (self.host, self.command_port)
        from .tello import _keep_host_registered

        _keep_host_registered(tello)  # collecting it must not unregister a newer client
        return tello

    # ------------------------------------------------------------------ queries
    def pose(self) -> tuple[float, float, float, float]:
        """The drone's ``(x, y, z, yaw_deg)`` in the scene (ground truth)."""
        return self._pose

    def ground_truth(self) -> dict:
        """Simulation ground truth since the last take-off: ``reached`` (the drone passed
        within the env's ``reach_radius`` of the goal point), ``crashed``, ``flying``,
        ``pose``, ``battery``, ``closest_goal_m`` (the closest approach to the goal
        point, m), ``land_offset_m`` (drone minus goal point, x/y/z in m, when
        the ``land`` command came; None before one) and ``crash_at`` (the drone's
        ``(x, y, z)`` at its collision; None without one)."""
        return {"reached": self.reached, "crashed": self.crashed, "flying": self.flying,
                "pose": self._pose, "battery": self.battery,
                "closest_goal_m": self.closest_goal_m, "land_offset_m": self.land_offset_m,
                "crash_at": self.crash_at}

    def reset_world(self, timeout: float = 30.0) -> None:
        """Puts the drone back, landed, at the start of a (new, for random layouts) layout.

        The out-of-band "carry the drone back to the start" between episodes;
        refused while flying.
        """
        self._call("reset", timeout=timeout)

    def sim_detector(self, min_pixels: int = 20) -> GoalDetector:
        """Ground-truth :class:`~torchrl_causal.perception.goal.GoalDetector` (simulation only).

        A **test aid**: it ignores the pixels it is given and answers from the
        emulator's current render at the same image size (the goal's visible
        box by segmentation rendering, confidence 1 with at least
        ``min_pixels`` visible pixels), exactly like
        :class:`~torchrl_causal.perception.goal.SimGoalDetector` in
        :class:`~torchrl_causal.envs.DroneNavEnv`. A real drone needs the
        RGB-only detector.
        """
        return _SimGoalDetector(self, int(min_pixels))

    def sim_depth_estimator(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """Ground-truth depth callable ``uint8 [B, H, W, 3] -> float32 [B, H, W]`` (simulation only).

        A **test aid** like :meth:`sim_detector`: the metric z-depth of the
        emulator's current render at the pixels' size (the centre crop of the
        video with the video's vertical field of view), in place of a
        monocular depth model.
        """

        def depth(pixels) -> torch.Tensor:
            pixels = torch.as_tensor(pixels)
            B, H, W = pixels.shape[0], pixels.shape[1], pixels.shape[2]
            _, d, _, _ = self._aux(H, W)
            return torch.from_numpy(d).unsqueeze(0).expand(B, H, W).clone()

        return depth

    def sim_render(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """The current ``(rgb uint8 [H, W, 3], depth float32 [H, W])`` at the given size,
        rendered with the video's vertical field of view (ground truth, for tests)."""
        rgb, d, _, _ = self._aux(int(height), int(width))
        return rgb, d

    def _aux(self, H: int, W: int):
        if H > self.video_size[0] or W > self.video_size[1]:
            raise ValueError(
                f"sim render size {(H, W)} exceeds video_size {self.video_size}")
        return self._call("aux", (H, W))

    def _call(self, kind, arg=None, timeout: float = 30.0):
        if self._sock is None:
            raise RuntimeError("TelloEmulator is not running (use it as a context manager)")
        done = threading.Event()
        box: dict = {}
        self._calls.put((kind, arg, done, box))
        if not done.wait(timeout):
            raise TimeoutError(f"TelloEmulator did not answer {kind!r} within {timeout} s")
        if "error" in box:
            raise box["error"]
        return box.get("value")

    # ------------------------------------------------------------------ receive thread
    def _receive_loop(self):
        while not self._stop.is_set():
            sock = self._sock
            if sock is None:
                return
            try:
                data, addr = sock.recvfrom(2048)
            except socket.timeout:
                continue
            except OSError:
                return
            self._inbox.put((data, addr, time.monotonic()))

    # ------------------------------------------------------------------ sim thread
    def _sim_loop(self):
        try:
            self._sim_setup()
        except BaseException as e:  # noqa: BLE001 - reported by start()
            self._error = e
            self._ready.set()
            return
        self._ready.set()
        now = time.monotonic()
        next_state = now
        next_frame = now
        last = now
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                dt, last = now - last, now
                self._handle_calls()
                self._handle_inbox(now)
                self._advance(now, dt)
                self._send_due_replies(now)
                if now >= next_state:
                    self._send_state()
                    next_state += 1.0 / self.state_hz
                    if next_state < now:
                        next_state = now + 1.0 / self.state_hz
                if self.streaming and now >= next_frame:
                    self._send_frame()
                    next_frame += 1.0 / self.fps
                    if next_frame < now:
                        next_frame = now + 1.0 / self.fps
                wake = min(next_state, next_frame if self.streaming else now + 0.01, now + 0.005)
                if self._replies:
                    wake = min(wake, self._replies[0][0])
                delay = wake - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
        except BaseException as e:  # noqa: BLE001
            self._error = e
            self._event(f"simulation thread failed: {e!r}", logging.ERROR)
        finally:
            self._sim_teardown()

    def _sim_setup(self):
        from .drone import DroneNavEnv

        opts = {"seed": self.seed, **self._env_options}
        self.env = DroneNavEnv(image_size=self.video_size, **opts)
        self.env.reset()
        self._aux_renderers: dict = {}
        self._aux_cache = None
        self._replies: list = []
        self._reply_seq = itertools.count()
        self._state_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._state_sock.bind((self.host, 0))
        self._video_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._video_sock.bind((self.host, 0))
        self._place_on_start()
        from ..perception.video_path import open_h264_encoder

        H, W = self.video_size
        self._encoder = open_h264_encoder(H, W, bitrate=self.bitrate, gop=self.gop, fps=self.fps)

    def _sim_teardown(self):
        for r in getattr(self, "_aux_renderers", {}).values():
            r.close()
        env = getattr(self, "env", None)
        if env is not None:
            env.close()
        for name in ("_state_sock", "_video_sock"):
            s = getattr(self, name, None)
            if s is not None:
                s.close()

    # -- scene helpers (sim thread only)
    def _ground_z(self) -> float:
        return 0.1

    def _place_on_start(self):
        env = self.env
        x, y, _ = env.layout.start_pos
        yaw = math.radians(env.layout.start_yaw_deg)
        env._executor.reset(x, y, self._ground_z(), yaw)
        self.flying = False
        self._motion = None
        self._pending.clear()
        self._rc = (0.0, 0.0, 0.0, 0.0)
        self._sync_pose()

    def _sync_pose(self):
        x, y, z, yaw = self.env._executor.pose()
        self._pose = (x, y, z, math.degrees(yaw))
        self._state_version += 1
        m = self._motion
        if self.flying and (m is None or m.kind == "move"):  # not while taking off / landing
            self.closest_goal_m = min(self.closest_goal_m, self._goal_offset_norm())

    def _goal_offset(self) -> tuple:
        g = self.env._goal_point
        return tuple(float(self._pose[i] - g[i]) for i in range(3))

    def _goal_offset_norm(self) -> float:
        return math.sqrt(sum(v * v for v in self._goal_offset()))

    def _set_z(self, z: float):
        import mujoco

        x, y, _, yaw = self.env._executor.pose()
        self.env._executor.set_pose(x, y, z, yaw)
        mujoco.mj_kinematics(self.env.model, self.env.data)
        self._sync_pose()

    def _render(self, renderer):
        import mujoco

        m, d = self.env.model, self.env.data
        mujoco.mj_kinematics(m, d)
        mujoco.mj_camlight(m, d)
        return renderer.render(d)

    # -- calls from other threads
    def _handle_calls(self):
        while True:
            try:
                kind, arg, done, box = self._calls.get_nowait()
            except queue.Empty:
                return
            try:
                if kind == "aux":
                    box["value"] = self._aux_render(*arg)
                elif kind == "reset":
                    if self.flying:
                        raise RuntimeError("reset_world() while flying: land first")
                    self.env.reset()
                    self._place_on_start()
                    self.crashed = self.reached = False
                    self._event("world reset: drone at the start, landed")
                elif kind == "fn":  # run a function in the sim thread (benchmarks, tests)
                    box["value"] = arg(self)
            except BaseException as e:  # noqa: BLE001 - handed to the caller
                box["error"] = e
            done.set()

    def _aux_render(self, H, W):
        from .scene import SceneRenderer

        key = (H, W, self._state_version, id(self.env.model))
        if self._aux_cache is not None and self._aux_cache[0] == key:
            return self._aux_cache[1]
        env = self.env
        r = self._aux_renderers.get((H, W))
        if r is None:
            r = SceneRenderer(env.model, H, W, camera=env.ids.camera, max_depth=env.max_depth)
            self._aux_renderers[(H, W)] = r
        elif r.model is not env.model:
            r.set_model(env.model, env.ids.camera)
        rgb, depth = self._render(r)
        mask = r.geom_mask(env.ids.goal_geoms)
        cols = np.flatnonzero(mask.any(0))
        box, count = [0.0, 0.0, 0.0, 0.0], 0
        if cols.size:
            rows = np.flatnonzero(mask.any(1))
            box = [float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)]
            count = int(mask.sum())
        value = (rgb.copy(), depth.copy(), box, count)
        self._aux_cache = (key, value)
        return value

    # -- commands
    def _reply(self, text: str, addr, now: float, force: bool = False):
        f = self.faults
        if not force and f.drop_reply_prob > 0 and self._rng.random() < f.drop_reply_prob:
            self._event(f"fault: reply {text!r} dropped")
            return
        when = now + (f.reply_delay_s if not force else 0.0)
        heapq.heappush(self._replies, (when, next(self._reply_seq), text.encode(), addr))

    def _send_due_replies(self, now: float):
        while self._replies and self._replies[0][0] <= now:
            _, _, data, addr = heapq.heappop(self._replies)
            try:
                self._sock.sendto(data, addr)
            except (OSError, AttributeError):
                pass

    def _handle_inbox(self, now: float):
        while True:
            try:
                data, addr, t = self._inbox.get_nowait()
            except queue.Empty:
                break
            self.commands_received += 1
            self._client_ip = addr[0]
            self._last_command = now
            try:
                text = data.decode("utf-8").strip()
            except UnicodeDecodeError:
                self._reply("error", addr, now)
                continue
            if text == "emergency":  # immediate, even during a motion; no reply (djitellopy reads none)
                self._emergency()
                continue
            if text.startswith("rc "):
                self._rc_command(text)
                continue
            self._pending.append((text, addr))
        while self._motion is None and self._pending:
            text, addr = self._pending.popleft()
            self._command(text, addr, now)

    def _emergency(self):
        self._motion = None
        self._pending.clear()
        if self.flying:
            self._event("emergency: motors stopped, the drone dropped")
        self.flying = False
        self._set_z(self._ground_z())

    def _rc_command(self, text: str):
        parts = text.split()
        try:
            vals = [max(-100, min(100, int(v))) for v in parts[1:5]]
            if len(vals) != 4:
                raise ValueError
        except ValueError:
            self._event(f"bad rc command {text!r} ignored", logging.WARNING)
            return
        self._rc = tuple(float(v) for v in vals)

    def _command(self, text: str, addr, now: float):
        parts = text.split()
        if not parts:
            self._reply("error", addr, now)
            return
        cmd, args = parts[0], parts[1:]
        f = self.faults
        if cmd == "command":
            self.sdk_mode = True
            self._reply("ok", addr, now)
            return
        if not self.sdk_mode:
            self._reply("error Not in SDK mode (send 'command' first)", addr, now)
            return
        if cmd.endswith("?"):
            self._reply(self._read(cmd), addr, now)
            return
        if cmd not in ("land",) and f.error_prob > 0 and self._rng.random() < f.error_prob:
            self._event(f"fault: {text!r} answered 'error'")
            self._reply("error", addr, now)
            return
        motion_cmds = ("takeoff", "up", "down", "left", "right", "forward", "back", "cw", "ccw",
                       "go")
        if f.no_valid_imu and cmd in motion_cmds:
            self._event(f"fault: {text!r} answered 'error No valid imu'")
            self._reply("error No valid imu", addr, now)
            return
        if cmd == "takeoff":
            if self.flying:
                self._reply("error Already flying", addr, now)
            elif self.battery < self.min_takeoff_battery:
                self._event(f"takeoff refused: battery {self.battery:.0f}%")
                self._reply(f"error Battery low ({self.battery:.0f}%)", addr, now)
            else:
                z0 = self.env._executor.pose()[2]
                target = self.takeoff_height or float(self.env.layout.start_pos[2])
                self.crashed = self.reached = False
                self.closest_goal_m, self.land_offset_m, self.crash_at = math.inf, None, None
                self._takeoff_yaw = self._pose[3]
                self._flight_time = 0.0
                self.flying = True
                self._start_motion(_Motion("takeoff", (0.0, 0.0, target - z0, 0.0),
                                           self.takeoff_s, addr, start_z=z0), now)
            return
        if cmd == "land":
            if not self.flying:
                self._reply("ok", addr, now)  # already on the ground
            else:
                self.land_offset_m = tuple(round(v, 3) for v in self._goal_offset())
                z0 = self.env._executor.pose()[2]
                self._start_motion(_Motion("land", (0.0, 0.0, self._ground_z() - z0, 0.0),
                                           self.takeoff_s, addr, start_z=z0), now)
            return
        if cmd in _MOVES or cmd in ("cw", "ccw"):
            if not self.flying:
                self._reply("error Not flying", addr, now)
                return
            lo, hi = (20, 500) if cmd in _MOVES else (1, 360)
            try:
                value = int(args[0])
                if not lo <= value <= hi or len(args) != 1:
                    raise ValueError
            except (ValueError, IndexError):
                self._reply(f"error Out of range: {cmd} takes {lo}..{hi}", addr, now)
                return
            if cmd in _MOVES:
                ux, uy, uz = _MOVES[cmd]
                d = value / 100.0
                delta = (ux * d, uy * d, uz * d, 0.0)
                duration = d / self.speed
            else:
                delta = (0.0, 0.0, 0.0, -value if cmd == "cw" else value)
                duration = value / self.turn_rate
            # the move's noise, drawn once per command from the episode's own generator
            # (DroneNavEnv.episode_noise_seed): the same commands fly the same way
            # however the simulation thread's ticks split the motion
            delta = self.env._executor.noisy_delta(delta, self.env._noise_rng)
            self._start_motion(_Motion("move", delta, duration, addr), now)
            return
        if cmd == "go":  # go x y z speed: x forward, y left, z up (cm), in the body frame
            if not self.flying:
                self._reply("error Not flying", addr, now)
                return
            try:
                x, y, z, v = (int(a) for a in args)
                if not (all(-500 <= c <= 500 for c in (x, y, z)) and 10 <= v <= 100):
                    raise ValueError
            except ValueError:
                self._reply("error Out of range: go takes x y z in -500..500 (cm) and speed "
                            "10..100", addr, now)
                return
            if all(-20 <= c <= 20 for c in (x, y, z)):  # the SDK's rule
                self._reply("error Out of range: x, y and z cannot all be within -20..20",
                            addr, now)
                return
            delta = self.env._executor.noisy_delta((x / 100.0, y / 100.0, z / 100.0, 0.0),
                                                   self.env._noise_rng)
            self._start_motion(_Motion("move", delta, math.sqrt(x * x + y * y + z * z) / v,
                                       addr), now)
            return
        if cmd in ("stop", "keepalive"):
            self._rc = (0.0, 0.0, 0.0, 0.0)
            self._reply("ok", addr, now)
            return
        if cmd == "streamon":
            self.streaming = True
            self._force_keyframe = True  # a client can decode from the first frame it gets
            self._event("video stream on")
            self._reply("ok", addr, now)
            return
        if cmd == "streamoff":
            self.streaming = False
            self._event("video stream off")
            self._reply("ok", addr, now)
            return
        if cmd == "speed":
            try:
                v = int(args[0])
                if not 10 <= v <= 100:
                    raise ValueError
            except (ValueError, IndexError):
                self._reply("error Out of range: speed takes 10..100", addr, now)
                return
            self.speed = v / 100.0
            self._reply("ok", addr, now)
            return
        if cmd == "port":
            try:
                self.set_client_ports(int(args[0]), int(args[1]))
            except (ValueError, IndexError):
                self._reply("error port takes <state port> <video port>", addr, now)
                return
            self._reply("ok", addr, now)
            return
        if cmd in ("setfps", "setbitrate", "setresolution", "downvision", "motoron", "motoroff"):
            self._reply("ok", addr, now)  # accepted; the stream keeps its settings
            return
        self._reply(f"error Unknown command: {cmd}", addr, now)

    def _read(self, cmd: str) -> str:
        x, y, z, yaw = self._pose
        if cmd == "battery?":
            return str(int(self.battery))
        if cmd == "speed?":
            return f"{self.speed * 100:.1f}"
        if cmd == "time?":
            return f"{int(self._flight_time)}s"
        if cmd == "height?":
            return f"{int(round(z * 10)) if self.flying else 0}dm"
        if cmd == "tof?":
            return f"{int(round(z * 1000))}mm"
        if cmd == "temp?":
            return "60~63C"
        if cmd == "attitude?":
            return f"pitch:0;roll:0;yaw:{self._state_yaw()};"
        if cmd == "baro?":
            return f"{z:.2f}"
        if cmd == "wifi?":
            return "90"
        if cmd == "sdk?":
            return "30"
        if cmd == "sn?":
            return "0TQZEMULATOR"
        return f"error Unknown command: {cmd}"

    def _state_yaw(self) -> int:
        d = -(self._pose[3] - self._takeoff_yaw)  # Tello: clockwise positive
        return int(round((d + 180.0) % 360.0 - 180.0))

    def _start_motion(self, motion: _Motion, now: float):
        motion.t0 = now
        motion.duration = motion.duration / self.time_scale
        self._motion = motion
        self._advance(now, 0.0)

    # -- time evolution
    def _advance(self, now: float, dt: float):
        if self.flying:
            self._flight_time += dt * self.time_scale
            drain = self.battery_drain_per_min * self.faults.battery_drain_scale
            self.battery = max(0.0, self.battery - drain * dt * self.time_scale / 60.0)
        m = self._motion
        if m is not None:
            frac = 1.0 if m.duration <= 0 else min(1.0, (now - m.t0) / m.duration)
            if m.kind in ("takeoff", "land"):
                self._set_z(m.start_z + frac * m.delta[2])
            else:
                step = frac - m.done_frac
                if step > 0:
                    delta = tuple(v * step for v in m.delta)
                    out = self.env._executor.execute(delta, None, self.env._goal_point,
                                                     self.env.reach_radius)
                    self._sync_pose()
                    if out.reached:
                        self.reached = True
                    if out.crashed:
                        self._crash(m.reply_to, now)
                        return
            m.done_frac = frac
            if frac >= 1.0:
                self._motion = None
                if m.kind == "land":
                    self.flying = False
                    self._event("landed")
                elif m.kind == "takeoff":
                    self._event("took off")
                self._reply("ok", m.reply_to, now)
        elif self.flying and any(self._rc):
            lr, fb, ud, yw = self._rc
            s = self.rc_speed * dt * self.time_scale / 100.0
            delta = (fb * s, -lr * s, ud * s, -yw * self.rc_yaw_rate * dt * self.time_scale / 100.0)
            out = self.env._executor.execute(delta, self.env._noise_rng, self.env._goal_point,
                                             self.env.reach_radius)
            self._sync_pose()
            self.reached = self.reached or out.reached
            if out.crashed:
                self._crash(None, now)
                return
        # the real drone's own safety
        if self.flying and self._motion is None:
            if self.auto_land_s is not None and now - self._last_command > self.auto_land_s:
                self._event(f"auto-land: no command for {self.auto_land_s:g} s")
                self._set_z(self._ground_z())
                self.flying = False
            elif self.battery <= self.auto_land_battery:
                self._event(f"auto-land: battery {self.battery:.0f}%")
                self._set_z(self._ground_z())
                self.flying = False

    def _crash(self, reply_to, now: float):
        self.crashed = True
        self.flying = False
        self._motion = None
        self._pending.clear()
        self._rc = (0.0, 0.0, 0.0, 0.0)
        x, y, z, _ = self._pose
        self.crash_at = (x, y, z)
        self._event(f"collision at ({x:.2f}, {y:.2f}, {z:.2f}): motors stopped", logging.WARNING)
        self._set_z(self._ground_z())
        if reply_to is not None:
            self._reply("error Motor stop", reply_to, now)

    # -- state and video
    def _send_state(self):
        if self._client_ip is None:
            return
        x, y, z, _ = self._pose
        tof = int(round(z * 100))
        h = tof if self.flying else 0
        bat = int(math.ceil(self.battery)) if self.battery > 0 else 0
        msg = (f"pitch:0;roll:0;yaw:{self._state_yaw()};vgx:0;vgy:0;vgz:0;templ:60;temph:63;"
               f"tof:{tof};h:{h};bat:{bat};baro:{z:.2f};time:{int(self._flight_time)};"
               f"agx:0.00;agy:0.00;agz:-1000.00;\r\n")
        try:
            self._state_sock.sendto(msg.encode("ascii"), (self._client_ip, self.state_port))
        except OSError:
            pass

    def _send_frame(self):
        if self._client_ip is None:
            return
        rgb, _ = self._render(self.env._renderer)
        t_render = time.perf_counter()
        frame = yuv420p_frame(rgb)  # on one thread (perception.video_path.SWS_THREADS)
        frame.pts = self.frames_sent
        if self._force_keyframe:
            from av.video.frame import PictureType

            frame.pict_type = PictureType.I
            self._force_keyframe = False
        packets = self._encoder.encode(frame)
        payload = b"".join(bytes(p) for p in packets)
        self.frame_times.append((self.frames_sent, t_render))
        self.frames_sent += 1
        if not payload or self.faults.video_stalled:
            return
        f = self.faults
        target = (self._client_ip, self.video_port)
        for i in range(0, len(payload), DATAGRAM_SIZE):
            chunk = payload[i:i + DATAGRAM_SIZE]
            if f.corrupt_video_prob > 0 and self._rng.random() < f.corrupt_video_prob:
                b = bytearray(chunk)
                for j in self._rng.integers(0, len(b), size=max(1, len(b) // 100)):
                    b[j] = int(self._rng.integers(0, 256))
                chunk = bytes(b)
            try:
                self._video_sock.sendto(chunk, target)
                self.datagrams_sent += 1
            except OSError:
                pass


# ---------------------------------------------------------------------- command line
def _stop_on_signal(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def main(argv=None) -> int:
    """``python -m torchrl_causal.envs.tello_emulator``: serve until Ctrl-C (or ``kill``)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--host", default="127.0.0.2", help="address to bind (default 127.0.0.2)")
    p.add_argument("--command-port", type=int, default=8889)
    p.add_argument("--state-port", type=int, default=8890, help="client's state port")
    p.add_argument("--video-port", type=int, default=11111, help="client's video port")
    p.add_argument("--layout", default="thesis", help="thesis | random")
    p.add_argument("--video-size", default="720x960", help="HxW, e.g. 240x320 or 720x960")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--time-scale", type=float, default=1.0)
    p.add_argument("--auto-land-s", type=float, default=15.0)
    p.add_argument("--battery", type=float, default=100.0)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    try:
        h, w = (int(v) for v in a.video_size.lower().split("x"))
    except ValueError:
        p.error(f"--video-size must look like 720x960, got {a.video_size!r}")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    # SIGINT (Ctrl-C, kill -INT) and SIGTERM (kill) stop it cleanly. Python installs its
    # KeyboardInterrupt handler only where SIGINT was not ignored at start-up, and a process
    # started in the background or by a worker that ignores SIGINT inherits the ignoring: the
    # server then could not be stopped but by SIGKILL
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _stop_on_signal)
    emu = TelloEmulator(a.host, command_port=a.command_port, state_port=a.state_port,
                        video_port=a.video_port, env_options={"layout": a.layout},
                        video_size=(h, w), fps=a.fps, time_scale=a.time_scale,
                        auto_land_s=a.auto_land_s, battery=a.battery, seed=a.seed)
    with emu:
        print(f"Tello emulator on {emu.host}:{emu.command_port} (state -> client:{emu.state_port}, "
              f"video -> client:{emu.video_port}); Ctrl-C to stop", flush=True)
        try:
            while True:
                time.sleep(0.5)
        except KeyboardInterrupt:
            print("stopping", flush=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
