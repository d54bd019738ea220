"""MuJoCo drone navigation environment (:class:`DroneNavEnv`), its scene, layouts and control;
and a small, fast grid world with a known causal structure (:class:`GridNavEnv`).

Names are imported lazily so that importing this package (e.g. by gymnasium's
registration) stays cheap and free of import cycles with torchrl.

* :class:`DroneNavEnv` -- the TorchRL env (:mod:`torchrl_causal.envs.drone`).
* :mod:`~torchrl_causal.envs.layouts` -- :func:`thesis_layout`,
  :class:`RandomLayoutGenerator`, :class:`Layout`, :class:`Obstacle`.
* :mod:`~torchrl_causal.envs.scene` -- :func:`build_model` (MjSpec), :class:`SceneRenderer`.
* :mod:`~torchrl_causal.envs.control` -- kinematic and physics (cascaded PID) execution.
* :mod:`~torchrl_causal.envs.rewards` -- the ``"progress"`` (default) and ``"thesis"`` rewards.
* :mod:`~torchrl_causal.envs.gridworld` -- :class:`GridNavEnv` (gymnasium, numpy),
  its schema :data:`GRIDNAV_SCHEMA`, expert CBNs :func:`gridnav_expert_dags` and
  the TorchRL factory :func:`make_gridnav_env`.
* :mod:`~torchrl_causal.envs.tello` -- :class:`TelloEnv`, the real DJI Tello (djitellopy) with safety.
* :mod:`~torchrl_causal.envs.tello_video` -- :class:`TelloFrameReader`, djitellopy's video
  reader that skips corrupt packets instead of stopping.
* :mod:`~torchrl_causal.envs.tello_emulator` -- :class:`TelloEmulator`, the Tello SDK over UDP
  with H.264 video, backed by :class:`DroneNavEnv` (software in the loop).
* :mod:`~torchrl_causal.envs.oracle` -- :class:`ShortestPathPlanner` (A* over the env's own
  moves and collision sweep) and :class:`OraclePolicy`: the shortest-path baseline, SPL's
  reference and the imitation teacher (privileged: simulation only).
* :mod:`~torchrl_causal.envs.gym_registration` -- ``torchrl_causal/DroneNav-v0``
  and ``torchrl_causal/GridNav-v0``.
"""

from __future__ import annotations

import importlib

_LAZY = {
    "DroneNavEnv": "drone",
    "EXECUTION_MODES": "drone",
    "LAYOUTS": "drone",
    "Layout": "layouts",
    "Obstacle": "layouts",
    "thesis_layout": "layouts",
    "RandomLayoutGenerator": "layouts",
    "free_path_exists": "layouts",
    "SPLITS": "layouts",
    "build_model": "scene",
    "SceneRenderer": "scene",
    "helipad_image": "scene",
    "board_face_image": "scene",
    "ReachRule": "reach",
    "FinalApproach": "reach",
    "BoardPlaneOffset": "reach",
    "KinematicExecutor": "control",
    "TELLO_MOVE_NOISE": "control",
    "PhysicsExecutor": "control",
    "CascadedPID": "control",
    "action_deltas": "control",
    "REWARDS": "rewards",
    "ProgressReward": "rewards",
    "ThesisReward": "rewards",
    "StepOutcome": "rewards",
    "make_reward": "rewards",
    "DroneNavGymEnv": "gym_registration",
    "register_envs": "gym_registration",
    "GYM_ID": "gym_registration",
    "GridNavEnv": "gridworld",
    "GRIDNAV_SCHEMA": "gridworld",
    "GRIDNAV_ACTIONS": "gridworld",
    "GRIDNAV_GYM_ID": "gridworld",
    "DEFAULT_GRIDNAV_OBSTACLES": "gridworld",
    "gridnav_expert_dags": "gridworld",
    "make_gridnav_env": "gridworld",
    "TelloEnv": "tello",
    "TelloError": "tello",
    "TelloCommandError": "tello",
    "TelloSafetyError": "tello",
    "TelloVideoError": "tello",
    "ACTION_COMMANDS": "tello",
    "TelloEmulator": "tello_emulator",
    "ShortestPathPlanner": "oracle",
    "OraclePolicy": "oracle",
    "PlanningError": "oracle",
    "TelloFaults": "tello_emulator",
    "TelloFrameReader": "tello_video",
}

__all__ = sorted(_LAZY)

# Importing this package registers ``torchrl_causal/DroneNav-v0`` and
# ``torchrl_causal/GridNav-v0`` with gymnasium
# (cheap: the MuJoCo env is only imported when gymnasium makes one), so
# ``gym.make("torchrl_causal.envs:torchrl_causal/DroneNav-v0")`` works without
# any prior import.
from .gym_registration import register_envs as _register_envs  # noqa: E402

_register_envs()


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{mod}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
