"""Videos of evaluated episodes: the onboard camera beside a MuJoCo chase view (H.264, PyAV).

:func:`record_episodes` flies greedy episodes of a policy with
:func:`~torchrl_causal.training.evaluate` (so the figures and the video are of
the same episodes) and writes one MP4. Every frame shows the drone's onboard
camera (``pixels``, upscaled to the chase view's height, nearest neighbour: the
policy's real resolution stays visible) beside a third-person chase view that
MuJoCo renders with :class:`mujoco.Renderer` from behind and above the drone.
Drawn on the chase view (OpenCV ``putText``): the layout, episode and step, the
action (:data:`~torchrl_causal.schema.ACTION_NAMES`), the gate's decision when
the policy has a :class:`~torchrl_causal.modules.CBNGate` (``vetoed``,
``replaced`` or ``kept``), whether the goal is in sight, and at the end of an
episode its outcome (reached / crash / geofence exit / timeout, coloured as in
the flight maps).

Frames: an episode of ``n`` steps gives ``n + 1 + end_frames`` frames -- its
first observation, one frame after every step (labelled with the action that
led to it and the gate's decision on it) and the last frame held
``end_frames`` more times under the outcome banner.

Why not TorchRL's ``VideoRecorder`` + ``CSVLogger(video_format="mp4")``: with
the installed TorchRL (0.14) the logger's MP4 path writes through
``torchcodec``'s ``VideoEncoder`` (not installed, and it brings its own FFmpeg
build), and torchvision 0.29 no longer has ``torchvision.io.write_video``; and
``VideoRecorder`` records one observation key of the env, while these frames
combine the env's camera, a second MuJoCo render and the policy's decision
(written by the policy, not the env). The frames are therefore drawn by a small
TorchRL :class:`~torchrl.envs.Transform` on the evaluated env (it sees every
step's policy output and observation) and encoded with PyAV (``libx264``,
``yuv420p``), streamed frame by frame into a temporary file that is renamed
to ``path`` when the video is complete.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path

import numpy as np
import torch

from ..perception.video_path import yuv420p_frame

__all__ = ["record_episodes", "OUTCOME_LABELS"]

#: Banner text of an episode's outcome (keys of
#: :func:`~torchrl_causal.training.flightmap.outcome_of`).
OUTCOME_LABELS = {"reached": "REACHED", "crash": "CRASH", "geofence": "GEOFENCE EXIT",
                  "timeout": "TIMEOUT"}


def _rgb(hex_colour: str) -> tuple[int, int, int]:
    h = hex_colour.lstrip("#")
    return tuple(int(h[i:i + 2], 16) for i in (0, 2, 4))


def _flag(td, key) -> bool | None:
    val = td.get(key, None)
    return None if val is None else bool(val.any())


def _image(pixels) -> np.ndarray:
    """``[H, W, 3]`` uint8 of an observation (HWC uint8 or CHW float in [0, 1])."""
    x = pixels.detach().cpu()
    if x.ndim == 3 and x.shape[0] in (1, 3) and x.shape[-1] not in (1, 3):
        x = x.permute(1, 2, 0)
    if x.is_floating_point():
        x = (x.clamp(0, 1) * 255).round()
    x = x.to(torch.uint8).numpy()
    if x.shape[-1] == 1:
        x = np.repeat(x, 3, axis=-1)
    return np.ascontiguousarray(x)


class _FlightRecorder:
    """Draws and encodes the frames; fed by :class:`_RecorderTransform`."""

    def __init__(self, base, path: Path, *, chase_size, fps, end_frames, episodes,
                 distance, elevation):
        self.base = base
        self.path = path
        self.tmp = path.with_name(f".{path.stem}.part{os.getpid()}.mp4")
        self.chase_h, self.chase_w = chase_size
        self.fps = int(fps)
        self.end_frames = int(end_frames)
        self.episodes = int(episodes)
        self.distance = float(distance)
        self.elevation = float(elevation)
        self.episode = 0
        self.step = 0
        self.open = False  # an episode was started and not closed
        self.frames = 0
        self.frame_size = None  # (height, width) of the video
        self._last = None  # (onboard, chase, lines) of the last frame
        self._renderer = None
        self._model_src = None
        self._container = None
        self._stream = None

    # ---------------------------------------------------------------- rendering
    def _chase(self) -> np.ndarray:
        import mujoco

        base = self.base
        if self._model_src is not base.model:  # a new layout: a renderer for its model
            self._close_renderer()
            model = copy.copy(base.model)
            model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.chase_w)
            model.vis.global_.offheight = max(model.vis.global_.offheight, self.chase_h)
            self._option = mujoco.MjvOption()
            # a closed hall's walls and ceiling would stand between the camera and the drone
            for g in range(model.ngeom):
                name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or ""
                if name.startswith("wall") or name == "ceiling":
                    model.geom_group[g] = 3
            self._option.geomgroup[3] = 0
            self._renderer = mujoco.Renderer(model, self.chase_h, self.chase_w)
            self._model_src = base.model
            self._cam = mujoco.MjvCamera()
            self._cam.type = mujoco.mjtCamera.mjCAMERA_FREE
            self._cam.distance = self.distance
            self._cam.elevation = self.elevation
        self._cam.lookat[:] = base.data.xpos[base.ids.drone_body]
        self._cam.azimuth = base.drone_pose()[3]
        self._renderer.update_scene(base.data, camera=self._cam, scene_option=self._option)
        return self._renderer.render()

    def _onboard(self, pixels) -> np.ndarray:
        import cv2

        img = _image(pixels)
        h, w = img.shape[:2]
        width = int(round(w * self.chase_h / h))
        width += width % 2  # H.264 (yuv420p) needs even sizes
        return cv2.resize(img, (width, self.chase_h), interpolation=cv2.INTER_NEAREST)

    @staticmethod
    def _text(img, lines, origin=(6, 6), scale=0.45, colour=(255, 255, 255)):
        import cv2

        font, thick = cv2.FONT_HERSHEY_SIMPLEX, 1
        sizes = [cv2.getTextSize(t, font, scale, thick) for t in lines]
        line_h = max(s[0][1] + s[1] for s in sizes) + 6
        width = max(s[0][0] for s in sizes) + 12
        x0, y0 = origin
        box = img[y0:y0 + line_h * len(lines) + 6, x0:x0 + width]
        box[:] = (box * 0.45).astype(np.uint8)  # a dark strip under the text
        for i, t in enumerate(lines):
            cv2.putText(img, t, (x0 + 6, y0 + (i + 1) * line_h), font, scale, colour, thick,
                        cv2.LINE_AA)

    def _banner(self, img, outcome: str) -> None:
        import cv2

        from .flightmap import OUTCOME_COLOURS

        text = OUTCOME_LABELS[outcome]
        font, scale, thick = cv2.FONT_HERSHEY_SIMPLEX, 1.0, 2
        (tw, th), base = cv2.getTextSize(text, font, scale, thick)
        h, w = img.shape[:2]
        y1 = h - 12
        y0 = y1 - th - base - 12
        cv2.rectangle(img, (0, y0), (w - 1, y1), _rgb(OUTCOME_COLOURS[outcome]), -1)
        cv2.putText(img, text, ((w - tw) // 2, y1 - base - 6), font, scale, (255, 255, 255),
                    thick, cv2.LINE_AA)

    def _compose(self, onboard, chase, lines, outcome=None) -> np.ndarray:
        left = onboard.copy()
        self._text(left, ["onboard"], scale=0.4)
        right = chase.copy()
        self._text(right, lines)
        if outcome is not None:
            self._banner(right, outcome)
        return np.concatenate([left, right], axis=1)

    # ------------------------------------------------------------------ writing
    def _write(self, frame: np.ndarray) -> None:
        import av

        if self._container is None:
            self._container = av.open(str(self.tmp), "w", format="mp4")
            self._stream = self._container.add_stream("libx264", rate=self.fps)
            self._stream.height, self._stream.width = frame.shape[:2]
            self._stream.pix_fmt = "yuv420p"
            self._stream.options = {"crf": "20"}
            self.frame_size = tuple(frame.shape[:2])
        video_frame = yuv420p_frame(frame)  # on one thread (perception.video_path.SWS_THREADS)
        for packet in self._stream.encode(video_frame):
            self._container.mux(packet)
        self.frames += 1

    def _emit(self, next_td, lines) -> None:
        onboard = self._onboard(next_td.get("pixels"))
        chase = self._chase()
        self._last = (onboard, chase, lines)
        self._write(self._compose(onboard, chase, lines))

    def _lines(self, next_td, action=None, decision=None) -> list[str]:
        from ..schema import ACTION_NAMES

        layout = getattr(self.base.layout, "name", "")
        lines = [f"{layout}  episode {self.episode}/{self.episodes}  step {self.step}"]
        if action is None:
            lines.append("action: -")
        else:
            name = ACTION_NAMES[action] if 0 <= action < len(ACTION_NAMES) else str(action)
            lines.append(f"action: {name}")
            if decision:
                lines.append(f"gate: {decision}")
        seen = _flag(next_td, "goal_in_sight")
        if seen is not None:
            lines.append(f"goal in sight: {'yes' if seen else 'no'}")
        return lines

    # ------------------------------------------------------------ episode events
    def on_reset(self, next_td) -> None:
        self.close_episode()
        self.episode += 1
        self.step = 0
        self.open = True
        self._emit(next_td, self._lines(next_td))

    def on_step(self, td, next_td) -> None:
        if not self.open:
            return
        self.step += 1
        action = td.get("action")
        action = int(action.argmax()) if action.numel() > 1 else int(action)
        decision = None
        if _flag(td, "gate_vetoed"):
            decision = "vetoed"
        elif _flag(td, "gate_replaced"):
            decision = "replaced"
        elif "gate_vetoed" in td.keys() or "gate_replaced" in td.keys():
            decision = "kept"
        self._emit(next_td, self._lines(next_td, action, decision))
        if _flag(next_td, "done"):
            from .flightmap import outcome_of

            self.close_episode(outcome_of({"success": _flag(next_td, "reached"),
                                           "crash": _flag(next_td, "crashed"),
                                           "out_of_bounds": _flag(next_td, "out_of_bounds")}))

    def close_episode(self, outcome: str = "timeout") -> None:
        """Ends the open episode: its last frame under the outcome banner, held."""
        if not self.open or self._last is None:
            return
        self.open = False
        onboard, chase, lines = self._last
        frame = self._compose(onboard, chase, lines, outcome)
        for _ in range(self.end_frames):
            self._write(frame)

    def finish(self) -> Path:
        self.close_episode()  # an episode cut by max_steps ends as a timeout
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()
        self._container = None
        os.replace(self.tmp, self.path)
        return self.path

    def _close_renderer(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
            self._model_src = None

    def close(self) -> None:
        """Frees the renderer; removes a partial video (after an error)."""
        self._close_renderer()
        if self._container is not None:
            self._container.close()
            self._container = None
        self.tmp.unlink(missing_ok=True)


def _recorder_transform(recorder: _FlightRecorder):
    from torchrl.envs import Transform

    class _RecorderTransform(Transform):
        """Hands every reset and step of the env to the recorder (changes nothing)."""

        def __init__(self):
            super().__init__(in_keys=[], out_keys=[])
            self.recorder = recorder

        def _reset(self, tensordict, tensordict_reset):
            self.recorder.on_reset(tensordict_reset)
            return tensordict_reset

        def _step(self, tensordict, next_tensordict):
            self.recorder.on_step(tensordict, next_tensordict)
            return next_tensordict

        def _call(self, next_tensordict):
            return next_tensordict

    return _RecorderTransform()


def _check_size(chase_size) -> tuple[int, int]:
    ok = (isinstance(chase_size, (tuple, list)) and len(chase_size) == 2
          and all(isinstance(v, int) and not isinstance(v, bool) for v in chase_size))
    if ok:
        h, w = chase_size
        ok = h >= 240 and w >= 320 and h % 2 == 0 and w % 2 == 0
    if not ok:
        raise ValueError(f"chase_size must be (height, width), even ints with height >= 240 "
                         f"and width >= 320, got {chase_size!r}")
    return int(chase_size[0]), int(chase_size[1])


def record_episodes(policy, env, episodes: int, seed: int, path, *, max_steps: int | None = None,
                    chase_size: tuple[int, int] = (240, 320), fps: int = 4,
                    end_frames: int = 4, distance: float = 1.6, elevation: float = -25.0,
                    spl: bool | None = None) -> dict:
    """Flies greedy episodes of ``policy`` on ``env`` and writes them as one MP4.

    The episodes are those of ``evaluate(policy, env, episodes, seed,
    per_episode=True)`` (TorchRL's ``DETERMINISTIC`` exploration type; the env
    and its sampling transforms seeded with ``seed``), flown once: the returned
    figures and the video show the same flights.

    Args:
        policy: a TorchRL policy, e.g. the ``TensorDictSequential(actor, gate)``
            of :func:`torchrl_causal.pretrained.load_policy`.
        env: a :class:`~torchrl_causal.envs.DroneNavEnv` or a ``TransformedEnv``
            over one (unbatched); it is wrapped, not changed.
        episodes: the number of episodes (>= 1).
        seed: seeds the env and its sampling transforms first.
        path: the ``.mp4`` file to write (its folder is created).
        max_steps: step limit of an episode (default: the env's ``max_steps``);
            an episode cut by it ends as a timeout.
        chase_size: ``(height, width)`` of the chase view (even, >= 240 x 320);
            the onboard view is upscaled to its height and drawn on its left.
        fps: frames per second of the video (one frame per step).
        end_frames: extra frames that hold an episode's last view under its
            outcome banner.
        distance, elevation: the chase camera's distance to the drone (m) and
            its elevation (deg, negative: above it, looking down); its azimuth
            follows the drone's yaw, so it looks the way the drone does.
        spl: passed to :func:`~torchrl_causal.training.evaluate` (``None``:
            measure SPL over a kinematic env).

    Returns:
        :func:`~torchrl_causal.training.evaluate`'s dict (``success_rate``,
        ``spl``, ...) with ``episodes`` (per episode ``success``, ``crash``,
        ``out_of_bounds``, ``steps``, ``oracle_steps``, ``spl``, ``layout``,
        ``path``, ...), plus ``video`` (the MP4's :class:`~pathlib.Path`),
        ``frames`` (its frame count: the steps plus ``1 + end_frames`` per
        episode), ``fps`` and ``frame_size`` (``(height, width)``).

    Raises:
        ValueError: ``env`` is not (over) a ``DroneNavEnv``; ``episodes`` < 1;
            ``path`` is not an ``.mp4`` file or its folder cannot be created;
            a bad ``chase_size``, ``fps`` or ``end_frames``. All before any
            episode runs.

    Example:
        >>> import pathlib, tempfile
        >>> from torchrl_causal.envs import DroneNavEnv, OraclePolicy
        >>> env = DroneNavEnv(image_size=32, seed=0)
        >>> out = record_episodes(OraclePolicy(env), env, episodes=1, seed=0,
        ...                       path=pathlib.Path(tempfile.mkdtemp()) / "flight.mp4")
        >>> out["episodes"][0]["success"], out["episodes"][0]["steps"], out["frames"]
        (True, 12, 17)
        >>> out["video"].is_file(), out["frame_size"]
        (True, (240, 560))
    """
    from torchrl.envs import TransformedEnv

    from ..envs.oracle import base_drone_env
    from .evaluation import evaluate, seed_transforms

    base = base_drone_env(env)
    if base is None:
        raise ValueError(f"record_episodes needs a DroneNavEnv or a TransformedEnv over one "
                         f"(env), got {type(env).__name__}")
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be an int >= 1, got {episodes!r}")
    chase_size = _check_size(chase_size)
    for name, value, low in (("fps", fps, 1), ("end_frames", end_frames, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"path must name an .mp4 file, got {str(path)!r}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"cannot create the folder of path={str(path)!r}: {err}") from err
    if path.is_dir():
        raise ValueError(f"path={str(path)!r} is a folder; give the .mp4 file to write")

    recorder = _FlightRecorder(base, path, chase_size=chase_size, fps=fps,
                               end_frames=end_frames, episodes=episodes,
                               distance=distance, elevation=elevation)
    watched = TransformedEnv(env, _recorder_transform(recorder), auto_unwrap=False)
    # evaluate() reseeds the outer env's transforms only: reseed the inner ones here
    seed_transforms(env, seed)
    try:
        out = evaluate(policy, watched, episodes, seed, max_steps=max_steps, spl=spl,
                       per_episode=True)
        out["video"] = recorder.finish()
    finally:
        recorder.close()
    out["frames"] = recorder.frames
    out["fps"] = recorder.fps
    out["frame_size"] = recorder.frame_size
    return out
