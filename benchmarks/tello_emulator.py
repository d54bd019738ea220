"""Tello emulator figures: command round trip, video latency and frame rate (JSON lines).

::

    python benchmarks/tello_emulator.py            # all figures
    python benchmarks/tello_emulator.py --seconds 3

Prints one JSON object per figure:

* ``command_rtt_ms`` -- ``battery?`` over a raw UDP socket (median, p95), and
  through djitellopy (whose reply loop polls every 0.1 s);
* ``video_latency_ms`` -- from the end of the render of a frame to the same
  frame decoded by PyAV from the received datagrams (median, p95), at
  320x240 and 960x720;
* ``video_fps`` -- frames decoded per second with the emulator asked for 30 fps,
  at 320x240 and 960x720.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import time

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only

import av  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchrl_causal.envs.tello_emulator import DATAGRAM_SIZE, TelloEmulator  # noqa: E402


def _pct(values, q):
    return float(np.percentile(np.asarray(values), q))


def command_rtt(n: int = 200) -> list[dict]:
    out = []
    with TelloEmulator(fps=1.0) as emu:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.settimeout(2.0)
        s.sendto(b"command", emu.address)
        s.recvfrom(64)
        ms = []
        for _ in range(n):
            t0 = time.perf_counter()
            s.sendto(b"battery?", emu.address)
            s.recvfrom(64)
            ms.append(1e3 * (time.perf_counter() - t0))
        s.close()
        out.append({"figure": "command_rtt_ms", "client": "raw_udp", "n": n,
                    "median": round(statistics.median(ms), 3), "p95": round(_pct(ms, 95), 3)})
        tello = emu.client()
        tello.connect()
        ms = []
        for _ in range(max(10, n // 10)):
            t0 = time.perf_counter()
            tello.query_battery()
            ms.append(1e3 * (time.perf_counter() - t0))
        out.append({"figure": "command_rtt_ms", "client": "djitellopy", "n": len(ms),
                    "median": round(statistics.median(ms), 3), "p95": round(_pct(ms, 95), 3)})
    return out


def video(height: int, width: int, seconds: float) -> list[dict]:
    """Receives, reassembles (a datagram shorter than 1460 bytes ends a frame) and decodes."""
    with TelloEmulator(fps=30.0, video_size=(height, width)) as emu:
        rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        rx.bind(("127.0.0.1", 0))
        rx.settimeout(1.0)
        emu.set_client_ports(video_port=rx.getsockname()[1])
        ctl = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        ctl.bind(("127.0.0.1", 0))
        ctl.settimeout(2.0)
        for cmd in (b"command", b"streamon"):
            ctl.sendto(cmd, emu.address)
            ctl.recvfrom(64)
        dec = av.CodecContext.create("h264", "r")
        first = emu.frames_sent
        buf = bytearray()
        decoded = []  # (wall time of decode, ...)
        t_end = time.perf_counter() + seconds
        while time.perf_counter() < t_end:
            try:
                d = rx.recv(4096)
            except socket.timeout:
                continue
            buf += d
            if len(d) < DATAGRAM_SIZE:
                for p in dec.parse(bytes(buf)):
                    for _ in dec.decode(p):
                        decoded.append(time.perf_counter())
                buf.clear()
        ctl.sendto(b"streamoff", emu.address)
        times = dict(emu.frame_times)
        ctl.close()
        rx.close()
    # the k-th decoded frame is frame first + k (loopback loses nothing; counted below)
    lat = [1e3 * (t - times[first + k]) for k, t in enumerate(decoded) if first + k in times]
    span = decoded[-1] - decoded[0] if len(decoded) > 1 else float("nan")
    size = f"{width}x{height}"
    return [
        {"figure": "video_latency_ms", "size": size, "n": len(lat),
         "median": round(statistics.median(lat), 2), "p95": round(_pct(lat, 95), 2)},
        {"figure": "video_fps", "size": size, "requested": 30.0,
         "decoded_fps": round((len(decoded) - 1) / span, 2), "frames_decoded": len(decoded),
         "frames_sent": len(times) - first},
    ]


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seconds", type=float, default=5.0, help="video measurement per size")
    p.add_argument("--commands", type=int, default=200)
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    for row in command_rtt(a.commands):
        print(json.dumps(row), flush=True)
    for h, w in ((240, 320), (720, 960)):
        for row in video(h, w, a.seconds):
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
