"""``VisitMemory``: which actions the drone already took from the pose it is at.

A deterministic policy that comes back to a pose it has already flown from,
with an observation that has not changed, takes the same action again and
flies the same cycle until the step limit. :class:`~torchrl_causal.modules.LoopGuard`
catches the shortest such cycles (two moves that undo each other) from the
action history alone; longer ones -- round a corner and back, a full turn in
place, a square of four moves -- need to know *where* the drone is.

:class:`VisitMemory` keeps, per episode, a count of the actions taken from each
dead-reckoned pose: the position and heading that
:class:`~torchrl_causal.transforms.EgoMap` integrates from the commanded moves
(``ego_pose``) and the number of ascents less descents commanded so far. Poses are binned (``position_resolution``
metres, ``heading_resolution_deg`` degrees), so the float error of the dead
reckoning does not split a pose in two. It writes ``visit_counts`` (float32
``[..., n_actions]``): how many times each action has been taken from the pose
the drone is at now (all zeros on a pose never flown from).
:class:`~torchrl_causal.modules.RevisitGuard` reads it. Dead reckoning is what
a real drone has too: the counts are the same on a Tello as in the simulator.

Example:
    >>> import torch
    >>> from torchrl.envs import TransformedEnv
    >>> from torchrl_causal.envs import DroneNavEnv
    >>> from torchrl_causal.transforms import EgoMap, VisitMemory
    >>> env = TransformedEnv(DroneNavEnv(seed=0, image_size=32), EgoMap())
    >>> env = env.append_transform(VisitMemory())
    >>> td = env.reset()
    >>> for a in (6, 7):                      # turn left, turn right: back where it started
    ...     td = env.step(td.set("action", torch.tensor(a)))["next"]
    >>> td["visit_counts"].tolist()           # turn left was taken once from here
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from torchrl.data import Unbounded
from torchrl.envs.transforms import Transform

__all__ = ["VisitMemory"]

#: Action indices of the vertical moves, in :data:`~torchrl_causal.schema.ACTION_NAMES` order.
_ASCEND, _DESCEND = 4, 5


def _positive(name, value):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or \
            not math.isfinite(value) or value <= 0:
        raise ValueError(f"VisitMemory {name} must be a finite number > 0, got {value!r}")


class VisitMemory(Transform):
    """Counts, per episode, the actions taken from each dead-reckoned pose.

    Append it after :class:`~torchrl_causal.transforms.EgoMap` (it reads
    ``ego_pose``).

    Args:
        n_actions: size of the action space.
        position_resolution: side of a position bin (m); well below the move
            length, well above the dead reckoning's float error.
        heading_resolution_deg: width of a heading bin (degrees); below the turn.
        pose_key, action_key: the keys read.

    Example:
        >>> t = VisitMemory(position_resolution=0.05)
        >>> t.out_keys
        ['visit_counts']
    """

    def __init__(self, n_actions: int = 8, *, position_resolution: float = 0.05,
                 heading_resolution_deg: float = 5.0,
                 pose_key: str = "ego_pose", action_key: str = "action"):
        if isinstance(n_actions, bool) or not isinstance(n_actions, int) or n_actions < 2:
            raise ValueError(f"VisitMemory n_actions must be an int >= 2, got {n_actions!r}")
        _positive("position_resolution", position_resolution)
        _positive("heading_resolution_deg", heading_resolution_deg)
        super().__init__(in_keys=[pose_key], out_keys=["visit_counts"])
        self.n_actions = n_actions
        self.position_resolution = float(position_resolution)
        self.heading_resolution_deg = float(heading_resolution_deg)
        self.pose_key, self.action_key = pose_key, action_key
        self._counts: list[dict] = []  # per flattened batch entry: pose bin -> counts
        self._bins: list[tuple] = []  # per entry: the bin of the current pose
        self._up: list[int] = []  # per entry: ascents minus descents

    def _bin(self, pose, up: int) -> tuple:
        x, y, yaw = (float(v) for v in pose)
        h = int(round(math.degrees(yaw) / self.heading_resolution_deg))
        h %= max(1, int(round(360.0 / self.heading_resolution_deg)))
        return (int(round(x / self.position_resolution)), int(round(y / self.position_resolution)),
                h, up)

    def _poses(self, td: TensorDictBase) -> torch.Tensor:
        pose = td.get(self.pose_key, None)
        if pose is None:
            raise KeyError(f"VisitMemory reads {self.pose_key!r}: append it after EgoMap")
        return pose.reshape(-1, pose.shape[-1]).detach().cpu()

    def _write(self, td: TensorDictBase) -> TensorDictBase:
        out = torch.zeros(len(self._bins), self.n_actions)
        for i, (counts, b) in enumerate(zip(self._counts, self._bins)):
            if b in counts:
                out[i] = torch.tensor(counts[b], dtype=torch.float32)
        pose = td.get(self.pose_key)
        td.set("visit_counts", out.reshape(*td.batch_size, self.n_actions).to(pose.device))
        return td

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
               ) -> TensorDictBase:
        poses = self._poses(tensordict_reset)
        n = poses.shape[0]
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        if len(self._bins) != n or mask is None or mask.numel() != n:
            reset = list(range(n))
            self._counts, self._bins, self._up = [{} for _ in range(n)], [None] * n, [0] * n
        else:
            reset = [i for i, m in enumerate(mask.reshape(-1).tolist()) if m]
        for i in reset:
            self._counts[i], self._up[i] = {}, 0
            self._bins[i] = self._bin(poses[i], 0)
        return self._write(tensordict_reset)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase
              ) -> TensorDictBase:
        if not self._bins:
            raise RuntimeError("VisitMemory: step before reset (call env.reset() first)")
        action = tensordict.get(self.action_key)
        batch = next_tensordict.batch_size
        if action.shape[len(batch):] == (self.n_actions,):  # one-hot action spec
            action = action.argmax(-1)
        action = action.reshape(-1).long().tolist()
        poses = self._poses(next_tensordict)
        for i, a in enumerate(action):
            counts = self._counts[i].setdefault(self._bins[i], [0] * self.n_actions)
            counts[a] += 1
            self._up[i] += (a == _ASCEND) - (a == _DESCEND)
            self._bins[i] = self._bin(poses[i], self._up[i])
        return self._write(next_tensordict)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict

    def transform_observation_spec(self, observation_spec):
        shape = observation_spec.shape
        observation_spec["visit_counts"] = Unbounded(shape=(*shape, self.n_actions),
                                                     dtype=torch.float32,
                                                     device=observation_spec.device)
        return observation_spec
