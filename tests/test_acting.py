"""EGreedyQValuePolicy: TensorDictSequential(QValueActor, EGreedyModule), bit for bit."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import pandas as pd
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Categorical, OneHot
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import EGreedyModule, QValueActor

from torchrl_causal.modules import CBNGate, EGreedyQValuePolicy, LoopGuard, acting_policy
from torchrl_causal.modules.acting import qvalue_parts

ROOT = Path(__file__).resolve().parents[1]


def _policy(one_hot=False, eps=0.5, mask=False, seed=0, n=5):
    torch.manual_seed(seed)
    spec = OneHot(n) if one_hot else Categorical(n)
    net = nn.Sequential(nn.Linear(3, 16), nn.ReLU(), nn.Linear(16, n))
    actor = QValueActor(net, in_keys=["obs"], spec=spec,
                        action_mask_key="mask" if mask else None)
    explorer = EGreedyModule(spec, eps_init=eps, eps_end=0.0, annealing_num_steps=10,
                             action_mask_key="mask" if mask else None)
    return actor, explorer


@pytest.mark.parametrize("one_hot", [False, True])
@pytest.mark.parametrize("batch", [(), (16,), (2, 3)])
@pytest.mark.parametrize("eps", [0.0, 0.5, 1.0])
def test_same_outputs_and_random_draws_as_the_sequence(one_hot, batch, eps):
    actor, explorer = _policy(one_hot, eps)
    fused, seq = EGreedyQValuePolicy(actor, explorer), TensorDictSequential(actor, explorer)
    assert fused.in_keys == seq.in_keys and fused.out_keys == seq.out_keys
    gen = torch.Generator().manual_seed(1)
    explored = 0
    for i in range(60):
        td = TensorDict({"obs": torch.randn(*batch, 3, generator=gen)}, list(batch))
        torch.manual_seed(i)
        a = fused(td.clone())
        after_fused = torch.rand(())  # the global RNG moved exactly as much
        torch.manual_seed(i)
        b = seq(td.clone())
        assert torch.rand(()) == after_fused
        for key in seq.out_keys:
            assert torch.equal(a[key], b[key]), key
        greedy = b["action_value"].argmax(-1)
        action = b["action"].argmax(-1) if one_hot else b["action"]
        explored += int((action != greedy).sum())
        explorer.step()  # eps anneals: the fused policy reads it live
    if eps == 0.0:
        assert explored == 0
    else:
        assert explored > 0


def test_state_dict_holds_the_actor_and_explorer_once():
    actor, explorer = _policy()
    fused = EGreedyQValuePolicy(actor, explorer)
    keys = set(fused.state_dict())
    assert keys == ({f"actor.{k}" for k in actor.state_dict()}
                    | {f"explorer.{k}" for k in explorer.state_dict()})
    other_actor, other_explorer = _policy(seed=1)
    fused.load_state_dict(EGreedyQValuePolicy(other_actor, other_explorer).state_dict())
    assert all(torch.equal(a, b) for a, b in zip(actor.parameters(), other_actor.parameters()))


def test_greedy_under_deterministic_exploration():
    actor, explorer = _policy(eps=1.0)
    fused = EGreedyQValuePolicy(actor, explorer)
    td = TensorDict({"obs": torch.randn(32, 3)}, [32])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        state = torch.get_rng_state()
        out = fused(td.clone())
        assert torch.equal(torch.get_rng_state(), state)  # no draw
    assert torch.equal(out["action"], out["action_value"].argmax(-1))


def test_layouts_it_does_not_cover_keep_the_sequence():
    actor, explorer = _policy(mask=True)
    with pytest.raises(ValueError, match="action mask"):
        EGreedyQValuePolicy(actor, explorer)
    assert type(acting_policy(actor, explorer)) is TensorDictSequential

    actor, _ = _policy()
    gate = CBNGate("v2", seed=0)
    with pytest.raises(ValueError, match="CBNGate, not an EGreedyModule"):
        EGreedyQValuePolicy(actor, gate)
    assert type(acting_policy(actor, gate)) is TensorDictSequential

    # a network split over two TensorDictModules is not QValueActor's layout
    split = TensorDictSequential(TensorDictModule(nn.Linear(3, 8), ["obs"], ["h"]),
                                 QValueActor(nn.Linear(8, 5), in_keys=["h"], spec=Categorical(5)))
    assert qvalue_parts(split) is None
    with pytest.raises(ValueError, match="not a QValueActor layout"):
        EGreedyQValuePolicy(split, EGreedyModule(Categorical(5)))


def test_guards_run_after_the_fused_policy():
    actor, explorer = _policy(eps=0.0, n=4)
    guard = LoopGuard(n_actions=4, inverse=(1, 0, 3, 2))
    policy = acting_policy(actor, explorer, guard)
    assert isinstance(policy, TensorDictSequential)
    assert isinstance(policy.module[0], EGreedyQValuePolicy) and policy.module[1] is guard


@pytest.mark.parametrize("overlap", [False, True])
def test_the_loop_trains_the_same_with_either_policy(tmp_path, overlap):
    """The grid world's DQNLoop with epsilon-greedy (a real env): fused vs sequential acting."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import gridnav

    torch.set_num_threads(1)
    summaries = {}
    for fused in (True, False):
        loop = gridnav.build_loop("dqn", 0, 600, output_dir=tmp_path / str(fused),
                                  fused_acting=fused, overlap=overlap)
        assert isinstance(loop.collector_policy, EGreedyQValuePolicy) == fused
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            summaries[fused] = loop.run()
    a, b = (pd.read_csv(tmp_path / str(f) / "episodes.csv") for f in (True, False))
    pd.testing.assert_frame_equal(a, b)
    assert len(a) > 5
    ma, mb = (torch.load(tmp_path / str(f) / "model.pt") for f in (True, False))
    assert all(torch.equal(ma[k], mb[k]) for k in ma)
    assert summaries[True]["updates"] == summaries[False]["updates"] > 0


def test_fused_acting_must_be_a_bool():
    from torchrl_causal.training import LoopConfig

    with pytest.raises(ValueError, match="fused_acting"):
        LoopConfig(fused_acting="yes")
