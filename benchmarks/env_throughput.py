"""DroneNavEnv throughput: one JSON line per execution mode.

Single process, one env, 84x84 RGB-D (``MUJOCO_GL=egl``), random actions,
auto-reset on episode end (thesis scene). Fields: ``mode``, ``steps_per_s``
(full ``EnvBase.step`` cost, TorchRL overhead included), ``render_ms`` (RGB-D
plus, when the goal may be in view, segmentation), ``physics_ms`` (executing
the action: sweep or PID-controlled simulation), ``steps``, ``threads``.

Usage: ``python benchmarks/env_throughput.py [--steps 1000] [--modes kinematic physics]``
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only
os.environ.setdefault("LP_NUM_THREADS", "0")

import numpy as np  # noqa: E402
import torch  # noqa: E402


def run(mode: str, steps: int, seed: int = 0) -> dict:
    from torchrl_causal.envs import DroneNavEnv

    env = DroneNavEnv(execution=mode, seed=seed)
    actions = np.random.default_rng(seed).integers(0, 8, size=steps + 50)
    td = env.reset()
    template = env.full_action_spec.zero()

    def one(a, td):
        td = td.update(template.set("action", torch.tensor(int(a))))
        td = env.step(td)
        nxt = td["next"]
        return env.reset() if bool(nxt["done"]) else nxt

    for a in actions[:50]:  # warm-up
        td = one(a, td)
    env.timings(reset=True)
    t0 = time.perf_counter()
    for a in actions[50:]:
        td = one(a, td)
    elapsed = time.perf_counter() - t0
    tm = env.timings()
    env.close()
    return {
        "mode": mode,
        "steps_per_s": round(steps / elapsed, 1),
        "render_ms": round(tm["render_ms"], 3),
        "physics_ms": round(tm["physics_ms"], 3),
        "steps": steps,
        "threads": torch.get_num_threads(),
    }


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--modes", nargs="+", default=["kinematic", "physics"])
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    for mode in args.modes:
        print(json.dumps(run(mode, args.steps)), flush=True)


if __name__ == "__main__":
    main()
