"""A CBN-gated DQN run on CartPole through :class:`torchrl_causal.training.DQNLoop`.

Used by ``tests/test_training.py``, which SIGKILLs it mid-run and resumes it::

    python tests/kill_resume_worker.py <output_dir> [--resume] [--frames N] [--overlap]

(``--overlap``: ``LoopConfig.overlap=True``, used by ``tests/test_training_overlap.py``.)
"""

from __future__ import annotations

import argparse
import json
import sys


def build_loop(output_dir, frames: int, seed: int = 0, overlap: bool = False):
    import torch
    from torchrl.envs import GymEnv, TransformedEnv
    from torchrl.modules import MLP, QValueActor

    from torchrl_causal.causal import CausalLearner
    from torchrl_causal.data import CausalLearningHook
    from torchrl_causal.modules import CBNGate
    from torchrl_causal.schema import Variable, VariableSchema
    from torchrl_causal.training import DQNLoop, LoopConfig
    from torchrl_causal.transforms import Discretize

    torch.manual_seed(seed)
    schema = VariableSchema((
        Variable("angle", ("left", "upright", "right"), bins=(-0.05, 0.05),
                 source="observation", index=2),
        Variable("spin", ("left", "still", "right"), bins=(-0.3, 0.3),
                 source="observation", index=3),
    ))

    def make_env():
        return TransformedEnv(GymEnv("CartPole-v1"), Discretize(schema=schema))

    env = make_env()
    actor = QValueActor(MLP(in_features=4, out_features=2, num_cells=[32]),
                        in_keys=["observation"], spec=env.action_spec)
    gate = CBNGate("v2", annealing_num_steps=frames // 2, seed=seed)
    hook = CausalLearningHook(CausalLearner(schema, n_actions=2), k=100, gates=[gate])
    config = LoopConfig(total_frames=frames, learning_starts=200, updates_per_frame=0.5,
                        target_update_interval=50, eval_interval_frames=frames // 4,
                        eval_episodes=2, final_eval_episodes=2, eval_max_steps=50,
                        checkpoint_interval_frames=150,
                        buffer_size=frames, seed=seed, overlap=overlap)
    return DQNLoop(env, actor, gate, hook=hook, config=config, output_dir=output_dir,
                   eval_envs={"cartpole": make_env},
                   outcome_keys={"success": "truncated", "crash": "terminated"})


def main(argv=None):
    import torch

    p = argparse.ArgumentParser()
    p.add_argument("output_dir")
    p.add_argument("--resume", action="store_true")
    p.add_argument("--frames", type=int, default=1200)
    p.add_argument("--overlap", action="store_true")
    args = p.parse_args(argv)
    torch.set_num_threads(1)  # same arithmetic in every process
    summary = build_loop(args.output_dir, args.frames, overlap=args.overlap).run(resume=args.resume)
    print(json.dumps({k: summary[k] for k in ("frames", "episodes", "updates", "n_relearns")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
