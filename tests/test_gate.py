"""CBNGate: each branch of thesis Alg. 3 (P, PN) and Alg. 4 (V2) checked statistically.

Every test drives the gate with a large batch of identical (or two kinds of)
states and compares the observed action / flag frequencies with the
probabilities the pseudo-code implies, with chi-square and binomial bounds.
Seeds are fixed, so the tests are deterministic; the bounds are wide enough
(p > 1e-4, 5 sigma) that any seed passes a correct implementation.
"""

import math

import pytest
import torch
from scipy.stats import chisquare
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torchrl.data import Categorical, OneHot
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import EGreedyModule, QValueActor
from torchrl.objectives import DQNLoss

from torchrl_causal.causal.tables import RewardTables
from torchrl_causal.modules import CBNGate, ThesisQNet
from torchrl_causal.schema import DEFAULT_SCHEMA

A = 8
N = 40_000
G = 2  # the DQN's greedy action in every test
PCM, THR = 0.7, 0.75


def tables_from(p_by_action, known=None):
    """Tables whose P(pos | s, a) does not depend on s."""
    p = torch.as_tensor(p_by_action, dtype=torch.float32)
    p = p.unsqueeze(1).expand(A, DEFAULT_SCHEMA.n_states).clone()
    known = torch.ones(A, dtype=torch.bool) if known is None else torch.as_tensor(known)
    return RewardTables(p, known)


def batch(n=N, greedy=G):
    q = torch.zeros(n, A)
    q[:, greedy] = 1.0
    return TensorDict(
        action_value=q,
        action=torch.full((n,), greedy),
        causal_state=torch.zeros(n, 9, dtype=torch.long),
        batch_size=[n],
    )


def run(variant, eps, tables, seed=0, **kw):
    gate = CBNGate(variant, PCM, THR, eps_init=eps, eps_end=eps, seed=seed, **kw)
    gate.set_tables(tables)
    return gate(batch())


def assert_action_freqs(action, expected):
    expected = torch.as_tensor(expected, dtype=torch.float64)
    assert math.isclose(expected.sum().item(), 1.0, abs_tol=1e-9)
    counts = torch.bincount(action, minlength=A).double()
    nz = expected > 0
    assert counts[~nz].sum() == 0, f"actions with probability 0 were taken: {counts}"
    _, pval = chisquare(counts[nz].numpy(), (expected[nz] * len(action)).numpy())
    assert pval > 1e-4, (counts / len(action), expected)


def assert_rate(flag, p):
    n = flag.numel()
    freq = flag.float().mean().item()
    tol = 5 * math.sqrt(max(p * (1 - p), 1e-12) / n) + 1e-12
    assert abs(freq - p) <= tol, (freq, p)


def dist(**probs):
    d = torch.zeros(A, dtype=torch.float64)
    for k, v in probs.items():
        if k == "rest":
            continue
        d[int(k[1:])] = v
    rest = probs.get("rest")
    if rest is not None:
        for a in range(A):
            if f"a{a}" not in probs:
                d[a] = rest
    return d


# ---------------------------------------------------------------- Algorithm 3
@pytest.mark.parametrize("eps", [0.0, 0.2])
def test_pn_veto_branch(eps):
    # greedy action is bad: P(neg) = 0.9 > 0.75 -> redraw uniformly among the others
    p = [0.5] * A
    p[G] = 0.1
    td = run("pn", eps, tables_from(p))
    e, k = eps, (1 - eps) * PCM
    assert_action_freqs(td["action"], dist(**{f"a{G}": e / A + (1 - e) * (1 - PCM)}, rest=e / A + k / (A - 1)))
    assert_rate(td["gate_explored"], e)
    assert_rate(td["gate_consulted"], k)
    assert_rate(td["gate_vetoed"], k)
    assert not td["gate_replaced"].any()
    assert (td["action"][td["gate_vetoed"]] != G).all()
    # the CBN is never consulted about an epsilon-random action (Alg. 3 line 10-11)
    assert not (td["gate_consulted"] & td["gate_explored"]).any()
    torch.testing.assert_close(td["gate_p_pos"][~td["gate_explored"]], torch.full(((~td["gate_explored"]).sum(),), 0.1))
    torch.testing.assert_close(td["gate_p_neg"] + td["gate_p_pos"], torch.ones(N))


@pytest.mark.parametrize("variant", ["pn", "p"])
def test_replace_branch_takes_argmax_p_pos(variant):
    # greedy action uncertain (P = 0.5 < 0.75, N = 0.5 not > 0.75) -> argmax P
    p = [0.5] * A
    p[5] = 0.8
    eps = 0.2
    td = run(variant, eps, tables_from(p))
    k = (1 - eps) * PCM
    expected = dist(**{f"a{G}": eps / A + (1 - eps) * (1 - PCM), "a5": eps / A + k}, rest=eps / A)
    assert_action_freqs(td["action"], expected)
    assert_rate(td["gate_replaced"], k)
    assert not td["gate_vetoed"].any()
    assert (td["action"][td["gate_replaced"]] == 5).all()
    assert (td["gate_dqn_action"][~td["gate_explored"]] == G).all()


def test_p_variant_has_no_veto():
    # the PN veto case: P has only the positive branch, so it replaces instead
    p = [0.5] * A
    p[G] = 0.1
    p[6] = 0.95
    eps = 0.1
    td = run("p", eps, tables_from(p))
    k = (1 - eps) * PCM
    assert_action_freqs(
        td["action"], dist(**{f"a{G}": eps / A + (1 - eps) * (1 - PCM), "a6": eps / A + k}, rest=eps / A)
    )
    assert not td["gate_vetoed"].any()
    assert_rate(td["gate_replaced"], k)


@pytest.mark.parametrize("variant", ["p", "pn", "v2"])
def test_confident_good_action_is_kept(variant):
    p = [0.5] * A
    p[G] = 0.9
    eps = 0.3
    td = run(variant, eps, tables_from(p))
    if variant == "v2":
        keep = PCM + (1 - PCM) * (1 - eps + eps / A)
        assert_rate(td["gate_consulted"], PCM)
    else:
        keep = eps / A + (1 - eps)
        assert_rate(td["gate_consulted"], (1 - eps) * PCM)
    assert_action_freqs(td["action"], dist(**{f"a{G}": keep}, rest=(1 - keep) / (A - 1)))
    assert not (td["gate_vetoed"] | td["gate_replaced"]).any()


def test_thresholds_are_strict_inequalities():
    # P(neg) == 0.75 is not "> threshold": PN goes on to the positive test, P = 0.25 < 0.75 -> replace
    p = [0.5] * A
    p[G], p[4] = 0.25, 0.6
    td = run("pn", 0.0, tables_from(p))
    assert not td["gate_vetoed"].any()
    assert_rate(td["gate_replaced"], PCM)
    assert (td["action"][td["gate_replaced"]] == 4).all()
    # P(pos) == 0.75 is not "< threshold": kept
    p[G] = 0.75
    td = run("pn", 0.0, tables_from(p))
    assert not (td["gate_vetoed"] | td["gate_replaced"]).any()
    assert (td["action"] == G).all()


# ---------------------------------------------------------------- Algorithm 4
@pytest.mark.parametrize("eps", [0.0, 0.25])
def test_v2_veto_branch(eps):
    p = [0.5] * A
    p[G] = 0.1  # P < 0.75 and N = 0.9 > 0.75
    td = run("v2", eps, tables_from(p))
    keep = (1 - PCM) * (1 - eps + eps / A)
    assert_action_freqs(td["action"], dist(**{f"a{G}": keep}, rest=PCM / (A - 1) + (1 - PCM) * eps / A))
    assert_rate(td["gate_consulted"], PCM)
    assert_rate(td["gate_vetoed"], PCM)
    # consulting comes first: no epsilon draw on consulted elements (Alg. 4 line 3 vs 10-12)
    assert not (td["gate_consulted"] & td["gate_explored"]).any()
    assert_rate(td["gate_explored"], (1 - PCM) * eps)
    assert not td["gate_replaced"].any()


def test_v2_uncertain_action_is_not_vetoed():
    p = [0.5] * A
    p[G] = 0.5  # P < 0.75 but N = 0.5 not > 0.75
    p[5] = 0.99  # V2 has no argmax-P replacement
    eps = 0.25
    td = run("v2", eps, tables_from(p))
    keep = PCM + (1 - PCM) * (1 - eps + eps / A)
    assert_action_freqs(td["action"], dist(**{f"a{G}": keep}, rest=(1 - PCM) * eps / A))
    assert not (td["gate_vetoed"] | td["gate_replaced"]).any()


# ---------------------------------------------------------------- state dependence, abstaining
@pytest.mark.parametrize("variant", ["pn", "v2"])
def test_tables_are_indexed_by_each_elements_state(variant):
    # P(pos | s, G) depends on goal_in_sight: 0.1 when not in sight, 0.9 in sight
    p = torch.full((A, DEFAULT_SCHEMA.n_states), 0.5)
    states = torch.from_numpy(DEFAULT_SCHEMA.all_states())
    in_sight = states[:, DEFAULT_SCHEMA.index("goal_in_sight")] == 1
    p[G] = torch.where(in_sight, 0.9, 0.1)
    gate = CBNGate(variant, eps_init=0.0, eps_end=0.0, seed=3)
    gate.set_tables(RewardTables(p, torch.ones(A, dtype=torch.bool)))
    td = batch()
    td["causal_state"][: N // 2, DEFAULT_SCHEMA.index("goal_in_sight")] = 1
    gate(td)
    assert not td["gate_vetoed"][: N // 2].any()
    assert (td["action"][: N // 2] == G).all()
    assert_rate(td["gate_vetoed"][N // 2 :], PCM)
    assert (td["gate_p_pos"][: N // 2] == 0.9).all() and torch.allclose(
        td["gate_p_pos"][N // 2 :], torch.tensor(0.1)
    )


@pytest.mark.parametrize("variant", ["p", "pn", "v2"])
def test_abstains_without_tables_like_egreedy(variant):
    eps = 0.4
    gate = CBNGate(variant, eps_init=eps, eps_end=eps, seed=1)
    assert gate.tables is None
    td = gate(batch())
    assert_action_freqs(td["action"], dist(**{f"a{G}": 1 - eps + eps / A}, rest=eps / A))
    assert not (td["gate_consulted"] | td["gate_vetoed"] | td["gate_replaced"]).any()
    assert td["gate_p_pos"].isnan().all() and td["gate_p_neg"].isnan().all()
    # same frequencies as torchrl's EGreedyModule with the same eps
    eg = EGreedyModule(Categorical(A), eps_init=eps, eps_end=eps)
    torch.manual_seed(1)
    ref = eg(batch())["action"]
    ref_greedy = (ref == G).float().mean().item()
    assert abs((td["action"] == G).float().mean().item() - ref_greedy) < 0.02
    # tables can be set, then removed again
    p = [0.5] * A
    p[G] = 0.05
    gate.set_tables(tables_from(p))
    assert gate(batch())["gate_consulted"].any()
    gate.set_tables(None)
    assert not gate(batch())["gate_consulted"].any()


@pytest.mark.parametrize("variant", ["p", "pn", "v2"])
def test_abstains_on_unknown_action(variant):
    p = [0.5] * A
    p[G] = 0.05  # would be vetoed / replaced if known
    p[7] = 0.99  # best P, but unknown: never chosen by argmax
    p[5] = 0.8
    known = [True] * A
    known[G] = known[7] = False
    eps = 0.2
    td = run(variant, eps, tables_from(p, known))
    assert_action_freqs(td["action"], dist(**{f"a{G}": 1 - eps + eps / A}, rest=eps / A))
    greedy = ~td["gate_explored"]
    assert not td["gate_consulted"][greedy].any()
    assert td["gate_p_pos"][greedy].isnan().all()
    # a known action uncertain -> replacement never picks the unknown action 7
    if variant != "v2":
        known[G] = True
        p[G] = 0.5
        td = run(variant, 0.0, tables_from(p, known))
        assert_rate(td["gate_replaced"], PCM)
        assert (td["action"][td["gate_replaced"]] == 5).all()


# ---------------------------------------------------------------- mechanics
def test_seeded_gate_is_reproducible():
    p = [0.5] * A
    p[G] = 0.1
    a1 = run("pn", 0.3, tables_from(p), seed=7)["action"]
    a2 = run("pn", 0.3, tables_from(p), seed=7)["action"]
    a3 = run("pn", 0.3, tables_from(p), seed=8)["action"]
    assert torch.equal(a1, a2) and not torch.equal(a1, a3)


@pytest.mark.parametrize("shape", [(), (5,), (3, 4)])
def test_batch_shapes(shape):
    gate = CBNGate("pn", eps_init=0.5, eps_end=0.5, seed=0)
    p = [0.5] * A
    p[0] = 0.1
    gate.set_tables(tables_from(p))
    q = torch.randn(*shape, A)
    td = TensorDict(
        action_value=q,
        action=q.argmax(-1),
        causal_state=torch.zeros(*shape, 9, dtype=torch.long),
        batch_size=shape,
    )
    gate(td)
    assert td["action"].shape == shape and td["action"].dtype == torch.int64
    for key in gate.diagnostic_keys.values():
        assert td[key].shape == shape
    assert ((td["action"] >= 0) & (td["action"] < A)).all()


def test_eps_schedule_matches_egreedy_module():
    gate = CBNGate("v2", eps_init=1.0, eps_end=0.05, annealing_num_steps=1000)
    eg = EGreedyModule(Categorical(A), eps_init=1.0, eps_end=0.05, annealing_num_steps=1000)
    total = 0
    for frames in (1, 10, 250, 300, 1000):
        gate.step(frames)
        eg.step(frames)
        total += frames
        # EGreedyModule accumulates float32 round-off over one update per frame
        torch.testing.assert_close(gate.eps, eg.eps, atol=1e-4, rtol=0)
        exact = max(0.05, 1.0 - 0.95 * total / 1000)
        assert gate.eps.item() == pytest.approx(exact, abs=1e-6)
    assert gate.eps.item() == pytest.approx(0.05)


def test_exploration_type_deterministic():
    p = [0.5] * A
    p[G] = 0.1
    gate = CBNGate("pn", prob_causal_model=1.0, eps_init=1.0, eps_end=1.0, seed=0)
    gate.set_tables(tables_from(p))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = gate(batch(1000))
        # eps is off, the CBN still vetoes
        assert not td["gate_explored"].any() and td["gate_vetoed"].all()
        gate.eval_gate = False
        td = gate(batch(1000))
        assert (td["action"] == G).all() and not td["gate_consulted"].any()


def test_state_dict_round_trip():
    p = [0.5] * A
    p[G] = 0.1
    gate = CBNGate("pn", eps_init=0.5, eps_end=0.1, annealing_num_steps=100, seed=11)
    gate.set_tables(tables_from(p))
    gate.step(30)
    gate(batch(10))
    sd = gate.state_dict()
    other = CBNGate("pn", eps_init=0.5, eps_end=0.1, annealing_num_steps=100, seed=0)
    other.load_state_dict(sd)
    assert other.eps.item() == pytest.approx(gate.eps.item())
    assert torch.equal(other.tables.p_pos, gate.tables.p_pos)
    assert torch.equal(other(batch(500))["action"], gate(batch(500))["action"])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(variant="pnx"), "variant"),
        (dict(prob_causal_model=1.5), "prob_causal_model"),
        (dict(threshold=-0.1), "threshold"),
        (dict(threshold="high"), "threshold"),
        (dict(eps_init=0.1, eps_end=0.5), "eps_end"),
        (dict(annealing_num_steps=0), "annealing_num_steps"),
        (dict(n_actions=1), "n_actions"),
        (dict(action_space="discrete"), "action_space"),
        (dict(seed=0, generator=torch.Generator()), "seed or generator"),
    ],
)
def test_bad_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        CBNGate(**kwargs)


def test_bad_tables():
    gate = CBNGate("pn", n_actions=8)
    with pytest.raises(ValueError, match="RewardTables"):
        gate.set_tables(torch.zeros(8, 1728))
    with pytest.raises(ValueError, match="n_actions"):
        gate.set_tables(RewardTables(torch.zeros(4, 1728), torch.ones(4, dtype=torch.bool)))


# ---------------------------------------------------------------- composition
def _policy_td(n=16):
    g = torch.Generator().manual_seed(0)
    return TensorDict(
        pixels=torch.randint(0, 256, (n, 84, 84, 3), dtype=torch.uint8, generator=g),
        causal_features=torch.rand(n, 9, generator=g),
        causal_state=torch.zeros(n, 9, dtype=torch.long),
        batch_size=[n],
    )


@pytest.mark.parametrize("spec", [Categorical(8), OneHot(8)])
def test_composes_with_qvalue_actor_and_dqn_loss(spec):
    torch.manual_seed(0)
    actor = QValueActor(ThesisQNet(8, n_features=9), in_keys=["pixels", "causal_features"], spec=spec)
    gate = CBNGate("pn", prob_causal_model=1.0, eps_init=0.0, eps_end=0.0, seed=0)
    policy = TensorDictSequential(actor, gate)
    td = _policy_td()
    # veto every action the DQN can pick: P(pos) = 0.05 everywhere
    gate.set_tables(tables_from([0.05] * A))
    policy(td)
    greedy = td["action_value"].argmax(-1)
    executed = td["action"] if isinstance(spec, Categorical) else td["action"].long().argmax(-1)
    if isinstance(spec, OneHot):
        assert td["action"].shape == (16, 8) and td["action"].sum(-1).eq(1).all()
    assert td["gate_vetoed"].all()
    assert torch.equal(td["gate_dqn_action"], greedy)
    assert (executed != greedy).all()
    torch.testing.assert_close(
        td["chosen_action_value"].squeeze(-1), td["action_value"].gather(-1, executed[:, None]).squeeze(-1)
    )
    # DQNLoss trains on the executed (stored) action, not on the DQN's greedy one
    td["next"] = _policy_td().exclude("causal_state")
    td["next", "reward"] = torch.randn(16, 1)
    td["next", "done"] = torch.zeros(16, 1, dtype=torch.bool)
    td["next", "terminated"] = torch.zeros(16, 1, dtype=torch.bool)
    loss = DQNLoss(actor, action_space=spec, loss_function="l2", delay_value=False)
    loss.make_value_estimator(gamma=0.9)
    out = loss(td.clone())
    with torch.no_grad():
        q = actor(td.clone())["action_value"]
        q_next = actor(td["next"].clone())["action_value"].max(-1).values
        target = td["next", "reward"].squeeze(-1) + 0.9 * q_next
        pred = q.gather(-1, executed[:, None]).squeeze(-1)
    torch.testing.assert_close(out["loss"], ((pred - target) ** 2).mean(), rtol=1e-4, atol=1e-4)


def test_device_option():
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for dev in devices:
        gate = CBNGate("v2", eps_init=0.5, eps_end=0.5, seed=0, device=dev)
        p = [0.5] * A
        p[G] = 0.1
        gate.set_tables(tables_from(p))
        assert gate.tables.p_pos.device.type == dev
        td = batch(1000).to(dev)
        gate(td)
        assert td["action"].device.type == dev
        assert_rate(td["gate_vetoed"].cpu(), PCM)


def test_state_dict_of_tables_with_a_custom_schema_loads_into_a_fresh_gate():
    from torchrl_causal.schema import Variable, VariableSchema

    schema = VariableSchema((Variable("a", ("x", "y")), Variable("b", ("x", "y", "z"))))
    tables = RewardTables(torch.rand(4, 6), torch.ones(4, dtype=torch.bool), schema)
    fresh = CBNGate("pn")
    fresh.load_state_dict(CBNGate("pn", tables=tables).state_dict())
    assert fresh.tables.schema == schema
    assert torch.equal(fresh.tables.p_pos, tables.p_pos)
