"""``GridNavEnv``: a small, fast grid-world navigation task with a known causal structure.

A companion to the MuJoCo drone for seeing in seconds whether the CBN gate
helps: an agent on a ``size x size`` grid (default 7) with fixed interior walls
must reach a goal with four moves (``up``, ``down``, ``left``, ``right``).
Moving into a wall or off the grid is a crash; both crash and reaching the goal
end the episode, and ``max_steps`` (default 50) truncates it. Start and goal are
drawn uniformly among the free cells at every reset (start != goal).

Reward ("progress", so that the CBN reward class ``reward >= 0`` means a good move):

===================================== =======
event                                 reward
===================================== =======
reach the goal                        +1.0
crash (wall or border)                -1.0
Manhattan distance to the goal drops  +0.1
otherwise (it rises)                  -0.1
===================================== =======

On a 4-connected grid every move that does not crash changes the Manhattan
distance by exactly one, so a move is good iff it is not blocked and goes
towards the goal along its axis. That is the *known causal structure*: for
action ``up`` the reward's parents are ``blocked_up`` and ``goal_row`` (is the
goal above, level, below), and likewise for the other three
(:func:`gridnav_expert_dags`).

The Q-network sees only the one-hot agent and goal cells (``observation``);
the causal variables come from the raw features ``blocked`` and ``goal_offset``
through :class:`~torchrl_causal.transforms.Discretize` with
:data:`GRIDNAV_SCHEMA`. :func:`make_gridnav_env` builds the whole TorchRL env.

Example:
    >>> from torchrl_causal.envs.gridworld import GridNavEnv
    >>> env = GridNavEnv()
    >>> obs, info = env.reset(seed=0, options={"start": (0, 0), "goal": (0, 3)})
    >>> obs["blocked"].tolist(), obs["goal_offset"].tolist()
    ([1.0, 0.0, 1.0, 0.0], [0.0, 3.0])
    >>> env.step(3)[1:4]  # right: one step closer
    (0.1, False, False)
    >>> env.step(0)[1:4]  # up: off the grid, a crash
    (-1.0, True, False)
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from torchrl_causal.schema import REWARD_NODE, T1_SUFFIX, T_SUFFIX, Variable, VariableSchema

__all__ = [
    "GridNavEnv",
    "GRIDNAV_ACTIONS",
    "GRIDNAV_SCHEMA",
    "GRIDNAV_GYM_ID",
    "DEFAULT_GRIDNAV_OBSTACLES",
    "gridnav_expert_dags",
    "make_gridnav_env",
]

#: Action names, in action order: action ``i`` is ``GRIDNAV_ACTIONS[i]``.
GRIDNAV_ACTIONS: tuple[str, ...] = ("up", "down", "left", "right")
#: Gymnasium id of :class:`GridNavEnv`.
GRIDNAV_GYM_ID = "torchrl_causal/GridNav-v0"

#: (row, col) step of each action; rows grow downwards.
_MOVES = np.array([(-1, 0), (1, 0), (0, -1), (0, 1)], dtype=np.int64)

#: The walls of the default 7x7 map (``#``; every free cell reaches every other)::
#:
#:     . . . . . . .
#:     . # # . # # .
#:     . . . . . . .
#:     . # . # # . .
#:     . # . . . . .
#:     . . . # . # .
#:     . . . . . . .
DEFAULT_GRIDNAV_OBSTACLES: tuple[tuple[int, int], ...] = (
    (1, 1), (1, 2), (1, 4), (1, 5),
    (3, 1), (3, 3), (3, 4),
    (4, 1),
    (5, 3), (5, 5),
)

REWARD_GOAL = 1.0
REWARD_CRASH = -1.0
REWARD_CLOSER = 0.1
REWARD_FURTHER = -0.1


def _cell(value, what: str, size: int) -> tuple[int, int]:
    try:
        r, c = (int(v) for v in value)
        ok = all(float(v) == int(v) for v in value)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{what} must be a (row, col) pair of ints, got {value!r}")
    if not (0 <= r < size and 0 <= c < size):
        raise ValueError(f"{what} {value!r} is outside the {size}x{size} grid")
    return r, c


class GridNavEnv(gym.Env):
    """Grid-world navigation with walls, a goal and a known causal structure.

    Observation (a ``Dict``):

    * ``observation``: ``float32 [2 * size**2]``, the one-hot agent cell then
      the one-hot goal cell (row-major) -- what the Q-network sees;
    * ``blocked``: ``float32 [4]``, 1.0 where the neighbour cell up / down /
      left / right is a wall or off the grid;
    * ``goal_offset``: ``float32 [2]``, ``(goal_row - row, goal_col - col)``
      (negative row offset: the goal is above);
    * ``reached``, ``crashed``: ``bool [1]`` flags of the step (``Box`` of
      dtype bool, so TorchRL's ``GymWrapper`` gives them bool ``[1]`` specs).

    A crash leaves the agent where it was. ``info`` holds ``success`` (same
    as ``reached``), ``reached`` and ``crashed``. The module docs give the
    reward table.

    Args:
        size: grid side, ``>= 2`` (default 7).
        obstacles: wall cells ``(row, col)``; default
            :data:`DEFAULT_GRIDNAV_OBSTACLES` for ``size=7``, no walls otherwise.
            Every free cell must reach every other, and at least two must be free.
        max_steps: steps before truncation, ``>= 1`` (default 50).
        render_mode: ``None`` or ``"ansi"`` (``render()`` returns the map as text).
        goal: a fixed goal cell ``(row, col)`` for every episode (default
            ``None``: drawn at every reset); a ``"goal"`` reset option overrides it.

    Raises:
        ValueError: naming the value, for a bad size, ``max_steps``,
            obstacle outside the grid, a map whose free cells are not all
            connected, a ``goal`` on a wall or off the grid, or (at :meth:`reset`) a ``start`` / ``goal`` option on a
            wall, off the grid, or both on the same cell.

    :meth:`reset` accepts ``options={"start": (r, c), "goal": (r, c)}`` to
    place either by hand (the other one is drawn).

    Example:
        >>> env = GridNavEnv(size=5, obstacles=[(2, 2)], max_steps=10)
        >>> obs, info = env.reset(seed=3)
        >>> obs["observation"].shape, env.action_space
        ((50,), Discrete(4))
        >>> a = env.oracle_action()  # the first move of a shortest path
        >>> obs, r, terminated, truncated, info = env.step(a)
        >>> r > 0, sorted(info)
        (True, ['crashed', 'reached', 'success'])
        >>> GridNavEnv(obstacles=[(0, 1), (1, 0)])
        Traceback (most recent call last):
        ...
        ValueError: obstacles [(0, 1), (1, 0)] cut the free cells of the 7x7 grid apart: cell (0, 0) cannot reach (0, 2)
    """

    metadata = {"render_modes": ["ansi"], "render_fps": 4}

    def __init__(
        self,
        size: int = 7,
        obstacles: Iterable[tuple[int, int]] | None = None,
        max_steps: int = 50,
        render_mode: str | None = None,
        goal: tuple[int, int] | None = None,
    ):
        if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 2:
            raise ValueError(f"size must be an int >= 2, got {size!r}")
        if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
            raise ValueError(f"max_steps must be an int >= 1, got {max_steps!r}")
        if render_mode not in (None, "ansi"):
            raise ValueError(f"render_mode must be None or 'ansi', got {render_mode!r}")
        self.size = size = int(size)
        self.max_steps = int(max_steps)
        self.render_mode = render_mode
        if obstacles is None:
            obstacles = DEFAULT_GRIDNAV_OBSTACLES if size == 7 else ()
        given = list(obstacles)
        walls = np.zeros((size, size), dtype=bool)
        for cell in given:
            walls[_cell(cell, "obstacle", size)] = True
        self.walls = walls
        self.obstacles: tuple[tuple[int, int], ...] = tuple(
            (int(r), int(c)) for r, c in zip(*np.nonzero(walls))
        )
        self.free_cells = np.argwhere(~walls)
        if len(self.free_cells) < 2:
            raise ValueError(
                f"obstacles {given!r} leave {len(self.free_cells)} free cell(s) of the "
                f"{size}x{size} grid; need at least 2 (a start and a goal)"
            )
        self.fixed_goal = None if goal is None else _cell(goal, "goal", size)
        if self.fixed_goal is not None and walls[self.fixed_goal]:
            raise ValueError(f"goal {goal!r} is an obstacle cell")
        first = tuple(int(v) for v in self.free_cells[0])
        dist = self._bfs(first)
        unreached = np.argwhere(~walls & (dist < 0))
        if len(unreached):
            bad = tuple(int(v) for v in unreached[0])
            raise ValueError(
                f"obstacles {given!r} cut the free cells of the {size}x{size} grid apart: "
                f"cell {first} cannot reach {bad}"
            )
        n = size * size
        self.action_space = spaces.Discrete(4)
        self.observation_space = spaces.Dict(
            {
                "observation": spaces.Box(0.0, 1.0, (2 * n,), np.float32),
                "blocked": spaces.Box(0.0, 1.0, (4,), np.float32),
                "goal_offset": spaces.Box(-(size - 1), size - 1, (2,), np.float32),
                "reached": spaces.Box(0, 1, (1,), bool),
                "crashed": spaces.Box(0, 1, (1,), bool),
            }
        )
        self.agent: tuple[int, int] | None = None
        self.goal: tuple[int, int] | None = None
        self.steps = 0
        self._goal_dist: np.ndarray | None = None

    # ----------------------------------------------------------------- grid
    def _bfs(self, source: tuple[int, int]) -> np.ndarray:
        """Shortest-path step counts from ``source`` to every cell (-1: unreachable or wall)."""
        dist = np.full((self.size, self.size), -1, dtype=np.int64)
        dist[source] = 0
        queue = deque([source])
        while queue:
            r, c = queue.popleft()
            for dr, dc in _MOVES:
                nr, nc = r + dr, c + dc
                if 0 <= nr < self.size and 0 <= nc < self.size and not self.walls[nr, nc] and dist[nr, nc] < 0:
                    dist[nr, nc] = dist[r, c] + 1
                    queue.append((nr, nc))
        return dist

    def is_blocked(self, cell: tuple[int, int]) -> bool:
        """Whether ``cell`` is a wall or off the grid.

        Example:
            >>> env = GridNavEnv()
            >>> env.is_blocked((1, 1)), env.is_blocked((0, 0)), env.is_blocked((-1, 0))
            (True, False, True)
        """
        r, c = cell
        return not (0 <= r < self.size and 0 <= c < self.size) or bool(self.walls[r, c])

    def shortest_path_length(self) -> int:
        """Fewest moves from the agent to the goal (call after :meth:`reset`).

        Example:
            >>> env = GridNavEnv()
            >>> _ = env.reset(options={"start": (0, 0), "goal": (2, 2)})
            >>> env.shortest_path_length()
            4
        """
        self._check_started()
        return int(self._goal_dist[self.agent])

    def oracle_action(self) -> int:
        """The first move of a shortest path to the goal (lowest action index on ties).

        Example:
            >>> env = GridNavEnv()
            >>> _ = env.reset(options={"start": (2, 1), "goal": (0, 1)})
            >>> GRIDNAV_ACTIONS[env.oracle_action()]  # (1, 1) is a wall: go round
            'left'
        """
        self._check_started()
        here = self._goal_dist[self.agent]
        for a, (dr, dc) in enumerate(_MOVES):
            cell = (self.agent[0] + dr, self.agent[1] + dc)
            if not self.is_blocked(cell) and self._goal_dist[cell] == here - 1:
                return a
        raise RuntimeError("the agent is on the goal; reset the env")  # pragma: no cover

    def _check_started(self):
        if self.agent is None:
            raise RuntimeError("call reset() before step()")

    # ------------------------------------------------------------ gymnasium
    def _obs(self, reached: bool, crashed: bool) -> dict:
        n = self.size * self.size
        onehot = np.zeros(2 * n, dtype=np.float32)
        onehot[self.agent[0] * self.size + self.agent[1]] = 1.0
        onehot[n + self.goal[0] * self.size + self.goal[1]] = 1.0
        blocked = np.array(
            [self.is_blocked((self.agent[0] + dr, self.agent[1] + dc)) for dr, dc in _MOVES],
            dtype=np.float32,
        )
        offset = np.array(
            [self.goal[0] - self.agent[0], self.goal[1] - self.agent[1]], dtype=np.float32
        )
        return {
            "observation": onehot,
            "blocked": blocked,
            "goal_offset": offset,
            "reached": np.array([reached]),
            "crashed": np.array([crashed]),
        }

    def _placed(self, options: dict, key: str):
        if key not in options or options[key] is None:
            return None
        cell = _cell(options[key], key, self.size)
        if self.walls[cell]:
            raise ValueError(f"{key} {options[key]!r} is a wall cell")
        return cell

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode; ``options`` may hold ``"start"`` and/or ``"goal"`` cells."""
        super().reset(seed=seed)
        options = options or {}
        start, goal = self._placed(options, "start"), self._placed(options, "goal")
        if goal is None and self.fixed_goal is not None:
            goal = tuple(int(v) for v in self.fixed_goal)
        if start is not None and start == goal:
            raise ValueError(f"start {options['start']!r} and goal {options['goal']!r} are the same cell")
        free = [tuple(int(v) for v in c) for c in self.free_cells]
        if goal is None:
            pool = [c for c in free if c != start]
            goal = pool[int(self.np_random.integers(len(pool)))]
        if start is None:
            pool = [c for c in free if c != goal]
            start = pool[int(self.np_random.integers(len(pool)))]
        self.agent, self.goal, self.steps = start, goal, 0
        self._goal_dist = self._bfs(goal)
        info = {"success": False, "reached": False, "crashed": False}
        return self._obs(False, False), info

    def step(self, action):
        self._check_started()
        a = int(action)
        if not 0 <= a < 4:
            raise ValueError(f"action must be in [0, 4), got {action!r}")
        self.steps += 1
        dr, dc = _MOVES[a]
        target = (self.agent[0] + int(dr), self.agent[1] + int(dc))
        reached = crashed = False
        if self.is_blocked(target):
            crashed, reward = True, REWARD_CRASH
        else:
            before = abs(self.goal[0] - self.agent[0]) + abs(self.goal[1] - self.agent[1])
            self.agent = target
            after = abs(self.goal[0] - target[0]) + abs(self.goal[1] - target[1])
            if target == self.goal:
                reached, reward = True, REWARD_GOAL
            else:
                reward = REWARD_CLOSER if after < before else REWARD_FURTHER
        terminated = reached or crashed
        truncated = not terminated and self.steps >= self.max_steps
        info = {"success": reached, "reached": reached, "crashed": crashed}
        return self._obs(reached, crashed), float(reward), terminated, truncated, info

    def render(self):
        """The map as text (``A`` agent, ``G`` goal, ``#`` wall) in ``"ansi"`` mode, else None.

        Example:
            >>> env = GridNavEnv(size=3, obstacles=[(1, 1)], render_mode="ansi")
            >>> _ = env.reset(options={"start": (0, 0), "goal": (2, 2)})
            >>> print(env.render())
            A . .
            . # .
            . . G
        """
        if self.render_mode != "ansi" or self.agent is None:
            return None
        rows = []
        for r in range(self.size):
            row = []
            for c in range(self.size):
                row.append("A" if (r, c) == self.agent else "G" if (r, c) == self.goal
                           else "#" if self.walls[r, c] else ".")
            rows.append(" ".join(row))
        return "\n".join(rows)


# ------------------------------------------------------------------ causal side
def _blocked(k: int, direction: str) -> Variable:
    return Variable(
        f"blocked_{direction}",
        ("free", "blocked"),
        f"the cell {direction} of the agent is a wall or off the grid",
        bins=(0.5,),
        source="blocked",
        index=k,
        clip=(0.0, 1.0),
    )


#: The six causal variables of :class:`GridNavEnv`, with the rules that
#: :class:`~torchrl_causal.transforms.Discretize` applies to its raw features:
#:
#: ============== ===== =================================================
#: variable       card. categories (code order), rule
#: ============== ===== =================================================
#: blocked_up     2     free, blocked: ``blocked[..., 0] > 0.5``
#: blocked_down   2     free, blocked: ``blocked[..., 1]``
#: blocked_left   2     free, blocked: ``blocked[..., 2]``
#: blocked_right  2     free, blocked: ``blocked[..., 3]``
#: goal_row       3     above (``goal_offset[..., 0] < -0.5``), same, below (``> 0.5``)
#: goal_col       3     left (``goal_offset[..., 1] < -0.5``), same, right (``> 0.5``)
#: ============== ===== =================================================
#:
#: ``2**4 * 3**2 = 144`` joint states.
GRIDNAV_SCHEMA = VariableSchema(
    tuple(_blocked(k, d) for k, d in enumerate(GRIDNAV_ACTIONS))
    + (
        Variable(
            "goal_row",
            ("above", "same", "below"),
            "the goal's row relative to the agent",
            bins=(-0.5, 0.5),
            source="goal_offset",
            index=0,
        ),
        Variable(
            "goal_col",
            ("left", "same", "right"),
            "the goal's column relative to the agent",
            bins=(-0.5, 0.5),
            source="goal_offset",
            index=1,
        ),
    )
)

_AXIS = {"up": "goal_row", "down": "goal_row", "left": "goal_col", "right": "goal_col"}


def gridnav_expert_dags(schema: VariableSchema = GRIDNAV_SCHEMA) -> dict[str, list[tuple[str, str]]]:
    """The expert (true) DBN of each :class:`GridNavEnv` action.

    Same conventions as the drone's :func:`~torchrl_causal.causal.expert.expert_dags`:
    nodes ``<var>_t``, ``<var>_t1``, ``reward``; edges only forward in time, no
    same-slice edge. For an action moving in direction ``d`` along axis
    ``goal_row`` (up/down) or ``goal_col`` (left/right), 9 edges:

    * ``blocked_d_t -> reward``: a blocked move is a crash (-1);
    * ``<axis>_t -> reward``: a free move is good iff the goal lies that way;
    * ``goal_row_t -> goal_row_t1``, ``goal_col_t -> goal_col_t1``: the goal
      offset changes by at most one cell along the moving axis;
    * ``blocked_d_t -> <axis>_t1``: a crash leaves the offset as it was;
    * ``blocked_x_t -> blocked_x_t1`` for the four directions: a crash keeps
      the agent in place, and walls run in lines, so what blocks a cell
      tends to block its neighbour too.

    Args:
        schema: the schema the nodes must belong to (default :data:`GRIDNAV_SCHEMA`).

    Returns:
        ``{action_name: [(source, target), ...]}`` in :data:`GRIDNAV_ACTIONS` order.

    Raises:
        ValueError: the schema lacks a variable the DAGs use.

    Example:
        >>> dags = gridnav_expert_dags()
        >>> list(dags), len(dags["up"])
        (['up', 'down', 'left', 'right'], 9)
        >>> sorted(s for s, t in dags["left"] if t == "reward")
        ['blocked_left_t', 'goal_col_t']
    """
    names = [f"blocked_{d}" for d in GRIDNAV_ACTIONS] + ["goal_row", "goal_col"]
    missing = [n for n in names if n not in schema.names]
    if missing:
        raise ValueError(f"schema lacks the grid-world variables {missing}; it has {list(schema.names)}")
    dags = {}
    for d in GRIDNAV_ACTIONS:
        axis = _AXIS[d]
        dags[d] = [
            (f"blocked_{d}{T_SUFFIX}", REWARD_NODE),
            (f"{axis}{T_SUFFIX}", REWARD_NODE),
            (f"goal_row{T_SUFFIX}", f"goal_row{T1_SUFFIX}"),
            (f"goal_col{T_SUFFIX}", f"goal_col{T1_SUFFIX}"),
            (f"blocked_{d}{T_SUFFIX}", f"{axis}{T1_SUFFIX}"),
        ] + [(f"blocked_{x}{T_SUFFIX}", f"blocked_{x}{T1_SUFFIX}") for x in GRIDNAV_ACTIONS]
    return dags


def make_gridnav_env(seed: int | None = 0, device="cpu", **kwargs):
    """The TorchRL grid world: ``TransformedEnv(GymWrapper(GridNavEnv(**kwargs)), Discretize(GRIDNAV_SCHEMA))``.

    The action spec is ``Categorical(4)`` (an ``int64`` scalar action, like
    the drone's); the tensordict carries ``observation`` (float32
    ``[2 * size**2]``), ``blocked``, ``goal_offset``, ``reached`` / ``crashed``
    (bool ``[1]``), ``causal_features`` (float32 ``[6]``) and ``causal_state``
    (int64 ``[6]``); ``truncated`` marks the end at ``max_steps``.

    Args:
        seed: seed of the env (``None``: leave unseeded).
        device: device of the TorchRL env.
        **kwargs: :class:`GridNavEnv` options (``size``, ``obstacles``, ``max_steps``, ``goal``).

    Returns:
        a :class:`~torchrl.envs.TransformedEnv`.

    Example:
        >>> env = make_gridnav_env(seed=0)
        >>> td = env.rollout(5)
        >>> td["next", "causal_state"].shape[-1], td["action"].dtype
        (6, torch.int64)
        >>> env.action_spec.n
        4
    """
    from torchrl.envs import GymWrapper, TransformedEnv

    from torchrl_causal.transforms import Discretize

    base = GymWrapper(GridNavEnv(**kwargs), categorical_action_encoding=True, device=device)
    env = TransformedEnv(base, Discretize(schema=GRIDNAV_SCHEMA))
    if seed is not None:
        env.set_seed(int(seed))
    return env
