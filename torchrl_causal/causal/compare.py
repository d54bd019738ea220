"""Compare learned CBNs with the expert ones (thesis Table 5.1) and beyond.

* :func:`compare_dags`: edges in common / total edges (the format of Table 5.1),
  structural Hamming distance (SHD: edges to add, delete or reverse to turn
  one DAG into the other; a reversed edge counts once) and precision / recall
  of the reward's Markov blanket against the reference.
* :func:`table_5_1`: one row per action with the expert total, the first and
  last learned CBN's common/total edges and the best similarity
  ``max(common_first, common_last) / expert_total`` (the thesis's
  "percentage of best similarity"); :func:`write_table_5_1` writes it as
  Markdown and CSV.

Example:
    >>> from torchrl_causal.causal.compare import compare_dags
    >>> c = compare_dags([("a", "reward"), ("b", "c")], [("a", "reward"), ("c", "b"), ("d", "reward")])
    >>> c.common, c.n_learned, c.n_reference, c.shd
    (1, 2, 3, 2)
    >>> c.mb_precision, c.mb_recall
    (1.0, 0.5)
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping

from torchrl_causal.causal.inference import markov_blanket
from torchrl_causal.schema import REWARD_NODE

__all__ = ["GraphComparison", "compare_dags", "shd", "table_5_1", "write_table_5_1"]


@dataclass(frozen=True)
class GraphComparison:
    """Result of :func:`compare_dags`.

    Example:
        >>> GraphComparison(1, 2, 3, 2, 1.0, 0.5).similarity
        0.3333333333333333
    """

    common: int
    n_learned: int
    n_reference: int
    shd: int
    mb_precision: float
    mb_recall: float

    @property
    def similarity(self) -> float:
        """Common edges over the reference's total (Table 5.1's last column)."""
        return self.common / self.n_reference if self.n_reference else float("nan")


def shd(learned: Iterable[tuple[str, str]], reference: Iterable[tuple[str, str]]) -> int:
    """Structural Hamming distance between two DAGs given as edge lists.

    Example:
        >>> shd([("a", "b")], [("b", "a"), ("b", "c")])
        2
    """
    a, b = set(map(tuple, learned)), set(map(tuple, reference))
    skel_a = {frozenset(e) for e in a}
    skel_b = {frozenset(e) for e in b}
    missing_or_extra = len(skel_a ^ skel_b)
    reversed_ = sum(1 for e in a if e not in b and (e[1], e[0]) in b)
    return missing_or_extra + reversed_


def compare_dags(
    learned: Iterable[tuple[str, str]],
    reference: Iterable[tuple[str, str]],
    node: str = REWARD_NODE,
) -> GraphComparison:
    """Compare a learned DAG with a reference DAG.

    Args:
        learned: learned edges.
        reference: reference (e.g. expert) edges.
        node: node whose Markov blanket is compared (default the reward).

    Returns:
        :class:`GraphComparison`. Markov-blanket precision is 1.0 when the
        learned blanket is empty (nothing claimed), recall is 1.0 when the
        reference blanket is empty.

    Example:
        >>> c = compare_dags([("a_t", "a_t1"), ("a_t1", "reward")],
        ...                  [("a_t", "a_t1"), ("a_t", "reward")])
        >>> c.common, c.n_learned, c.n_reference, c.shd
        (1, 2, 2, 2)
    """
    a, b = set(map(tuple, learned)), set(map(tuple, reference))
    mb_a, mb_b = set(markov_blanket(a, node)), set(markov_blanket(b, node))
    hit = len(mb_a & mb_b)
    return GraphComparison(
        common=len(a & b),
        n_learned=len(a),
        n_reference=len(b),
        shd=shd(a, b),
        mb_precision=hit / len(mb_a) if mb_a else 1.0,
        mb_recall=hit / len(mb_b) if mb_b else 1.0,
    )


def table_5_1(
    expert: Mapping[str, list],
    first: Mapping[str, list],
    last: Mapping[str, list],
) -> list[dict]:
    """Rows of thesis Table 5.1, one per action of ``expert``.

    Args:
        expert: ``{action: edges}`` of the defined CBNs.
        first: ``{action: edges}`` of the first learned CBNs.
        last: ``{action: edges}`` of the last learned CBNs.

    Returns:
        list of dicts with keys ``action``, ``expert_edges``, ``first_common``,
        ``first_edges``, ``last_common``, ``last_edges``, ``best_similarity``,
        ``first_shd``, ``last_shd``, ``last_mb_precision``, ``last_mb_recall``.

    Example:
        >>> rows = table_5_1({"up": [("a", "b"), ("b", "c")]}, {"up": [("a", "b")]}, {"up": []})
        >>> rows[0]["first_common"], rows[0]["best_similarity"]
        (1, 0.5)
    """
    rows = []
    for action, ref in expert.items():
        c1 = compare_dags(first.get(action, []), ref)
        c2 = compare_dags(last.get(action, []), ref)
        rows.append(
            {
                "action": action,
                "expert_edges": c1.n_reference,
                "first_common": c1.common,
                "first_edges": c1.n_learned,
                "last_common": c2.common,
                "last_edges": c2.n_learned,
                "best_similarity": max(c1.common, c2.common) / c1.n_reference if c1.n_reference else float("nan"),
                "first_shd": c1.shd,
                "last_shd": c2.shd,
                "last_mb_precision": c2.mb_precision,
                "last_mb_recall": c2.mb_recall,
            }
        )
    return rows


def write_table_5_1(rows: list[dict], path: str | os.PathLike) -> tuple[Path, Path]:
    """Write :func:`table_5_1` rows as ``<path>.md`` and ``<path>.csv``.

    Args:
        rows: output of :func:`table_5_1`.
        path: file stem (a suffix, if any, is replaced).

    Returns:
        ``(markdown_path, csv_path)``.

    Example:
        >>> import tempfile, os
        >>> rows = table_5_1({"up": [("a", "b")]}, {"up": [("a", "b")]}, {"up": []})
        >>> md, _ = write_table_5_1(rows, os.path.join(tempfile.mkdtemp(), "table"))
        >>> md.read_text().splitlines()[2]
        '| up | 1 | 1/1 | 0/0 | 1.000 | 0 | 1 | 1.00 | 1.00 |'
    """
    if not rows:
        raise ValueError("rows must not be empty")
    stem = Path(path).with_suffix("")
    stem.parent.mkdir(parents=True, exist_ok=True)
    md, cv = stem.with_suffix(".md"), stem.with_suffix(".csv")
    header = (
        "| Action | Total edges given CBN | Common with first learned / total | "
        "Common with last learned / total | Best similarity | SHD first | SHD last | "
        "MB precision (last) | MB recall (last) |"
    )
    lines = [header, "|" + "---|" * 9]
    for r in rows:
        lines.append(
            f"| {r['action']} | {r['expert_edges']} | {r['first_common']}/{r['first_edges']} | "
            f"{r['last_common']}/{r['last_edges']} | {r['best_similarity']:.3f} | {r['first_shd']} | "
            f"{r['last_shd']} | {r['last_mb_precision']:.2f} | {r['last_mb_recall']:.2f} |"
        )
    md.write_text("\n".join(lines) + "\n")
    with open(cv, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return md, cv
