"""DroneNavEnv: rendering, actions, reward/termination, seeding, specs, gym, bad options.

The reward/termination tests here check the thesis's reward exactly (the
``envs`` fixture builds ``reward="thesis"`` envs); the default ``"progress"``
reward, the geofence and the enclosed hall are tested in
``tests/test_envs_rewards.py``.
"""

import math
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest
import torch

from torchrl_causal.envs import DroneNavEnv
from torchrl_causal.envs.layouts import Layout, thesis_layout
from torchrl_causal.schema import ACTION_NAMES

A = {n: i for i, n in enumerate(ACTION_NAMES)}
MODES = ("kinematic", "physics")


def open_layout(**kw) -> Layout:
    """A 6 x 6 m empty arena; the goal board behind the drone, facing +x."""
    base = dict(
        name="open",
        arena=(-3.0, -3.0, 3.0, 3.0),
        height=3.0,
        start_pos=(0.0, 0.0, 1.2),
        start_yaw_deg=0.0,
        goal_center=(-2.5, 0.0, 1.0),
        goal_yaw_deg=0.0,
        goal_size=(1.0, 0.8),
    )
    base.update(kw)
    return Layout(**base)


def act(env, name_or_idx, td=None):
    a = A[name_or_idx] if isinstance(name_or_idx, str) else int(name_or_idx)
    td = env.full_action_spec.zero().set("action", torch.tensor(a))
    return env.step(td)["next"]


@pytest.fixture(scope="module")
def envs():
    """Thesis-scene envs with the thesis's reward (the values asserted below)."""
    made = {m: DroneNavEnv(execution=m, reward="thesis", seed=0) for m in MODES}
    yield made
    for e in made.values():
        e.close()


@pytest.fixture(scope="module")
def open_envs():
    made = {m: DroneNavEnv(open_layout(), execution=m, seed=0) for m in MODES}
    yield made
    for e in made.values():
        e.close()


# ----------------------------------------------------------------- rendering
def test_goal_visible_ahead_absent_behind(envs):
    env = envs["kinematic"]
    td = env.reset()
    assert td["pixels"].dtype == torch.uint8 and td["pixels"].shape == (84, 84, 3)
    assert td["goal_pixels"].item() >= 20 and td["goal_in_sight"].item()
    x0, y0, x1, y1 = td["goal_box"].tolist()
    assert 0 <= x0 < x1 <= 84 and 0 <= y0 < y1 <= 84
    # the pillar hides the right part of the board: the visible part is left of centre
    assert td["goal_angle"].item() > 0 and td["goal_true_bearing"].abs().item() < 1.0
    assert abs(td["goal_true_distance"].item() - (3.0 - 0.125)) < 0.01
    # the measured distance is the depth inside the box (the board face, ~2.86 m)
    assert abs(td["goal_distance"].item() - 2.855) < 0.1
    for _ in range(12):  # 12 x 15 deg = 180 deg: goal behind
        nxt = act(env, "turn_right")
    assert nxt["goal_pixels"].item() == 0 and not nxt["goal_in_sight"].item()
    assert nxt["goal_box"].tolist() == [0.0, 0.0, 0.0, 0.0]
    assert nxt["reward"].item() == -9.0
    assert nxt["goal_distance"].item() == 0.0 and nxt["goal_angle"].item() == 0.0
    assert abs(abs(nxt["goal_true_bearing"].item()) - 180.0) < 1.0


def test_depth_to_wall_within_2_percent():
    # facing the +x wall at x = 2.0 from x = 0.0: camera 0.125 m ahead of the centre
    # (walls exist only in an enclosed layout; an open one's arena is a geofence)
    env = DroneNavEnv(open_layout(arena=(-3.0, -3.0, 2.0, 3.0), enclosed=True), seed=0)
    td = env.reset()
    expected = 2.0 - 0.125
    depth = td["depth"]
    assert depth.dtype == torch.float32 and depth.shape == (84, 84)
    centre = depth[30:54, 30:54]
    assert torch.allclose(centre, torch.full_like(centre, expected), rtol=0.02)
    assert depth.max().item() <= env.max_depth
    env.close()


# ------------------------------------------------------------------- actions
@pytest.mark.parametrize("mode", MODES)
def test_every_action_moves_by_its_step(open_envs, mode):
    env = open_envs[mode]
    tol_m, tol_deg = (1e-6, 1e-6) if mode == "kinematic" else (0.03, 1.5)
    for name in ACTION_NAMES:
        env.reset()
        x0, y0, z0, yaw0 = env.drone_pose()
        nxt = act(env, name)
        assert not nxt["crashed"].item()
        x1, y1, z1, yaw1 = env.drone_pose()
        fwd, left, up, dyaw = {
            "forward": (0.25, 0, 0, 0), "backward": (-0.25, 0, 0, 0),
            "left": (0, 0.25, 0, 0), "right": (0, -0.25, 0, 0),
            "ascend": (0, 0, 0.25, 0), "descend": (0, 0, -0.25, 0),
            "turn_left": (0, 0, 0, 15.0), "turn_right": (0, 0, 0, -15.0),
        }[name]
        assert abs((x1 - x0) - fwd) <= tol_m, name
        assert abs((y1 - y0) - left) <= tol_m, name
        assert abs((z1 - z0) - up) <= tol_m, name
        assert abs((yaw1 - yaw0) - dyaw) <= tol_deg, name


def test_step_size_options_and_heading_frame():
    env = DroneNavEnv(open_layout(start_yaw_deg=90.0), step_size=0.5, turn_deg=30.0, seed=0)
    env.reset()
    act(env, "forward")  # heading +y
    x, y, z, yaw = env.drone_pose()
    assert abs(x) < 1e-6 and abs(y - 0.5) < 1e-6 and abs(yaw - 90.0) < 1e-6
    act(env, "turn_left")
    assert abs(env.drone_pose()[3] - 120.0) < 1e-6
    env.close()


def test_physics_camera_sees_tilt():
    """Mid-manoeuvre the physics drone is tilted: its view differs from a level
    camera at the same position and heading (rendered by a kinematic env)."""
    from dataclasses import replace

    env = DroneNavEnv(open_layout(), execution="physics", action_duration=0.3, seed=0)
    env.reset()
    nxt = act(env, "forward")
    w, qx, qy, qz = env.data.qpos[3:7]
    tilt = math.degrees(2 * math.asin(min(1.0, math.hypot(qx, qy))))
    x, y, z, yaw = env.drone_pose()
    env.close()
    assert tilt > 2.0
    level = DroneNavEnv(replace(open_layout(), start_pos=(x, y, z), start_yaw_deg=yaw), seed=0)
    flat = level.reset()["pixels"]
    level.close()
    diff = (nxt["pixels"].float() - flat.float()).abs().mean().item()
    assert diff > 2.0


# ------------------------------------------------------ reward / termination
@pytest.mark.parametrize("mode", MODES)
def test_collision_ends_episode_with_minus_1000(envs, mode):
    env = envs[mode]
    env.reset()
    for k in range(10):
        nxt = act(env, "forward")  # straight into the pillar
        if nxt["done"].item():
            break
    assert k == 3
    assert nxt["reward"].item() == -1000.0
    assert nxt["crashed"].item() and not nxt["reached"].item()
    assert nxt["terminated"].item() and nxt["done"].item() and not nxt["truncated"].item()


@pytest.mark.parametrize("mode", MODES)
def test_reaching_goal_ends_episode_with_plus_1000(envs, mode):
    env = envs[mode]
    td = env.reset()
    plan = ["left"] + ["forward"] * 10 + ["right"]
    rewards = []
    for k, name in enumerate(plan):
        nxt = act(env, name)
        rewards.append(nxt["reward"].item())
        if k < len(plan) - 1:
            assert not nxt["done"].item(), (k, name)
    assert nxt["reward"].item() == 1000.0
    assert nxt["reached"].item() and not nxt["crashed"].item()
    assert nxt["terminated"].item() and nxt["done"].item()
    # shaping: goal recognised on the way, reward = 100 - distance - |angle|
    assert all(0 < r < 100 for r in rewards[:-1])
    x, y, z, _ = env.drone_pose()
    gp = thesis_layout().goal_point()
    assert np.linalg.norm(np.array([x, y, z]) - gp) <= 0.2
    del td


def test_shaped_reward_formula(envs):
    env = envs["kinematic"]
    env.reset()
    nxt = act(env, "left")
    assert nxt["goal_in_sight"].item()
    expected = 100.0 - nxt["goal_distance"].item() - abs(nxt["goal_angle"].item())
    assert nxt["reward"].item() == pytest.approx(expected, abs=1e-4)


def test_truncation_at_200_steps(envs):
    env = envs["kinematic"]
    env.reset()
    for k in range(200):
        nxt = act(env, "turn_left" if k % 2 == 0 else "turn_right")
        if k < 199:
            assert not nxt["done"].item()
    assert nxt["truncated"].item() and nxt["done"].item() and not nxt["terminated"].item()


# -------------------------------------------------------------------- seeding
@pytest.mark.parametrize("mode", MODES)
def test_same_seed_same_trajectory(mode):
    actions = np.random.default_rng(3).integers(0, 8, size=12)

    def run(seed):
        env = DroneNavEnv(
            "random", n_layouts=50, execution=mode, altitude_noise_std=0.05,
            position_noise_std=0.02, yaw_noise_std_deg=1.0, seed=seed,
        )
        tds = [env.reset()]
        for a in actions:
            nxt = act(env, int(a))
            tds.append(nxt)
            if nxt["done"].item():
                tds.append(env.reset())
        name = env.layout.name
        env.close()
        return name, tds

    n1, a = run(7)
    n2, b = run(7)
    n3, c = run(8)
    assert n1 == n2
    for x, y in zip(a, b):
        for key in ("pixels", "depth", "altitude", "goal_box"):
            assert torch.equal(x[key], y[key]), key
        if "reward" in x.keys():
            assert torch.equal(x["reward"], y["reward"])
    assert n3 != n1 or not all(torch.equal(x["altitude"], y["altitude"]) for x, y in zip(a, c))


# ---------------------------------------------------------------------- specs
def _make_env():
    return DroneNavEnv(seed=0)


def test_check_env_specs_single_serial_parallel():
    from torchrl.envs import ParallelEnv, SerialEnv
    from torchrl.envs.utils import check_env_specs

    env = _make_env()
    check_env_specs(env)
    assert env.action_spec.n == 8
    env.close()
    senv = SerialEnv(2, _make_env)
    check_env_specs(senv)
    senv.close()
    penv = ParallelEnv(2, _make_env, mp_start_method="fork")
    check_env_specs(penv)
    td = penv.rollout(3)
    assert td["pixels"].shape == (2, 3, 84, 84, 3)
    penv.close()


def test_device_option():
    env = DroneNavEnv(seed=0, device="cpu")
    td = env.reset()
    assert td.device == torch.device("cpu") and td["pixels"].device == torch.device("cpu")
    assert env.observation_spec["pixels"].device == torch.device("cpu")
    env.close()


# ------------------------------------------------------------------ gymnasium
def test_gymnasium_registration_and_checker():
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env

    from torchrl_causal.envs.gym_registration import GYM_ID, register_envs

    register_envs()
    env = gym.make(GYM_ID, max_steps=20)
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    # every bool key (out_of_bounds included) is MultiBinary / int8, not a float Box
    for key in ("goal_in_sight", "crashed", "reached", "out_of_bounds"):
        assert isinstance(env.observation_space[key], gym.spaces.MultiBinary), key
        assert obs[key].dtype == np.int8, key
    obs, r, term, trunc, info = env.step(A["forward"])
    assert isinstance(r, float) and set(info) == {"crashed", "reached"}
    env.close()


def test_gymnasium_make_without_prior_import():
    """A fresh interpreter makes the env from the id alone ("module:id" form)."""
    import subprocess
    import sys

    code = (
        "import gymnasium as gym\n"
        "env = gym.make('torchrl_causal.envs:torchrl_causal/DroneNav-v0', max_steps=5)\n"
        "obs, _ = env.reset(seed=0)\n"
        "print(obs['pixels'].shape)\n"
        "env.close()\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "(84, 84, 3)" in out.stdout


# ---------------------------------------------------------------- bad options
@pytest.mark.parametrize(
    "option,value",
    [
        ("step_size", -0.25),
        ("step_size", 0.0),
        ("turn_deg", -15.0),
        ("layout", "maze"),
        ("split", "test"),
        ("image_size", 16),
        ("image_size", (84, 31)),
        ("execution", "teleport"),
        ("max_steps", 0),
        ("reach_radius", -1.0),
        ("goal_min_pixels", 0),
        ("fov_deg", 200.0),
        ("max_depth", 0.0),
        ("altitude_noise_std", -0.1),
        ("action_duration", 0.0),
        ("n_layouts", 0),
        ("layout_index", -1),
    ],
)
def test_bad_option_raises_before_mujoco(monkeypatch, option, value):
    import torchrl_causal.envs.drone as drone

    def boom(*a, **k):  # pragma: no cover - must not be reached
        raise AssertionError("MuJoCo touched before validation")

    monkeypatch.setattr(drone, "build_model", boom)
    monkeypatch.setattr(drone, "SceneRenderer", boom)
    with pytest.raises(ValueError) as err:
        DroneNavEnv(**{option: value})
    msg = str(err.value)
    assert option in msg and repr(value) in msg


def test_timings_count_reset_renders_and_clear_on_reset():
    env = DroneNavEnv(seed=0)
    try:
        env.reset()
        tm = env.timings()
        assert tm["steps"] == 0 and tm["render_ms"] > 0  # the reset's render, over max(1, 0) steps
        act(env, "forward")
        tm = env.timings(reset=True)
        assert tm["steps"] == 1 and tm["render_ms"] > 0 and tm["physics_ms"] > 0
        assert env.timings() == {"render_ms": 0.0, "physics_ms": 0.0, "steps": 0}
    finally:
        env.close()


def test_noise_is_seeded_per_episode_not_by_what_earlier_episodes_did():
    """Issue 'Tello parity', seeded noise: episode i's move/turn/barometer noise
    draws from default_rng([seed, i]), so a second episode flies the same way
    whatever the first one did (and the random layouts stay the same)."""
    import numpy as np
    from tensordict import TensorDict

    def second_episode(first_actions):
        env = DroneNavEnv("random", split="train", image_size=32, seed=11,
                          position_noise_std=0.05, yaw_noise_std_deg=3.0,
                          altitude_noise_std=0.05)
        env.reset()
        for a in first_actions:
            td = env.step(TensorDict({"action": torch.tensor(a)}, []))
            if bool(td["next", "done"]):
                break
        env.reset()
        assert env.episode_noise_seed == (11, 1)
        out = []
        for a in (0, 6, 2, 4, 7, 0):
            td = env.step(TensorDict({"action": torch.tensor(a)}, []))
            out.append((env.layout.name, env._executor.pose(), float(td["next", "altitude"])))
        return out

    a = second_episode([0, 6, 6])
    b = second_episode([7, 2, 4, 4, 6, 1, 0, 7, 7, 3])
    assert a == b
    c = second_episode([])
    assert c == a
    poses = np.array([p for _, p, _ in a])
    assert np.all(np.isfinite(poses))
