"""GoalSearch: the search for a goal hidden behind an obstacle, on the drone's own map."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from torchrl_causal.envs import DroneNavEnv
from torchrl_causal.envs.layouts import Layout, Obstacle
from torchrl_causal.modules import GoalSearch
from torchrl_causal.pretrained import PolicySpec
from torchrl_causal.pretrained.policy import policy_guards
from torchrl_causal.transforms import EgoMap


def _td(occ=None, pose=(0.0, 0.0, 0.0), seen=False, action=0, mask=None, history=None):
    ego = torch.zeros(3, 32, 32, dtype=torch.uint8)
    if occ is not None:
        ego[0][occ] = 255
    td = TensorDict({"action": torch.tensor(action), "ego_map": ego,
                     "ego_pose": torch.tensor(pose, dtype=torch.float32),
                     "goal_seen": torch.tensor([seen]),
                     "action_mask": torch.ones(8, dtype=torch.bool) if mask is None else mask,
                     "goal_memory": torch.tensor([1.0, 0.6, 0.0, 0.0, 0.6, 0.0])}, [])
    if history is not None:
        td.set("action_history", history)
    return td


def _wall_ahead():
    occ = torch.zeros(32, 32, dtype=torch.bool)
    occ[10, 8:24] = True  # a wall 0.9 m ahead, 2.4 m wide, across the line
    return occ


def test_the_search_goes_round_an_obstacle_across_the_line_not_into_it():
    search = GoalSearch()
    td = search(_td(_wall_ahead()))
    assert td["goal_search_fired"].item()
    # far from the wall the way ahead still gets closer; next to it, it sidesteps
    occ = torch.zeros(32, 32, dtype=torch.bool)
    occ[13, 10:22] = True  # 0.45 m ahead
    a = search(_td(occ))["action"].item()
    assert a in (2, 3)  # left or right, the camera still on the searched point
    mask = torch.ones(8, dtype=torch.bool)
    mask[a] = False  # that side is not allowed: the other one
    assert search(_td(occ, mask=mask))["action"].item() == 5 - a


def test_the_search_keeps_the_camera_on_the_searched_point():
    search = GoalSearch(distance=4.0, turn_tolerance_deg=20.0)
    # the drone turned 40 deg left of the start heading: turn right, back towards it
    assert search(_td(pose=(0.0, 0.0, math.radians(40))))["action"].item() == 7
    assert search(_td(pose=(0.0, 0.0, math.radians(-40))))["action"].item() == 6
    # ... but not straight back after the previous turn the other way (no back and forth)
    hist = torch.zeros(4, 8)
    hist[0, 6] = 1  # the last action: turn left
    out = search(_td(pose=(0.0, 0.0, math.radians(40)), history=hist.flatten()))
    assert out["action"].item() != 7


def test_the_policy_keeps_its_action_once_the_goal_has_been_seen():
    search = GoalSearch()
    td = search(_td(_wall_ahead(), seen=True, action=5))
    assert td["action"].item() == 5 and not td["goal_search_fired"].item()
    # ... unless it is stuck turning back and forth: one planner step to the remembered goal
    hist = torch.zeros(4, 8)
    hist[[0, 1, 2, 3], [6, 7, 6, 7]] = 1
    occ = torch.zeros(32, 32, dtype=torch.bool)
    td = search(_td(occ, seen=True, action=6, history=hist.flatten()))
    assert td["goal_search_fired"].item() and td["action"].item() == 0  # the goal is ahead
    assert not GoalSearch(stuck_turns=0)(_td(occ, seen=True, action=6, history=hist.flatten())
                                         )["goal_search_fired"].item()


def test_the_search_reads_a_batch_and_replaces_only_the_unseen_entries():
    tds = torch.stack([_td(_wall_ahead(), seen=False, action=4),
                       _td(_wall_ahead(), seen=True, action=4)])
    out = GoalSearch()(tds)
    assert out["goal_search_fired"].tolist() == [[True], [False]] or \
        out["goal_search_fired"].reshape(-1).tolist() == [True, False]
    assert out["action"][1].item() == 4 and out["action"][0].item() != 4


@pytest.mark.parametrize("kwargs, name", [
    ({"distance": 0.0}, "distance"), ({"distance": float("nan")}, "distance"),
    ({"lead": -1.0}, "lead"), ({"inflate": -0.1}, "inflate"),
    ({"turn_tolerance_deg": 95.0}, "turn_tolerance_deg"), ({"stuck_turns": -1}, "stuck_turns"),
    ({"stuck_turns": True}, "stuck_turns"), ({"resolution": 0}, "resolution"),
])
def test_bad_options_are_named(kwargs, name):
    with pytest.raises(ValueError, match=name):
        GoalSearch(**kwargs)


def test_a_one_hot_or_float_action_is_refused():
    td = _td()
    td.set("action", torch.zeros(8))
    with pytest.raises(ValueError, match="action index"):
        GoalSearch()(td)


def test_policy_spec_goal_search_appends_the_search_last():
    spec = PolicySpec(inputs=["causal_features", "goal_memory", "map_clearance",
                              "action_history"], history=4, image=False, shield=True,
                      loop_guard=True, goal_search=4.0, ego_map={"resolution": 0.15})
    guards = policy_guards(spec)
    assert [type(m).__name__ for m in guards] == ["LoopGuard", "GoalSearch"]
    assert guards[1].distance == 4.0 and guards[1].action_mask_key == "action_mask"
    assert PolicySpec.from_json(spec.to_json()).goal_search == 4.0
    for bad in (-1.0, float("inf"), True, "4"):
        with pytest.raises(ValueError, match="goal_search"):
            PolicySpec(inputs=["goal_memory"], image=False, goal_search=bad)
    with pytest.raises(ValueError, match="goal_search needs EgoMap"):
        PolicySpec(inputs=["causal_features"], image=False, goal_search=4.0)


def _hidden_goal_layout(side: float) -> Layout:
    """A wall across the line of sight, 2 m ahead; the goal board 4.5 m ahead, behind it."""
    return Layout(
        name="hidden-goal", arena=(-1.2, -3.0, 6.5, 3.0), height=2.8,
        start_pos=(0.0, 0.0, 1.1), start_yaw_deg=0.0,
        goal_center=(4.8, side, 1.1), goal_yaw_deg=180.0, goal_size=(0.8, 0.7),
        obstacles=(Obstacle(center=(2.2, 0.1 * side, 1.2), half_size=(0.15, 0.55, 1.2),
                            rgba=(0.6, 0.3, 0.3, 1.0)),))


@pytest.mark.parametrize("side", [-0.3, 0.3])
def test_a_goal_hidden_behind_a_wall_is_found_on_the_drones_own_map(side):
    """Real MuJoCo scene: the start does not see the goal; the search (in place of a policy
    that only ascends) flies round the wall and sees it, without a crash or an exit."""
    env = TransformedEnv(DroneNavEnv(_hidden_goal_layout(side), image_size=48, seed=0),
                         EgoMap())
    search = GoalSearch()
    td = env.reset()
    assert not td["goal_seen"].item()  # hidden at the start

    def policy(td):
        return search(td.set("action", torch.tensor(4)))

    roll = env.rollout(60, policy, auto_reset=False, tensordict=td, break_when_any_done=True)
    seen = roll["next", "goal_seen"].reshape(-1)
    assert seen.any(), "the search never saw the goal"
    first = int(np.argmax(seen.numpy()))
    assert first < 40
    until = slice(0, first + 1)  # from then on the stand-in policy ascends out of the volume
    assert not roll["next", "crashed"][until].any()
    assert not roll["next", "out_of_bounds"][until].any()
    fired = roll["goal_search_fired"].reshape(-1)
    assert fired[: first + 1].all()  # it chose every action while the goal was unseen


def test_egomap_writes_the_dead_reckoned_pose_and_whether_the_goal_was_really_seen():
    env = TransformedEnv(DroneNavEnv(_hidden_goal_layout(0.3), image_size=32, seed=0),
                         EgoMap(goal_prior=4.0))
    td = env.reset()
    # the prior makes the memory "known", but the goal has not been seen
    assert td["goal_memory"][0].item() == 1.0 and not td["goal_seen"].item()
    assert torch.allclose(td["ego_pose"], torch.zeros(3))
    td = env.step(td.set("action", torch.tensor(3)))["next"]  # right, 0.25 m
    assert torch.allclose(td["ego_pose"], torch.tensor([0.0, -0.25, 0.0]), atol=1e-5)
    td = env.step(td.set("action", torch.tensor(6)))["next"]  # turn left 15 deg
    assert td["ego_pose"][2].item() == pytest.approx(math.radians(15.0), abs=1e-5)
