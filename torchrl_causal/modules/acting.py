"""Acting with a ``QValueActor`` and an ``EGreedyModule``, computed on tensors.

A DQN collector calls its policy once a frame. With TorchRL's usual policy,
``TensorDictSequential(QValueActor(net), EGreedyModule(spec))``, that call runs
three tensordict modules: the network's ``TensorDictModule``, the
``QValueModule`` (argmax, chosen value) and the explorer, each reading and
writing the tensordict by key. On the small Q-networks of this project the
network itself is a fraction of the call (``benchmarks/vs_sb3.py``: the
feature network 0.04 ms of a 0.15 ms call on a quiet core, and about twice
that inside a training loop, between renders).

:class:`EGreedyQValuePolicy` computes the same thing on tensors: it reads the
network's inputs, calls the network, takes the ``QValueModule``'s own action
and action-value functions, draws epsilon-greedy exploration exactly as
``EGreedyModule`` does (the same random calls in the same order, so the same
actions bit for bit under the same seed), and writes the three outputs once.
Layouts it does not cover (a network split over several modules, an action
mask, nested action keys, a reshaping action spec) are refused at construction
(:func:`acting_policy` then keeps ``TensorDictSequential``).

:func:`acting_policy` is what :class:`~torchrl_causal.training.DQNLoop` acts
with: the fused policy where the actor and explorer allow it, else
``TensorDictSequential(actor, explorer, *guards)``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from tensordict.utils import expand_as_right
from torchrl.data import Composite
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import EGreedyModule, QValueModule

__all__ = ["EGreedyQValuePolicy", "acting_policy", "qvalue_parts"]


def qvalue_parts(actor) -> tuple[TensorDictModule, QValueModule] | None:
    """``(network module, QValueModule)`` of an actor laid out as ``QValueActor`` is: one
    ``TensorDictModule`` around a plain network that writes the action values, then a
    ``QValueModule`` with a categorical or one-hot action space; else ``None``.

    Example:
        >>> from torch import nn
        >>> from torchrl.data import Categorical
        >>> from torchrl.modules import QValueActor
        >>> from torchrl_causal.modules.acting import qvalue_parts
        >>> tdm, qmod = qvalue_parts(QValueActor(nn.Linear(3, 4), in_keys=["obs"],
        ...                                      spec=Categorical(4)))
        >>> tdm.in_keys, qmod.action_space
        (['obs'], 'categorical')
    """
    mods = getattr(actor, "module", None)
    if not isinstance(mods, torch.nn.ModuleList) or len(mods) != 2:
        return None
    tdm, qmod = mods
    if (type(tdm) is not TensorDictModule or type(qmod) is not QValueModule
            or list(tdm.out_keys) != [qmod.action_value_key]
            or qmod.action_space not in ("categorical", "one_hot")
            or isinstance(tdm.module, TensorDictModuleBase)):
        return None
    return tdm, qmod


def _why_not(actor, explorer) -> str | None:
    """Why ``actor`` + ``explorer`` cannot be fused, or ``None`` when they can."""
    parts = qvalue_parts(actor)
    if parts is None:
        return (f"the actor {type(actor).__name__} is not a QValueActor layout (one "
                "TensorDictModule around a plain network, then a QValueModule)")
    tdm, qmod = parts
    if type(explorer) is not EGreedyModule:
        return f"the explorer is a {type(explorer).__name__}, not an EGreedyModule"
    action_key = qmod.out_keys[0]
    if not isinstance(action_key, str) or explorer.action_key != action_key:
        return (f"the explorer's action key {explorer.action_key!r} is not the actor's "
                f"plain action key {action_key!r}")
    if qmod.action_mask_key is not None or explorer.action_mask_key is not None:
        return "an action mask is used"
    if explorer.spec is None:
        return "the explorer has no action spec"
    return None


class EGreedyQValuePolicy(TensorDictModuleBase):
    """``TensorDictSequential(actor, explorer)`` for a ``QValueActor`` and an
    ``EGreedyModule``, computed on tensors.

    The actions, action values and chosen values are those of the sequence, bit
    for bit (the same random draws in the same order); ``explorer.eps`` and its
    schedule (``explorer.step``) are read live, and the actor's parameters are its
    own (nothing is copied). Exploration follows TorchRL's exploration type as
    ``EGreedyModule`` does (random under ``RANDOM`` or unset, greedy otherwise).

    Args:
        actor: a ``QValueActor`` (or the same layout: :func:`qvalue_parts`).
        explorer: an ``EGreedyModule`` on the actor's action key, without an action mask.

    Raises:
        ValueError: a layout the fused computation does not cover (the message says which).

    Example:
        >>> import torch
        >>> from torch import nn
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictSequential
        >>> from torchrl.data import Categorical
        >>> from torchrl.modules import EGreedyModule, QValueActor
        >>> from torchrl_causal.modules import EGreedyQValuePolicy
        >>> spec = Categorical(4)
        >>> actor = QValueActor(nn.Linear(3, 4), in_keys=["obs"], spec=spec)
        >>> explorer = EGreedyModule(spec, eps_init=0.5)
        >>> fused = EGreedyQValuePolicy(actor, explorer)
        >>> td = TensorDict({"obs": torch.randn(16, 3)}, [16])
        >>> _ = torch.manual_seed(0); a = fused(td.clone())["action"]
        >>> sequence = TensorDictSequential(actor, explorer)
        >>> _ = torch.manual_seed(0); b = sequence(td.clone())["action"]
        >>> bool((a == b).all())
        True
    """

    def __init__(self, actor, explorer):
        super().__init__()
        why = _why_not(actor, explorer)
        if why is not None:
            raise ValueError(f"EGreedyQValuePolicy cannot fuse this policy: {why}")
        self.actor, self.explorer = actor, explorer
        tdm, qmod = qvalue_parts(actor)
        # views into the actor (and the sequence below), kept out of the module tree so that
        # the state dict holds each tensor once, under actor.* / explorer.*
        self.__dict__["_tdm"], self.__dict__["_qmod"] = tdm, qmod
        self._action_func = qmod.action_func_mapping[qmod.action_space]
        self._value_func = qmod.action_value_func_mapping.get(qmod.action_space,
                                                              qmod._default_action_value)
        spec = explorer.spec
        self._spec = spec[explorer.action_key] if isinstance(spec, Composite) else spec
        # QValueModule reshapes the action to its spec's per-sample shape: the fused path
        # checks that no reshape is due (else it runs the sequence itself)
        qspec = qmod.spec
        action_spec = (qspec.get(qmod.out_keys[0], None) if isinstance(qspec, Composite)
                       else None)
        # the action's per-sample shape QValueModule enforces (None: it enforces none)
        self._per_sample = (action_spec.shape[len(qspec.shape):]
                            if action_spec is not None and qmod.strict_shape is not False
                            else None)
        self.__dict__["_sequence"] = TensorDictSequential(actor, explorer)
        self.in_keys = list(self._sequence.in_keys)
        self.out_keys = list(self._sequence.out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tdm = self._tdm
        values = tdm.module(*(tensordict.get(k) for k in tdm.in_keys))
        action = self._action_func(values)
        if self._per_sample is not None and action.shape != values.shape[:-1] + self._per_sample:
            return self._sequence(tensordict)  # QValueModule reshapes or raises
        chosen = self._value_func(values, action)
        if exploration_type() in (ExplorationType.RANDOM, None):
            eps = self.explorer.eps
            if action.device is not None and action.device != eps.device:
                raise RuntimeError(
                    f"Expected action and e-greedy module to be on the same device, but got "
                    f"{action.device=} and e-greedy device={eps.device}.")
            cond = expand_as_right(torch.rand(tensordict.shape, device=eps.device) < eps, action)
            spec = self._spec
            if spec.shape != action.shape:
                if not len(spec.shape) or action.shape[-len(spec.shape):] == spec.shape:
                    spec = spec.expand(action.shape)
                else:
                    raise ValueError("Action spec shape does not match the action shape")
            r = spec.rand()
            action = torch.where(cond, r.to(eps.device) if r.device != eps.device else r, action)
        out = dict(zip(self._qmod.out_keys, (action, values, chosen)))
        tensordict.update(out)
        return tensordict


def acting_policy(actor, explorer, *guards) -> TensorDictModuleBase:
    """The policy a DQN collector acts with: :class:`EGreedyQValuePolicy` where ``actor`` and
    ``explorer`` allow it, else ``TensorDictSequential(actor, explorer)``; ``guards`` (e.g.
    :class:`~torchrl_causal.modules.LoopGuard`) run after it in either case.

    Example:
        >>> from torch import nn
        >>> from torchrl.data import Categorical
        >>> from torchrl.modules import EGreedyModule, QValueActor
        >>> from torchrl_causal.modules import acting_policy
        >>> spec = Categorical(4)
        >>> actor = QValueActor(nn.Linear(3, 4), in_keys=["obs"], spec=spec)
        >>> type(acting_policy(actor, EGreedyModule(spec))).__name__
        'EGreedyQValuePolicy'
    """
    if _why_not(actor, explorer) is None:
        policy = EGreedyQValuePolicy(actor, explorer)
        return TensorDictSequential(policy, *guards) if guards else policy
    return TensorDictSequential(actor, explorer, *guards)
