"""Flight maps: top-down plots of evaluated episodes (matplotlib).

A map shows one layout from above: the geofence (flight volume), the obstacles
(boxes and cylinders, to scale and rotated), the goal board and its reach
sphere, the start, every greedy path coloured by its outcome (reached, crash,
timeout, geofence exit) and the shortest-path oracle's plan dashed. Feed it the
``episodes`` of :func:`~torchrl_causal.training.evaluate` with
``per_episode=True``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["OUTCOME_COLOURS", "outcome_of", "oracle_path", "plot_flight_map",
           "plot_flight_maps"]

#: Colour of a path by its episode's outcome.
OUTCOME_COLOURS = {"reached": "#1a9850", "crash": "#d73027", "timeout": "#fc8d59",
                   "geofence": "#7b3294"}


def outcome_of(episode: dict) -> str:
    """``"reached"``, ``"crash"``, ``"geofence"`` or ``"timeout"`` of an evaluated episode.

    Example:
        >>> outcome_of({"success": False, "crash": True, "out_of_bounds": False})
        'crash'
    """
    if episode.get("success"):
        return "reached"
    if episode.get("crash"):
        return "crash"
    if episode.get("out_of_bounds"):
        return "geofence"
    return "timeout"


def oracle_path(layout, plan, step_size: float = 0.25, turn_deg: float = 15.0) -> np.ndarray:
    """The ``(x, y)`` points the oracle's ``plan`` visits from the layout's start.

    Example:
        >>> from torchrl_causal.envs import thesis_layout
        >>> oracle_path(thesis_layout(), [0, 0])[-1].round(2).tolist()
        [0.5, 0.0]
    """
    from ..envs.control import action_deltas

    deltas = action_deltas(step_size, turn_deg)
    x, y, _ = layout.start_pos
    yaw = math.radians(layout.start_yaw_deg)
    pts = [(x, y)]
    for a in plan or []:
        fwd, left, _, dyaw = deltas[a]
        x += math.cos(yaw) * fwd - math.sin(yaw) * left
        y += math.sin(yaw) * fwd + math.cos(yaw) * left
        yaw += math.radians(dyaw)
        pts.append((x, y))
    return np.asarray(pts)


def _draw_layout(ax, layout, reach_radius: float):
    from matplotlib.patches import Circle, Polygon, Rectangle

    xmin, ymin, xmax, ymax = layout.arena
    ax.add_patch(Rectangle((xmin, ymin), xmax - xmin, ymax - ymin, fill=False, ls=":",
                           ec="0.4", lw=1.0, label="geofence"))
    for o in layout.obstacles:
        if o.shape == "cylinder":
            ax.add_patch(Circle(o.center[:2], o.half_size[0], fc=o.rgba[:3], ec="k", lw=0.5))
        else:
            c, s = math.cos(math.radians(o.yaw_deg)), math.sin(math.radians(o.yaw_deg))
            hx, hy = o.half_size[:2]
            corners = [(o.center[0] + c * dx - s * dy, o.center[1] + s * dx + c * dy)
                       for dx, dy in ((hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy))]
            ax.add_patch(Polygon(corners, fc=o.rgba[:3], ec="k", lw=0.5))
    board = layout.board_obstacle()
    c, s = math.cos(math.radians(board.yaw_deg)), math.sin(math.radians(board.yaw_deg))
    hy = board.half_size[1]
    bx, by = board.center[:2]
    ax.plot([bx - s * hy, bx + s * hy], [by + c * hy, by - c * hy], color="#2166ac", lw=4,
            solid_capstyle="butt", label="goal board")
    gp = layout.goal_point()
    ax.add_patch(Circle(gp[:2], reach_radius, fc="#92c5de", ec="#2166ac", alpha=0.6,
                        label="goal sphere"))
    sx, sy, _ = layout.start_pos
    ax.plot([sx], [sy], marker="^", color="k", ms=7, ls="", label="start")
    yaw = math.radians(layout.start_yaw_deg)
    ax.arrow(sx, sy, 0.35 * math.cos(yaw), 0.35 * math.sin(yaw), width=0.02, color="k")


def plot_flight_map(episodes, *, ax=None, title: str | None = None, path=None,
                    reach_radius: float = 0.2, oracle: bool = True):
    """Draws the episodes of one layout (the first episode's) from above.

    Args:
        episodes: episode dicts of ``evaluate(..., per_episode=True)`` (each with
            ``layout`` and ``path``); only those on the first one's layout are drawn.
        ax: a matplotlib axis (default: a new figure).
        title: the axis title (default: the layout's name and the outcomes).
        path: save the figure there (PNG) when given.
        reach_radius: the goal sphere's radius (m).
        oracle: draw the oracle's plan (``oracle_plan``) dashed.

    Returns:
        the axis.

    Raises:
        ValueError: no episode carries a ``layout`` and ``path``.

    Example:
        >>> from torchrl_causal.envs import DroneNavEnv, OraclePolicy
        >>> from torchrl_causal.training import evaluate
        >>> env = DroneNavEnv(image_size=32, seed=0)
        >>> res = evaluate(OraclePolicy(env), env, episodes=1, seed=0, per_episode=True)
        >>> ax = plot_flight_map(res["episodes"])
        >>> ax.get_title()
        'thesis: 1 reached'
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    eps = [e for e in episodes if e.get("layout") is not None and e.get("path")]
    if not eps:
        raise ValueError("plot_flight_map needs episodes with 'layout' and 'path' "
                         "(evaluate(..., per_episode=True) over a DroneNavEnv)")
    layout = eps[0]["layout"]
    eps = [e for e in eps if e["layout"] == layout]
    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(5.5, 5.5))
    _draw_layout(ax, layout, reach_radius)
    counts: dict[str, int] = {}
    for e in eps:
        kind = outcome_of(e)
        counts[kind] = counts.get(kind, 0) + 1
        xy = np.asarray([p[:2] for p in e["path"]])
        ax.plot(xy[:, 0], xy[:, 1], "-", color=OUTCOME_COLOURS[kind], lw=1.6, alpha=0.85,
                label=kind if counts[kind] == 1 else None)
        ax.plot(xy[-1, 0], xy[-1, 1], marker="x" if kind == "crash" else "o",
                color=OUTCOME_COLOURS[kind], ms=6)
    if oracle and eps[0].get("oracle_plan"):
        xy = oracle_path(layout, eps[0]["oracle_plan"])
        ax.plot(xy[:, 0], xy[:, 1], "--", color="k", lw=1.2, label="oracle")
    xmin, ymin, xmax, ymax = layout.arena
    ax.set_xlim(xmin - 0.3, xmax + 0.3)
    ax.set_ylim(ymin - 0.3, ymax + 0.3)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"{layout.name}: " + ", ".join(f"{n} {k}" for k, n in counts.items()))
    if fig is not None:
        ax.legend(loc="upper left", fontsize=7, framealpha=0.8)
        if path is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            fig.savefig(path, dpi=110, bbox_inches="tight")
        plt.close(fig)
    return ax


def plot_flight_maps(episodes, path, *, columns: int = 4, reach_radius: float = 0.2,
                     suptitle: str | None = None) -> Path:
    """A grid of flight maps, one per episode (e.g. a held-out evaluation), saved as PNG.

    Example:
        >>> import tempfile, pathlib
        >>> from torchrl_causal.envs import DroneNavEnv, OraclePolicy
        >>> from torchrl_causal.training import evaluate
        >>> env = DroneNavEnv("random", split="heldout", image_size=32, seed=0)
        >>> res = evaluate(OraclePolicy(env), env, episodes=2, seed=0, per_episode=True)
        >>> out = plot_flight_maps(res["episodes"], pathlib.Path(tempfile.mkdtemp()) / "m.png")
        >>> out.is_file()
        True
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    eps = [e for e in episodes if e.get("layout") is not None and e.get("path")]
    if not eps:
        raise ValueError("plot_flight_maps needs episodes with 'layout' and 'path'")
    n = len(eps)
    cols = min(columns, n)
    rows = int(math.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.6 * rows), squeeze=False)
    for ax, e in zip(axes.flat, eps):
        plot_flight_map([e], ax=ax, reach_radius=reach_radius,
                        title=f"{e['layout'].name}\n{outcome_of(e)}, {e['steps']} steps")
        ax.title.set_fontsize(8)
        ax.tick_params(labelsize=6)
        ax.set_xlabel("")
        ax.set_ylabel("")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=6, fontsize=8)
    if suptitle:
        fig.suptitle(suptitle)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path
