"""Random-policy statistics of the thesis scene: open field (default) and the old closed hall.

Prints one JSON object per scene: episodes, crash / geofence-exit / reach /
timeout rates and the mean episode length of uniformly random flight.

    python benchmarks/random_flight.py [--episodes 100] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only

import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchrl_causal.envs import DroneNavEnv, thesis_layout  # noqa: E402


def random_flight(layout, episodes: int, seed: int) -> dict:
    env = DroneNavEnv(layout, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    counts = {"crash": 0, "out_of_bounds": 0, "reach": 0, "timeout": 0}
    lengths = []
    for _ in range(episodes):
        env.reset()
        for t in range(env.max_steps):
            a = torch.randint(8, (), generator=gen)
            nxt = env.step(env.full_action_spec.zero().set("action", a))["next"]
            if nxt["done"].item():
                break
        lengths.append(t + 1)
        if nxt["reached"].item():
            counts["reach"] += 1
        elif nxt["crashed"].item():
            counts["crash"] += 1
        elif nxt["out_of_bounds"].item():
            counts["out_of_bounds"] += 1
        else:
            counts["timeout"] += 1
    env.close()
    out = {"scene": layout.name, "episodes": episodes, "seed": seed}
    out.update({f"{k}_rate": v / episodes for k, v in counts.items()})
    out["mean_length"] = float(np.mean(lengths))
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    for layout in (thesis_layout(), thesis_layout(enclosed=True)):
        print(json.dumps(random_flight(layout, args.episodes, args.seed)), flush=True)


if __name__ == "__main__":
    main()
