"""Where the arrival decision goes wrong, step by step. One JSON object per figure.

::

    python recipes/fly_tello.py --run torchrl_causal/pretrained/policies/generalist \\
        --layout heldout --episodes 50 --noise --goal-size 1.0 0.8 --seed 23 \\
        --log-steps --no-video --out flights/s23
    python benchmarks/arrival_steps.py flights/s23/steps.jsonl [more steps.jsonl ...]
    python benchmarks/arrival_steps.py    # the kept logs: docs/_static/results/tello/steps/

Reads the per-step records of emulated flights (``fly_tello.py --log-steps``: the
action, whether the detector saw the board, the arrival head's estimate, the verdicts,
and the drone's true offset from the goal point in the board's frame) and prints:

* ``near_goal``: the steps that end within 0.2 m of the goal point (the simulator's
  sphere), how many of them the detector saw the board on and the head was asked
  on, and how far the drone was turned from facing the board on the steps with
  and without the board in sight;
* ``missed``: the episodes the simulator counts as arrived and ``TelloEnv`` does
  not, with what the camera path did on the step of the pass (the first step whose
  segment entered the sphere) and how the episode ended;
* ``false_reached``: the episodes ``TelloEnv`` ended as arrived that never entered
  the sphere, with the true offset and the head's estimate on the last step;
* ``head_error``: the head's error (m) against the true ``(ahead, lateral)``, by the
  true sideways offset (inside and beyond the 0.6 m the shipped random-rooms head
  was trained on) and by whether the board was in sight (a held board: not).
* ``threshold_counterfactual``: the verdicts of the same flights had ``TelloEnv``
  also fired wherever the head's 3-D estimate lay within ``t`` of the goal point
  (``--thresholds``). Such a rule changes nothing before its first extra firing, so
  its verdicts read off the logs exactly: the episode ends at that step, and the
  simulator's verdict is whether the drone had entered the sphere by then. Per ``t``:
  the episodes that agree, the flights it lands early (a success before, now outside
  the sphere) and the missed arrivals it catches.

Inputs: ``steps.jsonl`` files, gzipped ones (``.jsonl.gz``) or flight folders holding
a ``steps.jsonl``.

Results: docs/tello.rst, "Step by step at the goal" (and, for ``climb_firings``, "Climbs
that read a new place").
"""

from __future__ import annotations

import argparse
import gzip
import json
import math
import os
from pathlib import Path

os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only

import numpy as np  # noqa: E402

SPHERE = 0.2  # the simulator's reach radius (m)
#: the step logs kept of the generalist's fresh-seed flights (docs/tello.rst)
KEPT_LOGS = Path(__file__).resolve().parents[1] / "docs" / "_static" / "results" / "tello" / "steps"
LATERAL_BINS = ((0.0, 0.3), (0.3, 0.6), (0.6, math.inf))


def load_episodes(paths) -> list[list[dict]]:
    """The records of ``steps.jsonl`` files, one list of steps per episode, in order."""
    episodes = []
    for path in map(Path, paths):
        if path.is_dir():
            path = path / "steps.jsonl"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such steps.jsonl (fly_tello.py --log-steps "
                                    "writes one into each flight folder)")
        current, last_ep = None, None
        with (gzip.open(path, "rt") if path.suffix == ".gz" else open(path)) as f:
            for line in f:
                if not line.strip():
                    continue
                rec = json.loads(line)
                if "true_offset" not in rec:
                    raise ValueError(f"{path}: a step without 'true_offset' (a real-drone "
                                     "flight: the figures need the emulator's ground truth)")
                if rec["episode"] != last_ep:
                    current, last_ep = [], rec["episode"]
                    episodes.append(current)
                current.append(rec)
    return episodes


def _norm(v) -> float:
    return float(np.linalg.norm(np.asarray(v, float)))


def figures(episodes: list[list[dict]]) -> list[dict]:
    """The four figures (see the module docstring) of ``episodes``.

    Example:
        >>> step = lambda **kw: {"in_sight": True, "arrival_estimate": None, "reached": False,
        ...                      "crashed": False, "sim_reached": False, "action": "forward",
        ...                      "true_offset": [1.0, 0.0, 0.0], **kw}
        >>> ep = [step(), step(true_offset=[0.05, 0.0, 0.0], in_sight=False, sim_reached=True),
        ...       step(true_offset=[-0.3, 0.0, 0.0], sim_reached=True, crashed=True)]
        >>> figs = figures([ep])
        >>> figs[0]["steps"], figs[0]["in_sight"], figs[1]["episodes"]
        (1, 0, 1)
        >>> figs[1]["pass_step"][0]["in_sight"], figs[1]["pass_step"][0]["ended"]
        (False, 'crash')
    """
    near = [s for ep in episodes for s in ep if _norm(s["true_offset"]) <= SPHERE]
    out = [{"figure": "near_goal", "episodes": len(episodes), "steps": len(near),
            "in_sight": sum(s["in_sight"] for s in near),
            "head_asked": sum(s["arrival_estimate"] is not None for s in near)}]
    if near and all("true_yaw_off_deg" in s for s in near):  # logs from 2026-11-28 on
        for seen in (True, False):
            yaw = [abs(s["true_yaw_off_deg"]) for s in near if s["in_sight"] == seen]
            out[0][f"yaw_off_deg_{'seen' if seen else 'unseen'}_pct_10_50_90"] = (
                [round(float(v), 1) for v in np.percentile(yaw, [10, 50, 90])] if yaw else None)
        out[0]["unseen_turned_over_45_deg"] = sum(
            not s["in_sight"] and abs(s["true_yaw_off_deg"]) > 45 for s in near)
    missed, false = [], []
    for ep in episodes:
        last = ep[-1]
        if last["sim_reached"] and not last["reached"]:
            k = next(i for i, s in enumerate(ep) if s["sim_reached"])
            s = ep[k]
            missed.append({"in_sight": s["in_sight"], "head_asked": s["arrival_estimate"] is not None,
                           "true_m": round(_norm(s["true_offset"]), 3), "action": s["action"],
                           "yaw_off_deg": s.get("true_yaw_off_deg"),
                           "steps_after": len(ep) - 1 - k,
                           "steps_inside": sum(_norm(x["true_offset"]) <= SPHERE for x in ep[k:]),
                           "head_asked_near": any(x["arrival_estimate"] is not None
                                                  for x in ep[max(0, k - 4):k + 5]),
                           "head_never_asked": all(x["arrival_estimate"] is None
                                                   for x in ep[:k + 1]),
                           "ended": "crash" if last["crashed"] else (
                               "out_of_bounds" if last.get("out_of_bounds") else "step_limit")})
        if last["reached"] and not last["sim_reached"]:
            false.append({"true_ahead_lateral": [round(v, 3) for v in last["true_offset"][:2]],
                          "estimate": last["arrival_estimate"], "in_sight": last["in_sight"],
                          "action": last["action"]})
    out.append({"figure": "missed", "episodes": len(missed), "pass_step": missed,
                "board_unseen_at_pass": sum(not m["in_sight"] for m in missed),
                "turned_over_45_deg_at_pass": sum(abs(m["yaw_off_deg"] or 0.0) > 45
                                                  for m in missed),
                "head_asked_within_4_steps": sum(m["head_asked_near"] for m in missed),
                "head_never_asked_before_pass": sum(m["head_never_asked"] for m in missed),
                "entered_at_0_15_m_or_more": sum(m["true_m"] >= 0.15 for m in missed),
                "inside_for_2_steps_or_fewer": sum(m["steps_inside"] <= 2 for m in missed),
                "ended_in_crash": sum(m["ended"] == "crash" for m in missed)})
    out.append({"figure": "false_reached", "episodes": len(false), "last_step": false,
                "beyond_0_6_m_sideways": sum(abs(f["true_ahead_lateral"][1]) > 0.6
                                             for f in false)})
    errs = {}
    for ep in episodes:
        for s in ep:
            est = s["arrival_estimate"]
            if est is None:
                continue
            t = s["true_offset"]
            lat = abs(t[1])
            b = next(f"{lo:g}-{hi:g}" for lo, hi in LATERAL_BINS if lo <= lat < hi)
            key = (b, "seen" if s["in_sight"] else "held")
            errs.setdefault(key, []).append(
                (abs(est[0] - t[0]), abs(est[1] - t[1])))
    rows = []
    for (b, seen), e in sorted(errs.items()):
        e = np.asarray(e)
        rows.append({"true_lateral_m": b, "board": seen, "n": len(e),
                     "ahead_err_median": round(float(np.median(e[:, 0])), 3),
                     "lateral_err_median": round(float(np.median(e[:, 1])), 3),
                     "lateral_err_p90": round(float(np.percentile(e[:, 1], 90)), 3)})
    out.append({"figure": "head_error", "bins": rows})
    return out


def threshold_counterfactual(episodes: list[list[dict]], thresholds) -> dict:
    """The ``threshold_counterfactual`` figure (see the module docstring).

    Example:
        >>> step = lambda d, sim, est=None, reached=False: {
        ...     "true_offset": [d, 0.0, 0.0], "sim_reached": sim, "reached": reached,
        ...     "arrival_estimate": est}
        >>> early = [step(0.3, False, [0.15, 0, 0]), step(0.1, True, [0.1, 0, 0], True)]
        >>> missed = [step(0.1, True, [0.15, 0, 0]), step(0.5, True)]
        >>> fig = threshold_counterfactual([early, missed], [0.13, 0.16])
        >>> [(r["threshold_m"], r["agree"], r["lands_early"], r["catches"]) for r in fig["rows"]]
        [(0.13, 1, 0, 0), (0.16, 1, 1, 1)]
    """
    rows = []
    for t in thresholds:
        agree = early = caught = 0
        for ep in episodes:
            last = len(ep) - 1
            fire = next((i for i, s in enumerate(ep) if s["arrival_estimate"] is not None
                         and _norm(s["arrival_estimate"]) <= t), None)
            reached, sim = bool(ep[-1]["reached"]), bool(ep[-1]["sim_reached"])
            if fire is None or (reached and fire >= last):  # as flown
                agree += reached == sim
                continue
            now = bool(ep[fire]["sim_reached"])  # "reached" at that step
            agree += now
            early += reached and sim and not now
            caught += sim and not reached and now
        rows.append({"threshold_m": t, "agree": agree, "lands_early": early, "catches": caught})
    flown = sum(bool(ep[-1]["reached"]) == bool(ep[-1]["sim_reached"]) for ep in episodes)
    return {"figure": "threshold_counterfactual", "episodes": len(episodes),
            "agree_as_flown": flown, "rows": rows}


CLIMBS = ("ascend", "descend")


def climb_firings(episodes: list[list[dict]], max_goal_offset: float = 0.13) -> dict:
    """The ``climb_firings`` figure (see the module docstring).

    Example:
        >>> step = lambda action, est, sim=False, reached=False, approaches=0: {
        ...     "action": action, "arrival_estimate": est, "sim_reached": sim,
        ...     "reached": reached, "approaches": approaches, "true_offset": [0.0, 0.4, 0.0]}
        >>> false = [step("forward", [0.0, -0.42, 0.02]), step("descend", [0.1, 0.0, -0.26],
        ...                                                     reached=True)]
        >>> fig = climb_firings([false])
        >>> fig["false"]["n"], fig["false"]["withheld_nearer"], fig["true"]["n"]
        (1, 1, 0)
    """
    rows = {True: [], False: []}
    other = {True: 0, False: 0}
    for ep in episodes:
        i = next((k for k, x in enumerate(ep) if x["reached"]), None)
        if i is None:
            continue
        s, prev = ep[i], ep[i - 1] if i else None
        sim = bool(ep[-1]["sim_reached"])
        cur, before = s["arrival_estimate"], prev and prev["arrival_estimate"]
        if (s["action"] not in CLIMBS or cur is None or before is None
                or s.get("approaches", 0) > prev.get("approaches", 0)):
            other[sim] += 1
            continue
        near = before if abs(before[2]) <= abs(cur[2]) else cur  # the reading nearer the height
        dz = 0.0 if before[2] * cur[2] <= 0 else min(abs(before[2]), abs(cur[2]))
        rows[sim].append({"jump_m": math.hypot(cur[0] - before[0], cur[1] - before[1]),
                          "dz_after_m": abs(cur[2]),
                          "withheld": math.hypot(math.hypot(near[0], near[1]), dz)
                          > max_goal_offset})

    def summary(rs):
        out = {"n": len(rs), "withheld_nearer": sum(r["withheld"] for r in rs)}
        for key in ("jump_m", "dz_after_m"):
            v = [r[key] for r in rs]
            out[f"{key}_pct_50_90"] = ([round(float(x), 3) for x in np.percentile(v, [50, 90])]
                                       if v else None)
        return out

    return {"figure": "climb_firings", "episodes": len(episodes),
            "max_goal_offset_m": max_goal_offset, "false": summary(rows[False]),
            "true": summary(rows[True]), "other_firings_false": other[False],
            "other_firings_true": other[True]}


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("steps", nargs="*", metavar="STEPS",
                   help="steps.jsonl (or .jsonl.gz) files or flight folders "
                        "(fly_tello.py --log-steps writes them; default: the kept logs of "
                        "the generalist's fresh seeds, docs/_static/results/tello/steps/)")
    p.add_argument("--thresholds", type=float, nargs="+",
                   default=[0.13, 0.14, 0.15, 0.16, 0.18, 0.2], metavar="T",
                   help="the threshold_counterfactual figure's thresholds (m, in (0, 1])")
    a = p.parse_args(argv)
    bad = [t for t in a.thresholds if not (math.isfinite(t) and 0.0 < t <= 1.0)]
    if bad:
        p.error(f"--thresholds must be in (0, 1] m, got {bad}")
    episodes = load_episodes(a.steps or sorted(KEPT_LOGS.glob("*_steps.jsonl.gz")))
    figs = figures(episodes) + [threshold_counterfactual(episodes, a.thresholds),
                                climb_firings(episodes)]
    for fig in figs:
        print(json.dumps(fig), flush=True)
    return figs


if __name__ == "__main__":
    main()
