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


_ADORNMENT = set("=-^~\"'`#*+:.")


def _short_title_underlines(text: str) -> list[tuple[int, str]]:
    """(line number, title) for each section title whose underline is shorter than it,
    the warning ``make docs`` (``sphinx -W``) turns into a failed build."""
    lines = text.splitlines()
    short = []
    for i in range(1, len(lines)):
        line, title = lines[i], lines[i - 1]
        if (len(line) >= 4 and len(set(line)) == 1 and line[0] in _ADORNMENT
                and title.strip() and not title[0].isspace() and len(set(title)) > 1
                and (i == 1 or not lines[i - 2].strip() or set(lines[i - 2]) == set(line))
                and len(title) > len(line)):
            short.append((i, title))
    return short


def test_short_title_underlines_are_found():
    """The check finds an underline two characters short (as one was on 2026-12-03) and
    passes titles underlined to their length, overlined ones and table borders."""
    bad = "Intro\n\nA title of twenty-one\n^^^^^^^^^^^^^^^^^^^\n\ntext\n"
    assert _short_title_underlines(bad) == [(3, "A title of twenty-one")]
    good = ("=====\nTop\n=====\n\nA title\n-------\n\n=====  =====\n a      b\n=====  =====\n")
    assert _short_title_underlines(good) == []


@pytest.mark.parametrize("page", sorted(p.name for p in DOCS.glob("*.rst")))
def test_docs_page_titles_are_underlined_to_their_length(page):
    """Caught here, in ``make test``, before the docs build fails on it."""
    assert _short_title_underlines((DOCS / page).read_text()) == []
