"""The final approach (``torchrl_causal.envs.reach.FinalApproach``): the board's heading
from a noisy history of head estimates and dead-reckoned moves, the SDK's ``go`` in the
real emulator (real UDP, djitellopy, the MuJoCo scene), and ``TelloEnv`` flying the last
leg from the sphere's edge into the goal point."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchrl_causal.envs import FinalApproach, ReachRule, TelloEnv
from torchrl_causal.envs.tello_emulator import TelloEmulator

pytestmark = pytest.mark.timeout(180)


def _rot(a, v):
    c, s = math.cos(a), math.sin(a)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def test_heading_is_recovered_from_noisy_estimates():
    """Random boards and random walks towards them, head estimates with 3 cm noise and
    moves with 5 cm noise (the emulator's): the planned go lands within the goal sphere
    in at least 90 % of 200 seeded trials, and the heading errs by under 10 deg in the
    median."""
    rng = np.random.default_rng(0)
    landed, errs = [], []
    for _ in range(200):
        alpha = rng.uniform(-math.pi, math.pi)  # odometry -> board rotation
        goal_w = rng.uniform(-1, 1, 2)  # the goal point in the odometry frame
        fa = FinalApproach(radius=0.4)
        pos = goal_w + _rot(-alpha, (rng.uniform(0.6, 0.9), rng.uniform(-0.4, 0.4)))
        seen = pos.copy()  # dead reckoning
        yaw = rng.uniform(-math.pi, math.pi)
        for _ in range(3):
            est = _rot(alpha, pos - goal_w) + rng.normal(0, 0.03, 2)
            fa.record(seen, est)
            step = _rot(yaw, (0.25, 0.0))
            if np.linalg.norm(pos + step - goal_w) > np.linalg.norm(pos - goal_w):
                step = (goal_w - pos) / np.linalg.norm(goal_w - pos) * 0.25
            noise = rng.normal(0, 0.05, 2)
            pos, seen = pos + step + noise, seen + step
        true_b = _rot(alpha, pos - goal_w)
        est = true_b + rng.normal(0, 0.03, 2)
        fa.record(seen, est)
        errs.append(abs((fa.heading() - alpha + math.pi) % (2 * math.pi) - math.pi))
        go = fa.plan((est[0], est[1], 0.0), yaw=yaw)
        if go is None:
            continue
        move = _rot(yaw, (go[0] / 100, go[1] / 100)) + rng.normal(0, 0.05, 2)
        a, b = pos - goal_w, pos - goal_w + move
        d = b - a
        t = float(np.clip(-(a @ d) / (d @ d), 0, 1))
        landed.append(float(np.linalg.norm(a + t * d)) <= 0.2)
    assert len(landed) >= 100
    assert np.mean(landed) >= 0.9, np.mean(landed)
    assert np.degrees(np.median(errs)) < 10.0


def test_no_plan_without_a_baseline_beyond_the_radius_or_within_the_rule():
    fa = FinalApproach(radius=0.4)
    assert fa.plan((0.3, 0.0, 0.0), yaw=0.0) is None  # no estimate yet
    fa.record((0.0, 0.0), (0.6, 0.0))
    fa.record((0.1, 0.0), (0.5, 0.0))  # 0.1 m apart: below min_baseline
    assert fa.heading() is None and fa.plan((0.3, 0.0, 0.0), yaw=0.0) is None
    fa.record((0.3, 0.0), (0.3, 0.0))
    assert fa.plan((0.3, 0.0, 0.0), yaw=0.0) == (30, 0, 0)
    assert fa.plan((0.12, 0.0, 0.0), yaw=0.0, threshold=0.15) is None  # the rule fires
    assert fa.plan((0.3, 0.3, 0.0), yaw=0.0) is None  # 0.42 m: beyond the radius
    assert fa.plan((float("nan"), 0.0, 0.0), yaw=0.0) is None
    # every plan is a go the SDK accepts: one axis beyond 20 cm, all within 500
    rng = np.random.default_rng(1)
    for est in rng.uniform(-0.3, 0.3, (500, 3)):
        go = fa.plan(est, yaw=float(rng.uniform(-4, 4)), threshold=0.05)
        if np.linalg.norm(est) <= 0.05 or np.linalg.norm(est) > 0.4:
            assert go is None
            continue
        assert max(abs(c) for c in go) > 20 and all(abs(c) <= 500 for c in go), (est, go)
    fa.reset()
    assert fa.heading() is None


@pytest.mark.parametrize("kwargs, match", [
    ({"radius": 0.0}, "radius must be a number in"),
    ({"radius": 2.0}, "radius must be a number in"),
    ({"radius": "0.4"}, "radius must be a number in"),
    ({"min_baseline": -1.0}, "min_baseline must be a number in"),
    ({"speed": 5}, "speed must be an int in"),
    ({"speed": 30.5}, "speed must be an int in"),
])
def test_bad_options_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FinalApproach(**kwargs)


def test_tello_env_refuses_an_approach_without_a_head():
    from torchrl_causal.perception.goal import SimGoalDetector

    depth = lambda p: torch.ones(p.shape[:3])  # noqa: E731
    with pytest.raises(ValueError, match="final_approach .* needs an arrival_head"):
        TelloEnv(dry_run=True, detector=SimGoalDetector(), depth_estimator=depth,
                 verbose=False, final_approach=0.4)
    with pytest.raises(ValueError, match="final_approach must be a FinalApproach"):
        TelloEnv(dry_run=True, detector=SimGoalDetector(), depth_estimator=depth,
                 verbose=False, reach_rule=ReachRule(max_goal_offset=0.15),
                 arrival_head=lambda f: torch.zeros(len(f), 2), final_approach="near")
    with pytest.raises(ValueError, match="FinalApproach.radius must be"):
        TelloEnv(dry_run=True, detector=SimGoalDetector(), depth_estimator=depth,
                 verbose=False, reach_rule=ReachRule(max_goal_offset=0.15),
                 arrival_head=lambda f: torch.zeros(len(f), 2), final_approach=3.0)
    with pytest.raises(ValueError, match="height_approach=0.3 lets the final approach fly "
                                         "the vertical leg: it needs final_approach"):
        TelloEnv(dry_run=True, detector=SimGoalDetector(), depth_estimator=depth,
                 verbose=False, reach_rule=ReachRule(max_goal_offset=0.15),
                 arrival_head=lambda f: torch.zeros(len(f), 2), height_approach=0.3)
    with pytest.raises(ValueError, match="height_approach must be a finite number > 0"):
        TelloEnv(dry_run=True, detector=SimGoalDetector(), depth_estimator=depth,
                 verbose=False, reach_rule=ReachRule(max_goal_offset=0.15),
                 arrival_head=lambda f: torch.zeros(len(f), 2), final_approach=0.4,
                 height_approach=-0.1)


@pytest.fixture(scope="module")
def emu():
    with TelloEmulator(fps=20, time_scale=20.0, video_size=(240, 320),
                       battery_drain_per_min=0.0) as e:
        yield e


def test_the_emulator_flies_go_in_the_body_frame(emu):
    """``go x y z speed`` moves x forward, y left, z up in the drone's frame (after a
    turn too), and the SDK's range rules are answered with errors."""
    emu.reset_world()
    tello = emu.client()
    try:
        tello.connect()
        tello.takeoff()
        x0, y0, z0, yaw0 = emu.pose()
        tello.go_xyz_speed(30, -20, 20, 50)
        x, y, z, _ = emu.pose()
        assert (x - x0, y - y0, z - z0) == pytest.approx((0.30, -0.20, 0.20), abs=1e-6)
        tello.rotate_counter_clockwise(90)  # now facing +y
        tello.go_xyz_speed(25, 0, 0, 30)
        assert emu.pose()[:2] == pytest.approx((x, y + 0.25), abs=1e-6)
        for cmd in ("go 10 10 10 30", "go 20 -20 0 30", "go 600 0 0 30", "go 30 0 0 5", "go 30 0 0"):
            assert tello.send_command_with_return(cmd).startswith("error Out of range"), cmd
        tello.land()
    finally:
        tello.is_flying = tello.stream_on = False


def test_tello_env_flies_the_last_leg_from_the_spheres_edge(emu):
    """A scripted flight that ends 0.34 m from the goal point, turned 15 deg off the
    board, with a head that reads the emulator's true offset: the rule alone does not
    fire there; with ``final_approach`` the env sends one ``go`` in the same step and
    the episode ends reached, the simulator agreeing (within 5 cm of the goal point)."""
    lay = emu.env.layout
    goal, centre = np.array(lay.goal_point()), np.array(lay.goal_center)
    n = (goal - centre)[:2] / np.linalg.norm((goal - centre)[:2])
    side = np.array([-n[1], n[0]])

    def head(frames):  # the true (ahead, lateral): a test aid, like emu.sim_detector()
        d = np.array(emu.pose()[:2]) - goal[:2]
        return torch.tensor([[float(d @ n), float(d @ side)]] * len(frames))

    rule = ReachRule(max_distance=1.0, max_goal_offset=0.15, goal_height=float(goal[2]))
    env = TelloEnv(emu.client(), detector=emu.sim_detector(),
                   depth_estimator=emu.sim_depth_estimator(), reach_rule=rule,
                   arrival_head=head, final_approach=0.4, command_timeout=2,
                   before_takeoff=lambda _: emu.reset_world(), verbose=False)
    # around the pillar: 0.75 m left, 2 m forward, back 0.5 m right, turn 15 deg, forward
    script = [2] * 3 + [0] * 8 + [3, 3, 7, 0]
    approach = env.final_approach
    try:
        for on in (False, True):
            env.final_approach = approach if on else None
            td = env.reset()
            yaw0 = emu.pose()[3]
            for a in script:
                td = env.step(td.set("action", torch.tensor(a)))["next"]
                assert not bool(td["done"]) or a == script[-1]
                if on:  # the yaw the approach turns by is the state's after the move
                    assert env._yaw == pytest.approx(math.radians(emu.pose()[3] - yaw0),
                                                     abs=0.01), a
            assert not any(c.startswith("go ") for c in env.sent) or on
            if not on:  # 0.34 m from the goal point: the rule alone does not fire
                assert not bool(td["reached"]) and not emu.ground_truth()["reached"]
                assert 0.3 < emu.ground_truth()["closest_goal_m"] < 0.4
                env.land()
                continue
            go = [c for c in env.sent if c.startswith("go ")]
            assert len(go) == 1 and env.approaches == 1, go
            assert bool(td["reached"]) and bool(td["done"]) and env.sent[-1] == "land"
            gt = emu.ground_truth()
            assert gt["reached"] and gt["closest_goal_m"] < 0.05, gt
    finally:
        env.close()


def test_the_replay_benchmark_prints_its_figures(capsys):
    """``benchmarks/final_approach_replay.py`` on a logged development flight: one JSON
    object per radius; the planned moves pass through the goal sphere."""
    import json
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(root / "benchmarks"))
    import final_approach_replay as bench

    log = root / "docs" / "_static" / "results" / "tello" / "s102_default_logged_steps.json"
    figs = bench.main(["--logs", str(log), "--radius", "0.3", "0.4"])
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert lines == figs and [f["radius_m"] for f in figs] == [0.3, 0.4]
    assert figs[1]["approaches"] > figs[0]["approaches"] > 50
    assert all(f["pass_within_0_2"] >= 0.9 and f["heading_error_deg_median"] < 10
               for f in figs)
    with pytest.raises(SystemExit):
        bench.main(["--logs", str(root / "README.md")])


def test_height_approach_flies_the_vertical_leg(emu):
    """A scripted flight that hovers 0.25 m above the goal point's height, straight in
    front of the board: the height sensor alone puts it outside the rule, so the head is
    not asked and the final approach never flies; with ``height_approach`` the head is
    asked there too, and one ``go`` with its vertical part brings the drone down to the
    goal point (the simulator agreeing)."""
    lay = emu.env.layout
    goal, centre = np.array(lay.goal_point()), np.array(lay.goal_center)
    n = (goal - centre)[:2] / np.linalg.norm((goal - centre)[:2])
    side = np.array([-n[1], n[0]])
    asked = []

    def head(frames):  # the true (ahead, lateral), as above
        d = np.array(emu.pose()[:2]) - goal[:2]
        asked.append(emu.pose()[2] - goal[2])
        return torch.tensor([[float(d @ n), float(d @ side)]] * len(frames))

    rule = ReachRule(max_distance=1.0, max_goal_offset=0.15, goal_height=float(goal[2]))
    # around the pillar: 0.75 m left, 2 m forward, back 0.75 m right, up 0.25 m, forward
    script = [2] * 3 + [0] * 8 + [3] * 3 + [4] + [0] * 2
    env = TelloEnv(emu.client(), detector=emu.sim_detector(),
                   depth_estimator=emu.sim_depth_estimator(), reach_rule=rule,
                   arrival_head=head, final_approach=0.4, height_approach=0.3,
                   command_timeout=2, before_takeoff=lambda _: emu.reset_world(),
                   verbose=False)
    try:
        for height_approach in (None, 0.3):
            asked.clear()
            env.height_approach = height_approach
            td = env.reset()
            sent0 = len(env.sent)
            for a in script:
                td = env.step(td.set("action", torch.tensor(a)))["next"]
                if bool(td["done"]):
                    break
            gt = emu.ground_truth()
            go = [c for c in env.sent[sent0:] if c.startswith("go ")]
            if height_approach is None:  # hovering 0.25 m above: never asked up there
                assert not go and not bool(td["reached"]) and not gt["reached"]
                assert 0.24 < gt["closest_goal_m"] < 0.3, gt
                # asked up there only on the climb, whose sweep crossed the goal's height
                assert sum(dz > 0.2 for dz in asked) == 1, asked
                env.land()
            else:  # asked 0.25 m up, 0.28 m short: one go, down to the goal point
                assert sum(dz > 0.2 for dz in asked) >= 2, asked
                assert len(go) == 1 and int(go[0].split()[3]) < -20, go
                assert bool(td["reached"]) and gt["reached"] and gt["closest_goal_m"] < 0.05, gt
    finally:
        env.close()
