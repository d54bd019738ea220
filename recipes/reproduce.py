"""Run the thesis protocol (sec. 5.2) and draw its comparison figures and tables.

Protocol (``--mode full``): the five variants (``dqn_image``, ``cbn_defined``,
``cbn_p``, ``cbn_pn``, ``cbn_v2``; k = 200) x ``--seeds`` seeds x 700 episodes
(thesis Fig. 5.4), and the k sweep 100 / 200 / 400 / 600 of ``cbn_v2``
(Fig. 5.3; the k = 200 runs are the ``cbn_v2`` runs). Each run is one
``recipes/train.py`` process writing its own run folder under ``--root``::

    <root>/variants/<variant>/seed_<s>/      (Fig. 5.4 runs)
    <root>/k_sweep/k_<k>/seed_<s>/           (Fig. 5.3 runs, k != 200)
    <root>/figures/fig5_3_k_sweep.png, fig5_4_variants.png, success_variants.png
    <root>/tables/summary.md, table_5_1_seed_<s>.md

``--mode reduced`` runs the same grid with a budget this 2-core machine can
afford (a few minutes per run; see ``--frames``); ``--aggregate-only`` redraws
figures and tables from existing runs; ``--dry-run`` prints the commands.
Already finished runs (with a ``summary.json``) are skipped, so an
interrupted reproduction can simply be started again. Extra hydra overrides
for every run go after ``--``, e.g. ``-- buffer.size=50000``.

Example::

    python recipes/reproduce.py --mode reduced --root outputs/reproduce_reduced
    python recipes/reproduce.py --mode full --seeds 5 --root outputs/reproduce
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))

import recipe_utils as ru  # noqa: E402
import results  # noqa: E402

TRAIN = Path(__file__).resolve().parent / "train.py"
K_SWEEP = (100, 200, 400, 600)

#: Budgets per mode. ``full`` is the thesis's 700 episodes (at most 200 steps each).
MODES = {
    "full": {
        "seeds": 5,
        "overrides": [
            "collector.total_episodes=700", "collector.total_frames=140000",
            "exploration.annealing_frames=70000", "buffer.size=100000",
            "eval.interval_frames=20000", "eval.episodes=10",
            "checkpoint.interval_frames=10000",
        ],
    },
    "reduced": {
        "seeds": 2,
        "overrides": [
            "collector.total_frames=2000", "exploration.annealing_frames=1500",
            "loss.learning_starts=300", "env.max_steps=100", "buffer.size=2000",
            "eval.interval_frames=0", "eval.episodes=2", "checkpoint.interval_frames=0",
            "progress=false", "threads=1",
        ],
    },
}


def run_plan(root: Path, mode: str, seeds: int, variants, k_values) -> list[tuple[Path, list[str]]]:
    """``(run_dir, argv)`` for every run of the protocol."""
    plan = []
    base = MODES[mode]["overrides"]
    for v in variants:
        for s in range(seeds):
            d = root / "variants" / v / f"seed_{s}"
            plan.append((d, ["--config-name", v, f"seed={s}", f"output_dir={d}", *base]))
    for k in k_values:
        if k == 200:
            continue  # the cbn_v2 runs above
        for s in range(seeds):
            d = root / "k_sweep" / f"k_{k}" / f"seed_{s}"
            plan.append((d, ["--config-name", "cbn_v2", f"seed={s}", f"causal.k={k}",
                             f"output_dir={d}", *base]))
    return plan


def run_all(plan, extra: list[str], dry_run: bool) -> None:
    env = dict(os.environ)
    env.setdefault("MUJOCO_GL", "egl")
    for i, (run_dir, argv) in enumerate(plan, 1):
        cmd = [sys.executable, str(TRAIN), *argv, *extra]
        if (run_dir / "summary.json").exists():
            print(f"[{i}/{len(plan)}] done already: {run_dir}")
            continue
        if (run_dir / ru.RUN_LAYOUT["checkpoint"]).exists():
            cmd.append("checkpoint.resume=true")
        print(f"[{i}/{len(plan)}] {' '.join(cmd)}", flush=True)
        if not dry_run:
            subprocess.run(cmd, check=True, env=env)


def _tail_mean(x: pd.Series, n: int) -> float:
    return float(x.tail(n).mean()) if len(x) else float("nan")


def _final_eval(run_dir: Path) -> dict:
    """Greedy success per layout: ``summary.json``'s final evaluation (``eval.final_episodes``
    episodes), else the last periodic evaluation in ``eval.csv``."""
    summary = run_dir / "summary.json"
    if summary.exists():
        final = json.loads(summary.read_text()).get("final_eval") or {}
        if final:
            return {f"eval_success_{k}": float(v["success_rate"]) for k, v in final.items()}
    path = run_dir / "eval.csv"
    if not path.exists():
        return {}
    ev = pd.read_csv(path)
    if ev.empty:
        return {}
    last = ev[ev["frames"] == ev["frames"].max()]
    return {f"eval_success_{r.layout}": float(r.success_rate) for r in last.itertuples()}


def _finished_runs(folder: Path) -> list[dict]:
    return [r for r in results.load_runs(folder) if (r["dir"] / "summary.json").exists()]


def aggregate(root: Path) -> dict:
    """Draws Fig. 5.3 / 5.4-style figures and the summary tables from all runs under ``root``."""
    fig_dir, tab_dir = root / "figures", root / "tables"
    fig_dir.mkdir(parents=True, exist_ok=True)
    tab_dir.mkdir(parents=True, exist_ok=True)
    out: dict = {"figures": [], "tables": []}
    var_runs, sweep_runs = _finished_runs(root / "variants"), _finished_runs(root / "k_sweep")

    groups: dict[str, list] = {}
    success: dict[str, list] = {}
    for v in ru.VARIANTS:
        rs = [r for r in var_runs if r["variant"] == v]
        if rs:
            groups[ru.VARIANTS[v].label] = [r["episodes"]["reward"].tolist() for r in rs]
            success[ru.VARIANTS[v].label] = [r["episodes"]["success"].astype(float).tolist()
                                             for r in rs]
    if groups:
        out["figures"].append(str(results.plot_reward_curves(
            groups, 50, fig_dir / "fig5_4_variants.png",
            title="Episode reward per variant, k=200 (cf. thesis Fig. 5.4)")))
        out["figures"].append(str(results.plot_reward_curves(
            success, 50, fig_dir / "success_variants.png", ylabel="success",
            title="Success rate per variant")))

    k_runs = [r for r in var_runs if r["variant"] == "cbn_v2"] + sweep_runs
    kgroups: dict[str, list] = {}
    vlines: dict[str, list] = {}
    for k in sorted({r["k"] for r in k_runs}):
        rs = [r for r in k_runs if r["k"] == k]
        label = f"k={k}"
        kgroups[label] = [r["episodes"]["reward"].tolist() for r in rs]
        firsts = [float(r["relearns"]["episode"].iloc[0]) for r in rs if len(r["relearns"])]
        vlines[label] = [float(np.mean(firsts))] if firsts else []
    if kgroups:
        out["figures"].append(str(results.plot_reward_curves(
            kgroups, 20, fig_dir / "fig5_3_k_sweep.png", vlines=vlines,
            title="CBN-DQN V2, episode reward per k (cf. thesis Fig. 5.3); "
                  "dashed: first CBN (mean over seeds)")))

    rows = []
    for label, rs in [(ru.VARIANTS[v].label, [r for r in var_runs if r["variant"] == v])
                      for v in ru.VARIANTS] + [
                     (f"CBN-DQN V2 k={k}", [r for r in sweep_runs if r["k"] == k])
                     for k in sorted({r["k"] for r in sweep_runs})]:
        if not rs:
            continue
        per_seed = []
        for r in rs:
            e = r["episodes"]
            per_seed.append({
                "episodes": len(e),
                "reward_last50": _tail_mean(e["reward"], 50),
                "success_all": float(e["success"].mean()) if len(e) else float("nan"),
                "success_last50": _tail_mean(e["success"].astype(float), 50),
                "crash_rate": float(e["crash"].mean()) if len(e) else float("nan"),
                **_final_eval(r["dir"]),
            })
        df = pd.DataFrame(per_seed)
        row = {"run": label, "seeds": len(rs)}
        for c in df.columns:
            m, s = df[c].mean(), df[c].std(ddof=0)
            row[c] = f"{m:.2f} +- {s:.2f}" if len(rs) > 1 else f"{m:.2f}"
        rows.append(row)
    if rows:
        cols = list(dict.fromkeys(c for r in rows for c in r))  # every row starts run, seeds
        md = results.summary_markdown(
            rows, cols, "Per-run summary (mean +- std over seeds; reward/success of the "
            "last 50 training episodes; eval_success_<layout>: greedy evaluation at the end)")
        (tab_dir / "summary.md").write_text(md)
        out["tables"].append(str(tab_dir / "summary.md"))
    for r in var_runs:
        t = r["dir"] / "tables" / "table_5_1.md"
        if r["variant"] == "cbn_v2" and t.exists():
            dst = tab_dir / f"table_5_1_seed_{r['seed']}.md"
            dst.write_text(t.read_text())
            out["tables"].append(str(dst))
    (root / "reproduce_summary.json").write_text(json.dumps(out, indent=2))
    return out


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--mode", choices=sorted(MODES), default="reduced")
    p.add_argument("--root", type=Path, default=None,
                   help="output root (default outputs/reproduce_<mode>)")
    p.add_argument("--seeds", type=int, default=None, help="seeds per configuration")
    p.add_argument("--variants", nargs="+", default=list(ru.VARIANTS), choices=list(ru.VARIANTS))
    p.add_argument("--k", nargs="+", type=int, default=list(K_SWEEP), help="k sweep values")
    p.add_argument("--frames", type=int, default=None,
                   help="override collector.total_frames of every run")
    p.add_argument("--aggregate-only", action="store_true")
    p.add_argument("--dry-run", action="store_true")
    p.add_argument("overrides", nargs="*", help="extra hydra overrides for every run (after --)")
    args = p.parse_args(argv)
    seeds = args.seeds if args.seeds is not None else MODES[args.mode]["seeds"]
    if seeds < 1:
        raise ValueError(f"Invalid option --seeds={seeds}: expected an integer >= 1")
    bad_k = [k for k in args.k if k <= 0]
    if bad_k:
        raise ValueError(f"Invalid option --k={bad_k}: expected integers > 0")
    root = (args.root or Path("outputs") / f"reproduce_{args.mode}").resolve()
    ru.check_writable(root)
    extra = list(args.overrides)
    if args.frames is not None:
        extra.append(f"collector.total_frames={args.frames}")
    if not args.aggregate_only:
        run_all(run_plan(root, args.mode, seeds, args.variants, args.k), extra, args.dry_run)
    if args.dry_run:
        return {}
    out = aggregate(root)
    print(f"Figures: {root / 'figures'}")
    print(f"Tables: {root / 'tables'}")
    return out


if __name__ == "__main__":
    main()
