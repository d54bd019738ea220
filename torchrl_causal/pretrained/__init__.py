"""Trained policies shipped with the package, loadable in one call.

* ``"thesis"`` -- CBN-DQN V2 trained on the thesis scene by ``make train``
  (greedy success 1.00 there; it does not generalise to other layouts).
* ``"generalist"`` -- trained across random training-split layouts by
  ``make generalist`` and selected on a validation set of training-split
  layouts; flies held-out layouts it has never seen.

Each name is a folder under ``torchrl_causal/pretrained/policies/`` holding
``policy.json`` (a :class:`~torchrl_causal.pretrained.policy.PolicySpec`),
``model.pt``, ``explorer.pt`` and ``provenance.json`` (command, seed, frames,
commit and the figures measured when it was made).

Example:
    >>> from torchrl_causal.pretrained import available, load_policy
    >>> "thesis" in available()
    True
    >>> from torchrl_causal.envs import DroneNavEnv
    >>> import torch
    >>> _ = torch.manual_seed(0)  # the V2 gate redraws vetoed actions at random
    >>> policy, env = load_policy("thesis", base_env=DroneNavEnv(seed=0))
    >>> td = env.rollout(200, policy, break_when_any_done=True)
    >>> bool(td["next", "reached"][-1])
    True
"""

from __future__ import annotations

import json
from pathlib import Path

from .policy import (
    FEATURE_SCALES,
    POLICY_FILES,
    PolicySpec,
    build_policy,
    policy_guards,
    load_policy_dir,
    policy_transforms,
    with_policy_features,
)

__all__ = ["available", "load_policy", "policy_dir", "provenance", "PolicySpec",
           "build_policy", "policy_guards", "policy_transforms", "with_policy_features", "load_policy_dir",
           "FEATURE_SCALES", "POLICY_FILES", "POLICIES_DIR"]

#: Where the shipped policies live (package data).
POLICIES_DIR = Path(__file__).resolve().parent / "policies"


def available() -> list[str]:
    """Names of the shipped policies.

    Example:
        >>> isinstance(available(), list)
        True
    """
    if not POLICIES_DIR.is_dir():
        return []
    return sorted(p.name for p in POLICIES_DIR.iterdir()
                  if p.is_dir() and (p / POLICY_FILES["spec"]).is_file())


def policy_dir(name: str) -> Path:
    """The folder of the shipped policy ``name``.

    Raises:
        ValueError: an unknown name (the message lists the available ones).

    Example:
        >>> (policy_dir("thesis") / "policy.json").is_file()
        True
    """
    names = available()
    if name not in names:
        raise ValueError(f"Unknown pretrained policy name={name!r}: available are {names}")
    return POLICIES_DIR / name


def provenance(name: str) -> dict:
    """How the shipped policy ``name`` was made (command, seed, frames, commit, figures).

    Example:
        >>> provenance("thesis")["variant"]
        'cbn_v2'
    """
    path = policy_dir(name) / "provenance.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def load_policy(name: str = "generalist", base_env=None, device: str = "cpu"):
    """A shipped policy and an env wrapped in its feature stack.

    Args:
        name: one of :func:`available` (``"thesis"``, ``"generalist"``).
        base_env: any :class:`~torchrl_causal.envs.DroneNavEnv` (or another env
            writing the same keys, e.g. :class:`~torchrl_causal.envs.TelloEnv`);
            default: held-out random layouts (the thesis scene for
            ``"thesis"``).
        device: device of the networks and the env outputs.

    Returns:
        ``(policy, env)``: a ``TensorDictSequential(actor, explorer)`` (greedy
        under ``set_exploration_type(DETERMINISTIC)``, the CBN gate still
        applies) and ``base_env`` wrapped in the policy's feature transforms.

    Raises:
        ValueError: an unknown ``name`` (the available names are listed).

    Example:
        >>> from torchrl.envs.utils import ExplorationType, set_exploration_type
        >>> policy, env = load_policy("thesis")
        >>> with set_exploration_type(ExplorationType.DETERMINISTIC):
        ...     td = env.rollout(200, policy, break_when_any_done=True)
        >>> bool(td["next", "reached"][-1]), td.shape[0] <= 16
        (True, True)
    """
    folder = policy_dir(name)
    if base_env is None:
        from ..envs import DroneNavEnv

        layout = "thesis" if name == "thesis" else "random"
        base_env = DroneNavEnv(layout, split="heldout", device=device)
    policy, env, _ = load_policy_dir(folder, env=base_env, device=device)
    return policy, env
