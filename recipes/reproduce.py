"""Run the thesis protocol (sec. 5.2) and draw its comparison figures and tables.

Protocol (``--mode full``): the five variants (``dqn_image``, ``cbn_defined``,
``cbn_p``, ``cbn_pn``, ``cbn_v2``; k = 200) and the two no-CBN controls on the
same features (``dqn_features``, ``dqn_features_v2eps``; docs/recipes.rst,
"Control variants") x ``--seeds`` seeds x 700 episodes (thesis Fig. 5.4;
``--variants`` picks a subset), and the k sweep 100 / 200 / 400 / 600 of ``cbn_v2``
(Fig. 5.3; the k = 200 runs are the ``cbn_v2`` runs). Each run is one job of a
hydra multirun of ``recipes/train.py`` writing its own run folder under ``--root``::

    <root>/variants/<variant>/seed_<s>/      (Fig. 5.4 runs)
    <root>/k_sweep/k_<k>/seed_<s>/           (Fig. 5.3 runs, k != 200)
    <root>/figures/fig5_3_k_sweep.png, fig5_4_variants.png, success_variants.png,
                  success_k_sweep.png
    <root>/tables/summary.md (mean +- 95 % t-interval half-width over seeds),
                 table_5_1.md (Table 5.1 over the cbn_v2 seeds), table_5_1_seed_<s>.md,
                 ordering.md (final greedy success ranked, pairwise Welch intervals),
                 grid_time.md (training-loop time of the finished runs)

The runs go through a hydra launcher (``--launcher``): ``joblib`` (default;
``--jobs`` local processes), ``submitit_local`` (submitit's local executor),
``submitit_slurm`` (a SLURM job array; partition, time limit, GPUs... as
``hydra.launcher.*`` overrides after ``--``), ``ray`` (every run one Ray task:
a local Ray instance with ``--jobs`` CPUs, or a running cluster with
``--ray-address auto``; ``--cpus-per-run``, ``--gpus-per-run``) or ``basic``
(one after the other, in one process). The joblib and submitit plugins are the
``cluster`` extra (``pip install -e '.[cluster]'``), Ray the ``ray`` extra (Ray
itself: hydra-ray-launcher pins ``cloudpickle<3``, which conflicts with
joblib >= 1.6). Before launching, a short warm-up run (``--warmup-frames``
frames of ``cbn_v2`` with the grid's settings) measures the training speed and
the estimated wall time of the grid is printed (``--no-estimate`` skips it,
``--estimate-only`` stops after it).

``--mode reduced`` runs the same grid with a budget this 2-core machine can
afford (a few minutes per run; see ``--frames``); ``--aggregate-only`` redraws
figures and tables from existing runs; ``--dry-run`` prints the multirun
commands and the estimate's formula without training.
Already finished runs (with a ``summary.json``) are not launched again and
interrupted ones resume from their checkpoint (every job runs with
``checkpoint.resume=auto``), so an interrupted reproduction can simply be
started again. ``--verify RUN ...`` re-trains the first frames of finished runs
with this checkout on this machine and compares their episode rows with the
records, e.g. before runs of several sessions or machines are pooled. Extra hydra overrides for every run, and the launcher's own
``hydra.launcher.*`` options, go after ``--``, e.g. ``-- buffer.size=50000``.

Example::

    python recipes/reproduce.py --mode reduced --jobs 2 --root outputs/reproduce_reduced
    python recipes/reproduce.py --mode full --seeds 5 --root outputs/reproduce
    python recipes/reproduce.py --mode full --launcher submitit_slurm --jobs 40 -- \\
        hydra.launcher.partition=gpu hydra.launcher.timeout_min=720 \\
        hydra.launcher.gpus_per_node=1 hydra.launcher.cpus_per_task=4 device=cuda
    python recipes/reproduce.py --mode full --launcher ray --jobs 16
    python recipes/reproduce.py --mode full --launcher ray --ray-address auto   # a cluster
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))

import recipe_utils as ru  # noqa: E402
import results  # noqa: E402

TRAIN = Path(__file__).resolve().parent / "train.py"
CONFIG_DIR = Path(__file__).resolve().parent / "config"
K_SWEEP = (100, 200, 400, 600)

#: Budgets per mode. ``full`` is the thesis's 700 episodes (at most 200 steps each).
MODES = {
    "full": {
        "seeds": 5,
        "overrides": [
            "collector.total_episodes=700", "collector.total_frames=140000",
            "exploration.annealing_frames=70000", "buffer.size=100000",
            "eval.interval_frames=5000", "eval.episodes=10",
            "checkpoint.interval_frames=10000",
        ],
    },
    "reduced": {
        "seeds": 2,
        "overrides": [
            "collector.total_frames=2000", "exploration.annealing_frames=1500",
            "loss.learning_starts=300", "env.max_steps=100", "buffer.size=2000",
            "eval.interval_frames=0", "eval.episodes=2", "checkpoint.interval_frames=0",
            "progress=false", "threads=1",
        ],
    },
}


class Launcher(NamedTuple):
    """A ``--launcher`` choice: hydra's ``hydra/launcher`` name and the plugin it needs."""

    hydra_name: str
    module: str | None  # the plugin's module under hydra_plugins (None: built into hydra)
    package: str | None  # its PyPI name
    extra: str | None  # the torchrl_causal extra that installs it


#: ``--launcher`` names.
LAUNCHERS = {
    "joblib": Launcher("joblib", "hydra_plugins.hydra_joblib_launcher",
                       "hydra-joblib-launcher", "cluster"),
    "submitit_local": Launcher("submitit_local", "hydra_plugins.hydra_submitit_launcher",
                               "hydra-submitit-launcher", "cluster"),
    "submitit_slurm": Launcher("submitit_slurm", "hydra_plugins.hydra_submitit_launcher",
                               "hydra-submitit-launcher", "cluster"),
    # Ray without hydra-ray-launcher: that plugin pins cloudpickle<3, which conflicts with
    # joblib >= 1.6 in one environment; every run is a Ray task instead (run_with_ray)
    "ray": Launcher("ray", "ray", "ray", "ray"),
    "basic": Launcher("basic", None, None, None),
}
#: submitit's local executor kills a job after ``timeout_min`` (60 by default): a week here.
LOCAL_TIMEOUT_MIN = 7 * 24 * 60


class Run(NamedTuple):
    """One run of the protocol: its folder, its group (``variants`` / ``k_sweep``), the
    value swept in that group (the variant, or k) and its seed."""

    run_dir: Path
    group: str
    value: str | int
    seed: int

    def argv(self, base: list[str]) -> list[str]:
        """``recipes/train.py`` arguments that run it alone (``output_dir`` set); the
        run's own seed, k and folder win over the same keys in ``base`` (as the
        multiruns' grid values do, :func:`sweep_command`)."""
        if self.group == "variants":
            name, own = str(self.value), [f"seed={self.seed}"]
        else:
            name, own = "cbn_v2", [f"seed={self.seed}", f"causal.k={self.value}"]
        own.append(f"output_dir={self.run_dir}")
        keys = {_override_key(o) for o in own}
        rest = [o for o in merge_overrides(base) if _override_key(o) not in keys]
        return ["--config-name", name, *own, *rest]


GROUPS = ("variants", "k_sweep")


def run_plan(root: Path, mode: str, seeds: int, variants, k_values,
             groups=GROUPS) -> list[Run]:
    """Every run of the protocol, or of its ``groups`` only (``variants``: Fig. 5.4, the
    cbn_v2 runs at k = 200 among them; ``k_sweep``: Fig. 5.3's other k values)."""
    plan = []
    for v in (variants if "variants" in groups else ()):
        for s in range(seeds):
            plan.append(Run(root / "variants" / v / f"seed_{s}", "variants", v, s))
    for k in (k_values if "k_sweep" in groups else ()):
        if k == 200:
            continue  # the cbn_v2 runs above
        for s in range(seeds):
            plan.append(Run(root / "k_sweep" / f"k_{k}" / f"seed_{s}", "k_sweep", k, s))
    return plan


def _override_key(override: str) -> str:
    """``key`` of a hydra override ``[+|~]key=value``."""
    return override.split("=", 1)[0].lstrip("+~")


def merge_overrides(*groups: list[str]) -> list[str]:
    """Hydra overrides with one entry per key: a later ``key=value`` replaces an earlier one
    (so ``-- collector.total_frames=500`` replaces the mode's)."""
    merged: dict[str, str] = {}
    for group in groups:
        for o in group:
            key = _override_key(o)
            merged.pop(key, None)
            merged[key] = o
    return list(merged.values())


def check_launcher(name: str) -> Launcher:
    """The :data:`LAUNCHERS` entry of ``--launcher``, its plugin checked to be installed.

    Raises:
        ValueError: naming ``--launcher`` for an unknown name or a missing plugin.
    """
    if name not in LAUNCHERS:
        raise ValueError(f"Invalid option --launcher={name!r}: expected one of "
                         f"{sorted(LAUNCHERS)}")
    launcher = LAUNCHERS[name]
    if launcher.module is not None and importlib.util.find_spec(launcher.module) is None:
        raise ValueError(
            f"Invalid option --launcher={name}: {launcher.package} is not installed "
            f"(pip install {launcher.package}, or pip install -e "
            f"'.[{launcher.extra}]')")
    return launcher


def _hydra_value(text: str) -> str:
    """``text`` as a hydra override value (quoted unless it is plain)."""
    if re.fullmatch(r"[\w./-]+", text):
        return text
    return "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"


def launcher_overrides(name: str, jobs: int | None) -> list[str]:
    """``hydra/launcher=...`` and the launcher's parallelism (``--jobs``)."""
    out = [f"hydra/launcher={LAUNCHERS[name].hydra_name}"]
    if name == "joblib":
        out.append(f"hydra.launcher.n_jobs={jobs or 1}")
    elif name == "submitit_local":
        out.append(f"hydra.launcher.timeout_min={LOCAL_TIMEOUT_MIN}")
    elif name == "submitit_slurm" and jobs:
        out.append(f"hydra.launcher.array_parallelism={jobs}")
    return out


def sweeps(pending: list[Run], launcher: str, jobs: int | None):
    """The pending runs as multirun grids ``(group, values, seeds)``: runs of a group that
    miss the same seeds share one grid (every grid is a full product, so nothing finished
    runs again). submitit's local executor starts every job of a grid at once, so for it
    grids hold at most ``jobs`` runs."""
    seeds_of: dict[tuple, list[int]] = {}
    for r in pending:
        seeds_of.setdefault((r.group, r.value), []).append(r.seed)
    grids: dict[tuple, list] = {}
    for (group, value), seeds in seeds_of.items():
        grids.setdefault((group, tuple(seeds)), []).append(value)
    out = [(g, values, list(seeds)) for (g, seeds), values in grids.items()]
    if launcher != "submitit_local":
        return out
    cap = max(1, jobs or 1)
    chunked = []
    for g, values, seeds in out:
        if len(seeds) > cap:
            for v in values:
                chunked += [(g, [v], seeds[i:i + cap]) for i in range(0, len(seeds), cap)]
        else:
            per = max(1, cap // len(seeds))
            chunked += [(g, values[i:i + per], seeds) for i in range(0, len(values), per)]
    return chunked


def sweep_command(root: Path, group: str, values, seeds, launch: list[str],
                  overrides: list[str]) -> list[str]:
    """The ``recipes/train.py -m`` command of one grid; hydra's sweep folder and
    sub-folder put every job's run folder at ``<root>/<group>/...`` (``output_dir``
    stays null)."""
    if group == "variants":
        axis, subdir, fixed = "variant", "${variant}/seed_${seed}", []
    else:
        axis, subdir, fixed = "causal.k", "k_${causal.k}/seed_${seed}", ["variant=cbn_v2"]
    # seed-major (hydra's product follows this order): a grid cut short holds every value's
    # first seeds rather than all seeds of the first values
    grid = [f"seed={','.join(map(str, seeds))}", f"{axis}={','.join(map(str, values))}", *fixed]
    return [
        sys.executable, str(TRAIN), "-m", "--config-name", "base", *launch,
        f"hydra.sweep.dir={_hydra_value(str(root / group))}", f"hydra.sweep.subdir={subdir}",
        # the grid's own values win over the same keys among the extra overrides
        *merge_overrides(overrides, ["checkpoint.resume=auto"], grid),
    ]


def job_env() -> dict:
    """The environment of the multirun process (and, inherited, of its jobs)."""
    env = dict(os.environ)
    env.setdefault("MUJOCO_GL", "egl")
    recipes = str(TRAIN.parent)  # jobs unpickled by submitit / Ray import recipe_utils
    env["PYTHONPATH"] = os.pathsep.join(p for p in (recipes, env.get("PYTHONPATH")) if p)
    return env


def run_with_ray(pending: list[Run], overrides: list[str], jobs: int | None = None,
                 address: str | None = None, cpus_per_run: float = 1.0,
                 gpus_per_run: float = 0.0, dry_run: bool = False) -> None:
    """Every pending run as one Ray task (``recipes/train.py`` in a subprocess of a Ray
    worker, its output in ``<run folder>.ray.log`` beside the run folder).

    ``address=None`` starts a local Ray instance with ``jobs`` CPUs (default: all
    cores); ``"auto"`` or ``"HOST:6379"`` joins a running cluster (``ray start --head``
    and ``ray start --address=...`` on the workers), whose nodes must see this
    repository and ``--root`` at the same paths (a shared file system, as for SLURM).
    Ray runs ``floor(CPUs / cpus_per_run)`` tasks at a time per node.
    """
    # seed-major, as the multiruns (Ray starts tasks in the order they are submitted): a
    # grid cut short holds every configuration's first seeds, not all seeds of the first
    runs = [(r, [sys.executable, str(TRAIN),
                 *r.argv(merge_overrides(overrides, ["checkpoint.resume=auto"]))])
            for r in sorted(pending, key=lambda r: r.seed)]
    for r, cmd in runs:
        print(f"Ray task: {shlex.join(cmd)}", flush=True)
    if dry_run or not runs:
        return
    import ray

    env = job_env()
    started_here = not ray.is_initialized()
    if started_here:
        if address is None:
            ray.init(num_cpus=jobs or os.cpu_count() or 1, include_dashboard=False,
                     log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    print(f"Ray: {len(runs)} runs on {ray.cluster_resources().get('CPU', 0):g} CPUs, "
          f"{len(ray.nodes())} node(s)", flush=True)

    @ray.remote(num_cpus=cpus_per_run, num_gpus=gpus_per_run, max_retries=0)
    def job(cmd: list[str], env: dict, log: str) -> tuple[int, str]:
        import socket
        import subprocess as sp

        Path(log).parent.mkdir(parents=True, exist_ok=True)
        with open(log, "w") as f:
            code = sp.run(cmd, env=env, stdout=f, stderr=sp.STDOUT, check=False).returncode
        return code, socket.gethostname()

    try:
        refs = {job.remote(cmd, env, str(r.run_dir.parent / f"{r.run_dir.name}.ray.log")): r
                for r, cmd in runs}
        left = list(refs)
        while left:
            done, left = ray.wait(left, num_returns=1)
            code, host = ray.get(done[0])
            r = refs[done[0]]
            state = "finished" if code == 0 else f"failed (exit {code}; see its .ray.log)"
            print(f"[{len(refs) - len(left)}/{len(refs)}] {state} on {host}: {r.run_dir}",
                  flush=True)
    finally:
        if started_here:
            ray.shutdown()


def run_all(plan: list[Run], overrides: list[str], launcher: str = "joblib",
            jobs: int | None = 1, dry_run: bool = False, ray_options: dict | None = None
            ) -> list[Run]:
    """Launches the unfinished runs of ``plan`` (one multirun per grid of :func:`sweeps`;
    with ``launcher="ray"`` one Ray task per run, :func:`run_with_ray`).

    Returns:
        The runs still without a ``summary.json`` afterwards (empty when all finished).
    """
    pending = []
    for i, r in enumerate(plan, 1):
        if (r.run_dir / "summary.json").exists():
            print(f"[{i}/{len(plan)}] done already: {r.run_dir}")
        else:
            state = "resumes" if (r.run_dir / ru.RUN_LAYOUT["checkpoint"]).exists() else "starts"
            print(f"[{i}/{len(plan)}] {state}: {r.run_dir}")
            pending.append(r)
    if launcher == "ray":
        run_with_ray(pending, overrides, jobs, dry_run=dry_run, **(ray_options or {}))
        if dry_run:
            return pending
        return [r for r in pending if not (r.run_dir / "summary.json").exists()]
    root = plan[0].run_dir.parents[2] if plan else None
    launch = launcher_overrides(launcher, jobs)
    env = job_env()
    for group, values, seeds in sweeps(pending, launcher, jobs):
        cmd = sweep_command(root, group, values, seeds, launch, overrides)
        print(f"{len(values) * len(seeds)} runs via --launcher={launcher}: {shlex.join(cmd)}",
              flush=True)
        if not dry_run:
            subprocess.run(cmd, check=False, env=env)
    if dry_run:
        return pending
    return [r for r in pending if not (r.run_dir / "summary.json").exists()]


# --------------------------------------------------------------------------- estimate
def estimate_wall_time(frames: int, runs: int, jobs: int, fps: float,
                       overhead_s: float = 0.0) -> float:
    """Estimated seconds for ``runs`` runs of ``frames`` frames each, ``jobs`` at a time,
    each training at ``fps`` frames per second after ``overhead_s`` seconds of start-up:
    ``ceil(runs / jobs) * (frames / fps + overhead_s)``."""
    if runs < 0 or frames < 0:
        raise ValueError(f"Invalid estimate input: runs={runs}, frames={frames} (expected >= 0)")
    if jobs < 1:
        raise ValueError(f"Invalid option --jobs={jobs}: expected an integer >= 1")
    if not fps > 0:
        raise ValueError(f"Invalid estimate input: fps={fps} (expected > 0)")
    if runs == 0:
        return 0.0
    return math.ceil(runs / min(jobs, runs)) * (frames / fps + max(0.0, overhead_s))


def format_duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 2 * 3600:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


def compose_run_config(overrides: list[str], variant: str = "cbn_v2"):
    """The run config the grid's overrides give (composed, not run; bad keys fail here)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    plain = [o for o in overrides if not o.lstrip("+~").startswith("hydra")]
    GlobalHydra.instance().clear()
    with initialize_config_dir(version_base=None, config_dir=str(CONFIG_DIR)):
        return compose("base", [*plain, f"variant={variant}"])


#: Top-level config keys that say where and how a run ran, not what it computed: a grid
#: may resume or extend runs that differ in these (``seed`` differs per run by design).
RUN_ONLY_KEYS = ("seed", "device", "threads", "progress", "output_dir", "checkpoint",
                 "logger", "outputs")
#: Nested keys that choose how the same numbers are computed (``loss.stateful``: the two
#: losses give the same runs bit for bit, ``tests/test_stateful_loss.py``;
#: ``collector.fused_acting``: the same actions, ``tests/test_acting.py``; ``optim.fused``:
#: the same Adam, rounded differently).
IMPLEMENTATION_KEYS = ("loss.stateful", "collector.fused_acting", "optim.fused")


#: Config keys added after runs were made, with the value that computes what their
#: absence did: a stored run without the key matches a grid that has this value.
ADDED_KEYS = {"env.noise": "none", "optim.fused": False}


def _flatten(node, prefix: str = "") -> dict:
    if isinstance(node, dict):
        out = {}
        for k, v in node.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: node}


def check_root_configs(root: Path, plan: list[Run], overrides: list[str]) -> None:
    """Refuses a ``--root`` whose run folders hold runs of another config than the grid's
    (another ``--mode``, preset or override), before any job starts: such a run would be
    resumed, or counted as done, under the wrong protocol. Keys of :data:`RUN_ONLY_KEYS`
    and :data:`IMPLEMENTATION_KEYS` may differ (a run of the grid may have trained on a GPU, for instance), and a key of
    :data:`ADDED_KEYS` missing from a stored run counts as its neutral value.

    Raises:
        ValueError: naming ``--root``, the run folder and the keys that differ.
    """
    from omegaconf import OmegaConf

    expected: dict[tuple, dict] = {}
    for r in plan:
        path = r.run_dir / ru.RUN_LAYOUT["config"]
        if not path.exists():
            continue
        key = (r.group, r.value)
        if key not in expected:
            variant, extra = ((r.value, []) if r.group == "variants"
                              else ("cbn_v2", [f"causal.k={r.value}"]))
            cfg = compose_run_config(merge_overrides(overrides, extra), variant)
            expected[key] = _flatten(OmegaConf.to_container(cfg, resolve=True))
        stored = _flatten(OmegaConf.to_container(OmegaConf.load(path), resolve=True))
        stored = {**ADDED_KEYS, **stored}  # keys newer than the run, at their neutral value
        want = expected[key]
        missing = object()
        diff = sorted(k for k in set(want) | set(stored)
                      if k.split(".")[0] not in RUN_ONLY_KEYS and k not in IMPLEMENTATION_KEYS
                      and want.get(k, missing) != stored.get(k, missing))
        if diff:
            shown = "; ".join(f"{k}: {stored.get(k, '(absent)')!r} there, "
                              f"{want.get(k, '(absent)')!r} in this grid" for k in diff[:4])
            more = f" and {len(diff) - 4} more" if len(diff) > 4 else ""
            raise ValueError(
                f"Invalid option --root={root}: {r.run_dir} holds a run of another config "
                f"({shown}{more}). Give another --root, or the same --mode, preset and "
                "overrides as that grid.")


def warmup_overrides(cfg, frames: int, out: Path) -> list[str]:
    """A ``frames``-frame run with the grid run's replay ratio and share of frames before
    learning starts, no evaluation, checkpoint or drawing."""
    total = int(cfg.collector.total_frames)
    starts = min(frames - 1, round(frames * cfg.loss.learning_starts / max(total, 1)))
    updates = max(1, int((frames - starts) * cfg.loss.updates_per_frame))
    return [
        f"collector.total_frames={frames}", "collector.total_episodes=null",
        f"loss.learning_starts={starts}",
        f"loss.target_update_interval={min(cfg.loss.target_update_interval, updates)}",
        f"buffer.size={min(cfg.buffer.size, max(frames, cfg.buffer.batch_size))}",
        "eval.interval_frames=0", "eval.final_episodes=0", "env.eval_layouts=[thesis]",
        "checkpoint.interval_frames=0", "checkpoint.resume=false", "checkpoint.stop_after_frames=null",
        "outputs.draw_cbns=false", "logger.backend=none", "progress=false",
        f"output_dir={_hydra_value(str(out))}",
    ]


def warmup(overrides: list[str], frames: int = 300, variant: str = "cbn_v2") -> tuple[float, float]:
    """Trains ``variant`` for ``frames`` frames with the grid's settings in a temporary
    folder; returns ``(frames per second of the training loop, seconds of start-up and
    outputs outside it)``."""
    cfg = compose_run_config(overrides, variant)
    with tempfile.TemporaryDirectory(prefix="reproduce_warmup_") as tmp:
        plain = [o for o in overrides if not o.lstrip("+~").startswith("hydra")]
        cmd = [sys.executable, str(TRAIN), "--config-name", "base", f"variant={variant}",
               *merge_overrides(plain, warmup_overrides(cfg, frames, Path(tmp) / "run"))]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, env=job_env(), capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise RuntimeError(f"the warm-up run failed ({shlex.join(cmd)}):\n"
                               f"{proc.stderr[-3000:]}")
        summary = json.loads((Path(tmp) / "run" / "summary.json").read_text())
    return float(summary["loop_frames_per_second"]), max(0.0, wall - summary["loop_seconds"])


def estimate_line(frames: int, runs: int, jobs: int, fps: float, overhead_s: float) -> str:
    secs = estimate_wall_time(frames, runs, jobs, fps, overhead_s)
    return (f"Estimated wall time for {runs} runs x {frames} frames on {min(jobs, max(runs, 1))} "
            f"parallel jobs: {format_duration(secs)} (warm-up: {fps:.1f} frames/s, "
            f"{overhead_s:.0f} s start-up per run; training frames only, evaluation "
            f"episodes come on top)")


def _tail_mean(x: pd.Series, n: int) -> float:
    return float(x.tail(n).mean()) if len(x) else float("nan")


def _final_eval(run_dir: Path) -> dict:
    """Greedy success per layout: ``summary.json``'s final evaluation (``eval.final_episodes``
    episodes), else the last periodic evaluation in ``eval.csv``."""
    summary = run_dir / "summary.json"
    if summary.exists():
        final = json.loads(summary.read_text()).get("final_eval") or {}
        if final:
            return {f"eval_success_{k}": float(v["success_rate"]) for k, v in final.items()}
    path = run_dir / "eval.csv"
    if not path.exists():
        return {}
    ev = pd.read_csv(path)
    if ev.empty:
        return {}
    last = ev[ev["frames"] == ev["frames"].max()]
    return {f"eval_success_{r.layout}": float(r.success_rate) for r in last.itertuples()}


def _finished_runs(folder: Path) -> list[dict]:
    return [r for r in results.load_runs(folder) if (r["dir"] / "summary.json").exists()]


#: What :func:`export_records` keeps of a finished run: every file the figures and tables are
#: drawn from, and the run's own tables (no checkpoint, buffer, model, plots or videos).
RECORD_FILES = ("config.yaml", "summary.json", "episodes.csv", "eval.csv", "relearns.csv")


def grid_status(plan: list[Run], root: Path, now: float | None = None) -> list[dict]:
    """Where each run of ``plan`` stands, read from its folder (nothing is trained or
    loaded): ``finished`` (``summary.json``), ``started`` (a ``config.yaml``: running, or
    stopped and resumable from its last checkpoint) or ``not started``; its episodes and
    frames so far, the episode budget of its ``config.yaml``, whether a checkpoint exists,
    the seconds since its episode rows were last written, and its latest greedy success
    on the thesis scene (the final evaluation when finished, else the last periodic one)."""
    import pandas as pd
    from omegaconf import OmegaConf

    now = time.time() if now is None else now
    rows = []
    for r in plan:
        d = r.run_dir
        row = {"run": str(d.relative_to(root)), "state": "not started", "episodes": 0,
               "frames": 0, "target_episodes": None, "checkpoint": False,
               "updated_s_ago": None, "thesis_success": None}
        if (d / "config.yaml").is_file():
            row["state"] = "started"
            cfg = OmegaConf.load(d / "config.yaml")
            row["target_episodes"] = OmegaConf.select(cfg, "collector.total_episodes")
        row["checkpoint"] = (d / "checkpoints" / "last.pt").is_file()
        eps_file = d / "episodes.csv"
        if eps_file.is_file():
            eps = pd.read_csv(eps_file)
            row["episodes"] = len(eps)
            row["frames"] = int(eps["frames"].iloc[-1]) if len(eps) else 0
            row["updated_s_ago"] = round(now - eps_file.stat().st_mtime)
        if (d / "summary.json").is_file():
            summary = json.loads((d / "summary.json").read_text())
            row.update(state="finished", frames=int(summary["frames"]),
                       episodes=int(summary["episodes"]))
            final = summary.get("final_eval", {}).get("thesis")
            row["thesis_success"] = None if final is None else final["success_rate"]
        elif (d / "eval.csv").is_file():
            ev = pd.read_csv(d / "eval.csv")
            ev = ev[ev["layout"] == "thesis"] if "layout" in ev else ev
            if len(ev):
                row["thesis_success"] = float(ev["success_rate"].iloc[-1])
        rows.append(row)
    return rows


def format_status(rows: list[dict]) -> str:
    """``grid_status``'s rows as a table, then the totals and the episodes left."""
    def cell(v, fmt="{}"):
        return "-" if v is None else fmt.format(v)
    lines = ["| run | state | episodes | frames | checkpoint | updated | thesis success |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        eps = f"{r['episodes']} / {r['target_episodes']}" if r["target_episodes"] else \
            str(r["episodes"])
        updated = "-" if r["updated_s_ago"] is None else format_duration(r["updated_s_ago"]) + \
            " ago"
        lines.append(f"| {r['run']} | {r['state']} | {eps} | {r['frames']:,} | "
                     f"{'yes' if r['checkpoint'] else 'no'} | {updated} | "
                     f"{cell(r['thesis_success'], '{:.2f}')} |")
    count = {s: sum(r["state"] == s for r in rows) for s in ("finished", "started",
                                                              "not started")}
    frames = sum(r["frames"] for r in rows)
    lines.append("")
    lines.append(f"{len(rows)} runs: {count['finished']} finished, {count['started']} started, "
                 f"{count['not started']} not started; {frames:,} frames so far.")
    budgets = [r["target_episodes"] for r in rows if r["target_episodes"]]
    episodes = sum(r["episodes"] for r in rows)
    if budgets and episodes:
        # every run of a grid shares its budget: the unstarted runs have the same
        budget = max(budgets)
        left = sum(max(budget - r["episodes"], 0) for r in rows if r["state"] != "finished")
        per_episode = frames / episodes
        lines.append(f"Episodes left: {left:,} (about {left * per_episode:,.0f} frames at this "
                     f"grid's {per_episode:.0f} frames per episode so far).")
    return "\n".join(lines)


def export_records(root: Path, dest: Path) -> list[Path]:
    """Copies the records of every finished run under ``root`` to ``dest`` (same layout):
    a few hundred kB per run, enough for ``--aggregate-only --root dest`` to draw the same
    figures and tables on another machine, or to publish a grid with its figures.

    Returns:
        The run folders written under ``dest``.

    Raises:
        ValueError: naming ``--export`` when it lies inside ``--root`` or holds no run folder.
    """
    import shutil

    root, dest = root.resolve(), dest.resolve()
    if dest == root or root in dest.parents:
        raise ValueError(f"Invalid option --export={dest}: it lies inside --root={root}")
    written = []
    for group in ("variants", "k_sweep"):
        for run in _finished_runs(root / group):
            out = dest / run["dir"].relative_to(root)
            out.mkdir(parents=True, exist_ok=True)
            for name in RECORD_FILES:
                if (run["dir"] / name).exists():
                    shutil.copy2(run["dir"] / name, out / name)
            if (run["dir"] / "tables").is_dir():
                shutil.copytree(run["dir"] / "tables", out / "tables", dirs_exist_ok=True)
            written.append(out)
    if not written:
        raise ValueError(f"Invalid option --export={dest}: --root={root} holds no finished run")
    return written


def _restarts(rows: list[dict], name: str) -> list[int]:
    """Row indices where a CSV of a run starts over: episode / relearn 1 again, or the
    first periodic evaluation's (frames, layout) again."""
    if name == "eval.csv":
        first = (rows[0]["frames"], rows[0]["layout"])
        return [i for i, r in enumerate(rows) if i and (r["frames"], r["layout"]) == first]
    key = "episode" if name == "episodes.csv" else "relearn"
    return [i for i, r in enumerate(rows) if i and r[key] == "1"]


def repair_records(root: Path) -> dict:
    """Drops the rows of earlier starts from the runs' ``episodes.csv``, ``eval.csv`` and
    ``relearns.csv`` under ``root``. Before a fix of 2026-11-27, a run cut short before its
    first checkpoint and started again in its folder (``checkpoint.resume=auto``) kept the
    first start's rows ahead of its own. Each file is kept from its last start, and only when
    every dropped segment is an exact copy of the rows kept first (a start with the same
    seed is deterministic); otherwise nothing is written.

    Returns:
        ``{file: {"rows_before", "rows_kept", "dropped_segments"}}`` for each file changed.

    Raises:
        ValueError: naming a file whose earlier rows are not a copy of its last start's.
    """
    import csv

    report = {}
    for run in results.load_runs(root):
        for name in ("episodes.csv", "eval.csv", "relearns.csv"):
            path = run["dir"] / name
            if not path.exists():
                continue
            with open(path, newline="") as f:
                reader = csv.reader(f)
                header = next(reader, None)
                raw = list(reader)
            if header is None or not raw:
                continue
            cuts = _restarts([dict(zip(header, r)) for r in raw], name)
            if not cuts:
                continue
            kept, starts = raw[cuts[-1]:], [0, *cuts]
            for a, b in zip(starts, starts[1:]):
                if raw[a:b] != kept[:b - a]:
                    raise ValueError(
                        f"Invalid option --repair-records: {path} rows {a + 1}-{b} are not a "
                        "copy of its last start's first rows; left as it is")
            with open(path, "w", newline="") as f:
                w = csv.writer(f)
                w.writerow(header)
                w.writerows(kept)
            report[str(path)] = {"rows_before": len(raw), "rows_kept": len(kept),
                                 "dropped_segments": [b - a for a, b in zip(starts, starts[1:])]}
    return report


def min_verify_frames(run_dir: Path) -> int:
    """The fewest frames a ``--verify`` re-run of ``run_dir`` may train: the loop refuses a
    budget in which no gradient step runs or the target network is never synced."""
    from omegaconf import OmegaConf

    loss = OmegaConf.load(Path(run_dir) / "config.yaml").loss
    return int(loss.learning_starts) + math.ceil(int(loss.target_update_interval)
                                                 / float(loss.updates_per_frame))


def check_verify_run(run_dir: Path, frames: int) -> None:
    """Raises ``ValueError`` naming ``run_dir`` when it is not a run folder, or ``frames``
    when it is below :func:`min_verify_frames` (before any re-run starts)."""
    for name in ("config.yaml", "episodes.csv"):
        if not (Path(run_dir) / name).is_file():
            raise ValueError(f"Invalid option --verify {run_dir}: no {name} (not a run folder "
                             "of recipes/train.py)")
    least = min_verify_frames(run_dir)
    if frames < least:
        raise ValueError(f"Invalid option --verify-frames={frames}: {run_dir} needs at least "
                         f"{least} (loss.learning_starts + one target sync's gradient steps)")


def verify_run(run_dir: Path, frames: int = 1500) -> dict:
    """Re-trains the first ``frames`` frames of a finished run with this checkout's code on
    this machine (its own ``config.yaml``, in a temporary folder) and compares the episode
    rows with the run's ``episodes.csv``: whether code or machine changed the run's course
    (CPU kernels differ between machines in the last bits, which a greedy argmax can
    amplify), e.g. before runs of several sessions are pooled in one figure.

    Returns:
        ``{"run", "frames", "episodes_compared", "identical", "first_difference"}``:
        the episodes that ended within ``frames`` (the loop records finished episodes
        only), how many of them match the record in every column, and the first that
        does not (``None`` when all do).

    Raises:
        ValueError: naming ``run_dir`` without ``config.yaml`` / ``episodes.csv``, or
            ``frames`` below :func:`min_verify_frames`.
        RuntimeError: with the re-run's error output when it fails.
    """
    run_dir = Path(run_dir)
    check_verify_run(run_dir, frames)
    with tempfile.TemporaryDirectory(prefix="reproduce_verify_") as tmp:
        cmd = [sys.executable, str(TRAIN), "--config-dir", str(run_dir.resolve()),
               "--config-name", "config", f"collector.total_frames={frames}",
               "collector.total_episodes=null", "eval.final_episodes=0",
               "checkpoint.resume=false", "outputs.draw_cbns=false", "logger.backend=none",
               "progress=false", f"output_dir={_hydra_value(str(Path(tmp) / 'run'))}"]
        proc = subprocess.run(cmd, env=job_env(), capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"the re-run of {run_dir} failed ({shlex.join(cmd)}):\n"
                               f"{proc.stderr[-3000:]}")
        new = pd.read_csv(Path(tmp) / "run" / "episodes.csv")
    old = pd.read_csv(run_dir / "episodes.csv")
    cols = [c for c in new.columns if c in old.columns]
    n = min(len(new), len(old))
    same = (new[cols].iloc[:n].reset_index(drop=True)
            == old[cols].iloc[:n].reset_index(drop=True)).all(axis=1)
    first = None if same.all() else int(new["episode"].iloc[int((~same).to_numpy().argmax())])
    return {"run": str(run_dir), "frames": frames, "episodes_compared": int(n),
            "identical": int(same.sum()), "first_difference": first}


def aggregate(root: Path) -> dict:
    """Draws Fig. 5.3 / 5.4-style figures and the summary tables from all runs under ``root``."""
    fig_dir, tab_dir = root / "figures", root / "tables"
    fig_dir.mkdir(parents=True, exist_ok=True)
    tab_dir.mkdir(parents=True, exist_ok=True)
    out: dict = {"figures": [], "tables": []}
    var_runs, sweep_runs = _finished_runs(root / "variants"), _finished_runs(root / "k_sweep")

    groups: dict[str, list] = {}
    success: dict[str, list] = {}
    for v in ru.VARIANTS:
        rs = [r for r in var_runs if r["variant"] == v]
        if rs:
            groups[ru.VARIANTS[v].label] = [r["episodes"]["reward"].tolist() for r in rs]
            success[ru.VARIANTS[v].label] = [r["episodes"]["success"].astype(float).tolist()
                                             for r in rs]
    if groups:
        out["figures"].append(str(results.plot_reward_curves(
            groups, 50, fig_dir / "fig5_4_variants.png",
            title="Episode reward per variant, k=200 (cf. thesis Fig. 5.4)")))
        out["figures"].append(str(results.plot_reward_curves(
            success, 50, fig_dir / "success_variants.png", ylabel="success",
            title="Success rate per variant")))

    k_runs = [r for r in var_runs if r["variant"] == "cbn_v2"] + sweep_runs
    kgroups: dict[str, list] = {}
    ksuccess: dict[str, list] = {}
    vlines: dict[str, list] = {}
    for k in sorted({r["k"] for r in k_runs}):
        rs = [r for r in k_runs if r["k"] == k]
        label = f"k={k}"
        kgroups[label] = [r["episodes"]["reward"].tolist() for r in rs]
        ksuccess[label] = [r["episodes"]["success"].astype(float).tolist() for r in rs]
        firsts = [float(r["relearns"]["episode"].iloc[0]) for r in rs if len(r["relearns"])]
        vlines[label] = [float(np.mean(firsts))] if firsts else []
    if kgroups:
        out["figures"].append(str(results.plot_reward_curves(
            kgroups, 20, fig_dir / "fig5_3_k_sweep.png", vlines=vlines,
            title="CBN-DQN V2, episode reward per k (cf. thesis Fig. 5.3)\n"
                  "dashed: episode of the first CBN (mean over seeds)")))
        out["figures"].append(str(results.plot_reward_curves(
            ksuccess, 20, fig_dir / "success_k_sweep.png", ylabel="success", vlines=vlines,
            title="CBN-DQN V2, success rate per k\n"
                  "dashed: episode of the first CBN (mean over seeds)")))

    rows, finals = [], {}
    for label, rs in [(ru.VARIANTS[v].label, [r for r in var_runs if r["variant"] == v])
                      for v in ru.VARIANTS] + [
                     (f"CBN-DQN V2 k={k}", [r for r in sweep_runs if r["k"] == k])
                     for k in sorted({r["k"] for r in sweep_runs})]:
        if not rs:
            continue
        per_seed = []
        for r in rs:
            e = r["episodes"]
            per_seed.append({
                "episodes": len(e),
                "reward_last50": _tail_mean(e["reward"], 50),
                "success_all": float(e["success"].mean()) if len(e) else float("nan"),
                "success_last50": _tail_mean(e["success"].astype(float), 50),
                "crash_rate": float(e["crash"].mean()) if len(e) else float("nan"),
                **_final_eval(r["dir"]),
            })
        df = pd.DataFrame(per_seed)
        row = {"run": label, "seeds": len(rs)}
        for c in df.columns:
            row[c] = results.mean_ci_text(df[c].tolist())
        rows.append(row)
        if not label.startswith("CBN-DQN V2 k="):  # the ordering ranks the variants only
            finals[label] = df
    if rows:
        cols = list(dict.fromkeys(c for r in rows for c in r))  # every row starts run, seeds
        md = results.summary_markdown(
            rows, cols, "Per-run summary (mean +- half-width of its 95 % t-interval over "
            "seeds; reward/success of the last 50 training episodes; eval_success_<layout>: "
            "greedy evaluation at the end)")
        (tab_dir / "summary.md").write_text(md)
        out["tables"].append(str(tab_dir / "summary.md"))
        out["tables"].append(str(_write_ordering(finals, tab_dir / "ordering.md")))
    # Fig. 5.3's runs ranked the same way: cbn_v2 at each k (k = 200: the variant grid's runs)
    kfinals = {f"CBN-DQN V2 k={k}": pd.DataFrame([_final_eval(r["dir"]) for r in k_runs
                                                  if r["k"] == k])
               for k in sorted({r["k"] for r in k_runs})}
    if kfinals:
        out["tables"].append(str(_write_ordering(kfinals, tab_dir / "ordering_k.md")))
    v2_tables = []
    for r in var_runs:
        t = r["dir"] / "tables" / "table_5_1.md"
        if r["variant"] == "cbn_v2" and t.exists():
            dst = tab_dir / f"table_5_1_seed_{r['seed']}.md"
            dst.write_text(t.read_text())
            out["tables"].append(str(dst))
        csv = r["dir"] / "tables" / "table_5_1.csv"
        if r["variant"] == "cbn_v2" and csv.exists():
            v2_tables.append(pd.read_csv(csv))
    if v2_tables:
        out["tables"].append(str(_write_table_5_1(v2_tables, tab_dir / "table_5_1.md")))
    out["grid_time"] = _grid_time(var_runs, sweep_runs)
    (tab_dir / "grid_time.md").write_text(_grid_time_markdown(out["grid_time"]))
    out["tables"].append(str(tab_dir / "grid_time.md"))
    (root / "reproduce_summary.json").write_text(json.dumps(out, indent=2))
    return out


def _write_table_5_1(tables: list, path: Path) -> Path:
    """Thesis Table 5.1 over seeds: per action, every column's mean +- 95 % t half-width
    over the ``cbn_v2`` runs' own tables (``tables/table_5_1.csv``)."""
    cat = pd.concat(tables, ignore_index=True)
    cols = [c for c in cat.columns if c != "action"]
    rows = []
    for action in dict.fromkeys(cat["action"]):  # the tables' own action order
        part = cat[cat["action"] == action]
        rows.append({"action": action, "seeds": len(part),
                     **{c: results.mean_ci_text(part[c].tolist()) for c in cols}})
    path.write_text(results.summary_markdown(
        rows, ["action", "seeds", *cols],
        f"Table 5.1 over {len(tables)} CBN-DQN V2 run(s): mean +- half-width of its 95 % "
        "t-interval over seeds (edges common with the expert CBN, first / last learned CBN)"))
    # the same rows as CSV (docs/results.rst shows it with a csv-table)
    pd.DataFrame(rows, columns=["action", "seeds", *cols]).to_csv(path.with_suffix(".csv"),
                                                                   index=False)
    return path


#: Seeds a variant needs on each side of a pair before the ordering calls the pair.
MIN_SEEDS_TO_ORDER = 3


def _write_ordering(finals: dict, path: Path) -> Path:
    """The runs of ``finals`` (variants, or ``cbn_v2`` at each k) ranked by mean final
    greedy success per evaluation layout set, each
    with its 95 % t-interval, and every pair's difference with its 95 % Welch interval:
    a pair is told apart only where that interval excludes 0, and only with at least
    ``MIN_SEEDS_TO_ORDER`` seeds on each side."""
    layouts = sorted({c for df in finals.values() for c in df.columns
                      if c.startswith("eval_success_")})
    lines = ["### Measured ordering: final greedy success, mean +- 95 % t half-width over "
             "seeds; pairs told apart where the 95 % Welch interval of the difference "
             f"excludes 0 (with >= {MIN_SEEDS_TO_ORDER} seeds a side); each interval is 95 % "
             "on its own, with no correction for the number of pairs", ""]
    for col in layouts:
        vals = {k: df[col].dropna().tolist() for k, df in finals.items() if col in df}
        ranked = sorted(vals, key=lambda k: -np.mean(vals[k]) if vals[k] else math.inf)
        lines += [f"#### {col[len('eval_success_'):]}", "", "| rank | run | seeds | success |",
                  "|---|---|---|---|"]
        lines += [f"| {i + 1} | {k} | {len(vals[k])} | {results.mean_ci_text(vals[k])} |"
                  for i, k in enumerate(ranked)]
        lines += ["", "| higher | lower | difference | 95 % Welch interval | told apart |",
                  "|---|---|---|---|---|"]
        for i, a in enumerate(ranked):
            for b in ranked[i + 1:]:
                d, lo, hi = results.welch_diff_ci95(vals[a], vals[b])
                # with two seeds (one degree of freedom), and a side stuck at 0 or 1 with no
                # spread, the interval is not worth a verdict: three seeds a side at least
                few = min(len(vals[a]), len(vals[b])) < MIN_SEEDS_TO_ORDER
                apart = f"n/a (< {MIN_SEEDS_TO_ORDER} seeds)" if few or math.isnan(lo) else (
                    "yes" if lo > 0 or hi < 0 else "no")
                ci = "" if math.isnan(lo) else f"[{lo:+.2f}, {hi:+.2f}]"
                lines.append(f"| {a} | {b} | {d:+.2f} | {ci} | {apart} |")
        lines.append("")
    path.write_text("\n".join(lines))
    return path


def _grid_time(var_runs: list, sweep_runs: list) -> dict:
    """Training-loop time of the finished runs (``summary.json``'s ``loop_seconds``, the
    last session of a resumed run only), per group and in all."""
    out = {}
    for group, rs in (("variants", var_runs), ("k_sweep", sweep_runs)):
        secs, frames = [], []
        for r in rs:
            s = json.loads((r["dir"] / "summary.json").read_text())
            secs.append(float(s.get("loop_seconds") or 0.0))
            frames.append(int(s.get("frames") or 0))
        out[group] = {"runs": len(rs), "frames": sum(frames),
                      "loop_hours": round(sum(secs) / 3600.0, 2)}
    out["all"] = {k: round(sum(out[g][k] for g in ("variants", "k_sweep")), 2)
                  for k in ("runs", "frames", "loop_hours")}
    return out


def _grid_time_markdown(t: dict) -> str:
    lines = ["### Training-loop time of the finished runs (sum of each run's `loop_seconds`: "
             "for a resumed run, its last session only; pauses of the machine included)", "",
             "| group | runs | frames | loop hours |", "|---|---|---|---|"]
    lines += [f"| {g} | {v['runs']} | {v['frames']:,} | {v['loop_hours']:.2f} |"
              for g, v in t.items()]
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--mode", choices=sorted(MODES), default="reduced")
    p.add_argument("--root", type=Path, default=None,
                   help="output root (default outputs/reproduce_<mode>)")
    p.add_argument("--seeds", type=int, default=None, help="seeds per configuration")
    p.add_argument("--variants", nargs="+", default=list(ru.VARIANTS), choices=list(ru.VARIANTS))
    p.add_argument("--k", nargs="+", type=int, default=list(K_SWEEP), help="k sweep values")
    p.add_argument("--groups", nargs="+", choices=GROUPS, default=list(GROUPS),
                   help="which runs of the grid to launch: the variants (Fig. 5.4) and/or "
                        "the k sweep (Fig. 5.3), e.g. to split the grid across machines "
                        "(default both); the figures are drawn from every run in --root")
    p.add_argument("--frames", type=int, default=None,
                   help="override collector.total_frames of every run")
    p.add_argument("--launcher", default="joblib",
                   help=f"hydra launcher of the runs: one of {sorted(LAUNCHERS)} "
                        "(default joblib: local processes)")
    p.add_argument("--jobs", type=int, default=None,
                   help="runs at a time: local processes (joblib, submitit_local; default 1) "
                        "or the SLURM array's parallelism (submitit_slurm; default the "
                        "plugin's 256), or the CPUs of the local Ray instance (ray; default "
                        "all cores)")
    p.add_argument("--ray-address", default=None,
                   help="--launcher ray: join this Ray cluster ('auto' or HOST:6379) instead "
                        "of starting a local instance")
    p.add_argument("--cpus-per-run", type=float, default=1.0,
                   help="--launcher ray: CPUs Ray reserves per run (default 1)")
    p.add_argument("--gpus-per-run", type=float, default=0.0,
                   help="--launcher ray: GPUs Ray reserves per run (default 0; add device=cuda)")
    p.add_argument("--warmup-frames", type=int, default=300,
                   help="frames of the warm-up run that measures the speed for the estimate")
    p.add_argument("--no-estimate", action="store_true", help="skip the warm-up and estimate")
    p.add_argument("--estimate-only", action="store_true",
                   help="print the estimate and stop before launching")
    p.add_argument("--aggregate-only", action="store_true")
    p.add_argument("--export", type=Path, default=None,
                   help="afterwards, copy the records of every finished run (configs, "
                        "summaries, episode/eval/relearn CSVs, tables; no checkpoints or "
                        "models) to this folder, from which --aggregate-only --root draws "
                        "the same figures")
    p.add_argument("--repair-records", action="store_true",
                   help="first drop the rows that runs cut short before their first checkpoint "
                        "left ahead of their restart in the CSVs under --root (grids made "
                        "before 2026-11-27; each dropped segment must be an exact copy)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the multirun commands and the estimate's formula, train nothing")
    p.add_argument("--verify", nargs="+", type=Path, metavar="RUN",
                   help="instead of a grid: re-train the first --verify-frames frames of these "
                        "finished runs with this code on this machine and compare their episode "
                        "rows with the records (one JSON line per run)")
    p.add_argument("--verify-frames", type=int, default=1500,
                   help="frames each --verify re-run trains (at least the run's "
                        "loss.learning_starts + one target sync's gradient steps; "
                        "default 1500)")
    p.add_argument("--status", action="store_true",
                   help="train nothing: print where each run of the selected grid stands "
                        "under --root (finished / started / not started, episodes, frames, "
                        "checkpoint, latest thesis-scene success) and the episodes left")
    p.add_argument("overrides", nargs="*", help="extra hydra overrides for every run (after --)")
    args = p.parse_args(argv)
    if args.verify:
        for run in args.verify:  # every folder before the first re-run
            check_verify_run(run, args.verify_frames)
        checks = []
        for run in args.verify:
            checks.append(verify_run(run, args.verify_frames))
            print(json.dumps(checks[-1]), flush=True)
        return {"verify": checks}
    launcher = args.launcher
    if not (args.aggregate_only or args.status):
        check_launcher(launcher)  # unknown name or missing plugin: before any work
    if args.jobs is not None and args.jobs < 1:
        raise ValueError(f"Invalid option --jobs={args.jobs}: expected an integer >= 1")
    if launcher == "basic" and (args.jobs or 1) > 1:
        raise ValueError(f"Invalid option --jobs={args.jobs}: --launcher=basic runs one job "
                         "at a time (use --launcher=joblib)")
    if not args.cpus_per_run > 0:
        raise ValueError(f"Invalid option --cpus-per-run={args.cpus_per_run}: expected > 0")
    if not args.gpus_per_run >= 0:
        raise ValueError(f"Invalid option --gpus-per-run={args.gpus_per_run}: expected >= 0")
    if launcher != "ray" and (args.ray_address is not None or args.cpus_per_run != 1.0
                              or args.gpus_per_run != 0.0):
        raise ValueError("Invalid options --ray-address / --cpus-per-run / --gpus-per-run: "
                         f"they apply to --launcher ray, not --launcher {launcher}")
    if args.warmup_frames < 10:
        raise ValueError(f"Invalid option --warmup-frames={args.warmup_frames}: expected an "
                         "integer >= 10")
    seeds = args.seeds if args.seeds is not None else MODES[args.mode]["seeds"]
    if seeds < 1:
        raise ValueError(f"Invalid option --seeds={seeds}: expected an integer >= 1")
    bad_k = [k for k in args.k if k <= 0]
    if bad_k:
        raise ValueError(f"Invalid option --k={bad_k}: expected integers > 0")
    root = (args.root or Path("outputs") / f"reproduce_{args.mode}").resolve()
    if args.status:
        rows = grid_status(run_plan(root, args.mode, seeds, args.variants, args.k,
                                    args.groups), root)
        print(format_status(rows), flush=True)
        return {"status": rows}
    ru.check_writable(root)
    # a second '--' (a wrapper that adds its own overrides after the caller's, as
    # benchmarks/gpu_box.sh does) reaches here as an override: it separates, nothing more
    extra = [o for o in args.overrides if o != "--"]
    if args.frames is not None:
        extra.append(f"collector.total_frames={args.frames}")
    overrides = merge_overrides(MODES[args.mode]["overrides"], extra)
    if args.repair_records:
        repaired = repair_records(root)
        print(f"Records repaired: {json.dumps(repaired)}", flush=True)
    if not args.aggregate_only:
        plan = run_plan(root, args.mode, seeds, args.variants, args.k, args.groups)
        check_root_configs(root, plan, overrides)  # before the warm-up and any job
        pending = [r for r in plan if not (r.run_dir / "summary.json").exists()]
        if pending and not args.no_estimate:
            cfg = compose_run_config(overrides)  # a bad override fails here, before training
            frames = int(cfg.collector.total_frames)
            parallel = args.jobs or (1 if launcher in ("joblib", "submitit_local", "basic")
                                     else (os.cpu_count() or 1) if launcher == "ray"
                                     else len(pending))
            if args.dry_run:
                print(f"Estimated wall time for {len(pending)} runs x {frames} frames on "
                      f"{min(parallel, len(pending))} parallel jobs: "
                      f"ceil({len(pending)} / {min(parallel, len(pending))}) x ({frames} / fps "
                      f"+ start-up s), fps and start-up from a {args.warmup_frames}-frame "
                      "warm-up run (not run with --dry-run)")
            else:
                variant = "cbn_v2" if "cbn_v2" in args.variants else args.variants[0]
                print(f"Warm-up: {args.warmup_frames} frames of {variant} ...", flush=True)
                fps, overhead = warmup(overrides, args.warmup_frames, variant)
                print(estimate_line(frames, len(pending), parallel, fps, overhead), flush=True)
                if parallel > (os.cpu_count() or 1) and launcher in ("joblib", "submitit_local"):
                    print(f"Note: {parallel} parallel jobs on {os.cpu_count()} CPU cores share "
                          "them; each job then trains slower than the warm-up", flush=True)
        if args.estimate_only:
            return {}
        failed = run_all(plan, overrides, launcher, args.jobs, args.dry_run, ray_options={
            "address": args.ray_address, "cpus_per_run": args.cpus_per_run,
            "gpus_per_run": args.gpus_per_run})
        if args.dry_run:
            return {}
    out = aggregate(root)
    print(f"Figures: {root / 'figures'}")
    print(f"Tables: {root / 'tables'}")
    if args.export is not None:
        written = export_records(root, args.export)
        print(f"Records of {len(written)} finished runs: {args.export}")
    if not args.aggregate_only and failed:
        raise RuntimeError(
            f"{len(failed)} run(s) did not finish: {[str(r.run_dir) for r in failed]} (the "
            "launcher's log is above; run the same command again to resume them)")
    return out


if __name__ == "__main__":
    main()
