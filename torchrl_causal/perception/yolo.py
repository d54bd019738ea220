"""``YoloGoalDetector``: the heliport detector of the thesis (sec. 4.2) over ultralytics YOLOv8.

ultralytics is AGPL-3.0 and an optional extra: ``pip install
torchrl_causal[perception]``. This module imports it only when a detector is
built, fully offline (:func:`ultralytics_offline`: no connectivity check, no
font or weight downloads, no telemetry).

The shipped weights (``torchrl_causal/perception/weights/goal_yolov8n.pt``, with
a JSON sidecar recording the command, seed, data, epochs and held-out metrics)
are made by ``recipes/train_detector.py`` from ``yolov8n.yaml`` (no pretrained
weights) on images rendered by :mod:`torchrl_causal.perception.dataset`.

Example:
    >>> import torch
    >>> from torchrl_causal.perception.yolo import YoloGoalDetector
    >>> det = YoloGoalDetector()  # the shipped weights
    >>> boxes, scores = det(torch.zeros(2, 240, 320, 3, dtype=torch.uint8))
    >>> boxes.shape[:2] == scores.shape, boxes.shape[-1], scores.dtype
    (True, 4, torch.float32)
"""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import torch
import torch.nn.functional as F

from .goal import GoalDetector

__all__ = [
    "YoloGoalDetector",
    "DEFAULT_WEIGHTS",
    "TRAIN_COMMAND",
    "ultralytics_offline",
    "load_sidecar",
    "calibrate_scores",
    "fit_calibration",
]

#: The shipped detector weights.
DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "goal_yolov8n.pt"
#: The command that (re)makes :data:`DEFAULT_WEIGHTS`.
TRAIN_COMMAND = "python recipes/train_detector.py"
_EXTRA_HINT = "pip install torchrl_causal[perception]"


def ultralytics_offline(config_dir: str | os.PathLike | None = None):
    """Imports ultralytics with every network access switched off; returns the module.

    Sets ``YOLO_OFFLINE=1`` and ``YOLO_AUTOINSTALL=False``, points
    ``YOLO_CONFIG_DIR`` (unless already set) at ``config_dir`` (default
    ``~/.config/torchrl_causal/yolo``), puts a copy of matplotlib's bundled
    DejaVuSans as ``Arial.ttf`` there (ultralytics' dataset check otherwise
    downloads the font, even with ``plots=False``) and turns settings ``sync``
    off.

    Raises:
        ImportError: ultralytics is not installed (names the extra to install).

    Example:
        >>> ultralytics_offline().__name__
        'ultralytics'
    """
    os.environ["YOLO_OFFLINE"] = "1"
    os.environ["YOLO_AUTOINSTALL"] = "False"
    if "YOLO_CONFIG_DIR" not in os.environ:
        default = Path(config_dir) if config_dir else Path.home() / ".config" / "torchrl_causal" / "yolo"
        os.environ["YOLO_CONFIG_DIR"] = str(default)
    cfg = Path(os.environ["YOLO_CONFIG_DIR"])
    try:
        cfg.mkdir(parents=True, exist_ok=True)
        font = cfg / "Arial.ttf"
        if not font.is_file():
            import matplotlib

            src = Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSans.ttf"
            shutil.copyfile(src, font)
    except (OSError, ImportError):  # pragma: no cover - read-only home etc.
        pass
    try:
        import ultralytics
        from ultralytics.utils import SETTINGS as settings
    except ImportError as e:  # pragma: no cover - exercised in a subprocess test
        raise ImportError(
            f"YoloGoalDetector and recipes/train_detector.py need ultralytics (AGPL-3.0), "
            f"an optional extra: {_EXTRA_HINT}"
        ) from e
    if settings.get("sync", False):
        settings.update({"sync": False})
    return ultralytics


def load_sidecar(weights: str | os.PathLike) -> dict:
    """The JSON sidecar ``<weights without .pt>.json`` of a weights file ({} if none).

    Example:
        >>> load_sidecar(DEFAULT_WEIGHTS)["model"]
        'yolov8n'
    """
    p = Path(weights).with_suffix(".json")
    if not p.is_file():
        return {}
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return {}


class YoloGoalDetector(GoalDetector):
    """A :class:`~torchrl_causal.perception.goal.GoalDetector` over an ultralytics YOLO model.

    Takes the env's ``pixels`` as they come: ``uint8 [B, H, W, 3]`` (or one
    ``[H, W, 3]`` frame), **RGB** (fed to the network as an RGB float tensor,
    so ultralytics' BGR convention for numpy input does not apply). Each batch
    is resized so that its longer side is ``imgsz`` (small frames such as the
    DQN's 84 x 84 are upsampled to the training scale), padded to a multiple
    of 32 and run in one forward pass; boxes come back in the input's pixels.

    The detector returns its scores (ultralytics' own ``conf`` floor is low,
    0.05 by default); the thesis's 0.7 rule is the
    :class:`~torchrl_causal.perception.goal.GoalMeter`'s
    ``confidence_threshold``. A YOLO score is not a probability: a detector
    trained briefly is under-confident (the shipped one ranks the goal well,
    mAP50 0.96, but scores many true goals 0.2-0.6). With ``calibration``
    the scores are Platt-calibrated -- ``sigmoid(a * logit(s) + b)``, fitted
    by :func:`fit_calibration` on the validation views so that a score is the
    probability that the best detection is the goal -- and the 0.7 rule reads
    as the thesis means it. The shipped weights' sidecar holds two fits: one
    for small frames (longer side <= ``calibration_small.max_side``, 128 px:
    the DQN's 84 x 84, where the goal is small and scores are lower) and one
    for the others (the 240 x 320 reference camera).

    Args:
        weights: path of an ultralytics detection checkpoint with one class;
            None: the shipped weights (:data:`DEFAULT_WEIGHTS`).
        conf: ultralytics' confidence floor (detections below are dropped).
        iou: NMS IoU threshold.
        imgsz: network input scale (longer side, px); None: the training
            ``imgsz`` from the weights' sidecar (320 if none).
        max_det: detections kept per image (``K`` of the output).
        device: torch device of the network (``"cpu"``, ``"cuda"``, ...).
        calibration: ``"auto"`` (the weights' sidecar ``calibration`` and
            ``calibration_small`` when it has them, else raw scores), None (raw
            scores) or ``(a, b)`` for every frame size.

    Raises:
        ImportError: ultralytics is missing (``pip install torchrl_causal[perception]``).
        FileNotFoundError: the weights file is missing (names the path and the
            command that trains it).
        ValueError: the file is not a loadable one-class detection checkpoint,
            or an option is bad.

    Example:
        >>> import torch
        >>> det = YoloGoalDetector(conf=0.05, max_det=3)
        >>> boxes, scores = det(torch.zeros(84, 84, 3, dtype=torch.uint8))  # one frame
        >>> tuple(boxes.shape), tuple(scores.shape)
        ((1, 3, 4), (1, 3))
    """

    def __init__(
        self,
        weights: str | os.PathLike | None = None,
        *,
        conf: float = 0.05,
        iou: float = 0.5,
        imgsz: int | None = None,
        max_det: int = 5,
        device: str | torch.device = "cpu",
        calibration="auto",
    ):
        if not (calibration is None or calibration == "auto" or (
                isinstance(calibration, (tuple, list)) and len(calibration) == 2
                and all(isinstance(v, (int, float)) and math.isfinite(v) for v in calibration))):
            raise ValueError(f"calibration must be 'auto', None or (a, b), got {calibration!r}")
        if not isinstance(conf, (int, float)) or not 0.0 <= conf < 1.0:
            raise ValueError(f"conf must be in [0, 1), got {conf!r}")
        if not isinstance(iou, (int, float)) or not 0.0 < iou <= 1.0:
            raise ValueError(f"iou must be in (0, 1], got {iou!r}")
        if imgsz is not None and (
            not isinstance(imgsz, int) or isinstance(imgsz, bool) or imgsz < 32 or imgsz % 32
        ):
            raise ValueError(f"imgsz must be None or a multiple of 32 >= 32, got {imgsz!r}")
        if not isinstance(max_det, int) or isinstance(max_det, bool) or max_det < 1:
            raise ValueError(f"max_det must be an int >= 1, got {max_det!r}")
        ultralytics_offline()
        from ultralytics import YOLO

        path = Path(weights) if weights is not None else DEFAULT_WEIGHTS
        if not path.is_file():
            raise FileNotFoundError(
                f"detector weights {str(path)!r} do not exist; train them with "
                f"`{TRAIN_COMMAND}` (see docs/perception.rst)"
            )

        try:
            model = YOLO(str(path), task="detect")
            net = model.model
            names = getattr(net, "names", None)
        except Exception as e:
            raise ValueError(
                f"detector weights {str(path)!r} cannot be loaded ({type(e).__name__}: {e}); "
                f"retrain them with `{TRAIN_COMMAND}`"
            ) from e
        if not isinstance(net, torch.nn.Module) or names is None or len(names) != 1:
            raise ValueError(
                f"detector weights {str(path)!r} are not a one-class detection model "
                f"(names={names!r}); retrain them with `{TRAIN_COMMAND}`"
            )
        self.weights = path
        self.sidecar = load_sidecar(path)
        #: the small-frame fit ``(max_side, a, b)`` ("auto" only), used for frames whose
        #: longer side is at most ``max_side``; :attr:`calibration` for the others
        self.calibration_small = None
        if calibration == "auto":
            cal, small = self.sidecar.get("calibration"), self.sidecar.get("calibration_small")
            calibration = (cal["a"], cal["b"]) if cal else None
            if small:
                self.calibration_small = (int(small["max_side"]), float(small["a"]),
                                          float(small["b"]))
        self.calibration = None if calibration is None else tuple(float(v) for v in calibration)
        self.imgsz = int(imgsz or self.sidecar.get("imgsz", 320))
        self.conf = float(conf)
        self.iou = float(iou)
        self.max_det = int(max_det)
        self.device = torch.device(device)
        self.model = model
        net.to(self.device).eval().float()
        for p in net.parameters():
            p.requires_grad_(False)

    def _prepare(self, pixels) -> tuple[torch.Tensor, float, tuple[int, int]]:
        x = torch.as_tensor(pixels)
        if x.dtype != torch.uint8:
            raise ValueError(f"pixels must be uint8 [B, H, W, 3] (RGB), got dtype {x.dtype}")
        if x.ndim == 3:
            x = x.unsqueeze(0)
        if x.ndim != 4 or x.shape[-1] != 3 or x.shape[1] < 8 or x.shape[2] < 8:
            raise ValueError(
                f"pixels must be uint8 [B, H, W, 3] or [H, W, 3] (RGB, H and W >= 8), "
                f"got shape {tuple(x.shape)}"
            )
        h, w = int(x.shape[1]), int(x.shape[2])
        scale = self.imgsz / max(h, w)
        x = x.to(self.device).permute(0, 3, 1, 2).float().div_(255.0)
        nh, nw = round(h * scale), round(w * scale)
        if (nh, nw) != (h, w):
            x = F.interpolate(x, size=(nh, nw), mode="bilinear", align_corners=False, antialias=scale < 1)
        ph, pw = math.ceil(nh / 32) * 32, math.ceil(nw / 32) * 32
        if (ph, pw) != (nh, nw):  # pad bottom / right with ultralytics' grey
            x = F.pad(x, (0, pw - nw, 0, ph - nh), value=114 / 255)
        return x.contiguous(), scale, (h, w)

    @torch.no_grad()
    def detect(self, pixels, depth=None, **gt):
        x, scale, (h, w) = self._prepare(pixels)
        B = x.shape[0]
        results = self.model.predict(
            x,
            imgsz=tuple(x.shape[-2:]),
            conf=self.conf,
            iou=self.iou,
            max_det=self.max_det,
            device=self.device,
            verbose=False,
        )
        boxes = torch.zeros(B, self.max_det, 4)
        scores = torch.zeros(B, self.max_det)
        for i, r in enumerate(results):
            k = min(len(r.boxes), self.max_det)
            if k:
                b = r.boxes.xyxy[:k].float().cpu() / scale
                b[:, 0::2] = b[:, 0::2].clamp(0, w)
                b[:, 1::2] = b[:, 1::2].clamp(0, h)
                boxes[i, :k] = b
                scores[i, :k] = r.boxes.conf[:k].float().cpu()
        if self.calibration_small is not None and max(h, w) <= self.calibration_small[0]:
            scores = calibrate_scores(scores, *self.calibration_small[1:])
        elif self.calibration is not None:
            scores = calibrate_scores(scores, *self.calibration)
        return boxes, scores

    def __repr__(self) -> str:
        return (
            f"YoloGoalDetector(weights={str(self.weights)!r}, imgsz={self.imgsz}, "
            f"conf={self.conf}, calibration={self.calibration}, device={str(self.device)!r})"
        )


def calibrate_scores(scores: torch.Tensor, a: float, b: float) -> torch.Tensor:
    """Platt calibration ``sigmoid(a * logit(s) + b)`` of scores in (0, 1); 0 (no detection) stays 0.

    Example:
        >>> [round(v, 3) for v in calibrate_scores(torch.tensor([0.0, 0.2, 0.5]), 2.0, 3.0).tolist()]
        [0.0, 0.557, 0.953]
    """
    s = scores.clamp(1e-6, 1 - 1e-6)
    out = torch.sigmoid(a * torch.log(s / (1 - s)) + b)
    return torch.where(scores > 0, out, torch.zeros_like(out))


def fit_calibration(detector: YoloGoalDetector, views, *, iou_threshold: float = 0.5,
                    batch_size: int = 32, l2: float = 1e-3) -> dict:
    """Fits the Platt calibration of a detector's best score per view.

    Per view, the best detection's raw score ``s`` is labelled 1 when the view
    has a goal box and the detection overlaps it with IoU >= ``iou_threshold``,
    else 0; a logistic regression of the label on ``logit(s)`` (Newton steps,
    a small L2 penalty) gives ``a, b``. Views without any detection keep
    score 0 and do not enter the fit.

    Args:
        detector: the detector (its raw scores are used whatever its ``calibration``).
        views: :class:`~torchrl_causal.perception.dataset.View` objects with ``box``
            ground truth (e.g. the validation split, at every image size the
            detector will see).
        iou_threshold: IoU of a correct detection.
        batch_size: frames per detector call.
        l2: L2 penalty of the fit.

    Returns:
        ``{"a", "b", "n", "positives"}`` (``n``: views with a detection).

    Example:
        >>> from torchrl_causal.perception.dataset import render_views
        >>> fit = fit_calibration(YoloGoalDetector(), list(render_views("val", 48, seed=0,
        ...                                                             image_size=84)))
        >>> fit["n"], fit["positives"], fit["a"] > 0
        (32, 31, True)
    """
    import numpy as np

    from torchrl_causal.perception.dataset import box_iou

    views = list(views)
    if not views:
        raise ValueError("views is empty")
    saved = detector.calibration, detector.calibration_small
    detector.calibration = detector.calibration_small = None
    # frames of one size per detector call (views of several sizes may come together)
    by_size: dict = {}
    for v in views:
        by_size.setdefault(v.rgb.shape, []).append(v)
    chunks = [group[i : i + batch_size] for group in by_size.values()
              for i in range(0, len(group), batch_size)]
    try:
        xs, ys = [], []
        for chunk in chunks:
            boxes, scores = detector(torch.from_numpy(np.stack([v.rgb for v in chunk])))
            best, j = scores.max(-1)
            for v, s, box in zip(chunk, best.tolist(), boxes[torch.arange(len(chunk)), j]):
                if s <= 0:
                    continue
                hit = v.box is not None and float(
                    box_iou(np.asarray([v.box], float), box.numpy()[None].astype(float))[0, 0]
                ) >= iou_threshold
                xs.append(s)
                ys.append(float(hit))
    finally:
        detector.calibration, detector.calibration_small = saved
    if len(set(ys)) < 2:
        raise ValueError(f"cannot calibrate on {len(ys)} detections that are all "
                         f"{'correct' if ys and ys[0] else 'wrong'}: give more varied views")
    s = np.clip(np.asarray(xs), 1e-6, 1 - 1e-6)
    x, y = np.log(s / (1 - s)), np.asarray(ys)
    a, b = 1.0, 0.0
    for _ in range(100):
        p = 1 / (1 + np.exp(-(a * x + b)))
        w = p * (1 - p)
        g = np.array([((p - y) * x).sum() + l2 * a, (p - y).sum()])
        h = np.array([[(w * x * x).sum() + l2, (w * x).sum()], [(w * x).sum(), w.sum() + 1e-9]])
        step = np.linalg.solve(h, g)
        a, b = a - step[0], b - step[1]
        if np.abs(step).max() < 1e-10:
            break
    return {"a": float(a), "b": float(b), "n": len(ys), "positives": int(y.sum())}
