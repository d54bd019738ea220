"""``TelloFrameReader``: the Tello's video stream decoded in the background, surviving corrupt packets.

The Tello streams raw H.264 over UDP; over Wi-Fi some datagrams arrive damaged.
``djitellopy.tello.BackgroundFrameRead`` (what ``Tello.get_frame_read()`` returns)
decodes the stream with ``container.decode(video=0)`` in one loop, so the first
packet the decoder rejects (``av.error.InvalidDataError`` from
``avcodec_send_packet()``) ends its thread: ``frame`` then never changes again
and every later step times out waiting for a fresh frame, although the drone
keeps streaming. Measured against the
:class:`~torchrl_causal.envs.tello_emulator.TelloEmulator` with
``corrupt_video_prob=0.3``: the djitellopy reader died after 26 three-step
flights.

:class:`TelloFrameReader` is that reader with the decode loop made per packet:
a packet the decoder rejects is skipped and counted (:attr:`decode_errors`),
the next key frame repairs the picture, and the thread ends only when the
stream does (or :meth:`stop`). It is a drop-in ``BackgroundFrameRead``
(``frame``, ``frames``/``get_queued_frame`` with ``with_queue``, ``stop``) and
:meth:`open` installs it as the ``Tello``'s ``background_frame_read``, so
``tello.get_frame_read()`` returns it afterwards. ``TelloEnv`` uses it.

Example:
    >>> import socket, threading, time
    >>> import av, numpy as np
    >>> from torchrl_causal.envs.tello_emulator import free_udp_port
    >>> port = free_udp_port("127.0.0.1")
    >>> enc = av.CodecContext.create("libx264", "w")
    >>> enc.width, enc.height, enc.pix_fmt = 64, 48, "yuv420p"
    >>> enc.options = {"tune": "zerolatency", "preset": "ultrafast", "g": "5"}
    >>> def stream():
    ...     s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ...     for i in range(300):
    ...         img = np.full((48, 64, 3), i % 256, np.uint8)
    ...         data = b"".join(bytes(p) for p in enc.encode(av.VideoFrame.from_ndarray(img, format="rgb24")))
    ...         if i == 150:  # a slice of garbage, which the decoder rejects
    ...             data = b"\\x00\\x00\\x00\\x01\\x41" + b"\\xff" * 200
    ...         s.sendto(data, ("127.0.0.1", port)); time.sleep(0.005)
    >>> t = threading.Thread(target=stream); t.start()
    >>> reader = TelloFrameReader.open(None, f"udp://@127.0.0.1:{port}")
    >>> t.join(); time.sleep(0.2)
    >>> reader.alive, reader.decode_errors >= 1, reader.frame.shape
    (True, True, (48, 64, 3))
    >>> reader.stop()
"""

from __future__ import annotations

import logging

import av
from djitellopy import Tello
from djitellopy.tello import BackgroundFrameRead

from ..perception.video_path import SWS_THREADS

__all__ = ["TelloFrameReader"]

LOGGER = logging.getLogger("torchrl_causal.tello")


class TelloFrameReader(BackgroundFrameRead):
    """``djitellopy``'s background frame reader, decoding packet by packet so a corrupt one is skipped.

    Args:
        tello: the ``djitellopy.Tello`` whose stream this is.
        address: the stream's address (``tello.get_udp_video_address()``).
        with_queue: keep every decoded frame in ``frames`` (as djitellopy's).
        maxsize: the queue's length.

    Attributes:
        decode_errors: packets the decoder rejected and that were skipped.
        decoded: frames decoded so far.
        error: what ended the thread early (None while it runs or after :meth:`stop`).

    Example:
        >>> from djitellopy.tello import BackgroundFrameRead
        >>> issubclass(TelloFrameReader, BackgroundFrameRead)  # a drop-in for get_frame_read()'s
        True
        >>> TelloFrameReader.open(None)  # the module's example streams real H.264 over UDP
        Traceback (most recent call last):
        ...
        ValueError: TelloFrameReader.open needs a tello or an address
    """

    def __init__(self, tello: Tello | None, address: str, with_queue: bool = False, maxsize: int = 32):
        super().__init__(tello, address, with_queue, maxsize)
        self.decode_errors = 0
        self.decoded = 0
        self.error: BaseException | None = None

    @classmethod
    def open(cls, tello: Tello | None, address: str | None = None, **kwargs) -> "TelloFrameReader":
        """Opens the stream, starts the thread and installs the reader as ``tello.background_frame_read``.

        Args:
            tello: the drone (None: just the stream at ``address``).
            address: the stream (default: ``tello.get_udp_video_address()``).
            **kwargs: ``with_queue``, ``maxsize``.
        """
        if address is None:
            if tello is None:
                raise ValueError("TelloFrameReader.open needs a tello or an address")
            address = tello.get_udp_video_address()
        reader = cls(tello, address, **kwargs)
        reader.start()
        if tello is not None:
            tello.background_frame_read = reader
        return reader

    def _keep(self, frame) -> None:
        img = frame.to_ndarray(format="rgb24", threads=SWS_THREADS)
        if self.with_queue:
            self.frames.append(img)
        else:
            self.frame = img
        self.decoded += 1

    def update_frame(self) -> None:
        """The thread: demux, decode each packet, skip (and count) those the decoder rejects."""
        try:
            for packet in self.container.demux(video=0):
                if self.stopped:
                    break
                try:
                    frames = packet.decode()
                except av.error.InvalidDataError as e:
                    self.decode_errors += 1
                    LOGGER.debug("Tello video: skipped a corrupt packet (%s)", e)
                    continue
                for frame in frames:
                    self._keep(frame)
        except Exception as e:  # noqa: BLE001 - the stream ended (timeout, closed socket)
            if not self.stopped:
                self.error = e
                LOGGER.warning("Tello video: the stream ended: %r", e)
        finally:
            try:
                self.container.close()
            except Exception:  # noqa: BLE001
                pass

    @property
    def alive(self) -> bool:
        """Whether the decoding thread still runs."""
        return self.worker.is_alive()

