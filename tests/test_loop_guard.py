"""LoopGuard: a deterministic policy never repeats a two-move loop (real env, real history)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs import TransformedEnv

from torchrl_causal.envs import DroneNavEnv
from torchrl_causal.modules import INVERSE_ACTIONS, LoopGuard
from torchrl_causal.schema import ACTION_NAMES
from torchrl_causal.transforms import ActionHistory

FWD, BACK, LEFT = (ACTION_NAMES.index(n) for n in ("forward", "backward", "left"))


def _history(*actions):
    """One-hot history, most recent first (as ActionHistory writes it)."""
    h = torch.zeros(4, 8)
    for i, a in enumerate(actions):
        h[i, a] = 1
    return h.flatten()


def test_inverse_actions_undo_each_move():
    from torchrl_causal.envs.control import action_deltas

    deltas = action_deltas(0.25, 15.0)
    for a, b in enumerate(INVERSE_ACTIONS):
        assert INVERSE_ACTIONS[b] == a and a != b
        assert all(x == -y for x, y in zip(deltas[a], deltas[b]))


def test_fires_only_on_a_repeated_two_move_loop():
    guard = LoopGuard(action_mask_key="action_mask")
    q = torch.tensor([5.0, 4.0, 1.0, 3.0, 0.0, 0.0, 0.0, 0.0])
    cases = [  # (history most recent first, chosen, expected)
        ((BACK, FWD, BACK, FWD), FWD, 1),       # fires: the best other action
        ((BACK, FWD, BACK, FWD), LEFT, LEFT),   # another action: passed through
        ((BACK, FWD, BACK, LEFT), FWD, FWD),    # only three moves of the loop
        ((BACK, FWD, BACK), FWD, FWD),          # too short a history
        ((FWD, FWD, FWD, FWD), FWD, FWD),       # going on is not a loop
    ]
    for hist, chosen, expect in cases:
        td = TensorDict({"action_history": _history(*hist), "action": torch.tensor(chosen),
                         "action_value": q, "action_mask": torch.ones(8, dtype=torch.bool)}, [])
        assert guard(td)["action"].item() == expect, hist
        assert td["loop_guard_fired"].item() == (expect != chosen)
    # the mask: the best other action must be allowed; nothing else allowed -> unchanged
    mask = torch.zeros(8, dtype=torch.bool)
    mask[[FWD, 3]] = True
    td = TensorDict({"action_history": _history(BACK, FWD, BACK, FWD), "action": torch.tensor(FWD),
                     "action_value": q, "action_mask": mask}, [])
    assert guard(td)["action"].item() == 3
    mask[3] = False
    assert guard(td.set("action", torch.tensor(FWD)))["action"].item() == FWD
    # batched
    td = TensorDict({"action_history": torch.stack([_history(BACK, FWD, BACK, FWD),
                                                    _history(LEFT, LEFT, LEFT, LEFT)]),
                     "action": torch.tensor([FWD, FWD]), "action_value": q.expand(2, 8)}, [2])
    assert LoopGuard()(td)["action"].tolist() == [1, FWD]


def test_breaks_the_loop_of_a_deterministic_policy_in_the_real_env():
    """A policy that answers forward with backward and backward with forward stays in
    place for ever; behind the guard the drone leaves after four moves."""
    env = TransformedEnv(DroneNavEnv(seed=0, max_steps=40), ActionHistory(8, length=4))

    def oscillate(hist):
        last = hist[..., :8].argmax(-1)
        q = torch.zeros(*hist.shape[:-1], 8)
        q[..., LEFT] = 1.0  # the second choice
        q[..., FWD] = torch.where(last == FWD, 0.0, 2.0)
        q[..., BACK] = torch.where(last == FWD, 2.0, 0.0)
        return q, q.argmax(-1)

    actor = TensorDictModule(oscillate, in_keys=["action_history"],
                             out_keys=["action_value", "action"])
    for guard in (False, True):
        policy = TensorDictSequential(actor, LoopGuard()) if guard else actor
        env.set_seed(0)
        first = env.reset()
        start = env.base_env.drone_pose()
        td = env.rollout(12, policy, break_when_any_done=False, auto_reset=False,
                         tensordict=first)
        actions = td["action"].tolist()
        assert actions[:4] == [BACK, FWD, BACK, FWD]  # no history yet: "last" reads forward
        if guard:
            assert actions[4] == LEFT and td["loop_guard_fired"][4].item()
            assert not td["loop_guard_fired"][:4].any()
            assert env.base_env.drone_pose()[:2] != start[:2]  # it left the loop's two cells
        else:
            assert actions == [BACK, FWD] * 6
            assert env.base_env.drone_pose()[:2] == pytest.approx(start[:2], abs=1e-6)
    env.close()


@pytest.mark.parametrize("kw,match", [({"n_actions": 1}, "n_actions"),
                                      ({"inverse": (1, 0)}, "inverse"),
                                      ({"inverse": tuple(range(8))}, "inverse")])
def test_bad_options_are_named(kw, match):
    with pytest.raises(ValueError, match=match):
        LoopGuard(**kw)


def test_a_short_history_or_a_one_hot_action_is_refused():
    td = TensorDict({"action_history": torch.zeros(16), "action": torch.tensor(0),
                     "action_value": torch.zeros(8)}, [])
    with pytest.raises(ValueError, match=">= 4 one-hot blocks"):
        LoopGuard()(td)
    td = TensorDict({"action_history": torch.zeros(32), "action": torch.zeros(8),
                     "action_value": torch.zeros(8)}, [])
    with pytest.raises(ValueError, match="action index"):
        LoopGuard()(td)
