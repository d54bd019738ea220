"""Causal learning benchmark: fast vs pgmpy structure learning, compiled lookup vs VariableElimination.

Prints one JSON object per line:

* ``{"bench": "structure", "rows": N, "fast_s": ..., "pgmpy_s": ..., "speedup": ..., "same_dag": ...}``
  for 19 variables and 1k / 16k / 64k rows (seconds per action, both backends in the same run);
* ``{"bench": "compile", "actions": 8, "states": S, "ms": ...}``: compiling 8 CBNs into reward tables;
* ``{"bench": "lookup", "batch": B, "us_per_batch": ...}`` for batches of 1 and 256 states x 8 actions,
  beside ``{"bench": "variable_elimination", "us_per_query": ...}`` (pgmpy, one state, one action).

Data are sampled from the expert "left" network with random CPTs (a realistic density of edges).
Targets: fast <= 50 ms per action at 16k rows; lookup <= 20 us per batch.

Run: ``python benchmarks/causal_learning.py [--quick]`` (under ~3 minutes; ``--quick`` skips 64k for pgmpy).
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")  # stdout carries the JSON only

import numpy as np
import torch

from torchrl_causal.causal import compile_tables, expert_dags, fit_cbn, learn_structure
from torchrl_causal.causal.inference import random_cbn
from torchrl_causal.schema import DEFAULT_SCHEMA


def best_of(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="skip pgmpy at 64k rows")
    args = parser.parse_args()
    torch.set_num_threads(1)
    import pgmpy.causal_discovery  # noqa: F401  (import once, outside the timings)
    import pgmpy.inference  # noqa: F401
    truth = random_cbn(expert_dags()["left"], seed=0, concentration=0.5)
    for n in (1_000, 16_000, 64_000):
        data = truth.sample(n, seed=n)
        t_fast, fast = best_of(lambda: learn_structure(data, backend="fast"), 5)
        if args.quick and n > 16_000:
            t_ref, ref = float("nan"), None
        else:
            t_ref, ref = best_of(lambda: learn_structure(data, backend="pgmpy"), 1)
        print(json.dumps({
            "bench": "structure", "variables": 19, "rows": n,
            "fast_s": round(t_fast, 4), "pgmpy_s": round(t_ref, 3),
            "speedup": round(t_ref / t_fast, 1) if ref is not None else None,
            "same_dag": None if ref is None else set(fast.edges) == set(ref.edges),
            "same_score": None if ref is None else abs(fast.score - ref.score) < 1e-6,
            "edges": len(fast.edges),
        }), flush=True)

    # compiled lookup vs pgmpy VariableElimination
    data = truth.sample(16_000, seed=1)
    edges = learn_structure(data).edges
    cbns = [fit_cbn(edges, data) for _ in range(8)]
    t_compile, tables = best_of(lambda: compile_tables(cbns), 3)
    print(json.dumps({"bench": "compile", "actions": 8, "states": DEFAULT_SCHEMA.n_states,
                      "ms": round(t_compile * 1e3, 2)}), flush=True)
    cards = torch.tensor(DEFAULT_SCHEMA.cardinalities)
    for batch in (1, 256):
        states = (torch.rand(batch, 9) * cards).long()
        for _ in range(100):
            tables.lookup(states)
        reps, us = 2000, float("inf")
        for _ in range(5):
            t0 = time.perf_counter()
            for _ in range(reps):
                tables.lookup(states)
            us = min(us, (time.perf_counter() - t0) / reps * 1e6)
        print(json.dumps({"bench": "lookup", "batch": batch, "actions": 8, "us_per_batch": round(us, 2)}), flush=True)

    from pgmpy.inference import VariableElimination

    ve = VariableElimination(cbns[0].to_pgmpy())
    labels = DEFAULT_SCHEMA.node_labels()
    names = [n + "_t" for n in DEFAULT_SCHEMA.names]
    states = DEFAULT_SCHEMA.all_states()[np.random.default_rng(0).choice(DEFAULT_SCHEMA.n_states, 200)]
    evidence = [{k: labels[k][v] for k, v in zip(names, s)} for s in states]
    t0 = time.perf_counter()
    for ev in evidence:
        ve.query(["reward"], evidence=ev, show_progress=False)
    us = (time.perf_counter() - t0) / len(evidence) * 1e6
    print(json.dumps({"bench": "variable_elimination", "batch": 1, "actions": 1,
                      "us_per_query": round(us, 1)}), flush=True)


if __name__ == "__main__":
    main()
