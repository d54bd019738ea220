"""The GPU path: ``device=cuda`` runs the Q-network, the replay buffer and the gate on the GPU
(the simulator stays on the CPU). Skipped where CUDA is absent (the CI machine)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


@pytest.mark.parametrize("variant", ["dqn_image", "cbn_v2"])
def test_train_on_cuda(variant, tmp_path):
    out = tmp_path / variant
    args = [
        "--config-name", variant, f"output_dir={out}", "device=cuda",
        "collector.total_frames=400", "loss.learning_starts=100",
        "loss.target_update_interval=20", "causal.k=100", "eval.interval_frames=200",
        "eval.episodes=1", "eval.final_episodes=1", "env.eval_layouts=[thesis]",
        "env.max_steps=50", "progress=false", "outputs.draw_cbns=false", "outputs.videos=0",
    ]
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    r = subprocess.run([sys.executable, str(ROOT / "recipes" / "train.py"), *args],
                       capture_output=True, text=True, env=env, timeout=600, cwd=ROOT)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 400 and summary["updates"] > 0
    assert "thesis" in summary["final_eval"]


def test_gate_accepts_bare_cuda_device():
    from torchrl_causal.modules import CBNGate
    from tensordict import TensorDict

    gate = CBNGate("v2", seed=0, device="cuda")
    td = TensorDict(action_value=torch.randn(4, 8, device="cuda"),
                    causal_state=torch.zeros(4, 9, dtype=torch.long, device="cuda"),
                    batch_size=[4])
    assert gate(td)["action"].device.type == "cuda"


def test_train_depth_on_cuda(tmp_path):
    """recipes/train_depth.py --device cuda: the network trains on the GPU, the weights
    are written from the CPU copy, and the held-out figures are computed on the CPU."""
    sys.path.insert(0, str(ROOT / "tests"))
    from _scripts import load_script
    from torchrl_causal.perception.dataset import write_datasets
    from torchrl_causal.perception.depth import MonoDepth

    data = tmp_path / "data"
    write_datasets(data, n_train=16, n_val=4, n_test=4, seed=0, image_size=(60, 80), progress=False)
    out = load_script("recipes/train_depth.py").main(
        ["--data", str(data), "--device", "cuda", "--epochs", "2", "--batch-size", "8",
         "--n-test-84", "0", "--reach-poses", "0", "--no-progress", "--out", str(tmp_path / "w.pt"),
         "--run-dir", str(tmp_path / "run")])
    est = MonoDepth.load(tmp_path / "w.pt")
    assert est.device.type == "cpu" and est.meta["device"] == "cuda"
    assert out["metrics"]["test_60x80"]["abs_rel"] > 0
