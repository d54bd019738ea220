"""The grid world (``GridNavEnv``): TorchRL specs, semantics, causal schema and expert CBNs."""

from __future__ import annotations

import functools

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torchrl_causal.causal import CausalLearner
from torchrl_causal.envs import (
    DEFAULT_GRIDNAV_OBSTACLES,
    GRIDNAV_ACTIONS,
    GRIDNAV_SCHEMA,
    GridNavEnv,
    gridnav_expert_dags,
    make_gridnav_env,
)
from torchrl_causal.envs.gym_registration import GRIDNAV_GYM_ID, register_envs
from torchrl_causal.transforms import Discretize

UP, DOWN, LEFT, RIGHT = range(4)


# ----------------------------------------------------------------- TorchRL
def test_check_env_specs_single_serial_parallel():
    from torchrl.envs import ParallelEnv, SerialEnv
    from torchrl.envs.utils import check_env_specs

    env = make_gridnav_env(seed=0)
    check_env_specs(env)
    assert env.action_spec.n == 4 and env.action_spec.shape == ()
    assert env.action_spec.dtype == torch.int64
    spec = env.observation_spec
    assert spec["observation"].shape == (98,)
    assert spec["reached"].dtype == spec["crashed"].dtype == torch.bool
    assert spec["reached"].shape == spec["crashed"].shape == (1,)
    assert spec["causal_state"].shape == (6,)
    env.close()
    make = functools.partial(make_gridnav_env, seed=None, size=5)
    senv = SerialEnv(2, make)
    senv.set_seed(1)
    check_env_specs(senv)
    senv.close()
    # "fork": the workers start in ~0.1 s (the default "spawn" re-imports torch, ~15 s here)
    penv = ParallelEnv(2, make, mp_start_method="fork")
    penv.set_seed(2)
    check_env_specs(penv)
    td = penv.rollout(4, break_when_any_done=False)
    assert td["next", "observation"].shape == (2, 4, 50)
    assert td["next", "crashed"].shape == (2, 4, 1)
    penv.close()


def test_rollout_flags_rewards_and_truncation():
    env = make_gridnav_env(seed=3, max_steps=3)
    torch.manual_seed(0)  # the rollout's random actions
    td = env.rollout(400, break_when_any_done=False)
    nxt = td["next"]
    r = nxt["reward"].squeeze(-1)
    reached, crashed = nxt["reached"].squeeze(-1), nxt["crashed"].squeeze(-1)
    term, trunc = nxt["terminated"].squeeze(-1), nxt["truncated"].squeeze(-1)
    assert crashed.any() and reached.any() and trunc.any()
    assert torch.equal(term, reached | crashed)
    assert not (trunc & term).any()
    assert torch.all(r[crashed] == -1.0) and torch.all(r[reached] == 1.0)
    moved = ~(reached | crashed)
    assert torch.allclose(r[moved].abs(), torch.tensor(0.1))
    # a truncated step is the 3rd of its episode
    steps = 0
    for i in range(len(td)):
        steps += 1
        if trunc[i]:
            assert steps == 3
        if nxt["done"][i]:
            steps = 0
    # seeding reproduces the rollout
    env2 = make_gridnav_env(seed=3, max_steps=3)
    torch.manual_seed(0)
    a = env2.rollout(20, break_when_any_done=False)
    env3 = make_gridnav_env(seed=3, max_steps=3)
    torch.manual_seed(0)
    b = env3.rollout(20, break_when_any_done=False)
    assert torch.equal(a["observation"], b["observation"]) and torch.equal(a["action"], b["action"])


def test_discretize_codes_match_raw_features():
    env = make_gridnav_env(seed=5)
    torch.manual_seed(0)  # the rollout's random actions
    td = env.rollout(300, break_when_any_done=False)
    for part in (td, td["next"]):
        codes = part["causal_state"]
        blocked = part["blocked"]
        off = part["goal_offset"]
        assert torch.equal(codes[:, :4], (blocked > 0.5).long())
        assert torch.equal(codes[:, 4], off[:, 0].sign().long() + 1)  # above, same, below
        assert torch.equal(codes[:, 5], off[:, 1].sign().long() + 1)  # left, same, right
        # the one-hot cells agree with the offset
        obs = part["observation"]
        agent, goal = obs[:, :49].argmax(-1), obs[:, 49:].argmax(-1)
        assert torch.equal((goal // 7 - agent // 7).float(), off[:, 0])
        assert torch.equal((goal % 7 - agent % 7).float(), off[:, 1])
        assert torch.all(obs.sum(-1) == 2)
    assert set(codes[:, 4].tolist()) == {0, 1, 2}
    assert GRIDNAV_SCHEMA["goal_row"].categories == ("above", "same", "below")
    assert GRIDNAV_SCHEMA["blocked_up"].categories == ("free", "blocked")
    assert GRIDNAV_SCHEMA.n_states == 144


def test_gym_registration():
    register_envs()
    register_envs()
    env = gym.make(GRIDNAV_GYM_ID, size=4, obstacles=[(1, 1)], max_steps=5)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert info == {"success": False, "reached": False, "crashed": False}
    env.close()


# ------------------------------------------------------------ semantics
def test_default_map_and_hand_placed_states():
    env = GridNavEnv()
    assert env.obstacles == tuple(sorted(DEFAULT_GRIDNAV_OBSTACLES))
    obs, _ = env.reset(seed=0, options={"start": (0, 1), "goal": (2, 1)})
    assert obs["blocked"].tolist() == [1.0, 1.0, 0.0, 0.0]  # grid edge above, wall (1, 1) below
    assert obs["goal_offset"].tolist() == [2.0, 0.0]
    assert env.observation_space.contains(obs)
    # into the wall: a crash, the agent stays
    obs2, r, term, trunc, info = env.step(DOWN)
    assert (r, term, trunc) == (-1.0, True, False)
    assert info == {"success": False, "reached": False, "crashed": True}
    assert obs2["crashed"].tolist() == [True] and obs2["reached"].tolist() == [False]
    assert env.agent == (0, 1) and np.array_equal(obs2["observation"], obs["observation"])
    # off the grid
    env.reset(options={"start": (0, 0), "goal": (6, 6)})
    assert env.step(LEFT)[1:3] == (-1.0, True)
    # away from the goal, then towards, then reach it
    env.reset(options={"start": (0, 0), "goal": (0, 2)})
    o, r, term, _, _ = env.step(DOWN)
    assert (env.agent, r, term) == ((1, 0), -0.1, False)
    assert o["goal_offset"].tolist() == [-1.0, 2.0]
    assert env.step(UP)[1] == 0.1
    assert env.step(RIGHT)[1] == 0.1
    o, r, term, trunc, info = env.step(RIGHT)
    assert (r, term, trunc, info["success"]) == (1.0, True, False, True)
    assert o["reached"].tolist() == [True] and o["goal_offset"].tolist() == [0.0, 0.0]


def test_truncation_at_max_steps():
    env = GridNavEnv(max_steps=4)
    env.reset(options={"start": (0, 0), "goal": (6, 6)})
    out = [env.step(a) for a in (RIGHT, LEFT, RIGHT, LEFT)]
    assert [o[3] for o in out] == [False, False, False, True]
    assert not any(o[2] for o in out)


def test_every_move_changes_the_distance_by_one():
    env = GridNavEnv()
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    for _ in range(500):
        before = abs(env.goal[0] - env.agent[0]) + abs(env.goal[1] - env.agent[1])
        _, r, term, trunc, info = env.step(int(rng.integers(4)))
        after = abs(env.goal[0] - env.agent[0]) + abs(env.goal[1] - env.agent[1])
        if info["crashed"]:
            assert after == before and r == -1.0
        else:
            assert abs(after - before) == 1
            assert r == (1.0 if after == 0 else 0.1 if after < before else -0.1)
        if term or trunc:
            env.reset()


def test_oracle_always_succeeds_along_a_shortest_path():
    env = GridNavEnv()
    for seed in range(200):
        env.reset(seed=seed)
        n = env.shortest_path_length()
        manhattan = abs(env.goal[0] - env.agent[0]) + abs(env.goal[1] - env.agent[1])
        assert 1 <= manhattan <= n <= env.max_steps
        rewards = []
        while True:
            _, r, term, trunc, info = env.step(env.oracle_action())
            rewards.append(r)
            if term or trunc:
                break
        assert info["success"] and not info["crashed"]
        assert len(rewards) == n and rewards[-1] == 1.0
        # a detour round a wall costs one step away (-0.1) and one back per extra pair of moves
        assert sorted(rewards[:-1]) == [-0.1] * ((n - manhattan) // 2) + [0.1] * ((n + manhattan) // 2 - 1)


def test_random_policy_rarely_succeeds():
    env = GridNavEnv()
    rng = np.random.default_rng(0)
    outcomes = []
    for seed in range(600):
        env.reset(seed=seed)
        while True:
            _, _, term, trunc, info = env.step(int(rng.integers(4)))
            if term or trunc:
                outcomes.append((info["success"], info["crashed"]))
                break
    success = np.mean([s for s, _ in outcomes])
    crashes = np.mean([c for _, c in outcomes])
    assert 0.005 < success < 0.15  # ~0.03 with these seeds
    assert crashes > 0.8


def test_start_and_goal_are_uniform_free_distinct_cells():
    env = GridNavEnv(size=4, obstacles=[(1, 1), (2, 2)])
    starts, goals = set(), set()
    for seed in range(300):
        env.reset(seed=seed)
        assert env.agent != env.goal
        assert not env.walls[env.agent] and not env.walls[env.goal]
        starts.add(env.agent)
        goals.add(env.goal)
    assert len(starts) == len(goals) == 14
    a = GridNavEnv().reset(seed=7)[0]
    b = GridNavEnv().reset(seed=7)[0]
    assert np.array_equal(a["observation"], b["observation"])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"size": 1}, "size must be an int >= 2, got 1"),
        ({"size": 7.0}, "size must be an int >= 2, got 7.0"),
        ({"max_steps": 0}, "max_steps must be an int >= 1, got 0"),
        ({"obstacles": [(7, 0)]}, r"obstacle \(7, 0\) is outside the 7x7 grid"),
        ({"obstacles": [(1,)]}, r"obstacle must be a \(row, col\) pair of ints, got \(1,\)"),
        ({"size": 3, "obstacles": [(0, 1), (1, 1), (2, 1)]}, r"cut the free cells .* cannot reach \(0, 2\)"),
        ({"size": 2, "obstacles": [(0, 0), (0, 1), (1, 0)]}, "leave 1 free cell"),
        ({"render_mode": "human"}, "render_mode must be None or 'ansi', got 'human'"),
    ],
)
def test_bad_options_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GridNavEnv(**kwargs)


@pytest.mark.parametrize(
    "options, match",
    [
        ({"start": (1, 1)}, r"start \(1, 1\) is a wall cell"),
        ({"goal": (3, 3)}, r"goal \(3, 3\) is a wall cell"),
        ({"start": (0, 9)}, r"start \(0, 9\) is outside the 7x7 grid"),
        ({"start": (0, 0), "goal": (0, 0)}, r"start \(0, 0\) and goal \(0, 0\) are the same cell"),
    ],
)
def test_bad_reset_options_raise(options, match):
    with pytest.raises(ValueError, match=match):
        GridNavEnv().reset(options=options)


def test_step_before_reset_and_bad_action():
    env = GridNavEnv()
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action must be in"):
        env.step(4)


# ---------------------------------------------------------------- causal
def _random_transitions(n: int, seed: int = 0):
    """``n`` random-policy transitions, coded with ``Discretize(GRIDNAV_SCHEMA)``."""
    env = GridNavEnv()
    rng = np.random.default_rng(seed)
    feats = {"t": [], "t1": []}
    actions, rewards = [], []
    obs, _ = env.reset(seed=seed)
    for _ in range(n):
        a = int(rng.integers(4))
        nxt, r, term, trunc, _ = env.step(a)
        feats["t"].append(obs)
        feats["t1"].append(nxt)
        actions.append(a)
        rewards.append(r)
        obs = env.reset()[0] if term or trunc else nxt
    disc = Discretize(schema=GRIDNAV_SCHEMA)
    codes = {}
    for k, rows in feats.items():
        td = TensorDict(
            {key: torch.as_tensor(np.stack([o[key] for o in rows])) for key in ("blocked", "goal_offset")},
            [n],
        )
        codes[k] = disc(td)["causal_state"]
    return codes["t"], torch.tensor(actions), codes["t1"], torch.tensor(rewards, dtype=torch.float32)


def _p_pos(tables, action: str, **values) -> torch.Tensor:
    """P(positive | state_t) of ``action`` over every joint state matching ``values``."""
    states = torch.as_tensor(GRIDNAV_SCHEMA.all_states())
    mask = torch.ones(len(states), dtype=torch.bool)
    for name, label in values.items():
        var = GRIDNAV_SCHEMA[name]
        mask &= states[:, GRIDNAV_SCHEMA.index(name)] == var.categories.index(label)
    p_pos, _, known = tables.lookup(states[mask])
    a = GRIDNAV_ACTIONS.index(action)
    assert known[:, a].all()
    return p_pos[:, a]


def test_expert_dags_shape_and_time_tiers():
    dags = gridnav_expert_dags()
    assert list(dags) == list(GRIDNAV_ACTIONS)
    nodes = set(GRIDNAV_SCHEMA.node_names())
    for action, edges in dags.items():
        axis = "goal_row" if action in ("up", "down") else "goal_col"
        assert {s for s, t in edges if t == "reward"} == {f"blocked_{action}_t", f"{axis}_t"}
        for s, t in edges:
            assert s in nodes and t in nodes and s.endswith("_t") and t != s
    with pytest.raises(ValueError, match="schema lacks the grid-world variables"):
        from torchrl_causal.schema import DEFAULT_SCHEMA

        gridnav_expert_dags(DEFAULT_SCHEMA)


def test_defined_learner_tables_follow_the_known_structure(tmp_path):
    learner = CausalLearner(
        GRIDNAV_SCHEMA, 4, mode="defined", expert_dags=gridnav_expert_dags(), min_rows=30
    )
    assert learner.action_names == list(GRIDNAV_ACTIONS)
    assert learner.expert == gridnav_expert_dags()
    learner.add(*_random_transitions(2000, seed=0))
    tables = learner.relearn()
    assert tables.known.all()
    for action, axis, towards in (
        ("up", "goal_row", "above"),
        ("down", "goal_row", "below"),
        ("left", "goal_col", "left"),
        ("right", "goal_col", "right"),
    ):
        assert _p_pos(tables, action, **{f"blocked_{action}": "blocked"}).max() < 0.2
        assert _p_pos(tables, action, **{f"blocked_{action}": "free", axis: towards}).min() > 0.8
        assert _p_pos(tables, action, **{f"blocked_{action}": "free", axis: "same"}).max() < 0.2
    assert learner.dags() == gridnav_expert_dags()
    assert learner.history_dags(-1) == gridnav_expert_dags()
    assert learner.first_searched_dags() == {a: [] for a in GRIDNAV_ACTIONS}  # nothing searched
    # persistence
    sd = learner.state_dict()
    other = CausalLearner(GRIDNAV_SCHEMA, 4, mode="defined", expert_dags=gridnav_expert_dags())
    other.load_state_dict(sd)
    assert torch.equal(other.tables.p_pos, tables.p_pos)
    out = learner.save(tmp_path / "cbns", fmt=".json")
    assert sorted(p.name for p in out.iterdir()) == sorted([f"{a}.json" for a in GRIDNAV_ACTIONS] + ["learner.json"])
    wrong_names = CausalLearner(GRIDNAV_SCHEMA, 4, action_names=["n", "s", "w", "e"])
    with pytest.raises(ValueError, match="state dict is for actions"):
        wrong_names.load_state_dict(sd)


def test_learned_mode_finds_the_crash_edges():
    learner = CausalLearner(GRIDNAV_SCHEMA, 4, mode="learned", action_names=GRIDNAV_ACTIONS)
    assert learner.expert is None
    learner.add(*_random_transitions(3000, seed=1))
    learner.relearn()
    dags = learner.dags()
    for action in GRIDNAV_ACTIONS:
        # BIC recovers exactly the true reward parents: the blocking wall and the goal's side
        axis = "goal_row" if action in ("up", "down") else "goal_col"
        parents = {s for s, t in dags[action] if t == "reward"}
        assert parents == {f"blocked_{action}_t", f"{axis}_t"}, (action, dags[action])
        # time tiers: nothing points back from reward or t+1 into t
        assert all(s.endswith("_t") or t == "reward" for s, t in dags[action])
    assert learner.first_searched_dags() == dags
    # the expert may be kept as a reference while the search ignores it
    ref = CausalLearner(GRIDNAV_SCHEMA, 4, expert_dags=gridnav_expert_dags())
    assert ref.expert == gridnav_expert_dags() and ref.dags() == {a: [] for a in GRIDNAV_ACTIONS}


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n_actions": 8}, r"expert_dags has 4 DAGs .* but n_actions=8"),
        ({"expert_dags": {**gridnav_expert_dags(), "up": [("blocked_top_t", "reward")]}},
         r"expert_dags\['up'\]: edge \('blocked_top_t', 'reward'\) names 'blocked_top_t'"),
        ({"expert_dags": {**gridnav_expert_dags(), "up": [("goal_row_t1", "goal_row_t")]}},
         r"expert_dags\['up'\]: edge \('goal_row_t1', 'goal_row_t'\) does not go forward in time"),
        ({"expert_dags": {**gridnav_expert_dags(), "up": [("goal_row_t", "goal_col_t")]}},
         "does not go forward in time"),
        ({"action_names": ["a", "b", "c", "d"]}, "must be the keys of expert_dags"),
        ({"action_names": ["up", "down"]}, "action_names has 2 names"),
    ],
)
def test_learner_rejects_bad_expert_options(kwargs, match):
    opts = {"n_actions": 4, "mode": "defined", "expert_dags": gridnav_expert_dags(), **kwargs}
    with pytest.raises(ValueError, match=match):
        CausalLearner(GRIDNAV_SCHEMA, **opts)
