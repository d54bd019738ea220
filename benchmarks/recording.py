"""Cost of recording: training frames/s with the run folder's videos on vs off.

``recipes/train.py`` records its videos (``outputs.videos``: the thesis scene and
held-out layouts, onboard camera beside a MuJoCo chase view, H.264 via PyAV)
*after* training, from evaluation episodes only; no training frame is rendered
for a video. This benchmark checks that on the training loop: the same recipe
and seed trained with ``outputs.videos=0`` and ``outputs.videos=N``, alternated
``--repeats`` times in one invocation (the machine's noise hits both), each run
in its own process with ``threads=1``.

Prints one JSON object per setting (``loop_frames_per_second`` per run and its
median, the recording's own seconds) and one ``ratio`` object: median frames/s
with recording over without (target of the issue "See it fly": within 2 %,
i.e. ``ratio >= 0.98``), and ``recording_seconds_per_loop_second``: what
the recording adds to a run's wall time, over its training loop's seconds
(it shrinks with longer runs: the videos cost the same few seconds).

::

    python benchmarks/recording.py                  # 2,000 frames, 2 repeats
    python benchmarks/recording.py --frames 4000 --repeats 3 --videos 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only

ROOT = Path(__file__).resolve().parents[1]


def run_once(out: Path, frames: int, videos: int, seed: int) -> dict:
    """One training run of ``recipes/train.py`` (thesis scene, default preset) in
    its own process; returns its ``summary.json``."""
    cmd = [sys.executable, str(ROOT / "recipes" / "train.py"), f"output_dir={out}",
           f"collector.total_frames={frames}", f"outputs.videos={videos}", f"seed={seed}",
           "threads=1", "progress=false", f"eval.interval_frames={frames}",
           "eval.episodes=2", "eval.final_episodes=5", "outputs.draw_cbns=false"]
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"training run failed ({' '.join(cmd)}):\n{proc.stderr[-3000:]}")
    return json.loads((out / "summary.json").read_text())


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=2000, help="training frames per run")
    p.add_argument("--repeats", type=int, default=2, help="runs per setting, alternated")
    p.add_argument("--videos", type=int, default=3, help="outputs.videos when recording is on")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if a.frames < 500:
        p.error(f"--frames must be >= 500, got {a.frames}")
    if a.repeats < 1:
        p.error(f"--repeats must be >= 1, got {a.repeats}")
    if a.videos < 1:
        p.error(f"--videos must be >= 1 (the 'on' setting), got {a.videos}")
    fps = {"off": [], "on": []}
    record_s, loop_s = [], []
    with tempfile.TemporaryDirectory(prefix="bench_recording_") as tmp:
        for r in range(a.repeats):
            for setting, videos in (("off", 0), ("on", a.videos)):
                s = run_once(Path(tmp) / f"{setting}{r}", a.frames, videos, a.seed)
                fps[setting].append(float(s["loop_frames_per_second"]))
                loop_s.append(float(s["loop_seconds"]))
                if videos:
                    assert "videos" in s, "outputs.videos > 0 but the run recorded no video"
                    record_s.append(sum(v["seconds"] for v in s["videos"].values()))
    rows = []
    for setting in ("off", "on"):
        row = {"bench": "recording", "setting": setting, "frames": a.frames,
               "videos": a.videos if setting == "on" else 0,
               "loop_frames_per_second": [round(v, 2) for v in fps[setting]],
               "median_frames_per_second": round(statistics.median(fps[setting]), 2)}
        if setting == "on":
            row["recording_seconds"] = [round(v, 1) for v in record_s]
        rows.append(row)
        print(json.dumps(row), flush=True)
    ratio = statistics.median(fps["on"]) / statistics.median(fps["off"])
    out = {"bench": "recording", "figure": "ratio", "ratio_on_over_off": round(ratio, 4),
           "within_2_percent": abs(1.0 - ratio) <= 0.02, "repeats": a.repeats,
           # what recording adds to a run: its seconds over the training loop's
           "recording_seconds_per_loop_second": round(
               statistics.median(record_s) / statistics.median(loop_s), 4)}
    print(json.dumps(out), flush=True)
    return out


if __name__ == "__main__":
    main()
