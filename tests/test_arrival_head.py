"""The learned arrival head (``torchrl_causal.perception.arrival``): real renders near the
thesis board through the real H.264 camera path, a real (small) training run that must
beat a constant guess on frames of another seed, the weights' round trip, and the head
deciding ``TelloEnv``'s arrival."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchrl_causal.envs import ReachRule, TelloEnv
from torchrl_causal.perception.arrival import (
    INPUT_SIZE,
    GoalOffsetEstimator,
    GoalOffsetNet,
    render_offset_views,
    segment_distance,
    train_goal_offset,
)
from torchrl_causal.perception.goal import GoalDetector


class FullView(GoalDetector):
    """A detector that sees the board filling the 84 x 84 view at 0.9 confidence."""

    def detect(self, pixels, depth=None, **_):
        return torch.tensor([[[0.0, 0.0, 84.0, 84.0]]]), torch.tensor([[0.9]])


#: The rule the dry-run envs below decide with.
RULE = ReachRule(max_distance=1.0, max_goal_offset=0.13)


def dry_env(**kw) -> TelloEnv:
    """A dry-run ``TelloEnv`` whose detector always sees the board and whose depth reads
    0.6 m everywhere; ``kw``: the arrival options under test (``reach_rule``: :data:`RULE`)."""
    kw.setdefault("reach_rule", RULE)
    return TelloEnv(dry_run=True, detector=FullView(), verbose=False,
                    depth_estimator=lambda p: torch.full(p.shape[:3], 0.6), **kw)


@pytest.fixture(scope="module")
def views():
    return render_offset_views(240, seed=5), render_offset_views(60, seed=6)


def test_views_are_labelled_frames_of_both_stream_sizes(views):
    (x, y), _ = views
    assert x.shape == (240, *INPUT_SIZE, 3) and x.dtype == np.uint8 and y.shape == (240, 5)
    assert (-0.42 <= y[:, 0]).all() and (y[:, 0] <= 0.8).all() and (abs(y[:, 1]) <= 0.6).all()
    assert (abs(y[:, 2]) <= 0.2).all() and (abs(y[:, 3]) <= 30).all()
    assert (0 <= y[:, 4]).all() and (y[:, 4] <= 1).all() and y[:, 4].max() > 0.5  # board share
    assert x.std() > 10  # real renders, not blank frames
    again, labels = render_offset_views(4, seed=5)
    np.testing.assert_array_equal(labels, y[:4])  # seeded poses


def test_a_short_training_beats_a_constant_guess(views):
    """40 epochs on 240 frames, measured on 60 frames of
    another seed, must read the range (ahead) far better than the training mean does."""
    (x, y), (xt, yt) = views
    est = train_goal_offset(x, y, epochs=40, seed=0)
    pred = est(torch.as_tensor(xt)).numpy()
    mae = np.abs(pred[:, 0] - yt[:, 0]).mean()
    constant = np.abs(y[:, 0].mean() - yt[:, 0]).mean()
    assert mae < 0.5 * constant, (mae, constant)


def test_weights_round_trip_and_bad_files(tmp_path):
    net = GoalOffsetNet(8)
    est = GoalOffsetEstimator(net, meta={"test": {"mae_ahead_m": 0.02}})
    path = est.save(tmp_path / "a.pt")
    back = GoalOffsetEstimator.load(path)
    frames = torch.randint(0, 255, (3, 240, 320, 3), dtype=torch.uint8)  # any 4:3 size
    torch.testing.assert_close(back(frames), est(frames), atol=2e-3, rtol=2e-3)  # float16
    assert back.meta["test"]["mae_ahead_m"] == 0.02 and back.net.width == 8
    with pytest.raises(FileNotFoundError, match="train_arrival.py"):
        GoalOffsetEstimator.load(tmp_path / "none.pt")
    torch.save({"format": "something else"}, tmp_path / "other.pt")
    with pytest.raises(RuntimeError, match="is not an arrival head"):
        GoalOffsetEstimator.load(tmp_path / "other.pt")
    with pytest.raises(ValueError, match="uint8"):
        est(torch.zeros(1, 96, 128, 3))
    with pytest.raises(ValueError, match="frames must be uint8"):
        train_goal_offset(np.zeros((2, 10, 10, 3), np.uint8), np.zeros((2, 4)))
    with pytest.raises(ValueError, match="epochs"):
        train_goal_offset(np.zeros((2, *INPUT_SIZE, 3), np.uint8), np.zeros((2, 4)), epochs=0)


def test_segment_distance_sees_a_pass_through_the_sphere():
    assert segment_distance((0.3, 0.0), (-0.1, 0.0)) == pytest.approx(0.0)  # flew through it
    assert segment_distance((0.3, 0.0), (0.25, 0.0), dz=0.1) == pytest.approx(np.hypot(0.25, 0.1))
    assert segment_distance((0.1, 0.1), (0.1, 0.1)) == pytest.approx(np.hypot(0.1, 0.1))
    # 3-D: a descent from 0.4 m above onto a point 0.35 m short never came near the goal
    assert segment_distance((0.1, 0.0, 0.4), (0.35, 0.0, 0.0)) > 0.25
    with pytest.raises(ValueError, match="start and end must both be"):
        segment_distance((0.1, 0.0, 0.4), (0.35, 0.0))


def test_tello_env_arrives_by_the_head():
    """TelloEnv asks the head for the offset: at the goal point it fires, 0.5 m off it does
    not, and a rule without max_goal_offset is refused with the head."""
    def head(at):
        return lambda frames: torch.tensor([at] * len(frames))

    rule = ReachRule(max_distance=1.0, max_goal_offset=0.2)  # depth reads 0.6 m: MonoDepth short
    for at, reached in (((0.05, 0.02), True), ((0.5, 0.0), False), ((0.0, 0.3), False)):
        env = dry_env(reach_rule=rule, arrival_head=head(at))
        m = env.measure_frame(np.zeros((720, 960, 3), np.uint8))
        assert m["reached"] is reached and m["goal_offset"] == pytest.approx(np.hypot(*at))
        env.close()
    # beyond the rule's range the head is not asked (it was not trained there), and a
    # segment never starts at an estimate from there
    calls = []

    def counting(frames):
        calls.append(len(frames))
        return torch.tensor([(0.0, 0.0)] * len(frames))

    far = TelloEnv(dry_run=True, detector=FullView(), verbose=False, reach_rule=rule,
                   depth_estimator=lambda p: torch.full(p.shape[:3], 1.5), arrival_head=counting)
    m = far.measure_frame(np.zeros((720, 960, 3), np.uint8))
    assert not m["reached"] and m["goal_offset"] is None and calls == []
    far.close()
    # the height sensor alone puts it outside the sphere: the head is not asked either
    high = dry_env(reach_rule=ReachRule(max_distance=1.0, max_goal_offset=0.2,
                                         goal_height=1.0), arrival_head=counting)
    m = high.measure_frame(np.zeros((720, 960, 3), np.uint8), altitude=1.35)
    assert not m["reached"] and m["goal_offset"] == pytest.approx(0.35) and calls == []
    m = high.measure_frame(np.zeros((720, 960, 3), np.uint8), altitude=1.05)
    assert m["reached"] and m["goal_offset"] == pytest.approx(0.05) and calls == [1]
    high.close()
    # a board the detector loses right after a sighting within range is held one step:
    # the head is asked on that frame, the segment runs on from the last estimate; a
    # second frame without a detection, or a loss with no sighting before, asks nothing
    seq = iter([(0.3, 0.0), (0.1, 0.0), (0.0, 0.0)])
    held = dry_env(reach_rule=rule, arrival_head=lambda f: torch.tensor([next(seq)]))
    frame, dmap, box = np.zeros((720, 960, 3), np.uint8), torch.zeros(84, 84), [0, 0, 84, 84]
    assert held._goal_offset(False, dmap, box, 1.0, frame, 0.0) is None  # never seen
    assert held._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(0.3)
    assert held._goal_offset(False, dmap, box, 1.0, frame, 0.0) == pytest.approx(0.1)
    assert held._goal_offset(False, dmap, box, 1.0, frame, 0.0) is None  # two in a row
    held.close()
    # ... only near the goal point (within twice max_goal_offset): a board lost after a
    # look that put the drone 0.5 m off is one the camera left, and nothing is asked
    seq = iter([(0.5, 0.0), (0.0, 0.0)])
    left = dry_env(reach_rule=rule, arrival_head=lambda f: torch.tensor([next(seq)]))
    assert left._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(0.5)
    assert left._goal_offset(False, dmap, box, 1.0, frame, 0.0) is None
    left.close()
    # ... unless hold_radius sets that distance itself: at 0.6 m the same loss is held
    seq = iter([(0.5, 0.0), (0.1, 0.0)])
    wide = dry_env(reach_rule=rule, arrival_head=lambda f: torch.tensor([next(seq)]),
                    hold_radius=0.6)
    assert wide._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(0.5)
    assert wide._goal_offset(False, dmap, box, 1.0, frame, 0.0) == pytest.approx(0.1)
    wide.close()
    # lost_board="carry": the lost board's step reads no frame; the last estimate is moved
    # by the dead-reckoned displacement, turned by the final approach's fitted heading
    # (here pi: flying +x in odometry brings the drone nearer the board)
    for lost, third in (("carry", 0.05), ("hold", 0.0)):
        seq = iter([(0.8, 0.0), (0.3, 0.0), (0.0, 0.0)])
        carry = dry_env(reach_rule=rule, arrival_head=lambda f: torch.tensor([next(seq)]),
                         final_approach=0.4, lost_board=lost)
        carry._world = np.array([-0.5, 0.0])
        assert carry._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(0.8)
        carry._world, carry._last_move = np.array([0.0, 0.0]), (0.5, 0.0, 0.0)
        assert carry._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(0.3)
        carry._world, carry._last_move = np.array([0.25, 0.0]), (0.25, 0.0, 0.0)
        # carry: from (0.3, 0) to (0.05, 0), 0.05 m off; hold: the head is asked on the
        # frame without the board and reads (0, 0)
        got = carry._goal_offset(False, dmap, box, 1.0, frame, 0.0)
        assert got == pytest.approx(third, abs=1e-6), lost
        assert (next(seq, None) is None) is (lost == "hold")  # carry asked no frame
        assert carry._goal_offset(False, dmap, box, 1.0, frame, 0.0) is None  # one step only
        carry.close()
    for bad, match in ((dict(hold_radius=-0.1, arrival_head=head((0.0, 0.0))), "hold_radius"),
                       (dict(lost_board="keep", arrival_head=head((0.0, 0.0))),
                        "lost_board must be 'hold', 'carry' or 'ask', got 'keep'"),
                       (dict(lost_board="carry", arrival_head=head((0.0, 0.0))),
                        "it needs final_approach"),
                       (dict(hold_radius=float("nan"), arrival_head=head((0.0, 0.0))),
                        "hold_radius"),
                       (dict(hold_radius=0.4), "hold_radius=0.4 .* needs arrival_head")):
        with pytest.raises(ValueError, match=match):
            dry_env(reach_rule=rule, **bad)
    # arrival_fusion: looks taken without a move across the floor (a turn: _last_move is
    # zero) are averaged; a move forward starts a new place, with its segment
    seq = iter([(0.30, 0.0), (0.10, 0.0), (0.20, 0.0), (0.05, 0.10)])
    fused = dry_env(reach_rule=rule, arrival_head=lambda f: torch.tensor([next(seq)]),
                     arrival_fusion=True)
    assert fused._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(0.30)
    fused._last_move = (0.0, 0.0, 0.0)  # turned in place
    assert fused._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(0.20)
    assert fused._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(0.20)
    fused._last_move = (0.0, 0.2, 0.0)  # flew forward: the segment from the fused place
    assert fused._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(
        segment_distance((0.20, 0.0), (0.05, 0.10)))
    fused.close()
    # a descent that crosses the goal's height: both ends are outside the sphere by the
    # height sensor, but the drone passed through it -- the head is asked, and the
    # vertical segment from the last height counts the pass; across the floor it is not
    hrule = ReachRule(max_distance=1.0, max_goal_offset=0.15, goal_height=1.0)
    for move, reached in (((0.0, 0.0, -0.4), True), ((0.0, 0.25, 0.0), False)):
        crossed = dry_env(reach_rule=hrule, arrival_head=head((0.05, 0.0)))
        assert crossed._goal_offset(True, dmap, box, 1.2, frame, 0.6) == pytest.approx(0.2)
        crossed._last_move = move
        off = crossed._goal_offset(True, dmap, box, 0.8, frame, 0.6)
        assert (off <= 0.15) is reached, (move, off)
        if reached:
            assert off == pytest.approx(0.05)
        crossed.close()
    # ... and when the detector loses the board on that descent (it was sighted within
    # range one step before, the head kept from being asked by the height sensor), the
    # board is held: a climb does not turn the camera away; a move across the floor does
    for move, expected in (((0.0, 0.0, -0.4), 0.05), ((0.0, 0.25, 0.0), None)):
        lost = dry_env(reach_rule=hrule, arrival_head=head((0.05, 0.0)))
        assert lost._goal_offset(True, dmap, box, 1.2, frame, 0.6) == pytest.approx(0.2)
        lost._last_move = move
        off = lost._goal_offset(False, dmap, box, 0.8, frame, 0.0)
        assert off == (None if expected is None else pytest.approx(expected)), (move, off)
        lost.close()
    with pytest.raises(ValueError, match="arrival_fusion must be a bool"):
        dry_env(reach_rule=rule, arrival_head=head((0.0, 0.0)), arrival_fusion="yes")
    with pytest.raises(ValueError, match="arrival_head needs a reach_rule with max_goal_offset"):
        dry_env(reach_rule=None, arrival_head=head((0.0, 0.0)))  # TelloEnv's default rule
    with pytest.raises(ValueError, match="arrival_head must be a callable"):
        dry_env(reach_rule=rule, arrival_head="arrival.pt")


def test_a_head_with_an_in_view_output_learns_to_decline(tmp_path):
    """``in_view_share``: on frames turned up to 80 deg and up to 1.2 m beside the thesis
    board (many without it), a short run learns when the board is in view far better than
    the majority guess on frames of another seed; the output survives the round trip."""
    wide = dict(yaw_deg=80.0, lateral=1.2, ahead=(-0.42, 1.0))
    x, y = render_offset_views(240, seed=5, **wide)
    xt, yt = render_offset_views(80, seed=6, **wide)
    seen, seen_t = y[:, 4] >= 0.05, yt[:, 4] >= 0.05
    assert 0.2 < seen.mean() < 0.9  # both kinds of frames are there
    est = train_goal_offset(x, y, epochs=25, seed=0, in_view_share=0.05)
    offsets, p_view = est.estimate(torch.as_tensor(xt))
    assert est.in_view and offsets.shape == (80, 2) and p_view.shape == (80,)
    accuracy = ((p_view.numpy() >= 0.5) == seen_t).mean()
    majority = max(seen_t.mean(), 1 - seen_t.mean())
    assert accuracy > majority + 0.1, (accuracy, majority)
    back = GoalOffsetEstimator.load(est.save(tmp_path / "ask.pt"))
    assert back.in_view and back.net.in_view
    torch.testing.assert_close(back.estimate(xt[:4])[1], p_view[:4], atol=2e-2, rtol=0)
    assert GoalOffsetEstimator(GoalOffsetNet()).estimate(xt[:2])[1] is None  # no such output
    with pytest.raises(ValueError, match="in_view_share must be a share in"):
        train_goal_offset(x, y, epochs=1, in_view_share=1.5)
    with pytest.raises(ValueError, match="needs labels \\[N, 5\\]"):
        train_goal_offset(x, y[:, :4], epochs=1, in_view_share=0.05)


def test_tello_env_asks_a_head_that_can_decline():
    """``lost_board="ask"``: once the head has read the board within ``hold_radius``, it is
    asked on the following frames without a detection for as long as it says the board is
    in view; a frame it declines gives nothing and ends the chain. A head without the
    in-view output is refused."""
    class Scripted:  # (ahead, lateral, p_in_view) per call
        in_view = True

        def __init__(self, looks):
            self.looks, self.calls = iter(looks), 0

        def __call__(self, frames):
            return self.estimate(frames)[0]

        def estimate(self, frames):
            self.calls += 1
            a, lat, p = next(self.looks)
            return torch.tensor([[a, lat]]), torch.tensor([p])

    frame, dmap, box = np.zeros((720, 960, 3), np.uint8), torch.zeros(84, 84), [0, 0, 84, 84]
    head = Scripted([(0.5, 0.0, 0.9), (0.3, 0.0, 0.9), (0.05, 0.0, 0.8), (0.0, 0.0, 0.2),
                     (0.0, 0.0, 0.2)])
    env = dry_env(arrival_head=head, lost_board="ask")
    assert env._goal_offset(False, dmap, box, 1.0, frame, 0.0) is None and head.calls == 0
    assert env._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(0.5)
    env._last_move = (0.2, 0.0, 0.0)
    # no detection, twice in a row: still asked, the segments run on from the last estimate
    assert env._goal_offset(False, dmap, box, 1.0, frame, 0.0) == pytest.approx(0.3)
    assert env._goal_offset(False, dmap, box, 1.0, frame, 0.0) == pytest.approx(0.05)
    assert env.arrival_estimate == pytest.approx((0.05, 0.0, 0.0))
    # the head declines: no estimate, and the chain ends (the next frame is not asked)
    assert env._goal_offset(False, dmap, box, 1.0, frame, 0.0) is None and head.calls == 4
    assert env.arrival_estimate is None
    assert env._goal_offset(False, dmap, box, 1.0, frame, 0.0) is None and head.calls == 4
    # with the board in the detector's sight a declined frame gives nothing either
    assert env._goal_offset(True, dmap, box, 1.0, frame, 0.6) is None and head.calls == 5
    env.close()
    # segment_slack: two estimates farther apart than the move flown (+ slack) cannot both
    # be right; the step counts at its current estimate, not along a segment that sweeps
    # through the goal sphere
    for slack, jumped in ((None, 0.3), (0.2, np.hypot(0.3, 0.5))):
        head = Scripted([(0.3, -0.3, 0.9), (0.3, 0.5, 0.9), (0.3, -0.05, 0.9), (0.3, 0.15, 0.9)])
        env = dry_env(arrival_head=head, lost_board="ask",
                       segment_slack=slack)
        assert env._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(
            np.hypot(0.3, 0.3))
        env._last_move = (0.25, 0.0, 0.0)  # 0.25 m to the right; the head reads 0.8 m moved
        assert env._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(jumped)
        env._goal_offset(True, dmap, box, 1.0, frame, 0.6)
        # 0.2 m read for a 0.25 m move: the segment counts either way
        assert env._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(0.3)
        env.close()
    with pytest.raises(ValueError, match="segment_slack=0.2 checks the arrival head's"):
        dry_env(segment_slack=0.2)
    with pytest.raises(ValueError, match="segment_slack must be a finite number >= 0"):
        dry_env(arrival_head=Scripted([]), segment_slack=-1.0)
    # height_margin: the rule's 0.13 m bounds the head's horizontal distance; 0.07 m is added
    # back for the height sensor's, so a pass 0.17 m above the goal point (inside the
    # simulator's 0.2 m sphere) is asked and counts; on the floor nothing changes
    hrule = ReachRule(max_distance=1.0, max_goal_offset=0.13, goal_height=1.0)
    for margin, alt, expected in ((None, 1.17, 0.17), (0.07, 1.17, np.hypot(0.07, 0.17) - 0.07),
                                  (0.07, 1.0, 0.1), (0.07, 1.25, 0.25)):
        head = Scripted([(0.1 if alt == 1.0 else 0.0, 0.0, 0.9)])
        env = dry_env(reach_rule=hrule, arrival_head=head, lost_board="ask",
                       height_margin=margin)
        got = env._goal_offset(True, dmap, box, alt, frame, 0.6)
        assert got == pytest.approx(expected), (margin, alt)
        assert head.calls == (0 if expected in (0.17, 0.25) else 1)
        env.close()
    with pytest.raises(ValueError, match="height_margin=0.07 widens the arrival head's rule"):
        dry_env(height_margin=0.07)
    real = GoalOffsetEstimator(GoalOffsetNet(8, in_view=True))
    dry_env(arrival_head=real, lost_board="ask").close()
    for plain in (GoalOffsetEstimator(GoalOffsetNet(8)), lambda f: torch.zeros(len(f), 2)):
        with pytest.raises(ValueError, match="needs a head that says whether the board is"):
            dry_env(arrival_head=plain, lost_board="ask")


def test_a_climb_keeps_one_place_across_the_floor():
    """``climb_reading="nearer"``: a descent moves nothing across the floor, so the step's
    segment stays at one place, the reading taken nearer the goal point's height, and a
    reading that jumped 0.3 m sideways below the head's height range does not fire (a
    logged false "reached" of the headline flights, seed 349, episode 3). With
    ``"both"`` (default) the slack keeps the new reading and the vertical sweep fires. A
    climb into the height band keeps the new reading; moves across the floor are as
    before; bad values are named."""
    class Scripted:  # (ahead, lateral) per call, the in-view output always sure
        in_view = True

        def __init__(self, looks):
            self.looks = iter(looks)

        def __call__(self, frames):
            return self.estimate(frames)[0]

        def estimate(self, frames):
            a, lat = next(self.looks)
            return torch.tensor([[a, lat]]), torch.tensor([0.9])

    frame, dmap, box = np.zeros((720, 960, 3), np.uint8), torch.zeros(84, 84), [0, 0, 84, 84]
    rule = ReachRule(max_distance=1.0, max_goal_offset=0.13, goal_height=1.0)
    before, after = (-0.148, -0.229), (0.024, 0.031)
    got = {}
    for climb in ("both", "nearer"):
        env = dry_env(reach_rule=rule, arrival_head=Scripted([before, after]),
                      lost_board="ask", segment_slack=0.2, climb_reading=climb)
        first = env._goal_offset(True, dmap, box, 0.946, frame, 0.6)
        assert first == pytest.approx(np.hypot(np.hypot(*before), 0.054))
        env._last_move = (0.0, 0.0, -0.21)  # a descent: 0.264 m below the goal's height
        got[climb] = env._goal_offset(True, dmap, box, 0.736, frame, 0.6)
        got[climb + " estimate"] = env.arrival_estimate
        env.close()
    assert got["both"] == pytest.approx(np.hypot(np.hypot(*after), 0.054))
    assert got["both"] <= rule.max_goal_offset  # fires, 0.27 m from the goal point
    assert got["nearer"] == pytest.approx(first) and got["nearer"] > rule.max_goal_offset
    assert got["nearer estimate"] == pytest.approx((*before, -0.264))
    assert got["both estimate"] == pytest.approx((*after, -0.264))
    # a climb from 0.26 m below into the band: the new reading is the nearer one
    env = dry_env(reach_rule=rule, arrival_head=Scripted([after, (0.05, 0.02)]),
                  lost_board="ask", segment_slack=0.2, climb_reading="nearer")
    env._goal_offset(True, dmap, box, 1.0, frame, 0.6)
    env._prev_offset = np.array([*after, -0.26])
    env._prev_dz = -0.26
    env._last_move = (0.0, 0.0, 0.25)
    assert env._goal_offset(True, dmap, box, 0.99, frame, 0.6) == pytest.approx(
        np.hypot(np.hypot(0.05, 0.02), 0.01))
    env.close()
    # a move across the floor: the segment between the two readings, as with "both"
    for climb in ("both", "nearer"):
        env = dry_env(reach_rule=rule, arrival_head=Scripted([(0.3, 0.0), (0.05, 0.0)]),
                      lost_board="ask", climb_reading=climb)
        env._goal_offset(True, dmap, box, 1.0, frame, 0.6)
        env._last_move = (0.25, 0.0, 0.0)
        got[climb] = env._goal_offset(True, dmap, box, 1.0, frame, 0.6)
        env.close()
    assert got["both"] == got["nearer"] == pytest.approx(0.05)
    with pytest.raises(ValueError, match="climb_reading must be 'both' or 'nearer', got 'up'"):
        dry_env(arrival_head=Scripted([]), climb_reading="up")
    with pytest.raises(ValueError, match="it needs a head that reads frames, got NoneType"):
        dry_env(climb_reading="nearer")
    with pytest.raises(ValueError, match="both decide where a climb's readings"):
        dry_env(arrival_head=Scripted([]), climb_reading="nearer", arrival_fusion=True)


def test_a_head_asked_on_the_frame_and_its_mirror():
    """``estimate_mirrored``: the mean of the frame's reading and its mirror image's (sideways
    turned back) and the two sideways readings' spread, bit for bit what two calls of
    ``estimate`` give; ``TelloEnv(mirror_check=)`` reads that mean and takes nothing from a
    frame whose spread exceeds the check, the chain then ending as for a declined frame."""
    from torchrl_causal.perception.goal import GoalDetector

    torch.manual_seed(0)
    est = GoalOffsetEstimator(GoalOffsetNet(8, in_view=True))
    frames = torch.randint(0, 255, (3, 240, 320, 3), dtype=torch.uint8)
    offsets, p_view, spread = est.estimate_mirrored(frames)
    one, p_one = est.estimate(frames)
    mirror, p_mirror = est.estimate(frames.flip(2))
    turned = mirror * torch.tensor([1.0, -1.0])
    torch.testing.assert_close(offsets, (one + turned) / 2)
    torch.testing.assert_close(p_view, (p_one + p_mirror) / 2)
    torch.testing.assert_close(spread, (one[:, 1] - turned[:, 1]).abs())
    assert GoalOffsetEstimator(GoalOffsetNet(8)).estimate_mirrored(frames)[1] is None

    class Full(GoalDetector):
        def detect(self, pixels, depth=None, **_):
            return torch.tensor([[[0.0, 0.0, 84.0, 84.0]]]), torch.tensor([[0.9]])

    class Mirrored:  # scripted (ahead, lateral) of a frame and of its mirror image per call
        in_view = True

        def __init__(self, pairs):
            self.pairs, self.calls = iter(pairs), 0

        def __call__(self, frames):
            raise AssertionError("mirror_check reads estimate_mirrored only")

        def estimate_mirrored(self, frames):
            self.calls += 1
            (a1, l1), (a2, l2) = next(self.pairs)  # l2: the mirror's, sign as read
            return (torch.tensor([[(a1 + a2) / 2, (l1 - l2) / 2]]), torch.tensor([0.9]),
                    torch.tensor([abs(l1 + l2)]))

    frame, dmap, box = np.zeros((720, 960, 3), np.uint8), torch.zeros(84, 84), [0, 0, 84, 84]
    # agree within 0.08 m: the mean (0.3, 0.09); disagree by 0.3 m: nothing, and no segment
    # to the next frame's reading
    head = Mirrored([])
    for ask in ("hold", "ask"):
        head.pairs = iter([((0.3, 0.05), (0.3, -0.13)), ((0.1, 0.0), (0.1, 0.3)),
                           ((-0.05, 0.02), (-0.05, -0.02))])
        env = dry_env(arrival_head=head, lost_board=ask, mirror_check=0.1)
        assert env._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(
            np.hypot(0.3, 0.09))
        env._last_move = (0.2, 0.0, 0.0)
        assert env._goal_offset(True, dmap, box, 1.0, frame, 0.6) is None  # unsure
        assert env.arrival_estimate is None
        assert env._goal_offset(True, dmap, box, 1.0, frame, 0.6) == pytest.approx(
            np.hypot(0.05, 0.02))  # one point: the unsure frame left no segment behind
        assert head.calls == (3 if ask == "hold" else 6)
        env.close()
    with pytest.raises(ValueError, match="mirror_check=0.1 asks the arrival head twice"):
        dry_env(mirror_check=0.1)
    with pytest.raises(ValueError, match="needs a learned head with estimate_mirrored"):
        dry_env(arrival_head=lambda f: torch.zeros(len(f), 2),
                 mirror_check=0.1)
    with pytest.raises(ValueError, match="mirror_check must be a finite number >= 0"):
        dry_env(arrival_head=est, mirror_check=-0.1)


def test_train_arrival_recipe_writes_measured_weights(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recipes"))
    import train_arrival

    out, data = tmp_path / "head.pt", tmp_path / "frames.npz"
    figures = train_arrival.main(["--out", str(out), "--train", "8", "--test", "6",
                                  "--epochs", "1", "--no-progress", "--yaw-weight", "1",
                                  "--yaw-deg", "45", "--data", str(data)])
    assert figures["test"]["n"] == 6 and len(figures["test"]["rule"]) == 5
    head = GoalOffsetEstimator.load(out)
    assert head.meta["near_share"] == 0.5 and head.meta["yaw_weight"] == 1.0
    assert head.meta["yaw_deg"] == 45.0
    frames = np.load(data)  # the rendered frames were kept, turned up to 45 deg
    assert frames["xtr"].shape == (8, *INPUT_SIZE, 3) and frames["yte"].shape == (6, 5)
    assert (abs(frames["ytr"][:, 3]) <= 45).all() and (abs(frames["ytr"][:, 3]) > 30).any()
    # a second run reads them back instead of rendering: the same figures
    again = train_arrival.main(["--out", str(tmp_path / "again.pt"), "--train", "8", "--test",
                                "6", "--epochs", "1", "--no-progress", "--yaw-weight", "1",
                                "--yaw-deg", "45", "--data", str(data)])
    assert again["test"] == figures["test"]
    # the auxiliary yaw output is kept in the file; the estimator still answers (ahead, lateral)
    assert head.net.outputs == 3 and tuple(head(np.zeros((2, 96, 128, 3), np.uint8)).shape) == (2, 2)
    import json

    assert json.loads(out.with_suffix(".json").read_text())["test"] == figures["test"]
    for argv, message in ((["--near-share", "2"], "--near-share=2.0"),
                          (["--epochs", "0"], "--epochs=0"),
                          (["--yaw-weight", "-1"], "--yaw-weight=-1.0"),
                          (["--yaw-deg", "120"], "--yaw-deg=120.0"),
                          (["--data", str(data), "--train", "9", "--yaw-deg", "45"],
                           "holds 8 \\+ 6 frames"),
                          (["--out", str(tmp_path / "head.bin")], "expected a .pt file")):
        with pytest.raises(ValueError, match=message):
            train_arrival.main(["--out", str(out), *argv])


def test_the_shipped_head_reads_the_range(views):
    """The shipped weights (make arrival-weights) on 60 renders of another seed: the range
    to the goal point within a few centimetres on average."""
    _, (xt, yt) = views
    est = GoalOffsetEstimator.load()
    pred = est(torch.as_tensor(xt)).numpy()
    assert np.abs(pred[:, 0] - yt[:, 0]).mean() < 0.08
    assert est.meta["test"]["n"] == 600 and "train_arrival.py" in est.meta["command"]


def test_the_shipped_rooms_head_reads_rooms_it_never_saw():
    """The shipped random-rooms head (make arrival-rooms-weights) on 60 renders in rooms of
    the held-out split with the printed 1.0 x 0.8 m board: the range to the goal point
    within a few centimetres on average, closer than the thesis-room head on the same
    frames."""
    from torchrl_causal.perception.arrival import ROOMS_WEIGHTS

    x, y = render_offset_views(60, seed=77, layout="heldout", goal_size=(1.0, 0.8))
    rooms, thesis = GoalOffsetEstimator.load(ROOMS_WEIGHTS), GoalOffsetEstimator.load()
    err = {name: np.abs(est(torch.as_tensor(x)).numpy()[:, 0] - y[:, 0]).mean()
           for name, est in (("rooms", rooms), ("thesis", thesis))}
    assert err["rooms"] < 0.08 and err["rooms"] < err["thesis"], err
    assert rooms.meta["rooms"] == "random" and rooms.meta["goal_size"] == [1.0, 0.8]
    assert rooms.meta["test"]["n"] == 600 and "--rooms random" in rooms.meta["command"]


def test_the_shipped_view_head_declines_frames_without_the_board():
    """The shipped head that can decline (make arrival-view-weights) on 80 renders in held-out
    rooms, turned up to 80 deg and up to 1.2 m beside the goal point: it tells frames with
    the board from frames without it, and where the board is in view it reads the offset
    closer than the random-rooms head (trained within 30 deg and 0.6 m) does."""
    from torchrl_causal.perception.arrival import ROOMS_WEIGHTS, VIEW_WEIGHTS

    x, y = render_offset_views(80, seed=78, layout="heldout", goal_size=(1.0, 0.8),
                               yaw_deg=80.0, lateral=1.2, ahead=(-0.42, 1.0))
    view, rooms = GoalOffsetEstimator.load(VIEW_WEIGHTS), GoalOffsetEstimator.load(ROOMS_WEIGHTS)
    offsets, p_view = view.estimate(x)
    seen = y[:, 4] >= view.meta["in_view_share"]
    assert 0.2 < seen.mean() < 0.95
    assert ((p_view.numpy() >= 0.5) == seen).mean() >= 0.9
    err = {"view": np.abs(offsets.numpy() - y[:, :2])[seen].mean(),
           "rooms": np.abs(rooms(x).numpy() - y[:, :2])[seen].mean()}
    assert err["view"] < err["rooms"], err
    assert view.in_view and view.net.width == 32 and view.meta["yaw_deg"] == 80.0
    assert "--in-view-share" in view.meta["command"]


def test_views_in_random_rooms_and_the_recipes_rooms_option(tmp_path):
    """``layout="train"/"heldout"``: frames near a board of the given size in random rooms
    (a new room every ``views_per_layout`` frames), seeded; ``train_arrival.py --rooms
    random`` trains on the training split, measures on the held-out one and, with
    ``--compare``, measures another head on the same test frames."""
    import json
    import sys
    from pathlib import Path

    kw = dict(seed=2, layout="heldout", views_per_layout=2, stream_sizes=((240, 320),))
    x, y = render_offset_views(4, **kw)
    x2, y2 = render_offset_views(4, **kw)
    np.testing.assert_array_equal(x, x2)
    np.testing.assert_array_equal(y, y2)
    assert x.shape == (4, *INPUT_SIZE, 3) and x.std() > 10
    assert (-0.42 <= y[:, 0]).all() and (y[:, 0] <= 0.8).all() and (abs(y[:, 1]) <= 0.6).all()
    thesis, _ = render_offset_views(4, seed=2, stream_sizes=((240, 320),))
    assert not np.array_equal(x, thesis)  # other rooms
    with pytest.raises(ValueError, match="layout must be 'thesis', 'train' or 'heldout'"):
        render_offset_views(1, seed=0, layout="val")
    with pytest.raises(ValueError, match="views_per_layout"):
        render_offset_views(1, seed=0, layout="train", views_per_layout=0)

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recipes"))
    import train_arrival

    out, data = tmp_path / "rooms.pt", tmp_path / "rooms.npz"
    figures = train_arrival.main(["--out", str(out), "--train", "4", "--test", "4",
                                  "--epochs", "1", "--no-progress", "--rooms", "random",
                                  "--compare", "shipped", "--data", str(data),
                                  "--lateral", "1.0", "--ahead-max", "1.2"])
    assert figures["rooms"] == "random" and figures["goal_size"] == [1.0, 0.8]
    assert (figures["lateral"], figures["ahead_max"]) == (1.0, 1.2)
    ytr = np.load(data)["ytr"]  # two near frames, then two of the wider far share
    assert (abs(ytr[:2, :2]) <= 0.35).all()
    assert (abs(ytr[2:, 1]) <= 1.0).all() and (ytr[2:, 0] <= 1.2).all()
    with pytest.raises(ValueError, match=r"rendered with --yaw-deg/--lateral/--ahead-max "
                                         r"\[30.0, 1.0, 1.2\], not \[30.0, 0.6, 0.8\]"):
        train_arrival.main(["--out", str(out), "--train", "4", "--test", "4",
                            "--rooms", "random", "--data", str(data)])
    assert figures["compare"]["weights"] == "shipped" and figures["compare"]["test"]["n"] == 4
    assert json.loads(out.with_suffix(".json").read_text())["compare"] == figures["compare"]
    with pytest.raises(ValueError, match="its frames are of --rooms random, not thesis"):
        train_arrival.main(["--out", str(out), "--train", "4", "--test", "4",
                            "--data", str(data)])
    for argv, message in ((["--compare", str(tmp_path / "none.pt")], "--compare=.*none.pt"),
                          (["--rooms", "random", "--goal-size", "0.1", "0.8"],
                           "--goal-size"),
                          (["--lateral", "0.2"], "--lateral=0.2"),
                          (["--ahead-max", "3"], "--ahead-max=3.0")):
        with pytest.raises(ValueError, match=message):
            train_arrival.main(["--out", str(out), *argv])
