"""``GoalSearch``: fly round what hides the goal, on the drone's own map, until the goal is seen.

Random layouts (and a Tello flight, and the thesis scene) start the drone facing
the goal, so a goal that is not in view at the start is hidden behind an
obstacle. A learned policy that has never seen the goal has no goal to steer
by: the generalist's remaining failures are mostly such starts, where it turns
away and leaves the arena while the shortest path flies round the first
obstacle (docs/results.rst, "Searching for a hidden goal").

:class:`GoalSearch` is placed after the policy (and its guards). While the goal
has not been in view this episode (``goal_seen`` False), it replaces the
action by a search move: a shortest path on the drone's own egocentric map
(:class:`~torchrl_causal.transforms.EgoMap`'s obstacle channel, unseen cells
counted free, obstacles grown by the hull) towards a point ``distance`` metres
ahead of the start, along the start's heading, and at least ``lead`` metres
beyond the drone's own progress along that line. The camera is kept on the
searched point (a turn when its bearing leaves the heading by more than
``turn_tolerance_deg``), and the drone translates along the path: of the
moves ``action_mask`` allows (forward, backward, left, right), the one whose
end is closest to the point along the path, if it gets closer; else it turns to
look round. Side-stepping round the obstacle with the camera still on the
searched point shows the goal as soon as the line of sight clears. Once the goal has
been seen the policy's own action is kept. It reads only what a real drone has
(depth map, dead reckoning, the goal detector's flag), never the simulator's
state.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> search = GoalSearch()
    >>> ego = torch.zeros(3, 32, 32, dtype=torch.uint8)
    >>> ego[0, 8:14, 12:20] = 255            # an obstacle 0.3-1.1 m ahead, across the line
    >>> td = TensorDict({"action": torch.tensor(0), "ego_map": ego,
    ...                  "ego_pose": torch.zeros(3), "goal_seen": torch.tensor([False]),
    ...                  "action_mask": torch.ones(8, dtype=torch.bool)}, [])
    >>> a = search(td)["action"].item()
    >>> a in (2, 3, 6, 7), td["goal_search_fired"].item()   # round it, not into it
    (True, True)
"""

from __future__ import annotations

import heapq
import math

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

__all__ = ["GoalSearch"]

#: Action indices in :data:`~torchrl_causal.schema.ACTION_NAMES` order.
_FORWARD, _BACKWARD, _LEFT, _RIGHT, _TURN_LEFT, _TURN_RIGHT = 0, 1, 2, 3, 6, 7
_SQRT2 = math.sqrt(2.0)


def _positive(name, value, low=0.0, strict=True):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > low if strict else value >= low)
    if not ok:
        raise ValueError(f"GoalSearch {name} must be a finite number {'>' if strict else '>='} "
                         f"{low}, got {value!r}")


class GoalSearch(TensorDictModuleBase):
    """Replaces the action by a search move round the map's obstacles while the goal is unseen.

    Args:
        distance: the searched point lies this far ahead of the start, on the
            start's heading (m).
        lead: ... and at least this far beyond the drone's own progress along
            that line (m), so the search keeps going ahead once it passes it.
        resolution: the ego map's cell side (m), as the
            :class:`~torchrl_causal.transforms.EgoMap` that writes it.
        inflate: obstacle cells are grown by this radius (m) before planning
            (the hull's half width and a margin); where that closes every way
            to the target, the plan is made again without growing.
        step_size: the length of one move (m), as the env's.
        turn_tolerance_deg: turn towards the searched point when its bearing
            leaves the heading by more than this.
        stuck_turns: once the goal has been seen, the same planner takes over
            towards the remembered goal (``goal_memory``) for a step where the
            policy's last ``stuck_turns`` actions (``action_history``) and its
            choice are all turns -- a policy turning back and forth in front of
            what blocks it (0: never; also never where the tensordict carries
            no ``action_history``).
        action_key, ego_map_key, pose_key, seen_key: the keys read
            (``ego_map``: uint8 ``[..., 3, S, S]`` with the obstacle channel
            first, row 0 ahead, column 0 to the left; ``ego_pose``: x, y, yaw
            in the start frame; ``goal_seen``: bool ``[..., 1]``).
        action_mask_key: the allowed actions (bool ``[..., 8]``), or None.
        history_key, goal_memory_key: the keys read for ``stuck_turns``.

    ``goal_search_fired`` (bool) records where the search chose the action.

    Example:
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl_causal.envs import DroneNavEnv
        >>> from torchrl_causal.transforms import EgoMap
        >>> env = TransformedEnv(DroneNavEnv("random", seed=3, image_size=32),
        ...                      EgoMap())
        >>> td = env.reset()
        >>> _ = td.set("action", torch.tensor(4))  # the policy's choice: ascend
        >>> out = GoalSearch()(td)
        >>> out["goal_search_fired"].item() == (not td["goal_seen"].item())
        True
    """

    def __init__(self, distance: float = 4.0, lead: float = 2.0, *, resolution: float = 0.15,
                 inflate: float = 0.2, step_size: float = 0.25,
                 turn_tolerance_deg: float = 20.0,
                 stuck_turns: int = 4, action_key="action", ego_map_key="ego_map",
                 pose_key="ego_pose", seen_key="goal_seen", action_mask_key="action_mask",
                 history_key="action_history", goal_memory_key="goal_memory"):
        super().__init__()
        _positive("distance", distance)
        _positive("lead", lead, strict=False)
        _positive("resolution", resolution)
        _positive("inflate", inflate, strict=False)
        _positive("step_size", step_size)
        _positive("turn_tolerance_deg", turn_tolerance_deg)
        if turn_tolerance_deg >= 90:
            raise ValueError(f"GoalSearch turn_tolerance_deg must be < 90, got "
                             f"{turn_tolerance_deg!r}")
        self.distance, self.lead = float(distance), float(lead)
        self.resolution, self.inflate = float(resolution), float(inflate)
        self.step_size = float(step_size)
        self.turn_tolerance = math.radians(float(turn_tolerance_deg))
        self.action_key, self.ego_map_key = action_key, ego_map_key
        self.pose_key, self.seen_key, self.action_mask_key = pose_key, seen_key, action_mask_key
        if isinstance(stuck_turns, bool) or not isinstance(stuck_turns, int) or stuck_turns < 0:
            raise ValueError(f"GoalSearch stuck_turns must be an int >= 0 (0: off), got "
                             f"{stuck_turns!r}")
        self.stuck_turns = stuck_turns
        self.history_key, self.goal_memory_key = history_key, goal_memory_key
        self.in_keys = [action_key, ego_map_key, pose_key, seen_key] + (
            [action_mask_key] if action_mask_key is not None else []) + (
            [history_key, goal_memory_key] if stuck_turns else [])
        self.out_keys = [action_key, "goal_search_fired"]

    # ------------------------------------------------------------ planning
    def target(self, pose) -> tuple[float, float]:
        """The searched point relative to the drone: (ahead, left) in metres."""
        x, y, yaw = (float(v) for v in pose)
        tx = max(self.distance, x + self.lead)
        dx, dy = tx - x, -y
        c, s = math.cos(yaw), math.sin(yaw)
        return c * dx + s * dy, -s * dx + c * dy

    def _cell(self, ahead, left, size):
        """Continuous (row, col) of an ego-frame point; the drone is at (size/2, size/2)."""
        return size / 2.0 - ahead / self.resolution, size / 2.0 - left / self.resolution

    @staticmethod
    def _grow(occ: np.ndarray, radius: int) -> np.ndarray:
        if radius <= 0:
            return occ.copy()
        out = occ.copy()
        size = occ.shape[0]
        for di in range(-radius, radius + 1):
            for dj in range(-radius, radius + 1):
                if di * di + dj * dj > radius * radius:
                    continue
                src = occ[max(0, -di): size - max(0, di), max(0, -dj): size - max(0, dj)]
                out[max(0, di): size - max(0, -di), max(0, dj): size - max(0, -dj)] |= src
        return out

    @staticmethod
    def _distances(blocked: np.ndarray, goal: tuple[int, int]) -> np.ndarray:
        """8-connected path length (cells) from every cell to ``goal`` (inf: no way)."""
        size = blocked.shape[0]
        dist = np.full(blocked.shape, np.inf)
        if blocked[goal]:
            return dist
        dist[goal] = 0.0
        heap = [(0.0, goal)]
        steps = [(-1, 0, 1.0), (1, 0, 1.0), (0, -1, 1.0), (0, 1, 1.0), (-1, -1, _SQRT2),
                 (-1, 1, _SQRT2), (1, -1, _SQRT2), (1, 1, _SQRT2)]
        while heap:
            d, (i, j) = heapq.heappop(heap)
            if d > dist[i, j]:
                continue
            for di, dj, w in steps:
                a, b = i + di, j + dj
                if 0 <= a < size and 0 <= b < size and not blocked[a, b] and d + w < dist[a, b]:
                    dist[a, b] = d + w
                    heapq.heappush(heap, (d + w, (a, b)))
        return dist

    def plan(self, occupied: np.ndarray, pose, target=None) -> np.ndarray:
        """Path length (m) to ``target`` (ahead, left; m; default :meth:`target`, the
        searched point) from every cell of the ego window.

        Obstacles are grown by ``inflate``; a cell inside the grown margin (but
        not on an obstacle) gets its path length on the map without growing,
        plus a metre, so that a drone already inside the margin is led out of
        it rather than stopped. ``inf``: no way there on the map.
        """
        size = occupied.shape[0]
        ahead, left = self.target(pose) if target is None else target
        # the point, or where its direction leaves the window
        reach = max(abs(ahead), abs(left), 1e-6)
        shrink = min(1.0, (size / 2.0 - 1.0) * self.resolution / reach)
        r, c = self._cell(ahead * shrink, left * shrink, size)
        goal = (int(np.clip(math.floor(r), 0, size - 1)), int(np.clip(math.floor(c), 0, size - 1)))
        radius = int(math.ceil(self.inflate / self.resolution))
        out = np.full(occupied.shape, np.inf)
        for rad, extra in ((radius, 0.0), (0, 1.0)):
            blocked = self._grow(occupied, rad)
            free = np.argwhere(~blocked)
            if not len(free):
                continue
            g = goal
            if blocked[g]:  # the nearest free cell to the point
                k = np.argmin(((free - np.array(g)) ** 2).sum(1))
                g = (int(free[k][0]), int(free[k][1]))
            dist = self._distances(blocked, g) * self.resolution + extra
            out = np.where(np.isfinite(out), out, dist)
        return out

    def _value(self, dist: np.ndarray, ahead: float, left: float) -> float:
        """The path length at a point: the least of the four cells nearest to it."""
        size = dist.shape[0]
        r, c = self._cell(ahead, left, size)
        i, j = int(round(r)) - 1, int(round(c)) - 1
        block = dist[max(i, 0): max(i + 2, 0), max(j, 0): max(j + 2, 0)]
        return float(block.min()) if block.size else math.inf

    def choose(self, occupied: np.ndarray, pose, allowed: np.ndarray, target=None,
               last: int | None = None) -> int:
        """The move for one drone (an action index) towards ``target`` (ahead, left; m; default
        :meth:`target`, the searched point); ``last``: the previous action, never undone
        by the next turn (the search does not turn back and forth)."""
        ahead, left = self.target(pose) if target is None else (float(target[0]),
                                                                 float(target[1]))
        bearing = math.atan2(left, ahead)
        toward = _TURN_LEFT if bearing > 0 else _TURN_RIGHT
        undo = {_TURN_LEFT: _TURN_RIGHT, _TURN_RIGHT: _TURN_LEFT, _FORWARD: _BACKWARD,
                _BACKWARD: _FORWARD, _LEFT: _RIGHT, _RIGHT: _LEFT}.get(last)
        if abs(bearing) > self.turn_tolerance and toward != undo:
            return toward  # keep the camera on where the goal should be
        dist = self.plan(occupied, pose, (ahead, left))
        here = self._value(dist, 0.0, 0.0)
        s = self.step_size
        moves = {_FORWARD: (s, 0.0), _LEFT: (0.0, s), _RIGHT: (0.0, -s), _BACKWARD: (-s, 0.0)}
        scored = [(self._value(dist, *moves[a]), a) for a in moves if allowed[a] and a != undo]
        # a move that gets closer along the path, the forward one first among equals
        scored = sorted((v, a) for v, a in scored if v < here - 0.5 * self.resolution)
        if scored:
            return scored[0][1]
        # no move gets closer: look round, on in the direction of the last turn
        return last if last in (_TURN_LEFT, _TURN_RIGHT) else toward

    def stuck(self, history: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Where the last ``stuck_turns`` actions and ``action`` are all turns (bool, batch
        shape): a policy turning back and forth in front of what blocks it."""
        n = 8
        k = self.stuck_turns
        if history.shape[-1] % n or history.shape[-1] // n < k:
            raise ValueError(f"GoalSearch(stuck_turns={k}) reads {k} one-hot blocks of {n} "
                             f"actions from {self.history_key!r}, got {history.shape[-1]} values")
        blocks = history.reshape(*history.shape[:-1], -1, n)[..., :k, :]
        turns = blocks[..., [_TURN_LEFT, _TURN_RIGHT]].sum(-1) > 0.5
        return turns.all(-1) & ((action == _TURN_LEFT) | (action == _TURN_RIGHT))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(self.action_key)
        if action.is_floating_point() or action.dtype == torch.bool:
            raise ValueError(f"GoalSearch needs an action index, got {action.dtype} "
                             f"{tuple(action.shape)}")
        seen = tensordict.get(self.seen_key).bool().reshape(action.shape)
        search = ~seen
        unstick = torch.zeros_like(seen)
        history = tensordict.get(self.history_key, None)
        if self.stuck_turns and history is not None:
            unstick = seen & self.stuck(history, action)
        ego = tensordict.get(self.ego_map_key)
        pose = tensordict.get(self.pose_key).reshape(-1, 3).cpu().numpy()
        occ = (ego[..., 0, :, :] > 0).reshape(-1, *ego.shape[-2:]).cpu().numpy()
        if self.action_mask_key is not None:
            mask = tensordict.get(self.action_mask_key).bool()
            allowed = mask.reshape(-1, mask.shape[-1]).cpu().numpy()
        else:
            allowed = np.ones((occ.shape[0], 8), dtype=bool)
        last = [None] * occ.shape[0]
        if history is not None and history.shape[-1] >= 8:
            first = history.reshape(-1, history.shape[-1])[:, :8]
            last = [int(a) if t else None for a, t in
                    zip(first.argmax(-1).tolist(), (first.sum(-1) > 0.5).tolist())]
        out = action.reshape(-1).clone()
        for b in torch.nonzero(search.reshape(-1)).flatten().tolist():
            out[b] = self.choose(occ[b], pose[b], allowed[b], last=last[b])
        flat_unstick = unstick.reshape(-1)
        if flat_unstick.any():
            memory = tensordict.get(self.goal_memory_key).reshape(-1, 6).cpu().numpy()
            for b in torch.nonzero(flat_unstick).flatten().tolist():
                goal = (5.0 * memory[b, 1], 5.0 * memory[b, 2])  # ahead, left (m)
                out[b] = self.choose(occ[b], pose[b], allowed[b], target=goal, last=last[b])
        tensordict.set(self.action_key, out.reshape(action.shape).to(action.dtype))
        tensordict.set("goal_search_fired", search | unstick)
        return tensordict
