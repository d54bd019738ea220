"""Print the goal board for a real Tello flight: ``python recipes/print_board.py --out DIR``.

Writes, for the thesis scene's board (1.0 m wide, 0.8 m high, heliport sign
stretched over it exactly as the simulator renders it --
:func:`torchrl_causal.envs.scene.board_face_image`):

* ``board.png`` -- the whole face at ``--dpi`` (its physical size in the PNG's
  metadata), for a print shop's poster printer;
* ``board_a4.pdf`` -- the same cut into A4 pages (portrait, 1 cm margins, each
  page labelled row/column with cut marks), for an office printer: tape the
  pages edge to edge on a 1.0 x 0.8 m board.

See docs/tello.rst, "Field guide". The last line printed is a JSON summary.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

A4_M = (0.210, 0.297)  # width, height (m)
MARGIN_M = 0.01


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--dpi", type=float, default=150.0, help="print resolution (50-600)")
    p.add_argument("--overwrite", action="store_true", help="replace existing files in --out")
    a = p.parse_args(argv)
    if not 50 <= a.dpi <= 600:
        p.error(f"--dpi must be in [50, 600], got {a.dpi}")
    files = [a.out / "board.png", a.out / "board_a4.pdf"]
    if any(f.exists() for f in files) and not a.overwrite:
        p.error(f"--out {a.out} already holds board files; pass --overwrite to replace them")
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.backends.backend_pdf import PdfPages
    from matplotlib.figure import Figure
    from PIL import Image

    from torchrl_causal.envs.layouts import thesis_layout
    from torchrl_causal.envs.scene import board_face_image

    layout = thesis_layout()
    ppm = a.dpi / 0.0254
    img = board_face_image(layout, pixels_per_m=ppm)
    a.out.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img).save(files[0], dpi=(a.dpi, a.dpi))
    w_m, h_m = layout.goal_size
    tile_w, tile_h = A4_M[0] - 2 * MARGIN_M, A4_M[1] - 2 * MARGIN_M
    cols, rows = math.ceil(w_m / tile_w), math.ceil(h_m / tile_h)
    H, W = img.shape[:2]
    with PdfPages(files[1]) as pdf:
        for r in range(rows):
            for c in range(cols):
                x0, y0 = int(round(c * tile_w * ppm)), int(round(r * tile_h * ppm))
                x1, y1 = min(W, int(round((c + 1) * tile_w * ppm))), \
                    min(H, int(round((r + 1) * tile_h * ppm)))
                piece = img[y0:y1, x0:x1]
                fig = Figure(figsize=(A4_M[0] / 0.0254, A4_M[1] / 0.0254))
                pw, ph = (x1 - x0) / ppm, (y1 - y0) / ppm  # the piece's size (m)
                ax = fig.add_axes((MARGIN_M / A4_M[0], 1 - (MARGIN_M + ph) / A4_M[1],
                                   pw / A4_M[0], ph / A4_M[1]))
                ax.imshow(piece, interpolation="nearest", aspect="auto")
                ax.set_xticks([])
                ax.set_yticks([])
                fig.text(0.5, 0.004, f"board {w_m:g} x {h_m:g} m -- row {r + 1}/{rows}, "
                         f"column {c + 1}/{cols} (from the top left); trim the margins",
                         ha="center", va="bottom", fontsize=7)
                pdf.savefig(fig)
    out = {"board_png": str(files[0]), "board_a4_pdf": str(files[1]), "pages": rows * cols,
           "size_m": [w_m, h_m], "dpi": a.dpi, "pixels": [W, H]}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
