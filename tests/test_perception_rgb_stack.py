"""The RGB-only feature stack (``make_causal_transforms(perception="rgb")``) with the shipped
YOLOv8 detector and MonoDepth: TorchRL transform checks (env, SerialEnv, ParallelEnv, replay
buffer), agreement with the ground-truth stack on held-out layouts, a policy trained on
ground-truth features flying on RGB-only features, and bad input."""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import ParallelEnv, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from torchrl_causal.envs import DroneNavEnv
from torchrl_causal.perception import SimGoalDetector
from torchrl_causal.perception.agreement import feature_agreement, reference_stack
from torchrl_causal.perception.dataset import render_views
from torchrl_causal.perception.depth import MonoDepth
from torchrl_causal.perception.yolo import YoloGoalDetector  # the perception extra
from torchrl_causal.transforms import EstimatedDepth, GoalFeatures, make_causal_transforms

ROOT = Path(__file__).resolve().parents[1]
POLICY = ROOT / "torchrl_causal" / "pretrained" / "policies" / "thesis"


@pytest.fixture(scope="module")
def models():
    return YoloGoalDetector(), MonoDepth.load()


def _rgb_stack(env, models, seed=0):
    det, depth = models
    return make_causal_transforms(env, perception="rgb", detector=det, depth_estimator=depth,
                                  seed=seed)


def test_rgb_stack_in_env_reads_no_simulator_truth(models):
    env = DroneNavEnv(seed=0)
    stack = _rgb_stack(env, models)
    assert isinstance(stack[0], EstimatedDepth) and isinstance(stack[1], GoalFeatures)
    assert stack[1].gt_keys is None  # the goal comes from the image, not from segmentation
    tenv = TransformedEnv(env, stack)
    check_env_specs(tenv, seed=0)
    td = tenv.rollout(5, break_when_any_done=False)
    assert td["causal_state"].shape == (5, 9) and td["causal_state"].dtype == torch.int64
    # the depth written is the estimate, not the simulator's exact depth
    raw = DroneNavEnv(seed=0)
    truth = raw.reset()["depth"]
    est = tenv.reset()["depth"]
    assert not torch.equal(est, truth)
    assert (est - truth).abs().mean() / truth.mean() < 0.5
    # goal_box (EgoMap's goal elevation) is the detector's box, not the segmentation's:
    # the same board, measured
    assert stack[1].box_key == "goal_box"
    truth = raw.step(raw.reset().set("action", torch.tensor(0)))["next"]["goal_box"]
    meas = tenv.step(tenv.reset().set("action", torch.tensor(0)))["next"]["goal_box"]
    assert not torch.equal(meas, truth)
    assert (meas - truth).abs().max() < 6.0  # pixels of 84 x 84
    tenv.close()
    raw.close()


@pytest.mark.parametrize("batched", [SerialEnv, ParallelEnv])
def test_rgb_stack_on_batched_envs(models, batched):
    make = functools.partial(DroneNavEnv, seed=0)
    # fork: the workers start with this process's imports (spawn re-imports torch and
    # MuJoCo in each, about 8 s of the suite's time)
    benv = batched(2, make, **({"mp_start_method": "fork"} if batched is ParallelEnv else {}))
    hfov = DroneNavEnv().hfov_deg
    det, depth = models
    tenv = TransformedEnv(benv, make_causal_transforms(
        benv, perception="rgb", detector=det, depth_estimator=depth, hfov_deg=hfov, seed=0))
    check_env_specs(tenv, seed=0)
    td = tenv.rollout(3, break_when_any_done=False)
    assert td["causal_state"].shape == (2, 3, 9)
    tenv.close()


def test_rgb_stack_as_replay_buffer_transform(models):
    """Raw frames stored, the nine features computed when the data are read."""
    env = DroneNavEnv(seed=1)
    frames = env.rollout(6, break_when_any_done=False).select("pixels", "altitude")
    stack = make_causal_transforms(perception="rgb", detector=models[0],
                                   depth_estimator=models[1], hfov_deg=env.hfov_deg, seed=0)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10), transform=stack, batch_size=4)
    rb.extend(frames)
    sample = rb.sample()
    assert sample["causal_state"].shape == (4, 9) and "depth" in sample.keys()
    assert "depth" not in rb.storage[:].keys()  # only the raw frames are stored
    env.close()


def test_agreement_with_ground_truth_on_heldout_layouts(models):
    """On views of held-out layouts, each discretised variable of the RGB-only stack
    agrees with the ground-truth stack most of the time (the benchmark measures it on
    300 views; here 48 fresh views with a margin)."""
    views = list(render_views("test", 48, seed=777, image_size=84))
    stack = make_causal_transforms(perception="rgb", detector=models[0],
                                   depth_estimator=models[1], hfov_deg=60.0, seed=0)
    res = feature_agreement(views, stack, hfov_deg=60.0, seed=0)
    assert res["n"] == 48
    assert res["per_variable"]["altitude"] == 1.0  # never from the image
    assert min(res["per_variable"].values()) >= 0.7, res["per_variable"]
    # the reference compared with itself agrees everywhere
    same = feature_agreement(views[:8], reference_stack(60.0), hfov_deg=60.0)
    assert same["all_nine"] == 1.0


def test_policy_trained_on_ground_truth_flies_on_rgb_features():
    """torchrl_causal/pretrained/policies/thesis (make train, seed 0: greedy success 1.00 on the thesis scene
    with ground-truth features) still reaches the goal when its nine features come from the
    RGB image alone."""
    sys.path.insert(0, str(ROOT / "recipes"))
    import train as recipe

    from torchrl_causal.training import evaluate

    policy, env, _ = recipe.load_policy(POLICY, overrides=["features.options.perception=rgb"])
    assert isinstance(env.transform[0], EstimatedDepth)
    res = evaluate(policy, env, episodes=2, seed=10_000_019)
    env.close()
    assert res["success_rate"] == 1.0 and res["collisions"] == 0, res


def test_bad_input(models):
    det, depth = models
    with pytest.raises(ValueError, match="perception must be one of"):
        make_causal_transforms(perception="lidar")
    with pytest.raises(ValueError, match="hfov_deg"):
        make_causal_transforms(perception="rgb", detector=det, depth_estimator=depth)
    with pytest.raises(ValueError, match="detector must be a GoalDetector"):
        make_causal_transforms(perception="rgb", detector="yolo", depth_estimator=depth,
                               hfov_deg=60.0)
    with pytest.raises(ValueError, match="depth_estimator must be callable"):
        make_causal_transforms(perception="rgb", detector=det, depth_estimator=3,
                               hfov_deg=60.0)
    with pytest.raises(ValueError, match="options of perception='rgb'"):
        make_causal_transforms(detector=SimGoalDetector())
    stack = make_causal_transforms(perception="rgb", detector=det, depth_estimator=depth,
                                   hfov_deg=60.0)
    bad = TensorDict({"pixels": torch.zeros(1, 84, 84, 3), "altitude": torch.ones(1, 1)}, [1])
    with pytest.raises(ValueError, match="uint8"):
        stack(bad)
    from torchrl.envs import GymEnv

    with pytest.raises(ValueError, match="needs the env's 'pixels' and 'altitude'"):
        make_causal_transforms(GymEnv("CartPole-v1"), perception="rgb", detector=det,
                               depth_estimator=depth, hfov_deg=60.0)


def test_depth_estimator_as_weights_path(models, tmp_path):
    """``depth_estimator`` may name MonoDepth weights (a recipe's
    ``features.options.depth_estimator``): that file is loaded, a missing one is named."""
    det, depth = models
    from torchrl_causal.perception.depth import DEFAULT_WEIGHTS, FCRN

    # other weights than the shipped ones: a small untrained network, saved
    other = MonoDepth(FCRN(widths=(8, 16, 16, 32, 32), decoder=(32, 16, 16, 8)))
    path = tmp_path / "other.pt"
    other.save(path)
    px = torch.randint(0, 256, (1, 84, 84, 3), dtype=torch.uint8,
                       generator=torch.Generator().manual_seed(0))
    for weights, ref in ((path, other), (str(DEFAULT_WEIGHTS), depth)):
        stack = make_causal_transforms(perception="rgb", detector=det, depth_estimator=weights,
                                       hfov_deg=60.0)
        est = stack[0].estimator
        assert isinstance(est, MonoDepth)
        # the weights are stored in half precision: equal to rounding
        assert torch.allclose(est(px), ref(px), atol=1e-2)
    assert not torch.allclose(other(px), depth(px), atol=0.1)  # two different estimators
    with pytest.raises(FileNotFoundError, match="nowhere.pt"):
        make_causal_transforms(perception="rgb", detector=det, hfov_deg=60.0,
                               depth_estimator=tmp_path / "nowhere.pt")
