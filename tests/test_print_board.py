"""recipes/print_board.py: the goal board at its true size, as the simulator renders it."""

from __future__ import annotations

import re

import numpy as np
import pytest
from PIL import Image

from torchrl_causal.envs.scene import board_face_image, helipad_image
from _scripts import load_script


def _recipe():
    return load_script("recipes/print_board.py")


def test_board_png_has_true_size_and_a4_pages_cover_it(tmp_path):
    out = _recipe().main(["--out", str(tmp_path), "--dpi", "50"])
    im = Image.open(tmp_path / "board.png")
    dpi = im.info["dpi"][0]
    w_in, h_in = im.size[0] / dpi, im.size[1] / dpi
    assert abs(w_in * 0.0254 - 1.0) < 0.005 and abs(h_in * 0.0254 - 0.8) < 0.005
    pdf = (tmp_path / "board_a4.pdf").read_bytes()
    pages = len(re.findall(rb"/Type\s*/Page[^s]", pdf))
    assert pages == out["pages"] == 18  # 6 columns x 3 rows of 0.19 x 0.277 m
    # the sign's colours, as the scene's texture: blue ground, white ring and "H"
    arr = np.asarray(im)
    colours = {tuple(c) for c in arr.reshape(-1, 3)[:: 997]}
    assert colours <= {tuple(c) for c in helipad_image(64).reshape(-1, 3)}
    with pytest.raises(SystemExit):  # refuses to overwrite without --overwrite
        _recipe().main(["--out", str(tmp_path), "--dpi", "50"])


def test_bad_resolution_is_named():
    with pytest.raises(ValueError, match="pixels_per_m"):
        board_face_image(pixels_per_m=1)
    with pytest.raises(SystemExit):
        _recipe().main(["--out", "/tmp/never", "--dpi", "5"])
