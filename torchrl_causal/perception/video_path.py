"""What a Tello's camera path does to a frame: H.264 at the stream's settings, and the stack's crop.

A real Tello sends 960x720 H.264 (Annex B over UDP); :class:`~torchrl_causal.envs.TelloEnv`
decodes it and centre-crops and resizes it to the policy's ``image_size``. The
perception networks should be trained and tested on frames that went the same
way. This module holds the pieces, shared by the emulator, ``TelloEnv`` and the
perception datasets (:func:`~torchrl_causal.perception.dataset.render_views`'s
``video_path``):

* :data:`X264_OPTIONS` and :func:`open_h264_encoder` -- the encoder settings
  the :class:`~torchrl_causal.envs.TelloEmulator` streams with (libx264,
  ``ultrafast`` / ``zerolatency``, no B-frames, a keyframe every ``gop``
  frames, the stream's bit rate);
* :func:`crop_resize` -- ``TelloEnv``'s centre crop to the target aspect and
  antialiased bilinear resize;
* :class:`VideoPath` -- a frame in, the frame out as the stack would see it:
  optional camera jitter (exposure, blur, sensor noise), then an H.264
  encode/decode round trip in a continuing stream (so most frames are
  P-frames, as in flight).

Example:
    >>> import numpy as np
    >>> vp = VideoPath(stream_size=(96, 128), seed=0)
    >>> out = vp(np.full((96, 128, 3), 120, np.uint8))
    >>> out.shape, out.dtype.name, abs(int(out.mean()) - 120) < 12
    ((96, 128, 3), 'uint8', True)
    >>> vp.close()
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["X264_OPTIONS", "open_h264_encoder", "crop_resize", "VideoPath",
           "TELLO_STREAM_SIZE"]

#: ``(height, width)`` of the Tello's video stream.
TELLO_STREAM_SIZE = (720, 960)

#: swscale threads for every PyAV colour conversion in this package (``threads=`` of
#: ``VideoFrame.reformat`` / ``to_ndarray``). PyAV >= 17 converts on several worker threads by
#: default and keeps the context in a thread-local; a process forked while a thread holding one
#: runs (a ``ParallelEnv`` started beside a live video thread) frees it in the child and hangs
#: there, waiting on workers that were not forked. One thread costs nothing at these sizes.
SWS_THREADS = 1


def yuv420p_frame(rgb: np.ndarray):
    """An ``av.VideoFrame`` in the encoders' ``yuv420p`` from uint8 RGB ``[H, W, 3]``, converted
    on ``SWS_THREADS`` (an encoder handed RGB would convert on its own worker threads)."""
    import av

    return av.VideoFrame.from_ndarray(rgb, format="rgb24").reformat(format="yuv420p",
                                                                   threads=SWS_THREADS)


def X264_OPTIONS(gop: int) -> dict:  # noqa: N802 - a constant-like factory
    """libx264 options of the Tello stream as the emulator sends it (``gop``: frames
    between keyframes)."""
    return {"preset": "ultrafast", "tune": "zerolatency", "bframes": "0",
            "keyint": str(gop), "min-keyint": str(gop), "scenecut": "0",
            "repeat-headers": "1"}


def open_h264_encoder(height: int, width: int, *, bitrate: int = 1_000_000, gop: int = 15,
                      fps: float = 30.0):
    """An open PyAV libx264 encoder (``yuv420p``) with :data:`X264_OPTIONS`."""
    import av

    enc = av.CodecContext.create("libx264", "w")
    enc.width, enc.height = int(width), int(height)
    enc.pix_fmt = "yuv420p"
    enc.bit_rate = int(bitrate)
    enc.gop_size = int(gop)
    enc.framerate = max(1, int(round(fps)))
    enc.options = X264_OPTIONS(int(gop))
    enc.open()
    return enc


def crop_resize(frame, size: tuple[int, int]) -> torch.Tensor:
    """``TelloEnv``'s preprocessing: centre crop of an RGB frame ``[H0, W0, 3]`` to the
    aspect of ``size = (h, w)``, then an antialiased bilinear resize; uint8 ``[h, w, 3]``.

    Example:
        >>> import numpy as np
        >>> crop_resize(np.zeros((720, 960, 3), np.uint8), (84, 84)).shape
        torch.Size([84, 84, 3])
    """
    h, w = int(size[0]), int(size[1])
    img = torch.as_tensor(np.ascontiguousarray(frame))
    H0, W0 = img.shape[:2]
    if W0 * h > H0 * w:  # too wide: crop the width
        cw = int(round(H0 * w / h))
        x0 = (W0 - cw) // 2
        img = img[:, x0:x0 + cw]
    elif W0 * h < H0 * w:
        ch = int(round(W0 * h / w))
        y0 = (H0 - ch) // 2
        img = img[y0:y0 + ch]
    if tuple(img.shape[:2]) != (h, w):
        x = img.permute(2, 0, 1).unsqueeze(0).float()
        x = torch.nn.functional.interpolate(x, size=(h, w), mode="bilinear",
                                            align_corners=False, antialias=True)
        img = x.round().clamp(0, 255).to(torch.uint8)[0].permute(1, 2, 0)
    return img.contiguous()


class VideoPath:
    """Frames through a Tello-like camera path: jitter, then an H.264 round trip.

    Args:
        stream_size: ``(height, width)`` of the stream (default the Tello's
            720 x 960); frames must have this size.
        bitrate: the encoder's bit rate (bit/s; the emulator's default 1 Mbit/s).
        gop: frames between keyframes.
        exposure: ``(low, high)`` gain drawn per frame (1 = unchanged);
            ``None``: no exposure jitter.
        blur: ``(low, high)`` Gaussian blur sigma (px at the stream size) drawn
            per frame; ``None``: no blur.
        noise: ``(low, high)`` std of additive Gaussian sensor noise (grey
            levels) drawn per frame; ``None``: no noise.
        seed: seed of the jitter draws.

    Raises:
        ValueError: a bad size, bit rate, gop or jitter range, naming it.

    Example:
        >>> import numpy as np
        >>> vp = VideoPath(stream_size=(64, 64), exposure=None, blur=None, noise=None)
        >>> frames = [vp(np.full((64, 64, 3), v, np.uint8)) for v in (50, 210)]
        >>> [int(f.mean()) // 20 for f in frames], vp.frames
        ([2, 10], 2)
        >>> vp.close()
    """

    def __init__(self, stream_size=TELLO_STREAM_SIZE, *, bitrate: int = 1_000_000,
                 gop: int = 15, exposure=(0.75, 1.25), blur=(0.0, 1.0), noise=(0.0, 4.0),
                 seed: int = 0):
        if (not isinstance(stream_size, (tuple, list)) or len(stream_size) != 2
                or not all(isinstance(v, (int, np.integer)) and v >= 32 and v % 2 == 0
                           for v in stream_size)):
            raise ValueError(f"VideoPath: stream_size must be a (height, width) pair of even "
                             f"ints >= 32, got {stream_size!r}")
        if not isinstance(bitrate, (int, np.integer)) or bitrate < 10_000:
            raise ValueError(f"VideoPath: bitrate must be an int >= 10000, got {bitrate!r}")
        if not isinstance(gop, (int, np.integer)) or gop < 1:
            raise ValueError(f"VideoPath: gop must be an int >= 1, got {gop!r}")
        for name, rng, low in (("exposure", exposure, 0.05), ("blur", blur, 0.0),
                               ("noise", noise, 0.0)):
            if rng is None:
                continue
            try:
                lo, hi = (float(v) for v in rng)
            except (TypeError, ValueError):
                lo = hi = float("nan")
            if not (math.isfinite(lo) and math.isfinite(hi) and low <= lo <= hi):
                raise ValueError(f"VideoPath: {name} must be None or (low, high) with "
                                 f"{low} <= low <= high, got {rng!r}")
        self.stream_size = (int(stream_size[0]), int(stream_size[1]))
        self.bitrate, self.gop = int(bitrate), int(gop)
        self.exposure, self.blur, self.noise = exposure, blur, noise
        self._rng = np.random.default_rng(seed)
        self._enc = None
        self._dec = None
        self.frames = 0

    def _open(self):
        import av

        h, w = self.stream_size
        self._enc = open_h264_encoder(h, w, bitrate=self.bitrate, gop=self.gop)
        self._dec = av.CodecContext.create("h264", "r")

    def jitter(self, rgb: np.ndarray) -> np.ndarray:
        """Exposure, blur and sensor noise, drawn from this path's generator."""
        out = rgb.astype(np.float32)
        if self.exposure is not None:
            out *= self._rng.uniform(*self.exposure)
        if self.blur is not None:
            sigma = self._rng.uniform(*self.blur)
            if sigma > 0.05:
                import cv2

                out = cv2.GaussianBlur(out, (0, 0), sigmaX=float(sigma))
        if self.noise is not None:
            std = self._rng.uniform(*self.noise)
            if std > 0:
                out += self._rng.normal(0.0, std, size=out.shape).astype(np.float32)
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """One frame (uint8 ``[H, W, 3]`` at ``stream_size``) through the path."""
        rgb = np.asarray(rgb)
        if rgb.shape != (*self.stream_size, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"VideoPath: frames must be uint8 {(*self.stream_size, 3)}, got "
                             f"{rgb.dtype} {tuple(rgb.shape)}")
        if self._enc is None:
            self._open()
        frame = yuv420p_frame(self.jitter(rgb))
        frame.pts = self.frames
        decoded = None
        for packet in self._enc.encode(frame):
            for out in self._dec.decode(packet):
                decoded = out
        if decoded is None:  # the decoder holds it back: flush this one frame
            raise RuntimeError("VideoPath: the H.264 round trip returned no frame "
                               "(encoder or decoder delay)")
        self.frames += 1
        return decoded.to_ndarray(format="rgb24", threads=SWS_THREADS)

    def to_dict(self) -> dict:
        """The path's settings (for a dataset's ``meta.json``)."""
        return {"stream_size": list(self.stream_size), "bitrate": self.bitrate, "gop": self.gop,
                "exposure": self.exposure, "blur": self.blur, "noise": self.noise,
                "codec": "libx264", "x264": X264_OPTIONS(self.gop)}

    @classmethod
    def from_dict(cls, settings: dict, seed: int = 0) -> "VideoPath":
        """The path :meth:`to_dict` described (a dataset's ``meta.json``), with a new
        jitter generator seeded ``seed``.

        Raises:
            ValueError: settings of another codec, or bad values (named).
        """
        if not isinstance(settings, dict) or settings.get("codec", "libx264") != "libx264":
            raise ValueError(f"VideoPath.from_dict: expected the settings of a libx264 path "
                             f"(VideoPath.to_dict), got {settings!r}")
        keys = ("stream_size", "bitrate", "gop", "exposure", "blur", "noise")
        kw = {k: settings[k] for k in keys if k in settings}
        for k in ("stream_size", "exposure", "blur", "noise"):  # JSON lists back to pairs
            if isinstance(kw.get(k), list):
                kw[k] = tuple(kw[k])
        return cls(**kw, seed=seed)

    def close(self) -> None:
        """Frees the codec contexts (a later call opens new ones)."""
        self._enc = self._dec = None
