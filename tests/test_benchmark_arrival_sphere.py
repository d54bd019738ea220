"""benchmarks/arrival_sphere.py: frames inside the goal sphere through the real camera path,
detector, MonoDepth and arrival head."""

import pytest

from tests._scripts import load_script

sphere = load_script("benchmarks/arrival_sphere.py", "arrival_sphere")


def test_frames_inside_the_sphere_are_seen_and_read_near_the_truth(capsys):
    fig = sphere.main(4)
    assert fig["frames"] == 4 and 0 <= fig["head_asked"] <= fig["in_sight"] <= 4
    # facing the board inside the sphere, the shipped models see it and the head reads
    # the distance from the goal point within centimetres (0.024 m median over 120 frames)
    assert fig["in_sight"] >= 3 and fig["distance_err_median_m"] < 0.1
    assert capsys.readouterr().out.count("\n") == 1  # one JSON line on stdout


def test_bad_frame_count_is_named():
    with pytest.raises(ValueError, match="n must be an int >= 1, got 0"):
        sphere.main(0)
