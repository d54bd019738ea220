"""Plots and tables from run folders (thesis Fig. 5.3 / 5.4 and Table 5.1).

Everything here reads the files a run writes (``episodes.csv``,
``relearns.csv``, ``config.yaml``) so figures can be redrawn from finished runs
without re-training:

* :func:`moving_average` -- the thesis's smoothing (window 20 in Fig. 5.3,
  50 in Fig. 5.4); the first ``window - 1`` episodes average what exists.
* :func:`plot_reward_curves` -- one line per group (variant or k); with
  three seeds or more, the mean of the smoothed curves and a band of the 95 %
  confidence interval of that mean (Student t over seeds).
* :func:`mean_ci_text` / :func:`welch_diff_ci95` -- a mean with its 95 %
  t-interval, and a difference of two means with its 95 % Welch interval (the
  protocol's tables and its measured ordering).
* :func:`summary_markdown` -- a plain Markdown table (Table 5.1 itself comes
  from :func:`torchrl_causal.causal.table_5_1`).
* :func:`load_runs` -- finds run folders under a root and labels them.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import yaml  # noqa: E402

__all__ = [
    "moving_average",
    "mean_ci95",
    "wilson",
    "mean_ci_text",
    "welch_diff_ci95",
    "load_episodes",
    "load_runs",
    "stack_curves",
    "plot_reward_curves",
    "plot_run",
    "summary_markdown",
]


def moving_average(x: Sequence[float], window: int) -> np.ndarray:
    """Trailing moving average; the first values average the episodes seen so far."""
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window!r}")
    return pd.Series(np.asarray(x, dtype=float)).rolling(window, min_periods=1).mean().to_numpy()


def load_episodes(run_dir: str | Path) -> pd.DataFrame:
    """The per-episode CSV of a run folder."""
    return pd.read_csv(Path(run_dir) / "episodes.csv")


def _read_config(run_dir: Path) -> dict:
    path = run_dir / "config.yaml"
    return yaml.safe_load(path.read_text()) if path.exists() else {}


def load_runs(root: str | Path) -> list[dict]:
    """Every run folder (one holding ``episodes.csv`` and ``config.yaml``) under ``root``.

    Returns:
        A list of ``{"dir", "variant", "seed", "k", "episodes", "relearns"}``
        dicts, sorted by folder name.
    """
    runs = []
    for csv_path in sorted(Path(root).rglob("episodes.csv")):
        run_dir = csv_path.parent
        cfg = _read_config(run_dir)
        if not cfg:
            continue
        rel_path = run_dir / "relearns.csv"
        relearns = pd.read_csv(rel_path) if rel_path.exists() else pd.DataFrame()
        runs.append(
            {
                "dir": run_dir,
                "variant": cfg.get("variant"),
                "seed": cfg.get("seed"),
                "k": (cfg.get("causal") or {}).get("k"),
                "episodes": pd.read_csv(csv_path),
                "relearns": relearns,
            }
        )
    return runs


def stack_curves(curves: Sequence[Sequence[float]]) -> np.ndarray:
    """Stacks curves of different lengths into ``[n, max_len]``, padding with NaN."""
    n = max((len(c) for c in curves), default=0)
    out = np.full((len(curves), n), np.nan)
    for i, c in enumerate(curves):
        out[i, : len(c)] = c
    return out


def mean_ci95(curves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column mean over seeds (rows, NaN = missing) and the half-width of its 95 %
    confidence interval (Student t with n - 1 dof; NaN where fewer than 2 seeds)."""
    from scipy import stats

    n = np.sum(~np.isnan(curves), axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.nanmean(curves, axis=0)
        sd = np.nanstd(curves, axis=0, ddof=1) if curves.shape[0] > 1 else np.full_like(mean, np.nan)
        half = stats.t.ppf(0.975, np.maximum(n - 1, 1)) * sd / np.sqrt(np.maximum(n, 1))
    half[n < 2] = np.nan
    return mean, half


def mean_ci_text(values: Sequence[float], digits: int = 2) -> str:
    """``"mean +- h"``, ``h`` the half-width of the 95 % Student-t interval of the mean
    over ``values`` (NaNs dropped); the mean alone for one value, ``"nan"`` for none.

    Example:
        >>> mean_ci_text([0.8, 1.0, 0.9])
        '0.90 +- 0.25'
    """
    v = np.asarray([x for x in values if not math.isnan(float(x))], dtype=float)
    if len(v) == 0:
        return "nan"
    if len(v) == 1:
        return f"{v[0]:.{digits}f}"
    mean, half = mean_ci95(v[:, None])
    return f"{mean[0]:.{digits}f} +- {half[0]:.{digits}f}"


def welch_diff_ci95(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float]:
    """Difference of means ``mean(a) - mean(b)`` and its 95 % Welch interval (unequal
    variances, Welch-Satterthwaite degrees of freedom); NaN bounds with fewer than two
    values on a side. Two constant samples give a zero-width interval.

    Example:
        >>> [round(x, 3) for x in welch_diff_ci95([1.0, 1.0, 0.9], [0.0, 0.2, 0.1])]
        [0.867, 0.662, 1.072]
    """
    from scipy import stats

    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    diff = float(a.mean() - b.mean()) if len(a) and len(b) else float("nan")
    if len(a) < 2 or len(b) < 2:
        return diff, float("nan"), float("nan")
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    se = math.sqrt(va + vb)
    if se == 0.0:
        return diff, diff, diff
    dof = (va + vb) ** 2 / (va ** 2 / (len(a) - 1) + vb ** 2 / (len(b) - 1))
    half = float(stats.t.ppf(0.975, dof)) * se
    return diff, diff - half, diff + half


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a success rate (sensible at 0 and 1, unlike Wald).

    Example:
        >>> [round(v, 3) for v in wilson(10, 10)]
        [0.722, 1.0]
    """
    if n == 0:
        return (float("nan"), float("nan"))
    p = successes / n
    den = 1 + z * z / n
    c = (p + z * z / (2 * n)) / den
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, c - h), min(1.0, c + h))


def plot_reward_curves(
    groups: Mapping[str, Sequence[Sequence[float]]],
    window: int,
    path: str | Path,
    *,
    title: str = "",
    vlines: Mapping[str, Sequence[float]] | None = None,
    ylabel: str = "episode reward",
    min_band_seeds: int = 3,
) -> Path:
    """Draws smoothed episode-reward curves, one line (mean over seeds) per group,
    with a band of the 95 % confidence interval of the mean where at least
    ``min_band_seeds`` seeds exist, over the episodes that every seed of the group reached.

    Args:
        groups: label -> list of per-seed reward sequences (one value per episode).
        window: moving-average window (thesis: 20 for Fig. 5.3, 50 for Fig. 5.4).
        path: the PNG file to write.
        title: figure title.
        vlines: label -> episodes to mark with dashed vertical lines (e.g. the
            episodes at which a CBN was (re)learned, as in Fig. 5.3); only the
            first few are drawn per group to keep the figure readable.
        ylabel: y axis label.
        min_band_seeds: the fewest seeds a group needs for its band. With two seeds
            (one degree of freedom, t = 12.7) the band spans most of the axis and hides
            the other groups, so it is left out by default.

    Returns:
        ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (label, seeds) in enumerate(groups.items()):
        seeds = [s for s in seeds if len(s)]
        if not seeds:
            continue
        color = colors[i % len(colors)]
        # episodes every seed reached (the band over fewer seeds is not comparable)
        common = min(len(s) for s in seeds)
        smooth = stack_curves([moving_average(s, window)[:common] for s in seeds])
        mean, half = mean_ci95(smooth)
        lo, hi = mean - half, mean + half
        if ylabel == "success":  # a rate stays in [0, 1]: each bound is cut, not the width
            lo, hi = np.clip(lo, 0.0, 1.0), np.clip(hi, 0.0, 1.0)
        x = np.arange(1, len(mean) + 1)
        n = len(seeds)
        ax.plot(x, mean, color=color, label=f"{label} (n={n})" if n > 1 else label)
        if n >= max(2, min_band_seeds):
            ax.fill_between(x, lo, hi, color=color, alpha=0.2, linewidth=0)
        for ep in list((vlines or {}).get(label, []))[:10]:
            ax.axvline(ep, color=color, linestyle="--", linewidth=0.8, alpha=0.6)
    ax.set_xlabel("episode")
    ax.set_ylabel(f"{ylabel} (moving average {window})")
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _relearn_episodes(relearns: pd.DataFrame) -> list[float]:
    if relearns is None or relearns.empty or "episode" not in relearns:
        return []
    return relearns["episode"].astype(float).tolist()


def plot_run(run_dir: str | Path, label: str | None = None) -> list[Path]:
    """Fig. 5.3-style (window 20, relearn lines) and Fig. 5.4-style (window 50) plots of one run.

    Returns:
        The PNG paths written under ``<run_dir>/plots``.
    """
    run_dir = Path(run_dir)
    cfg = _read_config(run_dir)
    label = label or str(cfg.get("variant", run_dir.name))
    eps = load_episodes(run_dir)
    rel_path = run_dir / "relearns.csv"
    rel = pd.read_csv(rel_path) if rel_path.exists() else None
    rewards = eps["reward"].tolist()
    out = [
        plot_reward_curves(
            {label: [rewards]}, 20, run_dir / "plots" / "reward_ma20.png",
            title=f"{label}: episode reward (cf. thesis Fig. 5.3)",
            vlines={label: _relearn_episodes(rel)},
        ),
        plot_reward_curves(
            {label: [rewards]}, 50, run_dir / "plots" / "reward_ma50.png",
            title=f"{label}: episode reward (cf. thesis Fig. 5.4)",
        ),
    ]
    if "success" in eps:
        out.append(
            plot_reward_curves(
                {label: [eps["success"].astype(float).tolist()]}, 50,
                run_dir / "plots" / "success_ma50.png",
                title=f"{label}: success rate", ylabel="success",
            )
        )
    return out


def summary_markdown(rows: Sequence[Mapping], columns: Sequence[str], title: str = "") -> str:
    """A plain Markdown table of ``rows`` (dicts) restricted to ``columns``."""
    lines = [f"### {title}", ""] if title else []
    lines.append("| " + " | ".join(columns) + " |")
    lines.append("|" + "---|" * len(columns))
    for r in rows:
        cells = []
        for c in columns:
            v = r.get(c, "")
            cells.append(f"{v:.3f}" if isinstance(v, float) else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_teacher_rounds(csvs: Mapping[str, str | Path], path: str | Path) -> Path:
    """The teacher phase's rounds (``imitation.csv``) of several runs side by side:
    the student's share of successful and crashed episodes on the round's new
    training layouts, and its agreement with the teacher, against the frames labelled.

    Args:
        csvs: ``{label: imitation.csv path}``.
        path: the PNG to write.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for label, csv_path in csvs.items():
        df = pd.read_csv(csv_path)
        frames = df["frames"].cumsum()
        for ax, col in zip(axes, ("success_rate", "crash_rate", "agreement")):
            ax.plot(frames, df[col], marker="o", ms=3, label=label)
    for ax, title in zip(axes, ("success (round's episodes)", "crash (round's episodes)",
                                "agreement with the teacher")):
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("frames labelled (cumulative)")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path
