"""benchmarks/reach_calibration.py: the pose sweep behind the arrival rule's range threshold."""

import pytest

from tests._scripts import load_script

bench = load_script("benchmarks/reach_calibration.py")


def test_thresholds_count_where_the_rule_would_fire():
    from torchrl_causal.envs.reach import _threshold_table

    rows = [{"to_goal_point_m": 0.1, "in_sight": True, "measured_m": 0.30},
            {"to_goal_point_m": 0.15, "in_sight": True, "measured_m": 0.42},
            {"to_goal_point_m": 0.4, "in_sight": True, "measured_m": 0.40},
            {"to_goal_point_m": 0.6, "in_sight": True, "measured_m": 0.70},
            {"to_goal_point_m": 0.1, "in_sight": False, "measured_m": 0.0}]  # not seen: left out
    table = _threshold_table(rows, [0.35, 0.41, 0.45])
    t = {r["threshold_m"]: r for r in table["thresholds"]}
    assert (t[0.35]["fire_inside"], t[0.35]["fire_outside"]) == (0.5, 0.0)
    assert (t[0.41]["fire_inside"], t[0.41]["fire_outside"]) == (0.5, 0.5)
    assert (t[0.45]["fire_inside"], t[0.45]["fire_outside"], t[0.45]["youden"]) == (1.0, 0.5, 0.5)
    assert table["n_inside"] == 2 and table["n_outside"] == 2
    # the best: the largest Youden's J, ties to the smaller threshold
    assert table["max_distance"] == 0.35 and table["youden"] == 0.5


def test_sweep_runs_the_rgb_stack_at_the_thesis_board(capsys):
    rows = bench.main(["--poses", "10", "--seed", "1"])
    best = rows[-1]
    assert best["figure"] == "best" and 0.28 <= best["threshold_m"] <= 0.51
    # the sweep's poses are real renders near the board: it is in sight in most of them
    assert 5 <= best["n_inside"] + best["n_outside"] <= 10
    assert all(0.0 <= r["fire_inside"] <= 1.0 for r in rows)
    assert best["stored_max_distance"] is None or 0.28 <= best["stored_max_distance"] <= 0.51
    printed = capsys.readouterr().out.strip().splitlines()
    assert len(printed) == len(rows)  # one JSON object per figure, nothing else


@pytest.mark.parametrize("argv,message", [(["--poses", "9"], "--poses"),
                                          (["--depth-weights", "/nowhere.pt"], "no such file")])
def test_bad_options(argv, message, capsys):
    with pytest.raises(SystemExit):
        bench.main(argv)
    assert message in capsys.readouterr().err
