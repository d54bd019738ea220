"""Gymnasium registration: ``torchrl_causal/DroneNav-v0`` and ``torchrl_causal/GridNav-v0``.

:func:`register_envs` registers :class:`DroneNavGymEnv` and the grid world
:class:`~torchrl_causal.envs.gridworld.GridNavEnv` (idempotent). It is
the package's ``gymnasium.envs`` entry point (``pyproject.toml``); gymnasium
1.x does not load entry points by itself, so call it (or import
:mod:`torchrl_causal.envs.gym_registration`, which calls it) before
``gymnasium.make``. Keyword arguments of ``gymnasium.make`` are
:class:`~torchrl_causal.envs.DroneNavEnv` options.

Example:
    >>> import gymnasium as gym
    >>> from torchrl_causal.envs.gym_registration import register_envs, GYM_ID
    >>> register_envs()
    >>> env = gym.make(GYM_ID, seed=0)
    >>> obs, info = env.reset(seed=0)
    >>> obs["pixels"].shape, env.action_space
    ((84, 84, 3), Discrete(8))
    >>> env.close()
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

__all__ = ["GYM_ID", "GRIDNAV_GYM_ID", "DroneNavGymEnv", "register_envs"]

#: Gymnasium id of the environment.
GYM_ID = "torchrl_causal/DroneNav-v0"
#: Gymnasium id of the grid world (same as ``torchrl_causal.envs.gridworld.GRIDNAV_GYM_ID``).
GRIDNAV_GYM_ID = "torchrl_causal/GridNav-v0"

_FLAGS = ("goal_in_sight", "crashed", "reached", "out_of_bounds")


class DroneNavGymEnv(gym.Env):
    """Gymnasium view of :class:`~torchrl_causal.envs.DroneNavEnv` (numpy, ``Dict`` observations).

    Bool observation keys (``goal_in_sight``, ``crashed``, ``reached``,
    ``out_of_bounds``) are
    ``MultiBinary(1)`` (``int8``); the others are ``Box`` spaces with the
    TorchRL spec's bounds. ``info`` holds ``crashed`` and ``reached``.

    Args:
        render_mode: ``None`` or ``"rgb_array"`` (returns the camera image).
        env: a TorchRL env to expose instead of a new ``DroneNavEnv`` -- e.g.
            a ``TransformedEnv`` with the nine features
            (:func:`~torchrl_causal.transforms.make_causal_transforms`), so that
            another library (Stable-Baselines3) trains on the same
            observations; unbatched, CPU, a ``Categorical`` action.
        obs_keys: the observation keys to expose (default: all of the env's).
        **options: :class:`~torchrl_causal.envs.DroneNavEnv` options
            (``device`` is forced to CPU), when ``env`` is not given.

    Example:
        >>> env = DroneNavGymEnv(seed=0)
        >>> obs, _ = env.reset(seed=1)
        >>> obs, r, term, trunc, info = env.step(0)
        >>> isinstance(r, float), sorted(info)
        (True, ['crashed', 'reached'])
        >>> env.close()
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 5}

    def __init__(self, render_mode: str | None = None, *, env=None, obs_keys=None, **options):
        from .drone import DroneNavEnv

        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        if env is None:
            options["device"] = "cpu"
            env = DroneNavEnv(**options)
        elif options:
            raise ValueError(f"DroneNavGymEnv: give env= or DroneNavEnv options, not both "
                             f"(got {sorted(options)})")
        if tuple(env.batch_size):
            raise ValueError(f"DroneNavGymEnv needs an unbatched env, got batch_size "
                             f"{tuple(env.batch_size)}")
        self.env = env
        self.action_space = spaces.Discrete(int(self.env.action_spec.n))
        spec_keys = list(self.env.observation_spec.keys())
        if obs_keys is not None:
            missing = [k for k in obs_keys if k not in spec_keys]
            if missing:
                raise ValueError(f"obs_keys {missing} are not observations of the env "
                                 f"(it has {spec_keys})")
        obs_spaces = {}
        for key, spec in self.env.observation_spec.items():
            if obs_keys is not None and key not in obs_keys:
                continue
            if not isinstance(key, str):
                continue
            shape = tuple(spec.shape)
            if key in _FLAGS:
                obs_spaces[key] = spaces.MultiBinary(shape)
                continue
            dtype = np.uint8 if key == "pixels" else (
                np.int64 if not spec.dtype.is_floating_point and spec.dtype != torch.bool
                else np.float32)
            if hasattr(spec, "space") and hasattr(spec.space, "low"):
                low = spec.space.low.cpu().numpy().astype(dtype)
                high = spec.space.high.cpu().numpy().astype(dtype)
            else:
                low = np.full(shape, -np.inf, dtype=np.float32)
                high = np.full(shape, np.inf, dtype=np.float32)
            obs_spaces[key] = spaces.Box(low=low, high=high, shape=shape, dtype=dtype)
        self.observation_space = spaces.Dict(obs_spaces)
        self._last = None

    def _to_obs(self, td):
        obs = {}
        for key in self.observation_space.spaces:
            v = td.get(key).cpu().numpy()
            space = self.observation_space.spaces[key]
            obs[key] = v.astype(np.int8) if key in _FLAGS else v.astype(space.dtype, copy=False)
        self._last = obs
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self.env.set_seed(int(seed))
        td = self.env.reset()
        obs = self._to_obs(td)
        return obs, {"crashed": False, "reached": False}

    def step(self, action):
        import torch

        if self._last is None:
            raise RuntimeError("call reset() before step()")
        td = self.env.step(
            self.env.full_action_spec.zero().set("action", torch.as_tensor(int(action)))
        )["next"]
        obs = self._to_obs(td)
        info = {"crashed": bool(td["crashed"]), "reached": bool(td["reached"])}
        return (
            obs,
            float(td["reward"]),
            bool(td["terminated"]),
            bool(td["truncated"]),
            info,
        )

    def render(self):
        if self.render_mode == "rgb_array" and self._last is not None:
            return self._last["pixels"].copy()
        return None

    def close(self):
        if getattr(self, "env", None) is not None and not self.env.is_closed:
            self.env.close()


def register_envs() -> None:
    """Registers :data:`GYM_ID` and :data:`GRIDNAV_GYM_ID` with gymnasium (idempotent).

    Keyword arguments of ``gymnasium.make(GRIDNAV_GYM_ID, ...)`` are
    :class:`~torchrl_causal.envs.gridworld.GridNavEnv` options; it truncates
    episodes itself (``max_steps``), so no ``TimeLimit`` is added.

    Example:
        >>> import gymnasium as gym
        >>> register_envs(); register_envs()  # safe to call twice
        >>> GYM_ID in gym.registry, GRIDNAV_GYM_ID in gym.registry
        (True, True)
        >>> env = gym.make(GRIDNAV_GYM_ID, size=5)
        >>> env.reset(seed=0)[0]["observation"].shape
        (50,)
    """
    if GYM_ID not in gym.registry:
        gym.register(
            id=GYM_ID,
            entry_point="torchrl_causal.envs.gym_registration:DroneNavGymEnv",
            max_episode_steps=None,
        )
    if GRIDNAV_GYM_ID not in gym.registry:
        gym.register(
            id=GRIDNAV_GYM_ID,
            entry_point="torchrl_causal.envs.gridworld:GridNavEnv",
            max_episode_steps=None,
        )


register_envs()
