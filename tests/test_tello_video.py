"""TelloFrameReader: a corrupt H.264 packet on real UDP ends djitellopy's reader but not ours."""

from __future__ import annotations

import os
import socket
import threading
import time

import av
import numpy as np
import pytest
import torch
from djitellopy.tello import BackgroundFrameRead

from torchrl_causal.envs.tello import TelloEnv
from torchrl_causal.envs.tello_emulator import TelloEmulator, free_udp_port
from torchrl_causal.envs.tello_video import TelloFrameReader

pytestmark = pytest.mark.timeout(120)

BAD_SLICE = b"\x00\x00\x00\x01\x41" + b"\xff" * 200  # a P slice of garbage: avcodec_send_packet rejects it


def _stream(port, n=240, bad_at=(120,), delay=0.3):
    """Sends ``n`` H.264 frames (a shade ramp, key frame every 5) to ``port``; garbage at ``bad_at``."""
    enc = av.CodecContext.create("libx264", "w")
    enc.width, enc.height, enc.pix_fmt = 64, 48, "yuv420p"
    enc.options = {"tune": "zerolatency", "preset": "ultrafast", "g": "5"}
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def run():
        time.sleep(delay)
        for i in range(n):
            img = np.full((48, 64, 3), (40 + i) % 256, np.uint8)
            data = b"".join(bytes(p) for p in enc.encode(av.VideoFrame.from_ndarray(img, format="rgb24")))
            sock.sendto(BAD_SLICE if i in bad_at else data, ("127.0.0.1", port))
            time.sleep(0.005)
        sock.close()

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


@pytest.mark.parametrize("reader_cls", [BackgroundFrameRead, TelloFrameReader])
def test_a_corrupt_packet_ends_djitellopys_reader_but_not_ours(reader_cls):
    port = free_udp_port("127.0.0.1")
    sender = _stream(port)
    errors = []
    hook, threading.excepthook = threading.excepthook, lambda a: errors.append(a.exc_value)
    try:
        reader = reader_cls(None, f"udp://@127.0.0.1:{port}")
        reader.start()
        sender.join()
        time.sleep(0.3)
        last = int(reader.frame[0, 0, 0])
        alive = reader.worker.is_alive()
        reader.stop()
    finally:
        threading.excepthook = hook
    # the ramp's last shade is (40 + 239) % 256 = 23 (H.264 rounds by a unit or two)
    if reader_cls is BackgroundFrameRead:  # the documented failure this module exists for
        assert not alive and any(isinstance(e, av.error.InvalidDataError) for e in errors)
        assert abs(last - 23) > 10  # frozen at a frame before the corrupt packet
    else:
        assert alive and not errors
        assert reader.decode_errors >= 1 and reader.decoded > 150
        assert abs(last - 23) <= 3


def test_open_installs_it_as_the_tellos_frame_read():
    from djitellopy import Tello

    from torchrl_causal.envs.tello_emulator import djitellopy_ports

    djitellopy_ports()
    port = free_udp_port("127.0.0.1")
    tello = Tello("127.0.0.1", vs_udp=port)
    sender = _stream(port, n=200, bad_at=())
    reader = TelloFrameReader.open(tello)
    sender.join()
    time.sleep(0.3)
    assert tello.get_frame_read() is reader and reader.decoded > 0
    reader.stop()
    with pytest.raises(ValueError, match="needs a tello or an address"):
        TelloFrameReader.open(None)


def test_telloenv_flies_on_through_corrupt_video_and_reopens_a_dead_stream():
    with TelloEmulator(fps=20, time_scale=20.0, video_size=(240, 320), battery_drain_per_min=0.0,
                       seed=3) as emu:
        env = TelloEnv(emu.client(), detector=emu.sim_detector(),
                       depth_estimator=emu.sim_depth_estimator(), command_timeout=1, takeoff_timeout=3,
                       retries=1, frame_timeout=3.0, before_takeoff=lambda _: emu.reset_world())
        try:
            td = env.reset()
            emu.faults.corrupt_video_prob = 0.5
            for _ in range(12):
                td = env.step(td.set("action", torch.tensor(6)))["next"]
                if bool(td["done"]):
                    td = env.reset()
            emu.faults.corrupt_video_prob = 0.0
            reader = env._frame_reader
            assert reader.alive and isinstance(reader, TelloFrameReader)
            # the stream ends under the env (as when the link drops): the next step reopens it
            reader.stop()
            reader.worker.join(timeout=5)
            assert not reader.alive
            td = env.step(td.set("action", torch.tensor(6)))["next"]
            assert env._frame_reader is not reader and env._frame_reader.alive
            assert td["pixels"].shape == (84, 84, 3)
            env.land()
            assert not emu.flying
        finally:
            env.close()


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork: POSIX only")
def test_a_process_forked_beside_a_live_reader_does_not_hang():
    """PyAV >= 17 converts frames on swscale worker threads kept in a thread-local; a process
    forked while the reader's thread runs (a ParallelEnv started beside a flight) frees that
    context in the child and hangs there, waiting on workers that were not forked (4 of 5
    forks hung with the default threads). The reader converts on one thread
    (``perception.video_path.SWS_THREADS``), so every fork exits."""
    port = free_udp_port("127.0.0.1")
    sender = _stream(port, n=2000, bad_at=(), delay=0.1)
    reader = TelloFrameReader(None, f"udp://@127.0.0.1:{port}")
    reader.start()
    try:
        deadline = time.time() + 10
        while reader.decoded < 50 and time.time() < deadline:
            time.sleep(0.05)
        assert reader.worker.is_alive() and reader.decoded >= 50
        hung = 0
        for _ in range(5):
            pid = os.fork()
            if pid == 0:  # the child: nothing but exit (the hang was in fork itself)
                os._exit(0)
            t0 = time.time()
            while time.time() - t0 < 5:
                if os.waitpid(pid, os.WNOHANG)[0]:
                    break
                time.sleep(0.02)
            else:
                hung += 1
                os.kill(pid, 9)
                os.waitpid(pid, 0)
        assert hung == 0
    finally:
        reader.stop()
        sender.join()
