"""Synthetic perception datasets: boxes vs segmentation and projection, determinism, splits, files."""

from __future__ import annotations

import json
import math
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np
import pytest
import torch
import yaml

from torchrl_causal.envs.layouts import RandomLayoutGenerator
from torchrl_causal.envs.scene import build_model
from torchrl_causal.perception.dataset import (
    DEFAULT_MIN_FRACTION,
    box_iou,
    evaluate_detector,
    layout_indices,
    load_views,
    main,
    render_views,
    write_datasets,
)
from torchrl_causal.perception.goal import SimGoalDetector

FOV = 60.0


def _quat(yaw, pitch, roll):
    """yaw (z) * pitch (y) * roll (x), written out (independent of the module's helper)."""
    cy, sy = math.cos(math.radians(yaw) / 2), math.sin(math.radians(yaw) / 2)
    cp, sp = math.cos(math.radians(pitch) / 2), math.sin(math.radians(pitch) / 2)
    cr, sr = math.cos(math.radians(roll) / 2), math.sin(math.radians(roll) / 2)
    return np.array(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ]
    )


def _layout(view):
    gen = RandomLayoutGenerator("heldout" if view.split == "test" else "train", seed=0)
    return gen.layout(view.layout_index)


def _posed(view, image_size):
    model, ids = build_model(_layout(view), image_size=image_size, fov_deg=FOV)
    data = mujoco.MjData(model)
    x, y, z, yaw, pitch, roll = view.pose
    qa = ids.qpos_adr
    data.qpos[qa : qa + 3] = (x, y, z)
    data.qpos[qa + 3 : qa + 7] = _quat(yaw, pitch, roll)
    mujoco.mj_kinematics(model, data)
    mujoco.mj_camlight(model, data)  # camera poses
    return model, ids, data


@pytest.fixture(scope="module")
def views_240():
    return list(render_views("train", 16, seed=5, image_size=(240, 320)))


def test_boxes_equal_mujoco_renderer_segmentation(views_240):
    """Re-render each pose with mujoco.Renderer's segmentation: same box and pixel count."""
    h, w = 240, 320
    checked = 0
    for v in views_240:
        model, ids, data = _posed(v, (h, w))
        with mujoco.Renderer(model, h, w) as r:
            r.enable_segmentation_rendering()
            r.update_scene(data, camera=ids.camera)
            seg = r.render()
        mask = (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & np.isin(seg[..., 0], ids.goal_geoms)
        count = int(mask.sum())
        assert abs(count - v.goal_pixels) <= max(2, 0.01 * count), (v.index, count, v.goal_pixels)
        if count >= DEFAULT_MIN_FRACTION * h * w + 3:
            cols, rows = np.flatnonzero(mask.any(0)), np.flatnonzero(mask.any(1))
            ref = (cols[0], rows[0], cols[-1] + 1, rows[-1] + 1)
            assert v.box is not None
            np.testing.assert_allclose(v.box, ref, atol=1.0)
            checked += 1
        elif count < DEFAULT_MIN_FRACTION * h * w - 3:
            assert v.box is None
    assert checked >= 5


def test_boxes_match_projected_board_corners(views_240):
    """The segmentation box lies inside the projected board; unoccluded boards agree to ~1 px."""
    h, w = 240, 320
    focal = (h / 2) / math.tan(math.radians(FOV) / 2)
    tight = 0
    for v in views_240:
        if v.box is None:
            continue
        model, ids, data = _posed(v, (h, w))
        pos = data.cam_xpos[ids.camera]
        rot = data.cam_xmat[ids.camera].reshape(3, 3)
        pc = (ids.goal_corners - pos) @ rot  # camera frame: x right, y up, looking along -z
        if not (pc[:, 2] < -1e-3).all():  # board partly behind the camera: no simple box
            continue
        u = w / 2 + focal * pc[:, 0] / -pc[:, 2]
        vv = h / 2 - focal * pc[:, 1] / -pc[:, 2]
        proj = np.array([max(u.min(), 0), max(vv.min(), 0), min(u.max(), w), min(vv.max(), h)])
        x0, y0, x1, y1 = v.box
        assert x0 >= proj[0] - 1 and y0 >= proj[1] - 1 and x1 <= proj[2] + 1 and y1 <= proj[3] + 1
        # board area from the projected polygon's box: unoccluded views fill it
        if box_iou(np.array([v.box]), proj[None])[0, 0] > 0.9:
            np.testing.assert_allclose(v.box, proj, atol=1.5)
            tight += 1
    assert tight >= 3


def test_view_contents_and_mix():
    views = list(render_views("train", 40, seed=1, image_size=(60, 80), views_per_layout=8))
    kinds = {v.kind for v in views}
    assert kinds == {"goal", "start", "absent"}
    for v in views:
        assert v.rgb.shape == (60, 80, 3) and v.rgb.dtype == np.uint8
        assert v.depth.shape == (60, 80) and v.depth.dtype == np.float32
        assert 0 < v.depth.min() and v.depth.max() <= 10.0
        if v.box is not None:
            x0, y0, x1, y1 = v.box
            assert 0 <= x0 < x1 <= 80 and 0 <= y0 < y1 <= 60
            assert v.goal_pixels >= DEFAULT_MIN_FRACTION * 60 * 80
            assert (x1 - x0) * (y1 - y0) >= v.goal_pixels
        if v.kind == "absent":
            assert v.box is None
    n_pos = sum(v.box is not None for v in views)
    assert 0.4 * len(views) <= n_pos <= 0.9 * len(views)
    assert [v.layout_index for v in views[::8]] == layout_indices("train", 5)
    # the appearance is randomised between views of one layout
    first = [v.rgb.reshape(-1, 3).mean(0) for v in views[:8]]
    assert np.std(first, axis=0).max() > 1.0


def test_goal_distance_draws_close_ups():
    """``goal_distance`` sets how far "goal" views stand from the board (close-ups where the
    board fills the view), and leaves the default views as they were."""
    opts = dict(seed=5, image_size=48, goal_absent_frac=0.0, start_frac=0.0)
    close = list(render_views("train", 24, goal_distance=(0.3, 0.6), **opts))
    usual = list(render_views("train", 24, **opts))
    same = list(render_views("train", 24, goal_distance=(0.5, 9.0), **opts))

    def dist(v):
        g = _layout(v).goal_center
        return math.hypot(v.pose[0] - g[0], v.pose[1] - g[1])

    assert all(v.kind == "goal" for v in close)
    assert all(0.3 - 1e-9 <= dist(v) <= 0.6 + 1e-9 for v in close), [dist(v) for v in close]
    assert np.median([dist(v) for v in usual]) > 1.0
    for x, y in zip(usual, same):  # the default range is the historical one
        np.testing.assert_array_equal(x.rgb, y.rgb)
    # close up, the board covers much more of the image
    cover = lambda vs: np.mean([v.goal_pixels for v in vs if v.box is not None])  # noqa: E731
    assert cover(close) > 3 * cover(usual)


def test_obstacle_close_ups():
    """``obstacle_frac`` draws close-ups of obstacles (the detector's hard negatives): the
    nearest obstacle is within the asked range, it fills much of the view, and the default
    (0) leaves every other view as it was."""
    opts = dict(seed=7, image_size=(48, 64), goal_absent_frac=0.0)
    views = list(render_views("train", 24, obstacle_frac=1.0, obstacle_distance=(0.3, 0.8), **opts))
    assert {v.kind for v in views} == {"obstacle"}
    near = []
    for v in views:
        lay = _layout(v)
        d = min(float(o.footprint_distance(v.pose[0], v.pose[1])) for o in lay.obstacles)
        assert d <= 0.8 + 1e-6, (v.index, d)
        near.append(float(np.mean(v.depth < 1.5)))
    # looking at the obstacle: most views are mostly near pixels; the goal, when it shows
    # beside the obstacle, is a small part of the view
    assert np.median(near) > 0.4, near
    assert np.median([v.goal_pixels / (48 * 64) for v in views]) < 0.02
    # the usual views: the board is mostly far, the median view has few pixels within 1.5 m
    usual = list(render_views("train", 24, **opts))
    assert np.median([np.mean(v.depth < 1.5) for v in usual]) < np.median(near) / 2
    # obstacle_frac=0 is the historical mix, view for view
    same = list(render_views("train", 24, obstacle_frac=0.0, **opts))
    for x, y in zip(usual, same):
        np.testing.assert_array_equal(x.rgb, y.rgb)
    # a mix draws all four kinds
    mix = list(render_views("train", 40, seed=1, image_size=48, obstacle_frac=0.3))
    assert {v.kind for v in mix} == {"goal", "start", "absent", "obstacle"}


def test_obstacle_yaw_spread_puts_the_near_obstacle_at_the_image_side():
    """``obstacle_yaw_spread`` above 1 turns the close-ups' heading past the obstacle: its near
    pixels sit off the image's centre far more often (statistically, 32 views each), while
    the explicit default is the historical view, pixel for pixel."""
    opts = dict(seed=5, image_size=(48, 64), goal_absent_frac=0.0, obstacle_frac=1.0,
                obstacle_distance=(0.25, 0.6))
    ahead = list(render_views("train", 32, **opts))
    side = list(render_views("train", 32, obstacle_yaw_spread=1.6, **opts))
    same = list(render_views("train", 4, obstacle_yaw_spread=0.5, **opts))
    for x, y in zip(ahead, same):
        np.testing.assert_array_equal(x.rgb, y.rgb)

    def off_centre(v):  # the near pixels' mean column, 0 at the centre, 1 at an edge
        cols = np.nonzero(v.depth < 0.8)[1]
        return abs(cols.mean() / (v.depth.shape[1] / 2) - 1) if cols.size else 1.0

    a = np.array([off_centre(v) for v in ahead])
    b = np.array([off_centre(v) for v in side])
    assert np.median(b) > np.median(a) + 0.15, (np.median(a), np.median(b))
    assert np.mean(b > 0.5) > np.mean(a > 0.5) + 0.15


def test_deterministic_and_start_offset():
    a = list(render_views("val", 6, seed=3, image_size=48, views_per_layout=3))
    b = list(render_views("val", 6, seed=3, image_size=48, views_per_layout=3))
    c = list(render_views("val", 3, seed=3, image_size=48, views_per_layout=3, start=3))
    d = list(render_views("val", 6, seed=4, image_size=48, views_per_layout=3))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.rgb, y.rgb)
        np.testing.assert_array_equal(x.depth, y.depth)
        assert x.box == y.box and x.pose == y.pose
    for x, y in zip(a[3:], c):
        np.testing.assert_array_equal(x.rgb, y.rgb)
        assert (x.index, x.layout_index, x.box) == (y.index, y.layout_index, y.box)
    assert any(not np.array_equal(x.rgb, y.rgb) for x, y in zip(a, d))


def test_splits_are_disjoint():
    train, val = set(layout_indices("train", 400)), set(layout_indices("val", 100))
    assert not train & val and len(train) == 400 and len(val) == 100
    test_views = list(render_views("test", 2, seed=0, image_size=48, views_per_layout=1))
    gen = RandomLayoutGenerator("heldout", seed=0)
    train_fps = {RandomLayoutGenerator("train", seed=0).layout(i).fingerprint() for i in range(20)}
    for v in test_views:
        lay = gen.layout(v.layout_index)
        assert gen.split_of(lay) == "heldout" and lay.fingerprint() not in train_fps


def test_write_datasets_files(tmp_path):
    meta = main(
        ["--out", str(tmp_path), "--n-train", "5", "--n-val", "3", "--n-test", "4",
         "--seed", "2", "--image-size", "48", "64", "--views-per-layout", "2"]
    )
    assert meta["counts"] == {"train": 5, "val": 3, "test": 4}
    data = yaml.safe_load((tmp_path / "yolo" / "data.yaml").read_text())
    assert data["nc"] == 1 and data["names"] == ["heliport"] and "download" not in data
    for s in ("train", "val", "test"):
        assert os.path.isabs(data[s]) and os.path.isdir(data[s])
        imgs = sorted((tmp_path / "yolo" / "images" / s).glob("*.png"))
        labels = sorted((tmp_path / "yolo" / "labels" / s).glob("*.txt"))
        assert len(imgs) == len(labels) == meta["counts"][s]
        z = np.load(tmp_path / "depth" / f"{s}.npz")
        assert z["rgb"].dtype == np.uint8 and z["rgb"].shape == (meta["counts"][s], 48, 64, 3)
        assert z["depth"].dtype == np.float16 and z["layout"].dtype == np.int32
        views = load_views(tmp_path, s)
        import cv2

        for v, img, lab in zip(views, imgs, labels):
            np.testing.assert_array_equal(cv2.imread(str(img))[..., ::-1], v.rgb)
            text = lab.read_text().split()
            if v.box is None:
                assert text == []
            else:
                c, xc, yc, bw, bh = (float(t) for t in text)
                x0, y0, x1, y1 = v.box
                assert c == 0
                np.testing.assert_allclose(
                    [xc, yc, bw, bh],
                    [(x0 + x1) / 128, (y0 + y1) / 96, (x1 - x0) / 64, (y1 - y0) / 48],
                    atol=1e-5,
                )
    # the stored test split is the rendered one
    fresh = list(render_views("test", 4, seed=2, image_size=(48, 64), views_per_layout=2))
    stored = load_views(tmp_path, "test")
    for x, y in zip(fresh, stored):
        np.testing.assert_array_equal(x.rgb, y.rgb)
        np.testing.assert_allclose(x.depth, y.depth, rtol=1e-3, atol=1e-2)
        assert x.box == y.box
    stored_meta = json.loads((tmp_path / "meta.json").read_text())
    assert stored_meta["seed"] == 2
    # the command that made it, for the provenance of weights trained on it
    assert stored_meta["command"].startswith("python -m torchrl_causal.perception.dataset --out ")
    assert "--views-per-layout 2" in stored_meta["command"]


def test_evaluate_detector_ground_truth_is_perfect():
    views = list(render_views("test", 12, seed=0, image_size=(60, 80)))
    m = evaluate_detector(SimGoalDetector(min_pixels=math.ceil(DEFAULT_MIN_FRACTION * 60 * 80)), views)
    assert m["n_views"] == 12 and m["n_positives"] == sum(v.box is not None for v in views) > 0
    assert m["precision"] == 1.0 and m["recall"] == 1.0 and m["map50"] == pytest.approx(1.0, abs=0.01)
    assert m["image_accuracy"] == 1.0 and m["false_sight_rate"] == 0.0
    # a detector that always sees the goal everywhere: every view without a box is a false sight
    always = lambda px, depth, **kw: (  # noqa: E731
        torch.tensor([[0.0, 0.0, 80.0, 60.0]]).expand(len(px), 1, 4), torch.ones(len(px), 1))
    m = evaluate_detector(always, views)
    assert m["false_sight_rate"] == 1.0 and m["n_views"] > m["n_positives"]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(split="valid", n=1, seed=0), "split"),
        (dict(split="train", n=-1, seed=0), "n must"),
        (dict(split="train", n=1, seed=-2), "seed"),
        (dict(split="train", n=1, seed=0, image_size=(16, 64)), "image_size"),
        (dict(split="train", n=1, seed=0, goal_absent_frac=1.5), "goal_absent_frac"),
        (dict(split="train", n=1, seed=0, views_per_layout=0), "views_per_layout"),
        (dict(split="train", n=1, seed=0, fov_deg=200.0), "fov_deg"),
        (dict(split="train", n=1, seed=0, goal_distance=(2.0, 1.0)), "goal_distance"),
        (dict(split="train", n=1, seed=0, goal_distance=(0.0, 1.0)), "goal_distance"),
        (dict(split="train", n=1, seed=0, goal_distance="near"), "goal_distance"),
        (dict(split="train", n=1, seed=0, goal_size=(0.1, 0.8)), "goal_size"),
        (dict(split="train", n=1, seed=0, obstacle_frac=1.2), "obstacle_frac"),
        (dict(split="train", n=1, seed=0, obstacle_frac=0.9), "goal_absent_frac \\+ obstacle_frac"),
        (dict(split="train", n=1, seed=0, obstacle_frac=0.5, obstacle_distance=(0.1, 1.0)),
         "obstacle_distance"),
        (dict(split="train", n=1, seed=0, obstacle_yaw_spread=-0.1), "obstacle_yaw_spread"),
        (dict(split="train", n=1, seed=0, obstacle_yaw_spread="wide"), "obstacle_yaw_spread"),
    ],
)
def test_bad_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        render_views(**kwargs)


def test_write_datasets_bad_options(tmp_path):
    with pytest.raises(ValueError, match="n_train"):
        write_datasets(tmp_path, n_train=0, n_val=1, n_test=1, seed=0)
    with pytest.raises(ValueError, match="goal_absent_frac"):
        write_datasets(tmp_path, n_train=1, n_val=1, n_test=1, seed=0, goal_absent_frac=-0.1)
    with pytest.raises(FileNotFoundError, match="torchrl_causal.perception.dataset"):
        load_views(tmp_path, "test")
    assert not (tmp_path / "yolo").exists()
