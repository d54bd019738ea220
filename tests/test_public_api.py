"""Outside-in tests: the public components dropped into a user's own TorchRL project.

Everything here is imported from the packages' public exports, exactly as a
user would, and wired to envs written in this file that are not drones:

* ``CorridorEnv``: a 1-D corridor with 4 actions and its own 3-variable schema
  (cardinalities 2, 3, 2), where one action ("push") is punished everywhere but
  at the right wall. A ``CausalLearner`` + ``CBNGate`` + ``CausalLearningHook``
  learn that from a torchrl ``Collector`` run and the gate then vetoes "push".
* ``RoomEnv``: a camera env that renders pixels, depth and an altitude but
  measures no goal; the feature stack (``DepthSections``, ``GoalFeatures`` with
  a custom colour-blob ``GoalDetector``, ``Discretize``) runs on it.
* The package surface: cheap root import, documented subpackages, docstrings.
"""

from __future__ import annotations

import importlib
import inspect
import subprocess
import sys

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import (
    Bounded,
    Categorical,
    Composite,
    LazyTensorStorage,
    MultiCategorical,
    TensorDictReplayBuffer,
    Unbounded,
)
from torchrl.envs import EnvBase, TransformedEnv, Compose
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type
from torchrl.modules import MLP, QValueActor

from torchrl_causal.causal import CausalLearner, RewardTables
from torchrl_causal.data import CausalLearningHook
from torchrl_causal.modules import CBNGate
from torchrl_causal.perception.goal import GoalDetector, GoalMeter
from torchrl_causal.schema import DEFAULT_SCHEMA, Variable, VariableSchema
from torchrl_causal.transforms import DepthSections, Discretize, GoalFeatures

# --------------------------------------------------------------------------- corridor

CORRIDOR_SCHEMA = VariableSchema(
    (
        Variable("lamp", ("off", "on"), "a lamp the agent can toggle"),
        Variable("zone", ("left_wall", "middle", "right_wall"), "where in the corridor"),
        Variable("parity", ("even", "odd"), "step counter parity (irrelevant noise)"),
    )
)
TOGGLE, RIGHT, LEFT, PUSH = range(4)
LENGTH = 4  # cells 0..3: 0 = left wall, 3 = right wall


class CorridorEnv(EnvBase):
    """A 1-D corridor. Actions: 0 toggle the lamp (reward 0), 1 move right, 2 move
    left (+1, or -1 when bumping into a wall), 3 push (+1 at the right wall,
    -5 anywhere else). Episodes last 10 steps; the start cell is random."""

    def __init__(self, seed: int = 0):
        super().__init__(batch_size=torch.Size([]))
        self.observation_spec = Composite(
            observation=Unbounded(shape=(4,), dtype=torch.float32),
            corridor_state=MultiCategorical(
                nvec=list(CORRIDOR_SCHEMA.cardinalities), dtype=torch.int64
            ),
        )
        self.action_spec = Categorical(4)
        self.reward_spec = Unbounded(shape=(1,))
        self._set_seed(seed)
        self.x, self.lamp, self.t = 0, 0, 0

    def _obs(self) -> TensorDict:
        zone = 0 if self.x == 0 else (2 if self.x == LENGTH - 1 else 1)
        state = torch.tensor([self.lamp, zone, self.t % 2], dtype=torch.int64)
        obs = torch.tensor(
            [self.x / (LENGTH - 1), float(self.lamp), float(self.t % 2), 1.0]
        )
        return TensorDict(observation=obs, corridor_state=state, batch_size=[])

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        self.x = int(torch.randint(0, LENGTH, (), generator=self.rng))
        self.lamp, self.t = 0, 0
        out = self._obs()
        out.set("done", torch.zeros(1, dtype=torch.bool))
        out.set("terminated", torch.zeros(1, dtype=torch.bool))
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        a = int(tensordict.get("action"))
        reward = 0.0
        if a == TOGGLE:
            self.lamp = 1 - self.lamp
        elif a in (RIGHT, LEFT):
            nx = self.x + (1 if a == RIGHT else -1)
            if 0 <= nx < LENGTH:
                self.x, reward = nx, 1.0
            else:
                reward = -1.0
        else:  # PUSH
            reward = 1.0 if self.x == LENGTH - 1 else -5.0
        self.t += 1
        out = self._obs()
        out.set("reward", torch.tensor([reward]))
        out.set("done", torch.tensor([self.t >= 10]))
        out.set("terminated", torch.zeros(1, dtype=torch.bool))
        return out

    def _set_seed(self, seed: int | None):
        self.rng = torch.Generator().manual_seed(0 if seed is None else int(seed))
        return seed


def test_corridor_env_specs():
    check_env_specs(CorridorEnv(seed=1))


def test_gate_and_hook_on_custom_env_and_schema():
    torch.manual_seed(0)
    env = CorridorEnv(seed=0)
    n_actions = env.action_spec.n
    learner = CausalLearner(schema=CORRIDOR_SCHEMA, n_actions=n_actions, min_rows=10)
    gate = CBNGate(
        "pn",
        eps_init=0.6,
        eps_end=0.6,  # keep exploring: every action must be tried in every zone
        n_actions=n_actions,
        action_value_key="q",
        causal_state_key="corridor_state",
        chosen_action_value_key="chosen_q",
        diagnostics_prefix="cbn_",
        seed=0,
    )
    actor = QValueActor(
        MLP(in_features=4, out_features=n_actions, num_cells=[16]),
        in_keys=["observation"],
        spec=env.action_spec,
        action_value_key="q",
    )
    policy = TensorDictSequential(actor, gate)
    hook = CausalLearningHook(
        learner,
        k=100,
        gates=[gate],
        causal_state_key="corridor_state",
        next_causal_state_key=("next", "corridor_state"),
    )
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), batch_size=32)
    rb.append_transform(hook)
    collector = Collector(
        env, policy, frames_per_batch=50, total_frames=400, auto_register_policy_transforms=False
    )
    try:
        for batch in collector:
            flat = batch.reshape(-1)
            assert ((flat["action"] >= 0) & (flat["action"] < n_actions)).all()
            # the executed action is the proposal unless the gate vetoed or replaced it
            changed = flat["cbn_vetoed"] | flat["cbn_replaced"]
            assert (flat["action"][~changed] == flat["cbn_dqn_action"][~changed]).all()
            rb.extend(flat)
    finally:
        collector.shutdown()

    assert hook.frames == 400 == len(rb)
    assert learner.n_relearns == 4  # at 100, 200, 300, 400 frames
    tables = gate.tables
    assert isinstance(tables, RewardTables) and tables is learner.tables
    assert tables.schema is CORRIDOR_SCHEMA
    assert tuple(tables.p_pos.shape) == (n_actions, CORRIDOR_SCHEMA.n_states) == (4, 12)
    # an action's model is known iff it was taken >= min_rows times and its reward
    # class varied: toggle always gives 0 (positive) -> unknown; push varies -> known
    stored = rb[:]
    for a in range(n_actions):
        r = stored["next", "reward"][stored["action"] == a]
        varied = r.numel() >= 10 and bool((r < 0).any() and (r >= 0).any())
        assert tables.known[a].item() is varied, (a, r.flatten().tolist())
    assert not tables.known[TOGGLE] and tables.known[PUSH]
    # the gate consulted its tables after the first relearn, never before it
    assert not stored["cbn_consulted"][:100].any()
    assert stored["cbn_consulted"][100:].any()

    # P(pos | s, push): low away from the right wall, high at the right wall
    states = torch.as_tensor(CORRIDOR_SCHEMA.all_states())
    p_pos, p_neg, known = tables.lookup(states)
    at_wall = states[:, CORRIDOR_SCHEMA.index("zone")] == 2
    seen = torch.zeros(CORRIDOR_SCHEMA.n_states, dtype=torch.bool)
    pushed = stored["action"] == PUSH
    seen[CORRIDOR_SCHEMA.state_index(stored["corridor_state"][pushed])] = True
    assert (p_pos[~at_wall & seen, PUSH] < 0.25).all(), p_pos[:, PUSH]
    assert (p_pos[at_wall & seen, PUSH] > 0.75).all(), p_pos[:, PUSH]
    assert torch.allclose(p_neg, 1 - p_pos)
    assert known[:, PUSH].all()

    # A DQN that always prefers "push": with the tables the gate vetoes it in the
    # states where its model says punishment, with prob. ProbCausalModel (0.7).
    reps = 400
    codes = states.repeat_interleave(reps, 0)
    q = torch.zeros(codes.shape[0], n_actions)
    q[:, PUSH] = 1.0
    td = TensorDict(q=q, corridor_state=codes, batch_size=[codes.shape[0]])
    with set_exploration_type(ExplorationType.DETERMINISTIC):  # eps = 0, CBN still applies
        td = gate(td)
    vetoed = td["cbn_vetoed"].reshape(-1, reps).float().mean(-1)
    risky = ~at_wall & seen
    assert risky.any()
    assert ((vetoed[risky] > 0.6) & (vetoed[risky] < 0.8)).all(), vetoed
    assert (vetoed[at_wall & seen] == 0).all()
    assert (td["action"][td["cbn_vetoed"]] != PUSH).all()
    assert torch.equal(td["cbn_consulted"], td["cbn_consulted"] & ~td["cbn_explored"])


# --------------------------------------------------------------------------- feature stack

H = W = 32


class RedBlobDetector(GoalDetector):
    """A user's own detector: the box around saturated red pixels, score = 1 if any."""

    def detect(self, pixels, depth=None, **gt):
        red = (pixels[..., 0] > 200) & (pixels[..., 1] < 50) & (pixels[..., 2] < 50)
        B = pixels.shape[0]
        boxes = torch.zeros(B, 1, 4)
        scores = torch.zeros(B, 1)
        for i in range(B):
            ys, xs = torch.nonzero(red[i], as_tuple=True)
            if ys.numel():
                boxes[i, 0] = torch.stack([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]).float()
                scores[i, 0] = 1.0
        return boxes, scores


class RoomEnv(EnvBase):
    """A camera in a room: pixels, metric depth and an altitude, no goal measurement.

    The state is the left column of an 8x8 red marker (out of view past the
    right edge); the wall is 3 m away, the marker 1.2 m. Actions: 0 shift the
    marker 6 px left, 1 right.
    """

    def __init__(self):
        super().__init__(batch_size=torch.Size([]))
        self.observation_spec = Composite(
            pixels=Bounded(0, 255, shape=(H, W, 3), dtype=torch.uint8),
            depth=Unbounded(shape=(H, W), dtype=torch.float32),
            height=Unbounded(shape=(1,), dtype=torch.float32),
        )
        self.action_spec = Categorical(2)
        self.reward_spec = Unbounded(shape=(1,))
        self.col = 8

    def _render(self) -> TensorDict:
        pixels = torch.full((H, W, 3), 90, dtype=torch.uint8)
        depth = torch.full((H, W), 3.0)
        if 0 <= self.col <= W - 8:
            pixels[12:20, self.col : self.col + 8] = torch.tensor([255, 0, 0], dtype=torch.uint8)
            depth[12:20, self.col : self.col + 8] = 1.2
        return TensorDict(pixels=pixels, depth=depth, height=torch.tensor([1.0]), batch_size=[])

    def _reset(self, tensordict=None, **kwargs):
        self.col = 8
        out = self._render()
        out.set("done", torch.zeros(1, dtype=torch.bool))
        out.set("terminated", torch.zeros(1, dtype=torch.bool))
        return out

    def _step(self, tensordict):
        self.col += -6 if int(tensordict["action"]) == 0 else 6
        if self.col < -8 or self.col > W:
            self.col = 8
        out = self._render()
        out.set("reward", torch.zeros(1))
        out.set("done", torch.zeros(1, dtype=torch.bool))
        out.set("terminated", torch.zeros(1, dtype=torch.bool))
        return out

    def _set_seed(self, seed):
        return seed


def _constant_policy(action: int) -> TensorDictModule:
    return TensorDictModule(
        lambda h: torch.full(h.shape[:-1], action, dtype=torch.int64),
        in_keys=["height"],
        out_keys=["action"],
    )


def _room_stack():
    meter = GoalMeter(RedBlobDetector(), hfov_deg=60.0)
    return Compose(
        DepthSections(seed=0),
        GoalFeatures(meter),
        Discretize(altitude_key="height"),
    )


def test_feature_stack_on_env_without_goal_measurement():
    base = RoomEnv()
    check_env_specs(base)
    env = TransformedEnv(base, _room_stack())
    check_env_specs(env)
    spec = env.observation_spec
    for key in ("depth_sections", "goal_in_sight", "goal_distance", "goal_angle",
                "causal_features", "causal_state"):
        assert key in spec.keys(), key
    assert spec["depth_sections"].shape == (5,)
    assert spec["goal_in_sight"].dtype == torch.bool
    assert spec["causal_features"].shape == (len(DEFAULT_SCHEMA),)
    assert isinstance(spec["causal_state"], MultiCategorical)
    assert spec["causal_state"].nvec.tolist() == list(DEFAULT_SCHEMA.cardinalities)

    td = env.reset()
    # marker at columns 8..15, rows 12..19: in view, 1.2 m, box centre x = 12, left
    # of the image centre x = 16 -> positive angle atan(4 / f), f = 16 / tan(30 deg)
    assert td["goal_in_sight"].item() is True
    assert td["goal_distance"].item() == pytest.approx(1.2, rel=0.1)
    assert td["goal_angle"].item() == pytest.approx(8.2, abs=0.2)
    state = dict(zip(DEFAULT_SCHEMA.names, td["causal_state"].tolist()))
    assert state["goal_in_sight"] == 1 and state["goal_distance"] == 1  # far (> 0.5 m)
    assert state["goal_angle"] == 0 and state["altitude"] == 1  # good, good (1 m)
    assert state["depth_center"] == 1  # the marker at 1.2 m is not "close"

    # walk the marker out of view to the right: no goal -> not_visible
    rollout = env.rollout(4, policy=_constant_policy(1))
    assert rollout["next", "causal_state"].shape == (4, len(DEFAULT_SCHEMA))
    in_sight = rollout["next", "goal_in_sight"].squeeze(-1).tolist()
    assert in_sight == [True, True, False, False]  # marker at columns 14, 20; 26, 32 out
    gd = rollout["next", "causal_state"][:, DEFAULT_SCHEMA.index("goal_distance")]
    assert gd.tolist()[2:] == [2, 2]
    # the marker at column 20 (box centre 24) is 16 deg right of the axis: far right
    assert rollout["next", "causal_state"][1, DEFAULT_SCHEMA.index("goal_angle")].item() == 2


def test_feature_stack_in_replay_buffer_and_batched():
    env = TransformedEnv(RoomEnv(), _room_stack())
    data = env.rollout(6, policy=_constant_policy(0))
    # the same stack as a buffer transform recomputes what the env wrote
    stack = _room_stack()
    raw = data.exclude("depth_sections", "goal_in_sight", "goal_distance", "goal_angle",
                       "causal_features", "causal_state")
    out = stack(raw.clone())
    assert torch.equal(out["causal_state"], data["causal_state"])
    assert out["goal_in_sight"].shape == (6, 1)


# --------------------------------------------------------------------------- package surface

SUBPACKAGES = (
    "torchrl_causal.schema",
    "torchrl_causal.envs",
    "torchrl_causal.perception",
    "torchrl_causal.perception.goal",
    "torchrl_causal.transforms",
    "torchrl_causal.causal",
    "torchrl_causal.modules",
    "torchrl_causal.data",
    "torchrl_causal.training",
    "torchrl_causal.pretrained",
)


def test_root_import_is_cheap_and_documents_subpackages():
    code = (
        "import sys, torchrl_causal\n"
        "heavy = [m for m in ('torch', 'torchrl', 'mujoco', 'pgmpy', 'ultralytics') "
        "if m in sys.modules]\n"
        "print(','.join(heavy))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout.strip() == "", f"importing torchrl_causal pulled in {res.stdout.strip()}"
    import torchrl_causal

    assert torchrl_causal.__version__
    for name in SUBPACKAGES:
        if name.count(".") == 1:
            assert f":mod:`{name}`" in torchrl_causal.__doc__, name


@pytest.mark.parametrize("modname", SUBPACKAGES)
def test_public_names_importable_with_examples(modname):
    mod = importlib.import_module(modname)
    assert mod.__doc__, f"{modname} has no module docstring"
    public = getattr(mod, "__all__", None)
    assert public, f"{modname} defines no __all__ (nothing is exported)"
    missing_example = []
    for name in public:
        obj = getattr(mod, name)  # raises if not importable
        if not (inspect.isclass(obj) or inspect.isfunction(obj)):
            continue  # constants (tuples, schemas) carry no docstring of their own
        doc = inspect.getdoc(obj) or ""
        if "Example" not in doc:
            missing_example.append(name)
    assert not missing_example, f"{modname}: no 'Example' in the docstring of {missing_example}"
