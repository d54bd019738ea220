"""Ship a finished run's policy as package data: ``python recipes/ship_policy.py RUN_DIR NAME``.

Copies ``config.yaml``, ``model.pt`` and ``explorer.pt`` of a run folder of ``recipes/train.py``
into ``torchrl_causal/pretrained/policies/NAME/``, writes its ``policy.json``
(the run's :class:`~torchrl_causal.pretrained.PolicySpec`, rebuilt from
``config.yaml`` when the run predates ``policy.json``) and ``provenance.json``
(the command, seed, frames, commit and the figures of the run's
``summary.json``), so that ``torchrl_causal.pretrained.load_policy(NAME)``
loads it. ``make generalist`` and ``make ship-thesis`` call it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

ROOT = Path(__file__).resolve().parents[1]
DEST = ROOT / "torchrl_causal" / "pretrained" / "policies"


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def ship(run_dir, name: str, *, command: str | None = None, notes: str = "",
         dest: Path = DEST, loop_guard: bool = False,
         flank_margin: float | None = None, revisit_guard: bool = False,
         geofence: str | None = None) -> Path:
    """Copies the policy of ``run_dir`` to ``dest/name``; returns that folder.

    ``loop_guard=True`` ships the policy with a
    :class:`~torchrl_causal.modules.LoopGuard` appended
    (``features.loop_guard=true`` in the shipped config and ``policy.json``);
    ``provenance.json`` records that it was added at shipping time when the run
    did not act with one. ``flank_margin`` sets the run's
    :class:`~torchrl_causal.transforms.EgoMap` ``flank_margin`` (m) in the
    shipped config (``features.ego_map.flank_margin``), recorded the same way.
    ``revisit_guard=True`` ships it with :class:`~torchrl_causal.transforms.VisitMemory`
    and :class:`~torchrl_causal.modules.RevisitGuard` (``features.revisit_guard``);
    ``geofence="env"`` sets the EgoMap's ``geofence`` (``features.ego_map.geofence``:
    the mask forbids moves that leave the env's flight area), both recorded the same way.

    Raises:
        FileNotFoundError: the run folder lacks ``config.yaml``, ``model.pt`` or
            ``explorer.pt`` (named).
        ValueError: ``name`` is not a plain folder name; ``flank_margin`` is
            negative, ``geofence`` is not ``"env"``, or the run builds no EgoMap
            for an option that needs one.
    """
    from omegaconf import OmegaConf

    import recipe_utils as ru
    import train

    run_dir = Path(run_dir)
    if not name or not name.replace("_", "").replace("-", "").isalnum():
        raise ValueError(f"Invalid policy name={name!r}: use letters, digits, '-' and '_'")
    for rel in ("config.yaml", "model.pt", "explorer.pt"):
        if not (run_dir / rel).is_file():
            raise FileNotFoundError(f"run folder {str(run_dir)!r} has no {rel}: is it a finished "
                                    "run of recipes/train.py?")
    cfg = OmegaConf.load(run_dir / "config.yaml")
    trained_with_guard = bool(OmegaConf.select(cfg, "features.loop_guard", default=False))
    if loop_guard:
        ru._require(int(OmegaConf.select(cfg, "features.history", default=0) or 0) >= 4,
                    "--loop-guard", True, f"a run with features.history >= 4 ({run_dir})")
        OmegaConf.set_struct(cfg, False)
        cfg.features.loop_guard = True
    trained_flank = OmegaConf.select(cfg, "features.ego_map.flank_margin", default=None)
    trained_fence = OmegaConf.select(cfg, "features.ego_map.geofence", default=None)
    trained_revisit = bool(OmegaConf.select(cfg, "features.revisit_guard", default=False))
    inputs = set(OmegaConf.select(cfg, "features.inputs", default=[]) or [])
    has_map = bool({"goal_memory", "map_clearance", "ego_map"} & inputs)
    ego_map: dict = {}
    if flank_margin is not None:
        ru._require(isinstance(flank_margin, (int, float)) and flank_margin >= 0,
                    "--flank-margin", flank_margin, "a number of metres >= 0")
        ru._require(has_map, "--flank-margin", flank_margin,
                    f"a run whose features build an EgoMap ({run_dir})")
        ego_map["flank_margin"] = float(flank_margin)
    if geofence is not None:
        ru._require(geofence == "env", "--geofence", geofence,
                    "'env' (the env's own flight area)")
        ru._require(has_map, "--geofence", geofence,
                    f"a run whose features build an EgoMap ({run_dir})")
        ego_map["geofence"] = geofence
    if revisit_guard:
        ru._require(has_map, "--revisit-guard", True,
                    f"a run whose features build an EgoMap ({run_dir})")
        OmegaConf.set_struct(cfg, False)
        cfg.features.revisit_guard = True
    if ego_map:
        OmegaConf.set_struct(cfg, False)
        kwargs = OmegaConf.select(cfg, "features.ego_map", default=None)
        kwargs = OmegaConf.to_container(kwargs) if kwargs is not None else {}
        cfg.features.ego_map = {**kwargs, **ego_map}
    summary_path = run_dir / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    # a shipped folder shipped again (e.g. with another guard): its record carries over
    prior_path = run_dir / "provenance.json"
    prior = json.loads(prior_path.read_text()) if prior_path.is_file() and not summary else {}
    if prior:
        summary = {k: prior.get(k) for k in ("frames", "teacher", "loop_seconds",
                                             "selected_frames", "final_eval")}
    provenance = {
        "name": name,
        "command": command or f"python recipes/train.py output_dir={run_dir}",
        "variant": cfg.variant, "seed": int(cfg.seed),
        "training_scene": cfg.env.layout,
        "frames": summary.get("frames", cfg.collector.total_frames),
        "teacher": summary.get("teacher"),
        "loop_seconds": summary.get("loop_seconds"),
        "selected_frames": summary.get("selected_frames"),
        "final_eval": summary.get("final_eval"),
        "commit": _commit(),
        "notes": notes,
    }
    # what shipping changed against the run as trained: (key, flag, changed, setting or None)
    shipped_changes = (
        ("loop_guard", "--loop-guard", loop_guard and not trained_with_guard, None),
        ("flank_margin", "--flank-margin",
         flank_margin is not None and trained_flank != flank_margin,
         (f"{flank_margin or 0:g} m", f"{trained_flank or 0:g} m")),
        ("revisit_guard", "--revisit-guard", revisit_guard and not trained_revisit, None),
        ("geofence", "--geofence", geofence is not None and trained_fence != geofence,
         (repr(geofence), repr(trained_fence))),
    )
    for key, _, _, _ in shipped_changes:
        if key in prior:
            provenance[key] = prior[key]
    if prior:
        provenance["shipped_from"] = {"name": prior.get("name"), "commit": prior.get("commit"),
                                      "command": prior.get("command")}
    for key, flag, changed, setting in shipped_changes:
        if not changed:
            continue
        provenance[key] = (
            f"added when shipped (ship_policy.py {flag}): the run trained and made final_eval "
            f"without it" if setting is None else
            f"EgoMap {key} {setting[0]} set when shipped (ship_policy.py {flag}); the run "
            f"trained and made final_eval with {setting[1]}")
    spec = train.policy_spec(cfg, ru.VARIANTS[cfg.variant], provenance=provenance)
    out = dest / name
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(run_dir / "model.pt", out / "model.pt")
    shutil.copyfile(run_dir / "explorer.pt", out / "explorer.pt")
    # the run's config too: the folder stays a valid run folder (train.load_policy, fly_tello --run)
    OmegaConf.save(cfg, out / "config.yaml")
    (out / "policy.json").write_text(spec.to_json())
    (out / "provenance.json").write_text(json.dumps(provenance, indent=2, default=str))
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", help="a finished run folder of recipes/train.py")
    p.add_argument("name", help="the pretrained name (e.g. generalist, thesis)")
    p.add_argument("--command", default=None, help="the command that made the run (provenance)")
    p.add_argument("--notes", default="", help="free text for provenance.json")
    p.add_argument("--loop-guard", action="store_true",
                   help="ship with a LoopGuard appended (features.loop_guard=true)")
    p.add_argument("--flank-margin", type=float, default=None, metavar="M",
                   help="ship with EgoMap's flank_margin set to M metres "
                        "(features.ego_map.flank_margin)")
    p.add_argument("--revisit-guard", action="store_true",
                   help="ship with VisitMemory + RevisitGuard (features.revisit_guard=true)")
    p.add_argument("--geofence", default=None, choices=("env",),
                   help="ship with EgoMap's geofence in the action mask "
                        "(features.ego_map.geofence=env: the env's own flight area)")
    a = p.parse_args(argv)
    try:
        out = ship(a.run_dir, a.name, command=a.command, notes=a.notes, loop_guard=a.loop_guard,
                   flank_margin=a.flank_margin, revisit_guard=a.revisit_guard,
                   geofence=a.geofence)
    except ValueError as e:
        p.error(str(e))
    print(f"Shipped {a.run_dir} as pretrained policy {a.name!r}: {out}")


if __name__ == "__main__":
    main()
