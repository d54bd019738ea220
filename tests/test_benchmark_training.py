"""benchmarks/training.py: bad options are named before any measurement."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import training as bench  # noqa: E402


@pytest.mark.parametrize("argv, message", [
    (["--device", "tpu"], "--device=tpu: expected cpu, cuda or cuda:N"),
    (["--frames", "100"], "--frames=100"),
    (["--ratios", "0"], "--ratios"),
    (["--envs", "1"], "--envs=1"),
])
def test_bad_options_are_named(argv, message, capsys):
    with pytest.raises(SystemExit):
        bench.main(argv)
    assert message in capsys.readouterr().err


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the machine without CUDA")
def test_cuda_without_cuda_is_named(capsys):
    with pytest.raises(SystemExit):
        bench.main(["--device", "cuda"])
    assert "--device=cuda: CUDA is not available" in capsys.readouterr().err
