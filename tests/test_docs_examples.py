"""The user guide's examples run as doctests (the page is the test)."""

from __future__ import annotations

import doctest
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"


@pytest.mark.parametrize("page", ["training.rst"])
def test_docs_page_examples_run(page):
    import logging

    import torchrl  # noqa: F401  (configures its logger on import; set the level after)

    # torchrl's INFO lines (e.g. "Initialized LazyTensorStorage") go to stdout,
    # which doctest compares: keep them out of the page's expected output
    torchrl_logger = logging.getLogger("torchrl")
    level = torchrl_logger.level
    torchrl_logger.setLevel(logging.WARNING)
    try:
        result = doctest.testfile(str(DOCS / page), module_relative=False,
                                  optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    finally:
        torchrl_logger.setLevel(level)
    assert result.attempted > 10, f"{page}: only {result.attempted} examples found"
    assert result.failed == 0, f"{page}: {result.failed} of {result.attempted} examples failed"
