"""The generalist recipe (teacher phase + DQN phase across layouts): config, bad input, a tiny
end-to-end run with its outputs (imitation.csv, policy.json, flight maps) and the resume that
skips a finished teacher phase."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))

import recipe_utils as ru  # noqa: E402
import train  # noqa: E402


def _cfg(overrides=(), name="generalist"):
    with initialize_config_dir(config_dir=train.CONFIG_DIR, version_base=None):
        return compose(config_name=name, overrides=list(overrides))


def test_generalist_config_trains_across_layouts_and_selects_on_val(tmp_path):
    cfg = _cfg([f"output_dir={tmp_path}"])
    ru.validate_config(cfg, tmp_path)
    assert cfg.env.layout == "train" and ru.selection_scene(cfg) == "val"
    assert cfg.teacher.rounds > 0 and "heldout" in cfg.env.eval_layouts
    spec = train.policy_spec(cfg, ru.VARIANTS[cfg.variant])
    assert spec.actor_keys == ["policy_features"] and spec.history == 4 and not spec.image
    assert spec.shield and spec.uses_ego_map and cfg.teacher.clearance > 0


@pytest.mark.parametrize("override, needle", [
    ("teacher.rounds=-1", "teacher.rounds=-1"),
    ("teacher.beta_decay=2", "teacher.beta_decay=2"),
    ("teacher.planner_weight=0.5", "teacher.planner_weight=0.5"),
    ("teacher.clearance=3", "teacher.clearance=3"),
    ("teacher.actions=[fly]", "teacher.actions"),
    ("env.num_envs=2", "env.num_envs=2"),
    ("features.history=0", "features.inputs"),
    ("features.frames=1", "features.frames=1"),
    ("features.inputs=[speed]", "features.inputs"),
    ("eval.select_layout=heldout", "held-out"),
    ("features.inputs=[causal_features]", "features.shield"),
])
def test_bad_teacher_and_feature_options_are_named_before_training(override, needle, tmp_path):
    cfg = _cfg([f"output_dir={tmp_path}", override, "collector.frames_per_batch=2"]
               if override == "env.num_envs=2" else [f"output_dir={tmp_path}", override])
    with pytest.raises(ValueError, match=needle.replace("[", r"\[")):
        ru.validate_config(cfg, tmp_path)


def test_loop_guard_needs_four_actions_of_history(tmp_path):
    cfg = _cfg([f"output_dir={tmp_path}", "features.loop_guard=true", "features.history=2"])
    with pytest.raises(ValueError, match="features.loop_guard"):
        ru.validate_config(cfg, tmp_path)
    from torchrl_causal.pretrained import PolicySpec

    with pytest.raises(ValueError, match="history >= 4"):
        PolicySpec(inputs=["causal_features", "action_history"], history=2, loop_guard=True)


@pytest.mark.parametrize("value", ["-1.0", "true", "nan"])
def test_goal_search_is_a_distance_and_needs_an_ego_map_input(tmp_path, value):
    cfg = _cfg([f"output_dir={tmp_path}", f"features.goal_search={value}"])
    with pytest.raises(ValueError, match="features.goal_search"):
        ru.validate_config(cfg, tmp_path)


def test_goal_search_in_the_config_builds_a_searching_policy(tmp_path):
    cfg = _cfg([f"output_dir={tmp_path}", "features.goal_search=4.0"])
    ru.validate_config(cfg, tmp_path)  # the generalist's inputs include goal_memory
    spec = train.policy_spec(cfg, ru.VARIANTS[cfg.variant])
    assert spec.goal_search == 4.0
    from torchrl_causal.pretrained.policy import policy_guards

    assert [type(m).__name__ for m in policy_guards(spec)] == ["GoalSearch"]


def test_revisit_guard_in_the_config_builds_a_guarded_policy_and_needs_a_map(tmp_path):
    cfg = _cfg([f"output_dir={tmp_path}", "features.revisit_guard=true",
                "features.loop_guard=true"])
    ru.validate_config(cfg, tmp_path)
    spec = train.policy_spec(cfg, ru.VARIANTS[cfg.variant])
    from torchrl_causal.pretrained.policy import policy_guards

    assert spec.revisit_guard
    assert [type(m).__name__ for m in policy_guards(spec)] == ["LoopGuard", "RevisitGuard"]
    bad = _cfg([f"output_dir={tmp_path}", "features.revisit_guard=true",
                "features.inputs=[causal_features,action_history]", "features.shield=false"])
    with pytest.raises(ValueError, match="features.revisit_guard"):
        ru.validate_config(bad, tmp_path)
    with pytest.raises(ValueError, match="features.revisit_guard"):
        ru.validate_config(_cfg([f"output_dir={tmp_path}", "features.revisit_guard=3"]),
                           tmp_path)


def test_ego_map_input_needs_the_image_off(tmp_path):
    cfg = _cfg([f"output_dir={tmp_path}", "features.inputs=[ego_map,causal_features,action_history]",
                "features.image=true"])
    with pytest.raises(ValueError, match="features.image=True"):
        ru.validate_config(cfg, tmp_path)


def test_tiny_generalist_run_writes_its_outputs_and_resume_skips_the_teacher(tmp_path,
                                                                            monkeypatch):
    args = [f"output_dir={tmp_path}", "teacher.rounds=1", "teacher.episodes_per_round=2",
            "teacher.max_expansions=4000", "collector.total_frames=120",
            "loss.learning_starts=60", "loss.target_update_interval=10",
            "eval.interval_frames=60", "eval.episodes=1", "eval.final_episodes=2",
            "env.image_size=48", "env.max_steps=40", "progress=false", "threads=1",
            "logger.backend=none", "outputs.draw_cbns=false", "checkpoint.interval_frames=60",
            "outputs.videos=1", "features.loop_guard=true"]
    # first session: the teacher phase, then stopped (as if killed) at the first checkpoint
    first = train.train(_cfg(args + ["checkpoint.stop_after_frames=60"]))
    assert first["stopped_early"]
    assert (tmp_path / "checkpoints" / "imitation.pt").is_file()
    rows = (tmp_path / "imitation.csv").read_text().strip().splitlines()
    assert len(rows) == 2 and rows[0].startswith("round,beta")
    # the resumed session does not teach again: it loads the teacher phase's result
    from torchrl_causal.training.imitation import OracleImitation

    calls = []
    original = OracleImitation.run
    monkeypatch.setattr(OracleImitation, "run",
                        lambda self, *a, **k: calls.append(1) or original(self, *a, **k))
    summary = train.train(_cfg(args + ["checkpoint.resume=true"]))
    assert calls == [] and summary["frames"] == 120
    assert summary["teacher"]["rounds"] == 1 and summary["teacher"]["frames"] > 0
    spec = json.loads((tmp_path / "policy.json").read_text())
    assert spec["inputs"] == ["causal_features", "goal_memory", "map_clearance", "action_history"]
    assert spec["shield"] is True and spec["loop_guard"] is True
    assert spec["provenance"]["teacher_frames"] == summary["teacher"]["frames"]
    assert {Path(p).name for p in summary["flight_maps"]} == {
        "flight_map_val.png", "flight_map_heldout.png", "flight_map_thesis.png"}
    assert set(summary["final_eval"]) == {"val", "heldout", "thesis"}
    # videos of evaluation episodes only: one thesis-scene, one held-out episode
    import av

    for scene in ("thesis", "heldout"):
        with av.open(str(tmp_path / "videos" / f"{scene}.mp4")) as video:
            stream = video.streams.video[0]
            assert stream.codec_context.name == "h264" and stream.width >= 320 + 48
            assert sum(1 for _ in video.decode(stream)) >= 2
    assert "spl" in summary["final_eval"]["heldout"]
    # the run folder is a policy folder: the pretrained loader rebuilds it
    from torchrl_causal.envs import DroneNavEnv
    from torchrl_causal.pretrained import load_policy_dir

    policy, env, _ = load_policy_dir(tmp_path, env=DroneNavEnv("random", split="heldout",
                                                                image_size=48, seed=0))
    td = env.rollout(5, policy, break_when_any_done=True)
    assert 1 <= td.shape[0] <= 5 and ((td["action"] >= 0) & (td["action"] < 8)).all()
    # the loop guard acts last, as it did in the run's collection and evaluation
    assert type(policy[-1]).__name__ == "LoopGuard" and "loop_guard_fired" in td.keys()
    run_policy, _, _ = train.load_policy(tmp_path, scene="heldout")
    assert type(run_policy[-1]).__name__ == "LoopGuard"
