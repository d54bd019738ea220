"""ReachRule: TelloEnv's arrival decision from measurements only."""

from __future__ import annotations

import math

import pytest
import torch

from torchrl_causal.envs import ReachRule
from torchrl_causal.envs.tello import TelloEnv
from torchrl_causal.perception.goal import SimGoalDetector

FULL = (0.0, 0.0, 84.0, 84.0)


def _m(**kw):
    base = dict(in_sight=True, distance=0.4, angle=0.0, box=FULL, width=84, altitude=1.0)
    base.update(kw)
    return base


def test_each_condition_vetoes_on_its_own():
    rule = ReachRule(max_distance=0.45, min_distance=0.1, max_angle=20, goal_height=1.0,
                     max_height_offset=0.12, full_width=True)
    assert rule(**_m())
    assert not rule(**_m(in_sight=False))
    assert not rule(**_m(distance=float("nan")))
    assert not rule(**_m(distance=0.46))
    assert not rule(**_m(distance=0.05))
    assert not rule(**_m(angle=-25.0))
    assert not rule(**_m(altitude=1.13))
    assert rule(**_m(altitude=0.89))
    assert not rule(**_m(box=(10.0, 0.0, 84.0, 84.0)))  # the board's left edge in view
    assert not rule(**_m(box=(0.0, 0.0, 70.0, 84.0)))
    # without goal_height: distance and angle only (0.45 m by default)
    plain = ReachRule()
    assert plain(**_m(distance=0.45, altitude=3.0, box=(30, 30, 50, 50)))
    assert not plain(**_m(distance=0.46))


@pytest.mark.parametrize("kw,name", [
    ({"max_distance": 0.0}, "max_distance"), ({"max_distance": math.inf}, "max_distance"),
    ({"min_distance": 0.9}, "min_distance"), ({"max_angle": 120}, "max_angle"),
    ({"goal_height": -1.0}, "goal_height"), ({"max_height_offset": 0.0}, "max_height_offset"),
    ({"full_width": 1}, "full_width"),
])
def test_bad_options_are_named(kw, name):
    with pytest.raises(ValueError, match=f"ReachRule.{name}"):
        ReachRule(**kw)


def test_tello_env_takes_a_rule_and_refuses_anything_else():
    depth = lambda p: torch.full(p.shape[:3], 3.0)  # noqa: E731
    env = TelloEnv(dry_run=True, detector=SimGoalDetector(), depth_estimator=depth,
                   verbose=False, reach_rule=ReachRule(max_distance=0.4))
    assert env.reach_rule.max_distance == 0.4
    env.close()
    with pytest.raises(ValueError, match="reach_rule"):
        TelloEnv(dry_run=True, detector=SimGoalDetector(), depth_estimator=depth,
                 verbose=False, reach_rule={"max_distance": 0.4})
