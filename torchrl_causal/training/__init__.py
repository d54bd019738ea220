"""Training: thesis Algorithm 1 as a library part, its evaluation and its run records.

* :class:`DQNLoop` / :class:`LoopConfig` -- Alg. 1 for any env, Q-network and
  schema: collector, replay buffer (+ causal-learning hook), DQN loss, target
  sync, the gate's epsilon, evaluation, checkpoints and exact resume
  (:mod:`torchrl_causal.training.loop`).
* :class:`StatefulDQNLoss` -- TorchRL's ``DQNLoss``, bit for bit, without its
  per-call parameter swaps (:mod:`torchrl_causal.training.loss`).
* :func:`dqn_optimizer` / :func:`fused_supported` -- Adam (fused where it runs) or
  the thesis's RMSprop (:mod:`torchrl_causal.training.optim`).
* :func:`evaluate` / :func:`seed_transforms` -- greedy evaluation
  (:mod:`torchrl_causal.training.evaluation`).
* :class:`OracleImitation` / :class:`ImitationConfig` -- a teacher phase:
  DAgger from the shortest-path oracle into the Q-network (DQfD margin loss)
  (:mod:`torchrl_causal.training.imitation`).
* :func:`plot_flight_map` / :func:`plot_flight_maps` -- evaluated episodes drawn
  from above (:mod:`torchrl_causal.training.flightmap`).
* :func:`record_episodes` -- evaluated episodes as one MP4: the onboard camera
  beside a MuJoCo chase view, with the action, the gate's decision and the
  outcome drawn on it (:mod:`torchrl_causal.training.video`).
* :class:`EpisodeCSV`, :func:`atomic_save`, :func:`rng_state`,
  :func:`set_rng_state` -- resumable run records (:mod:`torchrl_causal.training.records`).

Example:
    >>> from torchrl_causal.training import DQNLoop, LoopConfig
    >>> LoopConfig(total_frames=4000).target_update_interval
    250
"""

from torchrl_causal.training.evaluation import (
    OUTCOME_KEYS,
    env_max_steps,
    evaluate,
    seed_transforms,
    spl_of,
)
from torchrl_causal.training.flightmap import plot_flight_map, plot_flight_maps
from torchrl_causal.training.imitation import ImitationConfig, OracleImitation, margin_loss
from torchrl_causal.training.loop import RUN_FILES, DQNLoop, LoopConfig
from torchrl_causal.training.loss import StatefulDQNLoss
from torchrl_causal.training.optim import OPTIMIZERS, dqn_optimizer, fused_supported
from torchrl_causal.training.records import EpisodeCSV, atomic_save, rng_state, set_rng_state
from torchrl_causal.training.video import OUTCOME_LABELS, record_episodes

__all__ = [
    "DQNLoop",
    "LoopConfig",
    "StatefulDQNLoss",
    "OPTIMIZERS",
    "dqn_optimizer",
    "fused_supported",
    "RUN_FILES",
    "evaluate",
    "spl_of",
    "seed_transforms",
    "OracleImitation",
    "plot_flight_map",
    "plot_flight_maps",
    "record_episodes",
    "OUTCOME_LABELS",
    "ImitationConfig",
    "margin_loss",
    "env_max_steps",
    "OUTCOME_KEYS",
    "EpisodeCSV",
    "atomic_save",
    "rng_state",
    "set_rng_state",
]
