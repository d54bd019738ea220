"""Generalisation figures: greedy success, SPL and crashes on held-out layouts (and the thesis scene).

::

    python benchmarks/generalisation.py --runs 'outputs/gen/seed*' --episodes 100
    python benchmarks/generalisation.py --runs 'outputs/gen/seed*' --pretrained thesis generalist

Prints one JSON object per line:

* ``figure="oracle"``: the shortest-path oracle (:class:`torchrl_causal.envs.OraclePolicy`)
  on the same episodes -- success 1.0 and SPL 1.0 by construction, its mean plan length;
* ``figure="run"``: one per run folder (or ``--pretrained`` name) and setting
  (``heldout``, ``thesis``): success rate with its 95 % Wilson interval, SPL, crash
  rate, geofence exits, mean steps, success split by whether the goal was in view at
  the start (``goal_hidden_at_start`` episodes, ``success_goal_hidden`` /
  ``success_goal_visible``; None where the policy's stack has no ``goal_in_sight``),
  the run's frames (DQN and teacher phases) and training wall time;
* ``figure="variant"``: per variant and setting over its runs (seeds): mean success,
  its 95 % t-interval over seeds, how many seeds reach ``--target`` (0.9), mean SPL;
  with ``--gate-off`` also ``<variant>/gate_off``, the CBN-gated runs flown with the
  gate passing the greedy action through; with ``--loop-guard`` also
  ``<variant>/loop_guard``, the runs flown with a
  :class:`~torchrl_causal.modules.LoopGuard` appended; with ``--flank-margin M``
  also ``<variant>[/loop_guard]/flankM``, the same policy with its
  :class:`~torchrl_causal.transforms.EgoMap`'s ``flank_margin`` set to ``M``; with
  ``--goal-prior D`` also ``<variant>[/loop_guard][/flankM]/priorD``, with the map's
  ``goal_prior`` (a hidden goal guessed ``D`` m ahead of the start) set to ``D`` as well;
  with ``--geofence`` also ``<variant>[/loop_guard][/flankM]/fence``, the same
  policy with its EgoMap's ``geofence`` set to ``"env"``; with ``--revisit-guard`` also
  ``<variant>[...]/revisit``, with a :class:`~torchrl_causal.transforms.VisitMemory` and a
  :class:`~torchrl_causal.modules.RevisitGuard` appended;
  with ``--goal-search D`` also ``<variant>[/loop_guard][/flankM]/searchD``, the same policy
  with a :class:`~torchrl_causal.modules.GoalSearch` appended (no prior);
* ``figure="paired"`` (``--control dqn_features``): per variant and setting, the mean
  seed-by-seed difference of success against the control, its 95 % t-interval and the
  verdict (helps / hurts / cannot be told apart).

Every policy flies the same episodes (``--seed``): layouts of the held-out split of
layout world 0, never trained on.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))

SETTINGS = ("heldout", "thesis")


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of ``k`` successes in ``n``."""
    if n == 0:
        return (float("nan"), float("nan"))
    p = k / n
    d = 1 + z * z / n
    c = p + z * z / (2 * n)
    r = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return ((c - r) / d, (c + r) / d)


def t_interval(values: list[float]) -> tuple[float, float]:
    """95 % t-interval of the mean of ``values`` (NaN for fewer than 2)."""
    from scipy import stats

    n = len(values)
    if n < 2:
        return (float("nan"), float("nan"))
    m = sum(values) / n
    sd = math.sqrt(sum((v - m) ** 2 for v in values) / (n - 1))
    h = stats.t.ppf(0.975, n - 1) * sd / math.sqrt(n)
    return (m - h, m + h)


def scene_env(setting: str, seed: int):
    from torchrl_causal.envs import DroneNavEnv

    if setting == "thesis":
        return DroneNavEnv("thesis", seed=seed)
    return DroneNavEnv("random", split="heldout", layout_seed=0, seed=seed)


def run_rows(name: str, folder: Path, settings, episodes: int, seed: int,
             gate_off: bool = False, loop_guard: bool = False,
             flank_margin: float | None = None,
             goal_prior: float | None = None,
             goal_search: float | None = None, geofence: bool = False,
             revisit_guard: bool = False) -> list[dict]:
    import train

    summary_path = folder / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    prov_path = folder / "provenance.json"
    prov = json.loads(prov_path.read_text()) if prov_path.is_file() else {}
    rows = []
    for setting in settings:
        from omegaconf import OmegaConf

        cfg = OmegaConf.load(folder / "config.yaml")
        env = train.with_features(cfg, train.ru.VARIANTS[cfg.variant], scene_env(setting, seed))
        policy, env, cfg = train.load_policy(folder, env=env)
        gate = next((m for m in policy if hasattr(m, "eval_gate")), None)
        for off in ((False, True) if gate_off and gate is not None else (False,)):
            if gate is not None:
                gate.eval_gate = not off
            rows.append(_run_row(name, folder, cfg, summary, prov, policy, env, setting,
                                 episodes, seed, off))
        if gate is not None:
            gate.eval_gate = True
        suffix = ""
        if loop_guard and not any(type(m).__name__ == "LoopGuard" for m in policy):
            from tensordict.nn import TensorDictSequential

            from torchrl_causal.modules import LoopGuard

            mask = "action_mask" if "action_mask" in env.observation_spec.keys() else None
            policy = TensorDictSequential(*policy, LoopGuard(action_mask_key=mask))
            suffix = "/loop_guard"
            rows.append(_run_row(name, folder, cfg, summary, prov, policy, env, setting,
                                 episodes, seed, False, suffix=suffix))
        from torchrl_causal.transforms import EgoMap

        maps = [t for t in getattr(env, "transform", []) if isinstance(t, EgoMap)]
        if flank_margin is not None:
            if maps:  # the same policy (guarded if asked), the map's flank margin changed
                for t in maps:
                    t.flank_margin = float(flank_margin)
                suffix = f"{suffix}/flank{flank_margin:g}"
                rows.append(_run_row(name, folder, cfg, summary, prov, policy, env, setting,
                                     episodes, seed, False, suffix=suffix))
        if geofence and maps:  # the same policy, the env's flight area in the map's mask
            for t in maps:
                t.geofence = "env"
            suffix = f"{suffix}/fence"
            rows.append(_run_row(name, folder, cfg, summary, prov, policy, env, setting,
                                 episodes, seed, False, suffix=suffix))
        if revisit_guard and maps and not any(type(m).__name__ == "RevisitGuard"
                                              for m in policy):
            # the same policy (and the options above), a VisitMemory + RevisitGuard appended
            from tensordict.nn import TensorDictSequential

            from torchrl_causal.modules import RevisitGuard
            from torchrl_causal.transforms import VisitMemory

            env.append_transform(VisitMemory())
            mask = "action_mask" if "action_mask" in env.observation_spec.keys() else None
            policy = TensorDictSequential(*policy, RevisitGuard(action_mask_key=mask))
            suffix = f"{suffix}/revisit"
            rows.append(_run_row(name, folder, cfg, summary, prov, policy, env, setting,
                                 episodes, seed, False, suffix=suffix))
        if goal_prior is not None:
            if maps:  # the same policy (and flank margin, if asked), a hidden goal guessed ahead
                for t in maps:
                    t.goal_prior = float(goal_prior)
                rows.append(_run_row(name, folder, cfg, summary, prov, policy, env, setting,
                                     episodes, seed, False, suffix=f"{suffix}/prior{goal_prior:g}"))
        if goal_search is not None and maps and not any(type(m).__name__ == "GoalSearch"
                                                        for m in policy):
            # the same policy (guard and flank margin, if asked; no prior), a GoalSearch last
            from tensordict.nn import TensorDictSequential

            from torchrl_causal.modules import GoalSearch

            for t in maps:
                t.goal_prior = None
            mask = "action_mask" if "action_mask" in env.observation_spec.keys() else None
            searching = TensorDictSequential(*policy, GoalSearch(
                goal_search, resolution=maps[0].resolution, action_mask_key=mask))
            rows.append(_run_row(name, folder, cfg, summary, prov, searching, env, setting,
                                 episodes, seed, False, suffix=f"{suffix}/search{goal_search:g}"))
        env.close()
    return rows


def _run_row(name, folder, cfg, summary, prov, policy, env, setting, episodes, seed, gate_off,
             suffix=""):
    from torchrl_causal.training import evaluate

    t0 = time.perf_counter()
    n = episodes if setting == "heldout" else min(episodes, 20)
    res = evaluate(policy, env, n, seed=seed, per_episode=True)
    k = int(round(res["success_rate"] * n))
    split = _split_by_start_view(res["episodes"])
    lo, hi = wilson(k, n)
    return {
        "bench": "generalisation", "figure": "run", "name": name, "run": str(folder),
        # "/gate_off": the same policy evaluated with its CBN gate passing the greedy
        # action through (CBNGate.eval_gate=False), on the same episodes
        "variant": str(cfg.variant) + ("/gate_off" if gate_off else "") + suffix,
        "seed": int(cfg.seed),
        "training_scene": str(cfg.env.layout), "setting": setting, "episodes": n,
        "success_rate": res["success_rate"], "ci95": [round(lo, 4), round(hi, 4)],
        "spl": res.get("spl"), "crash_rate": res["collisions"] / n,
        "out_of_bounds": res["out_of_bounds"], "mean_length": res["mean_length"],
        "oracle_steps": res.get("oracle_steps"), **split,
        "frames": summary.get("frames", prov.get("frames")),
        "teacher_frames": (summary.get("teacher") or prov.get("teacher") or {}).get("frames", 0),
        "train_seconds": (summary.get("loop_seconds") or 0)
        + ((summary.get("teacher") or {}).get("seconds") or 0),
        "eval_seconds": round(time.perf_counter() - t0, 1),
    }


def _split_by_start_view(episodes: list[dict]) -> dict:
    """Success of the episodes that start with the goal hidden / in view."""
    views = [ep.get("goal_in_view_at_start") for ep in episodes]
    if any(v is None for v in views):
        return {"goal_hidden_at_start": None, "success_goal_hidden": None,
                "success_goal_visible": None}
    hidden = [ep["success"] for ep, v in zip(episodes, views) if not v]
    shown = [ep["success"] for ep, v in zip(episodes, views) if v]
    return {"goal_hidden_at_start": len(hidden),
            "success_goal_hidden": sum(hidden) / len(hidden) if hidden else None,
            "success_goal_visible": sum(shown) / len(shown) if shown else None}


def oracle_rows(settings, episodes: int, seed: int) -> list[dict]:
    from torchrl_causal.envs import OraclePolicy
    from torchrl_causal.training import evaluate

    rows = []
    for setting in settings:
        env = scene_env(setting, seed)
        n = episodes if setting == "heldout" else min(episodes, 20)
        t0 = time.perf_counter()
        res = evaluate(OraclePolicy(env), env, n, seed=seed)
        rows.append({"bench": "generalisation", "figure": "oracle", "name": "oracle",
                     "setting": setting, "episodes": n, "success_rate": res["success_rate"],
                     "spl": res["spl"], "crash_rate": res["collisions"] / n,
                     "mean_length": res["mean_length"], "oracle_steps": res["oracle_steps"],
                     "eval_seconds": round(time.perf_counter() - t0, 1)})
        env.close()
    return rows


def variant_rows(rows: list[dict], target: float) -> list[dict]:
    out = []
    keys = sorted({(r["variant"], r["training_scene"], r["setting"]) for r in rows
                   if r["figure"] == "run"})
    for variant, trained, setting in keys:
        group = [r for r in rows if r["figure"] == "run" and r["variant"] == variant
                 and r["training_scene"] == trained and r["setting"] == setting]
        succ = [r["success_rate"] for r in group]
        spl = [r["spl"] for r in group if r["spl"] is not None]
        lo, hi = t_interval(succ)
        out.append({"bench": "generalisation", "figure": "variant", "variant": variant,
                    "training_scene": trained, "setting": setting, "n_seeds": len(group),
                    "seeds": sorted(r["seed"] for r in group),
                    "success_mean": sum(succ) / len(succ),
                    "success_ci95": None if math.isnan(lo) else [round(lo, 4), round(hi, 4)],
                    "seeds_at_target": sum(s >= target for s in succ), "target": target,
                    "spl_mean": sum(spl) / len(spl) if spl else None,
                    "crash_rate_mean": sum(r["crash_rate"] for r in group) / len(group)})
    return out


def paired_rows(rows: list[dict], control: str) -> list[dict]:
    """Per variant and setting: the mean over seeds of (variant - ``control``) success on the
    same episodes, its 95 % t-interval, and what it says (helps / hurts / cannot be told
    apart: the interval excludes 0 or not)."""
    runs = [r for r in rows if r["figure"] == "run"]
    out = []
    keys = sorted({(r["variant"], r["training_scene"], r["setting"]) for r in runs
                   if r["variant"] != control})
    for variant, trained, setting in keys:
        ctrl = {r["seed"]: r["success_rate"] for r in runs if r["variant"] == control
                and r["training_scene"] == trained and r["setting"] == setting}
        diffs = [r["success_rate"] - ctrl[r["seed"]] for r in runs if r["variant"] == variant
                 and r["training_scene"] == trained and r["setting"] == setting
                 and r["seed"] in ctrl]
        if not diffs:
            continue
        lo, hi = t_interval(diffs)
        verdict = ("cannot be told apart" if math.isnan(lo) or lo <= 0 <= hi
                   else "helps" if lo > 0 else "hurts")
        out.append({"bench": "generalisation", "figure": "paired", "variant": variant,
                    "control": control, "training_scene": trained, "setting": setting,
                    "n_pairs": len(diffs), "diff_mean": sum(diffs) / len(diffs),
                    "diff_ci95": None if math.isnan(lo) else [round(lo, 4), round(hi, 4)],
                    "verdict": verdict})
    return out


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", nargs="*", default=[], help="run folders (globs allowed)")
    p.add_argument("--pretrained", nargs="*", default=[],
                   help="shipped policy names (torchrl_causal.pretrained)")
    p.add_argument("--episodes", type=int, default=100, help="held-out episodes per policy")
    p.add_argument("--settings", nargs="*", default=list(SETTINGS), choices=SETTINGS)
    p.add_argument("--seed", type=int, default=2024, help="seeds the evaluation episodes")
    p.add_argument("--target", type=float, default=0.9)
    p.add_argument("--no-oracle", action="store_true")
    p.add_argument("--out", default=None, help="also append the JSON lines to this file")
    p.add_argument("--gate-off", action="store_true",
                   help="also evaluate each CBN-gated run with its gate off (variant '<v>/gate_off')")
    p.add_argument("--loop-guard", action="store_true",
                   help="also evaluate each run without a LoopGuard with one appended "
                        "(variant '<v>/loop_guard'; it needs an action history of >= 4)")
    p.add_argument("--flank-margin", type=float, default=None, metavar="M",
                   help="also evaluate each run that builds an EgoMap with its flank_margin set "
                        "to M metres (variant '<v>[/loop_guard]/flankM', after --loop-guard)")
    p.add_argument("--geofence", action="store_true",
                   help="also fly each policy with its EgoMap's geofence set to 'env' (the "
                        "layout's arena in the action mask; variant '<v>[/loop_guard][/flankM]"
                        "/fence')")
    p.add_argument("--revisit-guard", action="store_true",
                   help="also fly each policy with a VisitMemory + RevisitGuard appended "
                        "(variant '<v>[/loop_guard][/flankM][/fence]/revisit')")
    p.add_argument("--goal-prior", type=float, default=None, metavar="D",
                   help="also evaluate each run that builds an EgoMap with its goal_prior set to "
                        "D metres (a goal the start does not see is guessed D m ahead; variant "
                        "'<v>[/loop_guard][/flankM]/priorD', after --flank-margin)")
    p.add_argument("--goal-search", type=float, default=None, metavar="D",
                   help="also evaluate each run that builds an EgoMap with a GoalSearch appended "
                        "(until the goal is seen, fly round the map's obstacles towards a point "
                        "D m ahead of the start; variant '<v>[/loop_guard][/flankM]/searchD')")
    p.add_argument("--control", default=None,
                   help="a variant (e.g. dqn_features): paired differences of every other "
                        "variant against it, seed by seed")
    a = p.parse_args(argv)
    if a.episodes < 1:
        p.error(f"--episodes must be >= 1, got {a.episodes}")
    if a.flank_margin is not None and not (math.isfinite(a.flank_margin) and a.flank_margin >= 0):
        p.error(f"--flank-margin must be a finite number >= 0, got {a.flank_margin}")
    if a.goal_prior is not None and not (math.isfinite(a.goal_prior) and 0 < a.goal_prior < 9):
        p.error(f"--goal-prior must be a distance in (0, 9) m, got {a.goal_prior}")
    if a.goal_search is not None and not (math.isfinite(a.goal_search) and 0 < a.goal_search < 9):
        p.error(f"--goal-search must be a distance in (0, 9) m, got {a.goal_search}")
    folders = [Path(f) for pat in a.runs for f in sorted(glob.glob(pat))]
    missing = [str(f) for f in folders if not (f / "model.pt").is_file()]
    if missing:
        p.error(f"--runs: no model.pt (not a finished run) in {missing}")
    if a.runs and not folders:
        p.error(f"--runs {a.runs} matched no folder")
    import torch

    from torchrl_causal.pretrained import policy_dir

    torch.set_num_threads(1)
    named = [(f.name, f) for f in folders]
    named += [(f"pretrained:{n}", policy_dir(n)) for n in a.pretrained]
    rows: list[dict] = []

    def emit(batch):
        for r in batch:
            line = json.dumps(r)
            print(line, flush=True)
            if a.out:
                with open(a.out, "a") as f:
                    f.write(line + "\n")
        rows.extend(batch)

    if not a.no_oracle:
        emit(oracle_rows(a.settings, a.episodes, a.seed))
    for name, folder in named:
        emit(run_rows(name, folder, a.settings, a.episodes, a.seed, gate_off=a.gate_off,
                      loop_guard=a.loop_guard, flank_margin=a.flank_margin,
                      goal_prior=a.goal_prior, goal_search=a.goal_search,
                      geofence=a.geofence, revisit_guard=a.revisit_guard))
    emit(variant_rows(rows, a.target))
    if a.control:
        emit(paired_rows(rows, a.control))
    return rows


if __name__ == "__main__":
    main()
