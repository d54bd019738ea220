"""Structure learning of the per-action DBNs: BIC hill climbing (thesis Alg. 2, line 9).

Two backends run the *same* search:

* ``backend="pgmpy"``: pgmpy 1.1's :class:`~pgmpy.causal_discovery.HillClimbSearch`
  with the ``bic-d`` score and an :class:`~pgmpy.causal_discovery.ExpertKnowledge`
  holding the constraints (the reference implementation);
* ``backend="fast"``: a re-implementation of pgmpy's hill climbing (same
  operations -- add, delete, reverse an edge --, same tabu list, same
  ``epsilon`` stop rule, same indegree limit) over integer count tables built
  with :func:`numpy.bincount`, with every local score cached.

The constraints are *time tiers*: an edge may only go from the ``t`` slice to the
``t+1`` slice or to ``reward``, or from the ``t+1`` slice to ``reward``.
Same-slice edges between state variables are

* ``synchronous="forbid"`` (default): excluded from the search. Then every
  allowed edge set is acyclic and no reversal is ever legal, so the search
  decomposes into independent parent selections, one per ``t+1`` variable and
  one for ``reward``: the fast backend evaluates each candidate parent with one
  bincount and is tens of times faster than pgmpy;
* ``synchronous="delete_after"``: allowed during the search and deleted
  afterwards, as the thesis does (Alg. 2, line 10). The fast backend then also
  checks cycles and reversals like pgmpy.

Both backends score with pgmpy's BIC, ``LL - 0.5 * log(N) * q * (r - 1)`` per
node (``q`` parent configurations, ``r`` states). ``cardinality="schema"``
(default) takes ``q`` and ``r`` from the schema; ``cardinality="observed"``
counts only the values present in the data, which is what pgmpy does when it is
given the string ``"bic-d"`` without state names.

When two moves have exactly the same score change, the two backends may take
different ones (pgmpy's candidate order depends on Python's set hashing); the
resulting DAGs then have the same score. Without ties they are equal.

Example:
    >>> import numpy as np
    >>> from torchrl_causal.schema import VariableSchema, Variable
    >>> from torchrl_causal.causal.structure import learn_structure
    >>> schema = VariableSchema((Variable("a", ("lo", "hi")),))
    >>> rng = np.random.default_rng(0)
    >>> a_t = rng.integers(0, 2, 500)
    >>> a_t1 = np.where(rng.random(500) < 0.9, a_t, 1 - a_t)
    >>> reward = a_t1.copy()
    >>> res = learn_structure(np.stack([a_t, a_t1, reward], 1), schema)
    >>> res.edges
    [('a_t', 'a_t1'), ('a_t1', 'reward')]
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np

from torchrl_causal.schema import DEFAULT_SCHEMA, REWARD_NODE, T1_SUFFIX, T_SUFFIX, VariableSchema

__all__ = [
    "BICScore",
    "LearnedStructure",
    "learn_structure",
    "allowed_edges",
    "time_tiers",
    "BACKENDS",
    "SYNCHRONOUS",
]

BACKENDS = ("fast", "pgmpy")
SYNCHRONOUS = ("forbid", "delete_after")
CARDINALITY = ("schema", "observed")


def time_tiers(schema: VariableSchema = DEFAULT_SCHEMA) -> list[list[str]]:
    """The temporal order ``[[t nodes], [t+1 nodes], ["reward"]]``.

    Example:
        >>> time_tiers()[2]
        ['reward']
    """
    return (
        [[n + T_SUFFIX for n in schema.names], [n + T1_SUFFIX for n in schema.names], [REWARD_NODE]]
    )


def _tier_of(schema: VariableSchema) -> np.ndarray:
    n = len(schema)
    return np.array([0] * n + [1] * n + [2])


def allowed_edges(schema: VariableSchema = DEFAULT_SCHEMA, synchronous: str = "forbid") -> np.ndarray:
    """Boolean matrix ``[n_nodes, n_nodes]``: may edge ``i -> j`` appear in the search?

    Args:
        schema: variable schema; nodes in :meth:`~torchrl_causal.schema.VariableSchema.node_names` order.
        synchronous: ``"forbid"`` (no same-slice edges) or ``"delete_after"``
            (same-slice edges allowed in the search).

    Example:
        >>> int(allowed_edges().sum())  # 9 x 9 (t -> t+1) + 9 (t -> reward) + 9 (t+1 -> reward)
        99
    """
    if synchronous not in SYNCHRONOUS:
        raise ValueError(f"synchronous must be one of {SYNCHRONOUS}, got {synchronous!r}")
    tier = _tier_of(schema)
    allowed = tier[:, None] < tier[None, :]
    if synchronous == "delete_after":
        allowed |= tier[:, None] == tier[None, :]
    np.fill_diagonal(allowed, False)
    return allowed


class BICScore:
    """pgmpy's discrete BIC over an integer-coded table, with cached local scores.

    For each child, the rows are first compressed to the distinct combinations
    of the child and its possible parents (``candidates``) with their counts:
    with time tiers a ``t+1`` variable sees at most ``1728 x 3`` combinations
    however many rows there are, so each score costs a weighted bincount over
    those instead of over ``N`` rows. Counts stay integers and the scores are
    exactly pgmpy's.

    Args:
        data: int codes ``[N, n_nodes]``, values in ``[0, index_cards[j])``.
        index_cards: cardinality used to index column ``j`` (the schema's).
        penalty_cards: cardinality used in the penalty (schema or observed).
        candidates: ``candidates[j]``: the columns that may become parents of
            ``j`` (``None``: all others).

    Example:
        >>> import numpy as np
        >>> s = BICScore(np.array([[0, 1], [1, 0], [1, 1], [0, 0]]), [2, 2], [2, 2])
        >>> round(s.local(1, (0,)), 3)
        -4.159
    """

    def __init__(
        self,
        data: np.ndarray,
        index_cards: Sequence[int],
        penalty_cards: Sequence[int],
        candidates: Sequence[Sequence[int]] | None = None,
    ):
        data = np.asarray(data)
        self.data = data.astype(np.int64)
        self.n_rows = data.shape[0]
        n_cols = data.shape[1]
        self.index_cards = [int(c) for c in index_cards]
        self.penalty_cards = [int(c) for c in penalty_cards]
        if candidates is None:
            candidates = [[k for k in range(n_cols) if k != j] for j in range(n_cols)]
        self.candidates = [sorted(int(k) for k in c) for c in candidates]
        self.half_log_n = 0.5 * math.log(self.n_rows) if self.n_rows > 0 else 0.0
        self._cache: dict = {}
        self._idx_cache: dict = {}
        self._views: dict = {}
        self._key_cache: dict = {}
        self.n_evaluations = 0
        k = np.arange(self.n_rows + 1, dtype=np.float64)
        self._xlogx = k * np.log(np.maximum(k, 1.0))

    def _view(self, child: int):
        """Distinct (child, candidate parents) combinations with counts, built once per child."""
        view = self._views.get(child)
        if view is not None:
            return view
        cols = self.candidates[child] + [child]
        key, size = self._prefix_key(tuple(cols))
        if size <= max(4 * self.n_rows, 1 << 16):
            weights = np.bincount(key, minlength=size)
            uniq = np.flatnonzero(weights)
            weights = weights[uniq]
        else:
            uniq, weights = np.unique(key, return_counts=True)
        columns = {}
        rest = uniq
        for c in reversed(cols):
            columns[c] = rest % self.index_cards[c]
            rest = rest // self.index_cards[c]
        view = (columns, weights.astype(np.float64))
        self._views[child] = view
        return view

    def _prefix_key(self, cols: tuple) -> tuple[np.ndarray, int]:
        """Mixed-radix key of the columns ``cols`` (first slowest), prefixes shared between children."""
        if not cols:
            return np.zeros(self.n_rows, np.int64), 1
        hit = self._key_cache.get(cols)
        if hit is None:
            key, size = self._prefix_key(cols[:-1])
            c = cols[-1]
            hit = (key * self.index_cards[c] + self.data[:, c], size * self.index_cards[c])
            self._key_cache[cols] = hit
        return hit

    def local(self, child: int, parents: Iterable[int]) -> float:
        """Local BIC of ``child`` given ``parents`` (order does not matter)."""
        parents = tuple(sorted(parents))
        key = (child, parents)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        columns, weights = self._view(child)
        if any(p not in columns for p in parents):
            raise ValueError(f"parents {parents} of column {child} are not among its candidates")
        if parents:
            # extend the cached index of (child, all parents but the last) by one column
            base, size = self._index(child, parents[:-1])
            last = parents[-1]
            idx = base + columns[last] * size
            size *= self.index_cards[last]
        else:
            idx, size = columns[child], self.index_cards[child]
        score = self._score(child, parents, idx, size, weights)
        self._cache[key] = score
        return score

    def _index(self, child: int, parents: tuple) -> tuple[np.ndarray, int]:
        """Joint index ``child + r * config(parents)`` and its range, cached per parent set."""
        key = (child, parents)
        hit = self._idx_cache.get(key)
        if hit is None:
            columns = self._view(child)[0]
            if not parents:
                hit = (columns[child], self.index_cards[child])
            else:
                base, size = self._index(child, parents[:-1])
                hit = (base + columns[parents[-1]] * size, size * self.index_cards[parents[-1]])
            if len(self._idx_cache) > 256:
                self._idx_cache.clear()
            self._idx_cache[key] = hit
        return hit

    def _score(self, child: int, parents: tuple, idx: np.ndarray, size: int, weights: np.ndarray) -> float:
        self.n_evaluations += 1
        r = self.index_cards[child]
        counts = np.bincount(idx, weights=weights, minlength=size).astype(np.int64)
        n_j = counts.reshape(-1, r).sum(1)  # rows = parent configurations
        # sum_jk N_jk log N_jk - sum_j N_j log N_j, with a k*log(k) lookup table
        ll = float(self._xlogx[counts].sum() - self._xlogx[n_j].sum())
        q = 1
        for p in parents:
            q *= self.penalty_cards[p]
        return ll - self.half_log_n * q * (self.penalty_cards[child] - 1)

    def total(self, parents: Sequence[Sequence[int]]) -> float:
        """Score of a whole DAG given the parent list of every node."""
        return float(sum(self.local(j, ps) for j, ps in enumerate(parents)))


@dataclass
class LearnedStructure:
    """Result of :func:`learn_structure`.

    Attributes:
        edges: final edges ``(source, target)`` (after deleting synchronous links).
        score: BIC of the DAG the search ended in (before any deletion).
        deleted_edges: same-slice edges removed after the search (``delete_after``).
        n_moves: hill-climbing moves taken (``-1`` from the pgmpy backend, which
            does not report them).
        backend: the backend that produced it.
        seconds: wall time of the search.

    Example:
        >>> LearnedStructure([("a_t", "reward")], -10.0).edges
        [('a_t', 'reward')]
    """

    edges: list
    score: float
    deleted_edges: list = field(default_factory=list)
    n_moves: int = 0
    backend: str = "fast"
    seconds: float = 0.0


def _observed_cards(data: np.ndarray) -> list[int]:
    return [max(len(np.unique(data[:, j])), 1) for j in range(data.shape[1])]


def _hill_climb(
    score: BICScore,
    allowed: np.ndarray,
    start: list[list[int]],
    max_indegree: float,
    tabu_length: int,
    epsilon: float,
    max_iter: int,
) -> tuple[list[list[int]], int]:
    """pgmpy's HillClimbSearch._fit, on integer node ids and cached local scores."""
    n = allowed.shape[0]
    parents = [list(p) for p in start]
    # If the allowed edges form a DAG, every subset does: no cycle checks, no reversals.
    acyclic = _is_acyclic(allowed)
    cand = [np.flatnonzero(allowed[:, y]).tolist() for y in range(n)]
    tabu: deque = deque(maxlen=tabu_length)
    node_moves: dict = {}
    moves = 0
    for _ in range(int(max_iter)):
        tabu_set = set(tabu)
        reach = None if acyclic else _reachability(parents)
        best_op, best_delta = None, -math.inf
        # Step 1: additions, Step 2: removals. The deltas of node y only change
        # when y's parents do: they are cached per (y, parents) and filtered here.
        for y in range(n):
            py = parents[y]
            moves_y = node_moves.get((y, tuple(py)))
            if moves_y is None:
                moves_y = _node_moves(score, y, py, cand[y], parents, reach, max_indegree)
                if acyclic:  # legality of y's moves depends on y's parents only
                    node_moves[(y, tuple(py))] = moves_y
            for op, delta in moves_y:
                if delta > best_delta and op not in tabu_set:
                    best_op, best_delta = op, delta
        # Step 3: reversals (only possible when same-tier edges are allowed)
        if not acyclic:
            for y in range(n):
                for x in parents[y]:
                    if not allowed[y, x] or len(parents[x]) + 1 > max_indegree:
                        continue
                    if ("flip", (x, y)) in tabu_set or ("flip", (y, x)) in tabu_set:
                        continue
                    children_x = [c for c in range(n) if x in parents[c] and c != y]
                    if any(reach[c][y] for c in children_x):
                        continue
                    delta = (
                        score.local(x, parents[x] + [y])
                        + score.local(y, [p for p in parents[y] if p != x])
                        - score.local(x, parents[x])
                        - score.local(y, parents[y])
                    )
                    if delta > best_delta:
                        best_op, best_delta = ("flip", (x, y)), delta
        if best_op is None or best_delta < epsilon:
            break
        kind, (x, y) = best_op
        if kind == "+":
            parents[y].append(x)
            tabu.append(("-", (x, y)))
        elif kind == "-":
            parents[y].remove(x)
            tabu.append(("+", (x, y)))
        else:
            parents[y].remove(x)
            parents[x].append(y)
            tabu.append(best_op)
        moves += 1
    return parents, moves


def _node_moves(score, y, py, cand_y, parents, reach, max_indegree) -> list:
    """Legal additions then removals of edges into ``y`` (ignoring tabu) with their score change."""
    out = []
    base = score.local(y, py)
    if len(py) + 1 <= max_indegree:
        for x in cand_y:
            if x in py or y in parents[x] or (reach is not None and reach[y][x]):
                continue
            out.append((("+", (x, y)), score.local(y, py + [x]) - base))
    for x in py:
        out.append((("-", (x, y)), score.local(y, [p for p in py if p != x]) - base))
    return out


def _is_acyclic(adj: np.ndarray) -> bool:
    indeg = adj.sum(0).astype(int)
    stack = [i for i in range(adj.shape[0]) if indeg[i] == 0]
    seen = 0
    while stack:
        i = stack.pop()
        seen += 1
        for j in np.flatnonzero(adj[i]):
            indeg[j] -= 1
            if indeg[j] == 0:
                stack.append(j)
    return seen == adj.shape[0]


def _reachability(parents: list[list[int]]) -> list[list[bool]]:
    """reach[u][v]: is there a directed path u -> ... -> v (length >= 1)?"""
    n = len(parents)
    children = [[] for _ in range(n)]
    for v, ps in enumerate(parents):
        for u in ps:
            children[u].append(v)
    reach = []
    for u in range(n):
        row = [False] * n
        stack = list(children[u])
        while stack:
            v = stack.pop()
            if not row[v]:
                row[v] = True
                stack.extend(children[v])
        reach.append(row)
    return reach


def _check_options(backend, synchronous, cardinality, max_indegree):
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if synchronous not in SYNCHRONOUS:
        raise ValueError(f"synchronous must be one of {SYNCHRONOUS}, got {synchronous!r}")
    if cardinality not in CARDINALITY:
        raise ValueError(f"cardinality must be one of {CARDINALITY}, got {cardinality!r}")
    if max_indegree is not None and (not isinstance(max_indegree, int) or max_indegree < 0):
        raise ValueError(f"max_indegree must be None or an int >= 0, got {max_indegree!r}")


def learn_structure(
    data,
    schema: VariableSchema = DEFAULT_SCHEMA,
    *,
    backend: str = "fast",
    start_dag: Iterable[tuple[str, str]] | None = None,
    synchronous: str = "forbid",
    max_indegree: int | None = None,
    cardinality: str = "schema",
    tabu_length: int = 100,
    epsilon: float = 1e-4,
    max_iter: int = 1_000_000,
) -> LearnedStructure:
    """Learn one action's DBN structure by BIC hill climbing under time tiers.

    Args:
        data: int codes ``[N, 2 * n_vars + 1]`` in
            :meth:`~torchrl_causal.schema.VariableSchema.node_names` order
            (t slice, t+1 slice, reward class), e.g. :meth:`TransitionData.rows`.
        schema: the variable schema.
        backend: ``"fast"`` (count tables) or ``"pgmpy"`` (HillClimbSearch).
        start_dag: edges to start from (warm start with the previous DAG, thesis
            Alg. 2 lines 4-6); edges that break the constraints are dropped.
            ``None`` starts from the empty graph.
        synchronous: ``"forbid"`` or ``"delete_after"`` (see module docs).
        max_indegree: maximum number of parents per node, ``None`` for no limit.
        cardinality: ``"schema"`` or ``"observed"`` cardinalities in the BIC penalty.
        tabu_length: length of the tabu list (pgmpy's default 100).
        epsilon: stop when the best score change is below it (pgmpy's default 1e-4).
        max_iter: maximum number of moves.

    Returns:
        :class:`LearnedStructure`.

    Example:
        >>> import numpy as np
        >>> rng = np.random.default_rng(0)
        >>> data = rng.integers(0, 2, (500, 19))
        >>> data[:, 17] = data[:, 8]  # altitude_t1 copies altitude_t
        >>> ("altitude_t", "altitude_t1") in learn_structure(data, backend="fast").edges
        True
    """
    _check_options(backend, synchronous, cardinality, max_indegree)
    nodes = schema.node_names()
    data = np.asarray(data)
    if data.ndim != 2 or data.shape[1] != len(nodes):
        raise ValueError(f"data must have shape [N, {len(nodes)}], got {tuple(data.shape)}")
    if data.shape[0] < 1:
        raise ValueError("data must have at least one row")
    index = {n: i for i, n in enumerate(nodes)}
    allowed = allowed_edges(schema, synchronous)
    start_ids = []
    for u, v in start_dag or ():
        if u not in index or v not in index:
            raise ValueError(f"start_dag edge {(u, v)!r} names a node not in {nodes}")
        if allowed[index[u], index[v]]:
            start_ids.append((index[u], index[v]))
    start = [[] for _ in nodes]
    for u, v in start_ids:
        start[v].append(u)
    if not _is_acyclic_parents(start):
        raise ValueError("start_dag is not acyclic")
    node_cards = schema.node_cardinalities()
    cards_schema = [node_cards[n] for n in nodes]
    t0 = time.perf_counter()
    if backend == "fast":
        pen = cards_schema if cardinality == "schema" else _observed_cards(data)
        score = BICScore(data, cards_schema, pen, [np.flatnonzero(allowed[:, j]) for j in range(len(nodes))])
        parents, moves = _hill_climb(
            score,
            allowed,
            start,
            float("inf") if max_indegree is None else max_indegree,
            tabu_length,
            epsilon,
            max_iter,
        )
        total = score.total(parents)
        searched = [(nodes[u], nodes[v]) for v, ps in enumerate(parents) for u in ps]
    else:
        searched, total, moves = _pgmpy_search(
            data, schema, nodes, [(nodes[u], nodes[v]) for u, v in start_ids], allowed,
            max_indegree, cardinality, tabu_length, epsilon, max_iter,
        )
    seconds = time.perf_counter() - t0
    tier = dict(zip(nodes, _tier_of(schema)))
    deleted = [e for e in searched if tier[e[0]] == tier[e[1]]]
    edges = sorted((e for e in searched if tier[e[0]] != tier[e[1]]), key=lambda e: (index[e[1]], index[e[0]]))
    return LearnedStructure(edges, total, sorted(deleted), moves, backend, seconds)


def _is_acyclic_parents(parents) -> bool:
    n = len(parents)
    adj = np.zeros((n, n), bool)
    for v, ps in enumerate(parents):
        adj[ps, v] = True
    return _is_acyclic(adj)


def _pgmpy_search(data, schema, nodes, start_edges, allowed, max_indegree, cardinality,
                  tabu_length, epsilon, max_iter):
    import pandas as pd
    from pgmpy.base import DAG
    from pgmpy.causal_discovery import ExpertKnowledge, HillClimbSearch
    from pgmpy.structure_score import BIC

    df = pd.DataFrame(np.asarray(data, dtype=np.int64), columns=nodes)
    if cardinality == "schema":
        state_names = {n: list(range(c)) for n, c in schema.node_cardinalities().items()}
        scorer = BIC(df, state_names=state_names)
    else:
        scorer = BIC(df)
    tier = _tier_of(schema)
    same_tier = [
        (nodes[i], nodes[j])
        for i in range(len(nodes))
        for j in range(len(nodes))
        if i != j and tier[i] == tier[j] and not allowed[i, j]
    ]
    expert = ExpertKnowledge(temporal_order=time_tiers(schema), forbidden_edges=same_tier)
    start = DAG()
    start.add_nodes_from(nodes)
    start.add_edges_from(start_edges)  # checked acyclic by learn_structure
    hc = HillClimbSearch(
        scoring_method=scorer,
        start_dag=start,
        tabu_length=tabu_length,
        max_indegree=max_indegree,
        expert_knowledge=expert,
        return_type="dag",
        epsilon=epsilon,
        max_iter=max_iter,
        show_progress=False,
    )
    hc.fit(df)
    dag = hc.causal_graph_
    edges = list(dag.edges())
    return edges, float(scorer.score(dag)), -1
