"""VideoPath: frames through the Tello camera path (real libx264 / PyAV H.264), and the
perception datasets rendered through it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from torchrl_causal.perception.dataset import render_views, write_datasets
from torchrl_causal.perception.video_path import VideoPath, crop_resize


def test_round_trip_is_lossy_h264_of_the_same_picture():
    vp = VideoPath(stream_size=(96, 128), exposure=None, blur=None, noise=None)
    yy, xx = np.mgrid[0:96, 0:128]
    img = np.stack([xx * 2, yy * 2, (xx + yy)], -1).clip(0, 255).astype(np.uint8)
    outs = [vp(img) for _ in range(20)]  # one keyframe, then P-frames of a still scene
    errs = [np.abs(o.astype(int) - img.astype(int)).mean() for o in outs]
    assert all(0 < e < 6 for e in errs), errs  # lossy but close (smooth gradients)
    assert vp.frames == 20
    # a noise image is hard for 1 Mbit/s: visibly degraded
    noisy = np.random.default_rng(0).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    low = VideoPath(stream_size=(96, 128), bitrate=20_000, exposure=None, blur=None, noise=None)
    assert np.abs(low(noisy).astype(int) - noisy).mean() > 20
    vp.close()


def test_jitter_is_seeded_and_changes_exposure():
    a = VideoPath(stream_size=(64, 64), seed=3, blur=None, noise=None)
    b = VideoPath(stream_size=(64, 64), seed=3, blur=None, noise=None)
    img = np.full((64, 64, 3), 128, np.uint8)
    ja, jb = a.jitter(img), b.jitter(img)
    assert np.array_equal(ja, jb)
    means = [a.jitter(img).mean() for _ in range(30)]
    assert min(means) < 110 and max(means) > 146  # exposure 0.75-1.25


@pytest.mark.parametrize("kw,name", [
    ({"stream_size": (31, 64)}, "stream_size"), ({"bitrate": 5}, "bitrate"), ({"gop": 0}, "gop"),
    ({"exposure": (1.2, 0.8)}, "exposure"), ({"blur": (-1, 1)}, "blur"), ({"noise": "x"}, "noise"),
])
def test_bad_options_are_named(kw, name):
    with pytest.raises(ValueError, match=name):
        VideoPath(**kw)


def test_crop_resize_is_tello_envs_preprocessing():
    from torchrl_causal.envs.tello import TelloEnv

    frame = np.random.default_rng(1).integers(0, 256, (720, 960, 3), dtype=np.uint8)
    ours = crop_resize(frame, (84, 84))
    assert ours.shape == (84, 84, 3)
    # the centre 720x720 square, not the whole width
    assert abs(float(ours.float().mean()) - float(frame[:, 120:840].mean())) < 1.0
    assert TelloEnv.preprocess.__doc__ and "crop" in TelloEnv.preprocess.__doc__


def test_dataset_views_through_the_video_path_keep_exact_depth_and_boxes(tmp_path):
    plain = list(render_views("val", 4, seed=1, image_size=(84, 84)))
    vp = VideoPath(stream_size=(240, 320), seed=0)
    vid = list(render_views("val", 4, seed=1, image_size=(84, 84), video_path=vp))
    for a, b in zip(plain, vid):
        assert a.box == b.box and np.array_equal(a.depth, b.depth)  # exact labels
        diff = np.abs(a.rgb.astype(int) - b.rgb.astype(int)).mean()
        assert 0.3 < diff < 20  # the same picture, through a camera path
    assert vp.frames == 4
    with pytest.raises(ValueError, match="wider than the video stream"):
        list(render_views("val", 1, seed=1, image_size=(84, 200), video_path=vp))
    with pytest.raises(ValueError, match="video_path"):
        list(render_views("val", 1, seed=1, image_size=(84, 84), video_path="h264"))
    meta = write_datasets(tmp_path, n_train=2, n_val=1, n_test=0, seed=0, image_size=(84, 84),
                          progress=False, video_path=VideoPath(stream_size=(240, 320)))
    saved = json.loads((tmp_path / "meta.json").read_text())
    assert saved["view_options"]["video_path"]["codec"] == "libx264"
    assert meta["counts"]["train"] == 2
    # meta.json's settings rebuild the path (train_detector re-renders val views at 84 x 84
    # from them), and the same seed jitters the same way
    again = VideoPath.from_dict(saved["view_options"]["video_path"], seed=5)
    assert again.to_dict() == VideoPath(stream_size=(240, 320)).to_dict()
    img = np.full((240, 320, 3), 128, np.uint8)
    assert np.array_equal(again.jitter(img), VideoPath(stream_size=(240, 320), seed=5).jitter(img))
    with pytest.raises(ValueError, match="libx264"):
        VideoPath.from_dict({**saved["view_options"]["video_path"], "codec": "vp9"})
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recipes"))
    import train_detector

    views84 = train_detector._views84(tmp_path, "train", 2)
    assert len(views84) == 2 and views84[0].rgb.shape == (84, 84, 3)
