"""Benchmarks print one JSON object per figure on stdout: TorchRL's log lines go to stderr."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = sorted(p.stem for p in (ROOT / "benchmarks").glob("*.py"))

# load a benchmark as a module (its top level runs, main() does not), then make
# TorchRL log an INFO line as a training run does (a replay buffer's first write)
PROBE = """
import os, runpy, sys
os.environ.pop("TORCHRL_CONSOLE_STREAM", None)
sys.path.insert(0, {bench_dir!r})
runpy.run_path({path!r}, run_name="benchmark_probe")
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
rb = TensorDictReplayBuffer(storage=LazyTensorStorage(4))
rb.extend(TensorDict(x=torch.zeros(2, 1), batch_size=[2]))
"""


# Every benchmark sets the stream with the same line before it imports TorchRL (the test
# below checks each file for it); these probes show that the line does its job, in
# benchmarks that import TorchRL through different paths (the loop, SB3's gym wrapper, the
# Tello emulator). One interpreter per probe: TorchRL reads the stream when first imported.
@pytest.mark.parametrize("name", ["training", "vs_sb3", "sim_to_real"])
def test_torchrl_log_lines_stay_off_stdout(name):
    assert name in BENCHMARKS
    path = ROOT / "benchmarks" / f"{name}.py"
    out = subprocess.run(
        [sys.executable, "-c", PROBE.format(bench_dir=str(path.parent), path=str(path))],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout == ""
    assert "Initialized LazyTensorStorage" in out.stderr


def test_every_benchmark_routes_torchrl_logs_to_stderr():
    """A benchmark added later must set the stream too, before it imports TorchRL."""
    for name in BENCHMARKS:
        text = (ROOT / "benchmarks" / f"{name}.py").read_text()
        line = 'os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")'
        assert line in text, name
        first_import = min((text.find(m) for m in ("import torch", "from torch", "import torchrl",
                                                    "from torchrl", "import tensordict",
                                                    "from tensordict") if m in text),
                           default=len(text))
        assert text.find(line) < first_import, name


def test_perception_camera_path_figures_include_obstacle_close_ups():
    """benchmarks/perception.py's camera-path figures: near, far and obstacle close-ups, plain
    and through the video path, at both sizes, each with the detector's false-sight rate; the
    obstacle views are hard negatives (few or no boards in them)."""
    import json

    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "perception.py"), "--skip",
                        "costs", "accuracy", "agreement", "flight", "--path-views", "3",
                        "--threads", "1"], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    figs = [json.loads(line) for line in r.stdout.splitlines()]
    det = [f for f in figs if f["figure"] == "detector_camera_path"]
    assert {(tuple(f["image_size"]), f["distance"], f["frames"]) for f in det} == {
        (size, d, p) for size in ((240, 320), (84, 84)) for d in ("near", "far", "obstacle")
        for p in ("plain", "video")}
    for f in det:
        assert f["n_views"] == 3 and "false_sight_rate" in f
        if f["distance"] == "far":  # every far view shows the board
            assert f["n_positives"] == 3 and f["false_sight_rate"] is None
        if f["distance"] == "obstacle":
            assert f["n_positives"] < 3 and 0.0 <= f["false_sight_rate"] <= 1.0
    assert sum(f["figure"] == "depth_camera_path" for f in figs) == len(det)
