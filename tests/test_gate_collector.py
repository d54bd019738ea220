"""End to end on the real MuJoCo env: features -> QValueActor(ThesisQNet) -> CBNGate,
collected by torchrl's Collector into a replay buffer whose CausalLearningHook
feeds the real CausalLearner and pushes its tables back to the gate."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import pytest  # noqa: E402
import torch  # noqa: E402
from tensordict.nn import TensorDictSequential  # noqa: E402
from torchrl.collectors import Collector  # noqa: E402
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer  # noqa: E402
from torchrl.envs import TransformedEnv  # noqa: E402
from torchrl.modules import QValueActor  # noqa: E402

from torchrl_causal.causal import CausalLearner  # noqa: E402
from torchrl_causal.data import CausalLearningHook  # noqa: E402
from torchrl_causal.envs import DroneNavEnv  # noqa: E402
from torchrl_causal.modules import CBNGate, ThesisQNet  # noqa: E402
from torchrl_causal.transforms import make_causal_transforms  # noqa: E402


@pytest.fixture
def one_thread():
    # 2-core CI runners with 2 pytest workers: intra-op threads would oversubscribe
    # the cores and make small convolutions tens of times slower.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_collector_gate_hook_loop_on_drone_env(one_thread):
    torch.manual_seed(0)
    base = DroneNavEnv()
    env = TransformedEnv(base, make_causal_transforms(base, seed=0))
    env.set_seed(0)
    net = ThesisQNet(8, n_features=9)
    actor = QValueActor(net, in_keys=["pixels", "causal_features"], spec=env.action_spec)
    gate = CBNGate("pn", eps_init=1.0, eps_end=0.1, annealing_num_steps=100, seed=0)
    policy = TensorDictSequential(actor, gate)
    hook = CausalLearningHook(CausalLearner(min_rows=5), k=40, gates=[gate])
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), batch_size=16)
    rb.append_transform(hook)
    collector = Collector(
        env, policy, frames_per_batch=20, total_frames=100, auto_register_policy_transforms=False
    )
    consulted = 0
    try:
        for batch in collector:
            assert gate.tables is hook.learner.tables
            flat = batch.reshape(-1)
            # the env executed the action the gate wrote; the buffer stores it
            assert ((flat["action"] >= 0) & (flat["action"] < 8)).all()
            assert flat["gate_dqn_action"].shape == flat["action"].shape
            changed = flat["gate_vetoed"] | flat["gate_replaced"]
            assert (flat["action"][~changed] == flat["gate_dqn_action"][~changed]).all()
            consulted += int(flat["gate_consulted"].sum())
            rb.extend(flat)
            gate.step(flat.numel())
    finally:
        collector.shutdown()
    assert hook.frames == 100 == len(rb)
    assert hook.learner.n_relearns == 2  # at 40 and 80 frames
    assert gate.tables is not None and gate.tables is hook.learner.tables
    # before the first relearn the gate abstained, afterwards it could consult
    assert rb[:40]["gate_consulted"].sum() == 0
    assert consulted == int(rb[:]["gate_consulted"].sum())
    assert gate.eps.item() < 1.0
