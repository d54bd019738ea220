"""CausalLearningHook with the real CausalLearner in a real TensorDictReplayBuffer."""

import threading

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ListStorage, TensorDictReplayBuffer

from torchrl_causal.causal import CausalLearner
from torchrl_causal.data import CausalLearningHook
from torchrl_causal.modules import CBNGate
from torchrl_causal.schema import DEFAULT_SCHEMA

CENTER = DEFAULT_SCHEMA.index("depth_center")
CARDS = torch.tensor(DEFAULT_SCHEMA.cardinalities)


def transitions(n, seed=0, one_hot=False):
    """Random states; action 0 with an obstacle close in the centre crashes (reward -1000)."""
    g = torch.Generator().manual_seed(seed)
    s = (torch.rand(n, 9, generator=g) * CARDS).long()
    a = torch.randint(0, 8, (n,), generator=g)
    s1 = (torch.rand(n, 9, generator=g) * CARDS).long()
    reward = torch.where((a == 0) & (s[:, CENTER] == 0), -1000.0, 10.0)
    # other actions: reward class varies at random so every model is "known"
    reward = torch.where((a != 0) & (torch.rand(n, generator=g) < 0.3), -9.0, reward)
    action = torch.nn.functional.one_hot(a, 8).bool() if one_hot else a
    return TensorDict(
        pixels=torch.randint(0, 256, (n, 8, 8, 3), dtype=torch.uint8, generator=g),
        causal_state=s,
        action=action,
        next=TensorDict(
            causal_state=s1,
            reward=reward.unsqueeze(-1),
            done=torch.zeros(n, 1, dtype=torch.bool),
            batch_size=[n],
        ),
        batch_size=[n],
    )


def make(k=200, background=False, gates=(), **learner_kw):
    learner = CausalLearner(**learner_kw)
    hook = CausalLearningHook(learner, k=k, gates=gates, background=background)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10_000), batch_size=16)
    rb.append_transform(hook)
    return rb, hook, learner


def test_data_passes_through_and_every_transition_reaches_the_learner():
    rb, hook, learner = make(k=10_000)
    td = transitions(300)
    rb.extend(td)
    stored = rb[:]
    for key in td.keys(True, True):
        assert torch.equal(stored[key], td[key]), key
    assert rb.sample().batch_size == (16,)
    assert hook.frames == 300 and learner.n_relearns == 0
    assert learner.data.counts().tolist() == torch.bincount(td["action"], minlength=8).tolist()
    # rows are (s_t, s_t1, reward class) in node order
    rows0 = learner.data.rows(0)
    mask = td["action"] == 0
    assert (rows0[:, :9] == td["causal_state"][mask].numpy()).all()
    assert (rows0[:, 9:18] == td["next", "causal_state"][mask].numpy()).all()
    assert (rows0[:, -1] == (td["next", "reward"][mask, 0] >= 0).numpy()).all()


def test_relearns_every_k_frames_and_pushes_tables_to_gates():
    gate = CBNGate("pn", eps_init=0.0, eps_end=0.0, seed=0)
    rb, hook, learner = make(k=200, gates=[gate])
    seen = []
    for i in range(9):  # 9 writes of 50 frames: boundaries at 200 and 400
        rb.extend(transitions(50, seed=i))
        seen.append(learner.n_relearns)
        if learner.tables is not None:
            assert gate.tables is learner.tables
    assert seen == [0, 0, 0, 1, 1, 1, 1, 2, 2]
    assert hook.frames == 450
    assert [h["frames"] for h in learner.history] == [200, 400]
    # a gate registered later gets the current tables at once
    late = CBNGate("v2")
    hook.register_gate(late)
    assert late.tables is learner.tables


def test_first_relearn_then_every_k():
    learner = CausalLearner()
    hook = CausalLearningHook(learner, k=200, first_relearn=100)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10_000), batch_size=16)
    rb.append_transform(hook)
    for i in range(9):  # 9 writes of 50 frames: relearns at 100, then 200 and 400
        rb.extend(transitions(50, seed=i))
    assert [h["frames"] for h in learner.history] == [100, 200, 400]


def test_learned_tables_make_the_gate_veto_the_crashing_action():
    gate = CBNGate("pn", prob_causal_model=1.0, eps_init=0.0, eps_end=0.0, seed=0)
    rb, hook, learner = make(k=2000, gates=[gate])
    rb.extend(transitions(2000, seed=1))
    assert learner.n_relearns == 1 and bool(gate.tables.known.all())
    states = torch.from_numpy(DEFAULT_SCHEMA.all_states())
    p_pos, _, _ = gate.tables.lookup(states)
    close = states[:, CENTER] == 0
    assert p_pos[close, 0].max() < 0.25 and p_pos[~close, 0].min() > 0.75
    # the DQN wants action 0 everywhere: vetoed exactly where the centre is close
    q = torch.zeros(len(states), 8)
    q[:, 0] = 1.0
    td = gate(TensorDict(action_value=q, causal_state=states, batch_size=[len(states)]))
    assert torch.equal(td["gate_vetoed"], close)
    assert (td["action"][close] != 0).all() and (td["action"][~close] == 0).all()


def test_one_hot_actions_time_batches_and_collector_mask():
    rb, hook, learner = make(k=10_000)
    td = transitions(60, one_hot=True).reshape(3, 20)  # [envs, time]
    td["collector", "mask"] = torch.ones(3, 20, dtype=torch.bool)
    td["collector", "mask"][2, 10:] = False  # padding: not a transition
    rb2 = TensorDictReplayBuffer(storage=ListStorage(100), batch_size=4)
    rb2.append_transform(hook)
    rb2.extend(td.reshape(-1))
    assert hook.frames == 50
    a = td["action"].reshape(-1, 8).long().argmax(-1)[td["collector", "mask"].reshape(-1)]
    assert learner.data.counts().tolist() == torch.bincount(a, minlength=8).tolist()
    # single transitions through rb.add (unsqueezed by the buffer) count too
    rb.add(transitions(1)[0])
    assert hook.frames == 51


def test_missing_key_is_reported():
    rb, hook, _ = make()
    with pytest.raises(KeyError, match="next.*causal_state"):
        rb.extend(transitions(5).exclude(("next", "causal_state")))


class BlockingLearner(CausalLearner):
    """The real learner, with relearn() held until the test releases it."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.release = threading.Event()
        self.started = threading.Event()

    def relearn(self):
        self.started.set()
        assert self.release.wait(timeout=30)
        return super().relearn()


def test_background_relearn_does_not_block_collection():
    gate = CBNGate("v2")
    learner = BlockingLearner()
    hook = CausalLearningHook(learner, k=100, gates=[gate], background=True)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10_000), batch_size=16)
    rb.append_transform(hook)
    rb.extend(transitions(100, seed=0))  # crosses 100: relearn starts in the worker
    assert learner.started.wait(timeout=30)
    assert hook.relearning and gate.tables is None
    # collection goes on while the worker is held; data is queued, not lost
    rb.extend(transitions(150, seed=1))  # crosses 200: merged into one follow-up relearn
    assert len(rb) == 250 and hook.frames == 250
    assert learner.data.total_added == 100
    learner.release.set()
    hook.wait()
    assert learner.data.total_added == 250
    assert learner.n_relearns == 2  # the first, plus the follow-up for the 200 boundary
    assert [h["frames"] for h in learner.history] == [100, 250]
    assert gate.tables is learner.tables
    hook.close()


def test_background_worker_errors_surface():
    class Failing(CausalLearner):
        def relearn(self):
            raise RuntimeError("boom")

    hook = CausalLearningHook(Failing(), k=10, background=True)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=4)
    rb.append_transform(hook)
    rb.extend(transitions(10))
    with pytest.raises(RuntimeError, match="boom"):
        hook.wait()
    hook.close()


@pytest.mark.parametrize("background", [False, True])
def test_checkpoint_resume_matches_uninterrupted_run(background):
    batches = [transitions(70, seed=i) for i in range(8)]  # 560 frames, k = 200
    # uninterrupted
    rb, hook, learner = make(k=200, background=background)
    for b in batches:
        rb.extend(b)
    hook.wait()
    # interrupted after 4 writes (280 frames: one relearn done, next at 400)
    rb1, hook1, learner1 = make(k=200, background=background)
    for b in batches[:4]:
        rb1.extend(b)
    sd = rb1.state_dict()  # the buffer's state carries the hook's
    hook1.close()
    gate = CBNGate("pn")
    rb2, hook2, learner2 = make(k=200, background=background, gates=[gate])
    rb2.load_state_dict(sd)
    assert hook2.frames == 280 and learner2.n_relearns == 1
    assert torch.equal(gate.tables.p_pos, learner1.tables.p_pos)
    for b in batches[4:]:
        rb2.extend(b)
    hook2.wait()
    assert hook2.frames == hook.frames == 560
    assert learner2.n_relearns == learner.n_relearns == 2
    assert learner2.data.total_added == learner.data.total_added == 560
    if not background:  # in the background, which rows a relearn sees depends on timing
        assert [h["frames"] for h in learner2.history] == [h["frames"] for h in learner.history]
        assert learner2.dags() == learner.dags()
        torch.testing.assert_close(learner2.tables.p_pos, learner.tables.p_pos)
    # the hook's own state_dict works the same way
    hook3 = CausalLearningHook(CausalLearner(), k=200)
    hook3.load_state_dict(hook2.state_dict())
    assert hook3.frames == 560 and hook3.learner.data.total_added == 560
    for h in (hook, hook2):
        h.close()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(k=0), "k must be"),
        (dict(k=-5), "k must be"),
        (dict(k=2.5), "k must be"),
        (dict(background="yes"), "background"),
        (dict(gates=[object()]), "set_tables"),
        (dict(learner=object()), "learner must provide"),
        (dict(first_relearn=0), "first_relearn must be"),
        (dict(first_relearn=1.5), "first_relearn must be"),
    ],
)
def test_bad_options(kwargs, match):
    kwargs.setdefault("learner", CausalLearner())
    with pytest.raises(ValueError, match=match):
        CausalLearningHook(**kwargs)


@pytest.mark.parametrize("background", [False, True])
def test_buffer_holding_the_hook_pickles(background):
    import pickle

    rb, hook, learner = make(k=100, background=background)
    rb.extend(transitions(150))
    rb2 = pickle.loads(pickle.dumps(rb))
    hook2 = rb2._transform[0]
    assert isinstance(hook2, CausalLearningHook)
    assert hook2.frames == 150 and hook2.learner.n_relearns == 1
    assert hook2.learner.data.counts().tolist() == learner.data.counts().tolist()
    rb2.extend(transitions(50, seed=1))  # the copy keeps learning
    hook2.wait()
    assert hook2.frames == 200 and hook2.learner.n_relearns == 2
    hook.close()
    hook2.close()
