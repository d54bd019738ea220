"""Where the goal point is, from one camera frame near the board: a small learned head.

A Tello decides that it has arrived from its camera alone
(:class:`~torchrl_causal.envs.reach.ReachRule`). Near the goal point the
1.0 m board fills the view, and MonoDepth reads it 0.25-0.40 m short
(docs/tello.rst), so a range threshold on depth cannot tell the goal sphere
(0.2 m) from the places around it. The board's own texture can: its marks'
apparent size gives the range and their place and perspective the sideways
offset. :class:`GoalOffsetNet` is a four-layer CNN that reads a frame (as
``TelloEnv`` receives it, after the H.264 camera path) and returns the
drone's offset from the goal point in the board's frame, ``(ahead,
lateral)`` in metres (``ahead`` > 0: farther from the board than the goal
point). :class:`GoalOffsetEstimator` wraps it with its input size, saves and
loads it, and gives ``TelloEnv`` its ``goal_offset`` (the 3-D distance to
the goal point, with the height sensor's difference; to the segment of the
last move, since the simulator judges a pass through its sphere). The head
is not asked where the height sensor alone puts the drone outside the
sphere.

:func:`render_offset_views` renders the training data: poses in front of the
thesis board (0.42 m nearer to 0.8 m farther than the goal point, up to
0.6 m sideways, +-0.2 m in height, yaw within 30 deg of facing it, roll and
pitch within 3 deg), each frame through a
:class:`~torchrl_causal.perception.video_path.VideoPath` (jitter, H.264) at
one of the Tello path's stream sizes. ``recipes/train_arrival.py`` trains
and evaluates it (docs/tello.rst, "A learned arrival head").

Example:
    >>> import torch
    >>> est = GoalOffsetEstimator(GoalOffsetNet())
    >>> est(torch.zeros(2, 96, 128, 3, dtype=torch.uint8)).shape
    torch.Size([2, 2])
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import nn

__all__ = ["GoalOffsetNet", "GoalOffsetEstimator", "render_offset_views", "train_goal_offset",
           "segment_distance"]

_FORMAT = "torchrl_causal.GoalOffsetEstimator"
_VERSION = 1
#: (height, width) the network reads; frames are centre-cropped and resized to it.
INPUT_SIZE = (96, 128)
#: The shipped head (``make arrival-weights``), with its figures in ``arrival.json``.
DEFAULT_WEIGHTS: Path = Path(__file__).resolve().parent / "weights" / "arrival.pt"
#: The head for rooms nobody trained on (``make arrival-rooms-weights``): random layouts' rooms
#: with the printed 1.0 x 0.8 m board, figures in ``arrival_rooms.json`` (docs/tello.rst, "An
#: arrival head for rooms it has never seen").
ROOMS_WEIGHTS: Path = Path(__file__).resolve().parent / "weights" / "arrival_rooms.pt"
#: The head that can decline (``make arrival-view-weights``): random rooms, the camera turned up
#: to 80 deg and up to 1.2 m beside the goal point, with an in-view output, figures in
#: ``arrival_view.json`` (docs/tello.rst, "A head that can decline"; ``fly_tello.py
#: --arrival-head view``, asked with ``lost_board="ask"``).
VIEW_WEIGHTS: Path = Path(__file__).resolve().parent / "weights" / "arrival_view.pt"


class GoalOffsetNet(nn.Module):
    """Four stride-2 convolutions and two linear layers: uint8-range RGB ``[B, 3, 96, 128]``
    (scaled to 0-1) -> ``[B, 2]`` offsets (m). The head keeps the feature map's layout
    (no global pooling): where the board's marks are in the image is the sideways offset.
    With ``outputs=3`` a third output is the yaw off the board's normal (rad), an
    auxiliary target (:func:`train_goal_offset`'s ``yaw_weight``) that makes the network
    tell a turned camera from a shifted one. With ``in_view=True`` one more output, the
    last, is a logit of "the board is in view enough to read the offset from"
    (:func:`train_goal_offset`'s ``in_view_share``): a head with it can decline a frame,
    so ``TelloEnv`` may ask it without the detector (``lost_board="ask"``).

    Example:
        >>> import torch
        >>> GoalOffsetNet()(torch.zeros(1, 3, 96, 128)).shape
        torch.Size([1, 2])
        >>> GoalOffsetNet(in_view=True)(torch.zeros(1, 3, 96, 128)).shape
        torch.Size([1, 3])
    """

    def __init__(self, width: int = 16, outputs: int = 2, in_view: bool = False):
        super().__init__()
        if not isinstance(width, int) or width < 4:
            raise ValueError(f"GoalOffsetNet: width must be an int >= 4, got {width!r}")
        if outputs not in (2, 3):
            raise ValueError(f"GoalOffsetNet: outputs must be 2 (ahead, lateral) or 3 (+ yaw), "
                             f"got {outputs!r}")
        if not isinstance(in_view, bool):
            raise ValueError(f"GoalOffsetNet: in_view must be a bool, got {in_view!r}")
        w = width
        self.width, self.outputs, self.in_view = w, outputs, in_view
        self.features = nn.Sequential(
            nn.Conv2d(3, w, 5, 2, 2), nn.ReLU(), nn.Conv2d(w, 2 * w, 3, 2, 1), nn.ReLU(),
            nn.Conv2d(2 * w, 4 * w, 3, 2, 1), nn.ReLU(), nn.Conv2d(4 * w, 4 * w, 3, 2, 1),
            nn.ReLU(), nn.Flatten())
        h, wd = INPUT_SIZE
        self.head = nn.Sequential(nn.Linear(4 * w * (h // 16) * (wd // 16), 64), nn.ReLU(),
                                  nn.Linear(64, outputs + int(in_view)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))


def _to_input(frames) -> torch.Tensor:
    """uint8 ``[B, H, W, 3]`` (or one ``[H, W, 3]``) frames -> float ``[B, 3, 96, 128]``."""
    from .video_path import crop_resize

    x = torch.as_tensor(np.asarray(frames) if not torch.is_tensor(frames) else frames)
    if x.ndim == 3:
        x = x.unsqueeze(0)
    if x.ndim != 4 or x.shape[-1] != 3 or x.dtype != torch.uint8:
        raise ValueError("GoalOffsetEstimator: frames must be uint8 [B, H, W, 3] or "
                         f"[H, W, 3], got {x.dtype} {tuple(x.shape)}")
    if tuple(x.shape[1:3]) != INPUT_SIZE:
        x = torch.stack([crop_resize(f.numpy(), INPUT_SIZE) for f in x.cpu()])
    return x.permute(0, 3, 1, 2).float() / 255.0


def segment_distance(start, end, dz: float = 0.0) -> float:
    """Distance from the goal point (the origin) to the segment ``start -> end``: points
    ``(ahead, lateral)`` with a common height difference ``dz``, or ``(ahead, lateral, dz)``
    (m).

    Example:
        >>> round(segment_distance((0.3, 0.1), (-0.3, 0.1)), 3)  # passed 0.1 m beside it
        0.1
        >>> round(segment_distance((0.3, 0.0), (0.2, 0.0)), 3)  # stopped 0.2 m short
        0.2
        >>> round(segment_distance((0.1, 0.0, 0.4), (0.35, 0.0, 0.0)), 3)  # came down far off
        0.297
    """
    a, b = np.asarray(start, float), np.asarray(end, float)
    if a.shape != b.shape or a.shape not in ((2,), (3,)):
        raise ValueError(f"segment_distance: start and end must both be (ahead, lateral) or "
                         f"(ahead, lateral, dz), got {a.shape} and {b.shape}")
    if a.shape == (2,):
        a, b = np.append(a, dz), np.append(b, dz)
    d = b - a
    t = 0.0 if not d.any() else float(np.clip(-(a @ d) / (d @ d), 0.0, 1.0))
    p = a + t * d
    return float(math.sqrt(p @ p))


class GoalOffsetEstimator:
    """A :class:`GoalOffsetNet` with its input handling: frames in, ``(ahead, lateral)`` out.

    Args:
        net: the network (eval mode is set here).
        meta: what the weights were trained on and measured at (JSON types), saved with them.

    Example:
        >>> import torch, tempfile, os
        >>> est = GoalOffsetEstimator(GoalOffsetNet(), meta={"note": "untrained"})
        >>> path = est.save(os.path.join(tempfile.mkdtemp(), "arrival.pt"))
        >>> GoalOffsetEstimator.load(path).meta["note"]
        'untrained'
    """

    def __init__(self, net: GoalOffsetNet, meta: dict | None = None):
        if not isinstance(net, GoalOffsetNet):
            raise ValueError(f"GoalOffsetEstimator: net must be a GoalOffsetNet, got {net!r}")
        self.net = net.eval()
        self.meta = dict(meta or {})

    @torch.no_grad()
    def __call__(self, frames) -> torch.Tensor:
        """``[B, 2]`` offsets (m) of uint8 RGB frames of any 4:3-croppable size."""
        return self.net(_to_input(frames))[:, :2]

    @property
    def in_view(self) -> bool:
        """Whether the head also says if the board is in view (:meth:`estimate`)."""
        return self.net.in_view

    @torch.no_grad()
    def estimate(self, frames) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``([B, 2]`` offsets (m), ``[B]`` probability that the board is in view enough to
        read them, or None for a head without that output)."""
        out = self.net(_to_input(frames))
        return out[:, :2], (torch.sigmoid(out[:, -1]) if self.net.in_view else None)

    @torch.no_grad()
    def estimate_mirrored(self, frames) -> tuple[torch.Tensor, torch.Tensor | None,
                                                  torch.Tensor]:
        """:meth:`estimate` on each frame and on its mirror image (flipped left-right, its
        sideways reading turned back), the symmetry every head was trained with. Returns
        ``([B, 2]`` mean offsets (m), ``[B]`` mean in-view probability or None for a head
        without that output, ``[B]`` how far apart the two sideways readings lie (m)): the
        mean reads the offset better than one frame does, and the spread is large where the
        head is unsure (docs/tello.rst, "Asking the head twice").

        Example:
            >>> import torch
            >>> est = GoalOffsetEstimator(GoalOffsetNet(in_view=True))
            >>> frames = torch.randint(0, 255, (2, 240, 320, 3), dtype=torch.uint8)
            >>> offsets, p_view, spread = est.estimate_mirrored(frames)
            >>> offsets.shape, p_view.shape, bool((spread >= 0).all())
            (torch.Size([2, 2]), torch.Size([2]), True)
            >>> mirror = est.estimate_mirrored(frames.flip(2))  # the same two views
            >>> torch.allclose(mirror[0][:, 1], -offsets[:, 1], atol=1e-5)
            True
        """
        x = _to_input(frames)
        out = self.net(torch.cat([x, x.flip(-1)]))
        a, b = out[:len(x)], out[len(x):]
        back = b[:, :2] * torch.tensor([1.0, -1.0], dtype=b.dtype)  # the mirror's, turned back
        p = ((torch.sigmoid(a[:, -1]) + torch.sigmoid(b[:, -1])) / 2 if self.net.in_view
             else None)
        return (a[:, :2] + back) / 2, p, (a[:, 1] - back[:, 1]).abs()

    def save(self, path) -> Path:
        """Writes the weights (float16), the network's width and :attr:`meta` to ``path``."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        state = {k: v.half() for k, v in self.net.state_dict().items()}
        torch.save({"format": _FORMAT, "version": _VERSION, "width": self.net.width,
                    "outputs": self.net.outputs, "in_view": self.net.in_view,
                    "state_dict": state, "meta": self.meta}, path)
        return path

    @classmethod
    def load(cls, path=None) -> GoalOffsetEstimator:
        """Loads weights written by :meth:`save` (None: the shipped :data:`DEFAULT_WEIGHTS`;
        :data:`ROOMS_WEIGHTS` is the shipped head for rooms other than the thesis room).

        Raises:
            FileNotFoundError: no such file (naming it and the command that trains one).
            RuntimeError: a file of another format.
        """
        path = DEFAULT_WEIGHTS if path is None else Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"No arrival head at {path}; train one with "
                                    "python recipes/train_arrival.py --out PATH")
        try:
            blob = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001 - any unreadable file is named
            raise RuntimeError(f"{path} is not an arrival head ({e})") from e
        if not isinstance(blob, dict) or blob.get("format") != _FORMAT:
            raise RuntimeError(f"{path} is not an arrival head (format "
                               f"{blob.get('format') if isinstance(blob, dict) else None!r})")
        net = GoalOffsetNet(int(blob["width"]), int(blob.get("outputs", 2)),
                            bool(blob.get("in_view", False)))
        net.load_state_dict({k: v.float() for k, v in blob["state_dict"].items()})
        return cls(net, blob.get("meta"))


def render_offset_views(n: int, *, seed: int, stream_sizes=((720, 960), (240, 320)),
                        ahead=(-0.42, 0.8), lateral=0.6, height=0.2, yaw_deg=30.0,
                        video_path_options: dict | None = None, layout: str = "thesis",
                        goal_size=(1.0, 0.8), views_per_layout: int = 20):
    """``n`` frames near a goal board through the Tello camera path, with labels.

    Args:
        n: how many frames (>= 1).
        seed: seed of the poses and of the camera path's jitter.
        stream_sizes: the video stream sizes, used in turn (the Tello's 960 x 720 and the
            emulator's default 320 x 240).
        ahead: ``(low, high)`` range (m) of the offset along the board's normal from the goal
            point (the goal point is 0.45 m from the board's face: -0.42 is 3 cm from it).
        lateral: the largest sideways offset (m).
        height: the largest height offset (m; ``TelloEnv`` asks the head only when the
            height sensor puts the drone within the rule's ``max_goal_offset``, 0.2 m).
        yaw_deg: the largest yaw off facing the board (deg).
        video_path_options: extra :class:`~torchrl_causal.perception.video_path.VideoPath`
            options.
        layout: ``"thesis"`` (the thesis scene's board, the default) or a random-layout
            split, ``"train"`` or ``"heldout"``: then a new room (walls, floor, light,
            obstacles, the board's place and turn) every ``views_per_layout`` frames,
            each with a board of ``goal_size``, and no pose within 0.3 m of an obstacle
            or outside the room.
        goal_size: random layouts only: the board's ``(width, height)`` (m); the default
            is the field guide's printed 1.0 x 0.8 m board, the thesis board's size.
        views_per_layout: random layouts only: frames per room (>= 1).

    Returns:
        ``(frames uint8 [n, 96, 128, 3], labels float32 [n, 5])``: ``ahead``,
        ``lateral``, ``dz`` (m, the drone above the goal point), the yaw off the board's
        normal (deg) and the share of the stream's frame the board covers (0-1, from the
        env's segmentation render; occlusion counted).
    """
    from ..envs import DroneNavEnv
    from .dataset import _quat
    from .video_path import VideoPath, crop_resize

    if not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be an int >= 1, got {n!r}")
    if layout not in ("thesis", "train", "heldout"):
        raise ValueError(f"layout must be 'thesis', 'train' or 'heldout', got {layout!r}")
    if not isinstance(views_per_layout, int) or views_per_layout < 1:
        raise ValueError(f"views_per_layout must be an int >= 1, got {views_per_layout!r}")
    thesis = layout == "thesis"
    sizes = [tuple(int(v) for v in s) for s in stream_sizes]
    paths = {s: VideoPath(stream_size=s, seed=seed + i, **(video_path_options or {}))
             for i, s in enumerate(sizes)}
    rng = np.random.default_rng(seed)
    frames, labels = [], []
    envs: dict = {}

    def free(lay, xy) -> bool:  # inside the room, clear of every obstacle's footprint
        x0, y0, x1, y1 = lay.arena
        return (x0 + 0.3 <= xy[0] <= x1 - 0.3 and y0 + 0.3 <= xy[1] <= y1 - 0.3
                and all(float(o.footprint_distance(xy[0], xy[1])) >= 0.3
                        for o in lay.obstacles))

    try:
        for i in range(n):
            if not envs or (not thesis and i % views_per_layout == 0):  # a (new) room
                for env in envs.values():
                    env.close()
                kw = {} if thesis else dict(split=layout, goal_size=tuple(goal_size),
                                            layout_index=int(rng.integers(0, 1_000_000)))
                envs = {s: DroneNavEnv("thesis" if thesis else "random", image_size=s,
                                       seed=0, **kw) for s in sizes}
                for env in envs.values():
                    env.reset()
                lay = envs[sizes[0]].layout
                gp, gc = np.array(lay.goal_point()), np.array(lay.goal_center)
                normal = (gp - gc)[:2] / np.linalg.norm((gp - gc)[:2])
                side = np.array([-normal[1], normal[0]])
                facing = math.degrees(math.atan2(-normal[1], -normal[0]))
            size = sizes[i % len(sizes)]
            env = envs[size]
            qa = env.ids.qpos_adr
            for _ in range(1000):  # the thesis room has no obstacle near its board
                ahead_m, lat = rng.uniform(*ahead), rng.uniform(-lateral, lateral)
                dz = rng.uniform(-height, height)
                dyaw = rng.uniform(-yaw_deg, yaw_deg)
                xy = gp[:2] + ahead_m * normal + lat * side
                if thesis or free(lay, xy):
                    break
            env.data.qpos[qa:qa + 3] = (xy[0], xy[1], gp[2] + dz)
            env.data.qpos[qa + 3:qa + 7] = _quat(facing + dyaw, rng.uniform(-3, 3),
                                                 rng.uniform(-3, 3))
            obs = env._observe(False, False)
            rgb = np.asarray(obs["pixels"])
            frames.append(crop_resize(paths[size](rgb), INPUT_SIZE).numpy())
            share = float(obs["goal_pixels"][0]) / float(size[0] * size[1])
            labels.append((ahead_m, lat, dz, dyaw, share))
    finally:
        for env in envs.values():
            env.close()
        for p in paths.values():
            p.close()
    return np.stack(frames), np.asarray(labels, np.float32)


def train_goal_offset(frames, labels, *, epochs: int = 30, seed: int = 0, width: int = 16,
                      lr: float = 1e-3, batch_size: int = 64, yaw_weight: float = 0.0,
                      in_view_share: float | None = None,
                      progress: bool = False) -> GoalOffsetEstimator:
    """Trains a :class:`GoalOffsetNet` on :func:`render_offset_views`' output (smooth-L1 on
    ``(ahead, lateral)``, Adam, horizontal flips with the lateral sign flipped).
    ``yaw_weight > 0`` adds the yaw off the board's normal (``labels[:, 3]``, deg; in rad,
    its sign flipped with the frame) as a third output, its smooth-L1 weighted so.
    ``in_view_share`` (0-1) adds the in-view output: a frame counts as in view when the
    board covers at least that share of it (``labels[:, 4]``); the output learns that
    (binary cross-entropy), and the offsets are learnt on in-view frames only, so the head
    is not taught to guess where the board cannot be read.

    Raises:
        ValueError: frames and labels of other shapes or counts, or a bad option.
    """
    x = torch.as_tensor(np.asarray(frames))
    y = torch.as_tensor(np.asarray(labels, np.float32))
    if x.ndim != 4 or tuple(x.shape[1:]) != (*INPUT_SIZE, 3) or x.dtype != torch.uint8:
        raise ValueError(f"frames must be uint8 [N, {INPUT_SIZE[0]}, {INPUT_SIZE[1]}, 3], got "
                         f"{x.dtype} {tuple(x.shape)}")
    if y.ndim != 2 or y.shape[0] != x.shape[0] or y.shape[1] < 2:
        raise ValueError(f"labels must be [N, >=2] with N = {x.shape[0]}, got {tuple(y.shape)}")
    if not (isinstance(yaw_weight, (int, float)) and yaw_weight >= 0):
        raise ValueError(f"yaw_weight must be a number >= 0, got {yaw_weight!r}")
    if yaw_weight > 0 and y.shape[1] < 4:
        raise ValueError(f"yaw_weight={yaw_weight} needs labels [N, 4] (ahead, lateral, dz, "
                         f"yaw), got {tuple(y.shape)}")
    if in_view_share is not None:
        if not (isinstance(in_view_share, (int, float)) and 0.0 < in_view_share < 1.0):
            raise ValueError(f"in_view_share must be a share in (0, 1) or None, got "
                             f"{in_view_share!r}")
        if y.shape[1] < 5:
            raise ValueError(f"in_view_share={in_view_share} needs labels [N, 5] (... , the "
                             f"board's share of the frame), got {tuple(y.shape)}")
    for name, v in (("epochs", epochs), ("batch_size", batch_size)):
        if not isinstance(v, int) or v < 1:
            raise ValueError(f"{name} must be an int >= 1, got {v!r}")
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    net = GoalOffsetNet(width, 3 if yaw_weight > 0 else 2, in_view=in_view_share is not None)
    seen = (y[:, 4] >= in_view_share if in_view_share is not None
            else torch.ones(len(y), dtype=torch.bool))
    opt = torch.optim.Adam(net.parameters(), lr)
    xf = x.permute(0, 3, 1, 2).float() / 255.0
    target = y[:, :2] if yaw_weight == 0 else torch.cat([y[:, :2], torch.deg2rad(y[:, 3:4])], 1)
    from tqdm.auto import tqdm

    for _ in tqdm(range(epochs), desc="arrival head", disable=not progress):
        net.train()
        perm = torch.randperm(len(xf), generator=gen)
        for i in range(0, len(xf), batch_size):
            b = perm[i:i + batch_size]
            flip = torch.rand(len(b), generator=gen) < 0.5
            xb = torch.where(flip[:, None, None, None], xf[b].flip(-1), xf[b])
            yb = target[b].clone()
            yb[flip, 1:] *= -1  # a mirrored view: lateral (and yaw) change sign
            out, sb = net(xb), seen[b]
            n_seen = sb.sum().clamp(min=1)
            reg = nn.functional.smooth_l1_loss(out[:, :2], yb[:, :2], beta=0.05,
                                               reduction="none").sum(1)
            loss = (reg * sb).sum() / (2 * n_seen)  # the mean over the in-view frames
            if yaw_weight > 0:
                loss = loss + yaw_weight * (nn.functional.smooth_l1_loss(
                    out[:, 2], yb[:, 2], beta=0.05, reduction="none") * sb).sum() / n_seen
            if in_view_share is not None:
                loss = loss + nn.functional.binary_cross_entropy_with_logits(
                    out[:, -1], sb.float())
            opt.zero_grad()
            loss.backward()
            opt.step()
    return GoalOffsetEstimator(net)
