"""Package-level checks: metadata, citation, the README's two commands."""

from pathlib import Path

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
