"""TorchRL's ``DQNLoss`` without its per-call parameter swaps.

:class:`~torchrl.objectives.DQNLoss` is *functional*: on every call it swaps its
value parameters into the Q-network (``TensorDict.to_module``), runs it, and swaps
the target parameters in for the bootstrapped target through its value estimator.
On the small Q-networks of this project those swaps, and the tensordict work
around them, cost about a third of an update (``benchmarks/vs_sb3.py
--overheads``). :class:`StatefulDQNLoss` is the same loss, with the same
parameters, target parameters, value estimator, state dict and target updaters
(``HardUpdate`` / ``SoftUpdate``), computed without the swaps: the Q-network
already holds the value parameters, and a copy of it holds the target
parameters *as its own tensors*, so the updaters' in-place copies reach it.
Each update gives bit-for-bit the loss and gradients of ``DQNLoss``
(``tests/test_stateful_loss.py``); settings it does not cover (an estimator other
than TD(0), averaged rewards, multi-step gammas, prioritized weights) fall back
to ``DQNLoss.forward``.

When the value network is the usual ``QValueActor`` -- one ``TensorDictModule``
around a plain network, then a ``QValueModule`` -- the loss reads the input
tensors and calls that network directly, with the ``QValueModule``'s own action
and action-value functions, instead of writing every output into shallow copies
of the batch: the same operations on the same tensors, without the tensordict
work around them.
"""

from __future__ import annotations

import copy

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import DQNLoss
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value import TD0Estimator
from torchrl.objectives.value.functional import td0_return_estimate

from torchrl_causal.modules.acting import qvalue_parts

__all__ = ["StatefulDQNLoss"]


def _taken(values, action, categorical: bool, keepdim: bool = False):
    """``values`` at ``action`` (an index, or one-hot), as ``DQNLoss`` reads them: the
    predicted value of the action taken, or the target's value of the chosen next action
    (``keepdim``)."""
    if categorical:
        if action.ndim != values.ndim:
            action = action.unsqueeze(-1)
        out = torch.gather(values, -1, index=action)
        return out if keepdim else out.squeeze(-1)
    if keepdim:
        return (values * action).sum(-1, keepdim=True)
    return (values * action.to(torch.float)).sum(-1)


class StatefulDQNLoss(DQNLoss):
    """:class:`~torchrl.objectives.DQNLoss` computed without swapping parameters per call.

    Takes ``DQNLoss``'s arguments, with ``delay_value=True`` (a target network is
    what it keeps a stateful copy of). The loss, its gradients and its
    ``state_dict`` are ``DQNLoss``'s; ``loss.value_network_params`` and
    ``loss.target_value_network_params`` are still the parameters an optimiser and
    a target updater act on.

    Example:
        >>> import torch
        >>> from torch import nn
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Categorical
        >>> from torchrl.modules import QValueActor
        >>> from torchrl_causal.training.loss import StatefulDQNLoss
        >>> spec = Categorical(4)
        >>> actor = QValueActor(nn.Linear(3, 4), in_keys=["obs"], spec=spec)
        >>> loss = StatefulDQNLoss(actor, action_space=spec, loss_function="smooth_l1")
        >>> loss.make_value_estimator(gamma=0.9)
        >>> td = TensorDict({"obs": torch.randn(8, 3), "action": torch.randint(4, (8,)),
        ...                  "next": {"obs": torch.randn(8, 3), "reward": torch.randn(8, 1),
        ...                           "done": torch.zeros(8, 1, dtype=torch.bool),
        ...                           "terminated": torch.zeros(8, 1, dtype=torch.bool)}}, [8])
        >>> loss(td)["loss"].shape
        torch.Size([])
    """

    def __init__(self, value_network, **kwargs):
        if not kwargs.get("delay_value", True):
            raise ValueError("Invalid option delay_value=False for StatefulDQNLoss: it keeps "
                             "a stateful copy of the target network (use DQNLoss)")
        super().__init__(value_network, **kwargs)
        # the target copy lives outside the module tree (like DQNLoss's own value_network):
        # its tensors are target_value_network_params' own, so neither the state dict nor
        # .parameters() sees it twice
        self.__dict__["_target_network"] = None

    def _target(self):
        """The Q-network copy whose tensors are the target parameters."""
        net = self.__dict__["_target_network"]
        if net is None:
            net = copy.deepcopy(self.value_network).requires_grad_(False)
            self.target_value_network_params.to_module(net)  # permanently: holds them
            self.__dict__["_target_network"] = net
        return net

    def _apply(self, fn, *args, **kwargs):
        # .to(device) / .double() ... replace the target tensors: the copy is re-made
        self.__dict__["_target_network"] = None
        return super()._apply(fn, *args, **kwargs)

    def load_state_dict(self, *args, **kwargs):
        self.__dict__["_target_network"] = None
        return super().load_state_dict(*args, **kwargs)

    def _stateful_ok(self, tensordict: TensorDictBase) -> bool:
        est = self.value_estimator
        if type(est) is not TD0Estimator or est.average_rewards:
            return False
        if est.tensor_keys.steps_to_next_obs in tensordict.keys(True):
            return False
        if (self.use_prioritized_weights in (True, "auto")
                and self.tensor_keys.priority_weight in tensordict.keys()):
            return False
        return not torch.compiler.is_compiling()

    def _plain_parts(self):
        """``(network module, QValueModule)`` of a value network laid out as ``QValueActor``
        (:func:`~torchrl_causal.modules.acting.qvalue_parts`) whose outputs are the keys this
        loss reads, else ``None``."""
        parts = qvalue_parts(self.value_network)
        if parts is None:
            return None
        tdm, qmod = parts
        if (qmod.out_keys[0] != self.tensor_keys.action
                or qmod.out_keys[-1] != self.value_estimator.tensor_keys.value):
            return None
        return tdm, qmod

    def _q_values(self, tdm, qmod, module, td, prefix=()):
        """The network's action values on ``td``'s inputs (under ``prefix``), masked as
        ``QValueModule`` masks them."""
        def key(k):
            return (*prefix, *((k,) if isinstance(k, str) else k))
        q = module(*(td.get(key(k)) for k in tdm.in_keys))
        if qmod.action_mask_key is not None:
            q = torch.where(td.get(key(qmod.action_mask_key)), q, torch.finfo(q.dtype).min)
        return q

    def _forward_plain(self, tensordict, tdm, qmod) -> TensorDict:
        """The loss with the network called on tensors (see the module docstring)."""
        categorical = self.action_space == "categorical"
        action_func = qmod.action_func_mapping[qmod.action_space]
        value_func = qmod.action_value_func_mapping.get(qmod.action_space,
                                                        qmod._default_action_value)
        pred_val = self._q_values(tdm, qmod, tdm.module, tensordict)
        action = tensordict.get(self.tensor_keys.action)
        pred_val_index = _taken(pred_val, action, categorical)

        target_mod = self._target().module[0].module
        if self.double_dqn:
            with torch.no_grad():
                next_action = action_func(self._q_values(tdm, qmod, tdm.module, tensordict,
                                                         ("next",)))
            next_pred_val = self._q_values(tdm, qmod, target_mod, tensordict, ("next",))
            next_value = _taken(next_pred_val, next_action, categorical, keepdim=True)
        else:
            q_next = self._q_values(tdm, qmod, target_mod, tensordict, ("next",))
            next_value = value_func(q_next, action_func(q_next))
        return self._td_loss(tensordict, pred_val_index, next_value)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        """DQNLoss's loss on a sampled batch (it writes the same ``td_error``)."""
        if not self._stateful_ok(tensordict):
            return super().forward(tensordict)
        parts = self._plain_parts()
        if parts is not None:
            return self._forward_plain(tensordict, *parts)
        keys, est = self.tensor_keys, self.value_estimator
        td_copy = tensordict.clone(False)
        self.value_network(td_copy)  # holds the value parameters already
        action = tensordict.get(keys.action)
        pred_val = td_copy.get(keys.action_value)
        categorical = self.action_space == "categorical"
        pred_val_index = _taken(pred_val, action, categorical)

        # the next observations (DQNLoss: step_mdp(keep_other=False); the Q-network reads the
        # same entries, and its outputs land in this shallow copy only)
        step_td = td_copy.get("next").clone(False)
        target_net = self._target()
        if self.double_dqn:
            step_td_copy = step_td.clone(False)
            with torch.no_grad():  # DQNLoss: the online network on detached parameters
                self.value_network(step_td)
            next_action = step_td.get(keys.action)
            target_net(step_td_copy)
            next_pred_val = step_td_copy.get(keys.action_value)
            next_value = _taken(next_pred_val, next_action, categorical, keepdim=True)
        else:
            target_net(step_td)
            next_value = step_td.get(est.tensor_keys.value)

        return self._td_loss(tensordict, pred_val_index, next_value)

    def _td_loss(self, tensordict, pred_val_index, next_value) -> TensorDict:
        """The TD(0) target, ``td_error`` (written into ``tensordict``) and the loss."""
        keys, est = self.tensor_keys, self.value_estimator
        reward = tensordict.get(("next", est.tensor_keys.reward))
        if est.gamma.device != reward.device:
            est.gamma = est.gamma.to(reward.device)
        done = tensordict.get(("next", est.tensor_keys.done))
        terminated = tensordict.get(("next", est.tensor_keys.terminated), default=done)
        target_value = td0_return_estimate(gamma=est.gamma, next_state_value=next_value,
                                           reward=reward, terminated=terminated).squeeze(-1)

        with torch.no_grad():
            priority_tensor = (pred_val_index - target_value).pow(2).unsqueeze(-1)
        if tensordict.device is not None:
            priority_tensor = priority_tensor.to(tensordict.device)
        tensordict.set(keys.priority, priority_tensor, inplace=True)
        loss = distance_loss(pred_val_index, target_value, self.loss_function)
        loss = self._reduce_loss(loss, tensordict=tensordict, weights=None)
        return TensorDict(loss=loss)
