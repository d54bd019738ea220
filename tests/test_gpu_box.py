"""benchmarks/gpu_box.sh's grid stage on this machine's CPUs (``STAGES=4 GRID_DEVICE=cpu``):
parts launched side by side into one root, the finished runs packed as records, and a root
seeded from finished runs' records (``GRID_RECORDS``) that trains nothing twice."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tarfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TINY = ("--mode reduced --groups variants --seeds 1 --jobs 1 --frames 400 -- env.max_steps=30 "
        "eval.final_episodes=1 outputs.draw_cbns=false loss.target_update_interval=20")


def _box(out: Path, root: Path, parts: str, records: Path | None = None):
    env = dict(os.environ, STAGES="4", GRID_DEVICE="cpu", GRID_ROOT=str(root),
               PYTHON=sys.executable, GRID_PARTS=parts,
               MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    if records is not None:
        env["GRID_RECORDS"] = str(records)
    r = subprocess.run(["bash", str(ROOT / "benchmarks" / "gpu_box.sh"), str(out), "400"],
                       capture_output=True, text=True, env=env, cwd=ROOT, timeout=400)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return json.loads((out / "protocol.json").read_text()), r.stdout


def test_grid_parts_side_by_side_and_seeded_records(tmp_path):
    # another grid's processes on the same machine (named as joblib's workers and the
    # recipe are): the box's clean-up stops its own process groups only
    bystanders = [subprocess.Popen(["bash", "-c", f"exec -a '{name}' sleep 300"])
                  for name in ("python -m joblib.externals.loky.backend.popen_loky_posix",
                               "python recipes/train.py -m")]
    parts = ";".join(f"--variants {v} {TINY}" for v in ("dqn_features_v2eps", "dqn_features"))
    try:
        first, log = _box(tmp_path / "out1", tmp_path / "root1", parts)
        assert all(b.poll() is None for b in bystanders), "the clean-up killed other jobs"
    finally:
        for b in bystanders:
            b.kill()
    assert "2 runs finished" in log and "on 2 cpu jobs" in log
    assert first["rc"] == 0 and first["jobs"] == 2 and first["started"] == []
    assert sorted(r["run"] for r in first["runs"]) == [
        "variants/dqn_features/seed_0", "variants/dqn_features_v2eps/seed_0"]
    assert all(r["frames"] == 400 for r in first["runs"])
    with tarfile.open(tmp_path / "out1" / "grid.tgz") as tar:
        names = tar.getnames()
    assert any(n.endswith("dqn_features/seed_0/summary.json") for n in names)
    assert any(n.endswith("seed_0/config.yaml") for n in names)
    assert not any(n.endswith((".pt", ".png")) or "/checkpoints" in n for n in names)

    # the finished runs' records seed a fresh root: nothing is trained again, and the
    # copied records are not counted as runs of this box
    second, log = _box(tmp_path / "out2", tmp_path / "root2",
                       f"--variants dqn_features_v2eps {TINY}", records=tmp_path / "root1")
    assert second["rc"] == 0 and second["runs"] == [] and "0 runs finished" in log
    assert (tmp_path / "root2" / "variants" / "dqn_features_v2eps" / "seed_0"
            / "summary.json").is_file()
    assert not (tmp_path / "out2" / "grid.tgz").exists()
