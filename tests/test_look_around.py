"""``TelloEnv(look_around=DEG)``: near the goal point the drone turns right, left and back,
the arrival head reads the two turned views, and the reach rule decides on the mean of the
readings. Flown on the real emulator (UDP, djitellopy, the MuJoCo scene) with a scripted head
whose error depends on the view, as the learned head's does."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchrl_causal.envs import BoardPlaneOffset, ReachRule, TelloEnv
from torchrl_causal.envs.tello_emulator import TelloEmulator

pytestmark = pytest.mark.timeout(240)

#: left 0.75 m, forward 2 m, right 0.75 m, forward: 0.28 m short of the goal point (outside the
#: simulator's 0.2 m sphere), then one more forward: 0.03 m from it
SCRIPT = [2] * 3 + [0] * 8 + [3] * 3 + [0] * 2


@pytest.fixture(scope="module")
def emu():
    with TelloEmulator(fps=20, time_scale=20.0, video_size=(240, 320),
                       battery_drain_per_min=0.0) as e:
        yield e


def _view_head(emu, reads):
    """The true ``(ahead, lateral)`` of the drone, read 0.2 m short of the truth where the
    drone is more than 0.2 m short and faces the board straight (yaw within 5 deg of the
    take-off heading); from a turned view the truth."""
    lay = emu.env.layout
    goal, centre = np.array(lay.goal_point()), np.array(lay.goal_center)
    n = (goal - centre)[:2] / np.linalg.norm((goal - centre)[:2])
    side = np.array([-n[1], n[0]])

    def head(frames):
        x, y, _, yaw = emu.pose()
        d = np.array([x, y]) - goal[:2]
        ahead, lateral = float(d @ n), float(d @ side)
        straight = abs((yaw + 180) % 360 - 180) < 5
        read = ahead - 0.2 if (straight and ahead > 0.2) else ahead
        reads.append((round(ahead, 2), straight, round(read, 2)))
        return torch.tensor([[read, lateral]] * len(frames))

    return head, float(goal[2])


def test_looking_around_turns_a_false_reached_into_an_arrival(emu):
    """0.28 m short, the straight view reads 0.08 m: one view fires (a false "reached", the
    simulator disagreeing); looking around, the two turned views read 0.28 m, the mean 0.21 m
    does not fire, and the next step (0.03 m, read alike from every view) ends in an arrival
    both judges agree on, with the turns sent as SDK ``cw 12`` / ``ccw 24`` / ``cw 12``."""
    reads = []
    head, goal_z = _view_head(emu, reads)
    rule = ReachRule(max_distance=1.0, max_goal_offset=0.13, goal_height=goal_z)
    env = TelloEnv(emu.client(), detector=emu.sim_detector(),
                   depth_estimator=emu.sim_depth_estimator(), reach_rule=rule,
                   arrival_head=head, command_timeout=2, before_takeoff=lambda _: emu.reset_world(),
                   verbose=False)
    try:
        for look_around in (None, 12):
            env.look_around = look_around
            reads.clear()
            td = env.reset()
            sent0, steps = len(env.sent), 0
            for a in SCRIPT:
                td = env.step(td.set("action", torch.tensor(a)))["next"]
                steps += 1
                if bool(td["done"]):
                    break
            gt = emu.ground_truth()
            turns = [c for c in env.sent[sent0:] if c.split()[0] in ("cw", "ccw")]
            if look_around is None:  # fired 0.28 m short: the simulator disagrees
                assert steps == len(SCRIPT) - 1 and bool(td["reached"]), reads
                assert not gt["reached"] and 0.25 < gt["closest_goal_m"] < 0.31, gt
                assert not turns
            else:  # looked around there (and at the goal point): one step more, agreed
                assert steps == len(SCRIPT) and bool(td["reached"]), reads
                assert gt["reached"] and gt["closest_goal_m"] < 0.1, gt
                assert turns == ["cw 12", "ccw 24", "cw 12"] * 2, turns
                assert env.look_arounds >= 2
                turned = [r for r in reads if not r[1]]
                assert len(turned) == 4 and all(r[2] == r[0] for r in turned), reads
                assert abs(emu.pose()[3]) < 1 or not gt["flying"]  # back on its heading
    finally:
        env.close()


def test_look_around_options_are_checked():
    from torchrl_causal.perception.goal import SimGoalDetector

    kw = dict(dry_run=True, verbose=False, detector=SimGoalDetector(),
              depth_estimator=lambda p: torch.ones(p.shape[:3]))
    head = lambda frames: torch.zeros(len(frames), 2)  # noqa: E731
    with pytest.raises(ValueError, match="look_around=12 asks the arrival head at turned views"):
        TelloEnv(look_around=12, **kw)
    with pytest.raises(ValueError, match="it needs a head that reads frames, got BoardPlaneOffset"):
        TelloEnv(arrival_head=BoardPlaneOffset(), look_around=12,
                 reach_rule=ReachRule(max_goal_offset=0.2), **kw)
    with pytest.raises(ValueError, match="a turn of 1-45 deg"):
        TelloEnv(arrival_head=head, look_around=50, reach_rule=ReachRule(max_goal_offset=0.13),
                 **kw)
    with pytest.raises(ValueError, match="look_around_radius=0.1 is below the rule's"):
        TelloEnv(arrival_head=head, look_around=12, look_around_radius=0.1,
                 reach_rule=ReachRule(max_goal_offset=0.13), **kw)
    env = TelloEnv(arrival_head=head, look_around=12.4, reach_rule=ReachRule(max_goal_offset=0.13),
                   **kw)
    assert (env.look_around, env.look_around_radius) == (12, 0.2)  # whole degrees, as the SDK
    env.close()
