"""VisitMemory + RevisitGuard: cycles of any length are broken (real env, real dead reckoning)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs import SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from torchrl_causal.envs import DroneNavEnv
from torchrl_causal.modules import RevisitGuard
from torchrl_causal.pretrained.policy import PolicySpec, policy_guards, policy_transforms
from torchrl_causal.schema import ACTION_NAMES
from torchrl_causal.transforms import EgoMap, VisitMemory

FWD, BACK, LEFT, RIGHT, UP, DOWN, TL, TR = range(8)
assert ACTION_NAMES[TL] == "turn_left" and ACTION_NAMES[UP] == "ascend"


def _env(seed=0, max_steps=60):
    env = TransformedEnv(DroneNavEnv(seed=seed, image_size=32, max_steps=max_steps), EgoMap())
    env.append_transform(VisitMemory())
    return env


def _step(env, td, a):
    return env.step(td.set("action", torch.tensor(a)))["next"]


def test_counts_follow_the_dead_reckoned_pose():
    env = _env()
    td = env.reset()
    assert td["visit_counts"].sum() == 0
    # a square of four moves comes back to the start: forward was taken from it once
    for a in (LEFT, FWD, RIGHT, BACK):
        td = _step(env, td, a)
    assert td["visit_counts"].tolist() == [0, 0, 1, 0, 0, 0, 0, 0]
    # a full turn in place (24 turns of 15 deg) comes back to the same pose and heading
    for _ in range(24):
        td = _step(env, td, TL)
    assert td["visit_counts"][[LEFT, TL]].tolist() == [1, 1]
    # the same x, y and heading one step higher is another pose
    td = _step(env, td, UP)
    assert td["visit_counts"].sum() == 0
    td = _step(env, td, DOWN)
    assert td["visit_counts"][UP].item() == 1
    # a new episode forgets
    td = env.reset()
    assert td["visit_counts"].sum() == 0
    env.close()


def test_specs_alone_and_batched():
    check_env_specs(_env())
    penv = SerialEnv(2, lambda: _env())
    check_env_specs(penv)
    td = penv.reset()
    assert td["visit_counts"].shape == (2, 8)
    penv.close()


def test_guard_prefers_the_least_tried_allowed_action():
    guard = RevisitGuard(action_mask_key="action_mask")
    q = torch.tensor([5.0, 4.0, 1.0, 3.0, 0.0, 0.0, 2.0, 0.0])
    allowed = torch.ones(8, dtype=torch.bool)
    cases = [  # (counts, chosen, expected)
        ([0, 0, 0, 0, 0, 0, 0, 0], FWD, FWD),   # a new pose: unchanged
        ([1, 0, 0, 0, 0, 0, 0, 0], FWD, BACK),  # forward taken: the best untried
        ([1, 1, 1, 1, 1, 1, 1, 1], FWD, FWD),   # every way tried once: unchanged
        ([2, 1, 1, 1, 1, 1, 1, 1], FWD, BACK),  # forward tried most: the best of the least
        ([0, 1, 0, 0, 0, 0, 0, 0], FWD, FWD),   # another was taken: unchanged
    ]
    for counts, chosen, expect in cases:
        td = TensorDict({"visit_counts": torch.tensor(counts, dtype=torch.float32),
                         "action": torch.tensor(chosen), "action_value": q,
                         "action_mask": allowed}, [])
        assert guard(td)["action"].item() == expect, counts
        assert td["revisit_guard_fired"].item() == (expect != chosen)
    # masked moves are never chosen; nothing less tried allowed -> unchanged
    mask = torch.zeros(8, dtype=torch.bool)
    mask[[FWD, LEFT]] = True
    td = TensorDict({"visit_counts": torch.tensor([1.0, 0, 0, 0, 0, 0, 0, 0]),
                     "action": torch.tensor(FWD), "action_value": q, "action_mask": mask}, [])
    assert guard(td)["action"].item() == LEFT
    td = TensorDict({"visit_counts": torch.tensor([1.0, 0, 1, 0, 0, 0, 0, 0]),
                     "action": torch.tensor(FWD), "action_value": q, "action_mask": mask}, [])
    assert guard(td)["action"].item() == FWD
    # repeats=2 lets an action be taken twice from one pose
    td = TensorDict({"visit_counts": torch.tensor([1.0, 0, 0, 0, 0, 0, 0, 0]),
                     "action": torch.tensor(FWD), "action_value": q}, [])
    assert RevisitGuard(repeats=2)(td)["action"].item() == FWD
    # batched
    td = TensorDict({"visit_counts": torch.tensor([[1.0] + [0] * 7, [0.0] * 8]),
                     "action": torch.tensor([FWD, FWD]), "action_value": q.expand(2, 8)}, [2])
    assert RevisitGuard()(td)["action"].tolist() == [BACK, FWD]


def test_breaks_a_four_move_cycle_that_the_loop_guard_cannot_see():
    """A policy flying a square (left, forward, right, back) for ever comes back to its
    start every four moves; behind the guard it leaves the cycle at the first return."""
    env = _env(max_steps=40)
    square = {LEFT: FWD, FWD: RIGHT, RIGHT: BACK, BACK: LEFT}

    class Square:
        def __init__(self):
            self.last = BACK

        def __call__(self, counts):
            a = square[self.last]
            self.last = a
            q = torch.zeros(8)
            q[a], q[TL] = 2.0, 1.0
            return q, torch.tensor(a)

    for guarded in (False, True):
        actor = TensorDictModule(Square(), in_keys=["visit_counts"],
                                 out_keys=["action_value", "action"])
        policy = TensorDictSequential(actor, RevisitGuard()) if guarded else actor
        env.set_seed(0)
        td = env.rollout(12, policy, break_when_any_done=False)
        actions = td["action"].tolist()
        assert actions[:4] == [LEFT, FWD, RIGHT, BACK]
        if guarded:
            assert td["revisit_guard_fired"][4].item() and actions[4] != LEFT
            assert not td["revisit_guard_fired"][:4].any()
        else:
            assert actions == [LEFT, FWD, RIGHT, BACK] * 3
    env.close()


def test_policy_spec_builds_it():
    spec = PolicySpec(inputs=["causal_features", "map_clearance"], image=False, shield=True,
                      revisit_guard=True)
    names = [type(t).__name__ for t in policy_transforms(spec)]
    assert names[names.index("EgoMap") + 1] == "VisitMemory"
    guards = policy_guards(spec)
    assert [type(m).__name__ for m in guards] == ["RevisitGuard"]
    assert guards[0].action_mask_key == "action_mask"
    with pytest.raises(ValueError, match="revisit_guard needs EgoMap"):
        PolicySpec(inputs=["causal_features"], image=False, revisit_guard=True)


@pytest.mark.parametrize("cls,kw,match", [
    (RevisitGuard, {"repeats": 0}, "repeats"), (RevisitGuard, {"n_actions": 1}, "n_actions"),
    (VisitMemory, {"position_resolution": 0}, "position_resolution"),
    (VisitMemory, {"heading_resolution_deg": float("nan")}, "heading_resolution_deg"),
])
def test_bad_options_are_named(cls, kw, match):
    with pytest.raises(ValueError, match=match):
        cls(**kw)


def test_without_a_pose_it_says_what_to_do():
    env = TransformedEnv(DroneNavEnv(seed=0, image_size=32), VisitMemory())
    with pytest.raises(KeyError, match="after EgoMap"):
        env.reset()


def test_a_shipped_copy_with_the_options_loads_them(tmp_path):
    """ship_policy --revisit-guard --geofence env: the shipped folder rebuilds a policy with a
    RevisitGuard after the LoopGuard and an EgoMap fenced by the env, and says so."""
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recipes"))
    import ship_policy

    from torchrl_causal.pretrained import policy_dir
    from torchrl_causal.pretrained.policy import load_policy_dir

    out = ship_policy.ship(policy_dir("generalist"), "gen_copy", dest=tmp_path,
                           revisit_guard=True, geofence="env")
    prov = json.loads((out / "provenance.json").read_text())
    assert "revisit_guard" in prov and "geofence" in prov
    # shipped again from a shipped folder: the run's record carries over
    old = json.loads((policy_dir("generalist") / "provenance.json").read_text())
    assert prov["teacher"] == old["teacher"] and prov["final_eval"] == old["final_eval"]
    assert prov["seed"] == old["seed"] and prov["shipped_from"]["name"] == "generalist"
    policy, env, spec = load_policy_dir(out, env=DroneNavEnv("random", split="heldout", seed=0))
    assert spec.revisit_guard and spec.ego_map["geofence"] == "env"
    assert [type(m).__name__ for m in policy][-2:] == ["LoopGuard", "RevisitGuard"]
    assert "visit_counts" in env.reset().keys()
    for bad, match in ((dict(geofence="room"), "--geofence"),):
        with pytest.raises(ValueError, match=match):
            ship_policy.ship(policy_dir("generalist"), "gen_bad", dest=tmp_path, **bad)
    env.close()
