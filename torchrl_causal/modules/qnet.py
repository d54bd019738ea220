"""The thesis Q-network (Fig. 5.1, and Fig. 5.2 with the nine state values).

Architecture (Mnih et al. 2015, as used in thesis sec. 5.1): three convolutions
32@8x8/4, 64@4x4/2, 64@3x3/1 with ReLU, flatten, a dense layer of 512 units
with ReLU, and one linear output per action. For the CBN variants (Fig. 5.2)
the nine state values are concatenated to the flattened convolution features
*before* the dense layer.

Example:
    >>> import torch
    >>> from torchrl_causal.modules import ThesisQNet
    >>> net = ThesisQNet(n_actions=8)
    >>> net(torch.zeros(2, 84, 84, 3, dtype=torch.uint8)).shape
    torch.Size([2, 8])
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

__all__ = ["ThesisQNet", "FeatureQNet", "MapQNet"]


def _conv_out(size: int, kernel: int, stride: int) -> int:
    return (size - kernel) // stride + 1


class ThesisQNet(nn.Module):
    """Q-network of thesis Fig. 5.1 (image only) and Fig. 5.2 (image + features).

    A plain :class:`torch.nn.Module` mapping ``pixels`` (and optionally the
    state features) to one Q-value per action, ready to be wrapped by
    :class:`torchrl.modules.QValueActor` and trained with
    :class:`torchrl.objectives.DQNLoss`.

    Args:
        n_actions: number of discrete actions (8 in the thesis).
        n_features: number of extra state values concatenated before the dense
            layer (9 for Fig. 5.2); ``0`` (default) gives the image-only network
            of Fig. 5.1.
        image_size: ``(height, width)`` of the input image (84x84 in the thesis);
            used to size the dense layer.
        hidden: width of the dense layer (512 in the thesis).
        pixels_format: ``"hwc"`` (default; the env's ``pixels`` key, uint8
            ``[..., H, W, 3]``) or ``"chw"`` (e.g. after torchrl's
            ``ToTensorImage``).
        feature_scale: optional per-feature divisors applied to the features
            before concatenation (e.g. metres and degrees brought to order 1);
            ``None`` leaves them as they are.
        device: device of the parameters.

    Inputs: ``forward(pixels, features=None)``. ``uint8`` pixels are scaled to
    [0, 1]; floating pixels are taken as already scaled. Any number of leading
    batch dims is accepted; the output is ``[..., n_actions]``.

    Example:
        >>> import torch
        >>> from torchrl.data import Categorical
        >>> from torchrl.modules import QValueActor
        >>> from tensordict import TensorDict
        >>> net = ThesisQNet(n_actions=8, n_features=9)
        >>> actor = QValueActor(net, in_keys=["pixels", "causal_features"], spec=Categorical(8))
        >>> td = TensorDict(
        ...     pixels=torch.zeros(3, 84, 84, 3, dtype=torch.uint8),
        ...     causal_features=torch.zeros(3, 9),
        ...     batch_size=[3],
        ... )
        >>> actor(td)["action_value"].shape
        torch.Size([3, 8])
    """

    def __init__(
        self,
        n_actions: int = 8,
        n_features: int = 0,
        *,
        image_size: Sequence[int] = (84, 84),
        hidden: int = 512,
        pixels_format: str = "hwc",
        feature_scale: Sequence[float] | torch.Tensor | None = None,
        device: torch.device | str | None = None,
    ):
        super().__init__()
        if not isinstance(n_actions, int) or n_actions < 1:
            raise ValueError(f"n_actions must be a positive int, got {n_actions!r}")
        if not isinstance(n_features, int) or n_features < 0:
            raise ValueError(f"n_features must be a non-negative int, got {n_features!r}")
        if len(image_size) != 2:
            raise ValueError(f"image_size must be (height, width), got {image_size!r}")
        h, w = (int(s) for s in image_size)
        for k, s in ((8, 4), (4, 2), (3, 1)):
            h, w = _conv_out(h, k, s), _conv_out(w, k, s)
            if h < 1 or w < 1:
                raise ValueError(
                    f"image_size {tuple(image_size)} is too small for the thesis "
                    f"convolutions (needs at least 36x36)"
                )
        if not isinstance(hidden, int) or hidden < 1:
            raise ValueError(f"hidden must be a positive int, got {hidden!r}")
        if pixels_format not in ("hwc", "chw"):
            raise ValueError(f"pixels_format must be 'hwc' or 'chw', got {pixels_format!r}")
        self.n_actions = n_actions
        self.n_features = n_features
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.pixels_format = pixels_format
        self.conv = nn.Sequential(
            nn.Conv2d(3, 32, kernel_size=8, stride=4, device=device),
            nn.ReLU(),
            nn.Conv2d(32, 64, kernel_size=4, stride=2, device=device),
            nn.ReLU(),
            nn.Conv2d(64, 64, kernel_size=3, stride=1, device=device),
            nn.ReLU(),
            nn.Flatten(),
        )
        self.conv_out = 64 * h * w
        self.dense = nn.Sequential(
            nn.Linear(self.conv_out + n_features, hidden, device=device),
            nn.ReLU(),
        )
        self.head = nn.Linear(hidden, n_actions, device=device)
        if feature_scale is not None:
            feature_scale = torch.as_tensor(feature_scale, dtype=torch.float32, device=device)
            if feature_scale.shape != (n_features,):
                raise ValueError(
                    f"feature_scale must have {n_features} values, got shape "
                    f"{tuple(feature_scale.shape)}"
                )
            if (feature_scale == 0).any():
                raise ValueError("feature_scale must not contain zeros")
            self.register_buffer("feature_scale", feature_scale)
        else:
            self.feature_scale = None

    def forward(self, pixels: torch.Tensor, features: torch.Tensor | None = None) -> torch.Tensor:
        """Q-values ``[..., n_actions]`` of a batch of images (and features)."""
        if pixels.dtype == torch.uint8:
            x = pixels.float().div(255.0)
        else:
            x = pixels.float()
        if self.pixels_format == "hwc":
            x = x.movedim(-1, -3)
        if x.shape[-3] != 3 or tuple(x.shape[-2:]) != self.image_size:
            h, w = self.image_size
            expected = f"{h}, {w}, 3" if self.pixels_format == "hwc" else f"3, {h}, {w}"
            raise ValueError(
                f"expected pixels of shape [..., {expected}] ({self.pixels_format}), "
                f"got {tuple(pixels.shape)}"
            )
        batch = x.shape[:-3]
        z = self.conv(x.reshape(-1, *x.shape[-3:]))
        if self.n_features:
            if features is None:
                raise ValueError(
                    f"this ThesisQNet was built with n_features={self.n_features}: "
                    "pass the features (e.g. in_keys=['pixels', 'causal_features'])"
                )
            f = features.to(z.dtype)
            if f.shape[-1] != self.n_features:
                raise ValueError(
                    f"expected {self.n_features} features, got shape {tuple(features.shape)}"
                )
            if self.feature_scale is not None:
                f = f / self.feature_scale
            z = torch.cat([z, f.reshape(-1, self.n_features)], dim=-1)
        elif features is not None:
            raise ValueError("features given to a ThesisQNet built with n_features=0")
        q = self.head(self.dense(z))
        return q.reshape(*batch, self.n_actions)


def _register_feature_scale(module: nn.Module, feature_scale, n_features: int, device) -> None:
    """``module.feature_scale``: a buffer of ``n_features`` non-zero divisors, or None."""
    if feature_scale is None:
        module.feature_scale = None
        return
    feature_scale = torch.as_tensor(feature_scale, dtype=torch.float32, device=device)
    if feature_scale.shape != (n_features,) or (feature_scale == 0).any():
        raise ValueError(f"feature_scale must be {n_features} non-zero values")
    module.register_buffer("feature_scale", feature_scale)


class FeatureQNet(nn.Module):
    """A Q-network on state values alone (no image): two dense ReLU layers and a head.

    An ablation of :class:`ThesisQNet` for the generalisation study: the same
    features (e.g. the nine continuous values and the action history), no
    convolutions. Wrap it in :class:`torchrl.modules.QValueActor` with the
    features key as the only in-key.

    Args:
        n_actions: number of discrete actions.
        n_features: width of the feature vector.
        hidden: width of the two dense layers.
        feature_scale: optional per-feature divisors (see :class:`ThesisQNet`).
        device: device of the parameters.

    Example:
        >>> import torch
        >>> net = FeatureQNet(8, 41)
        >>> net(torch.zeros(3, 41)).shape
        torch.Size([3, 8])
    """

    def __init__(self, n_actions: int = 8, n_features: int = 9, *, hidden: int = 256,
                 feature_scale: Sequence[float] | torch.Tensor | None = None,
                 device: torch.device | str | None = None):
        super().__init__()
        if not isinstance(n_actions, int) or n_actions < 1:
            raise ValueError(f"n_actions must be a positive int, got {n_actions!r}")
        if not isinstance(n_features, int) or n_features < 1:
            raise ValueError(f"n_features must be a positive int, got {n_features!r}")
        self.n_actions, self.n_features = n_actions, n_features
        self.net = nn.Sequential(
            nn.Linear(n_features, hidden, device=device), nn.ReLU(),
            nn.Linear(hidden, hidden, device=device), nn.ReLU(),
            nn.Linear(hidden, n_actions, device=device),
        )
        _register_feature_scale(self, feature_scale, n_features, device)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """Q-values ``[..., n_actions]``."""
        f = features.float()
        if f.shape[-1] != self.n_features:
            raise ValueError(f"expected {self.n_features} features, got shape "
                             f"{tuple(features.shape)}")
        if self.feature_scale is not None:
            f = f / self.feature_scale
        return self.net(f)


class MapQNet(nn.Module):
    """A Q-network on an egocentric map and a feature vector (no camera image).

    Reads :class:`~torchrl_causal.transforms.EgoMap`'s ``ego_map`` (uint8
    ``[..., C, S, S]``, scaled to [0, 1]) through three convolutions
    (32@3x3/1, 64@4x4/2, 64@3x3/2, ReLU), concatenates the features (e.g. the
    nine continuous values, ``goal_memory`` and the action history, scaled by
    ``feature_scale``) and maps them through two dense ReLU layers to one
    Q-value per action.

    Args:
        n_actions: number of discrete actions.
        n_features: width of the feature vector (0: the map alone).
        map_channels: channels of the map.
        map_size: side of the map (cells, >= 8).
        hidden: width of the dense layers.
        feature_scale: optional per-feature divisors (see :class:`ThesisQNet`).
        device: device of the parameters.

    Example:
        >>> import torch
        >>> net = MapQNet(8, n_features=15)
        >>> net(torch.zeros(2, 3, 32, 32, dtype=torch.uint8), torch.zeros(2, 15)).shape
        torch.Size([2, 8])
    """

    def __init__(self, n_actions: int = 8, n_features: int = 0, *, map_channels: int = 3,
                 map_size: int = 32, hidden: int = 256,
                 feature_scale: Sequence[float] | torch.Tensor | None = None,
                 device: torch.device | str | None = None):
        super().__init__()
        if not isinstance(n_actions, int) or n_actions < 1:
            raise ValueError(f"n_actions must be a positive int, got {n_actions!r}")
        if not isinstance(n_features, int) or n_features < 0:
            raise ValueError(f"n_features must be a non-negative int, got {n_features!r}")
        if not isinstance(map_size, int) or map_size < 8:
            raise ValueError(f"map_size must be an int >= 8, got {map_size!r}")
        self.n_actions, self.n_features = n_actions, n_features
        self.map_shape = (int(map_channels), int(map_size), int(map_size))
        self.conv = nn.Sequential(
            nn.Conv2d(map_channels, 32, 3, stride=1, padding=1, device=device), nn.ReLU(),
            nn.Conv2d(32, 64, 4, stride=2, device=device), nn.ReLU(),
            nn.Conv2d(64, 64, 3, stride=2, device=device), nn.ReLU(),
            nn.Flatten(),
        )
        side = _conv_out(_conv_out(map_size, 4, 2), 3, 2)
        self.dense = nn.Sequential(
            nn.Linear(64 * side * side + n_features, hidden, device=device), nn.ReLU(),
            nn.Linear(hidden, hidden, device=device), nn.ReLU(),
            nn.Linear(hidden, n_actions, device=device),
        )
        _register_feature_scale(self, feature_scale, n_features, device)

    def forward(self, ego_map: torch.Tensor, features: torch.Tensor | None = None
                ) -> torch.Tensor:
        """Q-values ``[..., n_actions]``."""
        if tuple(ego_map.shape[-3:]) != self.map_shape:
            raise ValueError(f"expected a map of shape [..., {', '.join(map(str, self.map_shape))}]"
                             f", got {tuple(ego_map.shape)}")
        x = ego_map.float() / 255.0 if ego_map.dtype == torch.uint8 else ego_map.float()
        batch = x.shape[:-3]
        z = self.conv(x.reshape(-1, *self.map_shape))
        if self.n_features:
            if features is None:
                raise ValueError(f"this MapQNet was built with n_features={self.n_features}: "
                                 "pass the features")
            f = features.float()
            if f.shape[-1] != self.n_features:
                raise ValueError(f"expected {self.n_features} features, got shape "
                                 f"{tuple(features.shape)}")
            if self.feature_scale is not None:
                f = f / self.feature_scale
            z = torch.cat([z, f.reshape(-1, self.n_features)], -1)
        elif features is not None:
            raise ValueError("features given to a MapQNet built with n_features=0")
        return self.dense(z).reshape(*batch, self.n_actions)
