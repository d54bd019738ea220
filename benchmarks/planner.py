"""Cost of the shortest-path oracle: seconds per plan from the start of held-out layouts.

::

    python benchmarks/planner.py --layouts 100            # optimal A* (weight 1, as SPL uses)
    python benchmarks/planner.py --layouts 100 --weight 1.2   # the imitation teacher's setting

Prints one JSON object: the median, 90th percentile and worst planning time on one
core, the expansions, and the plan lengths (targets of the issue "See it fly": median
<= 0.3 s, worst <= 2 s per held-out layout). Every plan is replayed through
``env.step`` and must be judged ``reached`` by the env (``all_reached``).
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--layouts", type=int, default=100)
    p.add_argument("--weight", type=float, default=1.0)
    p.add_argument("--seed", type=int, default=2024, help="which held-out layouts (env seed)")
    a = p.parse_args(argv)
    if a.layouts < 1:
        p.error(f"--layouts must be >= 1, got {a.layouts}")
    if a.weight < 1:
        p.error(f"--weight must be >= 1, got {a.weight}")
    import numpy as np
    import torch
    from tensordict import TensorDict

    from torchrl_causal.envs import DroneNavEnv, ShortestPathPlanner

    torch.set_num_threads(1)
    env = DroneNavEnv("random", split="heldout", image_size=32, seed=a.seed)
    planner = ShortestPathPlanner(env, weight=a.weight)
    seconds, expansions, lengths, reached = [], [], [], 0
    t0 = time.perf_counter()
    for _ in range(a.layouts):
        env.reset()
        plan = planner.plan()
        seconds.append(planner.last_seconds)
        expansions.append(planner.last_expansions)
        lengths.append(len(plan))
        td = None
        for action in plan:
            td = env.step(TensorDict({"action": torch.tensor(action)}, []))
        reached += bool(td["next", "reached"]) if td is not None else 0
    out = {
        "bench": "planner", "layouts": a.layouts, "weight": a.weight, "seed": a.seed,
        "median_s": float(np.median(seconds)), "p90_s": float(np.percentile(seconds, 90)),
        "worst_s": float(np.max(seconds)), "median_expansions": float(np.median(expansions)),
        "worst_expansions": int(np.max(expansions)), "plan_steps_median": float(np.median(lengths)),
        "plan_steps_min": int(np.min(lengths)), "plan_steps_max": int(np.max(lengths)),
        "all_reached": reached == a.layouts, "wall_s": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(out), flush=True)
    return out


if __name__ == "__main__":
    main()
