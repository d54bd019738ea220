"""Scene layouts: the thesis scene and seeded random layouts with disjoint splits.

A :class:`Layout` is a plain, hashable description of one arena (no MuJoCo
objects): arena bounds, obstacles, the goal board, the start pose, colours and
lighting. :func:`~torchrl_causal.envs.scene.build_model` turns it into a MuJoCo
model.

* :func:`thesis_layout` is the embedded default (thesis Fig. 2.3): an open
  field with a geofence; the drone starts 1 m above the floor looking at the
  goal board about 3 m ahead; one pillar stands between them, slightly right of
  the line of sight, so the goal is partly visible from the start and the drone
  must side-step to pass.
* :class:`RandomLayoutGenerator` draws layouts from a seeded generator:
  obstacle count, size, shape and position, goal position and size, start pose,
  colours, floor/obstacle textures and lighting. Layout ``i`` of a split is a
  pure function of ``(seed, split, i)``. Every generated layout is checked to be
  solvable (:func:`free_path_exists`) and collision-free at the start.

**Splits.** Every layout has a :meth:`Layout.fingerprint` (a hash of its
parameters rounded to 1 cm / 0.1 deg / 1/100 colour). A layout belongs to the
``"heldout"`` split iff ``int(fingerprint, 16) % heldout_modulus == 0``, else to
``"train"``; the generator of a split rejects layouts of the other split, so the
two splits can never share a layout (identical layouts have identical
fingerprints and hence the same split).

**The goal point.** The drone "reaches" the goal when its centre comes within
``reach_radius`` (0.2 m) of :meth:`Layout.goal_point`: the point
``goal_standoff`` (default 0.45 m) in front of the board's face, at the height
of the board's centre. With the default drone (hull half-extent 0.12 m, at most
0.17 m to a corner) the hull is still >= 0.08 m from the board anywhere inside
the reach sphere, so reaching never requires touching the board.

Example:
    >>> from torchrl_causal.envs.layouts import thesis_layout, RandomLayoutGenerator
    >>> lay = thesis_layout()
    >>> [round(float(v), 2) for v in lay.goal_point()]
    [2.53, 0.0, 1.0]
    >>> gen = RandomLayoutGenerator(split="heldout", seed=0)
    >>> gen.layout(3) == gen.layout(3), gen.split_of(gen.layout(3))
    (True, 'heldout')
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field, replace

import numpy as np

__all__ = [
    "Obstacle",
    "Layout",
    "thesis_layout",
    "RandomLayoutGenerator",
    "free_path_exists",
    "SPLITS",
    "DRONE_HALF_EXTENTS",
]

#: Names of the random-layout splits.
SPLITS: tuple[str, ...] = ("train", "heldout")

#: Half extents (m) of the default drone's collision hull (x forward, y left, z up).
DRONE_HALF_EXTENTS: tuple[float, float, float] = (0.12, 0.12, 0.04)

Vec3 = tuple[float, float, float]
RGBA = tuple[float, float, float, float]


@dataclass(frozen=True)
class Obstacle:
    """One static obstacle standing on the floor.

    Args:
        center: ``(x, y, z)`` of the centre (m).
        half_size: for ``shape="box"`` the half extents ``(hx, hy, hz)``; for
            ``shape="cylinder"`` ``(radius, radius, half_height)``.
        yaw_deg: rotation about the vertical axis (boxes only).
        rgba: colour.
        shape: ``"box"`` or ``"cylinder"``.
        pattern: ``"plain"`` or ``"checker"`` (a small built-in checker texture
            in two shades of ``rgba``).

    Example:
        >>> Obstacle((1.0, 0.0, 1.0), (0.2, 0.2, 1.0)).footprint_radius() > 0.28
        True
    """

    center: Vec3
    half_size: Vec3
    yaw_deg: float = 0.0
    rgba: RGBA = (0.55, 0.3, 0.2, 1.0)
    shape: str = "box"
    pattern: str = "plain"

    def __post_init__(self):
        if self.shape not in ("box", "cylinder"):
            raise ValueError(f"Obstacle shape must be 'box' or 'cylinder', got {self.shape!r}")
        if self.pattern not in ("plain", "checker"):
            raise ValueError(
                f"Obstacle pattern must be 'plain' or 'checker', got {self.pattern!r}"
            )
        if min(self.half_size) <= 0:
            raise ValueError(f"Obstacle half_size must be positive, got {self.half_size!r}")

    def footprint_radius(self) -> float:
        """Radius of the obstacle's footprint's circumscribed circle (m)."""
        if self.shape == "cylinder":
            return float(self.half_size[0])
        return float(math.hypot(self.half_size[0], self.half_size[1]))

    def footprint_distance(self, xs, ys) -> np.ndarray:
        """Horizontal distance (m) of points ``(xs, ys)`` from the footprint (0 inside)."""
        dx = np.asarray(xs, dtype=np.float64) - self.center[0]
        dy = np.asarray(ys, dtype=np.float64) - self.center[1]
        if self.shape == "cylinder":
            return np.maximum(np.hypot(dx, dy) - self.half_size[0], 0.0)
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        lx = np.abs(c * dx + s * dy) - self.half_size[0]
        ly = np.abs(-s * dx + c * dy) - self.half_size[1]
        return np.hypot(np.maximum(lx, 0.0), np.maximum(ly, 0.0))

    def footprint_mask(self, xs: np.ndarray, ys: np.ndarray, inflate: float) -> np.ndarray:
        """Boolean mask of grid points ``(xs, ys)`` within ``inflate`` m of the footprint."""
        return self.footprint_distance(xs, ys) <= inflate


@dataclass(frozen=True)
class Layout:
    """A complete arena description (see the module docstring).

    Args:
        name: a label (``"thesis"``, ``"train-17"``, ...).
        arena: ``(xmin, ymin, xmax, ymax)`` of the flight volume (m); for an
            ``enclosed`` layout, the walls' inner faces.
        height: top of the flight volume (m); for an ``enclosed`` layout, the
            ceiling.
        start_pos: drone centre at reset ``(x, y, z)``.
        start_yaw_deg: drone heading at reset (deg, counter-clockwise from +x).
        goal_center: centre of the goal board ``(x, y, z)``.
        goal_yaw_deg: direction the board's heliport face points to (deg).
        goal_size: ``(width, height)`` of the board (m).
        obstacles: the obstacles.
        goal_standoff: distance of the goal point in front of the board's face (m).
        floor_rgb: the two colours of the floor's checker texture.
        wall_rgba: colour of the walls.
        ceiling_rgba: colour of the ceiling.
        helipad_rgb: background and marking colours of the heliport texture.
        light_dir: direction of the directional light.
        light_diffuse: its diffuse intensity (grey level).
        ambient: headlight ambient level.
        enclosed: ``False`` (default): an open field; ``arena`` and ``height``
            are the *flight volume* (a geofence: the episode ends when the
            drone's centre leaves it) and only the floor is solid. ``True``:
            the arena is a closed hall with four walls and a ceiling (the
            scene of earlier versions).

    Example:
        >>> lay = thesis_layout()
        >>> lay.name, len(lay.obstacles), lay.enclosed
        ('thesis', 1, False)
        >>> lay.inside((0.0, 0.0, 1.0)), lay.inside((0.0, 0.0, 3.5))
        (True, False)
    """

    name: str
    arena: tuple[float, float, float, float]
    height: float
    start_pos: Vec3
    start_yaw_deg: float
    goal_center: Vec3
    goal_yaw_deg: float
    goal_size: tuple[float, float]
    obstacles: tuple[Obstacle, ...] = ()
    goal_standoff: float = 0.45
    goal_thickness: float = 0.04
    floor_rgb: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (0.42, 0.42, 0.38),
        (0.36, 0.36, 0.33),
    )
    wall_rgba: RGBA = (0.75, 0.75, 0.72, 1.0)
    ceiling_rgba: RGBA = (0.85, 0.85, 0.85, 1.0)
    helipad_rgb: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (0.12, 0.25, 0.55),
        (0.97, 0.97, 0.97),
    )
    light_dir: Vec3 = (0.3, 0.2, -1.0)
    light_diffuse: float = 0.55
    ambient: float = 0.35
    enclosed: bool = False
    extra: dict = field(default_factory=dict, compare=False, hash=False, repr=False)

    def goal_normal(self) -> np.ndarray:
        """Unit vector (horizontal) the board's face points to."""
        a = math.radians(self.goal_yaw_deg)
        return np.array([math.cos(a), math.sin(a), 0.0])

    def inside(self, pos) -> bool:
        """Whether the point ``pos = (x, y, z)`` lies in the flight volume (arena x height)."""
        xmin, ymin, xmax, ymax = self.arena
        x, y, z = (float(v) for v in pos[:3])
        return xmin <= x <= xmax and ymin <= y <= ymax and z <= self.height

    def fence(self) -> tuple[tuple[float, float, float, float], tuple[float, float, float], float]:
        """The flight volume as a geofence: ``(arena, start, ceiling)`` with ``arena`` the
        rectangle ``(x_min, y_min, x_max, y_max)`` of the world frame, ``start`` the take-off
        pose ``(x, y, yaw_deg)`` in it and ``ceiling`` the volume's height: what
        ``TelloEnv(geofence=, geofence_origin=, max_height=)`` and ``EgoMap(geofence="env")``
        take (a drone's own frame starts at the take-off pose, possibly turned).

        Example:
            >>> from torchrl_causal.envs.layouts import thesis_layout
            >>> thesis_layout().fence()
            ((-2.0, -3.0, 5.0, 3.0), (0.0, 0.0, 0.0), 3.0)
        """
        x0, y0, _ = (float(v) for v in self.start_pos)
        return (tuple(float(v) for v in self.arena), (x0, y0, float(self.start_yaw_deg)),
                float(self.height))

    def goal_point(self) -> np.ndarray:
        """Where the drone's centre must get to (within ``reach_radius``)."""
        c = np.asarray(self.goal_center, dtype=np.float64)
        return c + self.goal_normal() * (self.goal_thickness / 2 + self.goal_standoff)

    def fingerprint(self) -> str:
        """Hex digest of the rounded layout parameters (used for the split rule)."""
        parts = [
            np.round(self.arena, 2),
            round(self.height, 2),
            np.round(self.start_pos, 2),
            round(self.start_yaw_deg, 1),
            np.round(self.goal_center, 2),
            round(self.goal_yaw_deg, 1),
            np.round(self.goal_size, 2),
            round(self.goal_standoff, 2),
        ]
        for o in self.obstacles:
            parts += [
                np.round(o.center, 2),
                np.round(o.half_size, 2),
                round(o.yaw_deg, 1),
                np.round(o.rgba, 2),
                o.shape,
                o.pattern,
            ]
        parts += [
            np.round(self.floor_rgb, 2),
            np.round(self.wall_rgba, 2),
            np.round(self.helipad_rgb, 2),
            np.round(self.light_dir, 2),
            round(self.light_diffuse, 2),
            round(self.ambient, 2),
        ]
        if self.enclosed:  # (open layouts keep the fingerprints of earlier versions)
            parts.append("enclosed")
        text = "|".join(
            str(p.tolist()) if isinstance(p, np.ndarray) else str(p) for p in parts
        ).replace("-0.0", "0.0")
        return hashlib.sha1(text.encode()).hexdigest()

    def nearest_surface(self, pos) -> tuple[str, float]:
        """What in the scene lies nearest the point ``pos = (x, y, z)``, and how far (m).

        ``"board"`` (the goal board), ``"obstacle"``, ``"wall"`` or ``"ceiling"`` (an
        ``enclosed`` layout's) or ``"floor"``: the distance is from ``pos`` to that
        object's surface (0 inside it). Tells what an emulated crash hit, from where the
        drone's centre was when it hit (``TelloEmulator.ground_truth()["crash_at"]``).

        Example:
            >>> from torchrl_causal.envs.layouts import thesis_layout
            >>> lay = thesis_layout()  # the board's face at x = 2.98
            >>> name, d = lay.nearest_surface((2.85, 0.0, 1.0))
            >>> name, round(d, 2)
            ('board', 0.13)
        """
        x, y, z = (float(v) for v in pos[:3])
        found = [("floor", max(z, 0.0))]
        for name, o in [("obstacle", o) for o in self.obstacles] + [
                ("board", self.board_obstacle())]:
            flat = float(o.footprint_distance(x, y))
            above = max(abs(z - o.center[2]) - o.half_size[2], 0.0)
            found.append((name, math.hypot(flat, above)))
        if self.enclosed:
            xmin, ymin, xmax, ymax = self.arena
            found += [("wall", max(min(x - xmin, xmax - x, y - ymin, ymax - y), 0.0)),
                      ("ceiling", max(self.height - z, 0.0))]
        return min(found, key=lambda f: f[1])

    def board_obstacle(self) -> Obstacle:
        """The goal board as a box obstacle (for path planning)."""
        return Obstacle(
            center=tuple(self.goal_center),
            half_size=(self.goal_thickness / 2, self.goal_size[0] / 2, self.goal_size[1] / 2),
            yaw_deg=self.goal_yaw_deg,
            rgba=(1.0, 1.0, 1.0, 1.0),
        )


def thesis_layout(enclosed: bool = False) -> Layout:
    """The embedded default scene (thesis Fig. 2.3, sec. 2.8: "an open environment").

    The drone starts at ``(0, 0, 1)`` facing +x, with the goal in view. The
    1.0 x 0.8 m goal board stands at ``x = 3`` facing the drone; its goal point
    is at ``(2.53, 0, 1)``, ten forward steps of 0.25 m away. One 0.3 x 0.3 x
    2 m pillar at ``(1.25, -0.1)`` blocks the straight line: a left side-step
    (0.25 m), ten forward steps and a right side-step reach the goal (12
    actions); flying over the pillar takes longer.

    The field is open: no walls and no ceiling, only the floor is solid. The
    flight volume (a geofence) is ``x in [-2, 5]``, ``y in [-3, 3]``,
    ``z <= 3`` m: the episode ends when the drone's centre leaves it.
    ``enclosed=True`` gives the closed 6 x 5 x 2.5 m hall of earlier versions
    (walls and a ceiling at the old arena bounds) for comparison.

    Example:
        >>> thesis_layout().start_pos, thesis_layout().arena
        ((0.0, 0.0, 1.0), (-2.0, -3.0, 5.0, 3.0))
        >>> thesis_layout(enclosed=True).height
        2.5
    """
    return Layout(
        name="thesis_hall" if enclosed else "thesis",
        arena=(-1.5, -2.5, 4.5, 2.5) if enclosed else (-2.0, -3.0, 5.0, 3.0),
        height=2.5 if enclosed else 3.0,
        start_pos=(0.0, 0.0, 1.0),
        start_yaw_deg=0.0,
        goal_center=(3.0, 0.0, 1.0),
        goal_yaw_deg=180.0,
        goal_size=(1.0, 0.8),
        obstacles=(
            Obstacle(
                center=(1.25, -0.1, 1.0),
                half_size=(0.15, 0.15, 1.0),
                rgba=(0.62, 0.32, 0.2, 1.0),
                pattern="checker",
            ),
        ),
        enclosed=enclosed,
    )


def free_path_exists(
    layout: Layout,
    clearance: float | None = None,
    cell: float = 0.05,
) -> bool:
    """Whether the drone can fly from the start to the goal point without collision.

    Conservative 2-D check: every obstacle (and the goal board) is treated as a
    floor-to-ceiling column, inflated by ``clearance`` (default: the drone's
    circumscribed horizontal radius plus 2 cm); the start and the goal point
    must lie in the same connected component of the free grid. Because the
    columns are conservative, altitude changes at any free cell are possible
    and ``True`` implies a collision-free 3-D path exists.

    Args:
        layout: the layout to check.
        clearance: inflation radius (m).
        cell: grid resolution (m).

    Example:
        >>> free_path_exists(thesis_layout())
        True
    """
    from scipy import ndimage

    if clearance is None:
        clearance = math.hypot(DRONE_HALF_EXTENTS[0], DRONE_HALF_EXTENTS[1]) + 0.02
    xmin, ymin, xmax, ymax = layout.arena
    xs = np.arange(xmin + cell / 2, xmax, cell)
    ys = np.arange(ymin + cell / 2, ymax, cell)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    blocked = (
        (gx - xmin < clearance)
        | (xmax - gx < clearance)
        | (gy - ymin < clearance)
        | (ymax - gy < clearance)
    )
    for o in layout.obstacles + (layout.board_obstacle(),):
        blocked |= o.footprint_mask(gx, gy, clearance)
    labels, _ = ndimage.label(~blocked)

    def cell_of(p):
        i = int(np.clip((p[0] - xmin) // cell, 0, len(xs) - 1))
        j = int(np.clip((p[1] - ymin) // cell, 0, len(ys) - 1))
        return i, j

    s = cell_of(layout.start_pos)
    g = cell_of(layout.goal_point())
    return bool(labels[s] != 0 and labels[s] == labels[g])


def _start_is_free(layout: Layout) -> bool:
    """The drone's hull at the start pose does not touch anything (exact for boxes)."""
    hx, hy, hz = DRONE_HALF_EXTENTS
    x, y, z = layout.start_pos
    r = math.hypot(hx, hy)
    xmin, ymin, xmax, ymax = layout.arena
    if not (xmin + r < x < xmax - r and ymin + r < y < ymax - r):
        return False
    if not (hz < z < layout.height - hz):
        return False
    for o in layout.obstacles + (layout.board_obstacle(),):
        top = o.center[2] + o.half_size[2]
        bottom = o.center[2] - o.half_size[2]
        if z - hz > top or z + hz < bottom:
            continue
        if o.footprint_mask(np.array([x]), np.array([y]), r)[0]:
            return False
    return True


def check_goal_size(goal_size) -> tuple[float, float] | None:
    """``None`` or a ``(width, height)`` board size in metres, each in [0.2, 2.0]."""
    if goal_size is None:
        return None
    try:
        w, h = (float(v) for v in goal_size)
    except (TypeError, ValueError):
        raise ValueError(f"goal_size must be (width, height) in metres, got {goal_size!r}") \
            from None
    if not (0.2 <= w <= 2.0 and 0.2 <= h <= 2.0):
        raise ValueError(f"goal_size must be (width, height) with each in [0.2, 2.0] m, "
                         f"got {goal_size!r}")
    return (w, h)


class RandomLayoutGenerator:
    """Seeded random layouts with disjoint ``train`` / ``heldout`` splits.

    Layout ``index`` of a split is a pure function of ``(seed, split, index)``.
    Drawn quantities: flight-volume size and height (open fields); 1 to ``max_obstacles``
    obstacles (boxes or cylinders, size, position, yaw, colour, plain or
    checker texture), at least one of them placed across the start-goal line;
    the goal board's size, height, position and facing; the start pose (the
    goal roughly ahead, within +-25 deg); floor, wall, heliport colours; light
    direction and intensity, ambient level. Layouts that are not solvable
    (:func:`free_path_exists`), start in collision, or belong to the other split
    are rejected and redrawn.

    Args:
        split: ``"train"`` or ``"heldout"``.
        seed: generator seed (the "world" seed, independent of the env's seed).
        min_obstacles: minimum obstacle count.
        max_obstacles: maximum obstacle count.
        heldout_modulus: one layout in ``heldout_modulus`` (by fingerprint) is
            held out.
        goal_size: ``(width, height)`` (m) of every goal board instead of a
            drawn one (0.7-1.2 x 0.6-0.9 m), e.g. the printed board a real
            Tello flies to. The draw consumes the same random numbers, but the
            board's size enters the fingerprint, so the splits hold other
            layouts than the default generator's. ``None``: drawn.

    Example:
        >>> gen = RandomLayoutGenerator("train", seed=1)
        >>> lay = gen.layout(0)
        >>> free_path_exists(lay), gen.split_of(lay)
        (True, 'train')
    """

    def __init__(
        self,
        split: str = "train",
        seed: int = 0,
        min_obstacles: int = 1,
        max_obstacles: int = 4,
        heldout_modulus: int = 5,
        goal_size: tuple[float, float] | None = None,
    ):
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative int, got {seed!r}")
        if min_obstacles < 0 or max_obstacles < min_obstacles:
            raise ValueError(
                f"need 0 <= min_obstacles <= max_obstacles, got "
                f"min_obstacles={min_obstacles!r}, max_obstacles={max_obstacles!r}"
            )
        if heldout_modulus < 2:
            raise ValueError(f"heldout_modulus must be >= 2, got {heldout_modulus!r}")
        self.split = split
        self.seed = int(seed)
        self.min_obstacles = int(min_obstacles)
        self.max_obstacles = int(max_obstacles)
        self.heldout_modulus = int(heldout_modulus)
        self.goal_size = check_goal_size(goal_size)

    def split_of(self, layout: Layout) -> str:
        """The split a layout belongs to (by its fingerprint)."""
        return "heldout" if int(layout.fingerprint(), 16) % self.heldout_modulus == 0 else "train"

    def layout(self, index: int) -> Layout:
        """Layout number ``index`` of this generator's split."""
        if index < 0:
            raise ValueError(f"layout index must be >= 0, got {index!r}")
        rng = np.random.default_rng(
            np.random.SeedSequence([self.seed, SPLITS.index(self.split), int(index)])
        )
        for _ in range(10_000):
            lay = self._draw(rng, f"{self.split}-{index}")
            if (
                self.split_of(lay) == self.split
                and _start_is_free(lay)
                and free_path_exists(lay)
            ):
                return lay
        raise RuntimeError("could not draw a valid layout")  # pragma: no cover

    def _draw(self, rng: np.random.Generator, name: str) -> Layout:
        u = rng.uniform
        length = u(5.0, 9.0)
        width = u(4.0, 7.0)
        height = u(2.4, 3.4)
        arena = (-1.2, -width / 2, length - 1.2, width / 2)
        z0 = u(0.8, 1.4)
        # goal board near the far wall, facing back towards the start region
        gw, gh = u(0.7, 1.2), u(0.6, 0.9)
        if self.goal_size is not None:  # drawn all the same: the draws after it do not move
            gw, gh = self.goal_size
        gz = float(np.clip(u(0.8, 1.5), gh / 2 + 0.1, height - gh / 2 - 0.1))
        gx = arena[2] - u(0.6, 1.5)
        gy = u(arena[1] + 1.0, arena[3] - 1.0)
        gyaw = 180.0 + u(-30.0, 30.0)
        base = Layout(
            name=name,
            arena=arena,
            height=height,
            start_pos=(0.0, 0.0, z0),
            start_yaw_deg=0.0,
            goal_center=(gx, gy, gz),
            goal_yaw_deg=gyaw,
            goal_size=(gw, gh),
        )
        gp = base.goal_point()
        sx, sy = u(-0.3, 0.6), u(arena[1] + 0.8, arena[3] - 0.8)
        bearing = math.degrees(math.atan2(gp[1] - sy, gp[0] - sx))
        syaw = bearing + u(-25.0, 25.0)
        # obstacles
        n = int(rng.integers(self.min_obstacles, self.max_obstacles + 1))
        obstacles = []
        for k in range(n):
            shape = "cylinder" if u() < 0.35 else "box"
            if k == 0:
                # across the line of sight, somewhere in the middle third
                t = u(0.35, 0.65)
                ox = sx + t * (gp[0] - sx) + u(-0.15, 0.15)
                oy = sy + t * (gp[1] - sy) + u(-0.25, 0.25)
            else:
                ox = u(arena[0] + 0.3, arena[2] - 0.3)
                oy = u(arena[1] + 0.3, arena[3] - 0.3)
            hz = u(0.8, height / 2)
            if shape == "cylinder":
                r = u(0.1, 0.3)
                hs = (r, r, hz)
            else:
                hs = (u(0.1, 0.4), u(0.1, 0.4), hz)
            rgb = rng.uniform(0.1, 0.9, size=3)
            obstacles.append(
                Obstacle(
                    center=(float(ox), float(oy), float(hz)),
                    half_size=tuple(float(v) for v in hs),
                    yaw_deg=float(u(0, 90)) if shape == "box" else 0.0,
                    rgba=(*(float(v) for v in rgb), 1.0),
                    shape=shape,
                    pattern="checker" if u() < 0.4 else "plain",
                )
            )
        # colours and lighting (solvability is checked by the caller, see layout())
        floor_a = rng.uniform(0.25, 0.6, size=3)
        floor_b = np.clip(floor_a * u(0.75, 0.95), 0, 1)
        wall = rng.uniform(0.45, 0.9, size=3)
        pad_bg = rng.uniform(0.05, 0.4, size=3)
        light_dir = (float(u(-0.6, 0.6)), float(u(-0.6, 0.6)), -1.0)
        return replace(
            base,
            start_pos=(float(sx), float(sy), float(z0)),
            start_yaw_deg=float(syaw),
            obstacles=tuple(obstacles),
            floor_rgb=(tuple(float(v) for v in floor_a), tuple(float(v) for v in floor_b)),
            wall_rgba=(*(float(v) for v in wall), 1.0),
            helipad_rgb=(tuple(float(v) for v in pad_bg), (0.97, 0.97, 0.97)),
            light_dir=light_dir,
            light_diffuse=float(u(0.35, 0.75)),
            ambient=float(u(0.2, 0.45)),
        )
