"""Learning benchmark: does each variant learn to reach the goal on the thesis scene?

Trains each of the five variants (``dqn_image``, ``cbn_defined``, ``cbn_p``,
``cbn_pn``, ``cbn_v2``) and the two no-CBN controls with the same features
(``dqn_features``, ``dqn_features_v2eps``) on the thesis scene for a frame budget and a list of
seeds, with ``recipes/train.py``'s :func:`train` (one process per run, so
runs can go in parallel with ``--jobs``), then prints one JSON object per
variant (and writes them to ``<out>/learning.jsonl``):

* ``final_success_mean`` / ``final_success_ci95``: greedy success rate on the
  thesis scene after training (``summary.json``'s ``final_eval``, over
  ``--eval-episodes`` episodes per seed), mean over seeds and the half-width
  of its 95% confidence interval (Student t, n - 1 degrees of freedom; 0 for
  one seed); ``seeds_at_0_9``: how many seeds reach a greedy success >= 0.9;
* ``frames_to_first_greedy_success``: per seed, the frames of the first
  periodic greedy evaluation (``eval.csv``, every ``eval.interval_frames``)
  on the thesis scene with a success rate > 0 (null if none), and
  ``frames_to_first_greedy_success_median`` over the seeds that have one;
* ``train_crash_rate`` / ``train_out_of_bounds_rate`` / ``train_success_rate``:
  share of all training episodes of all seeds (``episodes.csv``) that ended in
  a collision / out of bounds / at the goal;
* ``wall_seconds``: mean wall time of a run's training loop
  (``loop_seconds``; a resumed run counts only its last session).

Targets: the best variant reaches a final greedy success >= 0.9 in >= 4 of 5
seeds (``seeds_at_0_9 >= 4``) within 20,000 frames, on 2 CPU cores.

Run folders are ``<out>/<variant>/seed_<s>/``. A run whose folder has a
``summary.json`` is not trained again, and one with a checkpoint but no
summary is resumed (``checkpoint.resume=true``), so an interrupted benchmark
can simply be started again. ``--from-runs`` only aggregates existing run
folders (all ``seed_*`` folders found, or those of ``--seeds``).

Usage::

    python benchmarks/learning.py            # 7 variants x 5 seeds x 20,000 frames
    python benchmarks/learning.py --variants cbn_v2 dqn_image --seeds 0 1 --jobs 2
    python benchmarks/learning.py --preset thesis --heldout --override buffer.size=10000
    python benchmarks/learning.py --from-runs --out outputs/bench_learning
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import statistics
import sys
import time
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only
ROOT = Path(__file__).resolve().parents[1]
RECIPES = ROOT / "recipes"

VARIANTS = ("dqn_image", "cbn_defined", "cbn_p", "cbn_pn", "cbn_v2", "dqn_features",
            "dqn_features_v2eps")
LAYOUT = "thesis"
SUCCESS_TARGET = 0.9


# --------------------------------------------------------------------------- aggregation
def _nan_to_none(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _nan_to_none(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_nan_to_none(v) for v in x]
    return x


def _read_config(run_dir: Path) -> dict:
    path = run_dir / "config.yaml"
    if not path.exists():
        return {}
    import yaml

    return yaml.safe_load(path.read_text()) or {}


def _first_success_frames(run_dir: Path, layout: str = LAYOUT) -> int | None:
    """Frames of the first periodic greedy evaluation on ``layout`` with success > 0."""
    import pandas as pd

    path = run_dir / "eval.csv"
    if not path.exists() or path.stat().st_size == 0:
        return None
    ev = pd.read_csv(path)
    if ev.empty:
        return None
    hit = ev[(ev["layout"] == layout) & (ev["success_rate"] > 0)].sort_values("frames")
    return int(hit["frames"].iloc[0]) if len(hit) else None


def ci95(values) -> float:
    """Half-width of the 95% confidence interval of the mean (Student t, n - 1 dof)."""
    from scipy import stats

    n = len(values)
    if n < 2:
        return 0.0
    sd = statistics.stdev(values)
    return float(stats.t.ppf(0.975, n - 1) * sd / math.sqrt(n))


def aggregate(run_dirs) -> dict:
    """One variant's learning figures over its finished run folders (one per seed).

    Reads only the run folders' files (``summary.json``, ``config.yaml``,
    ``eval.csv``, ``episodes.csv``); folders without a ``summary.json``
    (unfinished runs) are counted in ``n_unfinished`` and otherwise ignored.

    Args:
        run_dirs: run folders of one variant, one per seed.

    Returns:
        The JSON-ready figures (NaN written as ``None``).

    Raises:
        ValueError: no finished run, or runs of more than one variant.
    """
    import pandas as pd

    dirs = [Path(d) for d in run_dirs]
    done = [d for d in dirs if (d / "summary.json").exists()]
    if not done:
        raise ValueError(f"Invalid run_dirs: no finished run (summary.json) among {dirs}")
    summaries = [json.loads((d / "summary.json").read_text()) for d in done]
    configs = [_read_config(d) for d in done]
    variants = sorted({s["variant"] for s in summaries})
    if len(variants) != 1:
        raise ValueError(f"Invalid run_dirs: runs of several variants {variants}; "
                         "aggregate one variant at a time")
    order = sorted(range(len(done)), key=lambda i: summaries[i].get("seed", i))
    done = [done[i] for i in order]
    summaries = [summaries[i] for i in order]
    configs = [configs[i] for i in order]

    final = [float(s["final_eval"][LAYOUT]["success_rate"]) for s in summaries]
    firsts = [_first_success_frames(d) for d in done]
    reached = [f for f in firsts if f is not None]

    episodes = [pd.read_csv(d / "episodes.csv") for d in done
                if (d / "episodes.csv").exists() and (d / "episodes.csv").stat().st_size > 0]
    ep = pd.concat(episodes, ignore_index=True) if episodes else pd.DataFrame()
    n_ep = len(ep)

    def rate(col: str) -> float | None:
        return float(ep[col].astype(float).sum() / n_ep) if n_ep else None

    budgets = sorted({c.get("collector", {}).get("total_frames", s["frames"])
                      for c, s in zip(configs, summaries)})
    presets = sorted({str(c.get("preset_name", "unknown")) for c in configs})
    out = {
        "benchmark": "learning",
        "variant": variants[0],
        "preset": presets[0] if len(presets) == 1 else presets,
        "frames": budgets[0] if len(budgets) == 1 else budgets,
        "n_seeds": len(done),
        "seeds": [s.get("seed") for s in summaries],
        "final_success": final,
        "final_success_mean": float(sum(final) / len(final)),
        "final_success_ci95": ci95(final),
        "seeds_at_0_9": sum(x >= SUCCESS_TARGET for x in final),
        "frames_to_first_greedy_success": firsts,
        "frames_to_first_greedy_success_median":
            float(statistics.median(reached)) if reached else None,
        "train_episodes": n_ep,
        "train_crash_rate": rate("crash"),
        "train_out_of_bounds_rate": rate("out_of_bounds"),
        "train_success_rate": rate("success"),
        "wall_seconds": float(sum(float(s["loop_seconds"]) for s in summaries) / len(summaries)),
        "n_unfinished": len(dirs) - len(done),
    }
    heldout = [float(s["final_eval"]["heldout"]["success_rate"]) for s in summaries
               if "heldout" in s.get("final_eval", {})]
    if heldout:
        out["final_success_heldout_mean"] = float(sum(heldout) / len(heldout))
        out["final_success_heldout_ci95"] = ci95(heldout)
    return _nan_to_none(out)


CONTROL = "dqn_features"


def paired_vs_control(results: list[dict], control: str = CONTROL) -> list[dict]:
    """Per variant with a CBN: the seed-paired difference of final greedy success
    against ``control`` (same features, same seeds, no CBN), mean and 95 % t-interval,
    and a verdict: ``helps`` / ``hurts`` (the interval excludes 0) or ``cannot be told
    apart``.

    Example:
        >>> rows = [{"variant": "dqn_features", "seeds": [0, 1], "final_success": [0.5, 0.7]},
        ...         {"variant": "cbn_v2", "seeds": [0, 1], "final_success": [0.9, 0.8]}]
        >>> r = paired_vs_control(rows)[0]
        >>> r["variant"], r["n_pairs"], round(r["difference_mean"], 2), r["verdict"]
        ('cbn_v2', 2, 0.25, 'cannot be told apart')
    """
    base = next((r for r in results if r["variant"] == control), None)
    if base is None:
        return []
    ref = dict(zip(base["seeds"], base["final_success"]))
    out = []
    for r in results:
        if r["variant"] == control or not r["variant"].startswith("cbn"):
            continue
        diffs = [s - ref[seed] for seed, s in zip(r["seeds"], r["final_success"]) if seed in ref]
        if not diffs:
            continue
        mean = sum(diffs) / len(diffs)
        half = ci95(diffs) if len(diffs) > 1 else float("nan")
        lo, hi = mean - half, mean + half
        verdict = ("helps" if lo > 0 else "hurts" if hi < 0 else "cannot be told apart") \
            if len(diffs) > 1 else "cannot be told apart"
        out.append(_nan_to_none({
            "benchmark": "learning", "figure": "paired_vs_control", "variant": r["variant"],
            "control": control, "n_pairs": len(diffs), "differences": diffs,
            "difference_mean": mean, "difference_ci95": [lo, hi], "verdict": verdict}))
    return out


def find_runs(out: Path, variant: str, seeds=None) -> list[Path]:
    """Run folders ``<out>/<variant>/seed_<s>`` (all found, or those of ``seeds``)."""
    folder = Path(out) / variant
    if seeds is not None:
        return [folder / f"seed_{s}" for s in seeds if (folder / f"seed_{s}").is_dir()]
    if not folder.is_dir():
        return []

    def key(p: Path):
        tail = p.name.split("_", 1)[-1]
        return (0, int(tail), "") if tail.isdigit() else (1, 0, p.name)

    return sorted((p for p in folder.glob("seed_*") if p.is_dir()), key=key)


# --------------------------------------------------------------------------- training
def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def run_overrides(run_dir: Path, seed: int, frames: int, preset: str, eval_episodes: int,
                  heldout: bool, extra=(), threads: int | None = None) -> list[str]:
    """Hydra overrides of one run (``extra`` replaces an option of the same key)."""
    layouts = f"[{LAYOUT},heldout]" if heldout else f"[{LAYOUT}]"
    base = [
        f"output_dir={run_dir}",
        f"seed={seed}",
        f"preset={preset}",
        f"env.layout={LAYOUT}",
        f"env.eval_layouts={layouts}",
        f"collector.total_frames={frames}",
        f"eval.final_episodes={eval_episodes}",
        "progress=false",
        "outputs.draw_cbns=false",
    ]
    if threads:
        base.append(f"threads={threads}")
    merged = {_key(o): o for o in base}
    for o in extra:
        merged[_key(o)] = o
    return list(merged.values())


def train_one(variant: str, run_dir: str, overrides: list[str]) -> dict:
    """One training run (in a worker process): composes the config and calls ``train``."""
    sys.path.insert(0, str(RECIPES))
    from hydra import compose, initialize_config_dir

    import train as recipe

    run_dir = Path(run_dir)
    overrides = list(overrides)
    if (run_dir / "checkpoints" / "last.pt").exists():
        overrides.append("checkpoint.resume=true")
    with initialize_config_dir(config_dir=recipe.CONFIG_DIR, version_base=None):
        cfg = compose(config_name=variant, overrides=overrides)
    t0 = time.perf_counter()
    summary = recipe.train(cfg)
    return {"variant": variant, "run_dir": str(run_dir), "seconds": time.perf_counter() - t0,
            "stopped_early": bool(summary.get("stopped_early"))}


def train_all(args) -> list[str]:
    """Trains every missing run; returns the failures (one line each)."""
    threads = None
    if args.jobs > 1 and not any(_key(o) == "threads" for o in args.override):
        threads = max(1, (os.cpu_count() or 1) // args.jobs)
    todo = []
    for v in args.variants:
        for s in args.seeds:
            d = (args.out / v / f"seed_{s}").resolve()
            if (d / "summary.json").exists():
                print(f"done already: {d}", file=sys.stderr, flush=True)
                continue
            ov = run_overrides(d, s, args.frames, args.preset, args.eval_episodes,
                               args.heldout, args.override, threads)
            todo.append((v, str(d), ov))
    failures = []
    if not todo:
        return failures
    ctx = multiprocessing.get_context("spawn")
    # max_tasks_per_child=1: every run starts in a fresh process
    with ProcessPoolExecutor(max_workers=args.jobs, mp_context=ctx,
                             max_tasks_per_child=1) as pool:
        futures = {pool.submit(train_one, *t): t for t in todo}
        for fut in as_completed(futures):
            v, d, _ = futures[fut]
            try:
                res = fut.result()
                print(f"trained {v} in {res['seconds']:.0f} s: {d}", file=sys.stderr, flush=True)
            except Exception as exc:  # keep the other runs going
                msg = f"{v} {d}: {type(exc).__name__}: {exc}"
                failures.append(msg)
                print(f"FAILED {msg}", file=sys.stderr, flush=True)
                traceback.print_exception(exc, file=sys.stderr)
    return failures


# --------------------------------------------------------------------------- main
def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    p.add_argument("--seeds", nargs="+", type=int, default=None,
                   help="seeds (default 0 1 2 3 4; with --from-runs: every seed_* folder)")
    p.add_argument("--frames", type=int, default=20000, help="training frames per run")
    p.add_argument("--preset", default="default", choices=("default", "thesis"))
    p.add_argument("--out", type=Path, default=Path("outputs/bench_learning"),
                   help="folder of the run folders and learning.jsonl")
    p.add_argument("--jobs", type=int, default=1, help="runs in parallel (processes)")
    p.add_argument("--eval-episodes", type=int, default=20,
                   help="final greedy episodes per run (eval.final_episodes)")
    p.add_argument("--heldout", action="store_true",
                   help="also evaluate on the held-out layouts (eval_layouts=[thesis,heldout])")
    p.add_argument("--override", action="append", default=[],
                   help="extra hydra override for every run (repeatable), e.g. buffer.size=10000")
    p.add_argument("--from-runs", action="store_true",
                   help="train nothing; aggregate the existing run folders under --out")
    args = p.parse_args(argv)
    for name in ("frames", "jobs", "eval_episodes"):
        if getattr(args, name) < 1:
            p.error(f"invalid option --{name.replace('_', '-')}={getattr(args, name)}: "
                    "expected >= 1")

    failures: list[str] = []
    if not args.from_runs:
        if args.seeds is None:
            args.seeds = [0, 1, 2, 3, 4]
        failures = train_all(args)

    results = []
    for v in args.variants:
        dirs = find_runs(args.out, v, args.seeds)
        if not any((d / "summary.json").exists() for d in dirs):
            print(f"no finished run of {v} under {args.out / v}", file=sys.stderr, flush=True)
            continue
        res = aggregate(dirs)
        results.append(res)
        print(json.dumps(res), flush=True)
    for row in paired_vs_control(results):
        print(json.dumps(row), flush=True)
        results.append(row)
    if results:
        args.out.mkdir(parents=True, exist_ok=True)
        with open(args.out / "learning.jsonl", "w") as f:
            f.writelines(json.dumps(r) + "\n" for r in results)
    if failures:
        raise SystemExit(f"{len(failures)} run(s) failed:\n" + "\n".join(failures))
    return results


if __name__ == "__main__":
    main()
