"""Package-level checks: metadata, citation, the README's two commands."""

from pathlib import Path

import pytest
import yaml

import torchrl_causal

ROOT = Path(__file__).resolve().parents[1]


def test_version_and_citation():
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0"
    assert cff["version"] == torchrl_causal.__version__
    thesis = cff["preferred-citation"]
    assert thesis["type"] == "thesis" and thesis["year"] == 2024
    assert "causal models in deep reinforcement learning" in thesis["title"]
    assert thesis["authors"][0]["family-names"] == "Xolo Tlapanco"
    assert "INAOE" in thesis["institution"]["name"]


def test_readme_opens_with_the_two_commands_and_makefile_has_them():
    readme = (ROOT / "README.md").read_text()
    head = readme[: readme.find("##", 10)] if "##" in readme[10:] else readme
    assert "make train" in head and "make test" in head
    makefile = (ROOT / "Makefile").read_text()
    for target in ("train:", "test:", "docs:"):
        assert target in makefile
    ci = (ROOT / ".ci" / "run").read_text()
    assert "make test" in ci


def test_make_protocol_runs_the_grid_in_order():
    """``make protocol``: the variants, the k sweep, then preset=thesis, each a resumable
    reproduce.py grid (printed by ``make -n``, nothing run)."""
    import shutil
    import subprocess

    if shutil.which("make") is None:
        pytest.skip("no make on this machine")
    out = subprocess.run(["make", "-n", "protocol", "VENV=.venv-dry", "PYTHON=true"],
                         cwd=ROOT, capture_output=True, text=True, check=True).stdout
    runs = [line for line in out.splitlines() if "recipes/reproduce.py" in line]
    assert len(runs) == 3
    assert "--groups variants" in runs[0] and "--seeds 5" in runs[0]
    assert "--groups k_sweep" in runs[1]
    assert "--seeds 2" in runs[2] and "outputs/reproduce_thesis" in runs[2]
    assert all("--launcher ray --jobs 2" in r for r in runs)
    tail = out[out.index(runs[2]):]
    assert "preset=thesis" in tail and "cbn_v2" in tail


def test_readme_torchrl_example_runs_as_printed(tmp_path):
    """The README's "In your own TorchRL code" block, run as printed on the real thesis
    scene, with only the budget shrunk (``LoopConfig(total_frames=20_000)`` ->
    300 frames, learning after 100, target sync every 10 updates) and the run folder
    moved under ``tmp_path``: it trains, relearns its CBN through the buffer hook,
    and writes its run folder."""
    import csv
    import re

    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", readme, re.S)
    assert len(blocks) == 1
    code = blocks[0]
    for old, new in (("LoopConfig(total_frames=20_000)",
                      "LoopConfig(total_frames=300, learning_starts=100, "
                      "target_update_interval=10)"),
                     ('output_dir="runs/v2"', f'output_dir={str(tmp_path / "v2")!r}')):
        assert code.count(old) == 1, old
        code = code.replace(old, new)
    scope: dict = {}
    exec(compile(code, "README.md", "exec"), scope)
    out = tmp_path / "v2"
    assert (out / "model.pt").is_file() and (out / "checkpoints").is_dir()
    episodes = list(csv.DictReader((out / "episodes.csv").open()))
    assert episodes and sum(int(r["length"]) for r in episodes) <= 300
    assert scope["hook"].learner.n_relearns >= 1  # k=200: the CBN was learned from the buffer
    assert len(list(csv.DictReader((out / "relearns.csv").open()))) >= 1
