"""Depth estimated from the RGB image, as a transform (in place of the simulator's depth)."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Composite
from torchrl.envs.transforms import Transform

__all__ = ["EstimatedDepth"]


class EstimatedDepth(Transform):
    """Writes ``depth`` estimated from ``pixels`` by a monocular depth estimator.

    Reads ``pixels`` (``uint8 [..., H, W, 3]``) and writes ``depth``
    (``float32 [..., H, W]``, metres, clipped to ``[0, max_depth]``) with any
    depth estimator, a callable ``uint8 [B, H, W, 3] -> float32 [B, H, W]``
    (default: :class:`~torchrl_causal.perception.depth.MonoDepth` with the
    shipped weights). On a :class:`~torchrl_causal.envs.DroneNavEnv` the
    default ``out_key="depth"`` replaces the simulator's exact depth, so
    :class:`~torchrl_causal.transforms.DepthSections` placed after it reads
    the estimate, as on a real drone with an RGB camera only. The output spec
    is ``Bounded(0, max_depth, (*batch, H, W))``.

    Args:
        estimator: the depth estimator (None: ``MonoDepth.load()``).
        max_depth: the output range (m; default: the estimator's
            ``max_depth`` attribute, else 10).
        in_key: the RGB key.
        out_key: the depth key written.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> t = EstimatedDepth(lambda px: torch.full(px.shape[:-1], 2.0))
        >>> td = TensorDict({"pixels": torch.zeros(4, 84, 84, 3, dtype=torch.uint8)}, [4])
        >>> out = t(td)
        >>> out["depth"].shape, out["depth"].dtype, float(out["depth"].max())
        (torch.Size([4, 84, 84]), torch.float32, 2.0)
    """

    def __init__(self, estimator=None, *, max_depth: float | None = None, in_key="pixels", out_key="depth"):
        if estimator is None:
            from torchrl_causal.perception.depth import MonoDepth

            estimator = MonoDepth.load()
        if not callable(estimator):
            raise ValueError(f"estimator must be callable (uint8 [B, H, W, 3] -> [B, H, W]), got {estimator!r}")
        if max_depth is None:
            max_depth = float(getattr(estimator, "max_depth", 10.0))
        if isinstance(max_depth, bool) or not (
            isinstance(max_depth, (int, float)) and math.isfinite(max_depth) and max_depth > 0
        ):
            raise ValueError(f"max_depth must be a positive finite number, got {max_depth!r}")
        super().__init__(in_keys=[in_key], out_keys=[out_key])
        self.estimator = estimator
        self.max_depth = float(max_depth)

    def estimate(self, pixels: torch.Tensor) -> torch.Tensor:
        """``uint8 [..., H, W, 3]`` -> ``float32 [..., H, W]`` metres in ``[0, max_depth]``."""
        if not isinstance(pixels, torch.Tensor):
            raise ValueError(f"{self.in_keys[0]!r} must be a tensor, got {type(pixels).__name__}")
        if pixels.dtype != torch.uint8:
            raise ValueError(f"{self.in_keys[0]!r} must be uint8 [..., H, W, 3], got dtype {pixels.dtype}")
        if pixels.ndim < 3 or pixels.shape[-1] != 3:
            raise ValueError(f"{self.in_keys[0]!r} must be [..., H, W, 3], got shape {tuple(pixels.shape)}")
        H, W = pixels.shape[-3:-1]
        batch = pixels.shape[:-3]
        flat = pixels.reshape(-1, H, W, 3)
        if flat.shape[0] == 0:
            return torch.zeros((*batch, H, W), dtype=torch.float32, device=pixels.device)
        depth = torch.as_tensor(self.estimator(flat))
        if depth.shape != (flat.shape[0], H, W):
            raise ValueError(
                f"the estimator returned shape {tuple(depth.shape)}, expected {(flat.shape[0], H, W)}"
            )
        depth = depth.to(device=pixels.device, dtype=torch.float32).clamp(0.0, self.max_depth)
        return depth.reshape(*batch, H, W)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.set(self.out_keys[0], self.estimate(next_tensordict.get(self.in_keys[0])))
        return next_tensordict

    forward = _call

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase):
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        in_spec = observation_spec[self.in_keys[0]]
        H, W = in_spec.shape[-3], in_spec.shape[-2]
        observation_spec[self.out_keys[0]] = Bounded(
            low=0.0,
            high=self.max_depth,
            shape=(*observation_spec.shape, H, W),
            dtype=torch.float32,
            device=in_spec.device,
        )
        return observation_spec
