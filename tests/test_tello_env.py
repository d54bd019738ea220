"""TelloEnv against the TelloEmulator: specs, the policy interface, safety and every injected fault."""

from __future__ import annotations

import gc
import logging
import time

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from torchrl_causal.envs import DroneNavEnv
from torchrl_causal.envs.tello import (
    ACTION_COMMANDS,
    TelloCommandError,
    TelloEnv,
    TelloSafetyError,
    TelloVideoError,
)
from torchrl_causal.envs.tello_emulator import (
    TelloEmulator,
    TelloFaults,
    djitellopy_ports,
    free_udp_port,
)
from torchrl_causal.perception.goal import SimGoalDetector
from torchrl_causal.schema import ACTION_NAMES

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def emu():
    with TelloEmulator(fps=20, time_scale=20.0, video_size=(240, 320), battery_drain_per_min=0.0) as e:
        yield e


@pytest.fixture(scope="module")
def env(emu):
    e = TelloEnv(emu.client(), detector=emu.sim_detector(),
                 depth_estimator=emu.sim_depth_estimator(), command_timeout=1, takeoff_timeout=3, retries=1,
                 frame_timeout=3.0, before_takeoff=lambda _: emu.reset_world())
    yield e
    e.close()


@pytest.fixture(autouse=True)
def _clean_faults(request):
    yield
    if "emu" in request.fixturenames:
        emu = request.getfixturevalue("emu")
        emu.faults = TelloFaults()
        emu.auto_land_s = 15.0


def _step(env, td, action):
    return env.step(td.set("action", torch.tensor(action)))["next"]


def test_specs_and_observations_match_dronenavenv(env, emu):
    check_env_specs(env)
    td = env.reset()
    ref = DroneNavEnv(seed=0)
    r = ref.reset()
    for a in (0, 6, 4):
        td, r = _step(env, td, a), ref.step(r.set("action", torch.tensor(a)))["next"]
    for key in ("goal_in_sight", "crashed", "reached", "out_of_bounds"):
        assert bool(td[key]) == bool(r[key]), key
    for key in ("goal_distance", "goal_angle", "altitude"):
        assert float(td[key]) == pytest.approx(float(r[key]), abs=0.05), key
    assert torch.equal(td["depth"], r["depth"])  # the sim depth aid renders the same view
    # the measured goal box (EgoMap reads the goal's elevation from it), as DroneNavEnv's
    assert bool(td["goal_in_sight"]) and float(td["goal_box"][3]) > 0
    assert torch.allclose(td["goal_box"], r["goal_box"], atol=1.0)
    assert (td["pixels"].float() - r["pixels"].float()).abs().mean() < 4.0  # H.264 + resize
    assert float(td["reward"]) == pytest.approx(
        100 - float(td["goal_distance"]) - abs(float(td["goal_angle"])), abs=1e-4)
    ref.close()
    env.land()
    assert not emu.flying


def test_action_names_map_to_sdk_commands(env):
    assert len(ACTION_COMMANDS) == len(ACTION_NAMES) == env.action_spec.n
    assert [env.action_command(i) for i in range(8)] == [
        "forward 25", "back 25", "left 25", "right 25", "up 25", "down 25", "ccw 15", "cw 15"]


def test_crash_ends_the_episode_landed(env, emu):
    td = env.reset()
    for _ in range(10):  # straight into the pillar 1.1 m ahead
        td = _step(env, td, 0)
        if td["done"]:
            break
    assert bool(td["crashed"]) and bool(td["terminated"])
    assert float(td["reward"]) == -1000.0
    assert emu.crashed and not emu.flying and not env.flying


def test_geofence_refuses_the_move_without_sending_it(env, emu):
    env.geofence = (-0.3, -0.3, 0.3, 0.3)
    try:
        td = env.reset()
        td = _step(env, td, 0)
        sent = list(env.sent)
        td = _step(env, td, 0)  # would reach x = 0.5 > 0.3
        assert bool(td["out_of_bounds"]) and bool(td["done"])
        assert env.sent[len(sent):] == ["land"]
        assert not emu.flying
    finally:
        env.geofence = (-2.0, -3.0, 5.0, 3.0)


def test_error_replies_are_retried_then_land_with_a_clear_error(env, emu):
    td = env.reset()
    emu.faults.error_prob = 1.0  # every command but land answers 'error'
    with pytest.raises(TelloCommandError, match=r"'forward 25' failed after 2 attempt"):
        _step(env, td, 0)
    assert not emu.flying and not env.flying


def test_no_valid_imu_refuses_takeoff_with_its_message(env, emu):
    emu.faults.no_valid_imu = True
    with pytest.raises(TelloCommandError, match="No valid imu"):
        env.reset()
    assert not emu.flying and not env.flying


def test_low_battery_floor_before_takeoff(env, emu):
    emu.battery = 15.0
    time.sleep(0.25)  # the next state message
    try:
        with pytest.raises(TelloSafetyError, match="battery 15% is below min_battery_takeoff 20%"):
            env.reset()
        assert not emu.flying
    finally:
        emu.battery = 100.0
        time.sleep(0.25)


def test_low_battery_in_flight_truncates_and_lands(env, emu, caplog):
    td = env.reset()
    emu.battery = 8.0
    time.sleep(0.25)
    try:
        with caplog.at_level(logging.WARNING, logger="torchrl_causal.tello"):
            td = _step(env, td, 6)
        assert bool(td["truncated"]) and not bool(td["terminated"])
        assert "below min_battery" in caplog.text
        assert not emu.flying
    finally:
        emu.battery = 100.0
        time.sleep(0.25)


def test_video_stall_lands_with_a_video_error(env, emu):
    td = env.reset()
    emu.faults.video_stalled = True
    with pytest.raises(TelloVideoError, match="no fresh video frame"):
        _step(env, td, 6)
    assert not emu.flying


def test_corrupt_video_still_flies_and_lands(env, emu):
    td = env.reset()
    emu.faults.corrupt_video_prob = 0.3
    for _ in range(3):
        td = _step(env, td, 6)
    assert td["pixels"].shape == (84, 84, 3)
    env.land()
    assert not emu.flying


def test_dropped_and_delayed_replies(env, emu, caplog):
    td = env.reset()
    emu.faults.reply_delay_s = 0.3  # late, within the timeout: just slower
    td = _step(env, td, 6)
    assert not bool(td["done"])
    emu.faults.reply_delay_s = 0.0
    emu.faults.drop_reply_prob = 1.0  # the move runs, its reply is lost: not repeated
    yaw = emu.pose()[3]
    env.takeoff_timeout = 1
    with caplog.at_level(logging.WARNING, logger="torchrl_causal.tello"):
        td = _step(env, td, 6)
        assert emu.pose()[3] == pytest.approx(yaw + 15.0)
        env.land()  # the land reply is lost too: emergency is the last resort
    assert "no reply to 'ccw 15'" in caplog.text
    assert "sending 'emergency'" in caplog.text
    env.takeoff_timeout = 3
    assert env.sent[-1] == "emergency"
    assert not emu.flying


def test_keepalive_prevents_the_auto_land(env, emu):
    emu.auto_land_s = 0.6
    env.keepalive_s = 0.2
    try:
        env.reset()
        time.sleep(1.2)  # the policy thinks; the keepalive keeps the drone up
        assert emu.flying
        assert "keepalive" in env.sent
        env.land()
    finally:
        env.keepalive_s = 5.0


def test_auto_land_without_keepalive_counts_as_crash(env, emu):
    emu.auto_land_s = 0.4
    env.keepalive_s = 1e6
    try:
        td = env.reset()
        time.sleep(0.9)
        assert not emu.flying  # the drone landed by itself
        td = _step(env, td, 6)
        assert bool(td["crashed"]) and bool(td["done"])
    finally:
        env.keepalive_s = 5.0


@pytest.mark.parametrize("exc", [KeyboardInterrupt, RuntimeError])
def test_exception_or_ctrl_c_during_a_step_lands(env, emu, exc):
    td = env.reset()
    real = env.depth_estimator

    def boom(pixels):
        raise exc("interrupted")

    env.depth_estimator = boom
    try:
        with pytest.raises(exc):
            _step(env, td, 6)
    finally:
        env.depth_estimator = real
    assert not emu.flying and not env.flying


class _NoGoal(SimGoalDetector):
    def detect(self, pixels, depth=None, **_):
        return torch.zeros(len(pixels), 0, 4), torch.zeros(len(pixels), 0)


def test_dry_run_prints_commands(capsys):
    env = TelloEnv(dry_run=True, detector=_NoGoal(),
                   depth_estimator=lambda p: torch.full(p.shape[:3], 2.0))
    td = env.reset()
    td = _step(env, td, 7)
    env.close()
    out = capsys.readouterr().out.splitlines()
    assert out == ["[dry-run] command", "[dry-run] takeoff", "[dry-run] cw 15", "[dry-run] land"]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"step_size": 0.1}, "step_size"),
        ({"turn_deg": 400}, "turn_deg"),
        ({"image_size": 16}, "image_size"),
        ({"geofence": (1, -1, 2, 1)}, "geofence"),
        ({"min_height": 3.0}, "min_height"),
        ({"command_timeout": 0.5}, "command_timeout"),
        ({"reward": "bogus"}, "reward"),
        ({"detector": "yolo"}, "detector"),
    ],
)
def test_bad_options_are_named(kwargs, match):
    base = {"dry_run": True, "detector": SimGoalDetector(),
            "depth_estimator": lambda p: torch.ones(p.shape[:3])}
    with pytest.raises(ValueError, match=match):
        TelloEnv(**{**base, **kwargs})


def test_egomap_remembers_the_goal_where_it_does_over_dronenavenv(env, emu):
    """EgoMap over TelloEnv (the emulator's perception aids) keeps the goal where it keeps it
    over DroneNavEnv at the same poses, its height above the camera included: that height
    comes from ``goal_box``, which TelloEnv did not write (the goal then sat at camera
    height on the Tello path, ``goal_memory[3] == 0``)."""
    from torchrl.envs import TransformedEnv

    from torchrl_causal.transforms import EgoMap

    tello = TransformedEnv(env, EgoMap())
    ref = TransformedEnv(DroneNavEnv(seed=0), EgoMap())
    td, r = tello.reset(), ref.reset()
    for a in (4, 0, 4):  # climb above the board's centre, then look at it from there
        td = tello.step(td.set("action", torch.tensor(a)))["next"]
        r = ref.step(r.set("action", torch.tensor(a)))["next"]
        assert bool(td["goal_memory"][0]) and bool(r["goal_memory"][0])
        assert torch.allclose(td["goal_memory"], r["goal_memory"], atol=0.02), (
            td["goal_memory"], r["goal_memory"])
    assert float(r["goal_memory"][3]) < -0.2  # the goal is below the camera now
    ref.close()
    env.land()


def test_takeoff_reads_its_height_from_a_state_record_sent_after_it():
    """The take-off's height comes from a state record sent once the drone is up, not
    from the last record before it (``h: 0``, ``tof`` the ground's). With a slow state
    stream the ``ok`` to ``takeoff`` arrives before any record of the drone in the air;
    read from the stale record, the dead-reckoned height sat on the ground, so the first
    sideways move was refused as below ``min_height`` (or the first step counted
    ``h: 0`` as a crash) and the episode ended at its first step."""
    with TelloEmulator(fps=20, time_scale=20.0, video_size=(240, 320), state_hz=2.0,
                       battery_drain_per_min=0.0) as emu:
        env = TelloEnv(emu.client(), detector=emu.sim_detector(),
                       depth_estimator=emu.sim_depth_estimator(), command_timeout=2,
                       before_takeoff=lambda _: emu.reset_world(), verbose=False)
        try:
            for _ in range(3):  # each take-off after a landing, as between episodes
                td = env.reset()
                assert env._odom[2] == pytest.approx(emu.pose()[2], abs=0.011)
                td = _step(env, td, ACTION_NAMES.index("left"))
                assert not bool(td["done"]) and not bool(td["out_of_bounds"]), td
                env.land()
        finally:
            env.close()



def test_a_new_env_after_close_flies_on_the_same_drone_and_video_port(emu):
    """A second ``TelloEnv`` for the same drone in one process (a notebook's next flight;
    a real Tello always streams to port 11111) flies, even when the first env's
    ``djitellopy.Tello`` is collected after the second was made: djitellopy's ``end()``
    (its ``__del__``) deleted the drone's entry in its process-wide table, and the new
    env's next command raised ``KeyError``. The first reader, blocked in ``demux`` after
    ``streamoff``, ends at the first packet after its ``stop()``."""
    from djitellopy import Tello

    port = free_udp_port()

    def make():  # a plain djitellopy.Tello, as for a real drone (emu.client() protects its own)
        _, state_port = djitellopy_ports()
        emu.set_client_ports(state_port=state_port, video_port=port)
        tello = Tello(host=emu.host, retry_count=1, vs_udp=port)
        tello.address = emu.address
        assert "end" not in vars(tello)
        return TelloEnv(tello, detector=emu.sim_detector(),
                        depth_estimator=emu.sim_depth_estimator(), command_timeout=2,
                        frame_timeout=5.0, before_takeoff=lambda _: emu.reset_world(),
                        verbose=False)

    first = make()
    try:
        first.reset()
    finally:
        first.close()
    old_reader = first._frame_reader
    second = make()
    del first
    gc.collect()  # the first env's Tello goes now, after the second was made
    try:
        td = second.reset()
        td = _step(second, td, ACTION_NAMES.index("turn_left"))
        assert not bool(td["done"])
        assert second._frame_reader.decoded > 0 and second._frame_reader.error is None
    finally:
        second.close()
    old_reader.worker.join(timeout=5.0)
    assert not old_reader.alive
