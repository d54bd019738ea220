"""TelloEmulator: the Tello SDK over real UDP sockets on loopback, unmodified djitellopy, real H.264."""

from __future__ import annotations

import gc
import os
import signal
import socket
import subprocess
import sys
import time

import av
import numpy as np
import pytest

from torchrl_causal.envs.tello_emulator import DATAGRAM_SIZE, TelloEmulator, TelloFaults

pytestmark = pytest.mark.timeout(120)


def _udp(timeout=1.0):
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(timeout)
    return s


def _ask(sock, emu, cmd, timeout=2.0):
    sock.settimeout(timeout)
    sock.sendto(cmd.encode(), emu.address)
    try:
        return sock.recvfrom(256)[0].decode()
    except socket.timeout:
        return None


@pytest.fixture(scope="module")
def emu():
    with TelloEmulator(fps=15, time_scale=20.0, video_size=(240, 320)) as e:
        yield e


def test_djitellopy_connect_fly_every_action_video_and_land(emu):
    emu.reset_world()
    tello = emu.client()
    try:
        _fly_every_action(emu, tello)
    finally:
        tello.is_flying = tello.stream_on = False  # no landing attempts at garbage collection


def _fly_every_action(emu, tello):
    tello.connect()
    assert tello.get_battery() == 100
    tello.streamon()
    reader = tello.get_frame_read()
    tello.takeoff()
    assert emu.flying
    time.sleep(0.25)  # a state message after the take-off
    assert tello.get_height() == 100 and tello.get_distance_tof() == 100
    x0, y0, z0, yaw0 = emu.pose()
    goal = np.asarray(emu.env._goal_point, dtype=float)
    gt = emu.ground_truth()
    assert gt["closest_goal_m"] == float("inf") and gt["land_offset_m"] is None  # no move yet
    tello.move_forward(25)
    assert emu.pose()[0] == pytest.approx(x0 + 0.25, abs=1e-6)
    # the goal point lies ahead: the closest approach is where the move ended
    assert goal[0] > x0 + 0.25
    after = np.linalg.norm(np.asarray(emu.pose()[:3]) - goal)
    assert emu.ground_truth()["closest_goal_m"] == pytest.approx(after, abs=1e-6)
    tello.move_back(25)
    tello.move_left(30)
    assert emu.pose()[1] == pytest.approx(y0 + 0.30, abs=1e-6)
    tello.move_right(30)
    tello.move_up(20)
    assert emu.pose()[2] == pytest.approx(z0 + 0.20, abs=1e-6)
    tello.move_down(20)
    tello.rotate_clockwise(15)
    assert emu.pose()[3] == pytest.approx(yaw0 - 15, abs=1e-6)
    time.sleep(0.25)
    assert tello.get_yaw() == 15  # the Tello's yaw is clockwise positive
    tello.rotate_counter_clockwise(15)
    assert emu.pose() == pytest.approx((x0, y0, z0, yaw0), abs=1e-6)
    # rc gets no reply: the next command's reply is still its own
    tello.send_rc_control(0, 0, 0, 0)
    assert abs(tello.query_battery() - emu.battery) <= 1  # (it drains at time_scale 20)
    # a decoded frame matches the simulator's own render within compression error
    time.sleep(0.4)
    frame = reader.frame
    rgb, _ = emu.sim_render(240, 320)
    assert frame.shape == (240, 320, 3)
    err = np.abs(frame.astype(np.float32) - rgb.astype(np.float32)).mean()
    assert err < 4.0, err
    assert np.abs(frame.astype(np.float32) - np.roll(rgb, 40, axis=1)).mean() > 2 * err
    offset = np.asarray(emu.pose()[:3]) - goal
    tello.land()
    assert emu.ground_truth()["land_offset_m"] == pytest.approx(tuple(offset), abs=1e-3)
    assert emu.ground_truth()["closest_goal_m"] == pytest.approx(after, abs=1e-6)
    assert not emu.flying
    # djitellopy's own reader converts frames on swscale worker threads (PyAV >= 17): a process
    # forked while its thread runs (a later test's ParallelEnv in this worker) hangs, so the
    # reader is stopped while frames still arrive (after streamoff its thread would block in
    # decode for good) and its thread joined
    reader.stop()
    reader.worker.join(timeout=10)
    assert not reader.worker.is_alive()
    tello.streamoff()


def test_state_stream_rate_and_format(emu):
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(1.0)
    old = emu.state_port
    emu.set_client_ports(state_port=s.getsockname()[1])
    try:
        # the emulator learns the client's address; a state record may come before the
        # reply (an earlier test already told it where the client is)
        s.sendto(b"command", emu.address)
        reply = s.recvfrom(1024)[0]
        while reply.startswith(b"pitch"):
            reply = s.recvfrom(1024)[0]
        assert reply == b"ok"
        t0, msgs = time.monotonic(), []
        while time.monotonic() - t0 < 1.0:
            data, addr = s.recvfrom(1024)
            if data.startswith(b"pitch"):
                msgs.append(data.decode("ascii"))
                assert addr[0] == emu.host
    finally:
        emu.set_client_ports(state_port=old)
        s.close()
    assert 8 <= len(msgs) <= 12
    from djitellopy import Tello

    st = Tello.parse_state(msgs[-1])
    assert msgs[-1].endswith(";\r\n")
    assert {"pitch", "roll", "yaw", "tof", "h", "bat", "baro", "time", "agz"} <= set(st)
    assert abs(st["bat"] - emu.battery) <= 1 and st["h"] == 0


def test_video_datagrams_are_1460_byte_annex_b_h264(emu):
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(1.0)
    old = emu.video_port
    emu.set_client_ports(video_port=s.getsockname()[1])
    ctl = _udp()
    try:
        assert _ask(ctl, emu, "command") == "ok"
        assert _ask(ctl, emu, "streamon") == "ok"
        sizes, data = [], bytearray()
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.5:
            d, addr = s.recvfrom(4096)
            assert addr[0] == emu.host
            sizes.append(len(d))
            data += d
        assert _ask(ctl, emu, "streamoff") == "ok"
    finally:
        emu.set_client_ports(video_port=old)
        s.close()
        ctl.close()
    assert max(sizes) == DATAGRAM_SIZE
    dec = av.CodecContext.create("h264", "r")
    frames = [f for p in dec.parse(bytes(data)) for f in dec.decode(p)]
    assert len(frames) >= 5  # keyframes carry SPS/PPS: decodable from the first IDR on
    img = frames[-1].to_ndarray(format="rgb24")
    assert img.shape == (240, 320, 3)
    rgb, _ = emu.sim_render(240, 320)
    assert np.abs(img.astype(np.float32) - rgb.astype(np.float32)).mean() < 4.0


def test_protocol_errors_and_faults_on_raw_socket(emu):
    s = _udp()
    try:
        emu.reset_world()
        emu.sdk_mode = False
        assert _ask(s, emu, "takeoff").startswith("error Not in SDK mode")
        assert _ask(s, emu, "command") == "ok"
        assert _ask(s, emu, "forward 25") == "error Not flying"
        assert _ask(s, emu, "takeoff") == "ok"
        assert _ask(s, emu, "forward 10").startswith("error Out of range")
        assert _ask(s, emu, "cw 400").startswith("error Out of range")
        assert _ask(s, emu, "flyaway").startswith("error Unknown command")
        # error replies: the command is not executed
        emu.faults.error_prob = 1.0
        x = emu.pose()[0]
        assert _ask(s, emu, "forward 25") == "error"
        assert emu.pose()[0] == x
        emu.faults.error_prob = 0.0
        # "No valid imu"
        emu.faults.no_valid_imu = True
        assert _ask(s, emu, "up 20") == "error No valid imu"
        emu.faults.no_valid_imu = False
        # dropped reply: the move is executed, no answer comes
        emu.faults.drop_reply_prob = 1.0
        assert _ask(s, emu, "forward 25", timeout=0.5) is None
        assert emu.pose()[0] == pytest.approx(x + 0.25)
        emu.faults.drop_reply_prob = 0.0
        # delayed reply
        emu.faults.reply_delay_s = 0.3
        t0 = time.monotonic()
        assert _ask(s, emu, "battery?").isdigit()
        assert time.monotonic() - t0 >= 0.3
        emu.faults.reply_delay_s = 0.0
        # a collision stops the motors: the pillar of the thesis scene is 1.1 m ahead
        assert _ask(s, emu, "forward 200") == "error Motor stop"
        assert emu.crashed and not emu.flying
        assert any("collision" in line for line in emu.log)
        # where it hit: the drone's centre at the pillar's face, the pillar nearest it
        hit = emu.ground_truth()["crash_at"]
        assert hit is not None and emu.env.layout.nearest_surface(hit)[0] == "obstacle"
        assert emu.env.layout.nearest_surface(hit)[1] < 0.25
    finally:
        emu.faults = TelloFaults()
        s.close()


def test_low_battery_refuses_takeoff_and_auto_lands():
    with TelloEmulator(fps=5, time_scale=20.0, battery=8.0) as e:
        s = _udp()
        assert _ask(s, e, "command") == "ok"
        assert _ask(s, e, "takeoff").startswith("error Battery low")
        assert not e.flying
        e.battery = 12.0
        e.faults.battery_drain_scale = 200.0  # 12% -> 5% within a fraction of a second
        assert _ask(s, e, "takeoff") == "ok"
        t0 = time.monotonic()
        while e.flying and time.monotonic() - t0 < 5.0:
            time.sleep(0.05)
        assert not e.flying
        assert any("auto-land: battery" in line for line in e.log)
        s.close()


def test_client_that_disappears_is_answered_by_auto_land(emu):
    emu.reset_world()
    s = _udp()
    old = emu.auto_land_s
    emu.auto_land_s = 0.5
    try:
        assert _ask(s, emu, "command") == "ok"
        assert _ask(s, emu, "takeoff") == "ok"
        assert emu.flying
        time.sleep(1.0)  # the client is gone
        assert not emu.flying
        assert any("auto-land: no command" in line for line in emu.log)
    finally:
        emu.auto_land_s = old
        s.close()


def test_sim_aids_answer_from_the_current_render(emu):
    import torch

    emu.reset_world()
    det, depth = emu.sim_detector(), emu.sim_depth_estimator()
    px = torch.zeros(2, 84, 84, 3, dtype=torch.uint8)
    boxes, scores = det(px)
    assert boxes.shape == (2, 1, 4) and scores.tolist() == [[1.0], [1.0]]  # goal ahead
    d = depth(px)
    assert d.shape == (2, 84, 84) and d.dtype == torch.float32 and 0 < float(d.min()) <= 10
    with pytest.raises(ValueError, match="exceeds video_size"):
        emu.sim_render(480, 640)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"video_size": (240, 321)}, "video_size"),
        ({"fps": 0}, "fps"),
        ({"battery": 120}, "battery"),
        ({"faults": {"error_prob": 2.0}}, "error_prob"),
        ({"command_port": 70000}, "command_port"),
        ({"env_options": {"image_size": 84}}, "image_size"),
        ({"auto_land_s": -1}, "auto_land_s"),
    ],
)
def test_bad_options_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TelloEmulator(**kwargs)


@pytest.mark.parametrize("stop", ["SIGINT", "SIGTERM"])
def test_command_line_serves_any_client(stop):
    """It serves, and stops cleanly on Ctrl-C or kill -- also when started with SIGINT ignored,
    as a background job or a worker process that ignores it hands down (that hung the test
    in two CI runs)."""
    port = None
    s = _udp(timeout=1.0)
    host = "127.0.0.3"
    from torchrl_causal.envs.tello_emulator import free_udp_port

    port = free_udp_port(host)
    # PYTHONFAULTHANDLER: a SIGABRT prints every thread's stack (the diagnosis of a hang below)
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
           "PYTHONFAULTHANDLER": "1"}
    # SIGINT ignored before the module runs, set by a wrapper rather than a preexec_fn: a
    # preexec_fn runs Python in a fork of this worker, which hangs where a thread of an earlier
    # test still holds PyAV's swscale workers (PyAV >= 17)
    wrapper = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "
               "sys.argv = ['tello_emulator', *sys.argv[1:]]; "
               "runpy.run_module('torchrl_causal.envs.tello_emulator', run_name='__main__')")
    p = subprocess.Popen(
        [sys.executable, "-c", wrapper, "--host", host,
         "--command-port", str(port), "--video-size", "240x320", "--fps", "5"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        lines = []
        while not any(f"{host}:{port}" in ln for ln in lines):
            line = p.stdout.readline()  # log lines first; the banner once it listens
            assert line, "".join(lines)
            lines.append(line)
        s.sendto(b"command", (host, port))
        assert s.recvfrom(64)[0] == b"ok"
        s.sendto(b"sdk?", (host, port))
        assert s.recvfrom(64)[0] == b"30"
    finally:
        p.send_signal(getattr(signal, stop))
        try:
            # about 1.5 s; if it hangs, have it print where it is stuck
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:  # pragma: no cover
            p.send_signal(signal.SIGABRT)
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        s.close()
    out = p.stdout.read()
    assert p.returncode == 0, out[-6000:]
    assert "stopping" in out


def _noisy_flight(seed, time_scale, episodes=2, noise=True):
    """Fly the same commands in ``episodes`` episodes; the true end pose of each."""
    poses = []
    opts = {"position_noise_std": 0.05, "yaw_noise_std_deg": 3.0} if noise else {}
    with TelloEmulator(fps=5, time_scale=time_scale, video_size=(64, 64), seed=seed,
                       env_options=opts) as e:
        s = _udp()
        try:
            for _ in range(episodes):
                e.reset_world()
                assert _ask(s, e, "command") == "ok"
                assert _ask(s, e, "takeoff", timeout=5.0) == "ok"
                for cmd in ("forward 50", "cw 30", "left 40", "up 30", "ccw 45", "forward 20"):
                    assert _ask(s, e, cmd, timeout=5.0) == "ok", cmd
                poses.append(tuple(round(v, 9) for v in e.pose()))
                assert _ask(s, e, "land", timeout=5.0) == "ok"
        finally:
            s.close()
    return poses


def test_move_noise_is_seeded_per_episode_and_independent_of_simulation_ticks():
    """Issue 'Tello parity', seeded noise: the same commands under one seed end at
    the same true pose, whatever the emulator's tick timing (time_scale); another
    episode or another seed draws other noise."""
    a = _noisy_flight(seed=7, time_scale=20.0)
    b = _noisy_flight(seed=7, time_scale=8.0)  # other ticks, other splits of each motion
    c = _noisy_flight(seed=8, time_scale=20.0)
    assert a == b
    assert a[0] != a[1]  # episode 1 has its own noise
    assert a[0] != c[0]
    # near the noise-free flight (six moves of std 0.05 m / 3 deg), but not on it
    clean = _noisy_flight(seed=7, time_scale=20.0, episodes=1, noise=False)[0]
    for noisy in a:
        off = np.linalg.norm(np.subtract(noisy[:3], clean[:3]))
        assert 1e-4 < off < 0.5
        assert 1e-4 < abs(noisy[3] - clean[3]) < 20.0


def test_a_collected_client_leaves_a_newer_one_working(emu):
    """djitellopy's ``Tello.end()``, which its ``__del__`` calls, deletes the drone's entry
    in a process-wide table that every client of that address reads; ``client()`` keeps
    it, so a client collected after a newer one was made (a test's, a notebook's) does
    not break the newer one (``KeyError`` on its next command)."""
    old = emu.client()
    assert old.send_command_with_return("command") == "ok"
    new = emu.client()
    del old
    gc.collect()
    assert new.send_command_with_return("battery?").strip().isdigit()
    new.end()  # and ending one by hand leaves the entry to any later client
    assert emu.client().send_command_with_return("command") == "ok"
