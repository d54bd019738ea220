"""ReachRule: TelloEnv's arrival decision from measurements only."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchrl_causal.envs import ReachRule
from torchrl_causal.envs.tello import TelloEnv
from torchrl_causal.perception.goal import SimGoalDetector

FULL = (0.0, 0.0, 84.0, 84.0)


def _m(**kw):
    base = dict(in_sight=True, distance=0.4, angle=0.0, box=FULL, width=84, altitude=1.0)
    base.update(kw)
    return base


def test_each_condition_vetoes_on_its_own():
    rule = ReachRule(max_distance=0.45, min_distance=0.1, max_angle=20, goal_height=1.0,
                     max_height_offset=0.12, full_width=True)
    assert rule(**_m())
    assert not rule(**_m(in_sight=False))
    assert not rule(**_m(distance=float("nan")))
    assert not rule(**_m(distance=0.46))
    assert not rule(**_m(distance=0.05))
    assert not rule(**_m(angle=-25.0))
    assert not rule(**_m(altitude=1.13))
    assert rule(**_m(altitude=0.89))
    assert not rule(**_m(box=(10.0, 0.0, 84.0, 84.0)))  # the board's left edge in view
    assert not rule(**_m(box=(0.0, 0.0, 70.0, 84.0)))
    # without goal_height: distance and angle only (0.45 m by default)
    plain = ReachRule()
    assert plain(**_m(distance=0.45, altitude=3.0, box=(30, 30, 50, 50)))
    assert not plain(**_m(distance=0.46))


@pytest.mark.parametrize("kw,name", [
    ({"max_distance": 0.0}, "max_distance"), ({"max_distance": math.inf}, "max_distance"),
    ({"min_distance": 0.9}, "min_distance"), ({"max_angle": 120}, "max_angle"),
    ({"goal_height": -1.0}, "goal_height"), ({"max_height_offset": 0.0}, "max_height_offset"),
    ({"full_width": 1}, "full_width"), ({"max_goal_offset": 0.0}, "max_goal_offset"),
    ({"board_width": -1.0}, "board_width"), ({"goal_standoff": math.nan}, "goal_standoff"),
])
def test_bad_options_are_named(kw, name):
    with pytest.raises(ValueError, match=f"ReachRule.{name}"):
        ReachRule(**kw)


def test_tello_env_takes_a_rule_and_refuses_anything_else():
    depth = lambda p: torch.full(p.shape[:3], 3.0)  # noqa: E731
    env = TelloEnv(dry_run=True, detector=SimGoalDetector(), depth_estimator=depth,
                   verbose=False, reach_rule=ReachRule(max_distance=0.4))
    assert env.reach_rule.max_distance == 0.4
    env.close()
    with pytest.raises(ValueError, match="reach_rule"):
        TelloEnv(dry_run=True, detector=SimGoalDetector(), depth_estimator=depth,
                 verbose=False, reach_rule={"max_distance": 0.4})


def test_tello_env_default_rule_is_the_depth_models_calibrated_range(tmp_path):
    """No rule given: a depth model that carries a calibrated range (its weights'
    ``reach_calibration``) sets ``max_distance``; one without keeps 0.45 m; a rule
    given explicitly wins."""
    from torchrl_causal.perception.depth import FCRN, MonoDepth

    calibrated = MonoDepth(FCRN(widths=(8, 8, 8, 8, 8), decoder=(8, 8, 8, 8)),
                           meta={"reach_calibration": {"max_distance": 0.38}})
    calibrated.save(tmp_path / "d.pt")
    loaded = MonoDepth.load(tmp_path / "d.pt")  # carried inside the weights file
    assert loaded.reach_distance == 0.38
    for depth, expect in ((loaded, 0.38), (MonoDepth(FCRN()), 0.45),
                          (lambda p: torch.ones(p.shape[:3]), 0.45)):
        env = TelloEnv(dry_run=True, detector=SimGoalDetector(), depth_estimator=depth,
                       verbose=False)
        assert env.reach_rule.max_distance == expect
        env.close()
    env = TelloEnv(dry_run=True, detector=SimGoalDetector(), depth_estimator=loaded,
                   verbose=False, reach_rule=ReachRule(max_distance=0.5))
    assert env.reach_rule.max_distance == 0.5
    env.close()


# ------------------------------------------------------------------ goal-point offset

def _view(env, x, y, yaw_offset_deg=0.0):
    """Depth and goal box of the real MuJoCo scene from (x, y) at the goal's height,
    looking at the board's centre (+ ``yaw_offset_deg``)."""
    lay = env.layout
    gc = lay.goal_center
    yaw = math.atan2(gc[1] - y, gc[0] - x) + math.radians(yaw_offset_deg)
    env._executor.set_pose(x, y, lay.goal_point()[2], yaw)
    obs = env._observe(False, False)
    return obs["depth"].numpy(), obs["goal_box"].tolist()


def _random_views(env, rng, n, max_deg, radii):
    """``n`` views ``(x, y, depth, box)`` from around the board: up to ``max_deg`` off its
    normal, ``radii = (low, high)`` m from its centre, looking at it within 10 deg."""
    lay = env.layout
    gc, nrm = np.asarray(lay.goal_center), lay.goal_normal()
    for _ in range(n):
        phi = math.radians(rng.uniform(-max_deg, max_deg))
        r = rng.uniform(*radii)
        base = math.atan2(nrm[1], nrm[0]) + phi
        x, y = gc[0] + r * math.cos(base), gc[1] + r * math.sin(base)
        depth, box = _view(env, x, y, rng.uniform(-10, 10))
        yield x, y, depth, box


def test_goal_offset_reads_where_the_goal_point_is_on_real_renders():
    """Square on, seen at an angle, with the board's edges in view or filling it:
    the estimate of the drone's distance to the goal point is within 5 cm of the truth
    whenever an edge is in view, where range and bearing alone mistake places 0.4-0.7 m
    beside the goal point for arrivals (the random layouts' turned boards)."""
    from torchrl_causal.envs import DroneNavEnv
    from torchrl_causal.envs.layouts import RandomLayoutGenerator
    from torchrl_causal.envs.reach import goal_point_offset

    lay = RandomLayoutGenerator("heldout", seed=0).layout(7)
    env = DroneNavEnv(lay, image_size=(84, 84), seed=0)
    env.reset()
    try:
        gp, gc, n = lay.goal_point(), np.asarray(lay.goal_center), lay.goal_normal()
        rule = ReachRule(max_goal_offset=0.2, board_width=float(lay.goal_size[0]),
                         goal_standoff=float(lay.goal_standoff))
        old = ReachRule()
        rng = np.random.default_rng(0)
        errors, fooled, kept_off = [], 0, 0
        for x, y, depth, box in _random_views(env, rng, 24, 60, (0.3, 0.9)):
            est, facing = goal_point_offset(depth, box, env.hfov_deg,
                                            goal_standoff=lay.goal_standoff,
                                            board_width=lay.goal_size[0])
            true = math.hypot(x - gp[0], y - gp[1])
            if box[0] > 0 or box[2] < 84:  # an edge in view
                errors.append(abs(est - true))
            if true > 0.35:
                meas = dict(in_sight=True, distance=float(np.median(depth)), angle=0.0, box=box,
                            width=84, altitude=1.0)
                fooled += old(**meas)
                kept_off += not rule(**meas, goal_offset=est)
        assert len(errors) >= 8 and max(errors) < 0.05, errors
        assert kept_off >= fooled  # never fooled where the plain rule is not ...
        # ... and square on at the goal point: ~0
        depth, box = _view(env, gp[0], gp[1])
        assert goal_point_offset(depth, box, env.hfov_deg, goal_standoff=lay.goal_standoff,
                                 board_width=lay.goal_size[0])[0] < 0.03
    finally:
        env.close()


def test_offset_rule_needs_an_estimate_and_reads_the_swept_move():
    from torchrl_causal.envs.reach import goal_point_offset

    rule = ReachRule(max_goal_offset=0.2)
    assert rule(**_m(), goal_offset=0.1)
    assert not rule(**_m(), goal_offset=0.25)
    assert not rule(**_m())  # no estimate: never fires
    assert not rule(**_m(), goal_offset=float("nan"))
    past = np.full((84, 84), 0.1)  # 0.225 m past the goal point after a 0.25 m forward move
    assert goal_point_offset(past, FULL, 60.0)[0] == pytest.approx(0.225, abs=1e-6)
    assert goal_point_offset(past, FULL, 60.0, moved=(0.0, 0.25))[0] == pytest.approx(0.0, abs=1e-6)
    assert math.isnan(goal_point_offset(past, (0, 0, 2, 84), 60.0)[0])  # too narrow a box


def test_tello_env_declares_reached_by_the_offset_rule():
    """A TelloEnv whose depth reads the board square on at the goal point fires the
    offset rule; one whose board shows its left edge 0.5 m aside does not."""
    from torchrl_causal.perception.goal import GoalDetector

    class Box(GoalDetector):
        def __init__(self, box):
            self.box = box

        def detect(self, pixels, depth=None, **_):
            return torch.tensor([[self.box]]), torch.tensor([[0.9]])

    rule = ReachRule(max_goal_offset=0.2, board_width=1.0, goal_standoff=0.45)
    at_goal = TelloEnv(dry_run=True, detector=Box([0.0, 0.0, 84.0, 84.0]), verbose=False,
                       depth_estimator=lambda p: torch.full(p.shape[:3], 0.345),
                       reach_rule=rule)
    m = at_goal.measure_frame(np.zeros((720, 960, 3), np.uint8))
    assert m["reached"] and m["goal_offset"] < 0.05
    at_goal.close()
    beside = TelloEnv(dry_run=True, detector=Box([40.0, 0.0, 84.0, 84.0]), verbose=False,
                      depth_estimator=lambda p: torch.full(p.shape[:3], 0.345),
                      reach_rule=rule)
    m = beside.measure_frame(np.zeros((720, 960, 3), np.uint8))
    assert not m["reached"] and m["goal_offset"] > 0.3  # the board's centre is off to the right
    beside.close()


def test_offset_is_three_dimensional_with_a_goal_height():
    """With a goal height, the offset includes the height sensor's difference and the
    vertical part of the last move (the simulator's sphere is 3-D), and replaces the
    separate height check."""
    from torchrl_causal.envs.reach import goal_point_offset

    at = np.full((84, 84), 0.345)  # horizontally at the goal point
    assert goal_point_offset(at, FULL, 60.0, height_offset=0.15)[0] == pytest.approx(0.152, abs=2e-3)
    # 0.1 m above the goal point after a 0.25 m ascent: the climb passed through it
    assert goal_point_offset(at, FULL, 60.0, moved=(0.0, 0.0, 0.25),
                             height_offset=-0.1)[0] == pytest.approx(0.02, abs=2e-3)
    rule = ReachRule(max_goal_offset=0.2, goal_height=1.0, max_height_offset=0.12)
    assert rule.goal_offset(at, FULL, 60.0, altitude=1.15) == pytest.approx(0.152, abs=2e-3)
    assert rule.goal_offset(at, FULL, 60.0, altitude=1.25) > 0.2
    # 0.15 m above: outside max_height_offset, inside the sphere -> the offset decides
    assert rule(**_m(altitude=1.15), goal_offset=0.152)
    assert not rule(**_m(altitude=1.15), goal_offset=0.25)


# ------------------------------------------------------------------ the board plane as a head

def _board_frame(lay, x, y):
    """The drone centre's ``(ahead, lateral)`` from the goal point, in the board's frame."""
    gp, n = np.asarray(lay.goal_point()), np.asarray(lay.goal_normal())
    v = np.array([x - gp[0], y - gp[1]])
    side = np.array([-n[1], n[0]])
    return float(v @ n[:2]), float(v @ side)


def test_board_plane_head_reads_the_drones_place_in_the_boards_frame_on_real_renders():
    """On a held-out layout's real renders, wherever a side edge of the board is in view,
    BoardPlaneOffset reads the drone centre's (ahead, lateral) within 5 cm; closer in,
    where the board fills the view, its memory carries the lateral place on by the moves
    since (within 5 cm), where the box centre's ray alone is 0.1 m off or more."""
    from torchrl_causal.envs import BoardPlaneOffset, DroneNavEnv
    from torchrl_causal.envs.layouts import RandomLayoutGenerator

    lay = RandomLayoutGenerator("heldout", seed=0).layout(7)
    env = DroneNavEnv(lay, image_size=(84, 84), seed=0)
    env.reset()
    kw = dict(board_width=float(lay.goal_size[0]), goal_standoff=float(lay.goal_standoff))
    try:
        gp, gc, n = lay.goal_point(), np.asarray(lay.goal_center), lay.goal_normal()
        rng = np.random.default_rng(1)
        errors = []
        for x, y, depth, box in _random_views(env, rng, 16, 45, (0.9, 1.4)):
            if box[0] > 0 or box[2] < 84:
                est = BoardPlaneOffset()(depth, box, env.hfov_deg, **kw)
                assert est is not None
                errors.append(np.abs(est - np.array(_board_frame(lay, x, y))).max())
        assert len(errors) >= 8 and max(errors) < 0.05, errors
        # from 1.2 m out, 0.25 m to the side (both edges in view) to 0.05 m from the goal
        # point's plane at the same lateral place, square on: the board fills the view
        head, plain = BoardPlaneOffset(), BoardPlaneOffset(memory=False)
        side = np.array([-n[1], n[0]])
        far = np.asarray(gp[:2]) + 0.8 * np.asarray(n[:2]) + 0.25 * side
        near = np.asarray(gp[:2]) + 0.05 * np.asarray(n[:2]) + 0.25 * side
        yaw = math.atan2(-n[1], -n[0])
        for (x, y) in (far, near):
            env._executor.set_pose(x, y, gp[2], yaw)
            obs = env._observe(False, False)
            depth, box = obs["depth"].numpy(), obs["goal_box"].tolist()
            est = head(depth, box, env.hfov_deg, pose=(x, y, yaw), **kw)
            guess = plain(depth, box, env.hfov_deg, pose=(x, y, yaw), **kw)
        assert box == [0.0, 0.0, 84.0, 84.0] or (box[0] == 0 and box[2] == 84)
        truth = np.array(_board_frame(lay, *near))
        assert np.abs(est - truth).max() < 0.05, (est, truth)
        assert abs(guess[1] - truth[1]) > 0.1, (guess, truth)
        head.reset()  # a new episode: nothing to carry on
        assert abs(head(depth, box, env.hfov_deg, pose=tuple(near) + (yaw,), **kw)[1]
                   - truth[1]) > 0.1
    finally:
        env.close()


def test_board_plane_head_refuses_what_is_not_the_boards_plane():
    """An obstacle in front of part of the board breaks the line fit: no estimate (the
    plain goal-point offset reads it); a nearer obstacle just beyond a side of the box
    hides the board's end: that side is not taken for its edge."""
    from torchrl_causal.envs import BoardPlaneOffset
    from torchrl_causal.envs.reach import goal_point_offset

    head = BoardPlaneOffset(memory=False)
    depth = np.full((84, 84), 1.0)
    depth[:, 40:84] = 0.5  # the right half of the box is an obstacle, 0.5 m nearer
    assert head(depth, (20, 0, 84, 84), 60.0) is None
    assert math.isfinite(goal_point_offset(depth, (20, 0, 84, 84), 60.0)[0])
    # the board at 1 m fills columns 30-84; something at 0.6 m covers columns 0-30
    depth = np.full((84, 84), 1.0)
    depth[:, :30] = 0.6
    hidden = head(depth, (30, 0, 84, 84), 60.0)
    edge = BoardPlaneOffset(memory=False, max_residual=0.03)(np.full((84, 84), 1.0),
                                                             (30, 0, 84, 84), 60.0)
    centre_ray = goal_point_offset(np.full((84, 84), 1.0), (30, 0, 84, 84), 60.0,
                                   board_width=None)
    assert hidden is not None and edge is not None
    assert abs(hidden[1] - edge[1]) > 0.1  # the hidden side was not read as the edge
    # ... it fell back on the box centre's ray: the same distance as with no board width
    assert math.hypot(*hidden) == pytest.approx(centre_ray[0], abs=1e-6)
    with pytest.raises(ValueError, match="BoardPlaneOffset.max_residual"):
        BoardPlaneOffset(max_residual=-1.0)
    with pytest.raises(ValueError, match="BoardPlaneOffset.max_age"):
        BoardPlaneOffset(max_age=1.5)


def test_tello_env_flies_the_board_plane_head():
    """TelloEnv(arrival_head=BoardPlaneOffset()) declares reached at the goal point and
    not 0.5 m beside it, as the offset rule does, without a learned head's frames."""
    from torchrl_causal.envs import BoardPlaneOffset
    from torchrl_causal.perception.goal import GoalDetector

    class Box(GoalDetector):
        def __init__(self, box):
            self.box = box

        def detect(self, pixels, depth=None, **_):
            return torch.tensor([[self.box]]), torch.tensor([[0.9]])

    rule = ReachRule(max_distance=1.0, max_goal_offset=0.2, board_width=1.0, goal_standoff=0.45)
    for box, reached in (([0.0, 0.0, 84.0, 84.0], True), ([40.0, 0.0, 84.0, 84.0], False)):
        env = TelloEnv(dry_run=True, detector=Box(box), verbose=False,
                       depth_estimator=lambda p: torch.full(p.shape[:3], 0.345),
                       reach_rule=rule, arrival_head=BoardPlaneOffset(), final_approach=0.4)
        m = env.measure_frame(np.zeros((720, 960, 3), np.uint8))
        assert m["reached"] is reached, (box, m)
        env.close()


def test_board_plane_head_reads_no_sliver_and_no_board_seen_edge_on():
    """A box narrower than a quarter of the image, or a board whose normal is more than
    70 deg off the camera's axis, gives no estimate (in flight both read a drone beside
    the board as in front of its goal point)."""
    from torchrl_causal.envs import BoardPlaneOffset

    head = BoardPlaneOffset(memory=False)
    flat = np.full((84, 84), 1.0)
    assert head(flat, (70, 0, 84, 84), 60.0) is None  # 14 columns
    assert head(flat, (60, 0, 84, 84), 60.0) is not None  # 24 columns
    assert BoardPlaneOffset(min_width=0.1)(flat, (70, 0, 84, 84), 60.0) is not None
    # a plane turned 75 deg: z = 1 + x * tan(75 deg) along the rows' rays
    f = 42 / math.tan(math.radians(30))
    cols = np.arange(84) + 0.5 - 42
    slope = math.tan(math.radians(75))
    z = 1.0 / (1.0 - slope * cols / f)
    z = np.where(z > 0, z, np.nan)
    turned = np.tile(z, (84, 1))
    ok = np.isfinite(z) & (z < 10)
    lo = int(np.argmax(ok))
    assert head(turned, (lo, 0, lo + 30, 84), 60.0) is None
    assert BoardPlaneOffset(memory=False, max_facing=80.0)(turned, (lo, 0, lo + 30, 84),
                                                           60.0) is not None
    with pytest.raises(ValueError, match="BoardPlaneOffset.min_width"):
        BoardPlaneOffset(min_width=2.0)


def test_tello_env_lets_the_board_plane_head_remember_an_edge_seen_above_the_goal():
    """A view with the board's edge, taken where the height sensor alone puts the drone
    outside the offset (the head's estimate is not used there), still leaves its lateral
    place for the next view that shows no edge: TelloEnv reads every frame in range."""
    from torchrl_causal.envs import BoardPlaneOffset
    from torchrl_causal.perception.goal import SimGoalDetector

    rule = ReachRule(max_distance=1.0, max_goal_offset=0.2, goal_height=1.0,
                     board_width=1.0, goal_standoff=0.45)
    env = TelloEnv(dry_run=True, detector=SimGoalDetector(), verbose=False,
                   depth_estimator=lambda p: torch.ones(p.shape[:3]), reach_rule=rule,
                   arrival_head=BoardPlaneOffset())
    try:
        env._forget_arrival()
        env._world, env._yaw, env._last_move = np.zeros(2), 0.0, (0.0, 0.0, 0.0)
        # 1 m from the board, its left edge at column 20: the drone 0.3 m to the goal's
        # right... and 0.3 m above the goal height: the height alone says "outside"
        edge = torch.full((84, 84), 1.0)
        off = env._goal_offset(True, edge, [20.0, 0.0, 84.0, 84.0], 1.3, None, 1.0)
        assert off == pytest.approx(0.3)
        # a descent and 0.55 m forward (dead-reckoned), the board now fills the view
        env._world, env._last_move = np.array([0.55, 0.0]), (0.0, 0.0, -0.25)
        near = torch.full((84, 84), 0.45)
        env._goal_offset(True, near, [0.0, 0.0, 84.0, 84.0], 1.05, None, 0.45)
        lateral = float(env._prev_offset[1])
        f = 42 / math.tan(math.radians(env.hfov_deg / 2))
        x_edge = (20 - 42) / f * 1.0  # the edge's x at 1 m; the board's centre 0.5 m right
        assert lateral == pytest.approx(-(x_edge + 0.5), abs=1e-6)
        assert abs(lateral) > 0.1  # the box centre's ray alone would read about 0
    finally:
        env.close()
