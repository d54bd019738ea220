"""Which depth range holds the generalist's RGB shortfall: MonoDepth with the truth below T.

::

    python benchmarks/depth_range_oracle.py                        # T = 0, 1, inf; seeds 733, 741
    python benchmarks/depth_range_oracle.py --below 0 0.6 1 2 3 inf --seeds 749 757 --episodes 50
    python benchmarks/depth_range_oracle.py --below 0 --ego-map max_range=2.5   # a map option too
    python benchmarks/depth_range_oracle.py --below 0 --depth-weights W.pt      # candidate MonoDepth
    python benchmarks/depth_range_oracle.py --pool runs/*.jsonl   # pair arms flown in several runs

The shipped generalist flies :class:`~torchrl_causal.envs.DroneNavEnv` as
``recipes/fly_tello.py --compare-sim --compare-perception rgb`` flies it (held-out
layouts, the printed 1.0 x 0.8 m board with a blank back, the Tello's move noise, the
shipped MonoDepth on the env's 84 x 84 renders, the estimated map with fresh hits), but
every pixel whose **simulator depth is below T metres** keeps that true depth in place
of MonoDepth's reading. ``T = 0`` is the RGB flight as it is; ``T = inf`` is the
simulator's depth everywhere, with the RGB flight's map and options. Every arm flies the
same episodes (layouts and noise draws from ``--seeds``), so the arms are paired episode
by episode. What ``T`` buys is what a perfect depth reading *within T* would be worth to
this policy: an upper bound on any near-range sensor or estimator.

This is a test aid, as the emulator's ``sim_depth_estimator``: it reads the simulator's
depth, which no drone has. It swaps the step of
:class:`~torchrl_causal.transforms.EstimatedDepth` for one that also reads the ``depth``
the env wrote before the estimate replaces it (:func:`oracle_depth` does the fusion).

An arm is ``--below``'s T with ``--depth-weights`` (candidate MonoDepth weights in place
of the shipped ones, ``recipes/fly_tello.py --depth-weights``) and ``--ego-map`` options.
Prints one JSON object per arm and seed (``{"figure": "depth_range_oracle", "arm",
"below", "depth_weights", "ego_map", "seed", "success", "n", "ci95", "mean_length",
"success_per_episode"}``), then one per arm pooled over the seeds all arms flew, with its
paired difference from the first arm
(``{"figure": "depth_range_oracle_pooled", ...}``: ``gains`` / ``losses`` are the
episodes only this arm / only the first arm finished, ``paired_difference`` the
difference of proportions with its 95 % interval ``paired_ci95``). Data of docs/tello.rst's "Which depth
range the RGB shortfall is in": ``docs/_static/results/tello/depth_range_oracle.jsonl``.
"""

from __future__ import annotations

import argparse
import contextlib
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

import torch  # noqa: E402

import fly_tello  # noqa: E402
from results import wilson  # noqa: E402

from torchrl_causal.pretrained import policy_dir  # noqa: E402
from torchrl_causal.transforms.estimated_depth import EstimatedDepth  # noqa: E402


def check_below(below) -> float:
    """``below`` as a float, or a ValueError naming it: a number >= 0 (m) or inf."""
    if not (isinstance(below, (int, float)) and not isinstance(below, bool) and below >= 0
            and not math.isnan(below)):
        raise ValueError(f"below must be a number >= 0 (m) or inf, got {below!r}")
    return float(below)


def oracle_depth(true: torch.Tensor, estimate: torch.Tensor, below: float) -> torch.Tensor:
    """The estimate, with the true depth wherever the truth is below ``below`` metres
    (``0``: the estimate as it is; ``inf``: the truth everywhere)."""
    below = check_below(below)
    if true.shape != estimate.shape:
        raise ValueError(f"true depth {tuple(true.shape)} and estimate "
                         f"{tuple(estimate.shape)} differ in shape")
    if below == 0:
        return estimate
    return torch.where(true < below, true.to(estimate.dtype), estimate)


@contextlib.contextmanager
def truth_below(below: float):
    """Within the block, every :class:`EstimatedDepth` keeps the env's own ``depth`` where
    it is below ``below`` metres (see :func:`oracle_depth`)."""
    below = check_below(below)  # named before any flight

    def _call(self, td):
        est = self.estimate(td.get(self.in_keys[0]))
        true = td.get(self.out_keys[0], None)
        if true is None:
            raise RuntimeError("the oracle needs the env's own depth under "
                               f"{self.out_keys[0]!r} before the estimate replaces it")
        td.set(self.out_keys[0], oracle_depth(true, est, below))
        return td

    saved = EstimatedDepth._call, EstimatedDepth.forward
    EstimatedDepth._call = EstimatedDepth.forward = _call
    try:
        yield
    finally:
        EstimatedDepth._call, EstimatedDepth.forward = saved


def arm_name(below: float, depth_weights=None, ego_map=None) -> str:
    """The arm's label: ``below=T`` and, where set, the weights file's name and map options."""
    parts = [f"below={below:g}"]
    if depth_weights is not None:
        parts.append(f"depth={Path(depth_weights).name}")
    parts += [f"{k}={v}" for k, v in sorted((ego_map or {}).items())]
    return ", ".join(parts)


def fly(below: float, seed: int, episodes: int, out: Path, ego_map: dict,
        depth_weights=None) -> dict:
    """One arm on one seed's episodes (fly_tello's ``--compare-sim`` reference on RGB)."""
    argv = ["--run", str(policy_dir("generalist")), "--episodes", str(episodes), "--noise",
            "--seed", str(seed), "--compare-sim", str(episodes), "--compare-perception", "rgb",
            "--goal-size", "1.0", "0.8", "--board-back", "blank", "--layout", "heldout",
            "--no-video", "--out", str(out)]
    if depth_weights is not None:
        argv += ["--depth-weights", str(depth_weights)]
    args = fly_tello.parse_args(argv)
    base = fly_tello.ego_map_options
    fly_tello.ego_map_options = lambda a: {**base(a), **ego_map}
    t0 = time.time()
    try:
        with truth_below(below):
            ref = fly_tello.dronenav_reference(args)
    finally:
        fly_tello.ego_map_options = base
    return {"figure": "depth_range_oracle", "arm": arm_name(below, depth_weights, ego_map),
            "below": below, "depth_weights": None if depth_weights is None else str(depth_weights),
            "ego_map": ego_map, "seed": seed,
            "success": ref["rate"], "n": ref["n"], "ci95": ref["ci95"],
            "mean_length": round(ref["mean_length"], 2),
            "success_per_episode": ref["success_per_episode"],
            "seconds": round(time.time() - t0, 1)}


def paired(a: list[int], b: list[int]) -> dict:
    """``a`` against ``b`` on the same episodes: discordant counts and the difference of
    proportions with its 95 % interval (Wald on the paired differences)."""
    if len(a) != len(b) or not a:
        raise ValueError(f"paired arms need the same non-zero number of episodes, got "
                         f"{len(a)} and {len(b)}")
    n = len(a)
    gains = sum(1 for x, y in zip(a, b) if x and not y)
    losses = sum(1 for x, y in zip(a, b) if y and not x)
    d = (gains - losses) / n
    var = ((gains + losses) / n - d * d) / n
    h = 1.96 * math.sqrt(max(var, 0.0))
    return {"gains": gains, "losses": losses, "paired_difference": round(d, 4),
            "paired_ci95": [round(d - h, 4), round(d + h, 4)]}


def pooled(rows: list[dict]) -> list[dict]:
    """One object per arm over its seeds, each paired with the first arm's episodes."""
    arms: dict[str, dict[int, list[int]]] = {}
    for r in rows:
        arm = r.get("arm") or arm_name(r["below"], r.get("depth_weights"), r.get("ego_map"))
        if r["seed"] in arms.get(arm, {}):
            raise ValueError(f"arm {arm!r} flew seed {r['seed']} twice")
        arms.setdefault(arm, {})[r["seed"]] = r["success_per_episode"]
    order = list(arms)
    seeds = sorted(set.intersection(*(set(v) for v in arms.values())))
    if not seeds:
        raise ValueError("the arms share no seed to pool")
    first = [x for s in seeds for x in arms[order[0]][s]]
    out = []
    for arm in order:
        eps = [x for s in seeds for x in arms[arm][s]]
        k = sum(eps)
        lo, hi = wilson(k, len(eps))
        out.append({"figure": "depth_range_oracle_pooled", "arm": arm, "seeds": seeds,
                    "success": round(k / len(eps), 4), "n": len(eps),
                    "ci95": [round(lo, 4), round(hi, 4)],
                    "against": order[0], **paired(eps, first)})
    return out


def _below(text: str) -> float:
    try:
        return check_below(float(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--below takes numbers >= 0 (m) or inf, got {text!r}")


def _map_option(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key or not value:
        raise argparse.ArgumentTypeError(f"--ego-map takes KEY=VALUE, got {text!r}")
    return key, value


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--below", type=_below, nargs="+", default=[0.0, 1.0, math.inf],
                   help="the arms: the truth replaces MonoDepth below this many metres "
                        "(0: none; inf: everywhere); the first is the pairing's reference")
    p.add_argument("--seeds", type=int, nargs="+", default=[733, 741])
    p.add_argument("--episodes", type=int, default=50, help="episodes per seed")
    p.add_argument("--ego-map", type=_map_option, nargs="*", default=[], metavar="KEY=VALUE",
                   help="EgoMap options added to the flight's (e.g. max_range=2.5)")
    p.add_argument("--depth-weights", default=None, metavar="PT",
                   help="MonoDepth weights to fly in place of the shipped ones")
    p.add_argument("--pool", nargs="+", default=None, metavar="JSONL",
                   help="fly nothing: pool the per-seed objects of earlier runs (the first "
                        "arm met is the pairing's reference)")
    p.add_argument("--out", default="outputs/depth_range_oracle")
    a = p.parse_args(argv)
    if a.episodes < 1:
        p.error(f"--episodes must be >= 1, got {a.episodes}")
    if a.depth_weights is not None and not Path(a.depth_weights).is_file():
        p.error(f"--depth-weights {a.depth_weights!r} is not a file")
    if a.pool is not None:
        rows = []
        for f in a.pool:
            if not Path(f).is_file():
                p.error(f"--pool {f!r} is not a file")
            rows += [r for r in map(json.loads, Path(f).read_text().splitlines())
                     if r.get("figure") == "depth_range_oracle"]
        summary = pooled(rows)
        for s in summary:
            print(json.dumps(s), flush=True)
        return summary
    torch.set_num_threads(1)
    rows = []
    for below in a.below:
        for seed in a.seeds:
            tag = f"below_{below:g}" + ("" if a.depth_weights is None else
                                       f"_{Path(a.depth_weights).stem}")
            r = fly(below, seed, a.episodes, Path(a.out) / f"{tag}_s{seed}",
                    dict(a.ego_map), a.depth_weights)
            print(json.dumps(r), flush=True)
            rows.append(r)
    summary = pooled(rows)
    for s in summary:
        print(json.dumps(s), flush=True)
    return rows + summary


if __name__ == "__main__":
    main()
