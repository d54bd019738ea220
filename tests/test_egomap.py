"""EgoMap on real MuJoCo scenes: dead reckoning, obstacles where they stand, goal memory."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torchrl.envs import Compose, SerialEnv, TransformedEnv, Transform
from torchrl.envs.utils import check_env_specs

from torchrl_causal.envs import DroneNavEnv
from torchrl_causal.modules import MapQNet
from torchrl_causal.pretrained import PolicySpec, build_policy, with_policy_features
from torchrl_causal.schema import ACTION_NAMES
from torchrl_causal.transforms import EgoMap

A = {name: i for i, name in enumerate(ACTION_NAMES)}


def _start_frame(env, point):
    """A world point in the frame of the episode's start pose (x ahead, y left)."""
    lay = env.layout
    sx, sy, _ = lay.start_pos
    yaw = math.radians(lay.start_yaw_deg)
    dx, dy = point[0] - sx, point[1] - sy
    return (math.cos(yaw) * dx + math.sin(yaw) * dy, -math.sin(yaw) * dx + math.cos(yaw) * dy)


def _fly(env, td, names):
    for name in names:
        td = env.step(td.set("action", torch.tensor(A[name])))
        assert not bool(td["next", "done"]), name
        td = env.step_mdp(td)
    return td


def test_dead_reckoning_matches_the_simulator_pose():
    base = DroneNavEnv("random", split="train", seed=3)
    env = TransformedEnv(base, EgoMap())
    td = env.reset()
    td = _fly(env, td, ["turn_left", "left", "turn_left", "turn_left", "backward", "turn_right",
                        "right", "ascend"])
    pose = env.transform._state["pose"][0]
    x, y, _, yaw = base.drone_pose()
    ex, ey = _start_frame(base, (x, y))
    assert float(pose[0]) == pytest.approx(ex, abs=1e-4)
    assert float(pose[1]) == pytest.approx(ey, abs=1e-4)
    dyaw = (yaw - base.layout.start_yaw_deg + 180) % 360 - 180
    assert math.degrees(float(pose[2])) == pytest.approx(dyaw, abs=1e-3)


def _occupied_points(transform, index=0):
    occ = transform._state["occ"][index].nonzero().float()
    half = transform.cells / 2.0
    return (occ - half + 0.5) * transform.resolution  # cell centres, start frame (x, y)


@pytest.mark.parametrize("layout_index", [0, 1, 2])
def test_obstacle_cells_lie_on_obstacles_or_the_board(layout_index):
    base = DroneNavEnv("random", split="heldout", layout_index=layout_index, seed=0)
    env = TransformedEnv(base, EgoMap())
    td = env.reset()
    td = _fly(env, td, ["turn_left", "turn_left", "turn_right", "turn_right", "turn_right",
                        "turn_right"])
    pts = _occupied_points(env.transform).numpy()
    assert len(pts) > 5  # the obstacle across the line of sight is seen
    lay = base.layout
    solids = [(_start_frame(base, o.center[:2]), o.footprint_radius()) for o in lay.obstacles]
    gw = lay.goal_size[0]
    solids.append((_start_frame(base, lay.goal_center[:2]), gw / 2 + 0.05))
    slack = 1.5 * env.transform.resolution
    for p in pts:
        gaps = [math.hypot(p[0] - c[0], p[1] - c[1]) - r for c, r in solids]
        assert min(gaps) < slack, (p, gaps)


def test_goal_memory_locates_the_board_and_keeps_it_out_of_view():
    base = DroneNavEnv(seed=0)  # thesis scene: the board is in view at reset
    env = TransformedEnv(base, EgoMap())
    td = env.reset()
    mem = td["goal_memory"]
    assert float(mem[0]) == 1.0 and float(mem[5]) == 0.0
    fwd, left = 5 * float(mem[1]), 5 * float(mem[2])
    gx, gy = _start_frame(base, base.layout.goal_center[:2])
    # board centre, from range and bearing; the pillar hides part of the board, which
    # moves the visible box's centre 6-7 degrees left (0.33 m at 2.9 m)
    assert math.hypot(fwd - gx, left - gy) < 0.45
    # turn away: after six 15-degree left turns the board is out of view, on the right
    td = _fly(env, td, ["turn_left"] * 6)
    mem = td["goal_memory"]
    assert not bool(td["goal_in_sight"])
    assert float(mem[0]) == 1.0 and 0 < float(mem[5]) <= 6 / 50  # steps since last seen
    f2, l2 = 5 * float(mem[1]), 5 * float(mem[2])
    x, y, _, yaw = base.drone_pose()
    gx, gy = base.layout.goal_center[0] - x, base.layout.goal_center[1] - y
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    assert math.hypot(f2 - (c * gx + s * gy), l2 - (-s * gx + c * gy)) < 0.45
    assert l2 < -2.0  # about 90 degrees to the right
    # the goal channel marks it on the map's right edge (2.8 m away, beyond the 2.4 m window)
    goal = td["ego_map"][2].nonzero()
    size = env.transform.size
    assert len(goal) == 9 and bool((goal[:, 1] >= size - 3).all())
    assert bool((goal[:, 0] - size / 2).abs().max() <= 4)


def test_specs_batched_and_partial_reset():
    env = TransformedEnv(SerialEnv(2, lambda: DroneNavEnv("random", image_size=48, seed=0)),
                         EgoMap(size=16, resolution=0.2))
    check_env_specs(env, seed=0)
    td = env.reset()
    td = env.step(td.set("action", torch.tensor([A["forward"], A["turn_left"]])))["next"]
    before = env.transform._state["pose"].clone()
    td2 = env.reset(td.clone().set("_reset", torch.tensor([[True], [False]])))
    after = env.transform._state["pose"]
    assert torch.equal(after[0], torch.zeros(3))
    assert torch.equal(after[1], before[1])
    assert td2["ego_map"].shape == (2, 3, 16, 16) and td2["ego_map"].dtype == torch.uint8


def test_bad_options_are_named():
    with pytest.raises(ValueError, match="size must be an int >= 8, got 4"):
        EgoMap(size=4)
    with pytest.raises(ValueError, match="resolution"):
        EgoMap(resolution=-0.1)
    with pytest.raises(ValueError, match="world_size"):
        EgoMap(size=64, resolution=0.5, world_size=10.0)
    with pytest.raises(ValueError, match="fov_deg"):
        EgoMap(fov_deg=200)
    env = TransformedEnv(DroneNavEnv(image_size=32, seed=0), EgoMap())
    with pytest.raises(RuntimeError, match="before reset"):
        env.transform._step(env.fake_tensordict(), env.fake_tensordict()["next"])


def test_map_policy_spec_builds_a_map_qnet_that_acts():
    spec = PolicySpec(inputs=["ego_map", "causal_features", "goal_memory", "action_history"],
                      history=2, image=False, explorer="egreedy",
                      ego_map={"size": 16, "resolution": 0.25})
    assert spec.actor_keys == ["ego_map", "policy_features"] and spec.n_features == 9 + 6 + 16
    env = with_policy_features(spec, DroneNavEnv(image_size=48, seed=0), seed=0)
    actor, _ = build_policy(spec, env.action_spec_unbatched)
    assert isinstance(actor.module[0].module if hasattr(actor.module[0], "module")
                      else actor.module[0], MapQNet) or "MapQNet" in repr(actor)
    td = env.rollout(3, actor)
    assert td["action"].shape == (3,) and td["next", "ego_map"].shape == (3, 3, 16, 16)
    assert PolicySpec.from_json(spec.to_json()) == spec
    with pytest.raises(ValueError, match="set image=False"):
        PolicySpec(inputs=["ego_map", "causal_features"])


def test_map_qnet_checks_its_input():
    net = MapQNet(8, n_features=4, map_size=16)
    assert net(torch.zeros(5, 3, 16, 16, dtype=torch.uint8), torch.zeros(5, 4)).shape == (5, 8)
    with pytest.raises(ValueError, match=r"map of shape \[\.\.\., 3, 16, 16\]"):
        net(torch.zeros(5, 3, 32, 32), torch.zeros(5, 4))
    with pytest.raises(ValueError, match="pass the features"):
        net(torch.zeros(5, 3, 16, 16))
    assert np.isfinite(net(torch.full((1, 3, 16, 16), 255, dtype=torch.uint8),
                           torch.ones(1, 4)).detach().numpy()).all()


def test_map_clearance_is_a_conservative_corridor_check():
    from torchrl_causal.envs.layouts import DRONE_HALF_EXTENTS
    from torchrl_causal.transforms.egomap import DRONE_HALF_WIDTH

    assert DRONE_HALF_WIDTH == DRONE_HALF_EXTENTS[1]
    base = DroneNavEnv(seed=0)  # thesis scene: the pillar's face 0.98 m ahead of the hull
    env = TransformedEnv(base, EgoMap())
    td = env.reset()
    ahead, back, left, right = (2 * td["map_clearance"]).tolist()
    assert 0.98 - 0.3 <= ahead <= 0.98 and back == left == right == 2.0
    steps = 0
    while 2 * float(td["map_clearance"][0]) >= base.step_size:
        td = env.step(td.set("action", torch.tensor(A["forward"])))
        assert not bool(td["next", "crashed"])  # the map said there was room
        td, steps = env.step_mdp(td), steps + 1
    assert steps == 3  # and the fourth step would hit the pillar:
    assert bool(env.step(td.set("action", torch.tensor(A["forward"])))["next", "crashed"])


def test_shielded_policy_never_takes_a_masked_move():
    from tensordict.nn import TensorDictSequential

    from torchrl_causal.modules import FeatureQNet

    torch.manual_seed(0)
    spec = PolicySpec(inputs=["goal_memory", "map_clearance"], image=False, shield=True,
                      explorer="egreedy", eps_init=0.3, eps_end=0.3)
    base = DroneNavEnv(seed=0)  # the pillar ahead: forward is masked after three steps
    env = with_policy_features(spec, base, seed=0)
    actor, explorer = build_policy(spec, env.action_spec_unbatched, seed=0)
    net = next(m for m in actor.modules() if isinstance(m, FeatureQNet))
    with torch.no_grad():  # a Q-network that always wants to fly forward
        net.net[-1].weight.zero_()
        net.net[-1].bias.copy_(torch.arange(8, 0, -1, dtype=torch.float32))
    policy = TensorDictSequential(actor, explorer)
    td = env.rollout(60, policy, break_when_any_done=False)
    masks, actions = td["action_mask"], td["action"]
    assert (~masks).any()  # some moves were masked
    assert bool(masks.gather(-1, actions[:, None]).all())  # never taken
    assert not bool(td["next", "crashed"].any())
    with pytest.raises(ValueError, match="shield=True needs EgoMap"):
        PolicySpec(inputs=["causal_features"], shield=True)
    with pytest.raises(ValueError, match="min_clearance"):
        EgoMap(min_clearance=-1.0)


def test_geofence_masks_moves_that_would_leave_the_area():
    """A tuple fence (start frame): forward is allowed while it ends 0.1 m inside the fence,
    masked once it would not; the other moves stay allowed."""
    env = TransformedEnv(DroneNavEnv(seed=0), EgoMap(geofence=(-2.0, -2.0, 0.5, 2.0)))
    td = env.reset()
    assert td["action_mask"][A["forward"]]  # 0.25 m ahead: inside 0.5 - 0.1
    td = _fly(env, td, ["forward"])
    mask = td["action_mask"]
    assert not mask[A["forward"]] and mask[A["backward"]]  # 0.5 m: beyond 0.4
    assert mask[A["turn_left"]] and mask[A["turn_right"]]
    env.close()
    with pytest.raises(ValueError, match="geofence"):
        EgoMap(geofence=(1.0, -1.0, 2.0, 1.0))  # the start must lie inside
    with pytest.raises(ValueError, match="geofence"):
        EgoMap(geofence="room")


def test_env_geofence_keeps_a_forward_flier_inside_random_arenas():
    """geofence='env' reads each layout's arena and ceiling at reset: a policy that flies
    forward (ascends when it can, turns when forward is masked) leaves the arena without
    the fence and never with it, over the same seeded episodes (the map's shield on in
    both, so that obstacles end few of them)."""
    def fly(fence):
        env = TransformedEnv(DroneNavEnv("random", split="train", seed=5, max_steps=60),
                             EgoMap(geofence=fence))
        env.set_seed(5)
        exits = 0
        for _ in range(6):
            td = env.reset()
            for t in range(60):
                mask = td["action_mask"]
                name = "ascend" if t % 5 == 0 and mask[A["ascend"]] else (
                    "forward" if mask[A["forward"]] else "turn_left")
                td = env.step(td.set("action", torch.tensor(A[name])))
                if bool(td["next", "done"]):
                    exits += bool(td["next", "out_of_bounds"])
                    break
                td = env.step_mdp(td)
        env.close()
        return exits

    assert fly(None) >= 2
    assert fly("env") == 0


@pytest.mark.parametrize("layout_index,actions", [
    (364254564, ["forward"] * 8 + ["left", "forward", "forward"]),
    (168654339, ["forward"] * 21),
])
def test_flank_margin_masks_the_sideways_move_into_an_obstacle_passed_on_its_side(
        layout_index, actions):
    """Two crashes of the generalist (validation layouts, docs/results.rst, "Crashes under
    the shield"), replayed: the drone has flown past an obstacle, whose mapped face is now
    behind it, and moves right into its unseen side face with the hull's back corner. With
    the hull's own corridor (flank_margin 0) the map says "right" is free and the move
    crashes; with flank_margin 0.3 m the mask forbids it, and forward stays allowed."""
    def fly(margin):
        env = TransformedEnv(DroneNavEnv("random", split="train", layout_seed=1,
                                         layout_index=layout_index), EgoMap(flank_margin=margin))
        td = _fly(env, env.reset(), actions)
        mask, right = td["action_mask"], 2 * float(td["map_clearance"][3])
        crashed = bool(env.step(td.set("action", torch.tensor(A["right"])))["next", "crashed"])
        env.close()
        return bool(mask[A["right"]]), bool(mask[A["forward"]]), right, crashed

    allowed, forward, right, crashed = fly(0.0)
    assert allowed and right >= 0.25 and crashed  # the map said there was room: there was not
    allowed, forward, right, crashed = fly(0.3)
    assert not allowed and forward and right < 0.2 and crashed  # masked (the same move)
    with pytest.raises(ValueError, match="flank_margin"):
        EgoMap(flank_margin=-0.1)


def test_goal_prior_guesses_a_hidden_goal_ahead_until_the_goal_is_seen():
    env = TransformedEnv(DroneNavEnv("random", split="heldout", image_size=48, seed=0),
                         EgoMap(goal_prior=4.0))
    plain = TransformedEnv(DroneNavEnv("random", split="heldout", image_size=48, seed=0),
                           EgoMap())
    env.set_seed(3)
    plain.set_seed(3)
    hidden = shown = 0
    for _ in range(12):
        td, ref = env.reset(), plain.reset()
        if bool(td["goal_in_sight"]):  # a goal in view is mapped where it is: no guess
            shown += 1
            assert torch.equal(td["goal_memory"], ref["goal_memory"])
            continue
        hidden += 1
        assert ref["goal_memory"][0] == 0  # without the prior: nothing known
        # the guess: 4 m straight ahead (forward / 5 m = 0.8), at the start's height, old (1.0)
        assert torch.allclose(td["goal_memory"], torch.tensor([1.0, 0.8, 0.0, 0.0, 0.8, 1.0]))
        assert td["ego_map"][2].any()  # and the goal channel marks it
        nxt = env.step(td.set("action", torch.tensor(A["turn_left"])))["next"]
        if not bool(nxt["goal_in_sight"]):  # turned left 15 deg: the guess is now right of ahead
            fwd, left = nxt["goal_memory"][1] * 5, nxt["goal_memory"][2] * 5
            assert abs(math.degrees(math.atan2(float(left), float(fwd))) + 15.0) < 0.5
    assert hidden >= 2 and shown >= 1
    check_env_specs(TransformedEnv(SerialEnv(2, lambda: DroneNavEnv("random", image_size=48,
                                                                      seed=0)),
                                   EgoMap(size=16, resolution=0.2, goal_prior=3.0)), seed=0)
    with pytest.raises(ValueError, match="goal_prior"):
        EgoMap(goal_prior=-1.0)
    with pytest.raises(ValueError, match="goal_prior must lie inside the map"):
        EgoMap(goal_prior=12.0)


def test_env_geofence_reads_a_tello_envs_own_fence():
    """geofence='env' over a TelloEnv (dry run: no drone, no socket) masks the moves its own
    geofence would refuse, in the same take-off frame."""
    import torch

    from torchrl_causal.envs import TelloEnv
    from torchrl_causal.perception.goal import SimGoalDetector

    class NoGoal(SimGoalDetector):
        def detect(self, pixels, depth=None, **_):
            return torch.zeros(len(pixels), 0, 4), torch.zeros(len(pixels), 0)

    tello = TelloEnv(dry_run=True, verbose=False, detector=NoGoal(),
                     depth_estimator=lambda p: torch.full(p.shape[:3], 5.0),
                     geofence=(-2.0, -0.3, 0.55, 3.0))
    env = TransformedEnv(tello, EgoMap(geofence="env"))
    td = env.reset()
    assert td["action_mask"][:4].tolist() == [True, True, True, False]  # right: y = -0.25 < -0.3 + 0.1
    td = env.step(td.set("action", torch.tensor(0)))["next"]  # forward to x = 0.25
    assert td["action_mask"][:4].tolist() == [False, True, True, False]  # 0.5 > 0.55 - 0.1
    env.close()
    # a TelloEnv without a geofence: nothing horizontal is fenced; its ceiling still is
    tello = TelloEnv(dry_run=True, verbose=False, detector=NoGoal(),
                     depth_estimator=lambda p: torch.full(p.shape[:3], 5.0), geofence=None,
                     max_height=1.0)
    env = TransformedEnv(tello, EgoMap(geofence="env"))
    td = env.reset()
    assert td["action_mask"][:4].all()
    assert td["action_mask"][4].item() == bool(td["altitude"].item() + 0.25 <= 1.0 - 0.1)
    env.close()


class _StrayDepth(Transform):
    """Writes a false near reading into ``depth`` while ``armed``: the whole of the central
    columns (``rows="band"``, a phantom obstacle) or one pixel per column (``rows="one"``,
    a stray pixel), ``dist`` metres away."""

    def __init__(self, dist=0.5, rows="band"):
        super().__init__(in_keys=["depth"], out_keys=["depth"])
        self.dist, self.rows, self.armed = dist, rows, False

    def _call(self, td):
        if self.armed:
            d = td["depth"].clone()
            h, w = d.shape[-2:]
            cols = slice(w // 2 - 4, w // 2 + 4)
            if self.rows == "band":
                d[..., cols] = self.dist
            else:
                d[..., h // 2, cols] = self.dist
            td["depth"] = d
        return td

    def _reset(self, td, td_reset):
        return self._call(td_reset)


def _cells_ahead(transform, lo, hi):
    """Occupied cells lying ``lo``-``hi`` m ahead of the start pose, within 0.3 m of its axis."""
    pts = _occupied_points(transform)
    return int(((pts[:, 0] >= lo) & (pts[:, 0] <= hi) & (pts[:, 1].abs() <= 0.3)).sum())


@pytest.mark.parametrize("depth", ["exact", "estimated"])
def test_a_phantom_stays_on_an_exact_map_and_later_views_erase_it_from_an_estimated_one(depth):
    stray = _StrayDepth(0.5, "band")
    env = TransformedEnv(DroneNavEnv(seed=0), Compose(stray, EgoMap(depth=depth)))
    ego = env.transform[-1]
    stray.armed = True
    td = env.reset()  # the thesis scene: nothing within 1 m ahead
    assert _cells_ahead(ego, 0.35, 0.7) > 0  # the phantom is on the map
    stray.armed = False
    td = _fly(env, td, ["ascend", "descend", "ascend", "descend"])  # four true views, no move
    if depth == "exact":
        assert _cells_ahead(ego, 0.35, 0.7) > 0  # a cell once occupied stays so
    else:
        assert _cells_ahead(ego, 0.35, 0.7) == 0  # seen through: free again
        assert bool(ego._state["free"][0].any())
        # the true obstacles ahead stay occupied: repeated hits, clamped log-odds
        assert _cells_ahead(ego, 1.0, 6.0) > 0


@pytest.mark.parametrize("fresh_hits", [False, True])
def test_fresh_hits_make_what_the_drone_sees_now_an_obstacle_for_this_step(fresh_hits):
    """Cells seen free for five views, then read occupied in one frame: the log-odds alone
    keep them free (the forward move stays allowed); with ``fresh_hits`` the reading blocks
    the forward move for that step, and the next true view frees it again."""
    stray = _StrayDepth(0.35, "band")
    env = TransformedEnv(DroneNavEnv(seed=0),
                         Compose(stray, EgoMap(depth="estimated", fresh_hits=fresh_hits)))
    ego = env.transform[-1]
    td = _fly(env, env.reset(), ["ascend", "descend", "ascend", "descend"])  # 5 views: free
    assert _cells_ahead(ego, 0.2, 0.5) == 0 and bool(td["action_mask"][A["forward"]])
    clear_before = float(td["map_clearance"][0])
    assert clear_before * 2 > 0.5
    stray.armed = True
    td = _fly(env, td, ["ascend"])  # one frame reads an obstacle 0.35 m ahead
    assert (_cells_ahead(ego, 0.2, 0.5) > 0) == fresh_hits
    assert bool(td["action_mask"][A["forward"]]) == (not fresh_hits)
    if fresh_hits:
        assert float(td["map_clearance"][0]) * 2 < 0.2
    else:
        assert float(td["map_clearance"][0]) == pytest.approx(clear_before, abs=0.08)
    stray.armed = False
    td = _fly(env, td, ["descend"])  # a true view: free again either way
    assert _cells_ahead(ego, 0.2, 0.5) == 0 and bool(td["action_mask"][A["forward"]])


@pytest.mark.parametrize("depth", ["exact", "estimated"])
def test_one_stray_pixel_per_column_is_an_obstacle_only_on_an_exact_map(depth):
    stray = _StrayDepth(0.5, "one")
    env = TransformedEnv(DroneNavEnv(seed=0), Compose(stray, EgoMap(depth=depth)))
    stray.armed = True
    env.reset()
    n = _cells_ahead(env.transform[-1], 0.35, 0.7)
    assert (n > 0) if depth == "exact" else (n == 0)


@pytest.mark.parametrize("layout_index", [0, 1])
def test_an_estimated_map_of_exact_depth_keeps_the_obstacles_where_they_stand(layout_index):
    """On the simulator's depth both models map the same scene: every occupied cell of the
    estimated map lies on a solid, and it finds most of the exact map's cells."""
    maps = {}
    for depth in ("exact", "estimated"):
        base = DroneNavEnv("random", split="heldout", layout_index=layout_index, seed=0)
        env = TransformedEnv(base, EgoMap(depth=depth))
        td = env.reset()
        _fly(env, td, ["turn_left", "turn_left", "turn_right", "turn_right", "turn_right",
                       "turn_right"])
        maps[depth] = env.transform._state["occ"][0].clone()
    exact, est = maps["exact"], maps["estimated"]
    assert int(est.sum()) > 5
    assert int((est & ~exact).sum()) == 0  # nothing the exact map does not have
    assert int((est & exact).sum()) >= 0.6 * int(exact.sum())


def test_depth_model_options_are_named():
    with pytest.raises(ValueError, match="depth must be one of .*'lidar'"):
        EgoMap(depth="lidar")
    with pytest.raises(ValueError, match="scan_quantile must be a number in \\[0, 1\\), got 1.0"):
        EgoMap(scan_quantile=1.0)
    with pytest.raises(ValueError, match="log_odds must be .*got \\(0.85, 0.4\\)"):
        EgoMap(depth="estimated", log_odds=(0.85, 0.4))
    with pytest.raises(ValueError, match="log_odds applies to depth='estimated'"):
        EgoMap(log_odds=(0.85, 0.4, 3.5))
    with pytest.raises(ValueError, match="fresh_hits applies to depth='estimated'"):
        EgoMap(fresh_hits=True)
    with pytest.raises(ValueError, match="fresh_hits must be True or False, got 'yes'"):
        EgoMap(depth="estimated", fresh_hits="yes")
    assert EgoMap(depth="estimated").scan_quantile == 0.5
    assert EgoMap().scan_quantile == 0.0


def test_a_policy_spec_passes_the_depth_model_to_its_egomap():
    spec = PolicySpec(inputs=["causal_features", "map_clearance"], history=0, shield=True,
                      explorer="egreedy", ego_map={"depth": "estimated"})
    env = with_policy_features(spec, DroneNavEnv(image_size=48, seed=0))
    assert [t.depth for t in env.transform if isinstance(t, EgoMap)] == ["estimated"]
    spec = PolicySpec(inputs=["causal_features", "map_clearance"], history=0, shield=True,
                      explorer="egreedy")
    env = with_policy_features(spec, DroneNavEnv(image_size=48, seed=0))
    assert [t.depth for t in env.transform if isinstance(t, EgoMap)] == ["exact"]
