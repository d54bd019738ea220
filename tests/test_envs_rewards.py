"""DroneNavEnv rewards (``"progress"`` default, ``"thesis"``, callables), the open
scene's geofence (``out_of_bounds``) and the enclosed hall, in the real MuJoCo env.

The episodes compared (thesis scene, kinematic execution, no noise):

* ``reach``: the shortest path ``left, forward x 10, right`` (12 actions) reaches
  the goal point on its last step;
* ``hover``: ``turn_left`` / ``turn_right`` alternately, the goal stays in view,
  until truncation after 200 steps;
* ``crash``: ``forward`` until the pillar is hit (the 4th forward).
"""

import math
import os
import re

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import pytest
import torch

from torchrl_causal.envs import DroneNavEnv
from torchrl_causal.envs.layouts import DRONE_HALF_EXTENTS, thesis_layout
from torchrl_causal.envs.rewards import (
    REWARDS,
    ProgressReward,
    StepOutcome,
    ThesisReward,
    make_reward,
)
from torchrl_causal.schema import ACTION_NAMES

A = {n: i for i, n in enumerate(ACTION_NAMES)}
GAMMAS = (0.9, 0.95, 0.99)
PLANS = {
    "reach": ["left"] + ["forward"] * 10 + ["right"],
    "hover": ["turn_left" if k % 2 == 0 else "turn_right" for k in range(200)],
    "crash": ["forward"] * 10,  # stops at the crash (4th step)
}


def act(env, name):
    td = env.full_action_spec.zero().set("action", torch.tensor(A[name]))
    return env.step(td)["next"]


def run(env, actions):
    """Resets, then steps ``actions`` until done: the list of ``next`` tensordicts."""
    env.reset()
    out = []
    for name in actions:
        out.append(act(env, name))
        if out[-1]["done"].item():
            break
    return out


def rewards_of(steps):
    return [s["reward"].item() for s in steps]


def discounted(rewards, gamma):
    return sum(r * gamma**k for k, r in enumerate(rewards))


@pytest.fixture(scope="module")
def episodes():
    """``{reward_name: {episode: [next tds]}}`` for both built-in rewards."""
    out = {}
    for name in REWARDS:
        env = DroneNavEnv(reward=name, seed=0)
        try:
            out[name] = {ep: run(env, plan) for ep, plan in PLANS.items()}
        finally:
            env.close()
    return out


# ------------------------------------------------------ the three episodes
@pytest.mark.parametrize("reward", REWARDS)
def test_reach_hover_crash_episodes_end_as_planned(episodes, reward):
    eps = episodes[reward]
    reach, hover, crash = eps["reach"], eps["hover"], eps["crash"]
    assert len(reach) == 12 and reach[-1]["reached"].item() and reach[-1]["terminated"].item()
    assert not any(s["done"].item() for s in reach[:-1])
    assert len(hover) == 200 and hover[-1]["truncated"].item()
    assert not hover[-1]["terminated"].item()
    assert all(s["goal_in_sight"].item() for s in hover)
    assert len(crash) == 4 and crash[-1]["crashed"].item() and crash[-1]["terminated"].item()
    for steps in (reach, hover, crash):
        assert not any(s["out_of_bounds"].item() for s in steps)


def test_progress_reward_values_in_env(episodes):
    """Progress = true distance gained towards the goal point - 0.01; +10 / -10 terminal."""
    eps = episodes["progress"]
    hover = rewards_of(eps["hover"])
    assert hover == pytest.approx([-0.01] * 200, abs=1e-6)
    crash = rewards_of(eps["crash"])
    assert crash == pytest.approx([0.24, 0.24, 0.24, -10.0], abs=1e-5)
    reach = rewards_of(eps["reach"])
    assert reach[-1] == 10.0
    # the progress terms telescope: d(start) - d(before the last step) - 11 x 0.01
    gp = thesis_layout().goal_point()
    d0 = math.dist((0.0, 0.0, 1.0), gp)
    d11 = math.dist((2.5, 0.25, 1.0), gp)  # after left + 10 forward
    assert sum(reach[:-1]) == pytest.approx(d0 - d11 - 0.11, abs=1e-5)
    assert reach[0] == pytest.approx(d0 - math.dist((0.0, 0.25, 1.0), gp) - 0.01, abs=1e-6)


@pytest.mark.parametrize("gamma", GAMMAS + (1.0,))
def test_progress_orders_reach_over_hover_over_crash(episodes, gamma):
    eps = episodes["progress"]
    reach, hover, crash = (discounted(rewards_of(eps[k]), gamma) for k in ("reach", "hover", "crash"))
    assert reach > hover > crash
    if gamma == 1.0:  # undiscounted episode returns
        assert reach == pytest.approx(12.168, abs=1e-3)
        assert hover == pytest.approx(-2.0, abs=1e-4)
        assert crash == pytest.approx(-9.28, abs=1e-4)


def test_thesis_returns_make_hovering_pay(episodes):
    """The thesis's reward pays ~+90 for every step the goal is in view.

    So hovering in view (200 steps of ~87-90) is worth about 8.8 times the
    shortest path (~2,020) undiscounted, more than reaching at gamma 0.95 and
    0.99, and is close to reaching at gamma 0.9 (888 against 948, within 7%).
    Only the crash is clearly worst. Measured values (the in-view terms depend
    on the rendered goal measurement, hence the 1% tolerance):

    ========  =======  =======  =======
    gamma     reach    hover    crash
    ========  =======  =======  =======
    0.9         948      888     -490
    0.95       1366     1778     -606
    0.99       1862     7700     -709
    1 (sum)    2017    17784     -736
    ========  =======  =======  =======
    """
    eps = episodes["thesis"]
    r = {k: rewards_of(eps[k]) for k in PLANS}
    assert r["reach"][-1] == 1000.0 and r["crash"][-1] == -1000.0
    # every in-view step pays 100 - distance - |angle|, here between 80 and 100
    assert all(80.0 < x < 100.0 for x in r["reach"][:-1] + r["hover"] + r["crash"][:-1])
    expected = {
        0.9: (948.4, 888.4, -490.4),
        0.95: (1365.7, 1777.5, -606.5),
        0.99: (1862.5, 7700.0, -709.3),
        1.0: (2016.5, 17784.0, -736.4),
    }
    for gamma, values in expected.items():
        got = tuple(discounted(r[k], gamma) for k in ("reach", "hover", "crash"))
        assert got == pytest.approx(values, rel=0.01), gamma
        reach, hover, crash = got
        assert crash < min(reach, hover)
        if gamma == 0.9:
            assert reach > hover > 0.9 * reach  # close
        else:
            assert hover > reach
    assert sum(r["hover"]) > 8 * sum(r["reach"])


# ------------------------------------------------------------- geofence
@pytest.mark.parametrize("reward,fail", [("progress", -10.0), ("thesis", -1000.0)])
def test_backward_leaves_the_geofence(reward, fail):
    """Start x = 0, geofence xmin = -2 (inclusive): the 8th backward ends at
    x = -2.0 (inside), the 9th at x = -2.25 (outside, no wall to hit)."""
    env = DroneNavEnv(reward=reward, seed=0)
    try:
        steps = run(env, ["backward"] * 20)
        assert len(steps) == 9
        for s in steps[:-1]:
            assert not (s["out_of_bounds"].item() or s["done"].item() or s["crashed"].item())
        last = steps[-1]
        assert last["out_of_bounds"].item() and not last["crashed"].item()
        assert not last["reached"].item()
        assert last["terminated"].item() and last["done"].item() and not last["truncated"].item()
        assert last["reward"].item() == fail
        x, y, z, yaw = env.drone_pose()
        assert (x, y, z, yaw) == pytest.approx((-2.25, 0.0, 1.0, 0.0), abs=1e-9)
        assert not env.layout.inside((x, y, z)) and env.layout.inside((-2.0, y, z))
    finally:
        env.close()


def test_ascending_leaves_above_the_flight_volume_without_a_ceiling():
    """From z = 1, 0.25 m per ascend: z = 3.0 (the top, inside) after 8, 3.25 after 9."""
    env = DroneNavEnv(seed=0)
    try:
        steps = run(env, ["ascend"] * 20)
        # an open layout has no ceiling and no walls, only the floor
        for geom in ("ceiling", "wall0"):
            assert mujoco.mj_name2id(env.model, mujoco.mjtObj.mjOBJ_GEOM, geom) == -1
        assert len(steps) == 9
        assert not any(s["done"].item() for s in steps[:-1])
        last = steps[-1]
        assert last["out_of_bounds"].item() and not last["crashed"].item()
        assert last["terminated"].item() and last["reward"].item() == -10.0
        assert env.drone_pose()[2] == pytest.approx(3.25, abs=1e-9)
    finally:
        env.close()


# ---------------------------------------------------------- enclosed hall
def test_enclosed_hall_crashes_into_ceiling_and_walls():
    hall = thesis_layout(enclosed=True)
    assert hall.enclosed and hall.height == 2.5 and hall.arena == (-1.5, -2.5, 4.5, 2.5)
    env = DroneNavEnv(hall, seed=0)
    try:
        up = run(env, ["ascend"] * 20)
        names = {mujoco.mj_id2name(env.model, mujoco.mjtObj.mjOBJ_GEOM, i) for i in range(env.model.ngeom)}
        assert {"ceiling", "wall0", "wall1", "wall2", "wall3"} <= names
        last = up[-1]
        assert len(up) == 6  # z 1.0 -> 2.25 after 5; the 6th hits the ceiling at 2.5
        assert last["crashed"].item() and not last["out_of_bounds"].item()
        assert last["terminated"].item() and last["reward"].item() == -10.0
        z = env.drone_pose()[2]
        assert 2.25 < z <= hall.height - DRONE_HALF_EXTENTS[2]  # stopped at the last free pose
        back = run(env, ["backward"] * 20)  # the wall at x = -1.5 stops it first
        assert len(back) == 6 and back[-1]["crashed"].item()
        assert not any(s["out_of_bounds"].item() for s in back)
    finally:
        env.close()


# ---------------------------------------------------------- reward option
def test_unknown_reward_name_raises_before_mujoco(monkeypatch):
    import torchrl_causal.envs.drone as drone

    def boom(*a, **k):  # pragma: no cover - must not be reached
        raise AssertionError("MuJoCo touched before validation")

    monkeypatch.setattr(drone, "build_model", boom)
    monkeypatch.setattr(drone, "SceneRenderer", boom)
    with pytest.raises(ValueError, match="bogus") as err:
        DroneNavEnv(reward="bogus")
    assert "progress" in str(err.value) and "thesis" in str(err.value)
    with pytest.raises(ValueError, match="reward"):
        DroneNavEnv(reward=3)


def test_callable_reward_is_used_as_is():
    seen = []

    def constant(o):
        seen.append(o)
        return 1.0

    env = DroneNavEnv(reward=constant, seed=0)
    try:
        assert env.reward_fn is constant
        steps = run(env, ["forward"] * 10)  # the pillar: crash at the 4th
        assert rewards_of(steps) == [1.0, 1.0, 1.0, 1.0]
        assert len(seen) == 4 and all(isinstance(o, StepOutcome) for o in seen)
        assert seen[-1].crashed and seen[-1].failed and not any(o.crashed for o in seen[:-1])
        # consecutive outcomes chain: the distance after a step is the next one's before
        for a, b in zip(seen, seen[1:]):
            assert b.distance_before == a.distance_after
        assert seen[0].distance_before == pytest.approx(2.53, abs=1e-9)
        assert seen[0].distance_after == pytest.approx(2.28, abs=1e-9)
        assert seen[0].in_sight and seen[0].goal_distance > 0
    finally:
        env.close()
    env = DroneNavEnv(reward=lambda o: 1.0, seed=0)
    try:
        assert rewards_of(run(env, ["turn_left"] * 3)) == [1.0, 1.0, 1.0]
    finally:
        env.close()


# ------------------------------------------------------------------ specs
@pytest.mark.parametrize("reward", [None, "thesis"])
def test_check_env_specs_and_out_of_bounds_key(reward):
    from torchrl.envs.utils import check_env_specs

    env = DroneNavEnv(seed=0) if reward is None else DroneNavEnv(reward=reward, seed=0)
    try:
        check_env_specs(env)
        spec = env.observation_spec["out_of_bounds"]
        assert spec.dtype == torch.bool and spec.shape == (1,)
        td = env.reset()
        assert td["out_of_bounds"].dtype == torch.bool and not td["out_of_bounds"].item()
        assert env.reward_fn.name == (reward or "progress")
    finally:
        env.close()


# ------------------------------------------------------------- unit tests
def test_step_outcome_failed():
    assert StepOutcome(crashed=True).failed and StepOutcome(out_of_bounds=True).failed
    assert not StepOutcome().failed
    assert not StepOutcome(crashed=True, reached=True).failed


def test_progress_reward_values():
    r = ProgressReward()
    assert r(StepOutcome(reached=True)) == 10.0
    assert r(StepOutcome(reached=True, distance_before=1.0, distance_after=5.0)) == 10.0
    assert r(StepOutcome(crashed=True)) == -10.0
    assert r(StepOutcome(out_of_bounds=True, in_sight=True, goal_distance=1.0)) == -10.0
    assert r(StepOutcome(distance_before=2.0, distance_after=1.75)) == pytest.approx(0.24)
    assert r(StepOutcome(distance_before=1.75, distance_after=2.0)) == pytest.approx(-0.26)
    assert r(StepOutcome(distance_before=1.0, distance_after=1.0)) == pytest.approx(-0.01)
    # the goal measurement plays no part
    assert r(StepOutcome(in_sight=True, goal_distance=0.5, goal_angle=3.0)) == pytest.approx(-0.01)
    custom = ProgressReward(reach=5, fail=-2, progress_per_m=2.0, step_cost=0.0)
    assert custom(StepOutcome(reached=True)) == 5.0 and custom(StepOutcome(crashed=True)) == -2.0
    assert custom(StepOutcome(distance_before=2.0, distance_after=1.5)) == 1.0
    assert custom.name == "progress" and "reach=5.0" in repr(custom)


def test_thesis_reward_values():
    r = ThesisReward()
    assert r(StepOutcome(crashed=True, in_sight=True)) == -1000.0
    assert r(StepOutcome(out_of_bounds=True)) == -1000.0
    assert r(StepOutcome(reached=True, in_sight=True, goal_distance=0.3)) == 1000.0
    assert r(StepOutcome(in_sight=True, goal_distance=2.0, goal_angle=-5.0)) == 93.0
    assert r(StepOutcome(in_sight=True, goal_distance=2.0, goal_angle=5.0)) == 93.0
    assert r(StepOutcome(in_sight=False)) == -9.0
    # the true distances play no part
    assert r(StepOutcome(distance_before=3.0, distance_after=1.0)) == -9.0
    custom = ThesisReward(reach=1, crash=-1, in_view=10, not_in_view=0)
    assert custom(StepOutcome(in_sight=True, goal_distance=1.0, goal_angle=2.0)) == 7.0
    assert custom(StepOutcome()) == 0.0 and custom(StepOutcome(crashed=True)) == -1.0
    assert custom.name == "thesis" and "in_view=10.0" in repr(custom)


def test_make_reward():
    assert REWARDS == ("progress", "thesis")
    assert isinstance(make_reward("progress"), ProgressReward)
    assert isinstance(make_reward("thesis"), ThesisReward)

    def f(o):
        return 0.0

    assert make_reward(f) is f
    for bad in ("bogus", None, 3):
        with pytest.raises(ValueError, match=f"got {re.escape(repr(bad))}$"):
            make_reward(bad)


@pytest.mark.parametrize(
    "kwargs,needle",
    [
        ({"reach": -1}, "reach"),
        ({"reach": 0}, "reach"),
        ({"fail": 1.0}, "fail"),
        ({"fail": 0}, "fail"),
        ({"reach": "10"}, "reach"),
        ({"fail": True}, "fail"),
        ({"progress_per_m": None}, "progress_per_m"),
        ({"step_cost": "0.01"}, "step_cost"),
    ],
)
def test_progress_reward_bad_inputs(kwargs, needle):
    with pytest.raises(ValueError, match=needle):
        ProgressReward(**kwargs)


@pytest.mark.parametrize("key", ["reach", "crash", "in_view", "not_in_view"])
def test_thesis_reward_bad_inputs(key):
    with pytest.raises(ValueError, match=key):
        ThesisReward(**{key: "x"})
