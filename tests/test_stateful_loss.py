"""StatefulDQNLoss is TorchRL's DQNLoss bit for bit, without the per-call parameter swaps."""

from __future__ import annotations

import copy
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
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss, HardUpdate, SoftUpdate

from torchrl_causal.training import DQNLoop, StatefulDQNLoss

ROOT = Path(__file__).resolve().parents[1]
N_OBS, N_ACT = 6, 5


def _batches(n: int, seed: int = 0, one_hot: bool = False, mask: bool = False):
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(n):
        a = torch.randint(N_ACT, (32,), generator=g)
        td = TensorDict({
            "obs": torch.randn(32, N_OBS, generator=g),
            "action": nn.functional.one_hot(a, N_ACT).bool() if one_hot else a,
            "next": {"obs": torch.randn(32, N_OBS, generator=g),
                     "reward": torch.randn(32, 1, generator=g),
                     "done": torch.rand(32, 1, generator=g) < 0.1,
                     "terminated": torch.rand(32, 1, generator=g) < 0.1}}, [32])
        if mask:
            m = torch.rand(32, N_ACT, generator=g) < 0.7
            m[:, 0] = True
            td["action_mask"] = m
            td["next", "action_mask"] = m.roll(1, 0)
        out.append(td)
    return out


def _actor(one_hot=False, mask=False, seed=0, split=False):
    """A ``QValueActor``: one ``TensorDictModule`` around the network (the layout the
    loss calls on tensors), or with ``split`` the network as two ``TensorDictModule``s in
    a ``TensorDictSequential`` (the loss then runs it on tensordicts)."""
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(N_OBS, 64), nn.ReLU(), nn.Linear(64, N_ACT))
    if split:
        net = TensorDictSequential(TensorDictModule(net[:2], ["obs"], ["hidden"]),
                                   TensorDictModule(net[2], ["hidden"], ["action_value"]))
    spec = OneHot(N_ACT) if one_hot else Categorical(N_ACT)
    return QValueActor(net, in_keys=["obs"], spec=spec,
                       action_mask_key="action_mask" if mask else None), spec


def _train(cls, *, double=False, one_hot=False, mask=False, updater="hard", steps=150,
           estimator=None, split=False):
    actor, spec = _actor(one_hot, mask, split=split)
    loss = cls(actor, loss_function="smooth_l1", delay_value=True, double_dqn=double,
               action_space=spec)
    if estimator is None:
        loss.make_value_estimator(gamma=0.9)
    else:
        loss.make_value_estimator(estimator, gamma=0.9, lmbda=0.8)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    upd = (HardUpdate(loss, value_network_update_interval=7) if updater == "hard"
           else SoftUpdate(loss, eps=0.9))
    losses, errors = [], []
    for b in _batches(steps, one_hot=one_hot, mask=mask):
        value = loss(b)["loss"]
        value.backward()
        nn.utils.clip_grad_norm_(loss.parameters(), 1.0)
        opt.step()
        opt.zero_grad(set_to_none=True)
        upd.step()
        losses.append(value.detach())
        errors.append(b["td_error"])
    return loss, torch.stack(losses), torch.stack(errors)


@pytest.mark.parametrize("double,one_hot,mask,updater,split", [
    (False, False, False, "hard", False), (True, False, False, "hard", False),
    (False, True, False, "soft", False), (True, False, True, "soft", False),
    (False, False, True, "hard", False), (True, True, True, "hard", False),
    # a value network the loss runs on tensordicts, not on tensors
    (False, False, False, "hard", True), (True, True, True, "soft", True)])
def test_training_is_bit_for_bit_dqnloss(double, one_hot, mask, updater, split):
    ref, ref_losses, ref_err = _train(DQNLoss, double=double, one_hot=one_hot, mask=mask,
                                      updater=updater, split=split)
    new, losses, err = _train(StatefulDQNLoss, double=double, one_hot=one_hot, mask=mask,
                              updater=updater, split=split)
    assert (new._plain_parts() is None) == split  # which of the two paths ran
    assert torch.equal(ref_losses, losses) and torch.equal(ref_err, err)
    sa, sb = ref.state_dict(), new.state_dict()
    assert list(sa) == list(sb)  # the same checkpoint layout
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    # the target network moved during training, and the copy follows it
    init = torch.cat([p.flatten() for p in _actor()[0].parameters()])
    target = torch.cat([t.flatten() for t in new.target_value_network_params.values(True, True)])
    assert target.numel() == init.numel() and not torch.equal(target, init)


def test_other_estimators_fall_back_to_dqnloss():
    _, a, _ = _train(DQNLoss, estimator="tdlambda", steps=20)
    _, b, _ = _train(StatefulDQNLoss, estimator="tdlambda", steps=20)
    assert torch.equal(a, b)


def test_state_dict_load_and_dtype_changes_keep_the_target_copy_in_step():
    trained, _, _ = _train(DQNLoss, double=True, steps=40)
    actor, spec = _actor(seed=3)
    fresh = StatefulDQNLoss(actor, delay_value=True, double_dqn=True, action_space=spec,
                            loss_function="smooth_l1")
    fresh.make_value_estimator(gamma=0.9)
    batch = _batches(1, seed=9)[0]
    fresh(batch.clone())  # builds its target copy before the load
    fresh.load_state_dict(trained.state_dict())
    assert torch.equal(fresh(batch.clone())["loss"], trained(batch.clone())["loss"])
    # .double() replaces every tensor: the copy is re-made from the new target tensors
    a, b = copy.deepcopy(trained).double(), fresh.double()
    b64 = batch.apply(lambda t: t.double() if t.is_floating_point() else t)
    assert b(b64.clone())["loss"].dtype == torch.float64
    assert torch.equal(a(b64.clone())["loss"], b(b64.clone())["loss"])


def test_delay_value_false_is_refused():
    actor, spec = _actor()
    with pytest.raises(ValueError, match="delay_value=False"):
        StatefulDQNLoss(actor, delay_value=False, action_space=spec)


def test_the_loop_trains_the_same_with_either_loss(tmp_path):
    """The grid world's DQNLoop (real env, hook and gate): default loss vs TorchRL's."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import gridnav

    torch.set_num_threads(1)
    runs = {}
    for name in ("default", "dqnloss"):
        out = tmp_path / name
        base = gridnav.build_loop("expert", 0, 600, output_dir=out)
        assert isinstance(base.loss, StatefulDQNLoss)
        if name == "dqnloss":
            cfg = base.config
            loss = DQNLoss(base.actor, loss_function=cfg.loss_function, delay_value=True,
                           double_dqn=cfg.double_dqn, action_space=base.env.action_spec_unbatched)
            loss.make_value_estimator(gamma=cfg.gamma)
            base = DQNLoop(base.env, base.actor, base.explorer, hook=base.hook, config=cfg,
                           loss=loss, output_dir=out, eval_envs=base.eval_envs)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            runs[name] = base.run()
    a, b = (pd.read_csv(tmp_path / n / "episodes.csv") for n in runs)
    pd.testing.assert_frame_equal(a, b)
    ma, mb = (torch.load(tmp_path / n / "model.pt") for n in runs)
    assert all(torch.equal(ma[k], mb[k]) for k in ma)
    assert runs["default"]["updates"] == runs["dqnloss"]["updates"] > 0
