"""Replay-buffer side: the hook that feeds causal learning.

* :class:`CausalLearningHook` -- a replay-buffer transform that appends every
  stored transition to a :class:`~torchrl_causal.causal.CausalLearner`, relearns
  every ``k`` frames (optionally in a background thread) and pushes the new
  compiled tables to the registered :class:`~torchrl_causal.modules.CBNGate`\\ s.
* :class:`FilledRowsCheckpointer` -- a replay-buffer storage checkpointer that
  writes only the filled rows, file to file (no second in-memory copy of a
  memory-mapped buffer at mid-run checkpoints).
"""

from torchrl_causal.data.checkpoint import FilledRowsCheckpointer, install_filled_rows_checkpointer
from torchrl_causal.data.hook import CausalLearningHook

__all__ = ["CausalLearningHook", "FilledRowsCheckpointer", "install_filled_rows_checkpointer"]
