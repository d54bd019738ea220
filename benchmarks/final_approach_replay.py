"""The final approach replayed on logged flights: where its ``go`` would have taken the drone.

::

    python benchmarks/final_approach_replay.py                 # the seed-102 logs, 0.4 m
    python benchmarks/final_approach_replay.py --radius 0.3 0.4 0.5

Reads the per-step logs of emulated flights that recorded, at every step, the
move, the arrival head's estimate ``(ahead, lateral, dz)`` and the emulator's true
offset and yaw in the board's frame (``docs/_static/results/tello/s102_*_steps.json``,
development seed 102, flown without the approach). It rebuilds each episode's
dead reckoning from the logged moves and yaws, feeds
:class:`~torchrl_causal.envs.FinalApproach` the head's estimates as ``TelloEnv``
does, and at every step where the approach would fly (the head's distance within
``--radius`` and beyond the rule's 0.15 m), applies the planned ``go`` to the
*true* pose with ``--move-noise`` (m, per axis, seeded). Prints one JSON object per
log and radius:

* ``approaches``: steps where a ``go`` would have been sent;
* ``pass_within_0_2``: the share whose straight move passed within 0.2 m of the
  goal point (the simulator's verdict for that step);
* ``end_within_0_2``: the share that ended within 0.2 m;
* ``heading_error_deg_median`` / ``_p90``: the fitted board heading against the truth,
  at every step with a fit.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only
ROOT = Path(__file__).resolve().parents[1]
LOGS = sorted((ROOT / "docs" / "_static" / "results" / "tello").glob("s102_*_steps.json"))


def _board(right: float, forward: float, yaw: float) -> np.ndarray:
    """A move in the camera's frame, in the board's frame, for the camera's yaw off the
    board's normal (rad; the logs' convention)."""
    fwd = np.array([-math.cos(yaw), -math.sin(yaw)])
    rgt = np.array([-math.sin(yaw), math.cos(yaw)])
    return forward * fwd + right * rgt


def _episodes(rows: list[dict]) -> list[list[dict]]:
    eps, cur = [], []
    for r in rows:
        if r["step"] == 0 and cur:
            eps.append(cur)
            cur = []
        cur.append(r)
    return eps + [cur] if cur else eps


def replay(rows: list[dict], radius: float, threshold: float, move_noise: float,
           seed: int) -> dict:
    from torchrl_causal.envs import FinalApproach

    rng = np.random.default_rng(seed)
    passed, ended, heading_err = [], [], []
    for ep in _episodes(rows):
        fa, world = FinalApproach(radius=radius), np.zeros(2)
        for i, r in enumerate(ep):
            if i:  # the logged move, dead-reckoned with the (IMU's) yaw before it
                right, forward, _ = ep[i]["move"]
                yaw = math.radians(ep[i - 1]["true"][3])
                c, s = math.cos(yaw), math.sin(yaw)
                world = world + np.array([c * forward + s * right, s * forward - c * right])
            if r["cur"] is None:
                continue
            est = np.asarray(r["cur"], float)
            fa.record(world, est[:2])
            yaw = math.radians(r["true"][3])
            alpha = fa.heading()
            if alpha is not None:  # the truth: odometry and board frames differ by pi
                heading_err.append(abs((alpha - math.pi + math.pi) % (2 * math.pi) - math.pi))
            go = fa.plan(est, yaw=yaw, threshold=threshold)
            if go is None:
                continue
            fwd, left, up = (v / 100.0 for v in go)
            noise = rng.normal(0.0, move_noise, 2)
            move = _board(-left + noise[1], fwd + noise[0], yaw)
            a = np.asarray(r["true"][:3], float)
            b = a + np.array([move[0], move[1], up])
            d = b - a
            t = float(np.clip(-(a @ d) / (d @ d), 0.0, 1.0))
            passed.append(float(np.linalg.norm(a + t * d)) <= 0.2)
            ended.append(float(np.linalg.norm(b)) <= 0.2)
    deg = np.degrees(heading_err) if heading_err else np.array([np.nan])
    return {"approaches": len(passed),
            "pass_within_0_2": round(float(np.mean(passed)), 3) if passed else None,
            "end_within_0_2": round(float(np.mean(ended)), 3) if ended else None,
            "heading_error_deg_median": round(float(np.median(deg)), 1),
            "heading_error_deg_p90": round(float(np.percentile(deg, 90)), 1)}


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--logs", nargs="+", type=Path, default=LOGS)
    p.add_argument("--radius", nargs="+", type=float, default=[0.4])
    p.add_argument("--threshold", type=float, default=0.15,
                   help="the rule's max_goal_offset: no approach within it (m)")
    p.add_argument("--move-noise", type=float, default=0.05,
                   help="per-axis Gaussian noise of the go (m), the emulator's")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if not a.logs:
        p.error("no step logs found: give --logs FILE ...")
    for f in a.logs:
        if not f.is_file():
            p.error(f"--logs {f}: no such file")
    out = []
    for f in a.logs:
        try:
            rows = json.loads(f.read_text())
        except ValueError:
            p.error(f"--logs {f}: not JSON")
        if not (isinstance(rows, list) and rows and {"move", "cur", "true"} <= set(rows[0])):
            p.error(f"--logs {f}: not a per-step log with move, cur and true")
        for r in a.radius:
            fig = {"bench": "final_approach_replay", "log": f.name, "radius_m": r,
                   **replay(rows, r, a.threshold, a.move_noise, a.seed)}
            print(json.dumps(fig), flush=True)
            out.append(fig)
    return out


if __name__ == "__main__":
    main()
