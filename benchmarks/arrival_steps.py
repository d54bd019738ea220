"""Where the arrival decision goes wrong, step by step. One JSON object per figure.

::

    python recipes/fly_tello.py --run torchrl_causal/pretrained/policies/generalist \\
        --layout heldout --episodes 50 --noise --goal-size 1.0 0.8 --seed 23 \\
        --log-steps --no-video --out flights/s23
    python benchmarks/arrival_steps.py flights/s23/steps.jsonl [more steps.jsonl ...]

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

Results: docs/tello.rst, "Step by step at the goal".
"""

from __future__ import annotations

import json
import math
import os
import sys

os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only

import numpy as np  # noqa: E402

SPHERE = 0.2  # the simulator's reach radius (m)
LATERAL_BINS = ((0.0, 0.3), (0.3, 0.6), (0.6, math.inf))


def load_episodes(paths) -> list[list[dict]]:
    """The records of ``steps.jsonl`` files, one list of steps per episode, in order."""
    episodes = []
    for path in paths:
        current, last_ep = None, None
        with open(path) as f:
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
                           "ended": "crash" if last["crashed"] else (
                               "out_of_bounds" if last.get("out_of_bounds") else "step_limit")})
        if last["reached"] and not last["sim_reached"]:
            false.append({"true_ahead_lateral": [round(v, 3) for v in last["true_offset"][:2]],
                          "estimate": last["arrival_estimate"], "in_sight": last["in_sight"],
                          "action": last["action"]})
    out.append({"figure": "missed", "episodes": len(missed), "pass_step": missed,
                "board_unseen_at_pass": sum(not m["in_sight"] for m in missed),
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


def main(argv=None) -> list[dict]:
    paths = list(sys.argv[1:] if argv is None else argv)
    if not paths:
        raise SystemExit("usage: arrival_steps.py STEPS.jsonl [STEPS.jsonl ...] "
                         "(fly_tello.py --log-steps writes them)")
    figs = figures(load_episodes(paths))
    for fig in figs:
        print(json.dumps(fig), flush=True)
    return figs


if __name__ == "__main__":
    main()
