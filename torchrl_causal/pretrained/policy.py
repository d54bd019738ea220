"""A policy described by data: what it reads, how its network and explorer are built.

:class:`PolicySpec` is the one construction path of every trained policy: the
training recipe builds its agent from one, writes it as ``policy.json`` next to
``model.pt`` / ``explorer.pt``, and :func:`load_policy_dir` (and so
:func:`torchrl_causal.pretrained.load_policy`) rebuilds exactly the same
modules from it -- without the recipe, in any TorchRL project.

The observation a policy reads (``inputs``) is the image plus either the nine
discretised variables (``causal_state``, thesis Fig. 5.2) or, for the
generalist, the continuous nine values (``causal_features``) and the last
actions (``action_history``, :class:`~torchrl_causal.transforms.ActionHistory`),
concatenated into ``policy_features`` by TorchRL's ``CatTensors``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

__all__ = ["PolicySpec", "FEATURE_SCALES", "policy_transforms", "build_policy",
           "load_policy_dir", "policy_guards", "POLICY_FILES"]

#: Divisors that bring each input key's values to order 1 inside the Q-network
#: (``causal_features``: five depths and the goal distance in metres / 5, the
#: goal angle in degrees / 30; the 0/1 flags and the altitude as they are).
_CF_SCALE = (5.0, 5.0, 5.0, 5.0, 5.0, 1.0, 5.0, 30.0, 1.0)
FEATURE_SCALES: dict[str, tuple[float, ...] | None] = {
    "causal_state": None,
    "causal_features": _CF_SCALE,
    "action_history": None,
    "feature_history": _CF_SCALE,  # per frame of the stack
    "goal_memory": None,  # EgoMap writes it at order 1
    "map_clearance": None,  # EgoMap, in [0, 1]
}
#: Inputs that are maps, read by the convolutions of :class:`~torchrl_causal.modules.MapQNet`.
MAP_INPUTS = ("ego_map",)
#: Files of a policy folder.
POLICY_FILES = {"spec": "policy.json", "model": "model.pt", "explorer": "explorer.pt"}
_EXPLORERS = ("egreedy", "cbn_gate")


@dataclass
class PolicySpec:
    """Everything needed to rebuild a trained policy's modules.

    Args:
        image_size: side of the square ``pixels`` the network reads.
        n_actions: size of the action space.
        inputs: keys read beside ``pixels`` (empty: the image-only Fig. 5.1
            network); among ``causal_state``, ``causal_features``,
            ``action_history``, ``feature_history``, ``goal_memory``,
            ``map_clearance`` and the map
            ``ego_map`` (see ``ego_map``).
        history: length of :class:`~torchrl_causal.transforms.ActionHistory`
            (needed when ``"action_history"`` is an input).
        frames: frames of ``causal_features`` stacked by TorchRL's ``CatFrames``
            into ``feature_history`` (needed when it is an input): a memory of
            what was seen, which, unlike the action history, does not hand the
            student its own last action to copy.
        features: keyword arguments of
            :func:`~torchrl_causal.transforms.make_causal_transforms`.
        explorer: ``"egreedy"`` (TorchRL ``EGreedyModule``) or ``"cbn_gate"``
            (:class:`~torchrl_causal.modules.CBNGate`).
        gate_mode: the gate's algorithm (``"p"``, ``"pn"``, ``"v2"``).
        prob_causal_model, threshold: the gate's parameters (thesis sec. 4.5).
        eps_init, eps_end, annealing_frames: exploration schedule.
        image: the Q-network reads the image (:class:`~torchrl_causal.modules.ThesisQNet`);
            False: the features alone (:class:`~torchrl_causal.modules.FeatureQNet`,
            an ablation).
        ego_map: keyword arguments of :class:`~torchrl_causal.transforms.EgoMap`,
            appended to the stack when ``"ego_map"``, ``"goal_memory"`` or
            ``"map_clearance"`` is an input; ``"ego_map"`` as an input makes the network a
            :class:`~torchrl_causal.modules.MapQNet` (with ``image=False``).
        shield: act only on moves that :class:`~torchrl_causal.transforms.EgoMap`'s
            ``action_mask`` allows (the Q-values of the others are masked out
            in the actor, and the explorer draws among the allowed ones);
            needs an EgoMap input.
        loop_guard: append :class:`~torchrl_causal.modules.LoopGuard` after the
            explorer: the policy never repeats a two-move loop
            (``A, inv(A), A, inv(A)``); needs ``history >= 4``.
        revisit_guard: append :class:`~torchrl_causal.transforms.VisitMemory` to
            the transforms and :class:`~torchrl_causal.modules.RevisitGuard`
            after the loop guard: the policy never takes an action again from
            a dead-reckoned pose it was taken from while another allowed one is
            untried there (cycles of any length); needs an EgoMap input.
        goal_search: 0 (off), or a distance (m): append
            :class:`~torchrl_causal.modules.GoalSearch` last -- until the goal
            has been in view, the drone flies round its map's obstacles towards
            a point this far ahead of its start; needs an EgoMap input.
        provenance: free-form record (command, seed, frames, commit, figures).

    Example:
        >>> spec = PolicySpec(inputs=["causal_features", "action_history"], history=4)
        >>> spec.n_features, spec.actor_keys
        (41, ['pixels', 'policy_features'])
    """

    image_size: int = 84
    n_actions: int = 8
    inputs: list = field(default_factory=lambda: ["causal_state"])
    history: int = 0
    frames: int = 0
    features: dict = field(default_factory=dict)
    explorer: str = "cbn_gate"
    gate_mode: str | None = "v2"
    prob_causal_model: float = 0.7
    threshold: float = 0.75
    eps_init: float = 1.0
    eps_end: float = 0.05
    annealing_frames: int = 8000
    image: bool = True
    ego_map: dict = field(default_factory=dict)
    shield: bool = False
    loop_guard: bool = False
    revisit_guard: bool = False
    goal_search: float = 0.0
    provenance: dict = field(default_factory=dict)

    def __post_init__(self):
        self.inputs = list(self.inputs)
        unknown = [k for k in self.inputs if k not in FEATURE_SCALES and k not in MAP_INPUTS]
        if unknown:
            raise ValueError(f"PolicySpec.inputs has unknown keys {unknown}: expected keys among "
                             f"{sorted(FEATURE_SCALES) + list(MAP_INPUTS)}")
        if "ego_map" in self.inputs and self.image:
            raise ValueError("PolicySpec: 'ego_map' takes the image's place in the network "
                             "(MapQNet); set image=False")
        self.ego_map = dict(self.ego_map)
        if self.shield and not self.uses_ego_map:
            raise ValueError("PolicySpec.shield=True needs EgoMap's action_mask: give an input "
                             "among 'ego_map', 'goal_memory', 'map_clearance'")
        if "action_history" in self.inputs and not (isinstance(self.history, int)
                                                    and self.history >= 1):
            raise ValueError(f"PolicySpec.history must be an int >= 1 when 'action_history' is "
                             f"an input, got {self.history!r}")
        if self.loop_guard and not (isinstance(self.history, int) and self.history >= 4):
            raise ValueError(f"PolicySpec.loop_guard=True reads the last four actions: it needs "
                             f"history >= 4, got {self.history!r}")
        if not isinstance(self.revisit_guard, bool):
            raise ValueError(f"PolicySpec.revisit_guard must be a bool, got "
                             f"{self.revisit_guard!r}")
        if self.revisit_guard and not self.uses_ego_map:
            raise ValueError("PolicySpec.revisit_guard needs EgoMap's dead-reckoned pose: give "
                             "an input among 'ego_map', 'goal_memory', 'map_clearance'")
        gs = self.goal_search
        if isinstance(gs, bool) or not isinstance(gs, (int, float)) or not math.isfinite(gs) \
                or gs < 0:
            raise ValueError(f"PolicySpec.goal_search must be 0 (off) or a distance > 0 (m), "
                             f"got {gs!r}")
        if gs > 0 and not self.uses_ego_map:
            raise ValueError("PolicySpec.goal_search needs EgoMap's map and pose: give an input "
                             "among 'ego_map', 'goal_memory', 'map_clearance'")
        if "feature_history" in self.inputs and not (isinstance(self.frames, int)
                                                     and self.frames >= 2):
            raise ValueError(f"PolicySpec.frames must be an int >= 2 when 'feature_history' "
                             f"is an input, got {self.frames!r}")
        if self.explorer not in _EXPLORERS:
            raise ValueError(f"PolicySpec.explorer must be one of {_EXPLORERS}, got "
                             f"{self.explorer!r}")
        if not self.image and not self.inputs:
            raise ValueError("PolicySpec.image=False needs inputs (the features to read)")
        if self.explorer == "cbn_gate" and "causal_state" not in self.features_written():
            raise ValueError("PolicySpec.explorer='cbn_gate' needs the feature stack "
                             "(causal_state): give inputs beside the image")

    def features_written(self) -> list[str]:
        """Keys the policy's transforms write (empty for the image-only network)."""
        if not self.inputs:
            return []
        keys = ["causal_features", "causal_state"]
        if self.history:
            keys.append("action_history")
        if self.frames:
            keys.append("feature_history")
        if self.uses_ego_map:
            keys += ["ego_map", "goal_memory", "map_clearance", "action_mask"]
        return keys

    @property
    def uses_ego_map(self) -> bool:
        """Whether an :class:`~torchrl_causal.transforms.EgoMap` is in the feature stack."""
        return bool({"ego_map", "goal_memory", "map_clearance"} & set(self.inputs))

    @property
    def vector_inputs(self) -> list[str]:
        """The inputs concatenated into the feature vector (all but the maps)."""
        return [k for k in self.inputs if k not in MAP_INPUTS]

    def _width(self, key: str) -> int:
        return {"causal_state": 9, "causal_features": 9, "feature_history": 9 * self.frames,
                "action_history": self.history * self.n_actions, "goal_memory": 6,
                "map_clearance": 4}[key]

    @property
    def n_features(self) -> int:
        """Width of the vector the Q-network reads beside the image."""
        return sum(self._width(k) for k in self.vector_inputs)

    @property
    def actor_keys(self) -> list[str]:
        """The actor's ``in_keys``."""
        image = ["pixels"] if self.image else []
        if not self.inputs:
            return ["pixels"]
        if "ego_map" in self.inputs:
            image = ["ego_map"]
        vec = self.vector_inputs
        if not vec:
            return image
        if len(vec) == 1:
            return image + [vec[0]]
        return image + ["policy_features"]

    def feature_scale(self) -> list[float] | None:
        """Per-value divisors of the Q-network's features (None: all ones)."""
        scale, any_set = [], False
        for k in self.vector_inputs:
            s = FEATURE_SCALES[k]
            n = self._width(k)
            any_set |= s is not None
            scale += list(s) * (n // len(s)) if s is not None else [1.0] * n
        return scale if any_set else None

    def to_json(self) -> str:
        """The spec as JSON (what ``policy.json`` holds)."""
        return json.dumps(asdict(self), indent=2, default=str)

    @classmethod
    def from_json(cls, text: str) -> "PolicySpec":
        """Parses :meth:`to_json`'s output; unknown fields are an error naming them."""
        data = json.loads(text)
        known = set(cls.__dataclass_fields__)
        extra = sorted(set(data) - known)
        if extra:
            raise ValueError(f"policy.json has unknown fields {extra}")
        return cls(**data)


def policy_transforms(spec: PolicySpec, env=None, seed: int | None = None) -> list:
    """The transforms that write what ``spec``'s actor reads (empty for the image-only net).

    Example:
        >>> ts = policy_transforms(PolicySpec(inputs=["causal_features", "action_history"],
        ...                                   history=2))
        >>> [type(t).__name__ for t in ts]
        ['Compose', 'ActionHistory', 'CatTensors']
    """
    from torchrl.envs import CatFrames, CatTensors

    from ..transforms import make_causal_transforms
    from ..transforms.history import ActionHistory

    if not spec.inputs:
        return []
    options = dict(spec.features)
    if seed is not None:
        options.setdefault("seed", seed)
    out = [make_causal_transforms(env, **options)]
    if spec.history:
        out.append(ActionHistory(spec.n_actions, length=spec.history))
    if spec.frames:
        out.append(CatFrames(N=spec.frames, dim=-1, in_keys=["causal_features"],
                             out_keys=["feature_history"]))
    if spec.uses_ego_map:
        from ..transforms.egomap import EgoMap

        out.append(EgoMap(**spec.ego_map))
        if spec.revisit_guard:
            from ..transforms.visits import VisitMemory

            out.append(VisitMemory(spec.n_actions))
    if len(spec.vector_inputs) > 1:
        out.append(CatTensors(list(spec.vector_inputs), "policy_features", del_keys=False))
    return out


def with_policy_features(spec: PolicySpec, env, seed: int | None = None):
    """``env`` wrapped in :func:`policy_transforms` (``env`` itself when there are none).

    Example:
        >>> from torchrl_causal.envs import DroneNavEnv
        >>> spec = PolicySpec(inputs=["causal_features", "action_history"], history=2)
        >>> env = with_policy_features(spec, DroneNavEnv(image_size=32, seed=0))
        >>> env.reset()["policy_features"].shape
        torch.Size([25])
    """
    from torchrl.envs import TransformedEnv

    transforms = policy_transforms(spec, env, seed=seed)
    if not transforms:
        return env
    tenv = TransformedEnv(env, transforms[0])
    for t in transforms[1:]:
        tenv.append_transform(t)
    return tenv


def build_policy(spec: PolicySpec, action_spec, *, device="cpu", seed: int | None = None):
    """``(actor, explorer)``: the Q-network in a ``QValueActor`` and its explorer.

    Args:
        spec: the :class:`PolicySpec`.
        action_spec: the env's (unbatched) action spec.
        device: device of the parameters and the gate.
        seed: seeds the explorer's random draws.

    Example:
        >>> from torchrl.data import Categorical
        >>> actor, explorer = build_policy(PolicySpec(), Categorical(8))
        >>> type(explorer).__name__, actor.in_keys
        ('CBNGate', ['pixels', 'causal_state'])
    """
    from torchrl.modules import EGreedyModule, QValueActor

    from ..modules import CBNGate, FeatureQNet, MapQNet, ThesisQNet

    if "ego_map" in spec.inputs:
        from ..transforms.egomap import EgoMap

        net = MapQNet(spec.n_actions, spec.n_features, device=device,
                      map_size=EgoMap(**spec.ego_map).size, feature_scale=spec.feature_scale())
    elif spec.image:
        net = ThesisQNet(spec.n_actions, n_features=spec.n_features, device=device,
                         image_size=(spec.image_size, spec.image_size),
                         feature_scale=spec.feature_scale())
    else:
        net = FeatureQNet(spec.n_actions, spec.n_features, device=device,
                          feature_scale=spec.feature_scale())
    mask = {"action_mask_key": "action_mask"} if spec.shield else {}
    actor = QValueActor(net, in_keys=spec.actor_keys, spec=action_spec, **mask)
    eps = dict(eps_init=spec.eps_init, eps_end=spec.eps_end,
               annealing_num_steps=spec.annealing_frames)
    if spec.explorer == "egreedy":
        return actor, EGreedyModule(action_spec, **eps, **mask)
    gate = CBNGate(spec.gate_mode, prob_causal_model=spec.prob_causal_model,
                   threshold=spec.threshold, seed=seed, device=device, **eps, **mask)
    return actor, gate


def load_policy_dir(folder, *, env=None, device="cpu"):
    """The policy saved in ``folder`` (``policy.json``, ``model.pt``, ``explorer.pt``).

    Args:
        folder: a policy folder (a finished run folder of ``recipes/train.py``,
            or a shipped one).
        env: the env to act in, *without* the policy's feature transforms
            (they are appended); ``None``: no env is built.
        device: device of the networks, the gate and the env outputs.

    Returns:
        ``(policy, env, spec)``: ``TensorDictSequential(actor, explorer)``, the
        wrapped env (or None), the :class:`PolicySpec`.

    Raises:
        FileNotFoundError: a policy file is missing (named).

    Example:
        >>> from torchrl_causal.envs import DroneNavEnv
        >>> from torchrl_causal.pretrained import policy_dir
        >>> policy, env, spec = load_policy_dir(policy_dir("thesis"), env=DroneNavEnv(seed=0))
        >>> spec.actor_keys, type(policy[1]).__name__
        (['pixels', 'causal_state'], 'CBNGate')
    """
    from tensordict.nn import TensorDictSequential

    folder = Path(folder)
    files = {name: folder / rel for name, rel in POLICY_FILES.items()}
    for name, path in files.items():
        if not path.is_file():
            raise FileNotFoundError(f"policy folder {str(folder)!r} has no {name} file "
                                    f"{str(path)!r}")
    spec = PolicySpec.from_json(files["spec"].read_text())
    wrapped = with_policy_features(spec, env) if env is not None else None
    if env is not None:
        action_spec = env.action_spec_unbatched if hasattr(env, "action_spec_unbatched") \
            else env.action_spec
    else:
        from torchrl.data import Categorical

        action_spec = Categorical(spec.n_actions)
    actor, explorer = build_policy(spec, action_spec, device=device)
    actor.load_state_dict(torch.load(files["model"], map_location=device, weights_only=False))
    explorer.load_state_dict(torch.load(files["explorer"], map_location=device,
                                        weights_only=False))
    return TensorDictSequential(actor, explorer, *policy_guards(spec)), wrapped, spec


def policy_guards(spec: PolicySpec) -> list:
    """The modules placed after the explorer (a :class:`~torchrl_causal.modules.LoopGuard`
    when ``spec.loop_guard``, a :class:`~torchrl_causal.modules.RevisitGuard` when
    ``spec.revisit_guard``, then a :class:`~torchrl_causal.modules.GoalSearch` when
    ``spec.goal_search``), at acting time, in training and evaluation alike.

    Example:
        >>> spec = PolicySpec(inputs=["causal_features", "action_history"], history=4,
        ...                   loop_guard=True)
        >>> [type(m).__name__ for m in policy_guards(spec)]
        ['LoopGuard']
    """
    from ..modules import GoalSearch, LoopGuard, RevisitGuard

    mask_key = "action_mask" if spec.shield else None
    out = [LoopGuard(spec.n_actions, action_mask_key=mask_key)] if spec.loop_guard else []
    if spec.revisit_guard:
        out.append(RevisitGuard(spec.n_actions, action_mask_key=mask_key))
    if spec.goal_search:
        out.append(GoalSearch(spec.goal_search,
                              resolution=float(spec.ego_map.get("resolution", 0.15)),
                              action_mask_key=mask_key))
    return out
