"""Fly a trained run on a Tello: the emulator by default, a real drone with ``--host``.

::

    python recipes/fly_tello.py --episodes 10          # the shipped generalist, held-out layouts
    python recipes/fly_tello.py --goal-size 1.0 0.8    # ... with the printed board: the
                                                       # random-rooms arrival head, as on a real drone
    python recipes/fly_tello.py --run outputs/make_train --episodes 10
    python recipes/fly_tello.py --run outputs/make_train --episodes 10 --compare-sim 10
    python recipes/fly_tello.py --run outputs/make_train --host 192.168.10.1
                                                 # asks for confirmation (or --yes)

The policy (Q-network, CBN gate with its tables) is rebuilt from the run folder
by ``recipes/train.py``'s :func:`load_policy`; the env is a
:class:`torchrl_causal.envs.TelloEnv` (with the run's feature stack for CBN
variants). Perception is RGB-only by default (``--perception rgb``): the
shipped YOLOv8 goal detector and ``MonoDepth`` see the decoded video, on the
emulator as on a real drone. ``--perception sim`` (emulator only) uses the
simulator's ground truth instead (a test aid); ``--perception module:factory``
names a callable returning ``(detector, depth_estimator)``. ``--noise`` adds
move and turn noise to the emulated drone (and to the ``--compare-sim`` runs),
so that episodes differ and the success rates' intervals mean something.

Writes to ``--out`` (default ``<run>/tello_<emulator|host>``): ``episodes.csv``
(the training loop's columns that apply: episode, frames, reward, length,
success, crash, out_of_bounds; plus ``success_sim``, ``closest_sim_m`` and
``land_offset_sim_m``, the emulator's ground truth, ``battery``, and
``goal_distance_m`` / ``goal_angle_deg``, the last step's measured range and bearing
to the goal box: for a "reached" episode, the reading the arrival rule fired on,
``approaches``, and ``crash_sim``, what an emulated crash hit: ``board``, ``obstacle``,
``wall``, ``ceiling`` or ``floor``),
``onboard.mp4`` (the decoded onboard video, H.264 via PyAV)
and ``summary.json`` (success rates with 95 % Wilson intervals; with
``--compare-sim N`` also the same policy's greedy episodes in ``DroneNavEnv``).
An ``--out`` that already holds a flight is refused before take-off unless
``--overwrite`` replaces it.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from results import wilson  # noqa: E402

from torchrl_causal.envs.control import TELLO_MOVE_NOISE as NOISE  # noqa: E402

REAL_HOST_DEFAULT = "192.168.10.1"
CSV_COLUMNS = ["episode", "frames", "reward", "length", "success", "crash", "out_of_bounds",
               "success_sim", "closest_sim_m", "land_offset_sim_m", "battery",
               "goal_distance_m", "goal_angle_deg", "approaches", "crash_sim"]



#: The keys a flight's ``summary.json`` records about its outcome rather than its setting:
#: ``benchmarks/sim_to_real.py --from-flights`` pools flights whose other keys all agree, so
#: a new outcome written below belongs here too.
SUMMARY_OUTCOME_KEYS = frozenset({
    "wall_s", "look_arounds", "success_sim", "agreement", "false_reached", "missed_reach",
    "closest_sim_m_median", "crash_sim", "success", "crashes", "mean_length", "dronenav"})

def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--run", default=None,
                   help="a finished run folder of recipes/train.py, or a shipped policy folder; "
                        "default: the shipped generalist (torchrl_causal.pretrained)")
    p.add_argument("--layout", default=None, choices=("thesis", "heldout", "train", "val"),
                   help="emulator scene; default: thesis for a policy trained on the thesis "
                        "scene, else held-out random layouts")
    p.add_argument("--episodes", type=int, default=5)
    p.add_argument("--host", default=None,
                   help=f"a real drone's address (e.g. {REAL_HOST_DEFAULT}); default: the emulator")
    p.add_argument("--yes", action="store_true", help="skip the real-drone confirmation prompt")
    p.add_argument("--perception", default="rgb",
                   help="rgb (shipped YOLOv8 + MonoDepth, default) | sim (emulator ground truth) "
                        "| sim-depth (the RGB detector, the emulator's depth) | sim-detector "
                        "(the emulator's detector, MonoDepth): which model an error comes "
                        "from | module:factory returning (detector, depth_estimator)")
    p.add_argument("--depth-weights", default=None,
                   help="--perception rgb: MonoDepth weights to use instead of the shipped ones "
                        "(e.g. a recipes/train_depth.py fine-tune)")
    p.add_argument("--detector-weights", default=None,
                   help="--perception rgb: YOLOv8 weights to use instead of the shipped ones "
                        "(e.g. a recipes/train_detector.py run)")
    p.add_argument("--noise", action="store_true",
                   help="emulator and --compare-sim: move noise 0.05 m, turn noise 3 deg")
    p.add_argument("--out", default=None)
    p.add_argument("--max-steps", type=int, default=None, help="default: the run's env.max_steps")
    p.add_argument("--compare-sim", type=int, default=0,
                   help="also run N greedy episodes in DroneNavEnv and compare: on the "
                        "emulator's own layouts and noise draws (--seed), in its order, so the "
                        "first min(N, --episodes) episodes are paired")
    p.add_argument("--compare-perception", choices=("sim", "rgb"), default="sim",
                   help="--compare-sim's perception: sim (default: the policy's own features, "
                        "the simulator's detector and depth) or rgb (the flight's MonoDepth, "
                        "--depth-weights or the shipped one, on DroneNavEnv's renders, and "
                        "--map's EgoMap; the goal keys stay DroneNavEnv's own measurement)")
    p.add_argument("--video-size", default="240x320", help="emulator video HxW")
    p.add_argument("--time-scale", type=float, default=10.0, help="emulator motion speed-up")
    p.add_argument("--fov", type=float, default=None,
                   help="camera vertical FOV after the square crop (default 60 emulator, 55.6 Tello)")
    p.add_argument("--settle", type=float, default=None,
                   help="s to wait after a move before observing (default 0 emulator, 0.5 Tello)")
    p.add_argument("--reach-distance", type=float, default=None,
                   help="TelloEnv's ReachRule: goal in sight within this measured distance (m) "
                        "of the camera (default: the depth model's calibrated range, stored "
                        "with its weights, else 0.45; see docs/tello.rst)")
    p.add_argument("--reach-height", type=float, default=0.12,
                   help="ReachRule: also |height sensor - goal height| <= this (m; default "
                        "0.12); the goal height is the emulated layout's, or --goal-height on "
                        "a real drone")
    p.add_argument("--no-height-check", action="store_true",
                   help="ReachRule: do not check the height sensor (the old rule)")
    p.add_argument("--goal-height", type=float, default=None,
                   help="real drone: the goal point's height above the floor (m), the board "
                        "centre's height (default 1.0, the field guide's board)")
    p.add_argument("--reach-full-width", nargs="?", const="on", default="auto",
                   choices=("auto", "on", "off"),
                   help="ReachRule: the goal's box must span the image's width. auto "
                        "(default): on for the emulator's random layouts, where the arrival "
                        "head does not apply (measured on two seeds, docs/tello.rst), off on "
                        "the thesis board and on a real drone; a bare --reach-full-width is on")
    p.add_argument("--map", default="auto", choices=("auto", "exact", "estimated"),
                   help="EgoMap's depth model, for policies that read its map (the "
                        "generalist): exact (every reading trusted, cells stay as first seen) "
                        "or estimated (median column reading, log-odds cells that later views "
                        "overturn). auto (default): estimated where the depth is estimated "
                        "(MonoDepth: --perception rgb, sim-detector or module:factory), exact "
                        "on the simulator's depth. On MonoDepth's depth the estimated map "
                        "arrives far more often (docs/tello.rst, 'A map for estimated depth')")
    p.add_argument("--fresh-hits", nargs="?", const="on", default="auto",
                   choices=("auto", "on", "off"),
                   help="with the estimated map: what the current frame reads is an obstacle "
                        "for that step whatever the map's log-odds say (EgoMap fresh_hits; "
                        "docs/tello.rst, 'What the drone sees now'). auto (default): on with "
                        "the estimated map (fewer crashes, more arrivals over six emulated "
                        "seeds); a bare --fresh-hits is on")
    p.add_argument("--reach-offset", type=float, default=None,
                   help="ReachRule: the drone's estimated distance to the goal point (board "
                        "plane from depth, board edges, --board-width, --goal-standoff) must "
                        "be <= this (m; e.g. 0.2); default: not checked. With it, "
                        "--reach-distance defaults to 1.0")
    p.add_argument("--board-width", type=float, default=None,
                   help="the board's width (m) for --reach-offset (default: the emulated "
                        "layout's; 1.0 on a real drone, the field guide's board)")
    p.add_argument("--goal-size", type=float, nargs=2, default=None, metavar=("W", "H"),
                   help="the emulator's random layouts: every board of this size (m), e.g. "
                        "1.0 0.8, the field guide's printed board (default: drawn, 0.7-1.2 x "
                        "0.6-0.9; the layouts then differ from the drawn-size ones)")
    p.add_argument("--board-back", choices=("heliport", "blank"), default="heliport",
                   help="the emulator: the back of the simulator's board shows the heliport "
                        "('heliport', default, as every model here was trained on) or is "
                        "blank, as a printed board's is ('blank'; docs/tello.rst, 'A head that "
                        "can decline')")
    p.add_argument("--goal-standoff", type=float, default=None,
                   help="the goal point in front of the board's face (m) for --reach-offset "
                        "(default: the emulated layout's; 0.45 on a real drone)")
    p.add_argument("--arrival-head", default="auto",
                   help="the learned arrival head: 'shipped' (make arrival-weights; the "
                        "thesis room), 'rooms' (make arrival-rooms-weights; random rooms with "
                        "the printed 1.0 x 0.8 m board), 'view' (make arrival-view-weights: "
                        "random rooms, turned up to 80 deg, with an in-view output; flown "
                        "with --lost-board ask) or a weights file of "
                        "recipes/train_arrival.py; the --reach-offset distance is then read "
                        "from the camera frame by it instead of the depth map's board plane "
                        "(needs --reach-offset). "
                        "'depth': the depth map's board plane read as a head (BoardPlaneOffset: "
                        "any board width, the segment between two steps' estimates, "
                        "--final-approach). "
                        "'auto' (default), on RGB perception and a 1.0 m board: the shipped "
                        f"head with --reach-offset {HEAD_REACH_OFFSET} on the thesis scene, "
                        f"'view' with --reach-offset {ROOMS_REACH_OFFSET} in any other room "
                        "(the emulator's random layouts with --goal-size 1.0 0.8, or a real "
                        "drone with the field guide's printed board); 'depth' with "
                        "--reach-offset "
                        f"{PLANE_REACH_OFFSET} on the emulator's random layouts with the "
                        "simulator's depth, else none; 'none': the depth map's rule")
    p.add_argument("--arrival-fusion", action="store_true",
                   help="with the arrival head: average its estimates over the steps that did "
                        "not move the drone across the floor (turns, climbs)")
    p.add_argument("--climb-reading", choices=("auto", "both", "nearer"), default="auto",
                   help="with the arrival head: where a climb or descent puts the step's "
                        "segment: between the head's readings before and after it ('both'), "
                        "or at one place across the floor, the reading taken nearer the goal "
                        "point's height ('nearer'; docs/tello.rst, 'Climbs that read a new "
                        "place'). 'auto' (default): 'nearer' with --lost-board ask (the view "
                        "head, where the arrival target is shown with it on fresh seeds, "
                        "both boards), else 'both'")
    p.add_argument("--final-approach", default="auto", metavar="RADIUS",
                   help="with the arrival head: when it puts the goal point within RADIUS m "
                        "and the rule has not fired, fly the last leg to its estimate with "
                        "one SDK 'go' (docs/tello.rst, 'A final approach'). 'auto' "
                        f"(default): {FINAL_APPROACH_RADIUS} m wherever the arrival head "
                        "flies, else off; 'none': off")
    p.add_argument("--hold-radius", type=float, default=None, metavar="M",
                   help="with the arrival head: a board the detector loses is held for one "
                        "step when the head's last estimate put the goal point within M m "
                        "(default: twice --reach-offset, 1.0 with --lost-board ask; "
                        "docs/tello.rst, 'The hold and the threshold')")
    p.add_argument("--lost-board", choices=("auto", "hold", "carry", "ask"), default="auto",
                   help="with the arrival head: a board the detector has just lost near the "
                        "goal point gives, for one step, the head's reading of the frame "
                        "without it ('hold') or the last estimate carried by the "
                        "dead-reckoned move ('carry'; needs the final approach's heading; "
                        "docs/tello.rst, 'Carrying a lost board'); 'ask': a head trained "
                        "with an in-view output (train_arrival.py --in-view-share) is asked "
                        "on every frame, detection or not, while it reads the board within "
                        "--hold-radius (default 1.0 m), and declines frames without it "
                        "(docs/tello.rst, 'A head that can decline'). 'auto' (default): "
                        "'ask' for a head with an in-view output (--arrival-head view), else "
                        "'hold'")
    p.add_argument("--segment-slack", default="auto", metavar="M",
                   help="with the arrival head: a step's segment counts only when the head's "
                        "two estimates lie at most M m farther apart than the drone flew "
                        "between them, else the step counts at its current estimate (docs/"
                        f"tello.rst, 'A head that can decline'). 'auto' (default): "
                        f"{SEGMENT_SLACK} m with --lost-board ask, else none; 'none': off")
    p.add_argument("--height-margin", type=float, default=None, metavar="M",
                   help="with the arrival head: --reach-offset bounds the head's horizontal "
                        "distance, and M m are added back for the height sensor's, so a step "
                        "counts when sqrt((h + M)^2 + dz^2) - M <= --reach-offset (e.g. 0.07 "
                        "with 0.13: the simulator's 0.2 m sphere in height; docs/tello.rst, 'A "
                        "head that can decline'); default none")
    p.add_argument("--height-approach", default="auto", metavar="M",
                   help="with the arrival head and the final approach: ask the head also where "
                        "the height sensor alone puts the drone outside --reach-offset but "
                        "within M m of the goal point's height, so the final approach flies "
                        "the vertical leg too (docs/tello.rst, 'The vertical leg'). 'auto' "
                        f"(default): {HEIGHT_APPROACH:g} m wherever the look-around flies "
                        "(with the final approach), else none; 'none': off")
    p.add_argument("--look-around", default="auto", metavar="DEG",
                   help="with a learned arrival head: where it puts the step within "
                        "--look-around-radius of the goal point, turn DEG (1-45) right, as far "
                        "left, and back, ask the head at the two turned views, and decide the "
                        "arrival on the mean of the readings (docs/tello.rst, 'Looking around "
                        f"before landing'). 'auto' (default): {LOOK_AROUND:g} deg with --lost-board "
                        "ask (the view head), else none; 'none': off")
    p.add_argument("--look-around-radius", type=float, default=0.2, metavar="M",
                   help="with --look-around: look where the head's segment comes within M m "
                        "of the goal point (default 0.2, the simulator's sphere; at least "
                        "--reach-offset)")
    p.add_argument("--mirror-check", default="auto", metavar="M",
                   help="with a learned arrival head: ask it on each frame and on its mirror "
                        "image, read the mean of the two, and take nothing from a frame whose "
                        "two sideways readings lie more than M m apart (docs/tello.rst, "
                        f"'Asking the head twice'). 'auto' (default): {MIRROR_CHECK} m (the "
                        "mean, hardly a frame declined) with --lost-board ask, else none; "
                        "'none': one reading")
    p.add_argument("--seed", type=int, default=None,
                   help="emulator: the seed of the scene and its per-episode noise draws "
                        "(default: the run's seed); another seed flies other episodes")
    p.add_argument("--dry-run", action="store_true", help="print the commands, fly nothing")
    p.add_argument("--no-video", action="store_true")
    p.add_argument("--log-steps", action="store_true",
                   help="write steps.jsonl to --out: one line per step with the action, what "
                        "the camera path measured, the arrival head's estimate and the "
                        "verdicts; on the emulator also the true offset from the goal point "
                        "and yaw in the board's frame (docs/tello.rst, 'Step by step at the "
                        "goal')")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the flight already recorded in --out (episodes.csv, "
                        "onboard.mp4, summary.json); without it such an --out is refused")
    a = p.parse_args(argv)
    if a.episodes < 1:
        p.error(f"--episodes must be >= 1, got {a.episodes}")
    if a.compare_sim < 0:
        p.error(f"--compare-sim must be >= 0, got {a.compare_sim}")
    try:
        a.video_hw = tuple(int(v) for v in a.video_size.lower().split("x"))
        assert len(a.video_hw) == 2
    except (ValueError, AssertionError):
        p.error(f"--video-size must look like 240x320, got {a.video_size!r}")
    h, w = a.video_hw
    # the Tello streams 960x720 (4:3); the emulator may send it downscaled, never otherwise
    if not (h * 4 == w * 3 and 120 <= h <= 720 and h % 2 == 0):
        p.error(f"--video-size {a.video_size}: a Tello streams 960x720 (4:3); the emulator "
                "sends that or a 4:3 downscale of even height 120-720 (e.g. 720x960, "
                "480x640, 240x320)")
    if a.host is not None and a.seed is not None:
        p.error(f"--seed {a.seed}: a real flight has no seeded noise; the option is the "
                "emulator's")
    if a.host is not None and a.video_size != p.get_default("video_size"):
        p.error(f"--video-size {a.video_size}: a real Tello streams 960x720; the option is "
                "the emulator's")
    if a.goal_size is not None:
        if a.host is not None:
            p.error(f"--goal-size {a.goal_size[0]:g} {a.goal_size[1]:g}: a real drone flies "
                    "to the board in the room; the option is the emulator's")
        from torchrl_causal.envs.layouts import check_goal_size

        try:
            check_goal_size(a.goal_size)
        except ValueError as e:
            p.error(f"--goal-size must be two sizes the layouts take: {e}")
    if a.run is None:  # the shipped generalist
        from torchrl_causal.pretrained import policy_dir

        a.run = str(policy_dir("generalist"))
        a.out = a.out or str(Path("outputs") / "tello" / "generalist")
    if not (Path(a.run) / "config.yaml").is_file():
        p.error(f"--run {a.run!r} has no config.yaml: not a run folder of recipes/train.py")
    a.out = a.out or str(Path(a.run) / (f"tello_{a.host}" if a.host else "tello_emulator"))
    if (Path(a.out) / "episodes.csv").exists() and not a.overwrite:
        # a second flight would add its rows to the first's and replace its video
        p.error(f"--out {a.out} holds a recorded flight (episodes.csv): give another --out, "
                "or --overwrite to replace it")
    if a.board_back != "heliport" and a.host is not None:
        p.error(f"--board-back {a.board_back}: the option is the emulator's (a real board's "
                "back is what it is)")
    if a.goal_size is not None and _emulated_layout(a) == "thesis":
        p.error("--goal-size applies to the emulator's random layouts (--layout heldout, "
                "train or val); the thesis scene's board is 1.0 x 0.8 m")
    if a.perception not in PERCEPTIONS and ":" not in a.perception:
        p.error(f"--perception must be one of {', '.join(PERCEPTIONS)} or module:factory, "
                f"got {a.perception!r}")
    for flag, model, perceptions in WEIGHT_OPTIONS:
        path = getattr(a, flag[2:].replace("-", "_"))
        if path is None:
            continue
        if a.perception not in perceptions:
            p.error(f"{flag} applies where the {model} is the RGB model (--perception rgb), "
                    f"got --perception {a.perception!r}")
        if not Path(path).is_file():
            p.error(f"{flag} {path!r}: no such file")
    if a.map == "auto":  # the log-odds map where the depth is an estimate (docs/tello.rst)
        a.map = "exact" if a.perception in ("sim", "sim-depth") else "estimated"
    if a.arrival_head == "auto":  # where each head was measured (docs/tello.rst)
        a.arrival_head = head_applies(a) or ("depth" if plane_applies(a) else None)
        if a.arrival_head is not None and a.reach_offset is None:
            a.reach_offset = {"shipped": HEAD_REACH_OFFSET, "view": ROOMS_REACH_OFFSET,
                              "depth": PLANE_REACH_OFFSET}[a.arrival_head]
    elif a.arrival_head == "none":
        a.arrival_head = None
    if a.arrival_head is not None:
        if a.reach_offset is None:
            p.error(f"--arrival-head {a.arrival_head!r} needs --reach-offset (e.g. 0.2): the "
                    "head estimates the distance to the goal point that it bounds")
        if a.arrival_head in ("shipped", "rooms", "view"):
            from torchrl_causal.perception.arrival import (
                DEFAULT_WEIGHTS,
                ROOMS_WEIGHTS,
                VIEW_WEIGHTS,
            )

            a.arrival_head = str({"shipped": DEFAULT_WEIGHTS, "rooms": ROOMS_WEIGHTS,
                                  "view": VIEW_WEIGHTS}[a.arrival_head])
        if a.arrival_head != "depth" and not Path(a.arrival_head).is_file():
            p.error(f"--arrival-head {a.arrival_head!r}: no such file")
    if a.climb_reading == "nearer" and a.arrival_head in (None, "depth"):
        p.error(f"--climb-reading {a.climb_reading} keeps one of the arrival head's readings "
                "around a climb: it needs a head that reads frames (--arrival-head shipped, "
                "rooms, view or a weights file; 'auto' chose "
                f"{a.arrival_head or 'none'} here)")
    if a.climb_reading == "nearer" and a.arrival_fusion:
        p.error("--climb-reading nearer and --arrival-fusion both decide where a climb's "
                "readings put the drone: choose one")
    if a.arrival_fusion and a.arrival_head is None:
        p.error("--arrival-fusion fuses the arrival head's estimates: it needs the head "
                "(--arrival-head shipped or a weights file; 'auto' chose none here)")
    if a.hold_radius is not None:
        if a.arrival_head is None:
            p.error(f"--hold-radius {a.hold_radius:g} holds the arrival head's board: it needs "
                    "the head (--arrival-head shipped or a weights file; 'auto' chose none here)")
        if not 0.05 <= a.hold_radius <= 1.0:
            p.error(f"--hold-radius must be a distance in [0.05, 1.0] m, got {a.hold_radius:g}")
    # measured with the head (docs/tello.rst)
    a.final_approach = _auto_distance(
        p, "--final-approach", "radius", a.final_approach,
        FINAL_APPROACH_RADIUS if a.arrival_head is not None else None)
    if a.final_approach is not None:
        if a.arrival_head is None:
            p.error(f"--final-approach {a.final_approach:g} flies to the arrival head's "
                    "estimate of the goal point: it needs the head (--arrival-head shipped or "
                    "a weights file; 'auto' chose none here)")
        if not 0.05 <= a.final_approach <= 1.0:
            p.error(f"--final-approach must be a radius in [0.05, 1.0] m, got "
                    f"{a.final_approach:g}")
    if a.fresh_hits == "on" and a.map != "estimated":
        p.error(f"--fresh-hits overrides the log-odds of the estimated map: it needs --map "
                f"estimated, got --map {a.map}")
    # resolved to a bool (auto: with the estimated map; docs/tello.rst, "The random-rooms head,
    # shipped")
    a.fresh_hits = a.fresh_hits == "on" or (a.fresh_hits == "auto" and a.map == "estimated")
    # whether the head's file has the in-view output (read once, for --lost-board auto / ask)
    in_view = False
    if a.arrival_head not in (None, "depth"):
        from torchrl_causal.perception.arrival import GoalOffsetEstimator

        in_view = GoalOffsetEstimator.load(a.arrival_head).in_view
    if a.lost_board == "auto":  # ask a head that can decline; hold the board for the others
        a.lost_board = "ask" if in_view else "hold"
    if a.climb_reading == "auto":  # where the arrival target is shown with it (docs/tello.rst)
        a.climb_reading = "nearer" if (a.lost_board == "ask" and not a.arrival_fusion
                                       and a.arrival_head not in (None, "depth")) else "both"
    explicit = a.segment_slack not in ("auto", "none")
    a.segment_slack = _auto_distance(p, "--segment-slack", "distance", a.segment_slack,
                                     SEGMENT_SLACK if a.lost_board == "ask" else None)
    if explicit:  # the board plane's segments are checked too
        _head_distance(p, a, "--segment-slack", a.segment_slack,
                       "checks the arrival head's segments", learned=False)
    if a.height_margin is not None:
        _head_distance(p, a, "--height-margin", a.height_margin,
                       "widens the learned arrival head's rule")
    if a.look_around in ("auto", "none"):
        explicit = False
        a.look_around = LOOK_AROUND if (a.look_around == "auto" and a.lost_board == "ask"
                                        and a.arrival_head not in (None, "depth")) else None
    else:
        explicit = True
        try:
            a.look_around = float(a.look_around)
        except ValueError:
            p.error(f"--look-around must be a turn (deg), 'auto' or 'none', got "
                    f"{a.look_around!r}")
    if a.look_around is not None:
        if explicit and (a.arrival_head is None or a.arrival_head == "depth"):
            p.error(f"--look-around {a.look_around:g} asks the learned arrival head at turned "
                    "views: it needs the head")
        if not 1 <= a.look_around <= 45:
            p.error(f"--look-around must be a turn of 1-45 deg, got {a.look_around:g}")
        _head_distance(p, a, "--look-around-radius", a.look_around_radius,
                       "widens where the arrival head looks around")
        if a.look_around_radius < (a.reach_offset or 0.0):
            p.error(f"--look-around-radius {a.look_around_radius:g} is below --reach-offset "
                    f"{a.reach_offset:g}: it would look at only some of the places where the "
                    "rule fires")
    # resolved after the look-around: auto flies the vertical leg wherever it looks around
    explicit = a.height_approach not in ("auto", "none")
    a.height_approach = _auto_distance(
        p, "--height-approach", "height", a.height_approach,
        HEIGHT_APPROACH if a.look_around is not None and a.final_approach is not None else None)
    if explicit:
        _head_distance(p, a, "--height-approach", a.height_approach,
                       "flies the vertical leg to the arrival head's goal point", learned=False)
        if a.height_approach == 0:
            p.error("--height-approach must be a height above 0 m ('none' for off), got 0")
        if a.final_approach is None:
            p.error(f"--height-approach {a.height_approach:g} lets the final approach fly the "
                    "vertical leg: it needs --final-approach")
    explicit = a.mirror_check not in ("auto", "none")
    a.mirror_check = _auto_distance(p, "--mirror-check", "distance", a.mirror_check,
                                    MIRROR_CHECK if a.lost_board == "ask" else None)
    if explicit:
        _head_distance(p, a, "--mirror-check", a.mirror_check,
                       "asks the learned arrival head twice")
    if a.lost_board == "ask":
        if a.arrival_head in (None, "depth"):
            p.error(f"--lost-board ask asks the arrival head without the detector: it needs a "
                    f"head weights file with an in-view output, got --arrival-head "
                    f"{a.arrival_head}")
        if not in_view:
            p.error(f"--lost-board ask needs a head trained with an in-view output "
                    f"(train_arrival.py --in-view-share); {a.arrival_head} has none")
    elif a.lost_board != "hold" and a.final_approach is None:
        p.error(f"--lost-board {a.lost_board} turns the dead-reckoned move into the board's "
                "frame with the final approach's heading: it needs --final-approach (and the "
                "arrival head)")
    if a.reach_full_width == "auto":  # where it was measured to help (docs/tello.rst)
        a.reach_full_width = "on" if full_width_applies(a) else "off"
    if a.no_height_check:
        a.reach_height = None
    try:
        a.reach_rule = reach_rule(a)
    except ValueError as e:
        p.error(f"--reach-* options: {e}")
    if a.host is not None and a.perception.startswith("sim"):
        p.error(f"--perception {a.perception} exists only in the emulator: a real drone needs "
                "RGB-only perception (--perception rgb)")
    return a


#: What one flight writes into ``--out`` (``--overwrite`` replaces them).
FLIGHT_FILES = ("episodes.csv", "onboard.mp4", "summary.json", "steps.jsonl")


#: ``--final-approach auto``'s radius (m), wherever the arrival head flies: chosen on the
#: development seeds 101 and 102 (docs/tello.rst, "A final approach").
FINAL_APPROACH_RADIUS = 0.4

#: ``--look-around auto``'s turn (deg) with ``--lost-board ask`` (the view head): made the
#: default on 2026-11-30 by a rule fixed before the paired flights (twelve fresh seeds,
#: agreement 577 against 562 of 600 emulated episodes, false "reached" 11 against 28;
#: docs/tello.rst, "Looking around before landing").
LOOK_AROUND = 12.0

#: ``--height-approach auto``'s height (m) wherever the look-around flies: made the default on
#: 2026-12-02 by a rule fixed before the paired flights (eight fresh seeds 251-283, agreement
#: 384 against 379 of 400 emulated episodes, false "reached" 12 against 11, missed arrivals 4
#: against 10; docs/tello.rst, "The two together, and the default on more fresh seeds").
HEIGHT_APPROACH = 0.2

#: ``--segment-slack auto``'s slack (m) with ``--lost-board ask``: about one 90th-percentile
#: sideways error of the in-view head on its test frames (docs/tello.rst, "A head that can
#: decline").
SEGMENT_SLACK = 0.2

#: ``--mirror-check auto``'s check (m) with ``--lost-board ask``: the mean of the frame's and
#: its mirror image's readings, a frame declined only where the two lie more than 1 m apart
#: (1 of the view head's 900 test frames); flown on
#: four seeds against the defaults then, 193 against 190 of 200 in agreement (docs/tello.rst,
#: "Asking the head twice").
MIRROR_CHECK = 1.0

#: ``--reach-offset`` of ``--arrival-head auto``: one 90th-percentile range error of the
#: shipped head inside the goal sphere's 0.2 m (docs/tello.rst, "A learned arrival head").
HEAD_REACH_OFFSET = 0.15

#: ``--reach-offset`` of ``--arrival-head auto`` with the random-rooms head: its 90th-percentile
#: range error on held-out rooms (0.066 m) inside the goal sphere's 0.2 m, the shipped head's
#: rule (docs/tello.rst, "An arrival head for rooms it has never seen"); the head that can
#: decline, ``auto``'s choice there since 2026-11-29, was flown at the same value.
ROOMS_REACH_OFFSET = 0.13

#: ``--reach-offset`` of ``--arrival-head auto`` where it reads the board plane: the goal
#: sphere's own radius (the simulator's depth; docs/tello.rst, "The board plane as the head").
PLANE_REACH_OFFSET = 0.2


def emulated_scene(args, cfg) -> tuple[str, dict]:
    """The emulator's scene name (``--layout``, else the run's) and its ``DroneNavEnv``
    layout options, with ``--goal-size``'s board on random layouts (parse_args refuses it
    on the thesis scene)."""
    import recipe_utils as ru

    scene = args.layout or ("thesis" if cfg.env.layout == "thesis" else "heldout")
    opts = dict(ru.SCENES[scene])
    if args.goal_size is not None:
        opts["goal_size"] = tuple(args.goal_size)
    if getattr(args, "board_back", "heliport") != "heliport":
        opts["board_back"] = args.board_back
    return scene, opts


def _emulated_layout(args) -> str | None:
    """The emulated flight's layout (``--layout``, else the run's), None on a real drone."""
    if args.host is not None:
        return None
    if args.layout is not None:
        return args.layout
    from omegaconf import OmegaConf

    return OmegaConf.load(Path(args.run) / "config.yaml").env.layout


def full_width_applies(args) -> bool:
    """Whether ``--reach-full-width auto`` checks that the goal's box spans the image: on the
    emulator's random layouts without the arrival head, where it removed most false
    "reached" (boards seen at an angle, obstacles taken for the board) and raised the
    simulator-judged success on two seeds; not on the thesis board, where the detector's box
    stops short of a border at the goal point, nor on a real drone (the field guide's board
    and the arrival head)."""
    layout = _emulated_layout(args)
    return layout is not None and layout != "thesis" and args.arrival_head is None


def _auto_distance(p, flag: str, what: str, value: str, auto: float | None) -> float | None:
    """An option that takes a length (m), ``auto`` (``auto``'s value, or None) or ``none``."""
    if value == "auto":
        return auto
    if value == "none":
        return None
    try:
        return float(value)
    except ValueError:
        p.error(f"{flag} must be a {what} (m), 'auto' or 'none', got {value!r}")


#: The largest length (m) each arrival-head option takes (``benchmarks/sim_to_real.py``
#: checks its pass-through options against the same bounds).
HEAD_DISTANCE_MAX = {"--segment-slack": 1.0, "--height-margin": 0.5, "--mirror-check": 1.0,
                     "--height-approach": 0.5, "--look-around-radius": 0.5}


def head_distance_error(flag: str, value: float) -> str | None:
    """Why ``value`` is not a length ``flag`` takes (``HEAD_DISTANCE_MAX``), or None."""
    high = HEAD_DISTANCE_MAX[flag]
    if not 0.0 <= value <= high:
        return f"{flag} must be a distance in [0, {high:g}] m, got {value:g}"
    return None


def _head_distance(p, a, flag: str, value: float, does: str, learned: bool = True) -> None:
    """An arrival-head option's length (m): refused without the head (``learned``: also with
    the depth map's board plane, ``--arrival-head depth``) or outside its range."""
    if a.arrival_head is None or (learned and a.arrival_head == "depth"):
        p.error(f"{flag} {value:g} {does}: it needs the head")
    why = head_distance_error(flag, value)
    if why is not None:
        p.error(why)


def head_applies(args) -> str | None:
    """Which learned head ``--arrival-head auto`` flies, if any: on RGB perception (the head
    replaces MonoDepth's reading of a board that fills the view) and the 1.0 x 0.8 m board the
    heads were trained on, ``"shipped"`` (the thesis room's) on the emulated thesis scene and
    ``"view"`` (random rooms', with the in-view output; flown with ``--lost-board ask``) in
    any other room: the emulator's random layouts with ``--goal-size 1.0 0.8``, or a real
    drone with the field guide's printed board (``--board-width`` unset or 1.0). It replaced
    ``"rooms"`` there on 2026-11-29 (agreement 185 against 178 of 200 emulated episodes;
    docs/tello.rst, "A head that can decline")."""
    if args.perception != "rgb" or args.board_width not in (None, 1.0):
        return None
    layout = _emulated_layout(args)
    if layout == "thesis":
        return "shipped"
    if layout is None:  # a real drone: a room nobody trained on
        return "view"
    from torchrl_causal.perception.arrival import VIEW_WEIGHTS
    from torchrl_causal.perception.depth import read_sidecar

    # the board the head was trained on (its sidecar: the printed 1.0 x 0.8 m)
    trained = read_sidecar(VIEW_WEIGHTS).get("goal_size")
    size = getattr(args, "goal_size", None)
    return "view" if size is not None and trained is not None and (
        [float(v) for v in size] == [float(v) for v in trained]) else None


def plane_applies(args) -> bool:
    """Whether ``--arrival-head auto`` reads the depth map's board plane as the head
    (:class:`~torchrl_causal.envs.BoardPlaneOffset`, ``--reach-offset 0.2``, and the final
    approach): the emulator's random layouts with the simulator's depth (``--perception sim``
    or ``sim-depth``), where it was measured (docs/tello.rst, "The board plane as the
    head"); not on MonoDepth's depth, which reads a board filling the view 0.25-0.40 m
    short."""
    layout = _emulated_layout(args)
    return (layout is not None and layout != "thesis"
            and args.perception in ("sim", "sim-depth"))


def reach_rule(args, goal_height=None, layout=None, depth=None):
    """The :class:`~torchrl_causal.envs.ReachRule` of the ``--reach-*`` options
    (``goal_height``: the emulated layout's, for ``--reach-height``; ``layout``:
    the emulated one, whose board size and goal standoff ``--reach-offset`` uses
    unless ``--board-width`` / ``--goal-standoff`` are given; ``depth``: the depth
    estimator, whose calibrated ``reach_distance`` is the range threshold unless
    ``--reach-distance`` or ``--reach-offset`` is given)."""
    from torchrl_causal.envs import ReachRule

    kw = {}
    if args.reach_distance is not None:
        kw["max_distance"] = args.reach_distance
    elif args.reach_offset is None and getattr(depth, "reach_distance", None) is not None:
        kw["max_distance"] = float(depth.reach_distance)
    if args.reach_height is not None:
        kw["max_height_offset"] = args.reach_height
        kw["goal_height"] = args.goal_height if args.goal_height is not None else (
            goal_height if goal_height is not None else 1.0)
    if args.reach_full_width in (True, "on"):
        kw["full_width"] = True
    if args.reach_offset is not None:
        kw["max_goal_offset"] = args.reach_offset
        if args.reach_distance is None:  # the offset decides; the range only bounds it
            kw["max_distance"] = 1.0
        kw["board_width"] = args.board_width if args.board_width is not None else (
            float(layout.goal_size[0]) if layout is not None else 1.0)
        kw["goal_standoff"] = args.goal_standoff if args.goal_standoff is not None else (
            float(layout.goal_standoff) if layout is not None else 0.45)
    return ReachRule(**kw)


def confirm_real_flight(host: str, yes: bool, ask=input) -> None:
    """Refuses to fly a real drone unless confirmed (``--yes`` or typing ``fly``)."""
    if yes:
        return
    print(f"About to FLY A REAL DRONE at {host}. Clear the area, keep a hand near the "
          "Tello app's emergency stop.")
    if ask("Type 'fly' to take off: ").strip().lower() != "fly":
        raise SystemExit("not confirmed: nothing was flown")


#: ``--perception`` choices besides ``module:factory`` (the ``sim*`` ones: emulator only).
PERCEPTIONS = ("rgb", "sim", "sim-depth", "sim-detector")
#: ``--*-weights`` options: the model they replace and the perceptions where it is the RGB one.
WEIGHT_OPTIONS = (("--depth-weights", "depth", ("rgb", "sim-detector")),
                  ("--detector-weights", "detector", ("rgb", "sim-depth")))


def perception_models(spec: str, emu=None, depth_weights=None, detector_weights=None):
    """``(detector, depth_estimator)`` for ``--perception``: ``rgb`` (the shipped models, or
    the given weights), ``sim`` (the emulator's ground truth), ``sim-depth`` / ``sim-detector``
    (one of each: which model an error comes from) or ``module:factory``."""
    if spec in PERCEPTIONS:
        from torchrl_causal.perception.depth import MonoDepth
        from torchrl_causal.perception.yolo import YoloGoalDetector

        detector = emu.sim_detector() if spec in ("sim", "sim-detector") \
            else YoloGoalDetector(detector_weights)
        depth = emu.sim_depth_estimator() if spec in ("sim", "sim-depth") \
            else MonoDepth.load(depth_weights)
        return detector, depth
    mod, _, fn = spec.partition(":")
    return getattr(importlib.import_module(mod), fn)()


def make_tello_env(args, cfg, tello, detector, depth, before_takeoff, layout=None):
    import recipe_utils as ru
    import train as train_recipe
    from torchrl_causal.envs import TelloEnv

    kw = {"reach_rule": args.reach_rule}
    if getattr(args, "arrival_head", None) == "depth":
        from torchrl_causal.envs import BoardPlaneOffset

        kw["arrival_head"] = BoardPlaneOffset()
    elif getattr(args, "arrival_head", None):
        from torchrl_causal.perception.arrival import GoalOffsetEstimator

        kw["arrival_head"] = GoalOffsetEstimator.load(args.arrival_head)
    if kw.get("arrival_head") is not None:
        kw["arrival_fusion"] = bool(getattr(args, "arrival_fusion", False))
        if getattr(args, "climb_reading", "both") != "both":
            kw["climb_reading"] = args.climb_reading
        kw["final_approach"] = getattr(args, "final_approach", None)
        kw["hold_radius"] = getattr(args, "hold_radius", None)
        kw["lost_board"] = getattr(args, "lost_board", "hold")
        kw["segment_slack"] = getattr(args, "segment_slack", None)
        kw["height_margin"] = getattr(args, "height_margin", None)
        kw["height_approach"] = getattr(args, "height_approach", None)
        kw["mirror_check"] = getattr(args, "mirror_check", None)
        if getattr(args, "look_around", None) is not None:
            kw["look_around"] = args.look_around
            kw["look_around_radius"] = args.look_around_radius
    if layout is not None:  # the emulated scene's flight volume (new_episode: each layout's)
        kw.update(zip(("geofence", "geofence_origin", "max_height"), layout.fence()))
    real = args.host is not None
    env = TelloEnv(
        tello, detector=detector, depth_estimator=depth, image_size=cfg.env.image_size,
        fov_deg=args.fov or (55.6 if real else 60.0), reward=cfg.env.reward,
        max_steps=args.max_steps or cfg.env.max_steps, settle_s=args.settle if args.settle
        is not None else (0.5 if real else 0.0), command_timeout=7 if real else 3,
        before_takeoff=before_takeoff, dry_run=args.dry_run, **kw)
    return env, train_recipe.with_features(cfg, ru.VARIANTS[cfg.variant], env)


def fly(args, policy, tenv, base, emu=None) -> list[dict]:
    """Greedy episodes; one CSV row each; the onboard video to ``onboard.mp4``."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from torchrl_causal.training import EpisodeCSV

    out = Path(args.out)
    csv = EpisodeCSV(out / "episodes.csv", CSV_COLUMNS)
    writer = None if args.no_video else _VideoWriter(out / "onboard.mp4")
    # line-buffered: the steps flown so far stay on disk if a flight is cut short
    steps = (open(out / "steps.jsonl", "w", buffering=1) if getattr(args, "log_steps", False)
             else None)
    rows, frames = [], 0
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for ep in range(1, args.episodes + 1):
            td = tenv.reset()
            total, length, approaches0 = 0.0, 0, base.approaches
            if writer is not None and base.last_frame is not None:
                writer.write(base.last_frame)
            while True:
                td = policy(td)
                td = tenv.step(td)
                nxt = td["next"]
                total += float(nxt["reward"])
                length += 1
                if steps is not None:
                    steps.write(json.dumps(step_record(ep, length, td, base, emu,
                                                       base.approaches - approaches0)) + "\n")
                if writer is not None and base.last_frame is not None:
                    writer.write(base.last_frame)
                if bool(nxt["done"]):
                    break
                td = nxt
            frames += length
            gt = emu.ground_truth() if emu is not None else {}
            row = {"episode": ep, "frames": frames, "reward": round(total, 4), "length": length,
                   "success": int(bool(nxt["reached"])), "crash": int(bool(nxt["crashed"])),
                   "out_of_bounds": int(bool(nxt["out_of_bounds"])),
                   "success_sim": int(gt["reached"]) if gt else "",
                   "closest_sim_m": (round(gt["closest_goal_m"], 3)
                                     if gt and math.isfinite(gt["closest_goal_m"]) else ""),
                   "land_offset_sim_m": (" ".join(f"{v:+.3f}" for v in gt["land_offset_m"])
                                         if gt and gt["land_offset_m"] else ""),
                   "battery": float(nxt["battery"]),
                   # the last step's measured range and bearing to the goal box (0 when not
                   # in sight): for a "reached" episode, the reading the rule fired on
                   "goal_distance_m": round(float(nxt["goal_distance"]), 3),
                   "goal_angle_deg": round(float(nxt["goal_angle"]), 1),
                   # final approaches (SDK go) flown in the episode (--final-approach)
                   "approaches": base.approaches - approaches0,
                   # what an emulated crash hit: the surface nearest the drone's centre
                   "crash_sim": (emu.env.layout.nearest_surface(gt["crash_at"])[0]
                                 if gt and gt.get("crash_at") else "")}
            csv.write(row)
            rows.append(row)
            print(json.dumps(row), flush=True)
    if writer is not None:
        writer.close()
    if steps is not None:
        steps.close()
    return rows


def step_record(episode: int, step: int, td, base, emu=None, approaches: int = 0) -> dict:
    """One line of ``steps.jsonl`` (``--log-steps``): the step's action, what the camera
    path measured (``in_sight``, ``goal_distance_m``, ``altitude_m``), the arrival head's
    estimate ``(ahead, lateral, dz)`` (None where it was not asked), the verdicts and the
    final approaches flown so far in the episode; on the emulator also ``true_offset``,
    the drone's true ``(ahead, lateral, dz)`` from the goal point in the board's frame,
    the drone's yaw off facing the board square on (``true_yaw_off_deg``), and the
    simulator's verdict so far (``sim_reached``, ``closest_sim_m``)."""
    from torchrl_causal.schema import ACTION_NAMES

    nxt = td["next"]
    est = base.arrival_estimate
    rec = {"episode": episode, "step": step, "action": ACTION_NAMES[int(td["action"])],
           "in_sight": bool(nxt["goal_in_sight"]),
           "goal_distance_m": round(float(nxt["goal_distance"]), 3),
           "altitude_m": round(float(nxt["altitude"]), 3),
           "arrival_estimate": None if est is None else [round(v, 3) for v in est],
           "reached": bool(nxt["reached"]), "crashed": bool(nxt["crashed"]),
           "out_of_bounds": bool(nxt["out_of_bounds"]), "approaches": int(approaches)}
    if emu is not None:
        lay, gt = emu.env.layout, emu.ground_truth()
        gp, normal = np.asarray(lay.goal_point(), float), lay.goal_normal()[:2]
        x, y, z, yaw = emu.pose()
        d = np.array([x, y]) - gp[:2]
        rec["true_offset"] = [round(float(d @ normal), 3),
                              round(float(d @ np.array([-normal[1], normal[0]])), 3),
                              round(float(z - gp[2]), 3)]
        facing = math.degrees(math.atan2(-normal[1], -normal[0]))  # square on to the board
        rec["true_yaw_off_deg"] = round((float(yaw) - facing + 180.0) % 360.0 - 180.0, 1)
        rec["sim_reached"] = bool(gt["reached"])
        rec["closest_sim_m"] = (round(float(gt["closest_goal_m"]), 3)
                                if math.isfinite(gt["closest_goal_m"]) else None)
    return rec


class _VideoWriter:
    """Frames of any size to an H.264 MP4 (PyAV), resized to the first frame's size."""

    def __init__(self, path: Path, fps: int = 5):
        self.path, self.fps, self.c, self.s = path, fps, None, None

    def write(self, rgb: np.ndarray):
        import av

        rgb = np.ascontiguousarray(rgb)
        if self.c is None:
            h, w = (rgb.shape[0] // 2) * 2, (rgb.shape[1] // 2) * 2
            self.c = av.open(str(self.path), "w")
            self.s = self.c.add_stream("libx264", rate=self.fps)
            self.s.width, self.s.height, self.s.pix_fmt = w, h, "yuv420p"
        rgb = rgb[: self.s.height, : self.s.width]
        if rgb.shape[:2] != (self.s.height, self.s.width):
            return
        for p in self.s.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
            self.c.mux(p)

    def close(self):
        if self.c is not None:
            for p in self.s.encode():
                self.c.mux(p)
            self.c.close()


def summarize(rows, key="success"):
    vals = [r[key] for r in rows if r[key] != ""]
    if not vals:
        return None
    k = int(sum(vals))
    lo, hi = wilson(k, len(vals))
    return {"rate": k / len(vals), "n": len(vals), "ci95": [round(lo, 4), round(hi, 4)]}


def ego_map_options(args) -> dict:
    """The :class:`~torchrl_causal.transforms.EgoMap` options a flight sets (``--map``,
    ``--fresh-hits``): for the flight's own feature stack and ``--compare-sim``'s."""
    return {"depth": args.map, **({"fresh_hits": True} if args.fresh_hits else {})}


def dronenav_reference(args, success_sim=None) -> dict:
    """``--compare-sim``: the same policy's greedy episodes in ``DroneNavEnv`` on the
    emulator's own layouts and noise draws (``--seed``, else the run's), with
    ``--compare-perception``'s features; with ``success_sim`` (the flight's simulator
    verdicts, one per episode) also the per-episode pairs. Nothing here flies the emulator,
    so a flight already flown gets its reference afterwards (``benchmarks/sim_to_real.py
    --from-flights --compare-sim``)."""
    from omegaconf import OmegaConf

    import train as train_recipe

    from torchrl_causal.training import evaluate

    run = Path(args.run)
    cfg = OmegaConf.load(run / "config.yaml")
    seed = int(cfg.seed if args.seed is None else args.seed)
    uses_map = train_recipe.policy_spec(cfg, train_recipe.ru.VARIANTS[cfg.variant]).uses_ego_map
    noise = ["env.noise=tello"] if args.noise else []
    if args.compare_perception == "rgb":
        # the flight's MonoDepth (the goal keys stay the env's own measurement, see
        # make_causal_transforms)
        noise += ([f"++features.options.depth_estimator={Path(args.depth_weights).resolve()}"]
                  if args.depth_weights is not None else [])
        noise += ["features.options.perception=rgb"] + (
            [f"++features.ego_map.{k}={str(v).lower() if isinstance(v, bool) else v}"
             for k, v in ego_map_options(args).items()] if uses_map else [])
    scene = emulated_scene(args, cfg)[0]
    if args.goal_size is not None:  # the emulator's layouts, boards and all
        noise += ["++env.options.goal_size=[{:g},{:g}]".format(*args.goal_size)]
    if getattr(args, "board_back", "heliport") != "heliport":
        noise += [f"++env.options.board_back={args.board_back}"]
    policy, env, _ = train_recipe.load_policy(run, overrides=noise, scene=scene)
    # the emulator's env draws the same layouts and noise from --seed, but it resets
    # once when it starts: DroneNavEnv's first episode is that reset's, dropped
    res = evaluate(policy, env, args.compare_sim + 1, seed=seed, per_episode=True,
                   max_steps=args.max_steps)
    eps = res["episodes"][1:]
    k = sum(bool(e["success"]) for e in eps)
    lo, hi = wilson(k, len(eps))
    out = {"rate": k / len(eps), "n": len(eps), "ci95": [round(lo, 4), round(hi, 4)],
           "mean_length": float(np.mean([e["steps"] for e in eps])),
           "layouts": "the emulator's (paired, episode by episode)",
           "perception": args.compare_perception,
           "success_per_episode": [int(bool(e["success"])) for e in eps]}
    if success_sim is not None:
        # paired: the same layout and noise draws in both, episode by episode
        pairs = list(zip(success_sim, out["success_per_episode"]))
        out["paired"] = {
            "episodes": len(pairs),
            "both": sum(1 for a, b in pairs if a and b),
            "emulator_only": sum(1 for a, b in pairs if a and not b),
            "dronenav_only": sum(1 for a, b in pairs if b and not a),
            "neither": sum(1 for a, b in pairs if not a and not b)}
    return out


def main(argv=None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(1)
    from omegaconf import OmegaConf

    import train as train_recipe

    run = Path(args.run)
    cfg = OmegaConf.load(run / "config.yaml")
    uses_map = train_recipe.policy_spec(cfg, train_recipe.ru.VARIANTS[cfg.variant]).uses_ego_map
    if uses_map:  # EgoMap reads the depth this flight has (--map)
        ego = cfg.features.get("ego_map")
        cfg.features.ego_map = {**(OmegaConf.to_container(ego) if ego is not None else {}),
                                **ego_map_options(args)}
    real = args.host is not None
    # the emulator's scene and noise draws, and --compare-sim's episodes (--seed: others)
    seed = int(cfg.seed if args.seed is None else args.seed)
    args.out = args.out or str(run / (f"tello_{args.host}" if real else "tello_emulator"))
    Path(args.out).mkdir(parents=True, exist_ok=True)
    if getattr(args, "overwrite", False):  # parse_args refused an --out with a flight without it
        for name in FLIGHT_FILES:
            (Path(args.out) / name).unlink(missing_ok=True)
    summary: dict = {"run": str(run), "target": args.host or "emulator",
                     "episodes": args.episodes, "perception": args.perception,
                     "noise": bool(args.noise), "reach_rule": args.reach_rule.to_dict()}
    if uses_map:
        summary["map"] = args.map
        if args.fresh_hits:
            summary["fresh_hits"] = True
    for opt in ("depth_weights", "detector_weights", "arrival_head"):
        if getattr(args, opt, None):
            summary[opt] = str(getattr(args, opt))
    if getattr(args, "arrival_fusion", False):
        summary["arrival_fusion"] = True
    if getattr(args, "climb_reading", "both") != "both":
        summary["climb_reading"] = args.climb_reading
    if getattr(args, "final_approach", None) is not None:
        summary["final_approach"] = args.final_approach
    if getattr(args, "hold_radius", None) is not None:
        summary["hold_radius"] = args.hold_radius
    if getattr(args, "lost_board", "hold") != "hold":
        summary["lost_board"] = args.lost_board
    if getattr(args, "segment_slack", None) is not None:
        summary["segment_slack"] = args.segment_slack
    for opt in ("height_margin", "height_approach", "mirror_check", "look_around"):
        if getattr(args, opt, None) is not None:
            summary[opt] = getattr(args, opt)
    if getattr(args, "look_around", None) is not None:
        summary["look_around_radius"] = args.look_around_radius
    if real:
        confirm_real_flight(args.host, args.yes or args.dry_run)
        detector, depth = perception_models(args.perception, None, args.depth_weights,
                                            args.detector_weights)
        args.reach_rule = reach_rule(args, depth=depth)
        summary["reach_rule"] = args.reach_rule.to_dict()
        tello = None
        if not args.dry_run:
            from djitellopy import Tello

            tello = Tello(host=args.host, retry_count=1)

        def carry_back(_env):
            if not args.yes and not args.dry_run:
                input("Put the drone at the start pose, then press Enter: ")

        base, tenv = make_tello_env(args, cfg, tello, detector, depth, carry_back)
        policy, _, _ = train_recipe.load_policy(run, env=tenv)
        try:
            rows = fly(args, policy, tenv, base)
        finally:
            base.close()
    else:
        from torchrl_causal.envs import TelloEmulator

        scene, layout_opts = emulated_scene(args, cfg)
        summary["layout"] = scene
        if args.goal_size is not None:
            summary["goal_size"] = list(args.goal_size)
        if args.board_back != "heliport":
            summary["board_back"] = args.board_back
        noise = NOISE if args.noise else {}
        summary["seed"] = seed
        with TelloEmulator(env_options=dict(layout_opts, seed=seed, **noise),
                           video_size=args.video_hw, time_scale=args.time_scale,
                           battery_drain_per_min=0.0) as emu:
            tello = emu.client()
            detector, depth = perception_models(args.perception, emu, args.depth_weights,
                                                args.detector_weights)
            args.reach_rule = reach_rule(args, depth=depth)
            summary["reach_rule"] = args.reach_rule.to_dict()

            def new_episode(env):
                emu.reset_world()
                lay = emu.env.layout  # this layout's goal height, board and arena
                fence, origin, ceiling = lay.fence()
                env.set_geofence(fence, origin=origin, max_height=ceiling)
                env.reach_rule = reach_rule(
                    args, float(lay.goal_point()[2]) if args.reach_height is not None else None,
                    layout=lay, depth=depth)

            base, tenv = make_tello_env(args, cfg, tello, detector, depth, new_episode,
                                        layout=emu.env.layout)
            policy, _, _ = train_recipe.load_policy(run, env=tenv)
            t0 = time.perf_counter()
            try:
                rows = fly(args, policy, tenv, base, emu)
            finally:
                base.close()
            summary["wall_s"] = round(time.perf_counter() - t0, 1)
            if getattr(args, "look_around", None) is not None:
                summary["look_arounds"] = base.look_arounds  # steps the drone looked around
        summary["success_sim"] = summarize(rows, "success_sim")
        # the arrival rule against the simulator's verdict, episode by episode
        summary["agreement"] = round(float(np.mean([r["success"] == r["success_sim"]
                                                    for r in rows])), 4)
        summary["false_reached"] = sum(1 for r in rows if r["success"] and not r["success_sim"])
        summary["missed_reach"] = sum(1 for r in rows if r["success_sim"] and not r["success"])
        closest = [r["closest_sim_m"] for r in rows if r["closest_sim_m"] != ""]
        summary["closest_sim_m_median"] = float(np.median(closest)) if closest else None
        sites = [r["crash_sim"] for r in rows if r["crash_sim"]]
        summary["crash_sim"] = {k: sites.count(k) for k in sorted(set(sites))}
    summary["success"] = summarize(rows)
    summary["crashes"] = sum(r["crash"] for r in rows)
    summary["mean_length"] = float(np.mean([r["length"] for r in rows]))
    if args.compare_sim:
        summary["dronenav"] = dronenav_reference(
            args, [r["success_sim"] for r in rows] if rows and rows[0]["success_sim"] != ""
            else None)
    (Path(args.out) / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary), flush=True)
    return summary


if __name__ == "__main__":
    main()
