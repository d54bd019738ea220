"""benchmarks/depth_ambiguity.py: what one frame cannot tell about a near plain surface."""

import numpy as np
import pytest

from tests._scripts import load_script

amb = load_script("benchmarks/depth_ambiguity.py", "depth_ambiguity")


def test_best_constant_abs_rel_is_the_minimum_over_every_scale():
    rng = np.random.default_rng(0)
    d = np.exp(rng.uniform(np.log(0.25), np.log(1.0), size=40))
    w = rng.integers(100, 5000, size=40)
    a, floor = amb.best_constant_abs_rel(d, w)
    grid = np.linspace(0.1, 1.5, 20001)
    brute = min(float(np.sum(w * np.abs(g / d - 1)) / w.sum()) for g in grid)
    assert floor == pytest.approx(brute, abs=1e-4)
    assert floor <= brute + 1e-9  # an optimum at one of the d_i: no grid point beats it
    assert float(np.sum(w * np.abs(a / d - 1)) / w.sum()) == pytest.approx(floor)
    # one distance: an estimator that knows it is exact
    assert amb.best_constant_abs_rel([0.4, 0.4], [1, 3])[1] == 0.0


def test_a_plain_face_filling_the_view_looks_the_same_at_every_distance():
    """The scene's lights are directional and cast no shadow: moving the camera back along
    its axis scales the depth and leaves the image as it was (real MuJoCo renders)."""
    dist = (0.25, 0.5, 1.0)
    for turn in (0.0, 25.0):
        frames, depths = amb.twin_frames((0.6, 0.35, 0.2), turn, dist, image_size=(60, 80))
        assert frames.shape == (3, 60, 80, 3) and depths.shape == (3, 60, 80)
        assert int(np.abs(frames[1:].astype(int) - frames[0].astype(int)).max()) <= 1
        # ... while the depth doubles from one render to the next
        if turn == 0.0:  # square on: the centre pixel reads the camera's distance
            assert depths[:, 30, 40] == pytest.approx(np.array(dist), rel=0.02)
        assert np.allclose(np.median(depths[1:], axis=(1, 2)) / np.median(depths[:-1], axis=(1, 2)),
                           2.0, rtol=0.03)
