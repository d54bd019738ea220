"""ThesisQNet: thesis Fig. 5.1 / 5.2 inside QValueActor and DQNLoss."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Categorical, OneHot
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss, HardUpdate

from torchrl_causal.modules import ThesisQNet


def _pixels(*batch, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (*batch, 84, 84, 3), dtype=torch.uint8, generator=g)


def test_architecture_is_fig_5_1():
    net = ThesisQNet(n_actions=8)
    convs = [m for m in net.conv if isinstance(m, torch.nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size, c.stride) for c in convs] == [
        (3, 32, (8, 8), (4, 4)),
        (32, 64, (4, 4), (2, 2)),
        (64, 64, (3, 3), (1, 1)),
    ]
    # 84 -> 20 -> 9 -> 7
    assert net.conv_out == 64 * 7 * 7
    assert net.dense[0].in_features == 3136 and net.dense[0].out_features == 512
    assert net.head.in_features == 512 and net.head.out_features == 8
    # Fig. 5.2: the nine values join before the dense layer
    assert ThesisQNet(8, n_features=9).dense[0].in_features == 3136 + 9


def test_batch_dims_and_uint8_scaling():
    torch.manual_seed(0)
    net = ThesisQNet(8)
    x = _pixels(2, 3)
    q = net(x)
    assert q.shape == (2, 3, 8)
    torch.testing.assert_close(q, net(x.float() / 255.0))
    torch.testing.assert_close(q[1, 2], net(x[1, 2]))
    # chw input gives the same function
    chw = ThesisQNet(8, pixels_format="chw")
    chw.load_state_dict(net.state_dict())
    torch.testing.assert_close(chw(x.movedim(-1, -3)), q)


def test_features_enter_the_dense_layer_and_are_scaled():
    torch.manual_seed(0)
    scale = torch.tensor([10.0] * 5 + [1.0, 10.0, 45.0, 2.0])
    net = ThesisQNet(8, n_features=9, feature_scale=scale)
    x = _pixels(4)
    f = torch.rand(4, 9) * 10
    q = net(x, f)
    assert q.shape == (4, 8)
    assert not torch.allclose(q, net(x, f + 1.0))
    plain = ThesisQNet(8, n_features=9)
    plain.load_state_dict({k: v for k, v in net.state_dict().items() if k != "feature_scale"})
    torch.testing.assert_close(q, plain(x, f / scale))
    with pytest.raises(ValueError, match="n_features=9"):
        net(x)
    with pytest.raises(ValueError, match="expected 9 features"):
        net(x, torch.zeros(4, 5))
    with pytest.raises(ValueError, match="n_features=0"):
        ThesisQNet(8)(x, f)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(n_actions=0), "n_actions"),
        (dict(n_features=-1), "n_features"),
        (dict(image_size=(20, 20)), "image_size"),
        (dict(pixels_format="nhwc"), "pixels_format"),
        (dict(n_features=2, feature_scale=[1.0]), "feature_scale"),
        (dict(n_features=2, feature_scale=[1.0, 0.0]), "feature_scale"),
    ],
)
def test_bad_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ThesisQNet(**kwargs)


def test_wrong_image_size_is_reported():
    with pytest.raises(ValueError, match="expected pixels"):
        ThesisQNet(8)(torch.zeros(1, 64, 64, 3, dtype=torch.uint8))
    assert ThesisQNet(8, image_size=(64, 48))(torch.zeros(1, 64, 48, 3)).shape == (1, 8)


@pytest.mark.parametrize("spec", [Categorical(8), OneHot(8)])
def test_inside_qvalue_actor_and_dqn_loss(spec):
    torch.manual_seed(0)
    net = ThesisQNet(8, n_features=9)
    actor = QValueActor(net, in_keys=["pixels", "causal_features"], spec=spec)
    td = TensorDict(pixels=_pixels(6), causal_features=torch.rand(6, 9), batch_size=[6])
    actor(td)
    q = td["action_value"]
    assert q.shape == (6, 8)
    greedy = q.argmax(-1)
    if isinstance(spec, Categorical):
        assert torch.equal(td["action"], greedy)
    else:
        assert torch.equal(td["action"].float().argmax(-1), greedy)
    # a DQN update on this network decreases the TD error on a fixed batch
    td["next"] = TensorDict(
        pixels=_pixels(6, seed=1),
        causal_features=torch.rand(6, 9),
        reward=torch.randn(6, 1),
        done=torch.zeros(6, 1, dtype=torch.bool),
        terminated=torch.zeros(6, 1, dtype=torch.bool),
        batch_size=[6],
    )
    loss = DQNLoss(actor, action_space=spec, delay_value=True, loss_function="l2")
    loss.make_value_estimator(gamma=0.9)
    HardUpdate(loss, value_network_update_interval=100)
    opt = torch.optim.RMSprop(actor.parameters(), lr=2.5e-4, eps=1e-8)
    losses = []
    for _ in range(5):
        out = loss(td.clone())
        losses.append(out["loss"].item())
        opt.zero_grad()
        out["loss"].backward()
        assert net.conv[0].weight.grad.abs().sum() > 0
        opt.step()
    assert losses[-1] < losses[0]


def test_wrong_image_size_message_follows_pixels_format():
    with pytest.raises(ValueError, match=r"\[\.\.\., 84, 84, 3\] \(hwc\)"):
        ThesisQNet(8)(torch.zeros(1, 64, 64, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match=r"\[\.\.\., 3, 84, 84\] \(chw\)"):
        ThesisQNet(8, pixels_format="chw")(torch.zeros(1, 3, 64, 64))
