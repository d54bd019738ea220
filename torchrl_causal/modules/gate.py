"""The CBN gate: thesis Algorithm 3 (variants P and PN) and Algorithm 4 (V2).

The gate sits right after :class:`torchrl.modules.QValueActor` and *replaces*
:class:`torchrl.modules.EGreedyModule` (it carries the same epsilon schedule:
``eps_init``, ``eps_end``, ``annealing_num_steps`` and :meth:`CBNGate.step`).
It must own the epsilon draw because both algorithms interleave it with the
CBN consultation:

* Algorithm 3 takes the epsilon-random branch *before* the CBN and never
  consults the CBN about a random action. A gate placed after an
  ``EGreedyModule`` cannot tell a random action from a greedy one (a random
  draw may equal the greedy action), so it would consult on random actions.
* Algorithm 4 draws ``rand < ProbCausalModel`` *first* and only falls back to
  epsilon-greedy when it does not consult; an ``EGreedyModule`` placed before
  the gate would have already randomised actions the gate must see greedy.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_causal.causal.tables import RewardTables
    >>> from torchrl_causal.modules import CBNGate
    >>> gate = CBNGate("pn", eps_init=0.0, eps_end=0.0, seed=0)
    >>> p_pos = torch.full((8, 1728), 0.9)
    >>> p_pos[2] = 0.05  # action 2 ("left") almost surely leads to a negative reward
    >>> gate.set_tables(RewardTables(p_pos, torch.ones(8, dtype=torch.bool)))
    >>> q = torch.zeros(1000, 8)
    >>> q[:, 2] = 1.0  # the DQN prefers "left"
    >>> td = TensorDict(action_value=q, causal_state=torch.zeros(1000, 9, dtype=torch.long),
    ...                 batch_size=[1000])
    >>> td = gate(td)
    >>> 0.6 < td["gate_vetoed"].float().mean().item() < 0.8  # ProbCausalModel = 0.7
    True
    >>> bool((td["action"][td["gate_vetoed"]] != 2).all())
    True
"""

from __future__ import annotations

import math

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, exploration_type

from torchrl_causal.causal.tables import RewardTables

__all__ = ["CBNGate", "GATE_VARIANTS"]

#: Accepted values of ``CBNGate(variant=...)``.
GATE_VARIANTS: tuple[str, ...] = ("p", "pn", "v2")

_DIAGNOSTICS = ("explored", "consulted", "vetoed", "replaced", "dqn_action", "p_pos", "p_neg")


def _check_prob(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a probability in [0, 1], got {value!r}") from None
    if not (0.0 <= v <= 1.0) or math.isnan(v):
        raise ValueError(f"{name} must be a probability in [0, 1], got {value!r}")
    return v


def _concrete(device) -> torch.device:
    """``"cuda"`` -> ``cuda:<current>`` (tensors always carry an index; a bare name does not)."""
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        return torch.device("cuda", torch.cuda.current_device())
    return device


def _kth_allowed(mask: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """Index of the ``k``-th (0-based) True entry of each row of ``mask`` (``k < row sum``).

    The cumulative count of True entries is ``<= k`` exactly at the positions before
    the ``k``-th True entry, so counting them gives its index (vectorised, no loops).
    """
    return (mask.long().cumsum(-1) <= k.unsqueeze(-1)).sum(-1)


class CBNGate(TensorDictModuleBase):
    """Epsilon-greedy action selection gated by per-action causal reward models.

    Reads the Q-values (``action_value``) and the discretised state
    (``causal_state``), draws the epsilon-greedy and the CBN branches exactly as
    the thesis pseudo-code, and writes the *executed* action to ``action`` (so
    the replay buffer stores it and :class:`~torchrl.objectives.DQNLoss` trains
    on it). Everything is vectorised over any batch shape; one uniform draw per
    branch per batch element is made on every call, whatever the branch
    outcomes, so a seeded gate is reproducible.

    With ``P = P(positive reward | s, a)`` and ``N = 1 - P`` from the compiled
    tables, ``pcm = prob_causal_model`` and ``thr = threshold``:

    * ``"pn"`` (Alg. 3): with prob. eps a uniform random action (CBN not
      consulted). Otherwise the greedy action ``a``; then with prob. ``pcm``
      consult: if ``N(a) > thr`` veto ``a`` and draw uniformly among the other
      actions; else if ``P(a) < thr`` replace ``a`` by ``argmax_a' P(a')``.
    * ``"p"`` (Alg. 3, positive branch only): as ``"pn"`` without the veto.
    * ``"v2"`` (Alg. 4): with prob. ``pcm`` take the greedy action ``a`` and
      consult: if ``P(a) < thr`` and ``N(a) > thr``, draw uniformly among the
      other actions. Otherwise plain epsilon-greedy.

    Abstaining: while no tables are set (``set_tables(None)``, the state before
    the first relearn) or for an action whose model is unknown
    (``known=False``), the CBN is not consulted. In ``"p"``/``"pn"`` the action
    stays the epsilon-greedy one; in ``"v2"`` the element falls through to the
    epsilon-greedy branch, so an abstaining gate of any variant behaves exactly
    like :class:`~torchrl.modules.EGreedyModule`. ``argmax_a' P(a')`` only
    ranges over known actions; ties go to the lowest index (the thesis's
    ``MaxIndex``).

    Action masks: with ``action_mask_key`` set, a bool mask ``[*batch, n_actions]``
    (True = allowed, as written by :class:`~torchrl.envs.transforms.ActionMask`)
    is read from that key and no masked action is ever proposed, vetoed into or
    replaced by: the greedy action is the argmax of Q over allowed actions, the
    epsilon-random action and the veto's redraw are uniform over allowed actions
    (the redraw over those other than the proposal; when the proposal is the
    only allowed action it is kept and ``gate_vetoed`` stays False), and
    ``argmax_a' P(a')`` ranges over known allowed actions. The same four draws
    per element are made, and an all-True mask gives exactly the actions of no
    mask.

    Exploration mode: under ``ExplorationType.RANDOM`` (collectors' default)
    epsilon is used; under any other exploration type epsilon is 0 and the CBN
    still applies when ``eval_gate=True`` (default), or the greedy action is
    passed through untouched when ``eval_gate=False``.

    Args:
        variant: ``"p"``, ``"pn"`` (Algorithm 3) or ``"v2"`` (Algorithm 4).
        prob_causal_model: ProbCausalModel, probability of consulting the CBN
            (0.7 in the thesis).
        threshold: ThresholdProb (0.75 in the thesis).
        eps_init: initial epsilon (as :class:`~torchrl.modules.EGreedyModule`).
        eps_end: final epsilon.
        annealing_num_steps: frames over which epsilon decays linearly from
            ``eps_init`` to ``eps_end``; advance it with :meth:`step`.

    Keyword Args:
        tables: initial :class:`~torchrl_causal.causal.tables.RewardTables`, or
            ``None`` to abstain until :meth:`set_tables` is called.
        n_actions: number of actions; inferred from ``action_value`` if ``None``
            (then checked against the tables).
        action_key: where the executed action is written (``"action"``).
        action_value_key: where the Q-values are read (``"action_value"``).
        causal_state_key: where the discretised state is read (``"causal_state"``).
        action_mask_key: where a bool action mask ``[*batch, n_actions]`` (True =
            allowed) is read, as :class:`~torchrl.modules.EGreedyModule` and
            :class:`~torchrl.modules.QValueActor` read theirs; ``None`` (default)
            for no mask. When set, the key must be present in every input
            (``KeyError`` otherwise), the mask must be bool with the shape of
            ``action_value``, and every row must allow at least one action
            (``ValueError`` otherwise).
        chosen_action_value_key: updated to ``Q(s, executed action)`` when present
            in the input (``QValueActor`` writes it for the greedy action).
        action_space: ``"categorical"`` (integer actions), ``"one_hot"``, or
            ``None`` to follow the format of the incoming ``action`` entry
            (integer if there is none).
        diagnostics_prefix: prefix of the diagnostic keys (``"gate_"``), or
            ``None`` to write no diagnostics.
        eval_gate: whether the CBN applies outside ``ExplorationType.RANDOM``.
        seed: seed of the gate's own :class:`torch.Generator`; ``None`` uses the
            global RNG (like ``EGreedyModule``) unless ``generator`` is given.
        generator: an explicit generator (on ``device``) to draw from.
        device: device of the buffers, generator and tables.

    Diagnostic keys (shape = batch shape of ``action_value`` without the action
    dim), with the default prefix:

    * ``gate_explored`` (bool): the epsilon-random branch produced the action.
    * ``gate_consulted`` (bool): the CBN was consulted (tables present, the
      action's model known, and the ``prob_causal_model`` draw succeeded).
    * ``gate_vetoed`` (bool): the veto fired and the action was redrawn
      among the others (the allowed others, with an action mask).
    * ``gate_replaced`` (bool): Alg. 3's positive branch fired and the action
      was set to ``argmax P`` (may equal the DQN's action when it is already
      the best).
    * ``gate_dqn_action`` (int64): the action the DQN proposed before the CBN
      (the epsilon-greedy action; in V2's consult branch the greedy one).
    * ``gate_p_pos`` / ``gate_p_neg`` (float32): P(positive / negative reward
      | s, ``gate_dqn_action``); NaN where no model was available.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictSequential
        >>> from torchrl.data import Categorical
        >>> from torchrl.modules import QValueActor
        >>> from torchrl_causal.modules import CBNGate, ThesisQNet
        >>> actor = QValueActor(ThesisQNet(8), in_keys=["pixels"], spec=Categorical(8))
        >>> gate = CBNGate("v2", eps_init=1.0, eps_end=0.05, annealing_num_steps=1000, seed=0)
        >>> policy = TensorDictSequential(actor, gate)
        >>> td = TensorDict(pixels=torch.zeros(4, 84, 84, 3, dtype=torch.uint8),
        ...                 causal_state=torch.zeros(4, 9, dtype=torch.long), batch_size=[4])
        >>> policy(td)["action"].shape
        torch.Size([4])
        >>> gate.step(500); round(gate.eps.item(), 3)
        0.525

        With an action mask, masked actions are never taken, whatever the branch:

        >>> from torchrl_causal.causal.tables import RewardTables
        >>> p_pos = torch.full((8, 1728), 0.9)
        >>> p_pos[2] = 0.05  # the DQN's favourite action 2 is vetoed...
        >>> gate = CBNGate("pn", eps_init=0.5, eps_end=0.5, seed=0, action_mask_key="action_mask",
        ...                tables=RewardTables(p_pos, torch.ones(8, dtype=torch.bool)))
        >>> q = torch.zeros(1000, 8)
        >>> q[:, 2] = 1.0
        >>> mask = torch.zeros(1000, 8, dtype=torch.bool)
        >>> mask[:, [2, 5, 6]] = True  # ...into 5 or 6, the only other allowed actions
        >>> td = gate(TensorDict(action_value=q, action_mask=mask,
        ...                      causal_state=torch.zeros(1000, 9, dtype=torch.long), batch_size=[1000]))
        >>> sorted(td["action"].unique().tolist())
        [2, 5, 6]
        >>> sorted(td["action"][td["gate_vetoed"]].unique().tolist())
        [5, 6]
    """

    def __init__(
        self,
        variant: str = "pn",
        prob_causal_model: float = 0.7,
        threshold: float = 0.75,
        eps_init: float = 1.0,
        eps_end: float = 0.1,
        annealing_num_steps: int = 1000,
        *,
        tables: RewardTables | None = None,
        n_actions: int | None = None,
        action_key: NestedKey = "action",
        action_value_key: NestedKey = "action_value",
        causal_state_key: NestedKey = "causal_state",
        action_mask_key: NestedKey | None = None,
        chosen_action_value_key: NestedKey | None = "chosen_action_value",
        action_space: str | None = None,
        diagnostics_prefix: str | None = "gate_",
        eval_gate: bool = True,
        seed: int | None = None,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
    ):
        if not isinstance(variant, str) or variant.lower() not in GATE_VARIANTS:
            raise ValueError(f"variant must be one of {GATE_VARIANTS}, got {variant!r}")
        prob_causal_model = _check_prob("prob_causal_model", prob_causal_model)
        threshold = _check_prob("threshold", threshold)
        eps_init = _check_prob("eps_init", eps_init)
        eps_end = _check_prob("eps_end", eps_end)
        if eps_end > eps_init:
            raise ValueError(
                f"eps_end must not exceed eps_init, got eps_init={eps_init}, eps_end={eps_end}"
            )
        if isinstance(annealing_num_steps, bool) or not isinstance(annealing_num_steps, int) or annealing_num_steps < 1:
            raise ValueError(
                f"annealing_num_steps must be a positive int, got {annealing_num_steps!r}"
            )
        if n_actions is not None and (not isinstance(n_actions, int) or n_actions < 2):
            raise ValueError(f"n_actions must be an int >= 2, got {n_actions!r}")
        if action_space not in (None, "categorical", "one_hot"):
            raise ValueError(
                f"action_space must be 'categorical', 'one_hot' or None, got {action_space!r}"
            )
        if seed is not None and generator is not None:
            raise ValueError("pass either seed or generator, not both")
        super().__init__()
        self.variant = variant.lower()
        self.prob_causal_model = prob_causal_model
        self.threshold = threshold
        self.annealing_num_steps = annealing_num_steps
        self.n_actions = n_actions
        self.action_key = action_key
        self.action_value_key = action_value_key
        self.causal_state_key = causal_state_key
        self.action_mask_key = action_mask_key
        self.chosen_action_value_key = chosen_action_value_key
        self.action_space = action_space
        self.eval_gate = bool(eval_gate)
        self.diagnostics_prefix = diagnostics_prefix
        self.diagnostic_keys = (
            {name: f"{diagnostics_prefix}{name}" for name in _DIAGNOSTICS}
            if diagnostics_prefix is not None
            else {}
        )
        self.in_keys = [action_value_key, causal_state_key]
        if action_mask_key is not None:
            self.in_keys.append(action_mask_key)
        self.out_keys = [action_key, *self.diagnostic_keys.values()]
        device = _concrete(device) if device is not None else None
        self.register_buffer("eps_init", torch.as_tensor(eps_init, dtype=torch.float32, device=device))
        self.register_buffer("eps_end", torch.as_tensor(eps_end, dtype=torch.float32, device=device))
        self.register_buffer("eps", torch.as_tensor(eps_init, dtype=torch.float32, device=device))
        if seed is not None:
            generator = torch.Generator(device=device or "cpu")
            generator.manual_seed(int(seed))
        self.generator = generator
        self._tables: RewardTables | None = None
        self.set_tables(tables)

    # ------------------------------------------------------------------ schedule
    @property
    def device(self) -> torch.device:
        return self.eps.device

    def step(self, frames: int = 1) -> None:
        """Advance the epsilon schedule by ``frames`` frames.

        Same linear schedule as :meth:`torchrl.modules.EGreedyModule.step`
        (computed in closed form instead of one update per frame).
        """
        if frames < 0:
            raise ValueError(f"frames must be >= 0, got {frames!r}")
        decay = (self.eps_init - self.eps_end) * (frames / self.annealing_num_steps)
        self.eps.data.copy_(torch.maximum(self.eps_end, self.eps - decay))

    # ------------------------------------------------------------------ tables
    @property
    def tables(self) -> RewardTables | None:
        """The compiled reward tables in use (``None``: the gate abstains)."""
        return self._tables

    def set_tables(self, tables: RewardTables | None) -> None:
        """Swap in new compiled tables (atomic: one reference assignment).

        Args:
            tables: :class:`~torchrl_causal.causal.tables.RewardTables`, or
                ``None`` to abstain.
        """
        if tables is not None:
            if not isinstance(tables, RewardTables):
                raise ValueError(
                    f"tables must be a RewardTables or None, got {type(tables).__name__}"
                )
            if self.n_actions is not None and tables.n_actions != self.n_actions:
                raise ValueError(
                    f"tables have {tables.n_actions} actions, the gate has n_actions={self.n_actions}"
                )
            if tables.p_pos.device != self.device:
                tables = tables.to(self.device)
        self._tables = tables

    # ------------------------------------------------------------------ state
    def get_extra_state(self) -> dict:
        return {
            "tables": None if self._tables is None else self._tables.state_dict(),
            "generator": None if self.generator is None else self.generator.get_state(),
        }

    def set_extra_state(self, state: dict) -> None:
        tables = state.get("tables")
        if tables is not None:
            # the schema of the tables in use, else the one stored with the tables
            schema = self._tables.schema if self._tables is not None else None
            tables = RewardTables.from_state_dict(tables, schema)
        self.set_tables(tables)
        if state.get("generator") is not None and self.generator is not None:
            self.generator.set_state(state["generator"])

    # ------------------------------------------------------------------ forward
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        q = tensordict.get(self.action_value_key)
        device = q.device
        if self.generator is not None and _concrete(self.generator.device) != device:
            raise RuntimeError(
                f"action_value is on {device} but the gate's generator is on "
                f"{self.generator.device}: build the gate with device={device}"
            )
        n_actions = q.shape[-1]
        if self.n_actions is not None and n_actions != self.n_actions:
            raise ValueError(
                f"action_value has {n_actions} actions, the gate has n_actions={self.n_actions}"
            )
        shape = q.shape[:-1]
        mask = self._get_mask(tensordict, q)
        expl = exploration_type()
        random_mode = expl in (ExplorationType.RANDOM, None)
        if mask is None:
            greedy = q.argmax(-1)
        else:
            low = -math.inf if q.is_floating_point() else torch.iinfo(q.dtype).min
            greedy = q.masked_fill(~mask, low).argmax(-1)
            # rows whose allowed Q-values all equal the fill value: the first allowed action
            bad = ~mask.gather(-1, greedy.unsqueeze(-1)).squeeze(-1)
            greedy = torch.where(bad, mask.long().argmax(-1), greedy)
        tables = self._tables  # read once: a concurrent set_tables cannot tear a call
        use_cbn = random_mode or self.eval_gate
        eps = self.eps.to(device) if random_mode else torch.zeros((), device=device)

        # One draw of each kind per element on every call (reproducible streams):
        # u_eps, u_cbn uniform in [0, 1); r_any uniform in {0..A-1}; r_other in {0..A-2}.
        # With a mask, r_any is uniform over the allowed actions (the k-th allowed one,
        # k = floor(u * n_allowed)); the veto's redraw is made from u[3] below. With an
        # all-True mask both reduce to the unmasked draws bit for bit.
        u = torch.rand((4, *shape), generator=self.generator, device=device)
        u_eps, u_cbn = u[0], u[1]
        if mask is None:
            r_any = (u[2] * n_actions).long().clamp_max_(n_actions - 1)
            r_other = (u[3] * (n_actions - 1)).long().clamp_max_(n_actions - 2)
        else:
            n_allowed = mask.sum(-1)
            r_any = _kth_allowed(mask, torch.minimum((u[2] * n_allowed).long(), n_allowed - 1))

        if tables is not None and use_cbn:
            if tables.n_actions != n_actions:
                raise ValueError(
                    f"tables have {tables.n_actions} actions, action_value has {n_actions}"
                )
            p_pos_all, _, known_all = tables.lookup(
                tensordict.get(self.causal_state_key).to(device)
            )
        else:
            p_pos_all = known_all = None

        false = torch.zeros(shape, dtype=torch.bool, device=device)
        explored = u_eps < eps
        consulted = vetoed = replaced = false
        # proposal, greedy and r_any are allowed actions; so is every action set below
        if self.variant == "v2" and known_all is not None:
            # Alg. 4 decides to consult (on the greedy action) before epsilon-greedy
            ok_greedy = known_all.gather(-1, greedy.unsqueeze(-1)).squeeze(-1)
            consulted = (u_cbn < self.prob_causal_model) & ok_greedy
            explored = explored & ~consulted
        proposal = torch.where(explored, r_any, greedy)
        action = proposal
        pp = ok = None
        if known_all is not None:
            pp = p_pos_all.gather(-1, proposal.unsqueeze(-1)).squeeze(-1)
            ok = known_all.gather(-1, proposal.unsqueeze(-1)).squeeze(-1)
            if self.variant == "v2":
                # P(a) < thr and N(a) = 1 - P(a) > thr
                vetoed = consulted & (pp < self.threshold) & ((1.0 - pp) > self.threshold)
            else:
                # Alg. 3 consults only about a non-random action
                consulted = ~explored & (u_cbn < self.prob_causal_model) & ok
                if self.variant == "pn":
                    vetoed = consulted & ((1.0 - pp) > self.threshold)
                    replaced = consulted & ~vetoed & (pp < self.threshold)
                else:
                    replaced = consulted & (pp < self.threshold)
            if self.variant != "p":
                if mask is None:
                    other = r_other + (r_other >= proposal).long()
                else:
                    # uniform among the allowed actions other than the proposal (itself
                    # allowed); with none, the proposal stands and is not flagged vetoed
                    others = mask.clone()
                    others.scatter_(-1, proposal.unsqueeze(-1), False)
                    n_others = n_allowed - 1
                    k = torch.minimum((u[3] * n_others).long(), n_others - 1).clamp_min_(0)
                    other = _kth_allowed(others, k)
                    vetoed = vetoed & (n_others > 0)
                action = torch.where(vetoed, other, action)
            if self.variant != "v2":
                # a replaced proposal is known (consulted) and allowed, so the argmax
                # always lands on a known allowed action
                eligible = known_all if mask is None else known_all & mask
                best = p_pos_all.masked_fill(~eligible, -1.0).argmax(-1)
                action = torch.where(replaced, best, action)

        self._write_action(tensordict, action, n_actions)
        cav = self.chosen_action_value_key
        old = tensordict.get(cav, None) if cav is not None else None
        if old is not None:
            chosen = q.gather(-1, action.unsqueeze(-1)).squeeze(-1)
            tensordict.set(cav, chosen.reshape(old.shape).to(old.dtype))
        if self.diagnostic_keys:
            if pp is not None:
                p_pos = torch.where(ok, pp.float(), float("nan"))
                p_neg = 1.0 - p_pos
            else:
                p_pos = torch.full(shape, float("nan"), device=device)
                p_neg = p_pos.clone()
            k = self.diagnostic_keys
            tensordict.set(k["explored"], explored)
            tensordict.set(k["consulted"], consulted)
            tensordict.set(k["vetoed"], vetoed)
            tensordict.set(k["replaced"], replaced)
            tensordict.set(k["dqn_action"], proposal)
            tensordict.set(k["p_pos"], p_pos)
            tensordict.set(k["p_neg"], p_neg)
        return tensordict

    def _get_mask(self, tensordict: TensorDictBase, q: torch.Tensor) -> torch.Tensor | None:
        key = self.action_mask_key
        if key is None:
            return None
        mask = tensordict.get(key, None)
        if mask is None:
            raise KeyError(
                f"action_mask_key {key!r} not found in the input tensordict "
                f"(keys: {list(tensordict.keys(include_nested=True, leaves_only=True))})"
            )
        if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
            raise ValueError(
                f"the action mask {key!r} must be a bool tensor (True = allowed), "
                f"got {getattr(mask, 'dtype', type(mask).__name__)}"
            )
        if mask.shape != q.shape:
            raise ValueError(
                f"the action mask {key!r} has shape {tuple(mask.shape)}, expected the shape of "
                f"{self.action_value_key!r}: {tuple(q.shape)} ([*batch, n_actions])"
            )
        mask = mask.to(q.device)
        empty = ~mask.any(-1)
        if empty.any():
            rows = empty.nonzero().tolist()
            raise ValueError(
                f"the action mask {key!r} (shape {tuple(mask.shape)}) allows no action in "
                f"{len(rows)} row(s), e.g. at batch index {tuple(rows[0])}"
            )
        return mask

    def _write_action(self, tensordict: TensorDictBase, action: torch.Tensor, n_actions: int):
        space = self.action_space
        old = tensordict.get(self.action_key, None)
        if space is None:
            space = (
                "one_hot"
                if old is not None and old.shape[-1:] == (n_actions,) and old.shape[:-1] == action.shape
                else "categorical"
            )
        if space == "one_hot":
            dtype = old.dtype if old is not None else torch.bool
            out = torch.nn.functional.one_hot(action, n_actions).to(dtype)
        else:
            out = action if old is None else action.reshape(old.shape).to(old.dtype)
        tensordict.set(self.action_key, out)

    def extra_repr(self) -> str:
        return (
            f"variant={self.variant!r}, prob_causal_model={self.prob_causal_model}, "
            f"threshold={self.threshold}, eps={self.eps.item():.4f}, "
            f"tables={'set' if self._tables is not None else 'None'}"
            + (f", action_mask_key={self.action_mask_key!r}" if self.action_mask_key is not None else "")
        )
