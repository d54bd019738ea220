"""The arrival head read once, and read on each frame and its mirror image. One JSON
object per reading.

::

    python benchmarks/arrival_mirror.py [--data outputs/arrival_ask/frames.npz] \\
        [--weights torchrl_causal/perception/weights/arrival_view.pt] [--checks 0.05 0.1 0.15]

Measures, on the held-out test frames of ``make arrival-view-weights`` (900 frames of
held-out rooms with the printed board, rendered here with the same poses and seed, or the
test half of a ``train_arrival.py --data`` file), what ``TelloEnv(mirror_check=)`` changes:
the head read once (``"reading": "once"``), the mean of the frame's and its mirror image's
readings (``"mirror_mean"``), and that mean where the two sideways readings lie at most
``check`` m apart (``"mirror_check"``). Each object carries
:func:`train_arrival.evaluate`'s figures: offset errors on in-view frames, and for each
threshold how often the rule fires inside and outside the 0.2 m goal sphere. Added here:
``fire_near_miss``, how often the rule at 0.13 m fires on frames 0.2-0.45 m from the goal
point, where a false "reached" comes from.

Results: docs/tello.rst, "Asking the head twice".
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recipes"))


def near_miss(est, frames, labels, check):
    """Share of frames 0.2-0.45 m from the goal point (3-D) on which the 0.13 m rule fires."""
    import train_arrival

    true = np.sqrt((labels[:, :3] ** 2).sum(1))
    near = (true > 0.2) & (true <= 0.45)
    row = train_arrival.evaluate(est, frames[near], labels[near], thresholds=(0.13,),
                                 mirror_check=check)
    return round(row["rule"][0]["fire_outside"], 3), int(near.sum())


def main(argv=None) -> None:
    import train_arrival

    from torchrl_causal.perception.arrival import VIEW_WEIGHTS, GoalOffsetEstimator

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--weights", type=Path, default=VIEW_WEIGHTS)
    p.add_argument("--data", type=Path, default=None,
                   help="a train_arrival.py --data file (its test half); default: render "
                        "make arrival-view-weights' 900 test frames")
    p.add_argument("--test", type=int, default=900, help="frames to render without --data")
    p.add_argument("--checks", type=float, nargs="+", default=[0.05, 0.1, 0.15])
    p.add_argument("--in-view-share", type=float, default=0.05)
    a = p.parse_args(argv)
    for c in a.checks:
        if not 0.0 <= c <= 1.0:
            p.error(f"--checks must be distances in [0, 1] m, got {c:g}")
    if a.data is not None and not a.data.is_file():
        p.error(f"--data {a.data}: no such file")
    if a.test < 1:
        p.error(f"--test must be >= 1, got {a.test}")
    torch.set_num_threads(1)
    est = GoalOffsetEstimator.load(a.weights)
    if a.data is not None:
        d = np.load(a.data)
        x, y = d["xte"], d["yte"]
    else:  # make arrival-view-weights' test frames: seed 1 + 1000, held-out rooms
        x, y = train_arrival.render_mixture(a.test, 1001, 0.35, 80.0, lateral=1.2,
                                            ahead_max=1.0, layout="heldout",
                                            goal_size=(1.0, 0.8))
    for reading, check in [("once", None), ("mirror_mean", 1e9)] + [
            ("mirror_check", c) for c in a.checks]:
        fig = train_arrival.evaluate(est, x, y, in_view_share=a.in_view_share,
                                     mirror_check=check)
        share, n_near = near_miss(est, x, y, check)
        print(json.dumps({"figure": "arrival_mirror", "reading": reading,
                          "check_m": None if check in (None, 1e9) else check,
                          "weights": str(a.weights), "fire_near_miss": share,
                          "n_near_miss": n_near, **fig}), flush=True)


if __name__ == "__main__":
    main()
