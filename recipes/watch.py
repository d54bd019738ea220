"""Watch a policy fly: ``python recipes/watch.py --policy thesis --layout thesis --out DIR``.

::

    python recipes/watch.py --policy thesis --layout thesis --episodes 2 --out outputs/watch/thesis
    python recipes/watch.py --policy generalist --layout heldout --episodes 3 --out outputs/watch/gen
    python recipes/watch.py --policy outputs/make_train --layout thesis --episodes 1 --out DIR

``--policy`` is a shipped policy (:func:`torchrl_causal.pretrained.available`:
``thesis``, ``generalist``) or a run folder of ``recipes/train.py`` (it needs
``policy.json``, ``model.pt`` and ``explorer.pt``). ``--layout``: ``thesis``
(the thesis scene), ``heldout`` or ``train`` (random layouts of that split, a
new one per episode, drawn from ``--seed``). The episodes are flown once,
greedily, by :func:`torchrl_causal.training.record_episodes`, and written to
``--out``:

* ``flight.mp4`` -- the onboard camera beside a chase view, with the action,
  the gate's decision, goal-in-sight and each episode's outcome drawn on it;
* ``flight_maps.png`` -- one top-down map per episode, the oracle's path dashed
  (:func:`torchrl_causal.training.plot_flight_maps`);
* ``episodes.jsonl`` -- one JSON line per episode: ``success``, ``outcome``,
  ``steps``, ``oracle_steps``, ``spl`` (and ``crash``, ``out_of_bounds``,
  ``reward``, ``layout``).

Bad input (an unknown policy name, a run folder without weights, an output
folder that already holds files without ``--overwrite``, ``--episodes`` < 1)
is refused before any episode runs. The last line printed is a JSON summary.
``make demo`` runs it on both shipped policies.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

#: ``--layout`` -> ``DroneNavEnv`` options (as ``recipe_utils.SCENES``).
LAYOUTS = {
    "thesis": {},
    "heldout": {"layout": "random", "split": "heldout"},
    "train": {"layout": "random", "split": "train"},
}
#: What a run folder given as ``--policy`` must hold.
POLICY_FILES = ("policy.json", "model.pt", "explorer.pt")
#: The files ``watch.py`` writes into ``--out``.
OUT_FILES = ("flight.mp4", "flight_maps.png", "episodes.jsonl")


def parse_args(argv=None):
    from torchrl_causal.pretrained import available

    names = available()
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policy", required=True,
                   help=f"a shipped policy ({', '.join(names)}) or a run folder of "
                        "recipes/train.py")
    p.add_argument("--layout", default="thesis", choices=sorted(LAYOUTS),
                   help="thesis scene, or random layouts of the heldout / train split")
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0, help="seeds the env (and the layouts drawn)")
    p.add_argument("--max-steps", type=int, default=None,
                   help="step limit of an episode (default: the env's, 200)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into an output folder that already holds files")
    a = p.parse_args(argv)
    if a.episodes < 1:
        p.error(f"--episodes must be >= 1, got {a.episodes}")
    if a.seed < 0:
        p.error(f"--seed must be >= 0, got {a.seed}")
    if a.max_steps is not None and a.max_steps < 1:
        p.error(f"--max-steps must be >= 1, got {a.max_steps}")
    # the policy: a shipped name or a run folder with its weights
    folder = Path(a.policy)
    if a.policy in names:
        from torchrl_causal.pretrained import policy_dir

        a.shipped, a.policy_folder = True, policy_dir(a.policy)
    elif folder.is_dir():
        missing = [f for f in POLICY_FILES if not (folder / f).is_file()]
        if missing:
            p.error(f"--policy {a.policy!r}: the run folder has no {', '.join(missing)} "
                    f"(a finished run of recipes/train.py has {', '.join(POLICY_FILES)})")
        a.shipped, a.policy_folder = False, folder
    else:
        p.error(f"--policy {a.policy!r}: unknown policy name and no such run folder; "
                f"the shipped policies are {names}")
    # the output folder: refuse to mix with other files unless --overwrite
    out = Path(a.out)
    if out.exists() and not out.is_dir():
        p.error(f"--out {a.out!r} is a file, not a folder")
    if out.is_dir() and any(out.iterdir()) and not a.overwrite:
        held = sorted(x.name for x in out.iterdir())
        p.error(f"--out {a.out!r} already holds files ({', '.join(held[:5])}"
                f"{', ...' if len(held) > 5 else ''}): pass --overwrite or choose an empty "
                "folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        p.error(f"--out {a.out!r} cannot be created: {err}")
    return a


def _json_value(v):
    if isinstance(v, float) and math.isnan(v):
        return None
    return v


def episode_rows(episodes) -> list[dict]:
    """One JSON-ready dict per evaluated episode (NaN -> null)."""
    from torchrl_causal.training.flightmap import outcome_of

    rows = []
    for i, e in enumerate(episodes):
        row = {"episode": i + 1, "layout": e["layout"].name if e.get("layout") else None,
               "success": bool(e["success"]), "outcome": outcome_of(e),
               "steps": int(e["steps"]), "oracle_steps": e.get("oracle_steps"),
               "spl": e.get("spl"), "crash": bool(e["crash"]),
               "out_of_bounds": bool(e["out_of_bounds"]), "reward": e.get("reward")}
        oracle = row["oracle_steps"]
        if oracle is not None and not math.isnan(oracle):
            row["oracle_steps"] = int(oracle)
        rows.append({k: _json_value(v) for k, v in row.items()})
    return rows


def main(argv=None) -> dict:
    args = parse_args(argv)
    import torch

    from torchrl_causal.envs import DroneNavEnv
    from torchrl_causal.pretrained import PolicySpec, load_policy, load_policy_dir
    from torchrl_causal.training import plot_flight_maps, record_episodes

    torch.set_num_threads(1)
    spec = PolicySpec.from_json((args.policy_folder / "policy.json").read_text())
    base = DroneNavEnv(**LAYOUTS[args.layout], image_size=spec.image_size, seed=args.seed)
    if args.shipped:
        policy, env = load_policy(args.policy, base_env=base, device="cpu")
    else:
        policy, env, _ = load_policy_dir(args.policy_folder, env=base)
    out = Path(args.out)
    try:
        res = record_episodes(policy, env, args.episodes, args.seed, out / "flight.mp4",
                              max_steps=args.max_steps)
    finally:
        base.close()
    label = args.policy if args.shipped else args.policy_folder.name
    plot_flight_maps(res["episodes"], out / "flight_maps.png",
                     suptitle=f"policy {label}, layout {args.layout}, seed {args.seed}")
    rows = episode_rows(res["episodes"])
    with open(out / "episodes.jsonl", "w") as f:
        for row in rows:
            f.write(json.dumps(row) + "\n")
    summary = {
        "policy": args.policy, "layout": args.layout, "episodes": args.episodes,
        "seed": args.seed, "success_rate": res["success_rate"], "spl": res.get("spl"),
        "crashes": res["collisions"], "geofence_exits": res["out_of_bounds"],
        "mean_steps": res["mean_length"], "oracle_steps": res.get("oracle_steps"),
        "video": str(res["video"]), "frames": res["frames"],
        "maps": str(out / "flight_maps.png"), "episodes_file": str(out / "episodes.jsonl"),
    }
    summary = {k: _json_value(v) for k, v in summary.items()}
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
