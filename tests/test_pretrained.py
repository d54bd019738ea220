"""torchrl_causal.pretrained from the outside: the shipped policies, PolicySpec, bad input."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_causal.envs import DroneNavEnv
from torchrl_causal.pretrained import (
    PolicySpec,
    available,
    load_policy,
    load_policy_dir,
    policy_dir,
    provenance,
)
from torchrl_causal.training import evaluate

ROOT = Path(__file__).resolve().parents[1]


def test_available_lists_the_shipped_policies_and_unknown_names_are_named():
    names = available()
    assert "thesis" in names
    with pytest.raises(ValueError, match=r"name='nope'.*available are \[.*'thesis'"):
        load_policy("nope")
    prov = provenance("thesis")
    assert prov["seed"] == 0 and prov["variant"] == "cbn_v2" and prov["commit"]


def test_thesis_policy_flies_the_thesis_scene_in_one_call():
    policy, env = load_policy("thesis", base_env=DroneNavEnv(seed=0))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.rollout(200, policy, break_when_any_done=True)
    assert bool(td["next", "reached"][-1]) and td.shape[0] <= 16
    # the default base env of the thesis policy is the thesis scene
    _, default_env = load_policy("thesis")
    assert default_env.base_env.layout_option == "thesis"


def test_recipe_loader_and_pretrained_loader_build_the_same_policy():
    sys.path.insert(0, str(ROOT / "recipes"))
    import train

    folder = policy_dir("thesis")
    a, env_a, _ = train.load_policy(folder)
    b, env_b, spec = load_policy_dir(folder, env=DroneNavEnv(seed=0))
    assert spec.inputs == ["causal_state"] and spec.explorer == "cbn_gate"
    td = env_b.reset()
    qa = a[0](td.clone())["action_value"]
    qb = b[0](td.clone())["action_value"]
    torch.testing.assert_close(qa, qb)
    assert a[1].tables is not None and b[1].tables is not None


def test_policy_spec_round_trip_and_bad_input(tmp_path):
    spec = PolicySpec(inputs=["causal_features", "action_history"], history=3,
                      explorer="egreedy", gate_mode=None)
    assert PolicySpec.from_json(spec.to_json()) == spec
    assert spec.n_features == 9 + 24 and spec.actor_keys == ["pixels", "policy_features"]
    with pytest.raises(ValueError, match="unknown keys"):
        PolicySpec(inputs=["speed"])
    with pytest.raises(ValueError, match="history"):
        PolicySpec(inputs=["action_history"], history=0)
    with pytest.raises(ValueError, match="explorer"):
        PolicySpec(explorer="softmax")
    with pytest.raises(ValueError, match="unknown fields"):
        PolicySpec.from_json(json.dumps({"image_size": 84, "colour": "red"}))
    folder = tmp_path / "pol"
    shutil.copytree(policy_dir("thesis"), folder)
    (folder / "model.pt").unlink()
    with pytest.raises(FileNotFoundError, match="model"):
        load_policy_dir(folder)


def test_shipped_generalist_flies_held_out_layouts_better_than_random_flight():
    """The shipped generalist on held-out random layouts it never saw. Its figures over 100
    layouts are in provenance.json (its run's final evaluation: 0.89 success, SPL 0.74); here
    12 seeded episodes against random flight (measured: 10 of 12 vs 0 of 12 reached, no
    crash vs 4, progress reward +10.9 vs -10.9 per episode)."""
    assert "generalist" in available()
    policy, env = load_policy("generalist")
    assert env.base_env.split == "heldout"
    res = evaluate(policy, env, episodes=12, seed=2024, spl=False)
    torch.manual_seed(0)
    rand = evaluate(lambda td: td.set("action", env.action_spec.rand()), env, episodes=12,
                    seed=2024, spl=False)
    assert res["success_rate"] >= rand["success_rate"] + 0.6, (res, rand)
    assert res["mean_reward"] >= rand["mean_reward"] + 15.0, (res, rand)
    assert res["collisions"] <= 1, res  # the shield: no move the map says will not fit
    prov = provenance("generalist")
    assert prov["training_scene"] == "train" and prov["teacher"]["frames"] > 0


def test_fly_tello_flies_the_shipped_generalist_when_no_run_is_given():
    sys.path.insert(0, str(ROOT / "recipes"))
    import fly_tello

    args = fly_tello.parse_args(["--episodes", "1"])
    assert Path(args.run) == policy_dir("generalist")
    assert Path(args.out) == Path("outputs") / "tello" / "generalist"  # not inside the package


def test_ship_policy_copies_a_run_and_can_add_the_loop_guard(tmp_path, capsys):
    """recipes/ship_policy.py: a run folder (here the shipped generalist's, itself a run
    folder) becomes a loadable policy folder; --loop-guard appends LoopGuard and says so."""
    sys.path.insert(0, str(ROOT / "recipes"))
    import ship_policy

    from omegaconf import OmegaConf

    run = tmp_path / "run"  # the generalist's run as trained: no guard in its config
    shutil.copytree(policy_dir("generalist"), run)
    cfg = OmegaConf.load(run / "config.yaml")
    cfg.features.loop_guard = False
    cfg.features.revisit_guard = False  # nor the revisit guard
    cfg.features.ego_map = {}  # nor the flank margin or the fence
    OmegaConf.save(cfg, run / "config.yaml")
    (run / "provenance.json").unlink()  # a run folder has no shipped record
    out = ship_policy.ship(run, "guarded", dest=tmp_path, loop_guard=True)
    spec = json.loads((out / "policy.json").read_text())
    assert spec["loop_guard"] is True and spec["shield"] is True
    assert "loop_guard" in json.loads((out / "provenance.json").read_text())
    policy, env, _ = load_policy_dir(out, env=DroneNavEnv("random", split="heldout", seed=0))
    assert type(policy[-1]).__name__ == "LoopGuard"
    shipped = load_policy_dir(policy_dir("generalist"))[0][0].state_dict()
    assert all(torch.equal(v, shipped[k]) for k, v in policy[0].state_dict().items())
    env.close()
    # the thesis policy has no action history: the guard cannot read four actions
    with pytest.raises(SystemExit):
        ship_policy.main([str(policy_dir("thesis")), "x", "--loop-guard"])
    assert "--loop-guard" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError, match="has no config.yaml"):
        ship_policy.ship(tmp_path / "guarded_missing", "y", dest=tmp_path)
    # --flank-margin: the shipped stack's EgoMap gets it, and provenance says so
    out = ship_policy.ship(run, "flanked", dest=tmp_path, loop_guard=True, flank_margin=0.3)
    spec = json.loads((out / "policy.json").read_text())
    assert spec["ego_map"]["flank_margin"] == 0.3
    assert "flank_margin" in json.loads((out / "provenance.json").read_text())
    policy, env, _ = load_policy_dir(out, env=DroneNavEnv("random", split="heldout", seed=0))
    maps = [t for t in env.transform if type(t).__name__ == "EgoMap"]
    assert len(maps) == 1 and maps[0].flank_margin == 0.3
    env.close()
    with pytest.raises(SystemExit):
        ship_policy.main([str(run), "x", "--flank-margin", "-1"])
    assert "--flank-margin" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # the thesis policy builds no map
        ship_policy.main([str(policy_dir("thesis")), "x", "--flank-margin", "0.3"])
    assert "EgoMap" in capsys.readouterr().err


def test_evaluate_restarts_the_gates_draws_and_puts_them_back():
    """The V2 gate draws random numbers even in greedy evaluation (it consults its CBNs
    with probability 0.7): two evaluations of one policy on one seed fly the same episodes,
    and the gate's own stream is where it was before (an evaluation inside a training run
    does not move it)."""
    from torchrl_causal.modules import CBNGate

    policy, env = load_policy("generalist")  # its gate draws from torch's global generator
    before = torch.get_rng_state()
    runs = [evaluate(policy, env, 4, seed=7, spl=False) for _ in range(2)]
    assert runs[0] == runs[1]
    assert torch.equal(torch.get_rng_state(), before)
    # a gate with a generator of its own: restarted, then put back
    gate = CBNGate("v2", seed=3)
    seeded = torch.nn.ModuleList([gate])  # anything with .modules() holding the gate
    state = gate.generator.get_state()
    from torchrl_causal.training.evaluation import _policy_generators

    assert _policy_generators(seeded) == [gate.generator]
    assert torch.equal(gate.generator.get_state(), state)
    env.close()
