"""benchmarks/arrival_mirror.py: the shipped in-view head read once and on frame + mirror."""

import json

import pytest

from tests._scripts import load_script

mirror = load_script("benchmarks/arrival_mirror.py", "arrival_mirror")


def test_readings_on_rendered_test_frames(capsys):
    """On 24 rendered held-out frames: one JSON object per reading, the mirrored mean's
    errors the same for every check, and a tighter check never fires more often."""
    mirror.main(["--test", "24", "--checks", "0.05", "0.5"])
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["reading"] for r in rows] == ["once", "mirror_mean", "mirror_check",
                                            "mirror_check"]
    assert all(r["figure"] == "arrival_mirror" and r["n"] == 24 for r in rows)
    assert rows[1]["mae_lateral_m"] == rows[2]["mae_lateral_m"] == rows[3]["mae_lateral_m"]
    for t in range(5):  # fires: 0.05 check <= 0.5 check <= no check
        a, b, c = (rows[i]["rule"][t] for i in (2, 3, 1))
        assert a["fire_inside"] <= b["fire_inside"] <= c["fire_inside"]
        assert a["fire_outside"] <= b["fire_outside"] <= c["fire_outside"]
    assert rows[2]["fire_near_miss"] <= rows[1]["fire_near_miss"]


@pytest.mark.parametrize("argv, message", [
    (["--checks", "-1"], "--checks must be distances in [0, 1] m, got -1"),
    (["--data", "missing.npz"], "--data missing.npz: no such file"),
    (["--test", "0"], "--test must be >= 1, got 0"),
])
def test_bad_options_are_named(argv, message, capsys):
    with pytest.raises(SystemExit):
        mirror.main(argv)
    assert message in capsys.readouterr().err
