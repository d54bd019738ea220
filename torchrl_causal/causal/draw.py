"""Draw a per-action CBN like the thesis figures: t slice | t+1 slice | reward.

The ``t`` variables form the left column, the ``t+1`` variables the middle
column (same row per variable) and ``reward`` sits on the right, vertically
centred. Edges into the reward are drawn in a separate colour, and edges
from ``t`` straight to the reward are curved so they do not run through the
``t+1`` nodes. Draws on a pyplot-free matplotlib ``Figure`` (Agg renderer, bundled
DejaVu font: no font or network access, and the user's backend is untouched).

Example:
    >>> import tempfile, os
    >>> from torchrl_causal.causal.draw import draw_cbn
    >>> from torchrl_causal.causal.expert import expert_dags
    >>> path = os.path.join(tempfile.mkdtemp(), "ascend.png")
    >>> fig = draw_cbn(expert_dags()["ascend"], path=path, title="ascend")
    >>> os.path.getsize(path) > 0
    True
"""

from __future__ import annotations

import os
from typing import Iterable

from torchrl_causal.schema import DEFAULT_SCHEMA, REWARD_NODE, T1_SUFFIX, T_SUFFIX, VariableSchema

__all__ = ["draw_cbn", "node_positions"]


def node_positions(schema: VariableSchema = DEFAULT_SCHEMA) -> dict[str, tuple[float, float]]:
    """Layout: ``t`` at x=0, ``t+1`` at x=1, reward at x=2; variable ``i`` at y=-i.

    Example:
        >>> node_positions()["reward"]
        (2.0, -4.0)
    """
    pos = {}
    n = len(schema)
    for i, name in enumerate(schema.names):
        pos[name + T_SUFFIX] = (0.0, -float(i))
        pos[name + T1_SUFFIX] = (1.0, -float(i))
    pos[REWARD_NODE] = (2.0, -(n - 1) / 2.0)
    return pos


def draw_cbn(
    edges: Iterable[tuple[str, str]],
    schema: VariableSchema = DEFAULT_SCHEMA,
    *,
    path: str | os.PathLike | None = None,
    title: str | None = None,
    hide_isolated: bool = False,
    highlight: Iterable[tuple[str, str]] | None = None,
    ax=None,
    dpi: int = 120,
):
    """Draw a CBN and optionally save it as PNG.

    Args:
        edges: ``(source, target)`` node names.
        schema: the variable schema.
        path: PNG file to write (``None``: don't save).
        title: figure title.
        hide_isolated: leave out nodes without edges (the thesis omits variables
            an action does not change).
        highlight: edges drawn thick (e.g. those shared with the expert CBN).
        ax: matplotlib axes to draw on (a new figure if ``None``).
        dpi: resolution of the saved PNG.

    Returns:
        the matplotlib ``Figure``.

    Example:
        >>> import tempfile, os
        >>> from torchrl_causal.causal import expert_dags
        >>> png = os.path.join(tempfile.mkdtemp(), "forward.png")
        >>> fig = draw_cbn(expert_dags()["forward"], path=png, title="forward", hide_isolated=True)
        >>> os.path.getsize(png) > 0
        True
    """
    import networkx as nx
    from matplotlib.figure import Figure

    edges = [tuple(e) for e in edges]
    nodes = schema.node_names()
    bad = {n for e in edges for n in e} - set(nodes)
    if bad:
        raise ValueError(f"edges name nodes not in the schema: {sorted(bad)}")
    highlight = {tuple(e) for e in (highlight or ())}
    pos = node_positions(schema)
    shown = [n for n in nodes if not hide_isolated or any(n in e for e in edges) or n == REWARD_NODE]
    g = nx.DiGraph()
    g.add_nodes_from(shown)
    g.add_edges_from(edges)
    if ax is None:
        # a pyplot-free Figure renders with Agg and never touches the user's backend
        fig = Figure(figsize=(10, 0.6 * len(schema) + 1.5))
        ax = fig.add_subplot()
    else:
        fig = ax.figure
    fill = {"t": "#e9ecef", "t1": "#a8dadc", "reward": "#f4d35e"}

    def kind(n):
        return "reward" if n == REWARD_NODE else ("t1" if n.endswith(T1_SUFFIX) else "t")

    def label(n):
        if n == REWARD_NODE:
            return "reward"
        return n[: -len(T1_SUFFIX)] if n.endswith(T1_SUFFIX) else n[: -len(T_SUFFIX)]

    for k, color in fill.items():
        nx.draw_networkx_labels(
            g, pos, labels={n: label(n) for n in shown if kind(n) == k}, font_size=7, ax=ax,
            bbox=dict(boxstyle="round,pad=0.35", fc=color, ec="#333333", lw=0.8),
        )
    groups = {
        "slice": [e for e in edges if e[1] != REWARD_NODE],
        "to_reward_t1": [e for e in edges if e[1] == REWARD_NODE and e[0].endswith(T1_SUFFIX)],
        "to_reward_t": [e for e in edges if e[1] == REWARD_NODE and not e[0].endswith(T1_SUFFIX)],
    }
    style = {
        "slice": dict(edge_color="#1d3557", connectionstyle="arc3,rad=0.0"),
        "to_reward_t1": dict(edge_color="#e63946", connectionstyle="arc3,rad=0.0"),
        "to_reward_t": dict(edge_color="#e76f51", connectionstyle="arc3,rad=-0.25"),
    }
    for key, es in groups.items():
        if not es:
            continue
        widths = [2.6 if e in highlight else 1.2 for e in es]
        nx.draw_networkx_edges(g, pos, edgelist=es, width=widths, arrows=True, arrowsize=10,
                               min_source_margin=42, min_target_margin=42, ax=ax, **style[key])
    ax.text(0.0, 1.0, "t", ha="center", fontsize=11, fontweight="bold")
    ax.text(1.0, 1.0, "t+1", ha="center", fontsize=11, fontweight="bold")
    ax.set_xlim(-0.5, 2.5)
    ax.set_ylim(-len(schema) + 0.3, 1.5)
    ax.set_axis_off()
    if title:
        ax.set_title(f"{title} ({len(edges)} edges)", fontsize=11)
    fig.tight_layout()
    if path is not None:
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        fig.savefig(path, dpi=dpi)
    return fig
