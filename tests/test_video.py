"""Videos of evaluated episodes (``record_episodes``) and ``recipes/watch.py``.

Real components throughout: the shipped ``thesis`` policy flies the thesis
scene, PyAV decodes what was written. The policy reads 84 x 84 images (its
``policy.json``), so its env keeps ``image_size=84``; the env-only checks use
smaller images.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import av
import numpy as np
import pytest

from torchrl_causal.envs import DroneNavEnv, make_gridnav_env
from torchrl_causal.pretrained import available, load_policy
from torchrl_causal.training import OUTCOME_LABELS, record_episodes
from torchrl_causal.training.flightmap import OUTCOME_COLOURS

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))

import watch  # noqa: E402

END = 3  # end_frames used below


def _decode(path):
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        codec = stream.codec_context.name
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    return codec, frames


@pytest.fixture(scope="module")
def thesis_video(tmp_path_factory):
    policy, env = load_policy("thesis", base_env=DroneNavEnv(seed=0))
    path = tmp_path_factory.mktemp("video") / "sub" / "flight.mp4"
    out = record_episodes(policy, env, 2, 0, path, end_frames=END)
    return out, path


def test_mp4_is_h264_with_onboard_beside_chase_view(thesis_video):
    out, path = thesis_video
    assert out["video"] == path and path.is_file()
    assert not list(path.parent.glob(".*part*"))  # the temporary file was renamed
    eps = out["episodes"]
    assert [(e["success"], e["steps"]) for e in eps] == [(True, 13), (True, 13)]
    assert out["success_rate"] == 1.0 and out["oracle_steps"] == 12.0
    codec, frames = _decode(path)
    assert codec == "h264"
    h, w = frames[0].shape[:2]
    # the onboard 84 x 84 image upscaled to the chase view's 240 rows, the chase view 320 wide
    assert (h, w) == out["frame_size"] == (240, 240 + 320)
    # per episode: its first view, one frame per step, END frames under the outcome banner
    expected = sum(e["steps"] for e in eps) + len(eps) * (1 + END)
    assert len(frames) == out["frames"] == expected


def test_overlay_is_drawn(thesis_video):
    _, path = thesis_video
    _, frames = _decode(path)
    chase = frames[0][:, 240:].astype(int)
    # the text block (top left of the chase view): light letters on a darkened strip
    text = chase[10:60, 10:150]
    assert text.max() > 200 and text.min() < 60 and text.std() > 30
    # the episode's last step (frame 13) and the same view held under the banner (frame 14):
    # equal above the banner, the banner in the "reached" colour below
    last, held = frames[13].astype(int), frames[14].astype(int)
    assert np.abs(last[:150] - held[:150]).mean() < 3
    banner = held[-40:-16, 240:260].reshape(-1, 3).mean(0)
    green = np.array([int(OUTCOME_COLOURS["reached"][i:i + 2], 16) for i in (1, 3, 5)])
    assert np.abs(banner - green).max() < 25, banner
    assert np.abs(last[-40:-16, 240:] - held[-40:-16, 240:]).mean() > 30
    assert OUTCOME_LABELS["reached"] == "REACHED"


def test_record_episodes_bad_input(tmp_path):
    env = DroneNavEnv(image_size=32, seed=0)
    policy = lambda td: td.set("action", env.action_spec.rand())  # noqa: E731
    with pytest.raises(ValueError, match="DroneNavEnv"):
        record_episodes(policy, make_gridnav_env(), 1, 0, tmp_path / "a.mp4")
    with pytest.raises(ValueError, match="episodes must be an int >= 1"):
        record_episodes(policy, env, 0, 0, tmp_path / "a.mp4")
    blocker = tmp_path / "file.txt"
    blocker.write_text("a file, not a folder")
    with pytest.raises(ValueError, match="cannot create the folder of path"):
        record_episodes(policy, env, 1, 0, blocker / "sub" / "a.mp4")
    with pytest.raises(ValueError, match=r"\.mp4"):
        record_episodes(policy, env, 1, 0, tmp_path / "a.avi")
    with pytest.raises(ValueError, match="chase_size"):
        record_episodes(policy, env, 1, 0, tmp_path / "a.mp4", chase_size=(120, 160))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt"]  # nothing was flown


def _refused(argv, capsys) -> str:
    with pytest.raises(SystemExit) as err:
        watch.main(argv)
    assert err.value.code == 2
    return capsys.readouterr().err


def test_watch_refuses_bad_input_before_flying(tmp_path, capsys):
    out = tmp_path / "out"
    msg = _refused(["--policy", "nosuchpolicy", "--out", str(out)], capsys)
    assert "--policy" in msg and "nosuchpolicy" in msg
    for name in available():
        assert name in msg
    run = tmp_path / "run"
    run.mkdir()
    (run / "policy.json").write_text("{}")
    msg = _refused(["--policy", str(run), "--out", str(out)], capsys)
    assert "--policy" in msg and "model.pt" in msg and "explorer.pt" in msg
    held = tmp_path / "held"
    held.mkdir()
    (held / "notes.txt").write_text("mine")
    msg = _refused(["--policy", "thesis", "--out", str(held)], capsys)
    assert "--out" in msg and "notes.txt" in msg and "--overwrite" in msg
    msg = _refused(["--policy", "thesis", "--episodes", "0", "--out", str(out)], capsys)
    assert "--episodes" in msg
    assert not out.exists() and sorted(p.name for p in held.iterdir()) == ["notes.txt"]
    # --overwrite lets a folder that holds files through the checks
    assert watch.parse_args(["--policy", "thesis", "--out", str(held), "--overwrite"]).overwrite


def test_watch_end_to_end(tmp_path, capsys):
    out = tmp_path / "watch"
    summary = watch.main(["--policy", "thesis", "--layout", "thesis", "--episodes", "1",
                          "--out", str(out)])
    assert sorted(p.name for p in out.iterdir()) == sorted(watch.OUT_FILES)
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed == summary
    assert summary["success_rate"] == 1.0 and summary["frames"] == 13 + 1 + 4
    rows = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert len(rows) == 1
    row = rows[0]
    assert (row["success"], row["outcome"], row["steps"], row["oracle_steps"]) == \
        (True, "reached", 13, 12)
    assert row["spl"] == pytest.approx(12 / 13)
    codec, frames = _decode(out / "flight.mp4")
    assert codec == "h264" and len(frames) == summary["frames"]
    assert (out / "flight_maps.png").stat().st_size > 10_000


def test_episode_cut_by_max_steps_ends_as_timeout(tmp_path):
    from torchrl_causal.envs import OraclePolicy

    env = DroneNavEnv(image_size=32, seed=0)
    out = record_episodes(OraclePolicy(env), env, 1, 0, tmp_path / "cut.mp4", max_steps=3,
                          end_frames=END, spl=False)
    assert out["episodes"][0]["steps"] == 3 and not out["episodes"][0]["success"]
    _, frames = _decode(tmp_path / "cut.mp4")
    assert len(frames) == out["frames"] == 3 + 1 + END
    # the onboard 32 x 32 image is upscaled to 240 rows: 240 columns
    assert out["frame_size"] == (240, 240 + 320)
    banner = frames[-1][-40:-16, 240:260].reshape(-1, 3).astype(int).mean(0)
    orange = np.array([int(OUTCOME_COLOURS["timeout"][i:i + 2], 16) for i in (1, 3, 5)])
    assert np.abs(banner - orange).max() < 25, banner
