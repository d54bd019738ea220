"""Feature transforms on the real DroneNavEnv: TorchRL's transform checklist
(in an env, SerialEnv / ParallelEnv in both orders, before a module, in a
replay buffer, batch sizes [], [1], [3, 2]) and correctness in rendered scenes."""

import dataclasses
import math
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import pytest
import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import ParallelEnv, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from torchrl_causal.envs import DroneNavEnv
from torchrl_causal.envs.layouts import Obstacle, thesis_layout
from torchrl_causal.envs.scene import CAMERA_OFFSET
from torchrl_causal.perception.goal import SimGoalDetector
from torchrl_causal.schema import DEFAULT_SCHEMA
from torchrl_causal.transforms import GoalFeatures, make_causal_transforms

IDX = {n: i for i, n in enumerate(DEFAULT_SCHEMA.names)}
CAM_X = CAMERA_OFFSET[0]
# empty 8 x 6 m arena, drone at the origin facing +x, goal board facing the drone
OPEN = dataclasses.replace(
    thesis_layout(), name="open", obstacles=(), arena=(-1.5, -3.0, 6.5, 3.0), height=2.6
)
SMALL = 32  # image size for the plumbing tests (the feature code is size-agnostic)


def scene(goal_ahead=4.0, goal_left=0.0, *, yaw=0.0, z=1.0, obstacles=()):
    """``OPEN`` with the board's face ``goal_ahead`` m in front of the camera."""
    face_x = CAM_X + goal_ahead
    return dataclasses.replace(
        OPEN,
        start_pos=(0.0, 0.0, z),
        start_yaw_deg=yaw,
        goal_center=(face_x + OPEN.goal_thickness / 2, goal_left, 1.0),
        obstacles=tuple(obstacles),
    )


def features(layout, **stack_kw):
    env = DroneNavEnv(layout, seed=0)
    try:
        td = env.reset()
        out = make_causal_transforms(env, seed=0, **stack_kw)(td.clone())
        # GoalFeatures with the env's own meter reproduces the env's measurement
        again = GoalFeatures(env.goal_meter)(td.exclude("goal_in_sight", "goal_distance", "goal_angle"))
        for key in ("goal_in_sight", "goal_distance", "goal_angle"):
            assert torch.equal(again[key], td[key]), key
        return out
    finally:
        env.close()


# ------------------------------------------------------------ correctness in scenes
@pytest.mark.parametrize("ahead,left", [(1.0, 0.0), (2.0, 0.45), (4.0, -1.2)])
def test_facing_the_goal(ahead, left):
    td = features(scene(ahead, left))
    true_d = td["goal_true_distance"].item()
    true_b = td["goal_true_bearing"].item()
    assert true_d == pytest.approx(math.hypot(ahead + OPEN.goal_thickness / 2, left), abs=1e-3)
    assert td["goal_in_sight"].item()
    assert abs(td["goal_angle"].item() - true_b) <= 2.0
    assert abs(td["goal_distance"].item() - true_d) <= 0.05 * true_d
    s = td["causal_state"]
    assert s[IDX["goal_in_sight"]] == 1 and s[IDX["goal_distance"]] == 1  # far (> 0.5 m)
    expected_angle = 0 if abs(true_b) <= 15 else (1 if true_b > 0 else 2)
    assert s[IDX["goal_angle"]] == expected_angle
    if ahead == 4.0:
        assert expected_angle == 2  # the scene covers the far-right category


@pytest.mark.parametrize("case", ["turned_away", "hidden"])
def test_goal_turned_away_or_hidden_is_not_in_sight(case):
    if case == "turned_away":
        layout = scene(2.0, yaw=180.0)
    else:  # a 2 m wide, 2.4 m high panel 1 m ahead hides the board 3 m ahead
        panel = Obstacle(center=(CAM_X + 1.05, 0.0, 1.2), half_size=(0.05, 1.0, 1.2))
        layout = scene(3.0, obstacles=[panel])
    td = features(layout)
    assert td["goal_pixels"].item() == 0
    assert not td["goal_in_sight"].item()
    assert td["goal_distance"].item() == 0.0 and td["goal_angle"].item() == 0.0
    s = td["causal_state"]
    assert s[IDX["goal_in_sight"]] == 0
    assert s[IDX["goal_distance"]] == 2 and s[IDX["goal_angle"]] == 0  # not_visible, good
    if case == "hidden":
        assert abs(td["goal_true_bearing"].item()) < 1.0  # it is straight ahead
        assert td["depth_sections"][0].item() == pytest.approx(1.0, abs=0.02)


@pytest.mark.parametrize("exact", [False, True])
def test_wall_ahead_is_close_and_open_space_is_far(exact):
    wall = Obstacle(center=(CAM_X + 0.3 + 0.05, 0.0, 1.3), half_size=(0.05, 2.0, 1.3))
    near = features(scene(4.0, obstacles=[wall]), exact=exact)
    assert near["depth_sections"][0].item() == pytest.approx(0.3, abs=0.01)
    assert near["causal_state"][IDX["depth_center"]] == 0
    assert (near["causal_state"][:5] == 0).all()  # the wall fills the view
    far = features(scene(4.0), exact=exact)
    assert far["depth_sections"][0].item() > 3.0
    assert (far["depth_sections"] > 1.0).all()  # floor and ceiling are > 1 m away too
    assert (far["causal_state"][:5] == 1).all()


def test_altitude_categories():
    codes = [
        features(scene(4.0, z=z))["causal_state"][IDX["altitude"]].item()
        for z in (0.3, 1.0, 2.0)
    ]
    assert codes == [0, 1, 2]


# ------------------------------------------------------------ TorchRL checklist
class CountingDetector(SimGoalDetector):
    calls = 0

    def detect(self, pixels, depth=None, **gt):
        CountingDetector.calls += pixels.shape[0]
        return super().detect(pixels, depth, **gt)


def make_env(seed=0, **kw):
    return DroneNavEnv(seed=seed, image_size=SMALL, max_steps=50, **kw)


def make_transformed(seed=0):
    env = make_env(seed)
    return TransformedEnv(env, make_causal_transforms(env, seed=seed))


def test_in_env_specs_rollout_and_one_detection_per_frame():
    CountingDetector.calls = 0
    env = make_env(detector=CountingDetector(min_pixels=4))
    stack = make_causal_transforms(env, seed=0)
    assert not any(isinstance(t, GoalFeatures) for t in stack)
    tenv = TransformedEnv(env, stack)
    check_env_specs(tenv)
    CountingDetector.calls = 0
    roll = tenv.rollout(4, break_when_any_done=False)
    assert CountingDetector.calls == 5  # reset + 4 steps: the stack detects nothing
    spec = tenv.observation_spec["causal_state"]
    assert spec.is_in(roll["causal_state"][0]) and spec.is_in(roll["next", "causal_state"][-1])
    assert roll["next", "causal_features"].shape == (4, 9)
    assert torch.equal(
        roll["next", "causal_state"][:, IDX["goal_in_sight"]].bool(),
        roll["next", "goal_in_sight"].squeeze(-1),
    )
    tenv.close()


def test_make_causal_transforms_validates_the_env():
    env = make_env()
    with pytest.raises(ValueError, match="goal_meter"):
        make_causal_transforms(env, goal_meter=env.goal_meter)
    assert make_causal_transforms(env)[0].max_depth == env.max_depth
    env.close()


@pytest.mark.parametrize("order", ["transform_inside", "transform_outside"])
def test_serial_env_both_orders_batch_1(order):
    if order == "transform_inside":
        env = SerialEnv(1, make_transformed)
    else:
        base = SerialEnv(1, make_env)
        env = TransformedEnv(base, make_causal_transforms(base, seed=0))
    check_env_specs(env)
    assert env.observation_spec["causal_state"].shape == (1, 9)
    roll = env.rollout(2)
    assert roll["next", "causal_state"].shape == (1, 2, 9)
    env.close()


def test_nested_serial_env_batch_3_2():
    base = SerialEnv(3, lambda: SerialEnv(2, make_env))
    env = TransformedEnv(base, make_causal_transforms(base, seed=0))
    assert env.batch_size == (3, 2)
    check_env_specs(env)
    td = env.reset()
    assert td["causal_state"].shape == (3, 2, 9)
    assert env.observation_spec["causal_state"].is_in(td["causal_state"])
    env.close()


@pytest.mark.parametrize("order", ["transform_inside", "transform_outside"])
def test_parallel_env_both_orders(order):
    if order == "transform_inside":
        env = ParallelEnv(
            2, make_transformed, create_env_kwargs=[{"seed": 0}, {"seed": 1}], mp_start_method="fork"
        )
    else:
        base = ParallelEnv(2, make_env, mp_start_method="fork")
        env = TransformedEnv(base, make_causal_transforms(base, seed=0))
    try:
        check_env_specs(env)
        roll = env.rollout(2)
        assert roll["next", "causal_state"].shape == (2, 2, 9)
        assert env.observation_spec["causal_state"].is_in(roll["next", "causal_state"])
    finally:
        env.close()


def test_before_a_module_policy():
    tenv = make_transformed()
    head = TensorDictModule(torch.nn.Linear(9, 8), ["causal_features"], ["action_value"])
    pick = TensorDictModule(lambda q: q.argmax(-1), ["action_value"], ["action"])
    policy = TensorDictSequential(head, pick)
    roll = tenv.rollout(3, policy, break_when_any_done=False)
    expected = head(roll.select("causal_features").clone())["action_value"].argmax(-1)
    assert torch.equal(roll["action"], expected)
    tenv.close()


def test_inside_a_replay_buffer_matches_the_env_stack():
    env = make_env()
    tenv = TransformedEnv(env, make_causal_transforms(env, exact=True))
    roll = tenv.rollout(6, break_when_any_done=False)
    raw = roll.exclude("causal_state", "causal_features", "depth_sections")
    rb = ReplayBuffer(
        storage=LazyTensorStorage(16), transform=make_causal_transforms(env, exact=True)
    )
    rb.extend(raw)
    assert torch.equal(rb[:]["causal_state"], roll["causal_state"])
    assert rb.sample(3)["causal_state"].shape == (3, 9)
    tenv.close()
