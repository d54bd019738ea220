"""Layouts: thesis scene, random generator determinism, solvability, disjoint splits."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np
import pytest

from torchrl_causal.envs.layouts import (
    DRONE_HALF_EXTENTS,
    Layout,
    Obstacle,
    RandomLayoutGenerator,
    free_path_exists,
    thesis_layout,
)
from torchrl_causal.envs.scene import build_model, helipad_image


def _start_contacts(layout: Layout) -> int:
    model, ids = build_model(layout)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return int(data.ncon)


def test_thesis_layout_geometry():
    lay = thesis_layout()
    assert free_path_exists(lay)
    assert _start_contacts(lay) == 0
    gp = lay.goal_point()
    start = np.asarray(lay.start_pos)
    # modest distance: about ten 0.25 m steps; goal point at the start altitude
    assert 2.0 <= np.linalg.norm(gp - start) <= 3.0 and gp[2] == start[2]
    # the single obstacle blocks the straight line
    (o,) = lay.obstacles
    assert o.footprint_mask(np.array([o.center[0]]), np.array([0.0]), DRONE_HALF_EXTENTS[1])[0]
    # the goal point leaves room between the hull and the board even at the reach radius
    face_x = lay.goal_center[0] - lay.goal_thickness / 2
    assert face_x - (gp[0] + 0.2) > np.hypot(*DRONE_HALF_EXTENTS[:2])


def test_open_thesis_layout_and_enclosed_hall():
    """Open (default): only the floor is solid, arena x height is a geofence; the
    enclosed hall keeps the old walls and ceiling."""
    lay, hall = thesis_layout(), thesis_layout(enclosed=True)
    assert not lay.enclosed and lay.arena == (-2.0, -3.0, 5.0, 3.0) and lay.height == 3.0
    assert hall.enclosed and hall.arena == (-1.5, -2.5, 4.5, 2.5) and hall.height == 2.5
    assert hall.name != lay.name and hall.fingerprint() != lay.fingerprint()
    # the bounds belong to the flight volume
    assert lay.inside((-2.0, -3.0, 3.0)) and lay.inside((5.0, 3.0, 1.0))
    for p in [(-2.01, 0, 1), (5.01, 0, 1), (0, -3.01, 1), (0, 3.01, 1), (0, 0, 3.01)]:
        assert not lay.inside(p), p
    assert lay.inside(lay.start_pos) and lay.inside(lay.goal_point())
    geoms = {}
    for name, layout in (("open", lay), ("hall", hall)):
        model, _ = build_model(layout)
        geoms[name] = {
            mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, i) for i in range(model.ngeom)
        }
    solid = {"ceiling", "wall0", "wall1", "wall2", "wall3"}
    assert solid <= geoms["hall"] and not (solid & geoms["open"])
    assert _start_contacts(hall) == 0 and free_path_exists(hall)


def test_blocked_layout_is_not_solvable():
    lay = thesis_layout()
    wall = Obstacle(center=(1.25, 0.0, 1.25), half_size=(0.1, 2.6, 1.25))
    from dataclasses import replace

    assert not free_path_exists(replace(lay, obstacles=(wall,)))


@pytest.mark.parametrize("split", ["train", "heldout"])
def test_random_layouts_deterministic_solvable_and_start_free(split):
    gen = RandomLayoutGenerator(split=split, seed=3)
    again = RandomLayoutGenerator(split=split, seed=3)
    for i in range(6):
        lay = gen.layout(i)
        assert lay == again.layout(i) and lay.fingerprint() == again.layout(i).fingerprint()
        assert gen.split_of(lay) == split
        assert free_path_exists(lay)
        assert _start_contacts(lay) == 0, lay.name
        # random layouts are open: the start and the goal point lie in the flight volume
        assert not lay.enclosed and lay.inside(lay.start_pos) and lay.inside(lay.goal_point())
    assert gen.layout(0) != gen.layout(1)
    assert RandomLayoutGenerator(split=split, seed=4).layout(0) != gen.layout(0)


def test_splits_never_share_a_layout():
    train = RandomLayoutGenerator("train", seed=0)
    held = RandomLayoutGenerator("heldout", seed=0)
    ft = {train.layout(i).fingerprint() for i in range(25)}
    fh = {held.layout(i).fingerprint() for i in range(25)}
    assert len(ft) == 25 and len(fh) == 25 and not (ft & fh)
    # the split is a function of the layout itself
    assert all(int(f, 16) % train.heldout_modulus != 0 for f in ft)
    assert all(int(f, 16) % held.heldout_modulus == 0 for f in fh)


def test_random_env_resets_draw_layouts_and_heldout_split():
    from torchrl_causal.envs import DroneNavEnv

    env = DroneNavEnv("random", split="heldout", n_layouts=1000, seed=0)
    names = set()
    for _ in range(3):
        td = env.reset()
        names.add(env.layout.name)
        assert env.layout.name.startswith("heldout-")
        assert not td["crashed"].item() and env.data.ncon == 0
    assert len(names) >= 2
    pinned = DroneNavEnv("random", layout_index=5, seed=1)
    pinned.reset()
    assert pinned.layout == RandomLayoutGenerator("train", seed=0).layout(5)
    env.close()
    pinned.close()


def test_fixed_goal_size_layouts():
    """``goal_size`` fixes every board (a printed one) and keeps the layouts valid and split."""
    from torchrl_causal.envs import DroneNavEnv

    drawn = {RandomLayoutGenerator("train", seed=0).layout(i).goal_size for i in range(6)}
    assert len(drawn) == 6  # drawn sizes differ
    for split in ("train", "heldout"):
        gen = RandomLayoutGenerator(split, seed=0, goal_size=(1.0, 0.8))
        for i in range(6):
            lay = gen.layout(i)
            assert lay.goal_size == (1.0, 0.8)
            assert gen.split_of(lay) == split and free_path_exists(lay)
    env = DroneNavEnv("random", goal_size=(0.6, 0.5), seed=0)
    env.reset()
    assert env.layout.goal_size == (0.6, 0.5)
    # the board in the MuJoCo model has that size (half extents of its box geom)
    gid = mujoco.mj_name2id(env.model, mujoco.mjtObj.mjOBJ_GEOM, "goal_board")
    assert gid >= 0
    np.testing.assert_allclose(sorted(env.model.geom_size[gid])[1:], [0.25, 0.3], atol=1e-6)
    env.close()
    with pytest.raises(ValueError, match="goal_size applies to layout='random'"):
        DroneNavEnv("thesis", goal_size=(1.0, 0.8))


def test_helipad_texture_in_memory():
    img = helipad_image(64)
    assert img.shape == (64, 64, 3) and img.dtype == np.uint8
    marking = (img == 247).all(-1)
    # the "H": two vertical bars and a cross bar, symmetric
    assert marking[32, 20:26].all() and marking[32, 38:44].all() and marking[32, 26:38].all()
    assert (marking == marking[:, ::-1]).mean() > 0.95


@pytest.mark.parametrize(
    "kwargs,name",
    [({"split": "validation"}, "split"), ({"seed": -1}, "seed"), ({"max_obstacles": -1}, "max_obstacles"),
     ({"goal_size": (3.0, 0.8)}, "goal_size"), ({"goal_size": "big"}, "goal_size")],
)
def test_generator_bad_options(kwargs, name):
    with pytest.raises(ValueError, match=name):
        RandomLayoutGenerator(**kwargs)


def test_nearest_surface_names_what_a_point_touches():
    """Layout.nearest_surface: the board, an obstacle, the floor, and an enclosed layout's
    walls and ceiling, each with the distance to its surface (what a crash hit)."""
    lay = thesis_layout(enclosed=True)  # pillar 0.3 x 0.3 at (1.25, -0.1); board face x=2.98
    name, d = lay.nearest_surface((2.80, 0.1, 1.0))
    assert name == "board" and d == pytest.approx(0.18)
    name, d = lay.nearest_surface((1.25, 0.15, 1.2))  # 0.1 m beside the pillar's side
    assert name == "obstacle" and d == pytest.approx(0.1)
    assert lay.nearest_surface((0.0, 0.0, 0.05)) == ("floor", pytest.approx(0.05))
    assert lay.nearest_surface((-1.4, 0.0, 1.2)) == ("wall", pytest.approx(0.1))
    assert lay.nearest_surface((0.0, 0.0, 2.45)) == ("ceiling", pytest.approx(0.05))
    open_lay = thesis_layout()  # open field: no walls, no ceiling
    assert open_lay.nearest_surface((-1.4, 0.0, 1.2))[0] not in ("wall", "ceiling")
    # inside the board: distance 0
    assert lay.nearest_surface((3.0, 0.0, 1.0)) == ("board", 0.0)


def test_a_blank_board_back_hides_the_heliport_from_behind():
    """``board_back="blank"``: seen from 0.45 m behind the board (the mirror image of the
    goal point) the heliport is gone -- no goal pixels, a near-uniform frame --, while the
    view from the goal point is the same render as with the default textured back."""
    import math

    from torchrl_causal.envs import DroneNavEnv
    from torchrl_causal.perception.dataset import _quat

    views = {}
    for back in ("heliport", "blank"):
        env = DroneNavEnv("random", split="heldout", layout_index=5, goal_size=(1.0, 0.8),
                          image_size=(60, 80), seed=0, board_back=back)
        env.reset()
        lay, qa = env.layout, env.ids.qpos_adr
        n = np.asarray(lay.goal_normal())[:2] / np.linalg.norm(np.asarray(lay.goal_normal())[:2])
        for side in (1, -1):  # in front (the goal point), behind
            xy = np.asarray(lay.goal_center)[:2] + side * 0.45 * n
            env.data.qpos[qa:qa + 3] = (xy[0], xy[1], lay.goal_point()[2])
            env.data.qpos[qa + 3:qa + 7] = _quat(math.degrees(math.atan2(-side * n[1],
                                                                         -side * n[0])), 0, 0)
            obs = env._observe(False, False)
            views[back, side] = (int(obs["goal_pixels"][0]),
                                 np.asarray(obs["pixels"]).astype(float))
        env.close()
    assert views["heliport", 1][0] == views["blank", 1][0] == 60 * 80
    np.testing.assert_array_equal(views["heliport", 1][1], views["blank", 1][1])
    assert views["heliport", -1][0] == 60 * 80 and views["heliport", -1][1].std() > 30
    assert views["blank", -1][0] == 0 and views["blank", -1][1].std() < 10
    with pytest.raises(ValueError, match="board_back must be 'heliport' or 'blank', got 'x'"):
        DroneNavEnv("random", board_back="x")
