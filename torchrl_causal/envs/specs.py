"""The specs shared by the navigation envs (:class:`~torchrl_causal.envs.DroneNavEnv`,
:class:`~torchrl_causal.envs.tello.TelloEnv`): the observation keys the causal feature stack
reads, the 8 actions, a scalar reward and the done flags."""

from __future__ import annotations

import torch
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from ..schema import ACTION_NAMES

__all__ = ["navigation_specs"]


def navigation_specs(image_size, max_depth: float, device, **extra) -> dict:
    """Specs of a navigation env with camera frames of ``image_size = (H, W)``.

    Observations: ``pixels`` uint8 ``[H, W, 3]``, ``depth`` float32 ``[H, W]``
    (metres, up to ``max_depth``), ``altitude`` ``[1]``, ``goal_in_sight`` bool
    ``[1]``, ``goal_distance`` ``[1]``, ``goal_angle`` ``[1]`` (deg), ``crashed`` /
    ``reached`` / ``out_of_bounds`` bool ``[1]``, plus ``extra`` (name -> spec
    factory called with ``(H, W, device)``). Action: ``Categorical(8)`` in
    :data:`~torchrl_causal.schema.ACTION_NAMES` order.

    Returns:
        ``{"observation_spec", "action_spec", "reward_spec", "done_spec"}``.

    Example:
        >>> specs = navigation_specs((84, 84), 10.0, "cpu")
        >>> specs["observation_spec"]["pixels"].shape, specs["action_spec"].space.n
        (torch.Size([84, 84, 3]), 8)
    """
    h, w = int(image_size[0]), int(image_size[1])
    dev = torch.device(device)
    f32 = torch.float32

    def flag():
        return Categorical(2, shape=(1,), dtype=torch.bool, device=dev)

    obs = {
        "pixels": Bounded(0, 255, shape=(h, w, 3), dtype=torch.uint8, device=dev),
        "depth": Bounded(0.0, max_depth, shape=(h, w), dtype=f32, device=dev),
        "altitude": Unbounded(shape=(1,), dtype=f32, device=dev),
        **{name: make(h, w, dev) for name, make in extra.items()},
        "goal_in_sight": flag(),
        "goal_distance": Bounded(0.0, max_depth, shape=(1,), dtype=f32, device=dev),
        "goal_angle": Bounded(-90.0, 90.0, shape=(1,), dtype=f32, device=dev),
        "crashed": flag(),
        "reached": flag(),
        "out_of_bounds": flag(),
    }
    return {
        "observation_spec": Composite(obs, shape=(), device=dev),
        "action_spec": Categorical(len(ACTION_NAMES), shape=(), dtype=torch.int64, device=dev),
        "reward_spec": Unbounded(shape=(1,), dtype=f32, device=dev),
        "done_spec": Composite(done=flag(), terminated=flag(), truncated=flag(), shape=(),
                               device=dev),
    }
