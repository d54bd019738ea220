"""torchrl_causal: TorchRL components for causal RL in visual drone navigation.

Subpackages:
    * :mod:`torchrl_causal.schema` -- the nine discretised scene variables, action names.
    * :mod:`torchrl_causal.envs` -- ``DroneNavEnv`` (MuJoCo) and layouts.
    * :mod:`torchrl_causal.perception` -- goal detectors and the goal measurement.
    * :mod:`torchrl_causal.transforms` -- the feature transforms (``causal_state``).
    * :mod:`torchrl_causal.causal` -- expert CBNs, structure learning, compiled inference.
    * :mod:`torchrl_causal.modules` -- the thesis Q-network, the CBN gate, the acting policy.
    * :mod:`torchrl_causal.data` -- the replay-buffer hook that feeds causal learning.
    * :mod:`torchrl_causal.training` -- Algorithm 1 (``DQNLoop``), evaluation, run records.
    * :mod:`torchrl_causal.pretrained` -- shipped trained policies (``load_policy``).
"""

__version__ = "0.1.0"
