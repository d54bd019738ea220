"""CBNGate with an action mask (``action_mask_key``), as TorchRL's EGreedyModule reads one.

No masked action is ever proposed, vetoed into or replaced by; the random
branches are uniform over the allowed actions; an all-True mask is bit for bit
the unmasked gate, which is itself pinned to the outputs of the gate before
masks existed. Seeds are fixed; statistical bounds as in ``test_gate.py``
(chi-square p > 1e-4).
"""

import math

import pytest
import torch
from scipy.stats import chisquare
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torchrl.data import Binary, Categorical, Composite, MultiCategorical, OneHot, Unbounded
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.transforms import ActionMask
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import QValueActor

from torchrl_causal.causal import CausalLearner
from torchrl_causal.causal.tables import RewardTables
from torchrl_causal.modules import CBNGate, ThesisQNet
from torchrl_causal.schema import DEFAULT_SCHEMA

A = 8
VARIANTS = ["p", "pn", "v2"]
EXPLORATION = [ExplorationType.RANDOM, ExplorationType.DETERMINISTIC]
CARDS = torch.tensor(DEFAULT_SCHEMA.cardinalities)
GOAL = DEFAULT_SCHEMA.index("goal_in_sight")
CENTER = DEFAULT_SCHEMA.index("depth_center")


# ---------------------------------------------------------------- helpers
def random_states(n, g):
    return (torch.rand(n, len(CARDS), generator=g) * CARDS).long()


def random_mask(n, n_actions, g, p_allowed=0.5):
    """Each action allowed with prob. ``p_allowed``; rows with none get one random action."""
    mask = torch.rand(n, n_actions, generator=g) < p_allowed
    empty = ~mask.any(-1)
    fill = torch.randint(0, n_actions, (n,), generator=g)
    mask[empty, fill[empty]] = True
    return mask


def spread_tables(g, n_actions=A, p_unknown=0.2):
    """Random state-dependent tables: P spread over [0, 1] so every branch fires often."""
    p = torch.rand(n_actions, DEFAULT_SCHEMA.n_states, generator=g) ** 2
    known = torch.rand(n_actions, generator=g) >= p_unknown
    known[0] = True
    return RewardTables(p, known)


def learned_tables(seed=0):
    """The real CausalLearner on synthetic transitions (action 7 never taken: unknown)."""
    g = torch.Generator().manual_seed(seed)
    n = 2400
    s0 = random_states(n, g)
    s1 = torch.where(torch.rand(n, 9, generator=g) < 0.7, s0, random_states(n, g))
    a = torch.randint(0, 7, (n,), generator=g)
    reward = torch.where(s1[:, GOAL] == 1, 50.0, -9.0)
    reward = torch.where((a == 0) & (s0[:, CENTER] == 0), torch.tensor(-1000.0), reward)
    learner = CausalLearner(min_rows=30)
    learner.add(s0, a, s1, reward)
    return learner.relearn()


def masked_td(q, mask, states):
    return TensorDict(action_value=q, action_mask=mask, causal_state=states, batch_size=q.shape[:-1])


def make_gate(variant, eps=0.3, pcm=0.7, thr=0.75, seed=0, **kw):
    return CBNGate(variant, pcm, thr, eps_init=eps, eps_end=eps, seed=seed, **kw)


def chi2_uniform(actions, allowed):
    """Chi-square p-value of ``actions`` against the uniform law on ``allowed``."""
    allowed = torch.as_tensor(allowed)
    counts = torch.bincount(actions, minlength=A).double()
    assert counts.sum() > 50 * len(allowed), "too few samples for a chi-square test"
    assert counts[~torch.isin(torch.arange(A), allowed)].sum() == 0, counts
    obs = counts[allowed]
    return chisquare(obs.numpy(), torch.full_like(obs, obs.sum() / len(allowed)).numpy()).pvalue


def assert_uniform_within_sets(actions, sets):
    """Each action is uniform over its own row's set of actions (bool ``[n, A]``).

    The rank of the action among its row's set must be uniform on {0..m-1}, for
    every set size m (chi-square per m with enough samples). Returns how many
    samples were tested.
    """
    assert sets.gather(-1, actions[:, None]).all(), "an action outside its set"
    rank = (sets.long().cumsum(-1) - 1).gather(-1, actions[:, None]).squeeze(-1)
    size = sets.sum(-1)
    tested = 0
    for m in range(2, sets.shape[-1] + 1):
        r = rank[size == m]
        if len(r) < 20 * m:
            continue
        counts = torch.bincount(r, minlength=m).double()
        pval = chisquare(counts.numpy(), torch.full((m,), len(r) / m, dtype=torch.float64).numpy()).pvalue
        assert pval > 1e-4, (m, counts)
        tested += len(r)
    return tested


# ---------------------------------------------------------------- no mask / all-True mask
def _random_case(g, variant):
    n_actions = int(torch.randint(2, 10, (1,), generator=g))
    p = torch.rand(n_actions, DEFAULT_SCHEMA.n_states, generator=g)
    known = torch.rand(n_actions, generator=g) < 0.8
    eps, pcm, thr = torch.rand(3, generator=g).tolist()
    n = 300
    q = torch.randn(n, n_actions, generator=g)
    states = random_states(n, g)
    return n_actions, RewardTables(p, known), (variant, pcm, thr, eps, eps), q, states


@pytest.mark.parametrize("expl", EXPLORATION)
@pytest.mark.parametrize("variant", VARIANTS)
def test_all_true_mask_is_bit_identical_to_no_mask(variant, expl):
    g = torch.Generator().manual_seed(VARIANTS.index(variant) + 10 * EXPLORATION.index(expl))
    for case in range(25):
        n_actions, tables, args, q, states = _random_case(g, variant)
        plain = CBNGate(*args, seed=case, tables=tables if case % 5 else None)
        masked = CBNGate(*args, seed=case, tables=tables if case % 5 else None, action_mask_key="action_mask")
        ones = torch.ones_like(q, dtype=torch.bool)
        with set_exploration_type(expl):
            for _ in range(2):  # the generators must also advance identically
                a = plain(TensorDict(action_value=q, causal_state=states, batch_size=[len(q)]))
                b = masked(masked_td(q, ones, states))
                for key in ["action", *plain.diagnostic_keys.values()]:
                    torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, equal_nan=True, msg=key)
        assert torch.equal(plain.generator.get_state(), masked.generator.get_state())


# Actions of the gate as it was before action masks (recorded from that code; every
# branch fires in these 40 elements): the unmasked path keeps its RNG stream and
# outputs bit for bit.
_GOLDEN = {
    ("p", "random"): [5, 3, 4, 2, 7, 1, 1, 2, 4, 2, 1, 0, 2, 2, 0, 6, 5, 4, 7, 5, 7, 0, 1, 4, 4, 2, 6, 3, 4, 0, 2, 7, 0, 2, 2, 2, 4, 3, 3, 0],
    ("p", "deterministic"): [5, 5, 4, 2, 7, 6, 6, 2, 6, 2, 1, 0, 3, 2, 0, 6, 5, 4, 3, 5, 7, 7, 5, 4, 4, 1, 6, 3, 3, 0, 7, 1, 2, 2, 2, 2, 4, 4, 3, 0],
    ("pn", "random"): [4, 3, 4, 2, 7, 1, 1, 2, 4, 2, 1, 0, 2, 2, 0, 6, 5, 0, 7, 5, 0, 0, 1, 2, 4, 2, 6, 3, 4, 0, 2, 7, 0, 2, 2, 2, 4, 3, 3, 0],
    ("pn", "deterministic"): [4, 1, 4, 2, 7, 6, 6, 2, 6, 2, 1, 0, 3, 2, 0, 6, 5, 0, 6, 5, 0, 7, 3, 2, 4, 1, 6, 3, 3, 0, 7, 5, 4, 2, 2, 2, 4, 4, 3, 0],
    ("v2", "random"): [4, 1, 4, 2, 7, 1, 1, 2, 4, 2, 1, 0, 3, 2, 0, 6, 5, 0, 6, 5, 0, 7, 3, 2, 4, 2, 6, 3, 4, 2, 2, 5, 4, 2, 2, 2, 4, 3, 3, 0],
    ("v2", "deterministic"): [4, 1, 4, 2, 7, 6, 6, 2, 6, 2, 1, 0, 3, 2, 0, 6, 5, 0, 6, 5, 0, 7, 3, 2, 4, 1, 6, 3, 3, 2, 7, 5, 4, 2, 2, 2, 4, 4, 3, 0],
}


def _golden_inputs():
    g = torch.Generator().manual_seed(2024)
    p = torch.rand(A, DEFAULT_SCHEMA.n_states, generator=g)
    known = torch.ones(A, dtype=torch.bool)
    known[6] = False
    q = torch.randn(40, A, generator=g)
    return RewardTables(p, known), q, random_states(40, g)


@pytest.mark.parametrize("expl", EXPLORATION)
@pytest.mark.parametrize("variant", VARIANTS)
def test_unmasked_outputs_match_the_gate_before_masks(variant, expl):
    tables, q, states = _golden_inputs()
    gate = CBNGate(variant, 0.7, 0.6, eps_init=0.3, eps_end=0.3, seed=5, tables=tables)
    with set_exploration_type(expl):
        td = gate(TensorDict(action_value=q, causal_state=states, batch_size=[40]))
    assert td["action"].tolist() == _GOLDEN[variant, str(expl).split(".")[-1].lower()]


# ---------------------------------------------------------------- random masks, every branch
@pytest.mark.parametrize("learned", [False, True], ids=["spread_tables", "causal_learner"])
@pytest.mark.parametrize("expl", EXPLORATION)
@pytest.mark.parametrize("variant", VARIANTS)
def test_random_masks_no_masked_action_ever(variant, expl, learned):
    g = torch.Generator().manual_seed(VARIANTS.index(variant) + 10 * EXPLORATION.index(expl) + 100 * learned)
    n = 6000
    tables = learned_tables() if learned else spread_tables(g)
    # thresholds at which both the veto (N > thr) and the replacement (P < thr, N <= thr)
    # fire often: the learned P cluster near 0.01-0.19 and 0.80-0.88; pcm = 0.9 to consult often
    thr = 0.85 if learned else 0.6
    gate = make_gate(variant, eps=0.3, pcm=0.9, thr=thr, seed=1, tables=tables, action_mask_key="action_mask")
    flags = {k: 0 for k in ("explored", "vetoed", "replaced", "kept_alone")}
    explored_draws, veto_draws = [], []
    for _ in range(3):
        q = torch.randn(n, A, generator=g)
        mask = random_mask(n, A, g, p_allowed=0.4)
        states = random_states(n, g)
        with set_exploration_type(expl):
            td = gate(masked_td(q, mask.clone(), states))
        action, proposal = td["action"], td["gate_dqn_action"]
        allowed_at = lambda a: mask.gather(-1, a[:, None]).squeeze(-1)  # noqa: E731
        # no masked action is ever output, nor proposed
        assert allowed_at(action).all() and allowed_at(proposal).all()
        # the greedy action is the argmax of Q over allowed actions
        greedy = q.masked_fill(~mask, -math.inf).argmax(-1)
        not_explored = ~td["gate_explored"]
        assert torch.equal(proposal[not_explored], greedy[not_explored])
        # vetoes land on another allowed action, never on the proposal
        vetoed = td["gate_vetoed"]
        assert (action[vetoed] != proposal[vetoed]).all()
        # a veto with nothing else allowed keeps the proposal and is not flagged
        alone = mask.sum(-1) == 1
        assert not vetoed[alone].any()
        # replacements take the best known allowed action
        p_pos, _, known = tables.lookup(states)
        eligible = known & mask
        best = p_pos.masked_fill(~eligible, -1.0).argmax(-1)
        replaced = td["gate_replaced"]
        assert torch.equal(action[replaced], best[replaced])
        assert allowed_at(best)[replaced].all() and known.gather(-1, best[:, None]).squeeze(-1)[replaced].all()
        # elements the CBN did not change keep the proposal
        unchanged = ~(vetoed | replaced)
        assert torch.equal(action[unchanged], proposal[unchanged])
        # the random branches are uniform over the allowed actions (resp. the allowed others)
        explored = td["gate_explored"]
        explored_draws.append((action[explored], mask[explored]))
        others = mask.scatter(-1, proposal[:, None], False)
        veto_draws.append((action[vetoed], others[vetoed]))
        flags["explored"] += int(explored.sum())
        flags["vetoed"] += int(vetoed.sum())
        flags["replaced"] += int(replaced.sum())
        flags["kept_alone"] += int((td["gate_consulted"] & alone).sum())
    # the branches the assertions are about actually happened
    assert (flags["explored"] > 0) == (expl == ExplorationType.RANDOM)
    assert (flags["vetoed"] > 100) == (variant != "p")
    assert (flags["replaced"] > 100) == (variant != "v2")
    assert flags["kept_alone"] > 0
    for draws in (explored_draws, veto_draws):
        actions, sets = (torch.cat(x) for x in zip(*draws))
        tested = assert_uniform_within_sets(actions, sets)
        # all but single-action sets and rare set sizes were checked
        assert tested >= 0.9 * int((sets.sum(-1) > 1).sum())


@pytest.mark.parametrize("variant", VARIANTS)
def test_epsilon_random_action_is_uniform_over_allowed(variant):
    # two row groups with different masks; tables set and the greedy action vetoed,
    # so the CBN is active, but explored elements are never changed by it
    g = torch.Generator().manual_seed(7)
    n = 24_000
    allowed = {0: [0, 2, 3, 6], 1: [1, 4, 5, 6, 7]}
    mask = torch.zeros(n, A, dtype=torch.bool)
    group = torch.arange(n) % 2
    for k, acts in allowed.items():
        mask[(group == k).nonzero(), torch.tensor(acts)] = True
    q = torch.randn(n, A, generator=g)
    p = torch.full((A,), 0.5)
    p[6] = 0.1  # vetoed when greedy
    tables = RewardTables(p[:, None].expand(A, DEFAULT_SCHEMA.n_states).clone(), torch.ones(A, dtype=torch.bool))
    gate = make_gate(variant, eps=0.5, seed=3, tables=tables, action_mask_key="action_mask")
    td = gate(masked_td(q, mask, torch.zeros(n, 9, dtype=torch.long)))
    explored = td["gate_explored"]
    for k, acts in allowed.items():
        sel = explored & (group == k)
        assert torch.equal(td["action"][sel], td["gate_dqn_action"][sel])
        assert chi2_uniform(td["action"][sel], acts) > 1e-4


@pytest.mark.parametrize("expl", EXPLORATION)
@pytest.mark.parametrize("variant", ["pn", "v2"])
def test_veto_redraw_is_uniform_over_other_allowed_actions(variant, expl):
    # allowed {0, 1, 3, 5}; Q's argmax 2 is masked, so the greedy action is 1 (next best)
    n = 24_000
    mask = torch.zeros(n, A, dtype=torch.bool)
    mask[:, [0, 1, 3, 5]] = True
    q = torch.zeros(n, A)
    q[:, 2], q[:, 1] = 2.0, 1.0
    p = torch.full((A,), 0.5)
    p[1] = 0.1  # N = 0.9 > 0.75 (and P < 0.75): vetoed
    p[2] = 0.1
    tables = RewardTables(p[:, None].expand(A, DEFAULT_SCHEMA.n_states).clone(), torch.ones(A, dtype=torch.bool))
    gate = make_gate(variant, eps=0.2, seed=4, tables=tables, action_mask_key="action_mask")
    with set_exploration_type(expl):
        td = gate(masked_td(q, mask, torch.zeros(n, 9, dtype=torch.long)))
    vetoed = td["gate_vetoed"]
    assert (td["gate_dqn_action"][vetoed] == 1).all()
    # pn consults only non-explored elements (eps = 0.2 under RANDOM); v2 consults first
    rate = 0.7 * (0.8 if variant == "pn" and expl == ExplorationType.RANDOM else 1.0)
    assert abs(vetoed.float().mean().item() - rate) < 0.02
    assert chi2_uniform(td["action"][vetoed], [0, 3, 5]) > 1e-4
    # nothing but allowed actions anywhere
    assert mask.gather(-1, td["action"][:, None]).all()


@pytest.mark.parametrize("variant", VARIANTS)
def test_only_the_proposal_allowed_is_kept(variant):
    n = 2000
    mask = torch.zeros(n, A, dtype=torch.bool)
    mask[:, 4] = True
    q = torch.randn(n, A, generator=torch.Generator().manual_seed(0))
    tables = RewardTables(torch.full((A, DEFAULT_SCHEMA.n_states), 0.05), torch.ones(A, dtype=torch.bool))
    gate = make_gate(variant, eps=0.5, pcm=1.0, seed=0, tables=tables, action_mask_key="action_mask")
    td = gate(masked_td(q, mask, torch.zeros(n, 9, dtype=torch.long)))
    assert (td["action"] == 4).all() and (td["gate_dqn_action"] == 4).all()
    assert not td["gate_vetoed"].any()
    if variant == "pn":
        # the veto judgement was made (N > thr), so Alg. 3's elif (replacement) is not entered
        assert td["gate_consulted"].any() and not td["gate_replaced"].any()


@pytest.mark.parametrize("variant", ["p", "pn"])
def test_replacement_picks_best_known_allowed_action(variant):
    n = 4000
    p = torch.full((A,), 0.3)
    p[2] = 0.5  # the greedy action: uncertain -> replaced (not vetoed: N = 0.5)
    p[5] = 0.95  # best, but masked
    p[7] = 0.99  # better still, allowed but unknown
    p[4] = 0.8  # best known allowed
    known = torch.ones(A, dtype=torch.bool)
    known[7] = False
    tables = RewardTables(p[:, None].expand(A, DEFAULT_SCHEMA.n_states).clone(), known)
    mask = torch.ones(n, A, dtype=torch.bool)
    mask[:, 5] = False
    mask[n // 2 :, 4] = False  # then the best known allowed action is the proposal 2 itself
    q = torch.zeros(n, A)
    q[:, 2] = 1.0
    gate = make_gate(variant, eps=0.0, seed=2, tables=tables, action_mask_key="action_mask")
    td = gate(masked_td(q, mask, torch.zeros(n, 9, dtype=torch.long)))
    replaced = td["gate_replaced"]
    assert abs(replaced.float().mean().item() - 0.7) < 0.03
    assert (td["action"][: n // 2][replaced[: n // 2]] == 4).all()
    # without 4: P = 0.5 of the proposal 2 beats 0.3 of the others -> replaced by itself
    assert replaced[n // 2 :].any()
    assert (td["action"][n // 2 :] == 2).all()


def test_greedy_respects_mask_and_eval_gate_off():
    g = torch.Generator().manual_seed(5)
    n = 3000
    q = torch.randn(n, A, generator=g)
    q[:10] = -math.inf  # degenerate rows: all Q = -inf -> first allowed action
    mask = random_mask(n, A, g)
    gate = make_gate("pn", seed=0, eval_gate=False, action_mask_key="action_mask",
                     tables=spread_tables(g))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = gate(masked_td(q, mask, random_states(n, g)))
    expected = q.masked_fill(~mask, -math.inf).argmax(-1)
    expected[:10] = mask[:10].long().argmax(-1)
    assert torch.equal(td["action"], expected)
    assert not td["gate_consulted"].any()


@pytest.mark.parametrize("shape", [(), (5,), (3, 4)])
def test_mask_batch_shapes_and_nested_key(shape):
    g = torch.Generator().manual_seed(1)
    q = torch.randn(*shape, A, generator=g)
    mask = random_mask(max(1, math.prod(shape)), A, g).reshape(*shape, A)
    td = TensorDict(action_value=q, causal_state=torch.zeros(*shape, 9, dtype=torch.long), batch_size=shape)
    td["obs", "mask"] = mask
    gate = make_gate("v2", eps=0.5, seed=0, action_mask_key=("obs", "mask"), tables=spread_tables(g))
    assert ("obs", "mask") in gate.in_keys
    gate(td)
    assert td["action"].shape == shape
    assert mask.gather(-1, td["action"].unsqueeze(-1)).all()


# ---------------------------------------------------------------- bad input
def test_missing_mask_key_raises_key_error():
    gate = make_gate("pn", action_mask_key=("obs", "legal"))
    td = TensorDict(action_value=torch.randn(6, A), causal_state=torch.zeros(6, 9, dtype=torch.long), batch_size=[6])
    with pytest.raises(KeyError, match="legal"):
        gate(td)


@pytest.mark.parametrize(
    "mask, shape, match",
    [
        (torch.ones(6, A + 1, dtype=torch.bool), (6,), r"'m'.*\(6, 9\).*\(6, 8\)"),
        (torch.ones(6, 2, A, dtype=torch.bool), (6,), r"'m'.*\(6, 2, 8\).*\(6, 8\)"),
        (torch.ones(6, 3, A, dtype=torch.bool), (6, 2), r"'m'.*\(6, 3, 8\).*\(6, 2, 8\)"),
        (torch.ones(6, A, dtype=torch.uint8), (6,), r"'m'.*bool.*uint8"),
        (torch.ones(6, A, dtype=torch.long), (6,), r"'m'.*bool.*int64"),
        (
            torch.ones(6, A, dtype=torch.bool).index_fill(0, torch.tensor([3]), False),
            (6,),
            r"'m'.*\(6, 8\).*no action.*\(3,\)",
        ),
    ],
    ids=["last_dim", "extra_dim", "batch_shape", "uint8", "long", "empty_row"],
)
def test_bad_mask_raises_value_error(mask, shape, match):
    gate = make_gate("pn", action_mask_key="m", tables=spread_tables(torch.Generator().manual_seed(0)))
    q = torch.randn(*shape, A)
    td = TensorDict(action_value=q, causal_state=torch.zeros(*shape, 9, dtype=torch.long), batch_size=shape[:1])
    td.set("m", mask)
    with pytest.raises(ValueError, match=match):
        gate(td)


# ---------------------------------------------------------------- composition
@pytest.mark.parametrize("spec", [Categorical(A), OneHot(A)])
def test_qvalue_actor_with_mask_then_gate(spec):
    # as the README: TensorDictSequential(QValueActor(ThesisQNet), CBNGate); both read the mask
    torch.manual_seed(0)
    n = 64
    g = torch.Generator().manual_seed(0)
    actor = QValueActor(ThesisQNet(A, n_features=9), in_keys=["pixels", "causal_state"], spec=spec,
                        action_mask_key="action_mask")
    gate = CBNGate("pn", prob_causal_model=1.0, eps_init=0.3, eps_end=0.3, seed=0, action_mask_key="action_mask",
                   tables=RewardTables(torch.full((A, DEFAULT_SCHEMA.n_states), 0.05), torch.ones(A, dtype=torch.bool)))
    policy = TensorDictSequential(actor, gate)
    mask = random_mask(n, A, g)
    td = TensorDict(
        pixels=torch.randint(0, 256, (n, 84, 84, 3), dtype=torch.uint8, generator=g),
        causal_state=random_states(n, g),
        action_mask=mask,
        batch_size=[n],
    )
    with torch.no_grad():
        policy(td)
    executed = td["action"] if isinstance(spec, Categorical) else td["action"].long().argmax(-1)
    if isinstance(spec, OneHot):
        assert td["action"].shape == (n, A) and td["action"].sum(-1).eq(1).all()
    assert mask.gather(-1, executed[:, None]).all()
    # the actor's greedy action (over allowed actions) is the gate's greedy proposal
    greedy = td["action_value"].argmax(-1)
    assert mask.gather(-1, greedy[:, None]).all()
    assert torch.equal(td["gate_dqn_action"][~td["gate_explored"]], greedy[~td["gate_explored"]])
    assert td["gate_vetoed"].any() and (executed[td["gate_vetoed"]] != td["gate_dqn_action"][td["gate_vetoed"]]).all()
    torch.testing.assert_close(
        td["chosen_action_value"].squeeze(-1), td["action_value"].gather(-1, executed[:, None]).squeeze(-1)
    )


class _MaskedEnv(EnvBase):
    """A new random legal-action mask every step; counts steps taken with an illegal action."""

    def __init__(self, n_actions=A, seed=0):
        super().__init__(batch_size=[])
        self.n_actions = n_actions
        self.action_spec = Categorical(n_actions)
        self.state_spec = Composite(action_mask=Binary(n_actions, dtype=torch.bool))
        self.observation_spec = Composite(
            obs=Unbounded(4),
            causal_state=MultiCategorical(DEFAULT_SCHEMA.cardinalities, dtype=torch.int64),
        )
        self.reward_spec = Unbounded(1)
        self.rng = torch.Generator().manual_seed(seed)
        self.illegal = 0
        self.steps = 0

    def _obs(self):
        mask = random_mask(1, self.n_actions, self.rng, p_allowed=0.3)[0]
        return TensorDict(
            obs=torch.randn(4, generator=self.rng),
            causal_state=random_states(1, self.rng)[0],
            action_mask=mask,
        )

    def _reset(self, tensordict=None):
        return self._obs()

    def _step(self, data):
        self.steps += 1
        self.illegal += int(not data["action_mask"][data["action"]])
        td = self._obs()
        td.set("reward", torch.randn(1, generator=self.rng))
        td.set("done", torch.tensor([self.steps % 25 == 0]))
        return td

    def _set_seed(self, seed):
        return seed


def test_collector_rollout_on_masked_env():
    from torchrl.collectors import Collector

    env = TransformedEnv(_MaskedEnv(), ActionMask())
    actor = QValueActor(torch.nn.Linear(4, A), in_keys=["obs"], spec=Categorical(A), action_mask_key="action_mask")
    gate = CBNGate("v2", prob_causal_model=0.9, eps_init=0.5, eps_end=0.5, seed=0, action_mask_key="action_mask",
                   tables=spread_tables(torch.Generator().manual_seed(3)))
    policy = TensorDictSequential(actor, gate)
    with torch.no_grad():
        roll = env.rollout(100, policy, break_when_any_done=False)
    collector = Collector(env, policy, frames_per_batch=100, total_frames=200, auto_register_policy_transforms=False)
    try:
        batches = [b.clone() for b in collector]
    finally:
        collector.shutdown()
    base = env.base_env
    assert base.steps == 300 and base.illegal == 0
    for data in [roll, *batches]:
        assert data["action_mask"].gather(-1, data["action"][..., None]).all()
    vetoed = sum(int(d["gate_vetoed"].sum()) for d in [roll, *batches])
    assert vetoed > 0
