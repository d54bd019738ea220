"""``CausalLearner``: thesis Alg. 2 for all actions, feeding the CBN gate.

It stores every transition for the action taken (:class:`TransitionData`),
and :meth:`CausalLearner.relearn` (called every ``k`` steps by the replay-buffer
hook) runs, for each action: warm-started BIC hill climbing under time tiers
(``mode="learned"``) or takes the expert structure (``mode="defined"``),
deletes/forbids synchronous links, fits the CPTs with a Dirichlet prior and
compiles P(reward | state_t) for every joint state into one
:class:`~torchrl_causal.causal.tables.RewardTables`.

An action's model is ``known=False`` (the gate abstains for it) when it has
fewer than ``min_rows`` transitions (including never taken) or when its reward
class never varied (a constant reward says nothing about which states are
risky). Constant state columns and parent configurations never seen are
handled by the prior and never raise.

:meth:`CausalLearner.transfer` (or :meth:`CausalLearner.from_saved`) starts a
learner from CBNs saved elsewhere (e.g. by a run in another place): their
structures and CPTs give tables at once, so the gate acts from the first frame.

Example:
    >>> import torch
    >>> from torchrl_causal.causal import CausalLearner
    >>> learner = CausalLearner(min_rows=10)
    >>> g = torch.Generator().manual_seed(0)
    >>> s0 = torch.randint(0, 2, (200, 9), generator=g)
    >>> s1 = torch.randint(0, 2, (200, 9), generator=g)
    >>> a = torch.zeros(200, dtype=torch.long)
    >>> r = torch.where(s1[:, 5] == 1, 50.0, -9.0)
    >>> learner.add(s0, a, s1, r)
    >>> tables = learner.relearn()
    >>> tables.known.tolist()
    [True, False, False, False, False, False, False, False]
    >>> ("goal_in_sight_t1", "reward") in learner.dags()["forward"]
    True
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from torchrl_causal.causal.data import TransitionData
from torchrl_causal.causal.expert import expert_dags as expert_dags_default
from torchrl_causal.causal.inference import CBN, compile_tables, fit_cbn
from torchrl_causal.causal.io import load_cbn_folder, save_cbn
from torchrl_causal.causal.structure import _check_options, learn_structure, time_tiers
from torchrl_causal.causal.tables import RewardTables
from torchrl_causal.schema import ACTION_NAMES, DEFAULT_SCHEMA, VariableSchema

__all__ = ["CausalLearner", "MODES"]

MODES = ("learned", "defined")


def _check_expert(dags, schema: VariableSchema, n_actions: int) -> dict[str, list[tuple[str, str]]]:
    """Validated copy of ``expert_dags``: one DAG per action, edges forward in time."""
    if not isinstance(dags, Mapping):
        raise ValueError(
            f"expert_dags must be a mapping {{action_name: [(source, target), ...]}}, got {type(dags).__name__}"
        )
    if len(dags) != n_actions:
        raise ValueError(
            f"expert_dags has {len(dags)} DAGs ({list(dags)}) but n_actions={n_actions}; "
            "give one expert DAG per action"
        )
    tiers = {node: k for k, tier in enumerate(time_tiers(schema)) for node in tier}
    out = {}
    for name, edges in dags.items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"expert_dags keys must be action names (non-empty str), got {name!r}")
        checked = []
        for edge in edges:
            if not (isinstance(edge, (tuple, list)) and len(edge) == 2):
                raise ValueError(f"expert_dags[{name!r}]: an edge must be (source, target), got {edge!r}")
            for node in edge:
                if node not in tiers:
                    raise ValueError(
                        f"expert_dags[{name!r}]: edge {tuple(edge)!r} names {node!r}, which is not a "
                        f"node of the schema; nodes: {schema.node_names()}"
                    )
            src, dst = edge
            if tiers[src] >= tiers[dst]:
                raise ValueError(
                    f"expert_dags[{name!r}]: edge {(src, dst)!r} does not go forward in time "
                    "(allowed: <var>_t -> <var>_t1, <var>_t -> reward, <var>_t1 -> reward)"
                )
            if (src, dst) not in checked:
                checked.append((src, dst))
        out[name] = checked
    return out


def _action_names(action_names, expert, n_actions: int) -> list[str]:
    if action_names is None:
        if expert is not None:
            return list(expert)
        if n_actions == len(ACTION_NAMES):
            return list(ACTION_NAMES)
        return [f"action_{i}" for i in range(n_actions)]
    if isinstance(action_names, str):
        raise ValueError(f"action_names must be a sequence of names, got the string {action_names!r}")
    names = list(action_names)
    if len(names) != n_actions:
        raise ValueError(f"action_names has {len(names)} names {names} but n_actions={n_actions}")
    if len(set(names)) != len(names) or not all(isinstance(n, str) and n for n in names):
        raise ValueError(f"action_names must be distinct non-empty strings, got {names}")
    if expert is not None and set(names) != set(expert):
        raise ValueError(f"action_names {names} must be the keys of expert_dags {list(expert)}")
    return names


class CausalLearner:
    """Learns (or fits) one CBN per action and compiles the reward tables.

    Any env works: pass its schema, its number of actions, and (for
    ``mode="defined"``) its expert DAGs, e.g. the grid world's
    :func:`~torchrl_causal.envs.gridnav_expert_dags`.

    Args:
        schema: the variable schema of ``causal_state``.
        n_actions: number of actions (8 for the drone). With ``mode="defined"``
            it must equal the number of expert DAGs (8 for the drone's default).
        mode: ``"learned"`` (BIC hill climbing, thesis Alg. 2) or ``"defined"``
            (the expert structures of ``expert_dags``, CPTs fitted from data at
            each relearn).
        backend: structure-learning backend, ``"fast"`` or ``"pgmpy"``.
        min_rows: minimum transitions of an action for its model to be known.
        prior: Dirichlet pseudo count per CPT cell (default 1.0).
        synchronous: ``"forbid"`` (default) or ``"delete_after"`` same-slice links.
        max_indegree: maximum parents per node (``None``: no limit).
        cardinality: ``"schema"`` or ``"observed"`` cardinalities in the BIC penalty.
        warm_start: start each search from the action's previous DAG (thesis Alg. 2 l. 4-6).
        max_rows: keep only the newest ``max_rows`` transitions per action (``None``: all).
        device: device of the compiled tables.
        expert_dags: ``{action_name: [(source, target), ...]}``, one DAG per
            action in action order, over the node names of ``schema``
            (``"<var>_t"``, ``"<var>_t1"``, ``"reward"``), every edge forward in
            time. ``None`` (default): the drone's
            :func:`~torchrl_causal.causal.expert.expert_dags` in ``"defined"``
            mode, none in ``"learned"`` mode. In ``"learned"`` mode given DAGs
            are only kept as the reference :attr:`expert` (for comparing and
            drawing), the search does not use them.
        action_names: names of the actions, in action order (default: the
            keys of ``expert_dags`` when given, else
            :data:`~torchrl_causal.schema.ACTION_NAMES` for 8 actions, else
            ``action_0, action_1, ...``). With ``expert_dags`` they must be its keys.

    Attributes:
        frozen: ``True`` after :meth:`transfer` with ``relearn=False``:
            :meth:`relearn` then keeps the transferred CBNs (transitions are
            still stored).
        transferred_from: the folder of :meth:`transfer` (``None``: none).
        expert: the expert DAGs in use (``mode="defined"``) or given for
            reference, ``{action_name: [(source, target), ...]}`` in action
            order; ``None`` in ``"learned"`` mode without ``expert_dags``.
        action_names: the action names, in action order.

    Raises:
        ValueError: a bad option; ``n_actions`` that does not match
            ``expert_dags`` or ``action_names``; an expert edge naming a node
            the schema lacks, or going backwards in (or within) a time slice.

    Example:
        >>> learner = CausalLearner(mode="defined")
        >>> learner.tables is None
        True
        >>> learner.relearn().known.any().item()
        False
        >>> from torchrl_causal.schema import Variable, VariableSchema
        >>> s = VariableSchema((Variable("wall", ("free", "blocked")),))
        >>> mine = CausalLearner(s, 2, mode="defined",
        ...                      expert_dags={"go": [("wall_t", "reward")], "stay": []})
        >>> mine.action_names, mine.expert["go"]
        (['go', 'stay'], [('wall_t', 'reward')])
        >>> CausalLearner(s, 2, mode="defined", expert_dags={"go": [("wal_t", "reward")], "stay": []})
        Traceback (most recent call last):
        ...
        ValueError: expert_dags['go']: edge ('wal_t', 'reward') names 'wal_t', which is not a node of the schema; nodes: ['wall_t', 'wall_t1', 'reward']
    """

    def __init__(
        self,
        schema: VariableSchema = DEFAULT_SCHEMA,
        n_actions: int = 8,
        *,
        mode: str = "learned",
        backend: str = "fast",
        min_rows: int = 30,
        prior: float = 1.0,
        synchronous: str = "forbid",
        max_indegree: int | None = None,
        cardinality: str = "schema",
        warm_start: bool = True,
        max_rows: int | None = None,
        device=None,
        expert_dags: Mapping[str, Sequence[tuple[str, str]]] | None = None,
        action_names: Sequence[str] | None = None,
    ):
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        _check_options(backend, synchronous, cardinality, max_indegree)
        if not isinstance(min_rows, int) or min_rows < 1:
            raise ValueError(f"min_rows must be an int >= 1, got {min_rows!r}")
        if not (isinstance(prior, (int, float)) and prior > 0):
            raise ValueError(f"prior must be a positive pseudo count, got {prior!r}")
        if not isinstance(n_actions, int) or n_actions < 1:
            raise ValueError(f"n_actions must be a positive int, got {n_actions!r}")
        if expert_dags is None and mode == "defined":
            expert_dags = expert_dags_default(schema)
            if n_actions != len(expert_dags):
                raise ValueError(
                    f"mode='defined' uses the {len(expert_dags)} expert CBNs, got n_actions={n_actions}"
                )
        expert = None if expert_dags is None else _check_expert(expert_dags, schema, n_actions)
        names = _action_names(action_names, expert, n_actions)
        self.schema = schema
        self.n_actions = n_actions
        self.mode = mode
        self.backend = backend
        self.min_rows = min_rows
        self.prior = float(prior)
        self.synchronous = synchronous
        self.max_indegree = max_indegree
        self.cardinality = cardinality
        self.warm_start = warm_start
        self.device = device
        self.action_names = names
        self.data = TransitionData(n_actions, schema, max_rows=max_rows)
        self.expert: dict[str, list[tuple[str, str]]] | None = expert
        self._dags: list[list] = [
            list(expert[a]) if mode == "defined" else [] for a in self.action_names
        ]
        self.cbns: list[CBN | None] = [None] * n_actions
        self._tables: RewardTables | None = None
        self.n_relearns = 0
        self.history: list[dict] = []
        self.frozen = False
        self.transferred_from: str | None = None
        self._transferred: list[CBN | None] = [None] * n_actions  # transfer(): the CBNs read
        self._from_transfer = [False] * n_actions  # action a holds its transferred CBN

    # ------------------------------------------------------------------ data
    def add(self, state_t, action, state_t1, reward) -> None:
        """Store transitions; reward class is positive iff ``reward >= 0``.

        Args:
            state_t: LongTensor ``[N, n_vars]``.
            action: LongTensor ``[N]``.
            state_t1: LongTensor ``[N, n_vars]``.
            reward: FloatTensor ``[N]``.
        """
        self.data.add(state_t, action, state_t1, reward)

    # -------------------------------------------------------------- learning
    def _degenerate(self, rows: np.ndarray) -> str | None:
        if rows.shape[0] < self.min_rows:
            return f"{rows.shape[0]} rows < min_rows={self.min_rows}"
        if rows[:, -1].min() == rows[:, -1].max():
            return "reward class never varied"
        return None

    def relearn(self) -> RewardTables:
        """Learn/fit every action's CBN and compile the reward tables (thesis Alg. 2).

        After :meth:`transfer`, an action whose own data is still degenerate
        keeps its transferred CBN; a :attr:`frozen` learner returns its tables
        unchanged (no relearn is counted).
        """
        if self.frozen:
            return self._tables
        t0 = time.perf_counter()
        record = {"relearn": self.n_relearns + 1, "frames": self.data.total_added, "actions": {}}
        for a, name in enumerate(self.action_names):
            rows = self.data.rows(a)
            why = self._degenerate(rows)
            info = {"n_rows": int(rows.shape[0]), "known": why is None, "reason": why}
            self._from_transfer[a] = why is not None and self._transferred[a] is not None
            if self._from_transfer[a]:
                cbn = self._transferred[a]
                self._dags[a] = list(cbn.edges)
                info.update(known=cbn.known, reason=f"{why}; kept the transferred CBN")
            else:
                if self.mode == "learned" and rows.shape[0] >= self.min_rows:
                    res = learn_structure(
                        rows,
                        self.schema,
                        backend=self.backend,
                        start_dag=self._dags[a] if self.warm_start else None,
                        synchronous=self.synchronous,
                        max_indegree=self.max_indegree,
                        cardinality=self.cardinality,
                    )
                    self._dags[a] = list(res.edges)
                    info.update(score=res.score, seconds=res.seconds,
                                deleted=[list(e) for e in res.deleted_edges])
                cbn = fit_cbn(self._dags[a], rows, self.schema, prior=self.prior, known=why is None)
                cbn.meta = {"action": name, "mode": self.mode}
            self.cbns[a] = cbn
            info["edges"] = [list(e) for e in self._dags[a]]
            info["markov_blanket"] = cbn.markov_blanket()
            record["actions"][name] = info
        self._tables = compile_tables(self.cbns, self.schema, device=self.device)
        self.n_relearns += 1
        record["seconds"] = time.perf_counter() - t0
        self.history.append(record)
        return self._tables

    # ------------------------------------------------------------- accessors
    @property
    def tables(self) -> RewardTables | None:
        """The last compiled tables (``None`` before the first :meth:`relearn`)."""
        return self._tables

    def dags(self) -> dict[str, list[tuple[str, str]]]:
        """Current DAG of every action, ``{action_name: [(source, target), ...]}``."""
        return {name: [tuple(e) for e in d] for name, d in zip(self.action_names, self._dags)}

    def history_dags(self, index: int) -> dict[str, list[tuple[str, str]]]:
        """The DAGs recorded at relearn ``index`` of :attr:`history` (``0`` first, ``-1`` last)."""
        rec = self.history[index]
        return {name: [tuple(e) for e in info["edges"]] for name, info in rec["actions"].items()}

    def first_searched_dags(self) -> dict[str, list[tuple[str, str]]]:
        """Per action, the DAG of the first relearn that ran a structure search for it.

        An action's structure is searched only once it has ``min_rows``
        transitions (and, in ``"learned"`` mode, a reward that varied); earlier
        relearns record an empty DAG, which is not the "first learned CBN" of
        thesis Table 5.1. Actions never searched get ``[]``.

        Example:
            >>> import torch
            >>> learner = CausalLearner(min_rows=5)
            >>> g = torch.Generator().manual_seed(0)
            >>> s = torch.randint(0, 2, (64, 9), generator=g)
            >>> learner.add(s, torch.zeros(64, dtype=torch.long), s, torch.randn(64, generator=g))
            >>> _ = learner.relearn()
            >>> first = learner.first_searched_dags()
            >>> len(first), first["backward"]
            (8, [])
        """
        first: dict[str, list[tuple[str, str]]] = {}
        for rec in self.history:
            for name, info in rec["actions"].items():
                if name not in first and "score" in info:
                    first[name] = [tuple(e) for e in info["edges"]]
        return {name: first.get(name, []) for name in self.action_names}

    # ---------------------------------------------------------- persistence
    def state_dict(self) -> dict:
        """Everything needed to resume: options, data, DAGs, history, tables."""
        return {
            "options": {
                "n_actions": self.n_actions,
                "mode": self.mode,
                "backend": self.backend,
                "min_rows": self.min_rows,
                "prior": self.prior,
                "synchronous": self.synchronous,
                "max_indegree": self.max_indegree,
                "cardinality": self.cardinality,
                "action_names": list(self.action_names),
            },
            "data": self.data.state_dict(),
            "dags": [[list(e) for e in d] for d in self._dags],
            "from_transfer": list(self._from_transfer),
            "n_relearns": self.n_relearns,
            "history": json.loads(json.dumps(self.history)),
            "tables": None if self._tables is None else self._tables.state_dict(),
        }

    def load_state_dict(self, sd: dict) -> None:
        """Restore a :meth:`state_dict`; the CBNs are refitted from the restored data.

        An action that held its transferred CBN keeps it when this learner has
        the same transfer (call :meth:`transfer` first, as a resumed run does).
        """
        if sd["options"]["n_actions"] != self.n_actions:
            raise ValueError(
                f"state dict is for n_actions={sd['options']['n_actions']}, this learner has {self.n_actions}"
            )
        names = sd["options"].get("action_names")
        if names is not None and list(names) != list(self.action_names):
            raise ValueError(
                f"state dict is for actions {list(names)}, this learner has {self.action_names}"
            )
        self.data.load_state_dict(sd["data"])
        self._dags = [[tuple(e) for e in d] for d in sd["dags"]]
        self.n_relearns = int(sd["n_relearns"])
        self.history = list(sd["history"])
        if sd["tables"] is None:
            self._tables = None
            self.cbns = [None] * self.n_actions
        else:
            kept = list(sd.get("from_transfer") or [False] * self.n_actions)
            for a in range(self.n_actions):
                self._from_transfer[a] = bool(kept[a]) and self._transferred[a] is not None
                if self._from_transfer[a]:
                    self.cbns[a] = self._transferred[a]
                    continue
                rows = self.data.rows(a)
                self.cbns[a] = fit_cbn(self._dags[a], rows, self.schema, prior=self.prior,
                                       known=bool(sd["tables"]["known"][a]))
            self._tables = RewardTables.from_state_dict(sd["tables"], self.schema)
            if self.device is not None:
                self._tables = self._tables.to(self.device)

    def transfer(self, directory, *, relearn: bool = True) -> RewardTables:
        """Start from the CBNs saved in ``directory``: structures and CPTs.

        Reads one CBN per action (:func:`~torchrl_causal.causal.io.load_cbn_folder`:
        the files :meth:`save` writes, e.g. a run's ``cbns/last``) and compiles
        the tables at once, so a gate given :attr:`tables` is active from the
        first frame.

        Args:
            directory: the folder of CBN files, ``<action>.xmlbif`` (or
                ``.xml`` / ``.json``) for every action of this learner.
            relearn: ``True``: keep relearning every ``k`` with the transferred
                structures as the warm start (``mode="learned"``; in
                ``"defined"`` mode the CPTs are refitted on them), an action
                keeping its transferred CBN while its own data is degenerate
                (fewer than ``min_rows`` transitions, or a constant reward).
                ``False``: :attr:`frozen`, :meth:`relearn` changes nothing.

        Returns:
            The compiled tables (also :attr:`tables`).

        Raises:
            ValueError: naming the folder: it does not exist, holds no CBN
                file, a file whose variables are not this learner's schema, or
                not one file per action.

        Example:
            >>> import tempfile
            >>> source = CausalLearner(min_rows=10)
            >>> g = torch.Generator().manual_seed(0)
            >>> s0, s1 = torch.randint(0, 2, (2, 200, 9), generator=g)
            >>> source.add(s0, torch.zeros(200, dtype=torch.long), s1,
            ...            torch.where(s1[:, 5] == 1, 50.0, -9.0))
            >>> _ = source.relearn()
            >>> folder = source.save(tempfile.mkdtemp())
            >>> new = CausalLearner.from_saved(folder, relearn=False)
            >>> torch.equal(new.tables.p_pos, source.tables.p_pos), new.frozen
            (True, True)
        """
        if not isinstance(relearn, bool):
            raise ValueError(f"relearn must be True or False, got {relearn!r}")
        cbns = load_cbn_folder(directory, self.schema, self.action_names)
        self._transferred = [cbns[name] for name in self.action_names]
        self._from_transfer = [True] * self.n_actions
        self.cbns = list(self._transferred)
        self._dags = [list(c.edges) for c in self._transferred]
        self._tables = compile_tables(self.cbns, self.schema, device=self.device)
        self.frozen = not relearn
        self.transferred_from = str(directory)
        return self._tables

    @classmethod
    def from_saved(cls, directory, schema: VariableSchema = DEFAULT_SCHEMA, n_actions: int = 8,
                   *, relearn: bool = True, **kwargs) -> "CausalLearner":
        """A new learner (``CausalLearner(schema, n_actions, **kwargs)``) started by
        :meth:`transfer` from the CBNs in ``directory``."""
        learner = cls(schema, n_actions, **kwargs)
        learner.transfer(directory, relearn=relearn)
        return learner

    def save(self, directory, fmt: str = ".xmlbif") -> Path:
        """Write every action's CBN (``<action><fmt>``) plus ``learner.json`` to ``directory``.

        Args:
            directory: output folder (created).
            fmt: ``".xmlbif"`` (default) or ``".json"``.

        Returns:
            the directory.
        """
        if fmt not in (".xmlbif", ".xml", ".json"):
            raise ValueError(f"fmt must be '.xmlbif', '.xml' or '.json', got {fmt!r}")
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        summary = {"mode": self.mode, "n_relearns": self.n_relearns, "actions": {}}
        for a, name in enumerate(self.action_names):
            cbn = self.cbns[a] or CBN.uniform(self._dags[a], self.schema)
            save_cbn(cbn, directory / f"{name}{fmt}")
            summary["actions"][name] = {
                "file": f"{name}{fmt}",
                "known": cbn.known,
                "n_rows": cbn.n_rows,
                "edges": [list(e) for e in cbn.edges],
                "markov_blanket": cbn.markov_blanket(),
            }
        (directory / "learner.json").write_text(json.dumps(summary, indent=1))
        return directory
