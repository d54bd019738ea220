"""Causal core: expert CBNs, structure learning, compiled inference, comparison, I/O, drawing.

One dynamic Bayesian network per action over the nine scene variables at
``t`` and ``t+1`` plus the binary ``reward`` node (positive iff the env reward
is ``>= 0``). See the user guide page "Causal models" for the full story.

* :mod:`~torchrl_causal.causal.expert` -- the defined (expert) CBNs, one edge rationale each.
* :mod:`~torchrl_causal.causal.data` -- compact per-action transition storage.
* :mod:`~torchrl_causal.causal.structure` -- BIC hill climbing, ``"fast"`` and ``"pgmpy"`` backends.
* :mod:`~torchrl_causal.causal.inference` -- CPTs with a Dirichlet prior, compiled P(reward | state_t).
* :mod:`~torchrl_causal.causal.tables` -- :class:`RewardTables`, what the gate reads.
* :mod:`~torchrl_causal.causal.compare` -- Table 5.1, SHD, Markov-blanket precision/recall.
* :mod:`~torchrl_causal.causal.io` -- XMLBIF / JSON save and load.
* :mod:`~torchrl_causal.causal.draw` -- PNG drawings (t | t+1 | reward).
* :mod:`~torchrl_causal.causal.learner` -- :class:`CausalLearner` (thesis Alg. 2).

Example:
    >>> from torchrl_causal.causal import CausalLearner, expert_dags
    >>> len(expert_dags()["turn_left"])
    16
"""

from torchrl_causal.causal.compare import GraphComparison, compare_dags, shd, table_5_1, write_table_5_1
from torchrl_causal.causal.data import TransitionData
from torchrl_causal.causal.draw import draw_cbn
from torchrl_causal.causal.expert import ExpertEdge, expert_dags, expert_edges
from torchrl_causal.causal.inference import CBN, compile_tables, fit_cbn, markov_blanket
from torchrl_causal.causal.io import load_cbn, save_cbn
from torchrl_causal.causal.learner import CausalLearner
from torchrl_causal.causal.structure import BICScore, LearnedStructure, allowed_edges, learn_structure
from torchrl_causal.causal.tables import RewardTables

__all__ = [
    "CausalLearner",
    "RewardTables",
    "TransitionData",
    "CBN",
    "fit_cbn",
    "compile_tables",
    "markov_blanket",
    "learn_structure",
    "LearnedStructure",
    "BICScore",
    "allowed_edges",
    "expert_dags",
    "expert_edges",
    "ExpertEdge",
    "compare_dags",
    "shd",
    "GraphComparison",
    "table_5_1",
    "write_table_5_1",
    "save_cbn",
    "load_cbn",
    "draw_cbn",
]
