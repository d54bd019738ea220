"""The no-CBN control variants, validation-set selection (``eval.select_layout``,
``eval.fixed_episodes``) and the transfer of learned CBNs (``causal.transfer_from``),
with their bad-input rules. Real components; a short end-to-end run at the end."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir
from torchrl.envs import Transform

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))

import recipe_utils as ru  # noqa: E402
import train  # noqa: E402

from torchrl_causal.causal import CausalLearner  # noqa: E402
from torchrl_causal.modules import CBNGate  # noqa: E402
from torchrl_causal.schema import DEFAULT_SCHEMA  # noqa: E402

CONTROLS = ("dqn_features", "dqn_features_v2eps")
CARDS = torch.tensor(DEFAULT_SCHEMA.cardinalities)
GOAL = DEFAULT_SCHEMA.index("goal_in_sight")
CENTER = DEFAULT_SCHEMA.index("depth_center")


def _cfg(name="cbn_v2", overrides=()):
    with initialize_config_dir(config_dir=train.CONFIG_DIR, version_base=None):
        return compose(config_name=name, overrides=list(overrides))


def _transitions(n, seed, actions=(0, 1, 2, 3, 4, 5, 6)):
    """Forward crashes when the centre is close; seeing the goal at t+1 is positive."""
    g = torch.Generator().manual_seed(seed)
    s0 = (torch.rand(n, 9, generator=g) * CARDS).long()
    s1 = torch.where(torch.rand(n, 9, generator=g) < 0.7, s0,
                     (torch.rand(n, 9, generator=g) * CARDS).long())
    a = torch.tensor(actions)[torch.randint(0, len(actions), (n,), generator=g)]
    reward = torch.where(s1[:, GOAL] == 1, 50.0, -9.0)
    reward = torch.where((a == 0) & (s0[:, CENTER] == 0), torch.tensor(-1000.0), reward)
    return s0, a, s1, reward


@pytest.fixture(scope="module")
def source_run(tmp_path_factory):
    """A run folder whose ``cbns/last`` holds CBNs learned from a little data (action 7 unknown)."""
    run = tmp_path_factory.mktemp("source_run")
    learner = CausalLearner(min_rows=30)
    learner.add(*_transitions(1600, 0))
    learner.relearn()
    learner.save(run / "cbns" / "last")
    return run, learner


# --------------------------------------------------------------------------- controls
@pytest.mark.parametrize("name", CONTROLS)
def test_control_configs_validate(name, tmp_path):
    for preset in ("default", "thesis"):
        cfg = _cfg(name, [f"output_dir={tmp_path}", f"preset={preset}"])
        v = ru.validate_config(cfg, tmp_path)
        assert v.name == name and v.features and v.causal_mode is None
        assert ru.gate_mode(cfg, v) is None and v.label not in {
            w.label for w in ru.VARIANTS.values() if w.name != name}


@pytest.mark.parametrize("name, scale", [("dqn_features", 1.0), ("dqn_features_v2eps", 0.3)])
def test_control_agent_is_the_feature_network_with_egreedy(name, scale, tmp_path):
    from torchrl.modules import EGreedyModule

    from torchrl_causal.modules import ThesisQNet

    cfg = _cfg(name, [f"output_dir={tmp_path}", "exploration.eps_init=0.8",
                      "exploration.eps_end=0.1", "gate.prob_causal_model=0.7"])
    v = ru.validate_config(cfg, tmp_path)
    kw = ru.exploration_kwargs(cfg, v)
    assert kw["eps_init"] == pytest.approx(0.8 * scale) and kw["eps_end"] == pytest.approx(0.1 * scale)
    assert kw["annealing_num_steps"] == cfg.exploration.annealing_frames
    env = train.build_env(cfg, v, "thesis", "cpu")
    actor, explorer, hook = train.build_agent(cfg, v, env, "cpu")
    net = actor.module[0].module
    assert isinstance(net, ThesisQNet) and net.n_features == 9  # the Fig. 5.2 network
    assert actor.module[0].in_keys == ["pixels", "causal_state"]
    assert env.observation_spec["causal_state"].shape[-1] == 9  # the CBN variants' feature stack
    assert type(explorer) is EGreedyModule and hook is None  # no gate, no causal learner
    assert float(explorer.eps_init) == pytest.approx(0.8 * scale)
    assert float(explorer.eps_end) == pytest.approx(0.1 * scale)
    # the CBN variants keep the unscaled schedule
    assert ru.exploration_kwargs(cfg, ru.VARIANTS["cbn_v2"])["eps_init"] == pytest.approx(0.8)


# --------------------------------------------------------------------------- validation set
def test_val_scene_is_the_training_split_of_another_world():
    from torchrl_causal.envs import DroneNavEnv
    from torchrl_causal.envs.layouts import RandomLayoutGenerator

    assert ru.SCENES["val"] == {"layout": "random", "split": "train", "layout_seed": 1}
    val, train_gen = RandomLayoutGenerator("train", seed=1), RandomLayoutGenerator("train", seed=0)
    for i in range(3):
        assert val.split_of(val.layout(i)) == "train"
        assert val.layout(i).fingerprint() != train_gen.layout(i).fingerprint()
    env = DroneNavEnv(**ru.SCENES["val"], image_size=32, max_steps=5)
    assert env.split == "train"


def test_select_layout_orders_the_eval_scenes(tmp_path):
    cfg = _cfg("cbn_v2", [f"output_dir={tmp_path}", "env.eval_layouts=[thesis,val,heldout]"])
    ru.validate_config(cfg, tmp_path)
    assert ru.selection_scene(cfg) == "thesis"  # null: the first, today's behaviour
    assert ru.eval_scenes(cfg) == ["thesis", "val", "heldout"]
    cfg = _cfg("cbn_v2", [f"output_dir={tmp_path}", "env.eval_layouts=[thesis,val,heldout]",
                          "eval.select_layout=val", "eval.fixed_episodes=true"])
    ru.validate_config(cfg, tmp_path)
    assert ru.eval_scenes(cfg) == ["val", "thesis", "heldout"]
    # no selection on held-out layouts, whether keep_best is on or off
    ok = _cfg("cbn_v2", [f"output_dir={tmp_path}", "env.eval_layouts=[heldout,thesis]",
                         "eval.keep_best=false"])
    ru.validate_config(ok, tmp_path)


@pytest.mark.parametrize(
    "overrides, needle",
    [
        (["eval.select_layout=heldout"], "eval.select_layout='heldout'.*keep_best must not "
                                         "select on held-out layouts"),
        (["eval.select_layout=heldout", "eval.keep_best=false"], "eval.select_layout='heldout'"),
        (["env.eval_layouts=[heldout,thesis]"], "eval.select_layout=None.*'heldout'.*keep_best "
                                                "must not select on held-out layouts"),
        (["eval.select_layout=val"], r"eval.select_layout='val'.*env.eval_layouts=\['thesis', "
                                     r"'heldout'\]"),
        (["eval.fixed_episodes=sometimes"], "eval.fixed_episodes='sometimes'"),
        (["env.eval_layouts=[thesis,val]", "++env.options.layout_seed=3"],
         "env.options.layout_seed=3.*'val' sets layout_seed=1"),
    ],
)
def test_bad_selection_options_fail_before_training(overrides, needle, tmp_path):
    with pytest.raises(ValueError, match=needle):
        ru.validate_config(_cfg("cbn_v2", [f"output_dir={tmp_path}", *overrides]), tmp_path)


class _Starts(Transform):
    """Records the observation at every reset of an env (the episode's start and goal)."""

    def __init__(self):
        super().__init__()
        self.seen = []

    def _reset(self, tensordict, tensordict_reset):
        self.seen.append(tensordict_reset["observation"].clone())
        return tensordict_reset


@pytest.mark.parametrize("fixed", [True, False])
def test_fixed_seed_periodic_evaluations_replay_the_same_episodes(fixed):
    from torchrl.modules import MLP, EGreedyModule, QValueActor

    from torchrl_causal.envs import make_gridnav_env
    from torchrl_causal.training import DQNLoop, LoopConfig

    torch.manual_seed(0)
    env = make_gridnav_env(seed=0)
    actor = QValueActor(MLP(in_features=env.observation_spec["observation"].shape[-1],
                            out_features=4, num_cells=[16]),
                        in_keys=["observation"], spec=env.action_spec)
    starts = _Starts()
    eval_env = make_gridnav_env(seed=1, max_steps=5).append_transform(starts)
    config = LoopConfig(total_frames=60, learning_starts=20, updates_per_frame=0.25,
                        target_update_interval=5, buffer_size=60, batch_size=8,
                        eval_interval_frames=20, eval_episodes=4, final_eval_episodes=0,
                        checkpoint_interval_frames=0, eval_fixed_seed=fixed, seed=0)
    loop = DQNLoop(env, actor, EGreedyModule(env.action_spec, annealing_num_steps=60),
                   config=config, eval_envs={"val": eval_env})
    loop.run()
    assert loop.state["n_evals"] >= 3
    evals = torch.stack(starts.seen).reshape(loop.state["n_evals"], 4, -1)
    same = [torch.equal(evals[0], e) for e in evals[1:]]
    assert all(same) if fixed else not any(same)


# --------------------------------------------------------------------------- transfer
def test_transferred_cbns_equal_the_saved_ones_and_gate_at_frame_0(source_run, tmp_path):
    run, source = source_run
    cfg = _cfg("cbn_v2", [f"output_dir={tmp_path}", f"causal.transfer_from={run}"])
    ru.validate_config(cfg, tmp_path)
    assert ru.transfer_source(cfg) == run / "cbns" / "last"
    learner = CausalLearner(min_rows=30)
    gate = CBNGate("v2", seed=0)
    assert ru.transfer_cbns(cfg, learner, [gate])
    assert torch.equal(learner.tables.p_pos, source.tables.p_pos)
    assert learner.tables.known.tolist() == source.tables.known.tolist() == [True] * 7 + [False]
    assert {a: sorted(e) for a, e in learner.dags().items()} == {
        a: sorted(e) for a, e in source.dags().items()}
    assert learner.n_relearns == 0 and not learner.frozen
    assert gate.tables is not None and torch.equal(gate.tables.p_pos, source.tables.p_pos)
    # frame 0: the gate consults the transferred CBNs (no relearn has run)
    g = torch.Generator().manual_seed(1)
    td = _gate_input(256, g)
    gate(td)
    assert td[gate.diagnostic_keys["consulted"]].any()
    assert td[gate.diagnostic_keys["vetoed"]].any()
    # a folder of XMLBIF files directly; the library's own entry point
    direct = CausalLearner.from_saved(run / "cbns" / "last", min_rows=30)
    assert torch.equal(direct.tables.p_pos, source.tables.p_pos)
    assert ru.transfer_cbns(_cfg("cbn_v2", []), CausalLearner()) is False  # null: nothing


def _gate_input(n, g):
    from tensordict import TensorDict

    state = (torch.rand(n, 9, generator=g) * CARDS).long()
    q = torch.randn(n, 8, generator=g)
    q[:, 0] += 10.0  # greedy: forward, whose CBN knows the crash
    state[:, CENTER] = 0
    return TensorDict({"action_value": q, "causal_state": state}, batch_size=[n])


def test_transfer_relearn_warm_starts_or_freezes(source_run, tmp_path):
    run, source = source_run
    folder = run / "cbns" / "last"
    # relearn: actions with data of their own are relearned from the transferred
    # structures; the others keep their transferred CBN
    warm = CausalLearner.from_saved(folder, min_rows=30)
    warm.add(*_transitions(800, 5, actions=(0,)))
    tables = warm.relearn()
    assert warm.n_relearns == 1
    assert torch.equal(tables.p_pos[1:], source.tables.p_pos[1:])
    assert not torch.equal(tables.p_pos[0], source.tables.p_pos[0])
    assert "kept the transferred CBN" in warm.history[-1]["actions"]["backward"]["reason"]
    # resume: transfer again, then the checkpointed state
    again = CausalLearner.from_saved(folder, min_rows=30)
    again.load_state_dict(warm.state_dict())
    np.testing.assert_array_equal(again.cbns[1].reward_table(), warm.cbns[1].reward_table())
    assert torch.equal(again.tables.p_pos, tables.p_pos)
    # frozen: relearn changes nothing
    cfg = _cfg("cbn_v2", [f"output_dir={tmp_path}", f"causal.transfer_from={folder}",
                          "causal.transfer_relearn=false"])
    ru.validate_config(cfg, tmp_path)
    frozen = CausalLearner(min_rows=30)
    ru.transfer_cbns(cfg, frozen)
    frozen.add(*_transitions(800, 5, actions=(0,)))
    assert frozen.frozen and torch.equal(frozen.relearn().p_pos, source.tables.p_pos)
    assert frozen.n_relearns == 0


def _grid_cbns(folder):
    from torchrl_causal.envs import GRIDNAV_ACTIONS, GRIDNAV_SCHEMA

    return CausalLearner(GRIDNAV_SCHEMA, 4, action_names=GRIDNAV_ACTIONS).save(folder)


@pytest.mark.parametrize(
    "case, needle",
    [
        ("missing", "is not an existing folder"),
        ("empty", "holds no CBN file"),
        ("gridworld", "is not a CBN over the schema's variables.*another env"),
        ("partial", r"one CBN file per action.*missing: \['backward'"),
        ("dqn_image", "variant=dqn_image, which has no CBN"),
        ("dqn_features", "variant=dqn_features, which has no CBN"),
        ("dqn_features_v2eps", "variant=dqn_features_v2eps, which has no CBN"),
    ],
)
def test_bad_transfer_fails_before_training(case, needle, source_run, tmp_path):
    run, _ = source_run
    variant, src = "cbn_v2", tmp_path / case
    if case == "empty":
        src.mkdir()
        (src / "notes.txt").write_text("no CBN here")
    elif case == "gridworld":
        _grid_cbns(src)
    elif case == "partial":
        src.mkdir()
        (src / "forward.xmlbif").write_bytes((run / "cbns" / "last" / "forward.xmlbif").read_bytes())
    elif case != "missing":
        variant, src = case, run
    cfg = _cfg(variant, [f"output_dir={tmp_path / 'out'}", f"causal.transfer_from={src}"])
    with pytest.raises(ValueError, match=re.escape(f"causal.transfer_from='{src}'") + ".*" + needle):
        ru.validate_config(cfg, tmp_path / "out")
    if variant == "cbn_v2":  # the library says the same, naming the folder
        with pytest.raises(ValueError, match=needle):
            CausalLearner().transfer(src)


def test_transfer_relearn_must_be_a_bool(tmp_path):
    cfg = _cfg("cbn_v2", [f"output_dir={tmp_path}", "causal.transfer_relearn=sometimes"])
    with pytest.raises(ValueError, match="causal.transfer_relearn='sometimes'"):
        ru.validate_config(cfg, tmp_path)


# --------------------------------------------------------------------------- end to end
def test_recipe_transfers_and_selects_on_val(source_run, tmp_path):
    """recipes/train.py with a transfer: the gate consults from the first episode,
    periodic evaluations (one fixed episode on ``val``) drive keep_best."""
    run, _ = source_run
    out = tmp_path / "run"
    cfg = _cfg("cbn_v2", [
        f"output_dir={out}", f"causal.transfer_from={run}", "env.eval_layouts=[thesis,val]",
        "eval.select_layout=val", "eval.fixed_episodes=true", "eval.interval_frames=30",
        "eval.episodes=1", "eval.final_episodes=1", "collector.total_frames=60",
        "env.max_steps=20", "loss.learning_starts=30", "loss.updates_per_frame=0.1",
        "loss.target_update_interval=2", "buffer.size=60", "buffer.batch_size=4",
        "checkpoint.interval_frames=0", "progress=false", "logger.backend=none",
        "outputs.draw_cbns=false", "outputs.videos=0", "causal.k=1000"])
    summary = train.train(cfg)
    eps = pd.read_csv(out / "episodes.csv")
    assert eps["gate_frac_consulted"].iloc[0] > 0  # active before any relearn (k=1000)
    assert summary["n_relearns"] == 0
    ev = pd.read_csv(out / "eval.csv")
    assert set(ev["layout"]) == {"val"} and len(ev) >= 2
    assert list(summary["final_eval"]) == ["val", "thesis"]
    assert summary["selected_frames"] in set(ev["frames"])
    assert json.loads((out / "summary.json").read_text())["variant"] == "cbn_v2"
    assert np.isfinite(ev["mean_reward"]).all()
