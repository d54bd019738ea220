"""Parameters and compiled inference of a per-action CBN (thesis Alg. 2, lines 11-13).

After the structure search, :func:`fit_cbn` estimates the conditional
probability tables (CPTs) of every node with a Dirichlet prior: each cell of a
CPT gets ``prior`` pseudo counts (default ``1.0``, i.e. Laplace / K2), so a
parent configuration never seen in the data gives a uniform distribution
instead of a division by zero, and a single sample never gives probability 1.
This is pgmpy's ``DiscreteBayesianEstimator(prior_type="dirichlet",
pseudo_counts=prior)``.

The gate asks P(reward | state at t). :meth:`CBN.reward_table` answers it for
every joint state at once: the nodes that matter are the reward, its Markov
blanket (with time tiers the reward has no children, so its blanket is its
parents) and, for the blanket's unobserved ``t+1`` nodes, their own parents --
i.e. the ancestors of ``reward``; every other node is barren and drops out.
The ancestral CPTs are contracted with one :func:`numpy.einsum` (summing out
the ``t+1`` nodes) into a ``[n_states]`` vector indexed like
:meth:`~torchrl_causal.schema.VariableSchema.state_index`. The result equals
pgmpy's :class:`~pgmpy.inference.VariableElimination` on the full network
(tested on every state). :func:`compile_tables` stacks the vectors of all actions
into :class:`~torchrl_causal.causal.tables.RewardTables` for batched lookup.

Example:
    >>> import numpy as np
    >>> from torchrl_causal.causal.inference import fit_cbn
    >>> rng = np.random.default_rng(0)
    >>> data = rng.integers(0, 2, (100, 19))
    >>> cbn = fit_cbn([("goal_in_sight_t", "goal_in_sight_t1"), ("goal_in_sight_t1", "reward")], data)
    >>> cbn.markov_blanket()
    ['goal_in_sight_t1']
    >>> cbn.reward_table().shape
    (1728,)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np
import torch

from torchrl_causal.causal.tables import RewardTables
from torchrl_causal.schema import DEFAULT_SCHEMA, REWARD_NODE, T_SUFFIX, VariableSchema

__all__ = ["CBN", "fit_cbn", "random_cbn", "markov_blanket", "compile_tables"]


def markov_blanket(edges: Iterable[tuple[str, str]], node: str = REWARD_NODE) -> list[str]:
    """Parents, children and the children's other parents of ``node``.

    Example:
        >>> markov_blanket([("a", "reward"), ("reward", "c"), ("b", "c")])
        ['a', 'b', 'c']
    """
    edges = list(edges)
    parents = {u for u, v in edges if v == node}
    children = {v for u, v in edges if u == node}
    co = {u for u, v in edges if v in children and u != node}
    return sorted(parents | children | co)


def _ancestors(edges, node) -> set:
    par: dict = {}
    for u, v in edges:
        par.setdefault(v, []).append(u)
    out, stack = set(), [node]
    while stack:
        for p in par.get(stack.pop(), ()):
            if p not in out:
                out.add(p)
                stack.append(p)
    return out


@dataclass
class CBN:
    """A per-action causal Bayesian network: structure plus CPTs.

    Attributes:
        edges: ``(source, target)`` node-name pairs.
        cpts: ``{node: array [card(node), prod(card(parents))]}`` in pgmpy's
            ``TabularCPD`` layout (parent configurations in C order of ``parents[node]``).
        parents: ``{node: tuple of parent names}``.
        schema: the variable schema.
        n_rows: number of transitions the CPTs were fitted on.
        known: False when the data was too little or degenerate (the gate abstains).
        prior: Dirichlet pseudo count used for the CPTs.

    Example:
        >>> cbn = CBN.uniform([("altitude_t", "altitude_t1")])
        >>> float(cbn.reward_table()[0])
        0.5
    """

    edges: list
    cpts: dict
    parents: dict
    schema: VariableSchema = DEFAULT_SCHEMA
    n_rows: int = 0
    known: bool = True
    prior: float = 1.0
    meta: dict = field(default_factory=dict)

    @classmethod
    def uniform(cls, edges, schema: VariableSchema = DEFAULT_SCHEMA) -> "CBN":
        """A CBN with uniform CPTs (no data), marked unknown."""
        data = np.zeros((0, len(schema.node_names())), dtype=np.int64)
        return fit_cbn(edges, data, schema, prior=1.0, known=False)

    def markov_blanket(self, node: str = REWARD_NODE) -> list[str]:
        """Markov blanket of ``node`` (default the reward)."""
        return markov_blanket(self.edges, node)

    def inference_nodes(self) -> list[str]:
        """The reward and its ancestors: the nodes P(reward | state_t) depends on."""
        nodes = self.schema.node_names()
        keep = _ancestors(self.edges, REWARD_NODE) | {REWARD_NODE}
        return [n for n in nodes if n in keep]

    def reward_table(self) -> np.ndarray:
        """P(reward = positive | state_t) for every joint state at t, ``[n_states]`` float64."""
        schema = self.schema
        t_nodes = [n + T_SUFFIX for n in schema.names]
        keep = self.inference_nodes()
        axis = {n: i for i, n in enumerate(schema.node_names())}  # einsum sublist ids
        cards = schema.node_cardinalities()
        args = []
        for node in keep:
            if node in t_nodes:
                continue  # evidence: its prior cancels in P(reward | state_t)
            pa = list(self.parents[node])
            args.append(self.cpts[node].reshape([cards[node]] + [cards[p] for p in pa]))
            args.append([axis[node]] + [axis[p] for p in pa])
        out_t = [n for n in t_nodes if n in keep]
        joint = np.einsum(*args, [axis[REWARD_NODE]] + [axis[n] for n in out_t], optimize=True)
        joint = joint / joint.sum(0, keepdims=True)
        p_pos = joint[1]
        # broadcast the kept t axes onto the full t grid (C order = state_index order)
        full_shape = [c if (n in out_t) else 1 for n, c in zip(t_nodes, schema.cardinalities)]
        p_pos = np.broadcast_to(p_pos.reshape(full_shape), schema.cardinalities)
        return np.ascontiguousarray(p_pos).reshape(-1)

    def sample(self, n: int, seed: int | None = None) -> np.ndarray:
        """Ancestral sampling: ``n`` integer-coded rows in node order (synthetic data).

        Example:
            >>> cbn = random_cbn([("altitude_t", "altitude_t1")], seed=0)
            >>> cbn.sample(5, seed=0).shape
            (5, 19)
        """
        rng = np.random.default_rng(seed)
        nodes = self.schema.node_names()
        index = {v: i for i, v in enumerate(nodes)}
        cards = self.schema.node_cardinalities()
        out = np.zeros((int(n), len(nodes)), np.int64)
        for v in _topological(nodes, self.parents):
            j = np.zeros(int(n), np.int64)
            for p in self.parents[v]:  # C order: first parent slowest
                j = j * cards[p] + out[:, index[p]]
            cdf = np.cumsum(self.cpts[v][:, j], axis=0)  # [card, n]
            u = rng.random(int(n))
            out[:, index[v]] = np.minimum((u[None, :] > cdf).sum(0), cards[v] - 1)
        return out

    def to_pgmpy(self):
        """The network as a fitted pgmpy ``DiscreteBayesianNetwork`` (state names = schema labels)."""
        from pgmpy.factors.discrete import TabularCPD
        from pgmpy.models import DiscreteBayesianNetwork

        nodes = self.schema.node_names()
        labels = self.schema.node_labels()
        model = DiscreteBayesianNetwork()
        model.add_nodes_from(nodes)
        model.add_edges_from(self.edges)
        cards = self.schema.node_cardinalities()
        cpds = []
        for n in nodes:
            pa = list(self.parents[n])
            cpds.append(
                TabularCPD(
                    n,
                    cards[n],
                    self.cpts[n],
                    evidence=pa or None,
                    evidence_card=[cards[p] for p in pa] or None,
                    state_names={v: labels[v] for v in [n] + pa},
                )
            )
        model.add_cpds(*cpds)
        return model

    @classmethod
    def from_pgmpy(cls, model, schema: VariableSchema = DEFAULT_SCHEMA, **kwargs) -> "CBN":
        """Build a CBN from a fitted pgmpy network whose nodes and states follow ``schema``."""
        labels = schema.node_labels()
        nodes = schema.node_names()
        if set(model.nodes()) != set(nodes):
            raise ValueError(f"model nodes {sorted(model.nodes())} do not match the schema's {nodes}")
        parents, cpts = {}, {}
        for n in nodes:
            cpd = model.get_cpds(n)
            pa = list(cpd.variables[1:])
            # reorder states to the schema's label order
            cpd = cpd.copy()
            order = [labels[v] for v in cpd.variables]
            vals = cpd.values  # [card(n), *card(pa)]
            for ax, v in enumerate(cpd.variables):
                names = [str(s) for s in cpd.state_names[v]]
                perm = [names.index(lab) for lab in order[ax]]
                vals = np.take(vals, perm, axis=ax)
            parents[n] = tuple(pa)
            cpts[n] = np.asarray(vals, dtype=np.float64).reshape(vals.shape[0], -1)
        edges = [(u, v) for v in nodes for u in parents[v]]
        return cls(edges, cpts, parents, schema, **kwargs)


def _topological(nodes, parents) -> list[str]:
    done, order = set(), []
    pending = list(nodes)
    while pending:
        rest = []
        for v in pending:
            if all(p in done for p in parents[v]):
                done.add(v)
                order.append(v)
            else:
                rest.append(v)
        if len(rest) == len(pending):
            raise ValueError("the CBN's graph has a cycle")
        pending = rest
    return order


def random_cbn(
    edges: Iterable[tuple[str, str]],
    schema: VariableSchema = DEFAULT_SCHEMA,
    *,
    concentration: float = 0.5,
    seed: int | None = None,
) -> CBN:
    """A CBN with CPT columns drawn from a symmetric Dirichlet (for synthetic data and tests).

    Args:
        edges: the DAG.
        schema: the variable schema.
        concentration: Dirichlet concentration; small values give strong dependencies.
        seed: random seed.

    Example:
        >>> cbn = random_cbn([("altitude_t", "altitude_t1")], seed=1)
        >>> cbn.cpts["altitude_t1"].shape
        (3, 3)
    """
    if concentration <= 0:
        raise ValueError(f"concentration must be > 0, got {concentration!r}")
    rng = np.random.default_rng(seed)
    cbn = CBN.uniform(edges, schema)
    for v, cpt in cbn.cpts.items():
        if cbn.parents[v]:
            cbn.cpts[v] = rng.dirichlet([concentration] * cpt.shape[0], size=cpt.shape[1]).T.copy()
    cbn.known = True
    return cbn


def fit_cbn(
    edges: Iterable[tuple[str, str]],
    data,
    schema: VariableSchema = DEFAULT_SCHEMA,
    *,
    prior: float = 1.0,
    known: bool = True,
) -> CBN:
    """Fit every node's CPT on integer-coded data with a Dirichlet prior.

    Args:
        edges: the DAG, as ``(source, target)`` node names.
        data: int codes ``[N, 2 * n_vars + 1]`` in node order (``N`` may be 0).
        schema: the variable schema.
        prior: Dirichlet pseudo count added to every CPT cell (> 0).
        known: the ``known`` flag to store.

    Example:
        >>> import numpy as np
        >>> cbn = fit_cbn([], np.zeros((3, 19), dtype=int), prior=1.0)
        >>> cbn.cpts["reward"].ravel().tolist()
        [0.8, 0.2]
    """
    if not (isinstance(prior, (int, float)) and prior > 0):
        raise ValueError(f"prior must be a positive pseudo count, got {prior!r}")
    nodes = schema.node_names()
    index = {n: i for i, n in enumerate(nodes)}
    data = np.asarray(data).reshape(-1, len(nodes))
    cards = schema.node_cardinalities()
    edges = list(edges)
    for u, v in edges:
        if u not in index or v not in index:
            raise ValueError(f"edge {(u, v)!r} names a node not in {nodes}")
    parents = {n: tuple(sorted({u for u, v in edges if v == n}, key=index.get)) for n in nodes}
    cpts = {}
    for n in nodes:
        pa = parents[n]
        r = cards[n]
        idx = np.zeros(data.shape[0], np.int64)
        size = 1
        for p in reversed(pa):  # C order over parents: first parent slowest
            idx += data[:, index[p]].astype(np.int64) * size
            size *= cards[p]
        idx = data[:, index[n]].astype(np.int64) * size + idx
        counts = np.bincount(idx, minlength=r * size).reshape(r, size).astype(np.float64) + prior
        cpts[n] = counts / counts.sum(0, keepdims=True)
    edges = [(u, v) for v in nodes for u in parents[v]]
    return CBN(edges, cpts, parents, schema, int(data.shape[0]), bool(known), float(prior))


def compile_tables(cbns: Sequence[CBN | None], schema: VariableSchema = DEFAULT_SCHEMA, device=None) -> RewardTables:
    """Stack the reward tables of all actions into :class:`RewardTables`.

    Args:
        cbns: one :class:`CBN` (or ``None`` = unknown) per action.
        schema: the variable schema.
        device: torch device of the tables.

    Example:
        >>> t = compile_tables([CBN.uniform([]), None])
        >>> t.known.tolist(), tuple(t.p_pos.shape)
        ([False, False], (2, 1728))
    """
    rows, known = [], []
    for cbn in cbns:
        if cbn is None:
            rows.append(np.full(schema.n_states, 0.5))
            known.append(False)
        else:
            rows.append(cbn.reward_table())
            known.append(cbn.known)
    p = torch.as_tensor(np.stack(rows), dtype=torch.float32)
    p = p.clamp_(0.0, 1.0)
    return RewardTables(p.to(device) if device is not None else p, torch.tensor(known, device=device), schema)
