"""``dqn_optimizer``: Adam, fused on request where it runs -- the same algorithm as PyTorch's
default path, which stays the default."""

import copy
import dataclasses
import sys
from pathlib import Path

import pytest
import torch
from torch import nn

from torchrl_causal.training import DQNLoop, dqn_optimizer, fused_supported

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))


def _net(seed=0):
    torch.manual_seed(seed)
    return nn.Sequential(nn.Linear(9, 64), nn.ReLU(), nn.Linear(64, 8))


def _train(net, opt, steps=200, seed=1):
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        x = torch.randn(32, 9, generator=g)
        y = torch.randn(32, 8, generator=g)
        loss = nn.functional.smooth_l1_loss(net(x), y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(net.parameters(), 10.0)
        opt.step()
    return torch.cat([p.detach().flatten() for p in net.parameters()])


def test_fused_adam_on_request_matches_the_default_path():
    a, b = _net(), _net()
    fused = dqn_optimizer(a.parameters(), lr=1e-3, eps=1e-8, fused=None)  # where it runs: CPU
    plain = dqn_optimizer(b.parameters(), lr=1e-3, eps=1e-8)  # the default
    assert fused.defaults["fused"] is True and plain.defaults["fused"] is None
    assert isinstance(fused, torch.optim.Adam) and isinstance(plain, torch.optim.Adam)
    wa, wb = _train(a, fused), _train(b, plain)
    moved = (wa - torch.cat([p.detach().flatten() for p in _net().parameters()])).abs().max()
    assert moved > 0.05  # 200 steps at lr 1e-3 moved the weights
    # the same algorithm: agreement to float rounding after 200 steps, not bit for bit
    assert torch.allclose(wa, wb, atol=1e-5, rtol=1e-4)
    for group in (fused.param_groups[0], plain.param_groups[0]):
        assert group["lr"] == 1e-3 and group["eps"] == 1e-8


def test_rmsprop_and_refusals():
    net = _net()
    rms = dqn_optimizer(net.parameters(), "rmsprop", lr=2.5e-4, eps=1e-8, alpha=0.95)
    assert isinstance(rms, torch.optim.RMSprop) and rms.defaults["alpha"] == 0.95
    assert isinstance(dqn_optimizer(net.parameters(), "rmsprop", fused=None), torch.optim.RMSprop)
    with pytest.raises(ValueError, match="fused=True with name='rmsprop'"):
        dqn_optimizer(net.parameters(), "rmsprop", fused=True)
    with pytest.raises(ValueError, match="name='sgd'"):
        dqn_optimizer(net.parameters(), "sgd")
    for lr in (0, -1e-3, "0.1", True):
        with pytest.raises(ValueError, match="Invalid lr="):
            dqn_optimizer(net.parameters(), lr=lr)
    with pytest.raises(ValueError, match="fused='auto'"):
        dqn_optimizer(net.parameters(), fused="auto")
    ints = [torch.zeros(3, dtype=torch.long)]
    assert not fused_supported(ints) and not fused_supported([])
    with pytest.raises(ValueError, match="torch.int64 on cpu"):
        dqn_optimizer(ints, fused=True)
    # auto falls back to PyTorch's default path where the kernel does not run
    double = [nn.Parameter(torch.zeros(3, dtype=torch.float64))]
    assert fused_supported(double)
    assert dqn_optimizer(double, fused=None).defaults["fused"] is True


def test_lazy_modules_are_fused_once_materialised():
    """A lazy network's parameters are uninitialised when the optimiser is built (as in
    ``DQNLoop``'s docstring example, ``MLP`` without ``in_features``)."""
    torch.manual_seed(0)
    net = nn.Sequential(nn.LazyLinear(16), nn.ReLU(), nn.Linear(16, 2))
    opt = dqn_optimizer(net.parameters(), lr=1e-2, fused=True)
    assert opt.defaults["fused"] is True
    x = torch.randn(8, 5)
    before = net(x).detach().clone()  # materialises the lazy layer
    for _ in range(5):
        opt.zero_grad()
        net(x).pow(2).mean().backward()
        opt.step()
    assert net(x).pow(2).mean() < before.pow(2).mean()


def test_a_checkpoint_of_the_plain_path_resumes_on_it():
    """Resume is exact: an optimiser state saved by the default path keeps that path when it
    is loaded into a fused optimiser, and the run continues as it would have."""
    a, b = _net(), _net()
    plain = dqn_optimizer(a.parameters(), lr=1e-3)
    _train(a, plain, steps=20)
    b.load_state_dict(a.state_dict())
    resumed = dqn_optimizer(b.parameters(), lr=1e-3, fused=True)
    resumed.load_state_dict(copy.deepcopy(plain.state_dict()))  # as through a checkpoint file
    assert resumed.param_groups[0]["fused"] is None  # the checkpoint's own path
    assert torch.equal(_train(a, plain, steps=20, seed=5), _train(b, resumed, steps=20, seed=5))


def test_dqnloop_default_optimiser_and_a_fused_one(tmp_path):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import gridnav

    torch.set_num_threads(1)
    loop = gridnav.build_loop("dqn", 0, 600, output_dir=tmp_path / "default")
    assert isinstance(loop.optimizer, torch.optim.Adam)
    assert loop.optimizer.defaults["fused"] is None  # PyTorch's default path
    assert loop.optimizer.defaults["lr"] == loop.config.lr
    # the fused kernel on request: DQNLoop takes it as any optimiser, and it trains
    fused = dqn_optimizer(loop.loss.parameters(), lr=loop.config.lr, fused=True)
    run = DQNLoop(loop.env, loop.actor, loop.explorer, loss=loop.loss, optimizer=fused,
                  config=dataclasses.replace(loop.config, final_eval_episodes=0),
                  output_dir=tmp_path / "fused")
    before = [p.detach().clone() for p in run.loss.parameters()]
    assert run.optimizer is fused and run.run()["updates"] > 0
    assert any(not torch.equal(a, p) for a, p in zip(before, run.loss.parameters()))
    assert fused.state  # its moments were written by the fused steps


def test_recipe_optim_fused(tmp_path):
    import recipe_utils as ru
    import train
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=train.CONFIG_DIR, version_base=None):
        cfg = compose(config_name="dqn_features", overrides=[f"output_dir={tmp_path}"])
        auto = compose(config_name="dqn_features",
                       overrides=[f"output_dir={tmp_path}", "optim.fused=auto"])
        thesis = compose(config_name="dqn_features",
                         overrides=[f"output_dir={tmp_path}", "preset=thesis"])
    assert cfg.optim.fused is False and ru.optim_fused(cfg) is False  # the default path
    assert ru.optim_fused(auto) is None
    # a stored config from before the key: the path its run trained on
    old = OmegaConf.create(OmegaConf.to_container(cfg))
    del old.optim["fused"]
    assert ru.optim_fused(old) is False and ru.validate_config(old, tmp_path).name == cfg.variant
    variant = ru.VARIANTS[cfg.variant]
    env = train.build_env(cfg, variant, "thesis", "cpu")
    actor, _, _ = train.build_agent(cfg, variant, env, "cpu")
    assert train.build_loss(cfg, actor, env)[1].defaults["fused"] is None
    assert train.build_loss(auto, actor, env)[1].defaults["fused"] is True
    rms = train.build_loss(thesis, actor, env)[1]
    assert isinstance(rms, torch.optim.RMSprop)  # the thesis's optimiser, unfused
    env.close()
