"""A policy trained in simulation flies the Tello emulator on RGB-only perception.

``recipes/fly_tello.py`` end to end: the policy of ``torchrl_causal/pretrained/policies/thesis`` (made by
``make train``, seed 0, on ground-truth features) flies unmodified djitellopy against the
emulator over real UDP sockets, sees the decoded H.264 video only (shipped YOLOv8 detector +
MonoDepth), and its success rate (judged by the simulator behind the emulator) lies in the
95 % interval of the same policy in ``DroneNavEnv``. The moves are noise-free here, so the
flights repeat (a stable check); with move noise the emulator's rate is lower than
DroneNavEnv's (docs/tello.rst has the measured 20-episode runs)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import av
import numpy as np
import pandas as pd
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
POLICY = ROOT / "torchrl_causal" / "pretrained" / "policies" / "thesis"
sys.path.insert(0, str(ROOT / "recipes"))

import fly_tello  # noqa: E402


def test_trained_policy_reaches_the_goal_in_the_emulator_on_rgb_only(tmp_path):
    out = tmp_path / "fly"
    summary = fly_tello.main(["--run", str(POLICY), "--episodes", "3", "--compare-sim", "3",
                              "--out", str(out)])
    assert summary["perception"] == "rgb" and summary["target"] == "emulator"
    emu, sim = summary["success_sim"], summary["dronenav"]
    assert emu["n"] == sim["n"] == 3
    assert emu["rate"] == 1.0, summary  # every flight reaches the simulator's goal sphere
    lo, hi = sim["ci95"]
    assert lo <= emu["rate"] <= hi, summary  # within the DroneNavEnv policy's 95 % interval
    # DroneNavEnv flew the emulator's own episodes: paired, one verdict each
    paired = sim["paired"]
    assert paired["episodes"] == 3 and sum(paired[k] for k in (
        "both", "emulator_only", "dronenav_only", "neither")) == 3
    assert len(sim["success_per_episode"]) == 3 and paired["both"] == sum(sim["success_per_episode"])
    # the run folder: one CSV row per episode, the onboard video decodes, the summary
    rows = pd.read_csv(out / "episodes.csv")
    assert list(rows["episode"]) == [1, 2, 3]
    assert set(rows["success_sim"]) <= {0, 1} and (rows["length"] >= 1).all()
    # the closest approach agrees with the simulator's verdict (0.2 m reach radius)
    assert ((rows["closest_sim_m"] <= 0.2) == (rows["success_sim"] == 1)).all(), rows
    # what a crash hit is named for every crash and only there
    hit = rows["crash_sim"].fillna("").astype(str)
    assert ((hit != "") == (rows["crash"] == 1)).all(), rows
    assert sum(summary["crash_sim"].values()) == int(rows["crash"].sum())
    offsets = rows["land_offset_sim_m"].str.split().apply(lambda v: [float(x) for x in v])
    assert (offsets.apply(len) == 3).all()
    # the reading each "reached" fired on: within the rule's range (or a board held out of
    # sight by the arrival head, 0 m)
    fired = rows[rows["success"] == 1]
    assert len(fired) and (fired["goal_distance_m"] <= summary["reach_rule"]["max_distance"]).all()
    assert (fired["goal_angle_deg"].abs() <= summary["reach_rule"]["max_angle"]).all()
    with av.open(str(out / "onboard.mp4")) as c:
        frames = sum(1 for _ in c.decode(video=0))
    assert frames >= rows["length"].sum()
    assert json.loads((out / "summary.json").read_text())["success_sim"] == emu
    # a second flight into that folder is refused before it flies (its rows would follow
    # the first flight's, its video replace it), unless told to replace the first
    with pytest.raises(SystemExit):
        fly_tello.parse_args(["--run", str(POLICY), "--out", str(out)])
    again = fly_tello.main(["--run", str(POLICY), "--episodes", "1", "--no-video",
                            "--out", str(out), "--overwrite", "--log-steps"])
    assert again["episodes"] == 1
    row = pd.read_csv(out / "episodes.csv").iloc[0]
    assert list(pd.read_csv(out / "episodes.csv")["episode"]) == [1]
    assert not (out / "onboard.mp4").exists()  # the first flight's video went with it
    # --log-steps: one line per step, the last one carrying the episode's verdicts
    steps = [json.loads(line) for line in (out / "steps.jsonl").read_text().splitlines()]
    assert [s["step"] for s in steps] == list(range(1, int(row["length"]) + 1))
    last = steps[-1]
    assert last["reached"] == bool(row["success"]) and last["sim_reached"] == bool(row["success_sim"])
    assert last["closest_sim_m"] == pytest.approx(row["closest_sim_m"], abs=1e-3)
    assert last["approaches"] == row["approaches"]
    # the simulator's verdict never goes back; its closest approach only shrinks, and the
    # drone's true place after each step is no nearer than that closest approach
    assert all(a["sim_reached"] <= b["sim_reached"] for a, b in zip(steps, steps[1:]))
    assert all(b["closest_sim_m"] <= a["closest_sim_m"] for a, b in zip(steps, steps[1:]))
    assert all(np.linalg.norm(s["true_offset"]) >= s["closest_sim_m"] - 1e-3 for s in steps)
    assert all(-180.0 <= s["true_yaw_off_deg"] <= 180.0 for s in steps)
    # the thesis scene starts the drone facing the board square on
    assert abs(steps[0]["true_yaw_off_deg"]) <= 30.0, steps[0]
    if last["reached"]:  # the thesis scene's rule fires on the arrival head's estimate
        assert last["arrival_estimate"] is not None and len(last["arrival_estimate"]) == 3
    from tests._scripts import load_script  # benchmarks/: the per-step figures of that flight

    arrival_steps = load_script("benchmarks/arrival_steps.py")
    figs = {f["figure"]: f for f in arrival_steps.main([str(out / "steps.jsonl")])}
    assert figs["near_goal"]["episodes"] == 1
    assert figs["missed"]["episodes"] == int(row["success_sim"] and not row["success"])
    assert figs["false_reached"]["episodes"] == int(row["success"] and not row["success_sim"])
    # the flight folder itself is read too, and the counterfactual at a threshold no
    # estimate reaches leaves every verdict as flown
    again = {f["figure"]: f for f in arrival_steps.main([str(out), "--thresholds", "0.001"])}
    cf = again["threshold_counterfactual"]
    assert cf["episodes"] == 1 and again["climb_firings"]["episodes"] == 1
    assert cf["rows"][0]["agree"] == cf["agree_as_flown"] == int(row["success"] == row["success_sim"])


def test_arrival_steps_on_the_kept_step_logs(tmp_path, capsys):
    """benchmarks/arrival_steps.py on the eighteen fresh seeds' gzipped step logs: the
    figures docs/tello.rst ("Where the last disagreements are") prints, and bad input
    named."""
    from tests._scripts import load_script

    arrival_steps = load_script("benchmarks/arrival_steps.py")
    logs = sorted((ROOT / "docs" / "_static" / "results" / "tello" / "steps").glob(
        "mirror_defaults_s*_steps.jsonl.gz"))
    assert len(logs) == 18
    figs = {f["figure"]: f for f in arrival_steps.main([])}  # the kept logs by default
    cf = figs["threshold_counterfactual"]
    assert cf["episodes"] == 900 and cf["agree_as_flown"] == 853
    # the verdicts as flown agree with the committed episode tables
    summaries = [json.loads(Path(str(f).replace("steps/", "").replace(
        "_steps.jsonl.gz", "_summary.json")).read_text()) for f in logs]
    assert sum(s["missed_reach"] for s in summaries) == figs["missed"]["episodes"] == 20
    assert sum(s["false_reached"] for s in summaries) == figs["false_reached"]["episodes"] == 27
    agree = {r["threshold_m"]: r["agree"] for r in cf["rows"]}
    assert agree == {0.13: 853, 0.14: 851, 0.15: 850, 0.16: 842, 0.18: 831, 0.2: 804}
    assert max(agree.values()) == agree[0.13]  # every looser threshold loses
    m = figs["missed"]
    assert (m["turned_over_45_deg_at_pass"], m["board_unseen_at_pass"],
            m["head_asked_within_4_steps"], m["head_never_asked_before_pass"],
            m["entered_at_0_15_m_or_more"], m["inside_for_2_steps_or_fewer"]) == (
        16, 10, 7, 13, 12, 15)
    capsys.readouterr()
    for argv, msg in (([str(logs[0]), "--thresholds", "0"], "--thresholds must be in (0, 1]"),
                      ([str(tmp_path)], "no such steps.jsonl")):
        with pytest.raises((SystemExit, FileNotFoundError)) as e:
            arrival_steps.main(argv)
        assert msg in (capsys.readouterr().err + str(e.value))


def test_climb_firings_on_the_headline_and_printed_step_logs():
    """benchmarks/arrival_steps.py's climb_firings figure on the kept step logs
    (docs/tello.rst, "Climbs that read a new place"): of the headline's 80 false
    "reached" (two-faced board, 2,800 episodes), 31 fired on a climb or descent with a
    reading on both sides, all 31 withheld by the nearer reading (and 6 of the 11 true
    firings of that kind); with the printed board, 2 of 13; flown with the nearer
    reading on twenty fresh seeds, none of 16 (and of 12 with the two-faced board); the
    episode counts agree with the committed summaries."""
    from tests._scripts import load_script

    arrival_steps = load_script("benchmarks/arrival_steps.py")
    steps = ROOT / "docs" / "_static" / "results" / "tello" / "steps"
    headline = sorted(p for d in ("fresh16", "fresh24", "third16")
                      for p in (steps / d).glob("*_steps.jsonl.gz"))
    printed = sorted((steps / "printed12").glob("*_steps.jsonl.gz"))
    nearer = sorted((steps / "printed_climb20").glob("*_steps.jsonl.gz"))
    twofaced = sorted((steps / "twofaced_climb20").glob("*_steps.jsonl.gz"))
    assert (len(headline), len(printed), len(nearer), len(twofaced)) == (56, 12, 20, 20)
    got = {}
    for name, logs in (("headline", headline), ("printed", printed), ("nearer", nearer),
                       ("twofaced", twofaced)):
        fig = arrival_steps.climb_firings(arrival_steps.load_episodes(logs))
        summaries = [json.loads(Path(str(f).replace(f"steps/{f.parent.name}/", "").replace(
            "_steps.jsonl.gz", "_summary.json")).read_text()) for f in logs]
        assert fig["false"]["n"] + fig["other_firings_false"] == sum(
            s["false_reached"] for s in summaries)
        got[name] = (fig["episodes"], fig["false"]["n"], fig["false"]["withheld_nearer"],
                     fig["other_firings_false"], fig["true"]["n"],
                     fig["true"]["withheld_nearer"])
        if name == "headline":
            assert fig["false"]["jump_m_pct_50_90"] == [0.3, 0.693]
            assert fig["true"]["jump_m_pct_50_90"] == [0.08, 0.16]
    # flown with the nearer reading (twenty fresh seeds): no false firing on a climb is left
    assert got == {"headline": (2800, 31, 31, 49, 11, 6), "printed": (600, 2, 2, 11, 3, 2),
                   "nearer": (1000, 0, 0, 16, 1, 0), "twofaced": (1000, 0, 0, 12, 5, 0)}


def test_the_climb_readings_mechanism_check_is_its_kept_flights():
    """docs/tello.rst, "Climbs that read a new place": seed 557 flown with
    --climb-reading nearer on both boards, beside the kept default flights: the table's
    [success, agreement, false "reached", missed], and no false firing on a climb."""
    from tests._scripts import load_script

    arrival_steps = load_script("benchmarks/arrival_steps.py")
    res = ROOT / "docs" / "_static" / "results" / "tello"
    got = {stem: _kept_flight(res, stem, 557, "climb_reading", value)
           for stem, value in (("climb_nearer_s557", "nearer"),
                               ("climb_nearer_blank_s557", "nearer"),
                               ("third16_default_s557", None), ("third16_blank_s557", None))}
    assert got == {"climb_nearer_s557": [36, 49, 1, 0], "climb_nearer_blank_s557": [38, 50, 0, 0],
                   "third16_default_s557": [34, 49, 0, 1], "third16_blank_s557": [33, 50, 0, 0]}
    for stem in ("climb_nearer_s557", "climb_nearer_blank_s557"):
        fig = arrival_steps.climb_firings(arrival_steps.load_episodes(
            [res / "steps" / "climb_check" / f"{stem}_steps.jsonl.gz"]))
        assert fig["false"]["n"] == 0
    assert json.loads((res / "climb_nearer_blank_s557_summary.json").read_text())[
        "board_back"] == "blank"


def test_the_mechanism_checks_other_three_seeds_are_their_kept_flights():
    """docs/tello.rst, "The check's other three seeds, flown after the question": seeds
    563, 569 and 571 with --climb-reading nearer on both boards, per seed [success,
    agreement, false "reached", missed] beside the kept default flights; the option's
    flights have no false firing on a climb, the defaults' have three (two-faced) and one
    (printed), all of which the nearer reading withholds."""
    from tests._scripts import load_script

    arrival_steps = load_script("benchmarks/arrival_steps.py")
    res = ROOT / "docs" / "_static" / "results" / "tello"
    want = {"climb_nearer": ([38, 48, 1, 1], [38, 46, 3, 1], [40, 50, 0, 0]),
            "climb_nearer_blank": ([32, 49, 0, 1], [40, 48, 2, 0], [40, 49, 0, 1]),
            "third16_default": ([33, 47, 3, 0], [41, 46, 3, 1], [38, 47, 3, 0]),
            "third16_blank": ([36, 49, 1, 0], [41, 48, 2, 0], [38, 49, 0, 1])}
    for stem, rows in want.items():
        value = "nearer" if stem.startswith("climb") else None
        got = [_kept_flight(res, f"{stem}_s{seed}", seed, "climb_reading", value)
               for seed in (563, 569, 571)]
        assert got == list(rows), stem
    for stem, folder, climbs in (("climb_nearer", "climb_check", 0),
                                 ("climb_nearer_blank", "climb_check", 0),
                                 ("third16_default", "third16", 3),
                                 ("third16_blank", "third16_blank", 1)):
        fig = arrival_steps.climb_firings(arrival_steps.load_episodes(
            [res / "steps" / folder / f"{stem}_s{seed}_steps.jsonl.gz"
             for seed in (557, 563, 569, 571)]))
        assert fig["episodes"] == 200
        assert fig["false"]["n"] == fig["false"]["withheld_nearer"] == climbs, stem
    assert all(json.loads((res / f"climb_nearer_blank_s{seed}_summary.json").read_text())[
        "board_back"] == "blank" for seed in (563, 569, 571))


def _kept_flight(res, stem: str, seed: int, option: str, value) -> list[int]:
    """A kept 50-episode flight's ``[success, agreement, false "reached", missed]`` (its
    summary says the seed and ``option``'s value it was flown with)."""
    ep = pd.read_csv(res / f"{stem}_episodes.csv")
    summary = json.loads((res / f"{stem}_summary.json").read_text())
    assert len(ep) == 50 and summary["seed"] == seed
    assert summary.get(option) == value
    tel, sim = ep["success"].astype(bool), ep["success_sim"].astype(bool)
    return [int(v) for v in (sim.sum(), (tel == sim).sum(), (tel & ~sim).sum(),
                             (~tel & sim).sum())]


def test_the_vertical_legs_published_figures_are_its_kept_flights():
    """docs/tello.rst, "The vertical leg": the pooled figures in height_approach.json are
    the kept episode tables' (twelve seeds, with and without --height-approach 0.3, paired
    by episode), and they show what the page says: agreement unchanged, missed arrivals
    traded for false "reached"."""
    res = ROOT / "docs" / "_static" / "results" / "tello"
    pooled = json.loads((res / "height_approach.json").read_text())
    seeds = pooled["groups"]["decision"] + pooled["groups"]["confirmation"]
    assert len(seeds) == 12
    tot = {"with": [0, 0, 0, 0], "without": [0, 0, 0, 0]}
    for s in seeds:
        for tag, name in (("with", f"height_approach_s{s}"), ("without", f"obst_depth_s{s}")):
            got = _kept_flight(res, name, s, "height_approach", 0.3 if tag == "with" else None)
            tot[tag] = [a + b for a, b in zip(tot[tag], got)]
    got = {k: dict(zip(("success", "agree", "false_reached", "missed"), v))
           for k, v in tot.items()}
    for tag, key in (("with", "height_approach"), ("without", "before_vertical_leg")):
        assert {k: pooled["all"][key][k] for k in got[tag]} == got[tag]
    assert got["with"]["agree"] == got["without"]["agree"] == 561
    assert (got["with"]["missed"], got["without"]["missed"]) == (7, 16)
    assert (got["with"]["false_reached"], got["without"]["false_reached"]) == (32, 23)
    steps = sorted((res / "steps" / "height_approach").glob("height_approach_s*_steps.jsonl.gz"))
    assert len(steps) == 12


@pytest.mark.parametrize("name, option, value, agree, false_reached, missed", [
    ("look_around", "look_around", 12.0, (577, 562), (11, 28), (12, 10)),
    ("cap02", "height_approach", 0.2, (574, 562), (18, 28), (8, 10)),
])
def test_the_fresh_seeds_published_figures_are_their_kept_flights(name, option, value, agree,
                                                                   false_reached, missed):
    """docs/tello.rst, "Looking around before landing" and the 0.2 m cap: the pooled figures
    in look_around.json / cap02.json are the kept episode tables' (twelve fresh seeds, each
    variant paired by episode with the default flights of the same seeds), and both rules
    fixed before the flights are met by them."""
    res = ROOT / "docs" / "_static" / "results" / "tello"
    pooled = json.loads((res / f"{name}.json").read_text())
    tot = {}
    for group in ("decision", "confirmation"):
        seeds = pooled[group]["seeds"]
        assert len(seeds) == 6
        g = {"variant": [0, 0, 0, 0], "default": [0, 0, 0, 0]}
        for s in seeds:
            for tag, stem in (("variant", f"{name}_s{s}"), ("default", f"fresh30_default_s{s}")):
                got = _kept_flight(res, stem, s, option, value if tag == "variant" else None)
                g[tag] = [a + b for a, b in zip(g[tag], got)]
        for tag in g:
            for i, key in enumerate(("success", "agreement", "false_reached", "missed")):
                assert pooled[group][f"{key}_{tag}"] == g[tag][i]
                tot.setdefault((tag, key), 0)
                tot[(tag, key)] += g[tag][i]
        assert g["variant"][1] >= g["default"][1] and g["variant"][2] < 15  # the rule
    assert (tot[("variant", "agreement")], tot[("default", "agreement")]) == agree
    assert (tot[("variant", "false_reached")], tot[("default", "false_reached")]) == false_reached
    assert (tot[("variant", "missed")], tot[("default", "missed")]) == missed
    steps = sorted((res / "steps" / "fresh30").glob(f"{name}_s*_steps.jsonl.gz"))
    assert len(steps) == 12


def test_bad_options_are_named_before_any_flight(capsys):
    with pytest.raises(SystemExit):
        fly_tello.main(["--run", str(POLICY), "--perception", "lidar"])
    assert "--perception must be one of rgb, sim, sim-depth, sim-detector or module:factory" \
        in capsys.readouterr().err
    with pytest.raises(SystemExit):
        fly_tello.main(["--run", str(POLICY), "--host", "192.168.10.1", "--perception", "sim"])
    assert "exists only in the emulator" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        fly_tello.main(["--run", str(ROOT / "docs"), "--episodes", "1"])
    assert "not a run folder" in capsys.readouterr().err


def test_rgb_perception_takes_other_weights(tmp_path, capsys):
    """--depth-weights / --detector-weights swap the shipped models (a fine-tune); a missing
    file or another perception is named before take-off."""
    from torchrl_causal.perception.depth import FCRN, MonoDepth

    small = tmp_path / "depth.pt"
    MonoDepth(FCRN(widths=(8, 8, 8, 8, 8), decoder=(8, 8, 8, 8))).save(small)
    args = fly_tello.parse_args(["--run", str(POLICY), "--depth-weights", str(small)])
    detector, depth = fly_tello.perception_models(args.perception, None, args.depth_weights,
                                                  args.detector_weights)
    assert tuple(depth.net.config["widths"]) == (8, 8, 8, 8, 8)
    assert type(detector).__name__ == "YoloGoalDetector"
    _, shipped = fly_tello.perception_models("rgb")
    assert tuple(shipped.net.config["widths"]) != (8, 8, 8, 8, 8)
    for argv, message in [
        (["--depth-weights", str(tmp_path / "none.pt")], "--depth-weights"),
        (["--detector-weights", str(tmp_path / "none.pt")], "no such file"),
        (["--perception", "sim", "--depth-weights", str(small)], "applies where the depth is"),
        (["--perception", "sim-depth", "--depth-weights", str(small)], "applies where the depth"),
        (["--host", "192.168.10.1", "--perception", "sim-depth"], "exists only in the emulator"),
    ]:
        with pytest.raises(SystemExit):
            fly_tello.main(["--run", str(POLICY), *argv])
        assert message in capsys.readouterr().err


def test_mixed_perception_takes_one_model_from_the_emulator(tmp_path):
    """sim-depth: the RGB detector with the emulator's depth; sim-detector: the emulator's
    detector with MonoDepth (the given weights) -- to tell which model an error comes from."""
    from torchrl_causal.envs.tello_emulator import TelloEmulator
    from torchrl_causal.perception.depth import FCRN, MonoDepth
    from torchrl_causal.perception.yolo import YoloGoalDetector

    small = tmp_path / "depth.pt"
    MonoDepth(FCRN(widths=(8, 8, 8, 8, 8), decoder=(8, 8, 8, 8))).save(small)
    with TelloEmulator(fps=5, time_scale=20.0, video_size=(240, 320)) as emu:
        det, depth = fly_tello.perception_models("sim-depth", emu)
        assert isinstance(det, YoloGoalDetector) and not isinstance(depth, MonoDepth)
        d = depth(torch.zeros(1, 60, 80, 3, dtype=torch.uint8))  # the emulator's true depth
        assert d.shape == (1, 60, 80) and torch.isfinite(d).all() and (d > 0).all()
        det, depth = fly_tello.perception_models("sim-detector", emu, depth_weights=str(small))
        assert not isinstance(det, YoloGoalDetector) and isinstance(depth, MonoDepth)
        assert tuple(depth.net.config["widths"]) == (8, 8, 8, 8, 8)
    args = fly_tello.parse_args(["--run", str(POLICY), "--perception", "sim-detector",
                                 "--depth-weights", str(small)])
    assert args.depth_weights == str(small)


@pytest.mark.parametrize("argv,message", [
    (["--video-size", "100x100"], "a Tello streams 960x720"),
    (["--video-size", "1080x1440"], "a Tello streams 960x720"),
    (["--host", "192.168.10.1", "--video-size", "480x640", "--dry-run"], "the option is the emulator's"),
    (["--reach-distance", "-0.3"], "ReachRule.max_distance"),
    (["--reach-height", "0"], "ReachRule.max_height_offset"),
    (["--reach-offset", "0"], "ReachRule.max_goal_offset"),
    (["--reach-offset", "0.2", "--board-width", "-1"], "ReachRule.board_width"),
    (["--arrival-head", "x.pt"], "--arrival-head 'x.pt' needs --reach-offset"),
    (["--arrival-head", "depth"], "--arrival-head 'depth' needs --reach-offset"),
    (["--host", "192.168.10.1", "--seed", "3", "--dry-run"], "the option is the emulator's"),
    (["--arrival-head", "missing.pt", "--reach-offset", "0.2"], "'missing.pt': no such file"),
    (["--arrival-head", "none", "--arrival-fusion"], "--arrival-fusion fuses the arrival head"),
    (["--arrival-head", "none", "--climb-reading", "nearer"],
     "--climb-reading nearer keeps one of the arrival head's readings"),
    (["--climb-reading", "nearer", "--arrival-fusion"], "both decide where a climb's readings"),
    (["--climb-reading", "first"], "invalid choice: 'first'"),
    (["--arrival-head", "none", "--final-approach", "0.4"], "it needs the head"),
    (["--final-approach", "near"], "--final-approach must be a radius (m), 'auto' or 'none'"),
    (["--final-approach", "2.5"], "--final-approach must be a radius in [0.05, 1.0] m"),
    (["--arrival-head", "none", "--hold-radius", "0.4"], "--hold-radius 0.4 holds the arrival"),
    (["--hold-radius", "0"], "--hold-radius must be a distance in [0.05, 1.0] m, got 0"),
    (["--lost-board", "carry", "--final-approach", "none"], "it needs --final-approach"),
    (["--lost-board", "keep"], "invalid choice: 'keep'"),
    (["--lost-board", "ask", "--arrival-head", "none"], "--lost-board ask asks the arrival head"),
    (["--host", "192.168.10.1", "--board-back", "blank", "--dry-run"],
     "--board-back blank: the option is the emulator's"),
    (["--board-back", "plain"], "invalid choice: 'plain'"),
    (["--height-margin", "0.07", "--arrival-head", "none"], "it needs the head"),
    (["--height-margin", "0.9"], "--height-margin must be a distance in [0, 0.5] m, got 0.9"),
    (["--height-approach", "0.3", "--arrival-head", "none"], "it needs the head"),
    (["--height-approach", "0.9"], "--height-approach must be a distance in [0, 0.5] m"),
    (["--height-approach", "0"], "--height-approach must be a height above 0 m"),
    (["--height-approach", "0.3", "--final-approach", "none"], "it needs --final-approach"),
    (["--height-approach", "high"], "--height-approach must be a height (m), 'auto' or 'none'"),
    (["--mirror-check", "0.1", "--arrival-head", "none"], "asks the learned arrival head twice"),
    (["--look-around", "12", "--arrival-head", "none"], "it needs the head"),
    (["--look-around", "60"], "--look-around must be a turn of 1-45 deg, got 60"),
    (["--look-around", "wide"], "--look-around must be a turn (deg), 'auto' or 'none', got 'wide'"),
    (["--look-around", "12", "--look-around-radius", "0.9"],
     "--look-around-radius must be a distance in [0, 0.5] m, got 0.9"),
    (["--look-around", "12", "--look-around-radius", "0.05"], "is below --reach-offset"),
    (["--mirror-check", "-0.1"], "--mirror-check must be a distance in [0, 1] m, got -0.1"),
    (["--mirror-check", "twice"], "--mirror-check must be a distance (m), 'auto' or 'none'"),
    (["--segment-slack", "wide"], "--segment-slack must be a distance (m), 'auto' or 'none'"),
    (["--segment-slack", "2"], "--segment-slack must be a distance in [0, 1] m, got 2"),
    (["--segment-slack", "0.2", "--arrival-head", "none"], "it needs the head"),
    (["--lost-board", "ask", "--arrival-head", "rooms", "--reach-offset", "0.13"],
     "has none"),
    (["--fresh-hits", "--map", "exact"], "--fresh-hits overrides the log-odds of the "
                                         "estimated map: it needs --map estimated, got --map "
                                         "exact"),
    (["--host", "192.168.10.1", "--goal-size", "1", "0.8", "--dry-run"],
     "the option is the emulator's"),
    (["--layout", "heldout", "--goal-size", "0.1", "0.8"], "--goal-size must be two sizes"),
    (["--goal-size", "1", "0.8"], "--goal-size applies to the emulator's random layouts"),
])
def test_bad_video_size_and_reach_rule_are_named_before_take_off(argv, message, capsys,
                                                                 tmp_path):
    out = tmp_path / "flight"  # an option that stopped being refused flies here, not into the run
    with pytest.raises(SystemExit):
        fly_tello.main(["--run", str(POLICY), "--out", str(out), *argv])
    assert message in capsys.readouterr().err
    assert not (out / "episodes.csv").exists()


def test_the_view_head_looks_around_by_default():
    """``--look-around auto`` (default): 12 deg where the view head flies (``--lost-board
    ask``), none with the other heads or without one; a number or ``none`` overrides it.
    ``--height-approach auto`` (default since 2026-12-02): 0.2 m wherever the look-around
    flies with the final approach, none elsewhere; a height or ``none`` overrides it."""
    common = ["--run", str(POLICY), "--layout", "heldout", "--goal-size", "1", "0.8",
              "--reach-offset", "0.13"]
    view = fly_tello.parse_args([*common, "--arrival-head", "view"])
    assert view.lost_board == "ask" and view.look_around == fly_tello.LOOK_AROUND == 12
    assert view.look_around_radius == 0.2
    assert view.height_approach == fly_tello.HEIGHT_APPROACH == 0.2
    off = fly_tello.parse_args([*common, "--arrival-head", "view", "--look-around", "none"])
    assert off.look_around is None and off.height_approach is None
    turned = fly_tello.parse_args([*common, "--arrival-head", "view", "--look-around", "20"])
    assert turned.look_around == 20 and turned.height_approach == 0.2
    assert fly_tello.parse_args([*common, "--arrival-head", "view", "--height-approach",
                                 "none"]).height_approach is None
    assert fly_tello.parse_args([*common, "--arrival-head", "view", "--height-approach",
                                 "0.3"]).height_approach == 0.3
    # the final approach flies the vertical leg: without it auto asks for none
    assert fly_tello.parse_args([*common, "--arrival-head", "view", "--final-approach",
                                 "none"]).height_approach is None
    rooms = fly_tello.parse_args([*common, "--arrival-head", "rooms"])
    assert rooms.look_around is None and rooms.height_approach is None
    thesis = fly_tello.parse_args(["--run", str(POLICY)])  # thesis room: the shipped head
    assert thesis.look_around is None and thesis.height_approach is None


def test_the_view_head_reads_a_climb_nearer_by_default():
    """``--climb-reading auto`` (default since 2026-12-07): ``nearer`` where the view head
    flies (``--lost-board ask``, the setting the arrival target is shown for on fresh seeds
    with both boards), ``both`` with the other heads, with ``--arrival-fusion`` and without a
    head; an explicit value overrides it, and the flight's summary records the one flown."""
    common = ["--run", str(POLICY), "--layout", "heldout", "--goal-size", "1", "0.8",
              "--reach-offset", "0.13"]
    assert fly_tello.parse_args([*common, "--arrival-head", "view"]).climb_reading == "nearer"
    assert fly_tello.parse_args(["--goal-size", "1.0", "0.8"]).climb_reading == "nearer"
    real = fly_tello.parse_args(["--run", str(POLICY), "--host", "192.168.10.1", "--dry-run"])
    assert real.climb_reading == "nearer"  # a real drone flies the view head
    assert fly_tello.parse_args([*common, "--arrival-head", "view", "--climb-reading",
                                 "both"]).climb_reading == "both"
    assert fly_tello.parse_args([*common, "--arrival-head", "view", "--lost-board",
                                 "hold"]).climb_reading == "both"
    assert fly_tello.parse_args([*common, "--arrival-head", "view", "--arrival-fusion"]
                                ).climb_reading == "both"  # fusion decides climbs instead
    assert fly_tello.parse_args([*common, "--arrival-head", "rooms"]).climb_reading == "both"
    assert fly_tello.parse_args(["--run", str(POLICY)]).climb_reading == "both"  # thesis head
    assert fly_tello.parse_args([]).climb_reading == "both"  # no head: the depth map's rule
    assert fly_tello.parse_args(["--run", str(POLICY), "--climb-reading", "nearer"]
                                ).climb_reading == "nearer"


def test_a_head_that_can_decline_is_asked_by_default():
    """``--arrival-head view`` (a head with an in-view output): ``--lost-board auto`` asks it
    without the detector and ``--segment-slack auto`` checks its segments; the other heads
    keep the one-step hold and every segment."""
    from torchrl_causal.perception.arrival import ROOMS_WEIGHTS, VIEW_WEIGHTS

    common = ["--run", str(POLICY), "--layout", "heldout", "--goal-size", "1", "0.8",
              "--reach-offset", "0.13"]
    view = fly_tello.parse_args([*common, "--arrival-head", "view"])
    assert (view.arrival_head, view.lost_board, view.segment_slack, view.mirror_check) == (
        str(VIEW_WEIGHTS), "ask", fly_tello.SEGMENT_SLACK, fly_tello.MIRROR_CHECK)
    rooms = fly_tello.parse_args([*common, "--arrival-head", "rooms"])
    assert (rooms.arrival_head, rooms.lost_board, rooms.segment_slack, rooms.mirror_check) == (
        str(ROOMS_WEIGHTS), "hold", None, None)
    off = fly_tello.parse_args([*common, "--arrival-head", "view", "--segment-slack", "none",
                                "--lost-board", "hold"])
    assert (off.lost_board, off.segment_slack, off.mirror_check) == ("hold", None, None)
    once = fly_tello.parse_args([*common, "--arrival-head", "view", "--mirror-check", "none"])
    assert once.mirror_check is None and once.lost_board == "ask"
    assert fly_tello.parse_args([*common, "--arrival-head", "rooms", "--mirror-check", "0.1"]
                                ).mirror_check == 0.1
    # --board-back blank: the emulator's DroneNavEnv gets the printed board's blank back
    blank = fly_tello.parse_args([*common, "--board-back", "blank"])
    assert fly_tello.emulated_scene(blank, None)[1]["board_back"] == "blank"
    assert "board_back" not in fly_tello.emulated_scene(view, None)[1]


def test_the_reach_rule_options_build_the_rule():
    args = fly_tello.parse_args(["--run", str(POLICY), "--reach-distance", "0.45",
                                 "--reach-height", "0.12", "--reach-full-width"])
    rule = args.reach_rule
    assert (rule.max_distance, rule.max_height_offset, rule.full_width) == (0.45, 0.12, True)
    assert rule.goal_height == 1.0  # the emulated layout's height comes per episode
    assert fly_tello.reach_rule(args, goal_height=1.3).goal_height == 1.3
    # without the head: 0.45 m and the height sensor within 0.12 m; --no-height-check: the
    # old form
    default = fly_tello.parse_args(["--run", str(POLICY), "--arrival-head", "none"]).reach_rule
    assert (default.max_distance, default.max_height_offset, default.goal_height) == \
        (0.45, 0.12, 1.0) and default.max_goal_offset is None
    plain = fly_tello.parse_args(["--run", str(POLICY), "--arrival-head", "none",
                                  "--no-height-check"]).reach_rule
    assert plain.goal_height is None


def test_the_arrival_head_is_the_default_where_it_was_measured():
    """--arrival-head auto, on RGB perception and the 1.0 x 0.8 m board: the shipped
    thesis-room head (offset <= 0.15 m, range bound 1.0 m) on the thesis scene, the shipped
    head that can decline (offset <= 0.13 m, asked with --lost-board ask) in other rooms -- a
    real drone's, the emulator's random layouts with the printed board --, and the depth map's
    rule elsewhere."""
    from torchrl_causal.perception.arrival import DEFAULT_WEIGHTS, ROOMS_WEIGHTS, VIEW_WEIGHTS

    thesis = fly_tello.parse_args(["--run", str(POLICY)])
    assert thesis.arrival_head == str(DEFAULT_WEIGHTS)
    rule = thesis.reach_rule
    assert (rule.max_goal_offset, rule.max_distance) == (fly_tello.HEAD_REACH_OFFSET, 1.0)
    assert fly_tello.parse_args(["--run", str(POLICY), "--arrival-fusion"]).arrival_fusion
    assert fly_tello.parse_args(["--run", str(POLICY), "--reach-offset", "0.18"]
                                ).reach_rule.max_goal_offset == 0.18  # the user's value wins
    real = fly_tello.parse_args(["--run", str(POLICY), "--host", "192.168.10.1", "--dry-run"])
    assert real.arrival_head == str(VIEW_WEIGHTS) and real.lost_board == "ask"
    assert real.mirror_check == fly_tello.MIRROR_CHECK  # the mean of frame and mirror image
    assert real.reach_rule.max_goal_offset == fly_tello.ROOMS_REACH_OFFSET == 0.13
    rooms = fly_tello.parse_args(["--goal-size", "1.0", "0.8"])  # the generalist, printed board
    assert rooms.arrival_head == str(VIEW_WEIGHTS) and rooms.final_approach == 0.4
    assert rooms.segment_slack == fly_tello.SEGMENT_SLACK
    assert (rooms.reach_rule.max_goal_offset, rooms.reach_rule.board_width) == (0.13, 1.0)
    assert fly_tello.parse_args(["--arrival-head", "rooms", "--reach-offset", "0.2"]
                                ).arrival_head == str(ROOMS_WEIGHTS)
    assert fly_tello.parse_args(["--goal-size", "0.8", "0.6"]).arrival_head is None
    assert fly_tello.parse_args(["--goal-size", "1.0", "0.8", "--board-width", "0.9"]
                                ).arrival_head is None
    for other in (["--layout", "heldout"], ["--perception", "sim"], ["--board-width", "0.8"],
                  ["--arrival-head", "none"]):
        args = fly_tello.parse_args(["--run", str(POLICY), *other])
        assert args.arrival_head is None and args.reach_rule.max_goal_offset in (None,), other
    generalist = fly_tello.parse_args([])  # the shipped generalist: random layouts
    assert generalist.arrival_head is None
    # --final-approach auto: wherever the head flies, and only there
    assert thesis.final_approach == real.final_approach == fly_tello.FINAL_APPROACH_RADIUS
    assert generalist.final_approach is None
    assert fly_tello.parse_args(["--run", str(POLICY), "--final-approach", "none"]
                                ).final_approach is None
    assert fly_tello.parse_args(["--run", str(POLICY), "--final-approach", "0.3"]
                                ).final_approach == 0.3
    # --hold-radius: unset (TelloEnv's twice --reach-offset) unless given
    assert thesis.hold_radius is None
    assert fly_tello.parse_args(["--run", str(POLICY), "--hold-radius", "0.4"]
                                ).hold_radius == 0.4


def test_the_full_width_check_is_the_default_on_random_layouts():
    """--reach-full-width auto: on for the emulator's random layouts (no arrival head, or
    none chosen), off on the thesis board and on a real drone; on / off / a bare flag
    override it."""
    def full_width(*argv):
        return fly_tello.parse_args(list(argv)).reach_rule.full_width

    assert full_width() is True  # the shipped generalist: held-out random layouts
    assert full_width("--run", str(POLICY)) is False  # the thesis scene, with the head
    assert full_width("--run", str(POLICY), "--arrival-head", "none") is False
    assert full_width("--run", str(POLICY), "--layout", "heldout") is True
    assert full_width("--run", str(POLICY), "--layout", "heldout", "--perception", "sim",
                      "--arrival-head", "none") is True
    # with the simulator's depth the board plane decides there (--arrival-head auto: depth)
    assert full_width("--run", str(POLICY), "--layout", "heldout", "--perception", "sim") is False
    assert full_width("--run", str(POLICY), "--host", "192.168.10.1", "--dry-run") is False
    assert full_width("--reach-full-width", "off") is False
    assert full_width("--run", str(POLICY), "--reach-full-width") is True
    assert full_width("--run", str(POLICY), "--reach-full-width", "on") is True
    args = fly_tello.parse_args(["--reach-full-width", "auto"])
    assert args.reach_full_width == "on"  # resolved, and recorded in the flight's summary


def test_the_depth_models_calibrated_range_is_the_default_threshold():
    """Without --reach-distance the range threshold is the depth model's own (stored with
    its weights by recipes/train_depth.py); --reach-distance and --reach-offset win."""
    from torchrl_causal.perception.depth import FCRN, MonoDepth

    depth = MonoDepth(FCRN(widths=(8, 8, 8, 8, 8), decoder=(8, 8, 8, 8)),
                      meta={"reach_calibration": {"max_distance": 0.38}})
    args = fly_tello.parse_args(["--run", str(POLICY), "--arrival-head", "none"])
    assert fly_tello.reach_rule(args, goal_height=1.2, depth=depth).max_distance == 0.38
    assert fly_tello.reach_rule(args, depth=MonoDepth(FCRN())).max_distance == 0.45
    given = fly_tello.parse_args(["--run", str(POLICY), "--reach-distance", "0.5"])
    assert fly_tello.reach_rule(given, depth=depth).max_distance == 0.5
    offset = fly_tello.parse_args(["--run", str(POLICY), "--reach-offset", "0.2"])
    assert fly_tello.reach_rule(offset, depth=depth).max_distance == 1.0


def test_the_board_plane_head_flies_any_board_with_the_final_approach():
    """--arrival-head depth: no weights file; the env gets a BoardPlaneOffset (reading the
    rule's per-layout board width) and, with --final-approach, the approach."""
    from torchrl_causal.envs import BoardPlaneOffset, FinalApproach
    from torchrl_causal.envs.layouts import RandomLayoutGenerator

    args = fly_tello.parse_args(["--run", str(POLICY), "--layout", "heldout", "--perception",
                                 "sim", "--arrival-head", "depth", "--reach-offset", "0.2",
                                 "--final-approach", "0.4", "--hold-radius", "0.5",
                                 "--lost-board", "carry", "--dry-run"])
    assert args.arrival_head == "depth" and args.final_approach == 0.4
    assert args.reach_rule.full_width is False  # the head decides, as on the thesis board
    # the default on random layouts with the simulator's depth, where it was measured
    auto = fly_tello.parse_args(["--run", str(POLICY), "--layout", "heldout",
                                 "--perception", "sim"])
    assert auto.arrival_head == "depth" and auto.final_approach == fly_tello.FINAL_APPROACH_RADIUS
    assert auto.reach_rule.max_goal_offset == fly_tello.PLANE_REACH_OFFSET == 0.2
    for other in (["--layout", "heldout"], ["--perception", "sim"]):  # MonoDepth; thesis board
        assert fly_tello.parse_args(["--run", str(POLICY), *other]).arrival_head != "depth"
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(POLICY / "config.yaml")
    lay = RandomLayoutGenerator("heldout", seed=0).layout(3)
    from torchrl_causal.perception.goal import SimGoalDetector

    env, _ = fly_tello.make_tello_env(args, cfg, None, SimGoalDetector(),
                                      lambda p: torch.ones(p.shape[:3]), None, layout=lay)
    try:
        assert isinstance(env.arrival_head, BoardPlaneOffset)
        assert isinstance(env.final_approach, FinalApproach) and env.final_approach.radius == 0.4
        assert env.hold_radius == 0.5 and env.lost_board == "carry"
    finally:
        env.close()


def test_reach_offset_takes_the_emulated_layouts_board():
    from torchrl_causal.envs.layouts import RandomLayoutGenerator

    args = fly_tello.parse_args(["--run", str(POLICY), "--reach-offset", "0.2"])
    rule = args.reach_rule
    assert (rule.max_goal_offset, rule.board_width, rule.goal_standoff) == (0.2, 1.0, 0.45)
    assert rule.max_distance == 1.0  # the offset decides; the camera's range only bounds it
    lay = RandomLayoutGenerator("heldout", seed=0).layout(3)
    per_layout = fly_tello.reach_rule(args, goal_height=1.2, layout=lay)
    assert per_layout.board_width == float(lay.goal_size[0]) != 1.0
    assert per_layout.goal_height == 1.2
    fixed = fly_tello.parse_args(["--run", str(POLICY), "--reach-offset", "0.2",
                                  "--board-width", "0.8"])
    assert fly_tello.reach_rule(fixed, layout=lay).board_width == 0.8  # the user's board wins


def test_goal_size_gives_the_emulators_random_layouts_that_board():
    """--goal-size: the emulator's random layouts (and DroneNavEnv's, for --compare-sim)
    all hold a board of that size, e.g. the field guide's printed 1.0 x 0.8 m one."""
    from omegaconf import OmegaConf

    from torchrl_causal.envs import DroneNavEnv

    cfg = OmegaConf.load(POLICY / "config.yaml")
    args = fly_tello.parse_args(["--run", str(POLICY), "--layout", "heldout",
                                 "--goal-size", "1.0", "0.8"])
    scene, opts = fly_tello.emulated_scene(args, cfg)
    assert scene == "heldout" and opts["goal_size"] == (1.0, 0.8)
    env = DroneNavEnv(**opts, image_size=32, seed=0)
    try:
        for _ in range(3):
            env.reset()
            assert tuple(env.layout.goal_size) == (1.0, 0.8)
            assert env.layout.name.startswith("heldout")
    finally:
        env.close()
    _, drawn = fly_tello.emulated_scene(fly_tello.parse_args(["--run", str(POLICY), "--layout",
                                                              "heldout"]), cfg)
    assert "goal_size" not in drawn


def test_sim_to_real_benchmark_prints_its_figures_as_json(tmp_path, capsys):
    """benchmarks/sim_to_real.py: one JSON object per seed and one pooled, with the targets;
    fly_tello's own lines stay off stdout."""
    from torchrl_causal.perception.yolo import DEFAULT_WEIGHTS

    bench = [sys.executable, str(ROOT / "benchmarks" / "sim_to_real.py")]
    # candidate weights fly in place of the shipped ones (here the shipped file, by path)
    r = subprocess.run(bench + ["--episodes", "2", "--seeds", "3", "--out", str(tmp_path),
                                "--detector-weights", str(DEFAULT_WEIGHTS),
                                "--compare-perception", "rgb"],
                       capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    figs = [json.loads(line) for line in r.stdout.splitlines()]
    assert [f["figure"] for f in figs] == ["sim_to_real", "sim_to_real_pooled"]
    one, pooled = figs
    assert one["episodes"] == pooled["episodes"] == 2 and one["layout"] == "thesis"
    assert one["arrival_head"].endswith("arrival.pt")  # the default rule on the thesis board
    assert 0.0 <= pooled["success_sim"] <= 1.0 and pooled["seeds"] == [3]
    assert set(pooled["targets"]) == {"inside_dronenav_ci", "agreement", "agreement_shown",
                                      "false_reached", "false_reached_shown", "success"}
    assert (tmp_path / "thesis_seed3" / "episodes.csv").is_file()
    assert one["detector_weights"] == str(DEFAULT_WEIGHTS) and one["depth_weights"] == "shipped"
    assert one["map"] is None  # the thesis policy reads no EgoMap
    # DroneNavEnv's reference flew the emulator's two episodes, on the same RGB models
    assert one["dronenav_perception"] == "rgb" and one["dronenav_paired"]["episodes"] == 2
    # a candidate that is not there is named before anything flies
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import sim_to_real

    with pytest.raises(SystemExit) as exit_:
        sim_to_real.main(["--depth-weights", str(tmp_path / "nope.pt")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "--depth-weights" in err and "nope.pt" in err


def test_sim_to_real_pools_flights_already_flown(tmp_path, capsys):
    """--from-flights: the twenty fresh seeds docs/tello.rst reports, pooled from their
    committed summaries; runs of another setting, a seed given twice, a file that is not
    a summary and a missing path are named and refused."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import sim_to_real

    data = sorted((ROOT / "docs" / "_static" / "results" / "tello").glob(
        "mirror_defaults_s*_summary.json"))
    assert len(data) == 20
    figs = sim_to_real.main(["--from-flights", *map(str, data)])
    *seeds, pooled = figs
    assert [f["figure"] for f in seeds] == ["sim_to_real"] * 20
    assert [f["seed"] for f in seeds] == sorted(f["seed"] for f in seeds)
    assert pooled["figure"] == "sim_to_real_pooled" and pooled["policy"] == "generalist"
    # the pooled counts are the seeds' counts summed, and what the docs print
    assert pooled["agreed"] == sum(round(f["agreement"] * f["episodes"]) for f in seeds) == 949
    assert pooled["episodes"] == 1000 and pooled["false_reached"] == 29
    assert pooled["crash_sim"] == {"board": 125, "obstacle": 228}
    lo, hi = pooled["agreement_ci95"]
    assert lo < 0.95 < hi and pooled["false_reached_ci95"][1] < 0.05
    assert pooled["targets"]["agreement"] is False and pooled["targets"]["agreement_shown"] is False
    assert pooled["targets"]["false_reached_shown"] is True
    # two of them flew DroneNavEnv beside the emulator, the rest did not: no pooled reference
    assert pooled["dronenav"] is None and pooled["targets"]["inside_dronenav_ci"] is None
    assert sum(f["dronenav"] is not None for f in seeds) == 2
    # a run folder holding a summary.json is taken as the file
    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text(data[0].read_text())
    one = sim_to_real.main(["--from-flights", str(run)])
    assert one[0]["seed"] == json.loads(data[0].read_text())["seed"]
    capsys.readouterr()
    other = json.loads(data[1].read_text())
    other.update(seed=9999, mirror_check=0.1, episodes=20)
    (tmp_path / "other.json").write_text(json.dumps(other))
    (tmp_path / "not_a_summary.json").write_text(json.dumps({"frames": 3}))
    for argv, message in (
            ([data[0], tmp_path / "other.json"], "episodes, mirror_check differ"),
            ([data[0], data[0]], "given more than once"),
            ([tmp_path / "not_a_summary.json"], "is not a fly_tello.py emulator summary"),
            ([tmp_path / "nope"], "is neither a summary.json nor a folder holding one")):
        with pytest.raises(SystemExit) as exit_:
            sim_to_real.main(["--from-flights", *map(str, argv)])
        assert exit_.value.code == 2
        assert message in capsys.readouterr().err


def test_sim_to_real_pools_the_look_around_flights(capsys):
    """The twelve look-around flights docs/tello.rst reports pool as one setting: how often
    each looked around is a flight's count, not its setting (the counts differ by seed)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import sim_to_real

    data = sorted((ROOT / "docs" / "_static" / "results" / "tello").glob(
        "look_around_s*_summary.json"))
    assert len(data) == 12
    counts = {json.loads(f.read_text())["look_arounds"] for f in data}
    assert len(counts) > 1  # differ between seeds, yet one setting
    *seeds, pooled = sim_to_real.main(["--from-flights", *map(str, data)])
    assert len(seeds) == 12 and pooled["episodes"] == 600
    assert pooled["agreed"] == 577 and pooled["false_reached"] == 11


#: Each pre-registered set of seeds: kept pool -> (the plan's seeds in its order, step-log
#: folder, DroneNavEnv's reference on the same episodes or None, its successes).
_PLANNED_SEEDS = {
    "fresh16_default.jsonl": ([293, 307, 311, 313, 317, 331, 337, 347, 349, 353, 359, 367, 373,
                               379, 383, 389], "fresh16", "fresh16_dronenav_reference.jsonl", 709),
    "fresh24_default.jsonl": ([397, 401, 409, 419, 421, 431, 433, 439, 443, 449, 457, 461, 463,
                               467, 479, 487, 491, 499, 503, 509, 521, 523, 541, 547], "fresh24",
                              None, None),
    "third16_default.jsonl": ([557, 563, 569, 571, 577, 587, 593, 599, 601, 607, 613, 617, 619,
                               631, 641, 643], "third16", "third16_dronenav_reference.jsonl", 698),
    "printed12.jsonl": ([647, 653, 659, 661, 673, 677, 683, 691, 701, 709, 719, 727], "printed12",
                        None, None),
    "printed_climb20.jsonl": ([733, 739, 743, 751, 757, 761, 769, 773, 787, 797, 809, 811, 821,
                               823, 827, 829, 839, 853, 857, 859], "printed_climb20", None, None),
    "twofaced_climb20.jsonl": ([863, 877, 881, 883, 887, 907, 911, 919, 929, 937, 941, 947, 953,
                                967, 971, 977, 983, 991, 997, 1009], "twofaced_climb20", None,
                               None),
}


@pytest.mark.parametrize("kept, globs, episodes, agreed, false_reached, shown", [
    ("fresh16_default.jsonl", ["fresh16_default_s*"], 800, 766, 19, False),
    ("fresh16_with_fresh8_combo.jsonl", ["fresh16_default_s*", "fresh8_combo_cap02_s*"],
     1200, 1150, 31, False),
    ("fresh24_default.jsonl", ["fresh24_default_s*"], 1200, 1152, 32, False),
    ("fresh24_with_fresh16.jsonl", ["fresh16_default_s*", "fresh24_default_s*"],
     2000, 1918, 51, False),  # the plan's headline: not shown (0.9494)
    ("fresh24_with_fresh16_fresh8_combo.jsonl",
     ["fresh16_default_s*", "fresh24_default_s*", "fresh8_combo_cap02_s*"], 2400, 2302, 63, True),
    ("third16_default.jsonl", ["third16_default_s*"], 800, 761, 29, False),
    ("third16_with_fresh40.jsonl",  # the third and last look's headline: not shown
     ["fresh16_default_s*", "fresh24_default_s*", "third16_default_s*"], 2800, 2679, 80, False),
    ("printed12.jsonl", ["printed12_s*"], 600, 579, 13, False),  # a printed board, one look
    # a printed board with --climb-reading nearer: its own question, one look, shown
    ("printed_climb20.jsonl", ["printed_climb20_s*"], 1000, 973, 16, True),
    # the two-faced board with --climb-reading nearer: its own question, one look, shown
    ("twofaced_climb20.jsonl", ["twofaced_climb20_s*"], 1000, 982, 12, True),
])
def test_todays_defaults_fresh_seeds_are_their_kept_flights(kept, globs, episodes, agreed,
                                                           false_reached, shown):
    """docs/tello.rst, "Today's default on sixteen more fresh seeds": the kept flights of
    today's default (look-around and the 0.2 m vertical leg; the sixteen seeds fixed before
    they were flown, and with the eight that chose it) pool to the published figures, as
    one setting, with the agreement target not shown and the false-"reached" one shown; and
    the printed-board question's twelve seeds (blank back, its own single look) likewise."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import sim_to_real

    res = ROOT / "docs" / "_static" / "results" / "tello"
    data = sorted(f for g in globs for f in res.glob(f"{g}_summary.json"))
    settings = [json.loads(f.read_text()) for f in data]
    assert all(d["height_approach"] == 0.2 for d in settings)
    *seeds, pooled = sim_to_real.main(["--from-flights", *map(str, data)])
    published = json.loads((res / kept).read_text().splitlines()[-1])
    assert pooled == published
    assert (pooled["episodes"], pooled["agreed"], pooled["false_reached"]) == (
        episodes, agreed, false_reached)
    assert pooled["targets"]["agreement"] and pooled["targets"]["agreement_shown"] == shown
    # the sixteen seeds of the third look alone do not show it (29 in 800, upper end 0.052)
    assert pooled["targets"]["false_reached_shown"] == (kept != "third16_default.jsonl")
    if kept in _PLANNED_SEEDS:  # the plan's seeds, in its order, every one flown
        seeds, steps, reference, dronenav = _PLANNED_SEEDS[kept]
        assert pooled["seeds"] == seeds
        assert len(list((res / "steps" / steps).glob("*_steps.jsonl.gz"))) == len(seeds)
        if reference is not None:
            # DroneNavEnv's reference on the same episodes: the emulator's side is the kept
            # flights', and the paired counts add up to both sides' successes
            ref = json.loads((res / reference).read_text().splitlines()[-1])
            for key in ("episodes", "agreed", "false_reached", "success_sim"):
                assert ref[key] == pooled[key]
            n, pairs = pooled["episodes"], ref["dronenav_paired"]
            assert pairs["both"] + pairs["emulator_only"] == round(pooled["success_sim"] * n)
            assert pairs["both"] + pairs["dronenav_only"] == round(ref["dronenav"] * n) == dronenav
            assert (ref["paired_difference_ci95"][1] < 0
                    and not ref["targets"]["inside_dronenav_ci"])
    if kept == "third16_with_fresh40.jsonl":  # decided by the 98.33 % interval (three looks)
        from results import wilson

        lo, _ = wilson(pooled["agreed"], pooled["episodes"], z=2.394)
        _, hi = wilson(pooled["false_reached"], pooled["episodes"], z=2.394)
        assert round(lo, 4) == 0.9466 and lo < 0.95  # agreement: not shown, the last look
        assert round(hi, 4) == 0.0371 and hi < 0.05  # false "reached": shown
    if kept == "printed12.jsonl":  # its own question: the blank back only, one look at 95 %
        assert all(d["board_back"] == "blank" for d in settings)
        assert pooled["agreement_ci95"][0] == 0.9471 and pooled["false_reached_ci95"][1] == 0.0367
    if kept == "printed_climb20.jsonl":  # the blank back and the nearer climb reading, one look
        from results import wilson

        assert all(d["board_back"] == "blank" and d["climb_reading"] == "nearer"
                   for d in settings)
        assert pooled["agreement_ci95"][0] == 0.961 and pooled["false_reached_ci95"][1] == 0.0258
        # the 97.5 % interval beside it (the second question asked of the printed board)
        lo, _ = wilson(pooled["agreed"], pooled["episodes"], z=2.2414)
        _, hi = wilson(pooled["false_reached"], pooled["episodes"], z=2.2414)
        assert round(lo, 4) == 0.9589 and lo > 0.95 and round(hi, 4) == 0.0276
    if kept == "twofaced_climb20.jsonl":  # the emulator's own board, the nearer climb reading
        assert all("board_back" not in d and d["climb_reading"] == "nearer" for d in settings)
        assert pooled["agreement_ci95"][0] == 0.9717 and pooled["false_reached_ci95"][1] == 0.0209


def test_sim_to_real_compares_two_settings_flown_on_the_same_seeds(tmp_path, capsys):
    """--from-flights A --against B: the look-around against the default on the twelve
    fresh seeds, episode by episode, gives docs/tello.rst's figures (look_around.json); the
    setting that differs is named; --plot draws both per seed; flights of other seeds,
    --against or --plot alone and a plot that is not a PNG are refused."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import sim_to_real

    res = ROOT / "docs" / "_static" / "results" / "tello"
    variant = sorted(res.glob("look_around_s*_summary.json"))
    baseline = sorted(res.glob("fresh30_default_s*_summary.json"))
    assert len(variant) == len(baseline) == 12
    figs = sim_to_real.main(["--from-flights", *map(str, variant),
                             "--against", *map(str, baseline)])
    got = figs[-1]
    assert got["figure"] == "sim_to_real_against" and got["episodes"] == 600
    assert set(got["differ"]) == {"look_around", "look_around_radius"}
    assert got["differ"]["look_around"] == [12.0, None]
    kept = json.loads((res / "look_around.json").read_text())
    for arm, tag in (("variant", "variant"), ("baseline", "default")):
        for key, name in (("success", "success"), ("agreed", "agreement"),
                          ("false_reached", "false_reached"), ("missed_reach", "missed")):
            assert got[arm][key] == sum(kept[g][f"{name}_{tag}"]
                                        for g in ("decision", "confirmation"))
    assert (got["variant"]["agreed"], got["baseline"]["agreed"]) == (577, 562)
    # the paired counts add up to the arms' difference, and the interval holds the estimate
    sp = got["success_paired"]
    assert sp["variant_only"] - sp["baseline_only"] == (got["variant"]["success"]
                                                        - got["baseline"]["success"])
    assert sp["ci95"][0] < sp["difference"] < sp["ci95"][1]
    assert sum(r["variant"]["agreed"] for r in got["per_seed"]) == 577
    # the decision seeds alone: look_around.json's decision figures
    dec = [f for f in variant if any(f"_s{x}_" in f.name for x in kept["decision"]["seeds"])]
    base = [f for f in baseline if any(f"_s{x}_" in f.name for x in kept["decision"]["seeds"])]
    one = sim_to_real.main(["--from-flights", *map(str, dec), "--against", *map(str, base)])[-1]
    assert (one["success_paired"]["variant_only"],
            one["success_paired"]["baseline_only"]) == (kept["decision"]["b10"],
                                                         kept["decision"]["b01"])
    assert [one["success_paired"]["difference"], *one["success_paired"]["ci95"]] == \
        pytest.approx(kept["decision"]["success_diff_ci"], abs=1e-3)
    # --plot draws both arms per seed
    png = tmp_path / "per_seed.png"
    sim_to_real.main(["--from-flights", *map(str, dec), "--against", *map(str, base),
                      "--plot", str(png)])
    import matplotlib.image

    img = matplotlib.image.imread(png)
    assert img.shape[0] > 300 and img.shape[1] > 1000
    capsys.readouterr()
    for argv, message in (
            (["--from-flights", *map(str, variant), "--against", *map(str, baseline[:6])],
             "must be the same seeds"),
            (["--against", str(baseline[0])], "give them with --from-flights"),
            (["--plot", str(png)], "give them with --from-flights"),
            (["--from-flights", str(variant[0]), "--plot", str(tmp_path / "x.pdf")],
             "--plot writes a PNG")):
        with pytest.raises(SystemExit) as exit_:
            sim_to_real.main(argv)
        assert exit_.value.code == 2
        assert message in capsys.readouterr().err


def test_sim_to_real_flies_dronenavs_reference_for_flights_already_flown(tmp_path, capsys):
    """--from-flights --compare-sim: DroneNavEnv's reference for a committed flight that
    flew without one (seed 89), on its own layouts and noise draws, paired with its episode
    table; a seed that has one keeps it; an episode table of another length and
    --compare-sim without --from-flights are refused."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import sim_to_real

    kept = ROOT / "docs" / "_static" / "results" / "tello"
    s89 = kept / "mirror_defaults_s89_summary.json"
    assert "dronenav" not in json.loads(s89.read_text())
    figs = sim_to_real.main(["--from-flights", str(s89), "--compare-sim",
                             "--out", str(tmp_path / "out")])
    seed, pooled = figs
    table = pd.read_csv(kept / "mirror_defaults_s89_episodes.csv")
    pairs = seed["dronenav_paired"]
    assert sum(pairs[k] for k in ("both", "emulator_only", "dronenav_only", "neither")) == 50
    assert pairs["both"] + pairs["emulator_only"] == table["success_sim"].sum()
    assert seed["dronenav"] == (pairs["both"] + pairs["dronenav_only"]) / 50 == 0.84
    assert seed["dronenav_perception"] == "sim"
    assert pooled["paired_difference"] == pytest.approx(
        (pairs["emulator_only"] - pairs["dronenav_only"]) / 50, abs=1e-4)
    lo, hi = pooled["paired_difference_ci95"]
    assert lo < pooled["paired_difference"] < hi < 0  # the emulator on RGB arrives less often
    assert pooled["targets"]["inside_dronenav_ci"] is False
    # the kept reference of all twenty seeds (docs/tello.rst): seed 89 as flown here, and
    # its pooled pairs are the per-episode lists against the committed episode tables
    ref = json.loads((kept / "dronenav_reference_s79_s179.json").read_text())
    per = ref["dronenav_success_per_episode"]
    assert len(per) == 20 and len(per["89"]) == 50
    both = em_only = dn_only = 0
    for s, dn in per.items():
        sim = pd.read_csv(kept / f"mirror_defaults_s{s}_episodes.csv")["success_sim"].tolist()
        both += sum(a and b for a, b in zip(sim, dn))
        em_only += sum(a and not b for a, b in zip(sim, dn))
        dn_only += sum(b and not a for a, b in zip(sim, dn))
    assert (both, em_only, dn_only) == (567, 63, 291)
    assert ref["pooled"]["dronenav_paired"]["both"] == 567 and ref["pooled"]["dronenav"] == 0.858
    assert sum(per["89"]) == pairs["both"] + pairs["dronenav_only"]
    # the kept reference with the same RGB models: its pairs, recomputed, and the emulator
    # above it (docs/tello.rst: the Tello path is not behind the simulator)
    rgb = json.loads((kept / "dronenav_rgb_reference_s79_s179.json").read_text())
    counts = {"both": 0, "emulator_only": 0, "dronenav_only": 0, "neither": 0}
    for s, dn in rgb["dronenav_rgb_success_per_episode"].items():
        sim = pd.read_csv(kept / f"mirror_defaults_s{s}_episodes.csv")["success_sim"].tolist()
        for a_, b_ in zip(sim, dn):
            counts[("both" if b_ else "emulator_only") if a_ else
                   ("dronenav_only" if b_ else "neither")] += 1
    assert counts == rgb["pooled"]["dronenav_paired"] == {
        "both": 419, "emulator_only": 211, "dronenav_only": 114, "neither": 256}
    assert rgb["pooled"]["paired_difference_ci95"][0] > 0
    # a flight that has its reference keeps it (nothing flown): seed 79's 0.84
    s79 = kept / "mirror_defaults_s79_summary.json"
    kept79 = json.loads(s79.read_text())["dronenav"]
    one = sim_to_real.main(["--from-flights", str(s79), "--compare-sim"])[0]
    assert one["dronenav"] == kept79["rate"] and one["dronenav_paired"] == kept79["paired"]
    capsys.readouterr()
    (tmp_path / "f").mkdir()
    (tmp_path / "f" / "summary.json").write_text(s89.read_text())
    table.head(10).to_csv(tmp_path / "f" / "episodes.csv", index=False)
    # a flight of candidate MonoDepth weights: its RGB reference flies them, so they must exist
    (tmp_path / "g").mkdir()
    (tmp_path / "g" / "summary.json").write_text(json.dumps(
        {**json.loads(s89.read_text()), "depth_weights": str(tmp_path / "gone.pt")}))
    table.to_csv(tmp_path / "g" / "episodes.csv", index=False)
    for argv, message in (
            (["--from-flights", str(tmp_path / "f"), "--compare-sim"], "has 10 episodes, its "
                                                                       "summary 50"),
            (["--from-flights", str(tmp_path / "g"), "--compare-sim", "--compare-perception",
              "rgb"], "gone.pt"),
            (["--compare-sim"], "--compare-sim is for --from-flights")):
        with pytest.raises(SystemExit) as exit_:
            sim_to_real.main(argv)
        assert exit_.value.code == 2
        assert message in capsys.readouterr().err


@pytest.mark.parametrize("argv, expected, fresh", [([], "estimated", True),
                                                   (["--map", "exact"], "exact", False),
                                                   (["--fresh-hits", "off"], "estimated", False)])
def test_map_option_builds_the_generalists_egomap(tmp_path, monkeypatch, capsys, argv, expected,
                                                  fresh):
    """--map: the generalist's EgoMap trusts every depth reading (exact) or treats the
    depth as an estimate (median column reading, log-odds cells: auto's choice on
    MonoDepth's depth); --fresh-hits (auto: on with the estimated map) adds what the current
    frame reads (EgoMap fresh_hits)."""
    from torchrl_causal.transforms import EgoMap

    assert fly_tello.parse_args(argv).map == expected
    assert fly_tello.parse_args(["--perception", "sim"]).map == "exact"  # the simulator's depth
    assert fly_tello.parse_args(["--perception", "sim-depth"]).map == "exact"
    assert fly_tello.parse_args(["--perception", "sim-detector"]).map == "estimated"
    with pytest.raises(SystemExit):
        fly_tello.parse_args(["--map", "guess"])
    assert "--map: invalid choice: 'guess'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        fly_tello.parse_args(["--perception", "sim", "--fresh-hits"])
    assert "--fresh-hits" in capsys.readouterr().err
    assert fly_tello.parse_args(["--perception", "sim"]).fresh_hits is False  # auto, exact map
    assert fly_tello.parse_args(["--fresh-hits", "on"]).fresh_hits is True
    with pytest.raises(SystemExit):
        fly_tello.parse_args(["--fresh-hits", "maybe"])
    assert "--fresh-hits: invalid choice: 'maybe'" in capsys.readouterr().err
    seen = []
    fly = fly_tello.fly

    def spy(args, policy, tenv, base, emu=None):
        seen.extend((t.depth, t.fresh_hits) for t in tenv.transform if isinstance(t, EgoMap))
        return fly(args, policy, tenv, base, emu)

    monkeypatch.setattr(fly_tello, "fly", spy)
    summary = fly_tello.main(["--episodes", "1", "--max-steps", "4", *argv,
                              "--out", str(tmp_path), "--no-video", "--seed", "3"])
    assert seen == [(expected, fresh)] and summary["map"] == expected
    assert summary.get("fresh_hits", False) is fresh
    assert (tmp_path / "episodes.csv").is_file()


def test_compare_sim_on_rgb_builds_the_flights_egomap(tmp_path, monkeypatch):
    """--compare-sim with --compare-perception rgb: DroneNavEnv's reference builds the same
    EgoMap options as the flight (ego_map_options: --map, --fresh-hits) and reads depth
    with the flight's MonoDepth (--depth-weights)."""
    from torchrl_causal import training
    from torchrl_causal.perception.depth import FCRN, MonoDepth
    from torchrl_causal.transforms import EgoMap, EstimatedDepth

    args = fly_tello.parse_args(["--fresh-hits"])
    assert fly_tello.ego_map_options(args) == {"depth": "estimated", "fresh_hits": True}
    assert fly_tello.ego_map_options(fly_tello.parse_args(["--map", "exact"])) == {
        "depth": "exact"}
    seen, widths = [], []
    evaluate = training.evaluate

    def spy(policy, env, *a, **kw):
        seen.extend((t.depth, t.fresh_hits) for t in env.transform if isinstance(t, EgoMap))
        widths.extend(tuple(t.estimator.net.config["widths"]) for t in env.transform
                      if isinstance(t, EstimatedDepth))
        return evaluate(policy, env, *a, **kw)

    monkeypatch.setattr(training, "evaluate", spy)
    summary = fly_tello.main(["--episodes", "1", "--max-steps", "3", "--fresh-hits",
                              "--compare-sim", "1", "--compare-perception", "rgb",
                              "--out", str(tmp_path), "--no-video", "--seed", "3"])
    assert seen == [("estimated", True)]
    assert widths == [tuple(MonoDepth.load().net.config["widths"])]  # the shipped one
    assert summary["dronenav"]["perception"] == "rgb"
    small = tmp_path / "depth.pt"  # other weights: the reference flies them too
    MonoDepth(FCRN(widths=(8, 8, 8, 8, 8), decoder=(8, 8, 8, 8))).save(small)
    widths.clear()
    fly_tello.dronenav_reference(fly_tello.parse_args(
        ["--episodes", "1", "--max-steps", "3", "--compare-sim", "1", "--compare-perception",
         "rgb", "--depth-weights", str(small), "--seed", "3"]))
    assert widths == [(8, 8, 8, 8, 8)]


def test_sim_to_real_benchmark_passes_the_map_option_to_each_flight(tmp_path, monkeypatch,
                                                                    capsys):
    """--map reaches fly_tello.py for every seed; a value fly_tello does not take is named."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import sim_to_real

    calls = []

    def fake_main(argv):
        calls.append(argv)
        return {"success_sim": {"rate": 0.5, "n": 2, "ci95": [0.1, 0.9]}, "agreement": 1.0,
                "false_reached": 0, "missed_reach": 0, "crashes": 1,
                "dronenav": {"rate": 0.5, "ci95": [0.1, 0.9]}, "map": argv[argv.index("--map") + 1]}

    monkeypatch.setattr(sim_to_real.fly_tello, "main", fake_main)
    figs = sim_to_real.main(["--policies", "generalist", "--seeds", "1", "2", "--episodes", "2",
                             "--out", str(tmp_path), "--map", "estimated"])
    assert [c[c.index("--map") + 1] for c in calls] == ["estimated", "estimated"]
    assert [f.get("map") for f in figs] == ["estimated", "estimated", None]
    assert not any("--fresh-hits" in c for c in calls)  # fly_tello's auto
    calls.clear()
    sim_to_real.main(["--policies", "generalist", "--seeds", "1", "--episodes", "2",
                      "--out", str(tmp_path), "--map", "estimated", "--fresh-hits"])
    assert len(calls) == 1 and calls[0][calls[0].index("--fresh-hits") + 1] == "on"
    calls.clear()
    sim_to_real.main(["--policies", "generalist", "--seeds", "1", "--episodes", "2",
                      "--out", str(tmp_path), "--map", "estimated", "--fresh-hits", "off"])
    assert calls[0][calls[0].index("--fresh-hits") + 1] == "off"
    with pytest.raises(SystemExit):
        sim_to_real.main(["--map", "auto"])
    assert "--map: invalid choice: 'auto'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        sim_to_real.main(["--fresh-hits", "--map", "exact"])
    assert "--fresh-hits needs the estimated map, got --map exact" in capsys.readouterr().err
    calls.clear()  # --goal-size reaches the generalist's flights, not the thesis scene's
    sim_to_real.main(["--policies", "thesis", "generalist", "--seeds", "1", "--episodes", "2",
                      "--out", str(tmp_path), "--map", "estimated", "--goal-size", "1.0", "0.8"])
    assert "--goal-size" not in calls[0]
    assert calls[1][calls[1].index("--goal-size"):][:3] == ["--goal-size", "1.0", "0.8"]
    calls.clear()  # the arrival options reach the generalist's flights only
    sim_to_real.main(["--policies", "thesis", "generalist", "--seeds", "1", "--episodes", "2",
                      "--out", str(tmp_path), "--map", "estimated", "--mirror-check", "0.1",
                      "--height-margin", "0.07"])
    assert "--mirror-check" not in calls[0] and "--height-margin" not in calls[0]
    assert calls[1][calls[1].index("--mirror-check") + 1] == "0.1"
    assert calls[1][calls[1].index("--height-margin") + 1] == "0.07"
    for flag, bad in (("--mirror-check", "2"), ("--height-margin", "-1")):
        with pytest.raises(SystemExit):
            sim_to_real.main([flag, bad])
        assert f"{flag} must be a distance in" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        sim_to_real.main(["--goal-size", "9", "9"])
    assert "--goal-size" in capsys.readouterr().err


def test_layout_fence_is_each_emulated_layouts_arena_from_its_turned_start():
    """fly_tello gives TelloEnv each emulated layout's arena with the start pose in it
    (``Layout.fence``; before, the first layout's fence and none at all for a turned start):
    the env refuses exactly the moves that leave that layout's arena, and EgoMap's
    ``geofence='env'`` over it holds the fence it holds over the DroneNavEnv of that layout."""
    import math

    import numpy as np
    from torchrl.envs import TransformedEnv

    from torchrl_causal.envs import DroneNavEnv, TelloEnv
    from torchrl_causal.perception.goal import SimGoalDetector
    from torchrl_causal.transforms import EgoMap

    class NoGoal(SimGoalDetector):
        def detect(self, pixels, depth=None, **_):
            return torch.zeros(len(pixels), 0, 4), torch.zeros(len(pixels), 0)

    sim = TransformedEnv(DroneNavEnv(layout="random", split="heldout", seed=7),
                         EgoMap(geofence="env"))
    tello = TelloEnv(dry_run=True, verbose=False, detector=NoGoal(),
                     depth_estimator=lambda p: torch.full(p.shape[:3], 5.0))
    real = TransformedEnv(tello, EgoMap(geofence="env"))
    rng = np.random.default_rng(0)
    turned = 0
    for _ in range(4):
        sim.reset()
        lay = sim.base_env.layout
        fence, origin, ceiling = lay.fence()
        tello.set_geofence(fence, origin=origin, max_height=ceiling)
        real.reset()
        assert torch.allclose(real.transform._state["fence"], sim.transform._state["fence"])
        turned += abs(lay.start_yaw_deg) > 1.0
        x0, y0, _ = lay.start_pos
        yaw = math.radians(lay.start_yaw_deg)
        xa, ya, xb, yb = lay.arena
        for p in rng.uniform(-8.0, 8.0, size=(200, 2)):  # points of the take-off frame
            wx = x0 + math.cos(yaw) * p[0] - math.sin(yaw) * p[1]
            wy = y0 + math.sin(yaw) * p[0] + math.cos(yaw) * p[1]
            assert tello._inside((p[0], p[1], 1.0, 0.0)) == (xa <= wx <= xb and ya <= wy <= yb)
        assert not tello._inside((0.0, 0.0, ceiling + 0.05, 0.0))
    assert turned >= 2  # held-out layouts start turned: the case that had no fence
    real.close()
    sim.close()
    with pytest.raises(ValueError, match="geofence_origin"):
        tello.set_geofence((-1.0, -1.0, 1.0, 1.0), origin=(0.0, 0.0))
    with pytest.raises(ValueError, match="take-off point"):
        tello.set_geofence((-1.0, -1.0, 1.0, 1.0), origin=(2.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="max_height"):
        tello.set_geofence((-1.0, -1.0, 1.0, 1.0), max_height=-1.0)


def test_the_blank_back_flights_are_their_kept_figures():
    """docs/tello.rst, "The blank back, paired": the four seeds flown with a blank-backed
    board against the same seeds' heliport-back flights, episode by episode, give the kept
    figures; only the board's back differs between the two settings."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import sim_to_real

    res = ROOT / "docs" / "_static" / "results" / "tello"
    blank = sorted(res.glob("third16_blank_s*_summary.json"))
    heliport = [res / f.name.replace("third16_blank", "third16_default") for f in blank]
    assert len(blank) == 4 and all(f.is_file() for f in heliport)
    got = sim_to_real.main(["--from-flights", *map(str, blank),
                            "--against", *map(str, heliport)])[-1]
    assert got == json.loads((res / "third16_blank.jsonl").read_text().splitlines()[-1])
    assert got["seeds"] == [557, 563, 569, 571] and got["episodes"] == 200
    assert got["differ"] == {"board_back": ["blank", None]}
    assert (got["variant"]["agreed"], got["baseline"]["agreed"]) == (196, 189)
    assert (got["variant"]["false_reached"], got["baseline"]["false_reached"]) == (3, 9)
    ap = got["agreement_paired"]
    assert ap["variant_only"] - ap["baseline_only"] == 196 - 189 and ap["ci95"][0] > 0
