"""Monocular metric depth from one RGB image (thesis Fig. 2.5; Laina et al. 2016, FCRN).

The real Tello has only an RGB camera, so the depth sections of the causal
state must come from the image. This module holds a small FCRN-style network
trained from scratch on image/depth pairs rendered by
:class:`~torchrl_causal.envs.DroneNavEnv` (``recipes/train_depth.py``), the
BerHu loss it is trained with, the :class:`MonoDepth` estimator (the shipped
weights load without touching the network) and the evaluation metrics.

Design:
    * :class:`FCRN` -- a compact residual encoder (ResNet-18-like: a stride-2
      stem and four stages of two basic blocks, stride 32 in all, few
      channels) and four :class:`UpProjection` decoder blocks (Laina et al.'s
      up-projection: 2x up -> 5x5 conv -> ReLU -> 3x3 conv, plus a 5x5
      projection branch, summed, ReLU; here the fast *pixel_shuffle* form: a
      3x3 conv to ``4 * C`` channels at the low resolution followed by
      :func:`torch.nn.functional.pixel_shuffle`, which is the same family of
      interleaved small convolutions as the paper's fast up-projection). Unlike
      the paper's FCRN, each decoder stage adds a 1x1-projected encoder feature
      of its resolution (skip connection): with so few channels it sharpens
      object edges at no measurable cost. The output is at half the working
      resolution, ``max_depth * sigmoid(.)`` metres, upsampled bilinearly.
    * Working resolution. The network always sees the same angular pixel
      scale: an ``H x W`` input is resized to ``work_height x
      round(W / H * work_height)`` (rounded to a multiple of 32), so the
      reference camera's 240x320 view becomes 96x128 and the DQN's 84x84 view
      (the env's vertical fov is 60 deg for every image size, so an 84x84 view
      is a scaled centre crop of a 4:3 view) becomes 96x96: the same objects at
      the same apparent size. Training uses random horizontal crops (96 and
      128 wide), flips, a low-resolution round trip and colour jitter so both
      sizes are covered. The prediction is resized back to ``H x W``.
      Inputs must be rendered with the env's vertical field of view (60 deg);
      metric scale from one image is only defined for a known camera.
    * :func:`berhu_loss` -- reverse Huber: ``|e|`` for ``|e| <= c`` else
      ``(e**2 + c**2) / (2 c)``, ``c = 0.2 * max |e|`` over the valid pixels of
      the batch; invalid pixels (target NaN, inf or ``<= 0``) are masked out.
    * :func:`depth_metrics` / :func:`evaluate_depth` -- abs rel, RMSE,
      ``delta < 1.25`` (and ``1.25**2``, ``1.25**3``), averaged per image over
      the valid pixels, the usual NYU/KITTI protocol.

Example:
    >>> import torch
    >>> from torchrl_causal.perception.depth import MonoDepth
    >>> est = MonoDepth.load()                 # the shipped weights, offline
    >>> est(torch.zeros(2, 84, 84, 3, dtype=torch.uint8)).shape
    torch.Size([2, 84, 84])
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "DEFAULT_WEIGHTS",
    "FCRN",
    "MonoDepth",
    "TRAIN_COMMAND",
    "UpProjection",
    "berhu_loss",
    "depth_metrics",
    "evaluate_depth",
]

#: The shipped weights (``recipes/train_depth.py`` writes them and a ``.json`` sidecar).
DEFAULT_WEIGHTS: Path = Path(__file__).resolve().parent / "weights" / "monodepth.pt"
#: The command that produces the shipped weights (quoted in load errors).
TRAIN_COMMAND: str = (
    "make depth-weights (python -m torchrl_causal.perception.dataset, then "
    "python recipes/train_depth.py on camera-path frames; minutes on a GPU, hours on one core)"
)
_FORMAT = "torchrl_causal.monodepth"
_VERSION = 1


# ----------------------------------------------------------------------------- loss


def berhu_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    c_frac: float = 0.2,
    log: bool = False,
) -> torch.Tensor:
    """The reverse Huber (BerHu) loss of Laina et al. (2016), mean over valid pixels.

    ``B(e) = |e|`` if ``|e| <= c`` else ``(e**2 + c**2) / (2 c)`` with
    ``c = c_frac * max |e|`` over the valid pixels of the whole batch (the
    threshold is treated as a constant, as in the paper). A pixel is valid
    where ``mask`` is True (default: everywhere) and the target is finite and
    ``> 0``. Returns 0 (with a gradient path) when no pixel is valid.

    Args:
        pred: predicted depth, any shape.
        target: true depth, the same shape.
        mask: optional boolean mask, the same shape.
        c_frac: the threshold as a fraction of the largest absolute error.
        log: the errors of ``log(depth)`` instead of depth (metres): relative
            errors, so a pixel 0.5 m away weighs as much as one 5 m away
            (``pred`` is clamped to >= 1e-3 m first).

    Example:
        >>> import torch
        >>> pred = torch.tensor([1.0, 2.0, 3.0, 0.0])
        >>> target = torch.tensor([1.0, 1.0, 1.0, float("nan")])   # errors 0, 1, 2; one invalid
        >>> round(float(berhu_loss(pred, target)), 4)  # c = 0.4: (0 + 1.16/0.8 + 4.16/0.8) / 3
        2.2167
    """
    if pred.shape != target.shape:
        raise ValueError(f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    if not 0.0 < c_frac <= 1.0:
        raise ValueError(f"c_frac must be in (0, 1], got {c_frac!r}")
    valid = torch.isfinite(target) & (target > 0)
    if mask is not None:
        if mask.shape != target.shape:
            raise ValueError(f"mask shape {tuple(mask.shape)} differs from target {tuple(target.shape)}")
        valid = valid & mask.bool()
    if not bool(valid.any()):
        return pred.sum() * 0.0
    if log:
        pred = pred.clamp_min(1e-3).log()
        target = torch.where(valid, target, torch.ones_like(target)).log()
    err = (pred - torch.where(valid, target, pred))[valid].abs()
    c = (c_frac * err.max()).detach().clamp_min(1e-6)
    loss = torch.where(err <= c, err, (err * err + c * c) / (2 * c))
    return loss.mean()


# ----------------------------------------------------------------------------- network


def _conv_bn(cin: int, cout: int, k: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, k, stride=stride, padding=k // 2, bias=False), nn.BatchNorm2d(cout)
    )


class _BasicBlock(nn.Module):
    """ResNet basic block: two 3x3 convs, identity or 1x1 projection shortcut."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.c1 = _conv_bn(cin, cout, 3, stride)
        self.c2 = _conv_bn(cout, cout, 3)
        self.short = None if (stride == 1 and cin == cout) else _conv_bn(cin, cout, 1, stride)

    def forward(self, x):
        y = self.c2(F.relu(self.c1(x)))
        return F.relu(y + (x if self.short is None else self.short(x)))


class UpProjection(nn.Module):
    """Laina et al.'s up-projection block, pixel_shuffle form (doubles H and W).

    Main branch: 2x up (3x3 conv to ``4 * cout`` channels + pixel_shuffle) ->
    BN -> ReLU -> 3x3 conv -> BN; projection branch: 2x up (same form) -> BN;
    the two are summed and passed through a ReLU. With ``skip_channels`` an
    encoder feature of the output resolution is added through a 1x1 conv
    before the final ReLU.

    Args:
        cin: input channels.
        cout: output channels.
        skip_channels: channels of the skip feature (0: none).

    Example:
        >>> import torch
        >>> UpProjection(8, 4)(torch.zeros(1, 8, 3, 4)).shape
        torch.Size([1, 4, 6, 8])
    """

    def __init__(self, cin: int, cout: int, skip_channels: int = 0):
        super().__init__()
        # both branches' low-resolution convs in one conv (2 * 4 * cout outputs)
        self.up = nn.Conv2d(cin, 8 * cout, 3, padding=1, bias=False)
        self.bn_main = nn.BatchNorm2d(cout)
        self.bn_proj = nn.BatchNorm2d(cout)
        self.conv = _conv_bn(cout, cout, 3)
        self.skip = None if not skip_channels else _conv_bn(skip_channels, cout, 1)
        self.cout = cout

    def forward(self, x, skip=None):
        u = F.pixel_shuffle(self.up(x), 2)
        main, proj = u[:, : self.cout], u[:, self.cout :]
        y = self.conv(F.relu(self.bn_main(main))) + self.bn_proj(proj)
        if self.skip is not None and skip is not None:
            y = y + self.skip(skip)
        return F.relu(y)


class FCRN(nn.Module):
    """A small fully convolutional residual network for metric depth (FCRN-style).

    Input: float ``[B, 3, h, w]`` (RGB in ``[0, 1]``), ``h`` and ``w``
    multiples of 32. Output: depth ``[B, 1, h, w]`` in ``(0, max_depth)``
    metres. See the module docs for the architecture.

    Args:
        widths: channels of the stem and the four encoder stages (strides 2,
            4, 8, 16, 32).
        decoder: channels of the four up-projection blocks (strides 16 to 2).
        max_depth: the output range (m).

    Example:
        >>> import torch
        >>> net = FCRN().eval()
        >>> net(torch.zeros(1, 3, 96, 128)).shape
        torch.Size([1, 1, 96, 128])
    """

    STRIDE = 32

    def __init__(
        self,
        widths: tuple[int, ...] = (16, 24, 32, 64, 96),
        decoder: tuple[int, ...] = (64, 32, 24, 16),
        max_depth: float = 10.0,
    ):
        super().__init__()
        widths, decoder = tuple(int(w) for w in widths), tuple(int(d) for d in decoder)
        if len(widths) != 5 or len(decoder) != 4 or min(widths + decoder) < 1:
            raise ValueError(
                f"widths must be 5 and decoder 4 positive channel counts, got {widths!r}, {decoder!r}"
            )
        if not (math.isfinite(max_depth) and max_depth > 0):
            raise ValueError(f"max_depth must be a positive finite number, got {max_depth!r}")
        self.config = {"widths": list(widths), "decoder": list(decoder), "max_depth": float(max_depth)}
        self.max_depth = float(max_depth)
        self.stem = _conv_bn(3, widths[0], 3, 2)
        stages = []
        for i in range(4):
            cin, cout = widths[i], widths[i + 1]
            stages.append(nn.Sequential(_BasicBlock(cin, cout, 2), _BasicBlock(cout, cout)))
        self.stages = nn.ModuleList(stages)
        ups, cin = [], widths[4]
        skips = (widths[3], widths[2], widths[1], widths[0])  # strides 16, 8, 4, 2
        for cout, sc in zip(decoder, skips):
            ups.append(UpProjection(cin, cout, sc))
            cin = cout
        self.ups = nn.ModuleList(ups)
        self.head = nn.Conv2d(cin, 1, 3, padding=1)
        self.register_buffer("mean", torch.tensor([0.5, 0.5, 0.5]).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        feats = [F.relu(self.stem(x - self.mean))]
        for stage in self.stages:
            feats.append(stage(feats[-1]))
        y = feats[-1]
        for up, skip in zip(self.ups, reversed(feats[:-1])):
            y = up(y, skip)
        y = self.max_depth * torch.sigmoid(self.head(y))
        return F.interpolate(y, size=(h, w), mode="bilinear", align_corners=False)


# ----------------------------------------------------------------------------- estimator


def _weights_error(path: Path, why: str, exc_type=RuntimeError):
    return exc_type(
        f"monocular depth weights {str(path)!r}: {why}. Train them with: {TRAIN_COMMAND}"
    )


def working_size(height: int, width: int, work_height: int = 96) -> tuple[int, int]:
    """The network's input size for an ``height x width`` image (same angular pixel scale).

    Example:
        >>> working_size(240, 320), working_size(84, 84), working_size(480, 640)
        ((96, 128), (96, 96), (96, 128))
    """
    s = FCRN.STRIDE
    ww = max(s, int(round(width / height * work_height / s)) * s)
    return int(work_height), ww


class MonoDepth(nn.Module):
    """Metric depth estimator: ``pixels uint8 [B, H, W, 3] -> depth float32 [B, H, W]`` (m).

    Wraps an :class:`FCRN`: resizes the image to the working resolution (see
    :func:`working_size`; 96 rows by default), runs the network and resizes the
    depth back to ``H x W``. Any ``H, W >= 32`` works; an unbatched
    ``[H, W, 3]`` image gives ``[H, W]``. Runs without gradients, in eval mode.
    ``MonoDepth.load()`` loads the shipped weights
    (:data:`DEFAULT_WEIGHTS`); a missing or corrupt file raises an error naming
    the path and :data:`TRAIN_COMMAND`.

    Args:
        net: the network (default: an untrained :class:`FCRN`).
        work_height: rows of the working resolution (a multiple of 32).
        chunk: frames per network call (bounds memory on big batches).
        meta: free-form metadata (the weights' sidecar record).

    Example:
        >>> import torch
        >>> est = MonoDepth(FCRN())                       # untrained, for the shapes
        >>> est(torch.zeros(1, 240, 320, 3, dtype=torch.uint8)).shape
        torch.Size([1, 240, 320])
        >>> est(torch.zeros(84, 84, 3, dtype=torch.uint8)).dtype
        torch.float32
    """

    def __init__(self, net: FCRN | None = None, *, work_height: int = 96, chunk: int = 64, meta=None):
        super().__init__()
        if net is None:
            net = FCRN()
        if not isinstance(net, FCRN):
            raise ValueError(f"net must be an FCRN, got {type(net).__name__}")
        if not (isinstance(work_height, int) and work_height >= 32 and work_height % FCRN.STRIDE == 0):
            raise ValueError(f"work_height must be a multiple of 32, >= 32; got {work_height!r}")
        if not (isinstance(chunk, int) and chunk >= 1):
            raise ValueError(f"chunk must be an int >= 1, got {chunk!r}")
        self.net = net.eval()
        self.work_height = work_height
        self.chunk = chunk
        self.meta = dict(meta or {})
        self.train(False)

    @property
    def max_depth(self) -> float:
        """The largest depth the network outputs (m)."""
        return self.net.max_depth

    @property
    def reach_distance(self) -> float | None:
        """The range threshold (m) at which this model's goal distance best says
        "arrived" (``meta["reach_calibration"]``, written by
        ``recipes/train_depth.py`` with
        :func:`~torchrl_causal.envs.reach.calibrate_reach_distance`); ``None``
        if the weights were never calibrated. :class:`~torchrl_causal.envs.TelloEnv`
        uses it when given no ``reach_rule``."""
        cal = self.meta.get("reach_calibration") or {}
        d = cal.get("max_distance")
        return None if d is None else float(d)

    @property
    def device(self) -> torch.device:
        """The device of the network's parameters."""
        return next(self.net.parameters()).device

    def train(self, mode: bool = True):  # the estimator is inference-only: keep BN in eval
        super().train(False)
        return self

    # -- io ---------------------------------------------------------------------------

    def save(self, path, meta: Mapping | None = None) -> Path:
        """Writes the weights (float16) and config to ``path``; returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        state = {k: (v.half() if v.is_floating_point() else v) for k, v in self.net.state_dict().items()}
        torch.save(
            {
                "format": _FORMAT,
                "version": _VERSION,
                "config": dict(self.net.config),
                "work_height": self.work_height,
                "state_dict": state,
                # plain JSON types only, so that loading works with weights_only=True
                "meta": json.loads(json.dumps(dict(meta if meta is not None else self.meta), default=str)),
            },
            path,
        )
        return path

    @classmethod
    def load(cls, path=None, device=None, **kwargs) -> MonoDepth:
        """Loads an estimator from ``path`` (default: the shipped :data:`DEFAULT_WEIGHTS`).

        Never touches the network. Raises :class:`FileNotFoundError` for a
        missing file and :class:`RuntimeError` for a corrupt or foreign one,
        both naming the path and the command that trains the weights.

        Args:
            path: a ``.pt`` file written by :meth:`save` (None: shipped weights).
            device: where to put the network (default CPU).
            **kwargs: passed to the constructor (``chunk``).
        """
        path = DEFAULT_WEIGHTS if path is None else Path(path)
        if not path.is_file():
            raise _weights_error(path, "file not found", FileNotFoundError)
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - any unpickling failure is "corrupt"
            raise _weights_error(path, f"cannot be read ({type(exc).__name__}: {exc})") from exc
        if not isinstance(ckpt, dict) or ckpt.get("format") != _FORMAT:
            raise _weights_error(path, f"not a MonoDepth weights file (expected format {_FORMAT!r})")
        if ckpt.get("version") != _VERSION:
            raise _weights_error(path, f"unsupported version {ckpt.get('version')!r}")
        try:
            net = FCRN(**ckpt["config"])
            net.load_state_dict({k: v.float() if v.is_floating_point() else v
                                 for k, v in ckpt["state_dict"].items()})
        except Exception as exc:  # noqa: BLE001
            raise _weights_error(path, f"does not match the network ({type(exc).__name__}: {exc})") from exc
        est = cls(net, work_height=int(ckpt.get("work_height", 96)), meta=ckpt.get("meta"), **kwargs)
        if device is not None:
            est = est.to(device)
        return est

    # -- inference --------------------------------------------------------------------

    @staticmethod
    def _check(pixels) -> torch.Tensor:
        if isinstance(pixels, np.ndarray):
            pixels = torch.from_numpy(np.ascontiguousarray(pixels))
        if not isinstance(pixels, torch.Tensor):
            raise ValueError(f"pixels must be a uint8 tensor [B, H, W, 3], got {type(pixels).__name__}")
        if pixels.dtype != torch.uint8:
            raise ValueError(f"pixels must be uint8 (0..255), got dtype {pixels.dtype}")
        if pixels.ndim not in (3, 4) or pixels.shape[-1] != 3:
            raise ValueError(f"pixels must be [B, H, W, 3] or [H, W, 3], got shape {tuple(pixels.shape)}")
        if pixels.shape[-3] < 32 or pixels.shape[-2] < 32:
            raise ValueError(f"image must be at least 32x32 pixels, got shape {tuple(pixels.shape)}")
        return pixels

    def prepare(self, pixels: torch.Tensor) -> torch.Tensor:
        """``uint8 [B, H, W, 3]`` -> the network's float input ``[B, 3, h, w]`` (working size)."""
        H, W = pixels.shape[-3:-1]
        x = pixels.permute(0, 3, 1, 2).float().div_(255.0)
        size = working_size(H, W, self.work_height)
        if (H, W) != size:
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)
        return x

    @torch.no_grad()
    def forward(self, pixels) -> torch.Tensor:
        """Depth in metres, ``float32 [B, H, W]`` (or ``[H, W]``), in ``(0, max_depth)``."""
        pixels = self._check(pixels)
        unbatched = pixels.ndim == 3
        if unbatched:
            pixels = pixels.unsqueeze(0)
        H, W = pixels.shape[1:3]
        dev = self.device
        outs = []
        for start in range(0, pixels.shape[0], self.chunk):
            x = self.prepare(pixels[start : start + self.chunk].to(dev))
            y = self.net(x)
            if y.shape[-2:] != (H, W):
                y = F.interpolate(y, size=(H, W), mode="bilinear", align_corners=False)
            outs.append(y[:, 0])
        out = torch.cat(outs) if outs else pixels.new_zeros((0, H, W), dtype=torch.float32)
        out = out.to(pixels.device, torch.float32)
        return out[0] if unbatched else out


# ----------------------------------------------------------------------------- metrics


def depth_metrics(pred: torch.Tensor, target: torch.Tensor, *, max_depth: float = 10.0,
                  near_m: float = 1.0) -> dict:
    """Per-image depth metrics, summed over images (divide by the image counts for means).

    Valid pixels: target finite and ``> 0`` (targets beyond ``max_depth`` are
    clipped to it, as the env does). Predictions are clipped to ``[1e-3,
    max_depth]``. Returns sums of per-image abs rel, RMSE, mean
    ``|log10 pred - log10 target|``, ``delta < 1.25 ** k`` (k = 1, 2, 3) and
    the image count ``n_images``, so batches can be accumulated; and
    ``abs_rel_in_range``, ``rmse_in_range``, ``delta1_in_range`` over the
    pixels whose target is below ``max_depth`` only (count
    ``n_images_in_range``): the clipped background is easy and often half of
    the image; and ``abs_rel_near``, ``delta1_near`` over the pixels within
    ``near_m`` (default 1 m; count ``n_images_near``): the board seen from
    the goal point, where the reach rule reads its distance.

    Example:
        >>> import torch
        >>> gt = torch.full((1, 4, 4), 2.0)
        >>> m = depth_metrics(gt * 1.1, gt)
        >>> round(m["abs_rel"], 3), round(m["rmse"], 3), m["delta1"], m["n_images"]
        (0.1, 0.2, 1.0, 1)
    """
    if pred.shape != target.shape:
        raise ValueError(f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    pred = pred.reshape(-1, *pred.shape[-2:]).double().clamp(1e-3, max_depth)
    target = target.reshape(-1, *target.shape[-2:]).double()
    valid = torch.isfinite(target) & (target > 0)
    target = torch.where(valid, target.clamp(max=max_depth), torch.ones_like(target))
    n = valid.sum((-2, -1))
    keep = n > 0
    nn_ = n.clamp_min(1)
    ratio = torch.maximum(pred / target, target / pred)

    def mean(v):
        return (torch.where(valid, v, torch.zeros_like(v)).sum((-2, -1)) / nn_)[keep]

    out = {
        "abs_rel": float(mean((pred - target).abs() / target).sum()),
        "rmse": float(mean((pred - target) ** 2).sqrt().sum()),
        "log10": float(mean((pred.log10() - target.log10()).abs()).sum()),
    }
    for k in (1, 2, 3):
        out[f"delta{k}"] = float(mean((ratio < 1.25**k).double()).sum())
    out["n_images"] = int(keep.sum())
    # the same over the pixels with something in range (target < max_depth): the
    # clipped background (often half the image) is easy and dominates the plain figures
    near = valid & (target < 0.999 * max_depth)
    n_near = near.sum((-2, -1))
    keep_near = n_near > 0

    def mean_near(v):
        return (torch.where(near, v, torch.zeros_like(v)).sum((-2, -1)) / n_near.clamp_min(1))[keep_near]

    out["abs_rel_in_range"] = float(mean_near((pred - target).abs() / target).sum())
    out["rmse_in_range"] = float(mean_near((pred - target) ** 2).sqrt().sum())
    out["delta1_in_range"] = float(mean_near((ratio < 1.25).double()).sum())
    out["n_images_in_range"] = int(keep_near.sum())
    close = valid & (target <= near_m)
    n_close = close.sum((-2, -1))
    keep_close = n_close > 0

    def mean_close(v):
        return (torch.where(close, v, torch.zeros_like(v)).sum((-2, -1))
                / n_close.clamp_min(1))[keep_close]

    out["abs_rel_near"] = float(mean_close((pred - target).abs() / target).sum())
    out["delta1_near"] = float(mean_close((ratio < 1.25).double()).sum())
    out["n_images_near"] = int(keep_close.sum())
    return out


def _iter_pairs(source, batch_size: int, limit: int | None):
    """Yields ``(rgb uint8 [b, H, W, 3], depth float32 [b, H, W])`` numpy batches."""
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        if not path.is_file():
            raise FileNotFoundError(f"depth data set {str(path)!r} not found")
        with np.load(path) as data:
            if "rgb" not in data or "depth" not in data:
                raise ValueError(f"{str(path)!r} must hold arrays 'rgb' and 'depth', has {list(data)}")
            rgb, depth = data["rgb"], data["depth"]
        n = len(rgb) if limit is None else min(limit, len(rgb))
        for s in range(0, n, batch_size):
            e = min(n, s + batch_size)
            yield rgb[s:e], depth[s:e].astype(np.float32)
        return
    rgbs, depths, count = [], [], 0
    for item in source:
        if limit is not None and count >= limit:
            break
        rgb, depth = (item.rgb, item.depth) if hasattr(item, "rgb") else item
        rgbs.append(np.asarray(rgb))
        depths.append(np.asarray(depth, dtype=np.float32))
        count += 1
        if len(rgbs) == batch_size:
            yield np.stack(rgbs), np.stack(depths)
            rgbs, depths = [], []
    if rgbs:
        yield np.stack(rgbs), np.stack(depths)


def evaluate_depth(
    estimator: Callable[[torch.Tensor], torch.Tensor],
    npz_path,
    *,
    batch_size: int = 16,
    max_depth: float = 10.0,
    limit: int | None = None,
) -> dict:
    """Evaluates a depth estimator on a depth data set; returns the mean metrics.

    Args:
        estimator: any callable ``pixels uint8 [B, H, W, 3] -> depth [B, H, W]``
            (metres), e.g. :class:`MonoDepth`.
        npz_path: an ``.npz`` file with ``rgb`` uint8 ``[N, H, W, 3]`` and
            ``depth`` ``[N, H, W]`` (metres), as written by
            ``torchrl_causal.perception.dataset``; or an iterable of views
            (objects with ``rgb`` and ``depth``) or ``(rgb, depth)`` pairs.
        batch_size: frames per estimator call.
        max_depth: the depth range (m).
        limit: evaluate the first ``limit`` frames only.

    Returns:
        ``dict(abs_rel, rmse, log10, delta1, delta2, delta3,
        abs_rel_in_range, rmse_in_range, delta1_in_range, abs_rel_near,
        delta1_near, n_images, n_images_near, image_size, ms_per_frame)``:
        per-image means over the valid pixels (``*_in_range``: over the pixels
        with a target below ``max_depth``; ``*_near``: within 1 m, over the
        ``n_images_near`` images that have such pixels, None if none; see
        :func:`depth_metrics`);
        ``ms_per_frame`` is the estimator's wall time per frame at this batch
        size (current thread settings).

    Example:
        >>> import numpy as np, torch
        >>> pairs = [(np.zeros((32, 32, 3), np.uint8), np.full((32, 32), 2.0, np.float32))]
        >>> m = evaluate_depth(lambda px: torch.full(px.shape[:-1], 2.2), pairs)
        >>> round(m["abs_rel"], 3), m["delta1"], m["n_images"], m["image_size"]
        (0.1, 1.0, 1, [32, 32])
    """
    if not (isinstance(batch_size, int) and batch_size >= 1):
        raise ValueError(f"batch_size must be an int >= 1, got {batch_size!r}")
    total: dict = {}
    seconds, frames, size = 0.0, 0, None
    for rgb, depth in _iter_pairs(npz_path, batch_size, limit):
        t0 = time.perf_counter()
        pred = estimator(torch.from_numpy(np.ascontiguousarray(rgb)))
        seconds += time.perf_counter() - t0
        frames += len(rgb)
        size = list(rgb.shape[1:3])
        pred = torch.as_tensor(pred, dtype=torch.float32).reshape(depth.shape)
        for k, v in depth_metrics(pred, torch.from_numpy(depth), max_depth=max_depth).items():
            total[k] = total.get(k, 0) + v
    n, n_near = total.get("n_images", 0), total.get("n_images_in_range", 0)
    n_close = total.get("n_images_near", 0)
    if n == 0:
        raise ValueError(f"no frame with valid depth in {npz_path!r}")
    out = {}
    for k, v in total.items():
        if k.startswith("n_images"):
            continue
        if k.endswith("_in_range"):
            out[k] = v / n_near if n_near else float("nan")
        elif k.endswith("_near"):
            out[k] = v / n_close if n_close else None  # no pixel within 1 m
        else:
            out[k] = v / n
    out.update(n_images=n, n_images_near=n_close, image_size=size, ms_per_frame=1000.0 * seconds / max(frames, 1))
    return out


def read_sidecar(path=None) -> dict:
    """The JSON sidecar of a weights file (``<name>.json``), or ``{}`` if there is none.

    Example:
        >>> isinstance(read_sidecar(), dict)
        True
    """
    path = DEFAULT_WEIGHTS if path is None else Path(path)
    side = path.with_suffix(".json")
    return json.loads(side.read_text()) if side.is_file() else {}
