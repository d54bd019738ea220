"""The Tello path beside the simulator: issue 19's targets as JSON lines.

::

    python benchmarks/sim_to_real.py                          # thesis policy, seeds 7 and 11
    python benchmarks/sim_to_real.py --policies thesis generalist --episodes 50
    python benchmarks/sim_to_real.py --episodes 2 --seeds 0   # a smoke run
    python benchmarks/sim_to_real.py --detector-weights W.pt  # candidate weights, same flights
    python benchmarks/sim_to_real.py --policies generalist --map exact  # EgoMap's depth model
    python benchmarks/sim_to_real.py --policies generalist --goal-size 1.0 0.8  # printed board
    python benchmarks/sim_to_real.py --from-flights flights/*/summary.json  # pool flown seeds
    python benchmarks/sim_to_real.py --from-flights flights/*/summary.json --compare-sim

For each shipped policy and emulator seed it flies ``recipes/fly_tello.py``'s
defaults -- RGB-only perception through the emulated camera path, noisy moves
(``--noise``), the default arrival rule (``--arrival-head auto``, and with the
head ``--final-approach auto``) -- and flies
the same policy in :class:`~torchrl_causal.envs.DroneNavEnv` under the same
noise model (``--compare-sim``) on the emulator's own layouts and noise draws,
episode by episode (``dronenav_paired``: both / emulator only / DroneNavEnv only /
neither), with the simulator's perception or, with ``--compare-perception rgb``, the
same MonoDepth (``--depth-weights`` or the shipped one; the goal keys stay
``DroneNavEnv``'s own measurement). The thesis policy flies the thesis scene, the
generalist held-out random layouts. Prints one JSON object per figure:

* ``{"figure": "sim_to_real", "policy", "seed", ...}`` -- one seed's flights:
  the simulator-judged success with its 95 % Wilson interval, the arrival
  rule's agreement with the simulator, false "reached", missed arrivals,
  crashes, and ``DroneNavEnv``'s success with its interval;
* ``{"figure": "sim_to_real_pooled", "policy", ...}`` -- all seeds of a policy
  together, with the targets: success >= 0.85 (thesis policy) and inside
  ``DroneNavEnv``'s interval, agreement >= 0.95, false "reached" rarer than
  1 in 20.

``--detector-weights`` / ``--depth-weights`` fly candidate perception weights
(a ``recipes/train_detector.py`` or ``recipes/train_depth.py`` run) in place of
the shipped ones; each seed's object names the weights it flew. ``--map``
(``exact`` or ``estimated``; default fly_tello's ``auto``: estimated on RGB) is
fly_tello's: the depth model of the generalist's
:class:`~torchrl_causal.transforms.EgoMap` (recorded as ``map``; None for a
policy without one). ``--goal-size W H`` gives the generalist's random layouts
every board that size; at 1.0 0.8, the field guide's printed board, fly_tello's
``--arrival-head auto`` flies the shipped random-rooms head.

``--from-flights SUMMARY [SUMMARY ...]`` flies nothing: it pools ``fly_tello.py``
runs already flown (their ``summary.json``, or the folders holding one), one object
per run and one pooled object, with the same targets and, beside them, whether each
rate's 95 % interval lies on the target's side (``*_shown``). The runs must be
flights of one setting: any difference in what they flew (policy, layout, board,
perception, arrival rule, map, noise, episodes per seed) is named and refused; a seed
given twice is refused too. Without ``--compare-sim`` in the flights the
``DroneNavEnv`` fields are null, unless ``--compare-sim`` is given here: it then flies
``DroneNavEnv``'s reference for each flight that lacks one of ``--compare-perception``'s
kind (``fly_tello.py --compare-sim``'s
episodes on that flight's layouts and noise draws, ``--compare-perception``'s features; the
emulator is not flown), paired episode by episode with the flight's episode table
(``episodes.csv`` beside ``summary.json``, ``X_episodes.csv`` beside ``X_summary.json``),
and the pooled object adds the pooled pairs and the emulator's success minus
``DroneNavEnv``'s on the same episodes with its 95 % interval (``paired_difference``). The figures of docs/tello.rst's "Twelve more fresh
seeds" come from ``--from-flights docs/_static/results/tello/mirror_defaults_s*_summary.json``.
``--against SUMMARY [SUMMARY ...]`` (with ``--from-flights``) compares those flights
with flights of another setting on the same seeds -- the same layouts and noise draws --
episode by episode, as a variant is compared with a default before it becomes one: a
``{"figure": "sim_to_real_against", ...}`` object after the pooled one, with each arm's
success, agreement, false "reached", missed arrivals and crashes (with 95 % Wilson
intervals), the variant's success and agreement minus the baseline's with paired 95 %
intervals (``success_paired``, ``agreement_paired``), the counts per seed, and
``differ``: what the two settings flew differently. ``--plot PNG`` draws the success
and agreement per seed (both arms with ``--against``) beside the pooled rates. The figures of docs/tello.rst's
"Looking around before landing" come from ``--from-flights
docs/_static/results/tello/look_around_s*_summary.json --against
docs/_static/results/tello/fresh30_default_s*_summary.json``.

fly_tello's own output goes to stderr; each flight's folder (``episodes.csv``,
``summary.json``) goes under ``--out``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))

import fly_tello  # noqa: E402
from results import wilson  # noqa: E402

from torchrl_causal.pretrained import policy_dir  # noqa: E402

#: The issue's targets (simulator-judged, RGB only, noisy moves).
TARGETS = {"success_min": {"thesis": 0.85}, "agreement_min": 0.95, "false_reached_max": 0.05}


def fly(policy: str, seed: int, episodes: int, out: Path, weights: dict | None = None,
        map_depth: str | None = None, compare_perception: str = "sim",
        fresh_hits: str | None = None, goal_size=None, arrival: dict | None = None) -> dict:
    """One ``fly_tello.py`` run: the policy's scene, RGB, noise, the default arrival rule.

    ``weights`` (``{"detector": path, "depth": path}``, either may be None) flies candidate
    perception weights in place of the shipped ones; ``map_depth`` is ``fly_tello.py --map``,
    ``compare_perception`` its ``--compare-perception``, ``fresh_hits`` its ``--fresh-hits``
    (``"on"`` / ``"off"``; None: fly_tello's ``auto``),
    ``goal_size`` its ``--goal-size`` (random layouts only); ``arrival``
    (``{"height_margin": m, "mirror_check": m}``, None values left out) its
    ``--height-margin`` / ``--mirror-check``, where the policy flies a learned arrival head.
    """
    argv = ["--run", str(policy_dir(policy)), "--episodes", str(episodes), "--noise",
            "--seed", str(seed), "--compare-sim", str(episodes), "--no-video",
            "--compare-perception", compare_perception,
            "--out", str(out), "--overwrite"]
    for key, flag in (("detector", "--detector-weights"), ("depth", "--depth-weights")):
        if (weights or {}).get(key) is not None:
            argv += [flag, str(weights[key])]
    if map_depth is not None:
        argv += ["--map", map_depth]
    if fresh_hits is not None:
        argv += ["--fresh-hits", fresh_hits]
    if goal_size is not None:
        argv += ["--goal-size", *(str(v) for v in goal_size)]
    for key, value in (arrival or {}).items():
        if value is not None:
            argv += ["--" + key.replace("_", "-"), str(value)]
    with contextlib.redirect_stdout(sys.stderr):
        return fly_tello.main(argv)


def seed_figure(policy: str, seed: int, s: dict) -> dict:
    n = s["success_sim"]["n"]
    dn = s.get("dronenav") or {}
    return {"figure": "sim_to_real", "policy": policy, "seed": seed, "episodes": n,
            "layout": s.get("layout"), "goal_size": s.get("goal_size"),
            "arrival_head": s.get("arrival_head"),
            "final_approach": s.get("final_approach"),
            "success_sim": s["success_sim"]["rate"], "success_sim_ci95": s["success_sim"]["ci95"],
            "agreement": s["agreement"], "false_reached": s["false_reached"],
            "missed_reach": s["missed_reach"], "crashes": s["crashes"],
            "crash_sim": s.get("crash_sim"),
            # None: flown without --compare-sim (a --from-flights run)
            "dronenav": dn.get("rate"), "dronenav_ci95": dn.get("ci95"),
            # DroneNavEnv flies the emulator's own layouts and noise draws: per-episode pairs
            "dronenav_paired": dn.get("paired"),
            "dronenav_perception": dn.get("perception", "sim") if dn else None,
            "detector_weights": s.get("detector_weights", "shipped"),
            "depth_weights": s.get("depth_weights", "shipped"),
            "map": s.get("map"), "fresh_hits": bool(s.get("fresh_hits", False)),
            "height_margin": s.get("height_margin"), "mirror_check": s.get("mirror_check"),
            "height_approach": s.get("height_approach"),
            "wall_s": s.get("wall_s")}


def paired_difference(pairs: dict) -> dict:
    """The emulator's success minus ``DroneNavEnv``'s on the same episodes, from the paired
    counts, with its 95 % interval (the normal approximation for paired proportions).

    Example:
        >>> out = paired_difference({"both": 60, "emulator_only": 5, "dronenav_only": 25,
        ...                          "neither": 10})
        >>> out["paired_difference"], out["paired_difference_ci95"]
        (-0.2, [-0.2999, -0.1001])
    """
    diff, ci = _paired_ci(pairs["emulator_only"], pairs["dronenav_only"], sum(pairs.values()))
    return {"dronenav_paired": dict(pairs), "paired_difference": diff,
            "paired_difference_ci95": ci}


def _paired_ci(b: int, c: int, n: int) -> tuple[float, list[float]]:
    """``(b - c) / n`` for ``b`` episodes only the first arm finishes and ``c`` only the
    second, of ``n`` paired ones, with its 95 % interval (normal approximation)."""
    diff = (b - c) / n
    half = 1.96 * math.sqrt(max(b + c - (b - c) ** 2 / n, 0.0)) / n
    return round(diff, 4), [round(diff - half, 4), round(diff + half, 4)]


def _episode_verdicts(s: dict, flag: str = "--against") -> tuple[list[bool], list[bool],
                                                                  list[bool]]:
    """A flight's episode table, per episode: TelloEnv's own verdict, the simulator's and
    whether it crashed. Raises ValueError (naming ``flag``) for a missing table or one of
    another length than its summary."""
    import csv

    table = _episodes_csv(s["_file"])
    if not table.is_file():
        raise ValueError(f"{flag}: {str(s['_file'])!r} has no episode table "
                         f"({str(table)!r})")
    with table.open() as fh:
        rows = list(csv.DictReader(fh))
    if len(rows) != s["success_sim"]["n"]:
        raise ValueError(f"{flag}: {str(table)!r} has {len(rows)} episodes, its summary "
                         f"{s['success_sim']['n']}")
    return ([bool(int(r["success"])) for r in rows], [bool(int(r["success_sim"])) for r in rows],
            [bool(int(r["crash"])) for r in rows])


def against_figure(variant: list[dict], baseline: list[dict]) -> dict:
    """Flights of one setting against flights of another on the same seeds (so the same
    layouts and noise draws), episode by episode: each arm's counts with their 95 % Wilson
    intervals, and the variant's success and agreement minus the baseline's with paired
    intervals (``variant_only`` / ``baseline_only``: episodes only that arm reaches, or
    judges as the simulator does). ``differ`` names what the two settings flew differently.

    Raises:
        ValueError: the two sets of flights are not of the same seeds, or an episode table
            is missing or of another length.
    """
    by_seed = {s["seed"]: s for s in baseline}
    seeds = sorted(s["seed"] for s in variant)
    if seeds != sorted(by_seed):
        raise ValueError(f"--against: the flights are of seeds {seeds}, the baseline's of "
                         f"{sorted(by_seed)}: they must be the same seeds")
    counts = {arm: dict.fromkeys(("success", "agreed", "false_reached", "missed_reach",
                                  "crashes"), 0) for arm in ("variant", "baseline")}
    paired = {key: {"variant_only": 0, "baseline_only": 0} for key in ("success", "agreement")}
    per_seed = []
    n = 0
    for s in sorted(variant, key=lambda r: r["seed"]):
        arms = {"variant": _episode_verdicts(s), "baseline": _episode_verdicts(by_seed[s["seed"]])}
        if len(arms["variant"][0]) != len(arms["baseline"][0]):
            raise ValueError(f"--against: seed {s['seed']} flew {len(arms['variant'][0])} "
                             f"episodes, its baseline {len(arms['baseline'][0])}")
        n += len(arms["variant"][0])
        row = {"seed": s["seed"], "episodes": len(arms["variant"][0])}
        ok = {}
        for arm, (tel, sim, crash) in arms.items():
            agree = [a == b for a, b in zip(tel, sim)]
            got = {"success": sum(sim), "agreed": sum(agree),
                   "false_reached": sum(a and not b for a, b in zip(tel, sim)),
                   "missed_reach": sum(b and not a for a, b in zip(tel, sim)),
                   "crashes": sum(crash)}
            for k, v in got.items():
                counts[arm][k] += v
            row[arm] = got
            ok[arm] = {"success": sim, "agreement": agree}
        for key in paired:
            pairs = list(zip(ok["variant"][key], ok["baseline"][key]))
            paired[key]["variant_only"] += sum(a and not b for a, b in pairs)
            paired[key]["baseline_only"] += sum(b and not a for a, b in pairs)
        per_seed.append(row)
    out = {"figure": "sim_to_real_against", "policy": variant[0].get("run") or "policy",
           "seeds": seeds, "episodes": n, "differ": _setting_diff(variant[0], baseline[0])}
    for arm, c in counts.items():
        out[arm] = dict(c)
        for k, key in (("success", "success_ci95"), ("agreed", "agreement_ci95"),
                       ("false_reached", "false_reached_ci95")):
            lo, hi = wilson(c[k], n)
            out[arm][key] = [round(lo, 4), round(hi, 4)]
    for key, pairs in paired.items():
        diff, ci = _paired_ci(pairs["variant_only"], pairs["baseline_only"], n)
        out[f"{key}_paired"] = {**pairs, "difference": diff, "ci95": ci}
    out["per_seed"] = per_seed
    return out


def pooled_figure(policy: str, figures: list[dict]) -> dict:
    """All seeds of a policy together, with the issue's targets (``*_shown``: the rate's
    95 % Wilson interval lies wholly on the target's side)."""
    n = sum(f["episodes"] for f in figures)
    k = round(sum(f["success_sim"] * f["episodes"] for f in figures))
    agree = round(sum(f["agreement"] * f["episodes"] for f in figures))
    false = sum(f["false_reached"] for f in figures)
    lo, hi = wilson(k, n)
    alo, ahi = wilson(agree, n)
    flo, fhi = wilson(false, n)
    crash_sim = {}
    for f in figures:
        for kind, count in (f.get("crash_sim") or {}).items():
            crash_sim[kind] = crash_sim.get(kind, 0) + count
    with_dn = all(f["dronenav"] is not None for f in figures)
    out = {"figure": "sim_to_real_pooled", "policy": policy,
           "seeds": [f["seed"] for f in figures], "episodes": n,
           "success_sim": round(k / n, 4), "success_sim_ci95": [round(lo, 4), round(hi, 4)],
           "agreement": round(agree / n, 4), "agreement_ci95": [round(alo, 4), round(ahi, 4)],
           "agreed": agree, "false_reached": false,
           "false_reached_rate": round(false / n, 4),
           "false_reached_ci95": [round(flo, 4), round(fhi, 4)],
           "missed_reach": sum(f["missed_reach"] for f in figures),
           "crashes": sum(f["crashes"] for f in figures), "crash_sim": crash_sim,
           "dronenav": None, "dronenav_ci95": None}
    if with_dn:
        kd = round(sum(f["dronenav"] * f["episodes"] for f in figures))
        dlo, dhi = wilson(kd, n)
        out.update(dronenav=round(kd / n, 4), dronenav_ci95=[round(dlo, 4), round(dhi, 4)])
        if all(f["dronenav_paired"] for f in figures):
            out.update(paired_difference(
                {k: sum(f["dronenav_paired"][k] for f in figures)
                 for k in ("both", "emulator_only", "dronenav_only", "neither")}))
    target = TARGETS["success_min"].get(policy)
    out["targets"] = {
        "inside_dronenav_ci": bool(dlo <= k / n <= dhi) if with_dn else None,
        "agreement": bool(agree / n >= TARGETS["agreement_min"]),
        "agreement_shown": bool(alo >= TARGETS["agreement_min"]),
        "false_reached": bool(false / n < TARGETS["false_reached_max"]),
        "false_reached_shown": bool(fhi < TARGETS["false_reached_max"]),
        **({"success": bool(k / n >= target)} if target is not None else {})}
    return out


#: What a flight's summary.json records about its outcome, not its setting (and its seed).
_OUTCOME_KEYS = fly_tello.SUMMARY_OUTCOME_KEYS | {"seed"}


def _load_flights(paths: list[Path]) -> list[dict]:
    """``fly_tello.py`` summaries, checked to be flights of one setting. Raises ValueError
    naming a missing file, a summary of another kind, a seed given twice, or the keys whose
    values differ between runs."""
    runs = []
    for path in paths:
        f = path / "summary.json" if path.is_dir() else path
        if not f.is_file():
            raise ValueError(f"--from-flights: {str(path)!r} is neither a summary.json nor a "
                             "folder holding one")
        s = json.loads(f.read_text())
        if "agreement" not in s or "success_sim" not in s or "seed" not in s:
            raise ValueError(f"--from-flights: {str(f)!r} is not a fly_tello.py emulator "
                             "summary (no agreement / success_sim / seed)")
        # the run folder's path may be written absolute: compare the policy by its name
        run_path = str(s.get("run", ""))
        s["run"] = Path(run_path).name
        if s.get("arrival_head"):
            s["arrival_head"] = Path(str(s["arrival_head"])).name
        runs.append((f, s, run_path))
    seeds = [s["seed"] for _, s, _ in runs]
    twice = sorted({x for x in seeds if seeds.count(x) > 1})
    if twice:
        raise ValueError(f"--from-flights: seed(s) {twice} given more than once")
    for f, s, _ in runs[1:]:
        diff = _setting_diff(runs[0][1], s)
        if diff:
            raise ValueError(f"--from-flights: {str(f)!r} flew another setting than "
                             f"{str(runs[0][0])!r}: {', '.join(diff)} differ")
    for f, s, run_path in runs:  # where each came from (not part of its setting)
        s["_file"], s["_run_path"] = f, run_path
    return [s for _, s, _ in runs]


def _setting_diff(a: dict, b: dict) -> dict:
    """The setting keys two flight summaries disagree on, each with ``[a's, b's]`` value
    (outcome keys and the loader's own ``_`` keys left out)."""
    keys = {k for k in set(a) | set(b) if k not in _OUTCOME_KEYS and not k.startswith("_")}
    return {k: [a.get(k), b.get(k)] for k in sorted(keys) if a.get(k) != b.get(k)}


def _episodes_csv(summary_file: Path) -> Path:
    """The episode table beside a summary: ``summary.json`` -> ``episodes.csv`` in a flight
    folder, ``X_summary.json`` -> ``X_episodes.csv`` where flights are kept side by side."""
    name = summary_file.name
    return summary_file.with_name("episodes.csv" if name == "summary.json"
                                  else name[: -len("summary.json")] + "episodes.csv")


def dronenav_reference(s: dict, perception: str, out: Path, verdicts=None,
                       depth_weights: Path | None = None) -> dict:
    """``DroneNavEnv``'s reference for a flight already flown (its ``summary.json`` ``s``, as
    :func:`_load_flights` read it): ``fly_tello.py --compare-sim``'s episodes on that flight's
    layouts and noise draws, with ``perception``'s features, paired with ``verdicts`` (the
    flight's simulator verdicts, :func:`_verdicts`) where given; ``depth_weights`` is the
    MonoDepth the flight flew (:func:`_flown_depth_weights`; None: the shipped one), read with
    ``perception="rgb"``. The emulator is not flown."""
    n, seed = int(s["success_sim"]["n"]), int(s["seed"])
    run = Path(s["_run_path"])
    if not run.is_absolute() and not run.is_dir():
        run = ROOT / run
    if not (run / "config.yaml").is_file():
        run = policy_dir(s["run"])
    argv = ["--run", str(run), "--episodes", str(n), "--seed", str(seed), "--compare-sim",
            str(n), "--compare-perception", perception, "--no-video", "--out", str(out),
            "--overwrite"]
    argv += ["--noise"] if s.get("noise") else []
    argv += ["--layout", s["layout"]] if s.get("layout") else []
    argv += ["--goal-size", *(str(v) for v in s["goal_size"])] if s.get("goal_size") else []
    argv += ["--board-back", s["board_back"]] if s.get("board_back") else []
    if s.get("map"):  # a policy with a map: its depth model, and fresh hits as flown
        argv += ["--map", s["map"], "--fresh-hits", "on" if s.get("fresh_hits") else "off"]
    if perception == "rgb" and depth_weights is not None:
        argv += ["--depth-weights", str(depth_weights)]
    with contextlib.redirect_stdout(sys.stderr):
        return fly_tello.dronenav_reference(fly_tello.parse_args(argv), verdicts)


def _flown_depth_weights(s: dict) -> Path | None:
    """The MonoDepth weights a flight flew (its ``--depth-weights``; None: the shipped
    ones). Raises ValueError naming them when they are no longer there."""
    if not s.get("depth_weights"):
        return None
    weights = Path(s["depth_weights"])
    if not weights.is_absolute() and not weights.is_file():
        weights = ROOT / weights
    if not weights.is_file():
        raise ValueError(f"--compare-perception rgb: {str(s['_file'])!r} flew MonoDepth "
                         f"weights {s['depth_weights']!r}, which are not there")
    return weights


def _verdicts(s: dict) -> list[int] | None:
    """The simulator's verdict per episode from the episode table beside a flight's
    summary (None without one). Raises ValueError for a table of another length."""
    if not _episodes_csv(s["_file"]).is_file():
        return None
    return [int(v) for v in _episode_verdicts(s, "--compare-sim")[1]]


def plot_flights(figures: list[dict], path: Path) -> Path:
    """Per seed, the simulator-judged success and the arrival rule's agreement of a
    ``--from-flights`` run (its ``sim_to_real`` objects; with a ``sim_to_real_against`` one
    last, both arms side by side), the pooled rates with their 95 % intervals at the right
    and the targets as dashed lines; written to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    against = figures[-1] if figures[-1]["figure"] == "sim_to_real_against" else None
    pooled = next(f for f in figures if f["figure"] == "sim_to_real_pooled")
    if against is not None:
        rows = against["per_seed"]
        seeds = [r["seed"] for r in rows]
        arms = {arm: {k: [r[arm][c] / r["episodes"] for r in rows]
                      for k, c in (("success", "success"), ("agreement", "agreed"))}
                for arm in ("variant", "baseline")}
        total = {arm: {"success": (against[arm]["success"] / against["episodes"],
                                   against[arm]["success_ci95"]),
                       "agreement": (against[arm]["agreed"] / against["episodes"],
                                     against[arm]["agreement_ci95"])} for arm in arms}
        label = {arm: ", ".join(f"{k}={v[i]}" for k, v in against["differ"].items()) or arm
                 for i, arm in enumerate(("variant", "baseline"))}
    else:
        seeds = [f["seed"] for f in figures if f["figure"] == "sim_to_real"]
        per = [f for f in figures if f["figure"] == "sim_to_real"]
        arms = {"flights": {"success": [f["success_sim"] for f in per],
                            "agreement": [f["agreement"] for f in per]}}
        total = {"flights": {"success": (pooled["success_sim"], pooled["success_sim_ci95"]),
                             "agreement": (pooled["agreement"], pooled["agreement_ci95"])}}
        label = {"flights": "flights"}
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), sharey=False)
    width = 0.8 / len(arms)
    x = list(range(len(seeds)))
    for ax, key, target in ((axes[0], "success", None),
                            (axes[1], "agreement", TARGETS["agreement_min"])):
        for i, (arm, vals) in enumerate(arms.items()):
            off = (i - (len(arms) - 1) / 2) * width
            bars = ax.bar([v + off for v in x], vals[key], width, label=label[arm])
            rate, (lo, hi) = total[arm][key]
            ax.errorbar([len(seeds) + 0.5 + off], [rate], yerr=[[rate - lo], [hi - rate]],
                        fmt="o", color=bars.patches[0].get_facecolor(), capsize=4)
        if key == "success" and pooled.get("dronenav") is not None and against is None:
            ax.axhline(pooled["dronenav"], color="k", ls=":", lw=1,
                       label="DroneNavEnv, same episodes")
        if target is not None:
            ax.axhline(target, color="k", ls="--", lw=1, label=f"target {target:g}")
        ax.set_xticks(x + [len(seeds) + 0.5], [str(s) for s in seeds] + ["all"], rotation=60)
        ax.set_xlabel("emulator seed")
        ax.set_title({"success": "success (simulator-judged)",
                      "agreement": "arrival rule agrees with the simulator"}[key])
        ax.set_ylim(0.4 if key == "success" else 0.8, 1.0)
        ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--policies", nargs="+", default=["thesis"],
                   help="shipped policies (torchrl_causal.pretrained): thesis, generalist")
    p.add_argument("--seeds", nargs="+", type=int, default=[7, 11],
                   help="emulator seeds: each flies its own noise draws (and layouts)")
    p.add_argument("--episodes", type=int, default=50, help="episodes per seed")
    p.add_argument("--out", type=Path, default=ROOT / "outputs" / "sim_to_real")
    p.add_argument("--detector-weights", type=Path, default=None,
                   help="candidate YOLO weights to fly instead of the shipped ones")
    p.add_argument("--depth-weights", type=Path, default=None,
                   help="candidate MonoDepth weights to fly instead of the shipped ones")
    p.add_argument("--map", choices=("exact", "estimated"), default=None,
                   help="fly_tello.py --map: EgoMap's depth model for a policy that reads its "
                        "map (default: fly_tello's auto, estimated on RGB)")
    p.add_argument("--fresh-hits", nargs="?", const="on", default=None, choices=("on", "off"),
                   help="fly_tello.py --fresh-hits on / off (on needs the estimated map): what "
                        "the current frame reads is an obstacle for that step (default: "
                        "fly_tello's auto, on with the estimated map; a bare --fresh-hits is on)")
    p.add_argument("--goal-size", type=float, nargs=2, default=None, metavar=("W", "H"),
                   help="fly_tello.py --goal-size for the generalist's random layouts, e.g. "
                        "1.0 0.8, the printed board (the thesis scene keeps its own)")
    p.add_argument("--compare-perception", choices=("sim", "rgb"), default="sim",
                   help="fly_tello.py --compare-perception: DroneNavEnv's reference with the "
                        "simulator's perception (default) or the flights' MonoDepth (the "
                        "goal keys stay DroneNavEnv's own)")
    p.add_argument("--height-margin", type=float, default=None, metavar="M",
                   help="fly_tello.py --height-margin for the generalist's flights (its "
                        "learned arrival head; default: off)")
    p.add_argument("--mirror-check", type=float, default=None, metavar="M",
                   help="fly_tello.py --mirror-check for the generalist's flights: the head read "
                        "on each frame and its mirror image (default: fly_tello's auto)")
    p.add_argument("--from-flights", nargs="+", type=Path, default=None, metavar="SUMMARY",
                   help="fly nothing: pool these fly_tello.py runs (summary.json files or their "
                        "folders), flights of one setting")
    p.add_argument("--against", nargs="+", type=Path, default=None, metavar="SUMMARY",
                   help="with --from-flights: compare those flights with these, flights of "
                        "another setting on the same seeds, episode by episode (one "
                        "sim_to_real_against object after the pooled one)")
    p.add_argument("--plot", type=Path, default=None, metavar="PNG",
                   help="with --from-flights: draw success and agreement per seed (with "
                        "--against, both settings side by side) to this PNG")
    p.add_argument("--compare-sim", action="store_true",
                   help="with --from-flights: fly DroneNavEnv's reference (fly_tello.py "
                        "--compare-sim, --compare-perception's features) for each flight that "
                        "flew without one (or with another perception), on its own layouts "
                        "and noise draws, paired "
                        "episode by episode with its episode table; the emulator is not flown")
    a = p.parse_args(argv)
    for flag, value in (("--against", a.against), ("--plot", a.plot)):
        if value is not None and a.from_flights is None:
            p.error(f"{flag} reads flights already flown: give them with --from-flights")
    if a.plot is not None and a.plot.suffix.lower() != ".png":
        p.error(f"--plot writes a PNG, got {str(a.plot)!r}")
    if a.from_flights is not None:
        try:
            runs = _load_flights(a.from_flights)
            baseline = _load_flights(a.against) if a.against is not None else None
            against = against_figure(runs, baseline) if baseline is not None else None
        except ValueError as e:
            p.error(str(e))
        name = runs[0]["run"] or "policy"
        if a.compare_sim:
            # a flight keeps a reference it was flown with, of the asked-for perception
            todo = [s for s in runs if s.get("dronenav") is None
                    or s["dronenav"].get("perception", "sim") != a.compare_perception]
            try:  # the episode tables first: a wrong one is named before any flight
                verdicts = [_verdicts(s) for s in todo]
                # and the MonoDepth each flew, still there
                weights = [_flown_depth_weights(s) if a.compare_perception == "rgb" else None
                           for s in todo]
            except ValueError as e:
                p.error(str(e))
            for s, v, w in zip(todo, verdicts, weights):
                s["dronenav"] = dronenav_reference(
                    s, a.compare_perception, a.out / f"{name}_seed{s['seed']}_dronenav", v, w)
        figures = [seed_figure(name, s["seed"], s) for s in sorted(runs, key=lambda r: r["seed"])]
        for f in figures:
            print(json.dumps(f), flush=True)
        figures.append(pooled_figure(name, figures))
        print(json.dumps(figures[-1]), flush=True)
        if against is not None:
            figures.append(against)
            print(json.dumps(against), flush=True)
        if a.plot is not None:
            plot_flights(figures, a.plot)
        return figures
    if a.compare_sim:
        p.error("--compare-sim is for --from-flights: flights flown here fly DroneNavEnv's "
                "reference beside them anyway")
    if a.episodes < 1:
        p.error(f"--episodes must be >= 1, got {a.episodes}")
    if a.fresh_hits == "on" and a.map == "exact":
        p.error("--fresh-hits needs the estimated map, got --map exact")
    for flag, value in (("--height-margin", a.height_margin), ("--mirror-check", a.mirror_check)):
        why = None if value is None else fly_tello.head_distance_error(flag, value)
        if why is not None:  # fly_tello's own bounds, before the first flight
            p.error(why)
    if a.goal_size is not None:
        from torchrl_causal.envs.layouts import check_goal_size

        try:
            check_goal_size(a.goal_size)
        except ValueError as e:
            p.error(f"--goal-size must be two sizes the layouts take: {e}")
    for flag, path in (("--detector-weights", a.detector_weights),
                       ("--depth-weights", a.depth_weights)):
        if path is not None and not path.is_file():
            p.error(f"{flag}: {str(path)!r} is not a file")
    weights = {"detector": a.detector_weights, "depth": a.depth_weights}
    for name in a.policies:
        try:
            policy_dir(name)
        except (KeyError, ValueError, FileNotFoundError) as e:
            p.error(f"--policies: {name!r} is not a shipped policy ({e})")
    figures = []
    for name in a.policies:
        per_seed = []
        for seed in a.seeds:
            s = fly(name, seed, a.episodes, a.out / f"{name}_seed{seed}", weights, a.map,
                    a.compare_perception, a.fresh_hits,
                    a.goal_size if name != "thesis" else None,
                    # the thesis scene's head has no in-view output and was not measured so
                    None if name == "thesis" else {"height_margin": a.height_margin,
                                                   "mirror_check": a.mirror_check})
            per_seed.append(seed_figure(name, seed, s))
            print(json.dumps(per_seed[-1]), flush=True)
        figures += per_seed
        figures.append(pooled_figure(name, per_seed))
        print(json.dumps(figures[-1]), flush=True)
    return figures


if __name__ == "__main__":
    main()
