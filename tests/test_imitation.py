"""ActionHistory and the oracle teacher (DAgger into a Q-network) with real MuJoCo scenes."""

from __future__ import annotations

import pytest
import torch
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import ParallelEnv, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from torchrl_causal.envs import DroneNavEnv
from torchrl_causal.pretrained import PolicySpec, build_policy, with_policy_features
from torchrl_causal.training import evaluate
from torchrl_causal.training.imitation import ImitationConfig, OracleImitation, margin_loss
from torchrl_causal.transforms.history import ActionHistory


def _hist_env(seed=0):
    return TransformedEnv(DroneNavEnv(image_size=32, seed=seed), ActionHistory(8, length=3))


def test_action_history_specs_alone_serial_and_parallel():
    check_env_specs(_hist_env())
    check_env_specs(SerialEnv(2, _hist_env))
    penv = ParallelEnv(2, _hist_env, mp_start_method="fork")
    try:
        check_env_specs(penv)
    finally:
        penv.close()


def test_action_history_shifts_and_clears_at_reset():
    env = _hist_env()
    td = env.reset()
    for a in (6, 7, 0):
        td = env.step(td.set("action", torch.tensor(a)))
        td = env.step_mdp(td)
    blocks = td["action_history"].view(3, 8)
    assert blocks.argmax(-1).tolist() == [0, 7, 6] and blocks.sum().item() == 3
    assert env.reset()["action_history"].abs().sum().item() == 0
    # partial reset in a batched env: only the reset sub-env is cleared
    benv = SerialEnv(2, _hist_env)
    td = benv.reset()
    td = benv.step(td.set("action", torch.tensor([1, 2])))
    td = benv.step_mdp(td)
    td.set("_reset", torch.tensor([[True], [False]]))
    out = benv.reset(td)
    assert out["action_history"][0].sum() == 0 and out["action_history"][1].argmax() == 2


def test_action_history_in_a_replay_buffer_and_bad_input():
    env = _hist_env()
    rollout = env.rollout(5)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=4)
    rb.extend(rollout)
    assert rb.sample()["next", "action_history"].shape == (4, 24)
    with pytest.raises(ValueError, match="length"):
        ActionHistory(8, length=0)


def test_margin_loss_is_zero_only_when_the_expert_wins_by_the_margin():
    q = torch.tensor([[2.0, 0.0, 0.5], [0.0, 0.0, 0.0]])
    expert = torch.tensor([0, 1])
    # row 0: expert ahead by 1.5 >= margin 1 -> 0; row 1: ties -> margin 1
    assert margin_loss(q, expert, 1.0).item() == pytest.approx(0.5)
    assert margin_loss(q[:1], expert[:1], 1.0).item() == 0.0


def test_imitation_config_rejects_bad_values():
    for kwargs, needle in [({"rounds": 0}, "rounds"), ({"beta_decay": 1.5}, "beta_decay"),
                           ({"lr": 0}, "lr"), ({"margin": -1}, "margin")]:
        with pytest.raises(ValueError, match=needle):
            ImitationConfig(**kwargs)


def _student_env(split, seed, layout_seed=0):
    spec = PolicySpec(image_size=40, inputs=["causal_features", "action_history"], history=4,
                      explorer="egreedy", gate_mode=None)
    base = DroneNavEnv("random", split=split, layout_seed=layout_seed, image_size=40, seed=seed)
    return spec, with_policy_features(spec, base, seed=seed)


def test_teacher_phase_labels_every_state_and_its_rounds_are_recorded():
    spec, env = _student_env("train", 0)
    actor, _ = build_policy(spec, env.action_spec_unbatched)
    teacher = OracleImitation(env, actor, ImitationConfig(rounds=2, episodes_per_round=2,
                                                          progress=False))
    hist = teacher.run()
    assert [r["round"] for r in hist] == [0, 1] and hist[0]["beta"] == 1.0
    assert hist[0]["success_rate"] == 1.0  # round 0: the oracle flies
    assert len(teacher.buffer) == sum(r["frames"] for r in hist)
    sample = teacher.buffer[:]
    valid = sample["expert_valid"]
    assert valid.float().mean() > 0.9 and (sample["expert_action"][valid] >= 0).all()
    # a continued run draws new layouts (not the first round's again)
    teacher.config.rounds = 3
    assert len(teacher.run()) == 3


@pytest.mark.slow
def test_learning_across_layouts_beats_random_flight_on_held_out_layouts():
    """Training across random layouts (the generalist's teacher phase, tiny budget) must
    fly held-out layouts it never saw clearly better than random flight.

    With ~1,000 frames the student does not yet reach held-out goals often (measured on
    the current 2-core machine: 3 of 24 for seed 0 vs 0 of 36 for random flight), so the
    margin is on the progress reward: metres flown towards the goal point, -10 per crash or
    geofence exit. One student is noisy: over 24 held-out episodes, students of seeds 0-2
    scored -5.0 / -2.6 / -3.4 per episode (another machine measured -2.3 for seed 0 over
    12), random flight -6.2. So two students (seeds 0 and 1) are trained and their mean is
    compared (measured: -3.8, a margin of 2.4). Random flight is cheap, so its mean is
    taken over 36 episodes (the first 24 are the students' layouts): over 12 alone it
    ranges -4.8 to -6.1 with the evaluation seed."""
    _, test_env = _student_env("heldout", 123)
    learned = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        spec, env = _student_env("train", 0)
        actor, _ = build_policy(spec, env.action_spec_unbatched)
        cfg = ImitationConfig(rounds=3, episodes_per_round=12, updates_per_frame=1.0,
                              batch_size=32, max_expansions=4000, seed=seed, progress=False)
        OracleImitation(env, actor, cfg).run()
        learned.append(evaluate(actor, test_env, episodes=24, seed=7, spl=False, max_steps=60))
    torch.manual_seed(1)

    def random_flight(td):
        return td.set("action", test_env.action_spec.rand())

    rand = evaluate(random_flight, test_env, episodes=36, seed=7, spl=False, max_steps=60)
    reward = sum(r["mean_reward"] for r in learned) / len(learned)
    success = sum(r["success_rate"] for r in learned) / len(learned)
    assert reward >= rand["mean_reward"] + 1.5, (learned, rand)
    assert success > 0 and success >= rand["success_rate"], (learned, rand)
