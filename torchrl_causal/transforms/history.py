"""Short-term memory for the policy: the last actions taken, as an observation.

A feed-forward Q-network sees only the current frame. Where the goal is hidden
(behind the obstacle that random layouts place across the line of sight) the
nine features say only "not in sight", and a memoryless greedy policy
alternates turn-left / turn-right for ever (measured: 69 % of the thesis
policy's actions on held-out layouts). :class:`ActionHistory` gives the policy
the actions it just took, so it can commit to a search direction.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from torchrl.data import Bounded
from torchrl.envs.transforms import Transform

__all__ = ["ActionHistory"]


class ActionHistory(Transform):
    """One-hot codes of the last ``length`` actions, most recent first.

    Writes ``out_key`` (float32 ``[..., length * n_actions]``): block ``i``
    is the one-hot code of the action taken ``i + 1`` steps ago (all zeros
    before the episode had that many steps). At reset the history is cleared
    (only for the sub-envs being reset, in a batched env).

    Args:
        n_actions: size of the discrete action space.
        length: how many past actions are kept (>= 1).
        action_key: the action's key (an integer index, as TorchRL's
            ``Categorical`` action spec writes it).
        out_key: the key written.

    Example:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from tensordict import TensorDict
        >>> from torchrl_causal.envs import DroneNavEnv
        >>> env = TransformedEnv(DroneNavEnv(image_size=32, seed=0), ActionHistory(8, length=2))
        >>> td = env.reset()
        >>> td["action_history"].sum().item()
        0.0
        >>> td = env.step(td.set("action", torch.tensor(6)))["next"]
        >>> td["action_history"].view(2, 8).argmax(-1).tolist(), td["action_history"].sum().item()
        ([6, 0], 1.0)
    """

    def __init__(self, n_actions: int = 8, length: int = 4, *, action_key="action",
                 out_key="action_history"):
        for name, val in (("n_actions", n_actions), ("length", length)):
            if isinstance(val, bool) or not isinstance(val, int) or val < 1:
                raise ValueError(f"{name} must be an int >= 1, got {val!r}")
        super().__init__(in_keys=[], out_keys=[out_key])
        self.n_actions = int(n_actions)
        self.length = int(length)
        self.action_key = action_key
        self.out_key = out_key

    @property
    def width(self) -> int:
        """Size of the written vector (``length * n_actions``)."""
        return self.length * self.n_actions

    def _zeros(self, batch_size, device) -> torch.Tensor:
        return torch.zeros(*batch_size, self.width, dtype=torch.float32, device=device)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(self.action_key)
        batch = next_tensordict.batch_size
        if action.shape[len(batch):] == (self.n_actions,):  # one-hot action spec
            action = action.argmax(-1)
        action = action.reshape(batch).long()
        onehot = F.one_hot(action, self.n_actions).to(torch.float32)
        prev = tensordict.get(self.out_key, None)
        if prev is None:
            prev = self._zeros(batch, onehot.device)
        hist = torch.cat([onehot, prev[..., : self.width - self.n_actions]], dim=-1)
        next_tensordict.set(self.out_key, hist)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
               ) -> TensorDictBase:
        batch = tensordict_reset.batch_size
        device = tensordict_reset.device
        fresh = self._zeros(batch, device)
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        prev = tensordict.get(self.out_key, None) if tensordict is not None else None
        if mask is not None and prev is not None and mask.numel() > 1:
            mask = mask.reshape(*batch, 1)
            fresh = torch.where(mask, fresh, prev.to(fresh.device))
        tensordict_reset.set(self.out_key, fresh)
        return tensordict_reset

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict

    def transform_observation_spec(self, observation_spec):
        observation_spec[self.out_key] = Bounded(
            0.0, 1.0, shape=(*observation_spec.shape, self.width), dtype=torch.float32,
            device=observation_spec.device)
        return observation_spec
