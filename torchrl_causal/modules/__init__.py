"""Policy-side modules: the thesis Q-network and the CBN gate.

* :class:`ThesisQNet` -- thesis Fig. 5.1 (image) and Fig. 5.2 (image + nine values).
* :class:`FeatureQNet` -- the same features without the image (an ablation).
* :class:`MapQNet` -- an egocentric map (:class:`~torchrl_causal.transforms.EgoMap`) and features.
* :class:`EGreedyQValuePolicy` -- ``QValueActor`` + ``EGreedyModule`` computed on tensors
  (what :func:`acting_policy` gives a collector where the layout allows it).
* :class:`CBNGate` -- Algorithm 3 (``"p"``, ``"pn"``) and Algorithm 4 (``"v2"``),
  a drop-in replacement of :class:`torchrl.modules.EGreedyModule` placed after
  :class:`torchrl.modules.QValueActor`.
* :class:`LoopGuard` -- placed last: a deterministic policy never repeats a
  two-move loop (``A, inv(A), A, inv(A)``).
* :class:`RevisitGuard` -- placed after it: never repeats an action from a pose
  it was already taken from while another way out is untried (any cycle).
* :class:`GoalSearch` -- placed last: until the goal has been seen, fly round
  the obstacles of the drone's own map towards a point ahead of the start.
"""

from torchrl_causal.modules.acting import EGreedyQValuePolicy, acting_policy
from torchrl_causal.modules.gate import GATE_VARIANTS, CBNGate
from torchrl_causal.modules.goal_search import GoalSearch
from torchrl_causal.modules.loop_guard import INVERSE_ACTIONS, LoopGuard, RevisitGuard
from torchrl_causal.modules.qnet import FeatureQNet, MapQNet, ThesisQNet

__all__ = ["CBNGate", "EGreedyQValuePolicy", "FeatureQNet", "GATE_VARIANTS", "GoalSearch",
           "INVERSE_ACTIONS", "LoopGuard", "MapQNet", "RevisitGuard", "ThesisQNet",
           "acting_policy"]
