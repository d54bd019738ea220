"""A top-down memory of what the drone has seen: an egocentric occupancy map and the goal's place.

A feed-forward policy that reads only the current frame forgets an obstacle the
moment it leaves the camera's 60 degree view and forgets the goal the moment it
is hidden; on random layouts it then crashes into obstacles beside it or
searches in circles (docs/generalisation.rst). :class:`EgoMap` gives the policy
the memory a navigation stack keeps (the egocentric maps of e.g. Gupta et al.,
2017, "Cognitive Mapping and Planning"; Chaplot et al., 2020, "Active Neural
SLAM"), built from what a real drone has too:

* **odometry by dead reckoning** from the commanded actions (each action is a
  known move of ``step_size`` metres or a turn of ``turn_deg`` degrees; a move
  that is blocked ends the episode as a crash), in the frame of the episode's
  start pose;
* **a depth scan**: for every image column, the nearest depth pixel within
  ``band`` metres of the camera's height is an obstacle point; the cells along
  the ray before it are seen free. The points are written into a world-frame
  grid that lives for the episode;
* **the goal's last estimated position**: each time ``goal_in_sight``, the
  goal measurement (range along the ray through the box centre, bearing, and
  the box's vertical position when ``goal_box`` is there) gives the board's
  place in the start frame; it is kept while the goal is out of view.

It writes ``ego_map`` (uint8 ``[..., 3, size, size]``: obstacle, seen-free and
goal channels, 0 or 255, a ``size`` x ``size`` window of ``resolution``-metre
cells centred on the drone with its heading pointing up, row 0 ahead; the goal
is a 3 x 3 mark, drawn at the window's edge in its direction when it is
farther) and
``goal_memory`` (float32 ``[..., 6]``: known flag, the goal's forward and
leftward offset in metres / 5, its height above the camera in metres, its
horizontal distance / 5, and the steps since it was last seen / 50, capped at 1)
and ``map_clearance`` (float32 ``[..., 4]``: how far the drone's hull can move
ahead, back, left and right before it meets an obstacle cell of the map, in
metres / 2, capped at 1 -- a corridor check of the four horizontal moves
against everything seen so far, also beside and behind the camera's view; with
``flank_margin`` a left / right move also counts obstacle cells up to that far
behind the hull's back edge),
``ego_pose`` (float32 ``[..., 3]``: the dead-reckoned pose in the start
frame -- x ahead and y to the left of the start, in metres, and the yaw in
radians -- for a planner on the map, e.g.
:class:`~torchrl_causal.modules.GoalSearch`), ``goal_seen`` (bool
``[..., 1]``: the goal has really been in view this episode; a
``goal_prior`` guess does not count),
and ``action_mask`` (bool ``[..., n_actions]``, TorchRL's action-mask
convention): False for a horizontal move whose clearance is below
``min_clearance`` and for a descent that would end below ``FLOOR_MARGIN``
(0.15 m) of altitude; turns and ascents are always allowed. A policy built
with ``PolicySpec(shield=True)`` never picks a masked move (a safety shield:
the map says the hull would not fit). With a ``geofence`` the mask also
forbids a horizontal move whose dead-reckoned end lies outside the flight
area, and an ascent above its ceiling (``"env"``: the ``DroneNavEnv``
layout's arena and height, read at every reset, or a
:class:`~torchrl_causal.envs.TelloEnv`'s own ``geofence`` and ``max_height``;
a tuple: the area in the start frame, as :class:`~torchrl_causal.envs.TelloEnv`'s
``geofence``).

The depth may be the simulator's (``DroneNavEnv``) or estimated from the RGB
image (``EstimatedDepth``, the Tello path): the transform reads ``depth``
after the feature stack has written it. ``depth="exact"`` (default) trusts
every reading: a column's nearest in-band pixel is the obstacle and a cell,
once seen occupied or free, stays so for the episode. ``depth="estimated"``
is the map for a depth *estimate* (MonoDepth's readings within 1 m scatter by
a factor of two either way, docs/perception.rst): a column's obstacle point
is the median of its in-band pixels (``scan_quantile``), so one stray pixel
makes no obstacle, and each cell keeps a log-odds occupancy (the sensor model
of OctoMap, Hornung et al., 2013: +0.85 per hit, -0.4 per pass, clamped to
+-3.5; ``log_odds``) that later views can overturn, so a phantom obstacle
read in one frame is erased when the drone looks through it again. With
``fresh_hits=True`` the current frame's readings are obstacles for that step
whatever the log-odds say, so the map never holds less than the drone sees now.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from torchrl.data import Binary, Bounded, Unbounded
from torchrl.envs.transforms import Transform

__all__ = ["EgoMap", "GOAL_MEMORY_FIELDS", "CLEARANCE_FIELDS", "DEPTH_MODELS",
           "ESTIMATED_SCAN_QUANTILE", "OCTOMAP_LOG_ODDS"]

#: Half width of the drone's collision hull (m), as in ``layouts.DRONE_HALF_EXTENTS``.
DRONE_HALF_WIDTH = 0.12
#: ``action_mask`` forbids a descent that would end lower than this altitude (m).
FLOOR_MARGIN = 0.15

#: ``depth`` choices: how far the map trusts a depth reading (see the module docstring).
DEPTH_MODELS = ("exact", "estimated")
#: ``depth="estimated"``'s defaults: the column statistic and the log-odds sensor model
#: (hit, pass, clamp) -- OctoMap's (Hornung et al., 2013: p_hit 0.7, p_miss 0.4, clamped
#: to [0.12, 0.97]).
ESTIMATED_SCAN_QUANTILE = 0.5
OCTOMAP_LOG_ODDS = (0.85, 0.4, 3.5)

#: The values of ``goal_memory``, in order.
GOAL_MEMORY_FIELDS: tuple[str, ...] = (
    "known", "forward_5m", "left_5m", "up_m", "distance_5m", "steps_since_seen_50",
)
#: The values of ``map_clearance``, in order (free distance on the map / 2 m, capped at 1).
CLEARANCE_FIELDS: tuple[str, ...] = ("forward", "backward", "left", "right")


def _number(name, value, low=0.0, strict=True):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > low if strict else value >= low)
    if not ok:
        raise ValueError(f"EgoMap {name} must be a finite number {'>' if strict else '>='} "
                         f"{low}, got {value!r}")


class EgoMap(Transform):
    """Egocentric occupancy map and goal memory from depth, goal measurement and dead reckoning.

    Args:
        size: side of the written window, in cells (>= 8).
        resolution: cell side (m).
        world_size: side of the episode's world-frame grid (m), centred on the
            start pose; points outside it are dropped.
        max_range: depth beyond this is not used (m): no obstacle, and free
            space is carved only up to it.
        band: obstacle points are the depth pixels within this many metres above
            or below the camera.
        step_size, turn_deg: the env's move (m) and turn (deg) per action
            (default: read from the env the transform is appended to, else
            0.25 and 15).
        fov_deg: the camera's vertical field of view (default: the env's, else 60).
        min_clearance: ``action_mask`` allows a horizontal move only where
            ``map_clearance`` (in metres) is at least this (0: every move).
        n_actions: size of the action space (actions in
            :data:`~torchrl_causal.schema.ACTION_NAMES` order).
        action_key: the action's key (index or one-hot).
        geofence: None (default: no fence in the mask); ``"env"``: the base
            :class:`~torchrl_causal.envs.DroneNavEnv`'s arena and ceiling,
            read at every reset (or a :class:`~torchrl_causal.envs.TelloEnv`'s
            own ``geofence``, if any, and ``max_height``); or ``(x_min, y_min, x_max, y_max)`` (m) in the
            start frame (x forward, y left at reset). ``action_mask`` then
            forbids a horizontal move that would end outside it (less
            ``geofence_margin``) and, with ``"env"``, an ascent above the
            ceiling.
        geofence_margin: how far inside the fence a move must end (m).
        flank_margin: a left / right move's corridor also reaches this far
            behind the hull's back edge (m; 0: the hull's own length). The
            camera looks ahead, so the flank a sideways move sweeps is mapped
            only from earlier views: a box passed on its side is on the map by
            its front face, behind the drone, and its unseen side face is what
            the hull's back corner meets (docs/results.rst, "Crashes under the
            shield").
        goal_prior: None (default), or a distance (m): where the reset does
            not see the goal, ``goal_memory`` starts from a guess -- the goal
            ``goal_prior`` metres straight ahead, at the start's height, last
            "seen" 50 steps ago (its age capped) -- until the goal is really
            seen. A prior for set-ups that start the drone facing the goal (the
            random layouts start it within 25 deg of the goal's bearing; the
            thesis and a Tello flight start it facing the board), so that a goal
            hidden behind the first obstacle is searched for ahead rather than
            anywhere (docs/results.rst, "Searching for a hidden goal").
        depth: ``"exact"`` (default: the simulator's depth; nearest in-band
            pixel per column, cells stay as first seen) or ``"estimated"``
            (a depth estimate such as MonoDepth's: the median in-band pixel,
            log-odds cells that later views can overturn; see the module
            docstring and docs/tello.rst, "A map for estimated depth").
        scan_quantile: which in-band depth of a column is its obstacle point,
            as a quantile in [0, 1) (0: the nearest; default 0 for
            ``"exact"``, :data:`ESTIMATED_SCAN_QUANTILE` for ``"estimated"``).
        log_odds: ``(hit, pass, clamp)``, all > 0: what a cell's log-odds
            gains when a reading ends in it, loses when a ray passes it, and
            its bound (``"estimated"`` only; default
            :data:`OCTOMAP_LOG_ODDS`). A cell is an obstacle while its
            log-odds is above 0 and seen free while below 0.
        fresh_hits: ``"estimated"`` only: a cell in which a reading of the
            current frame ends is an obstacle for this step whatever its
            log-odds (default False: the log-odds alone decide). Earlier views
            can have driven a cell's log-odds far below 0 (a reading that fell
            behind the surface, or a pose that drifted), and then the obstacle
            seen now takes several frames to flip back; with this option the
            map holds at least what the drone sees now, as the exact map does,
            and a phantom read in one frame masks moves for that step only
            (docs/tello.rst, "What the drone sees now").

    Example:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl_causal.envs import DroneNavEnv
        >>> env = TransformedEnv(DroneNavEnv(seed=0), EgoMap())
        >>> td = env.reset()
        >>> td["ego_map"].shape, td["goal_memory"][0].item()  # the goal is in view
        (torch.Size([3, 32, 32]), 1.0)
        >>> td = env.step(td.set("action", torch.tensor(6)))["next"]  # turn left 15 deg
        >>> bool(td["ego_map"][0].any())  # the pillar ahead is on the map
        True
    """

    def __init__(self, size: int = 32, resolution: float = 0.15, *, world_size: float = 20.0,
                 max_range: float = 4.0, band: float = 0.2, step_size: float | None = None,
                 turn_deg: float | None = None, fov_deg: float | None = None,
                 min_clearance: float = 0.2, n_actions: int = 8, action_key="action",
                 geofence=None, geofence_margin: float = 0.1, flank_margin: float = 0.0,
                 goal_prior: float | None = None, depth: str = "exact",
                 scan_quantile: float | None = None, log_odds=None, fresh_hits: bool = False):
        if depth not in DEPTH_MODELS:
            raise ValueError(f"EgoMap depth must be one of {DEPTH_MODELS}, got {depth!r}")
        if scan_quantile is None:
            scan_quantile = 0.0 if depth == "exact" else ESTIMATED_SCAN_QUANTILE
        if isinstance(scan_quantile, bool) or not isinstance(scan_quantile, (int, float)) \
                or not 0.0 <= scan_quantile < 1.0:
            raise ValueError(f"EgoMap scan_quantile must be a number in [0, 1), got "
                             f"{scan_quantile!r}")
        if log_odds is not None and depth != "estimated":
            raise ValueError(f"EgoMap log_odds applies to depth='estimated', got depth={depth!r}")
        if log_odds is None:
            log_odds = OCTOMAP_LOG_ODDS
        if not isinstance(fresh_hits, bool):
            raise ValueError(f"EgoMap fresh_hits must be True or False, got {fresh_hits!r}")
        if fresh_hits and depth != "estimated":
            raise ValueError(f"EgoMap fresh_hits applies to depth='estimated', got depth={depth!r}")
        ok = isinstance(log_odds, (tuple, list)) and len(log_odds) == 3 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
            for v in log_odds)
        if not ok:
            raise ValueError(f"EgoMap log_odds must be (hit, pass, clamp), three numbers > 0, "
                             f"got {log_odds!r}")
        if isinstance(size, bool) or not isinstance(size, int) or size < 8:
            raise ValueError(f"EgoMap size must be an int >= 8, got {size!r}")
        _number("resolution", resolution)
        _number("world_size", world_size)
        _number("max_range", max_range)
        _number("band", band)
        _number("min_clearance", min_clearance, strict=False)
        for name, val in (("step_size", step_size), ("turn_deg", turn_deg)):
            if val is not None:
                _number(name, val)
        if fov_deg is not None and not (isinstance(fov_deg, (int, float)) and 0 < fov_deg < 180):
            raise ValueError(f"EgoMap fov_deg must be in (0, 180), got {fov_deg!r}")
        if geofence is not None and geofence != "env":
            ok = isinstance(geofence, (tuple, list)) and len(geofence) == 4 and all(
                isinstance(v, (int, float)) and math.isfinite(v) for v in geofence)
            if not ok or not (geofence[0] < 0 < geofence[2] and geofence[1] < 0 < geofence[3]):
                raise ValueError(f"EgoMap geofence must be None, 'env' or (x_min, y_min, x_max, "
                                 f"y_max) around the start (x_min < 0 < x_max, y_min < 0 < "
                                 f"y_max), got {geofence!r}")
        _number("geofence_margin", geofence_margin, strict=False)
        _number("flank_margin", flank_margin, strict=False)
        if goal_prior is not None:
            _number("goal_prior", goal_prior)
            if goal_prior > max(world_size / 2 - 1.0, 0.0):
                raise ValueError(f"EgoMap goal_prior must lie inside the map (< world_size / 2 "
                                 f"- 1 = {world_size / 2 - 1:g} m), got {goal_prior!r}")
        if world_size < size * resolution:
            raise ValueError(f"EgoMap world_size ({world_size!r} m) must cover the window "
                             f"(size * resolution = {size * resolution:g} m)")
        super().__init__(in_keys=["depth", "goal_in_sight", "goal_distance", "goal_angle"],
                         out_keys=["ego_map", "goal_memory", "map_clearance", "action_mask",
                                   "ego_pose", "goal_seen"])
        self.size = int(size)
        self.resolution = float(resolution)
        self.cells = int(math.ceil(world_size / resolution))
        self.max_range = float(max_range)
        self.band = float(band)
        self._options = {"step_size": step_size, "turn_deg": turn_deg, "fov_deg": fov_deg}
        self.min_clearance = float(min_clearance)
        self.n_actions = int(n_actions)
        self.action_key = action_key
        self.geofence = tuple(float(v) for v in geofence) if isinstance(geofence, (tuple, list)) \
            else geofence
        self.geofence_margin = float(geofence_margin)
        self.flank_margin = float(flank_margin)
        self.goal_prior = None if goal_prior is None else float(goal_prior)
        self.depth = depth
        self.scan_quantile = float(scan_quantile)
        self.log_odds = tuple(float(v) for v in log_odds)
        self.fresh_hits = fresh_hits
        self._state = None  # per flattened batch entry: pose, maps, goal

    # ----------------------------------------------------------- geometry
    def _setting(self, name, default):
        val = self._options[name]
        if val is not None:
            return float(val)
        parent = self.parent
        base = getattr(parent, "base_env", None) if parent is not None else None
        for obj in (base, getattr(base, "base_env", None)):
            v = getattr(obj, name, None) if obj is not None else None
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                return float(v)
        return float(default)

    def _deltas(self, device):
        s = self._setting("step_size", 0.25)
        t = math.radians(self._setting("turn_deg", 15.0))
        # (forward, left, yaw) per action, in ACTION_NAMES order; ascend/descend move no cell
        table = [(s, 0, 0), (-s, 0, 0), (0, s, 0), (0, -s, 0), (0, 0, 0), (0, 0, 0), (0, 0, t),
                 (0, 0, -t)]
        return torch.tensor(table[: self.n_actions], dtype=torch.float32, device=device)

    def _fresh(self, n, device):
        lo = self.cells if self.depth == "estimated" else 0  # no log-odds grid on an exact map
        return {
            "pose": torch.zeros(n, 3, device=device),  # x, y, yaw in the start frame
            "occ": torch.zeros(n, self.cells, self.cells, dtype=torch.bool, device=device),
            "free": torch.zeros(n, self.cells, self.cells, dtype=torch.bool, device=device),
            # depth="estimated": each cell's log-odds of being occupied (occ / free: > 0 / < 0)
            "logodds": torch.zeros(n, lo, lo, device=device),
            "goal": torch.zeros(n, 3, device=device),  # x, y, z-above-start-camera
            "known": torch.zeros(n, dtype=torch.bool, device=device),
            "seen": torch.zeros(n, dtype=torch.bool, device=device),  # known, not a guess
            "since": torch.zeros(n, device=device),
            "alt0": torch.zeros(n, device=device),
            # the fence: its frame's origin and heading in the start frame, its rectangle
            # in that frame, its ceiling (inf: none)
            "fence": self._fence(n, device),
        }

    def _fence(self, n, device):
        """Per entry ``(x0, y0, yaw0, x_min, y_min, x_max, y_max, ceiling)``: a point ``p``
        of the start frame lies inside when ``R(yaw0) p + (x0, y0)`` is in the rectangle."""
        inf = math.inf
        out = torch.tensor([0.0, 0.0, 0.0, -inf, -inf, inf, inf, inf],
                           device=device).repeat(n, 1)
        if self.geofence is None:
            return out
        if self.geofence != "env":
            out[:, 3:7] = torch.tensor(self.geofence, device=device)
            return out
        parent = self.parent
        base = getattr(parent, "base_env", None) if parent is not None else None
        layout = getattr(base, "layout", None)
        if layout is None and hasattr(base, "geofence") and hasattr(base, "max_height"):
            # a TelloEnv: its own geofence (None: none), in its frame, with the take-off
            # pose in that frame (geofence_origin), and its height limit
            if base.geofence is not None:
                ox, oy, oyaw = getattr(base, "geofence_origin", (0.0, 0.0, 0.0))
                out[:, 0:3] = torch.tensor([ox, oy, math.radians(oyaw)], device=device)
                out[:, 3:7] = torch.tensor(tuple(base.geofence), device=device)
            out[:, 7] = float(base.max_height)
            return out
        if layout is None or n != 1:
            raise ValueError("EgoMap geofence='env' reads the arena of one DroneNavEnv (or the "
                             "geofence of a TelloEnv) under it, not a batched env; give "
                             "(x_min, y_min, x_max, y_max) instead")
        arena, (x0, y0, yaw0), ceiling = layout.fence()
        out[0] = torch.tensor([x0, y0, math.radians(yaw0), *arena, ceiling], device=device)
        return out

    def _fence_mask(self, st, idx, altitude):
        """``[n, n_actions]``: False where a move ends outside the fence (or above its ceiling)."""
        n = idx.numel()
        device = st["pose"].device
        mask = torch.ones(n, self.n_actions, dtype=torch.bool, device=device)
        if self.geofence is None:
            return mask
        f, pose = st["fence"][idx], st["pose"][idx]
        d = self._deltas(device)[:4]  # forward, backward, left, right
        c, s = pose[:, 2].cos(), pose[:, 2].sin()
        px = pose[:, 0, None] + c[:, None] * d[None, :, 0] - s[:, None] * d[None, :, 1]
        py = pose[:, 1, None] + s[:, None] * d[None, :, 0] + c[:, None] * d[None, :, 1]
        fc, fs = f[:, 2].cos()[:, None], f[:, 2].sin()[:, None]
        wx = f[:, 0, None] + fc * px - fs * py
        wy = f[:, 1, None] + fs * px + fc * py
        m = self.geofence_margin
        mask[:, :4] = ((wx >= f[:, 3, None] + m) & (wx <= f[:, 5, None] - m)
                       & (wy >= f[:, 4, None] + m) & (wy <= f[:, 6, None] - m))
        if self.n_actions > 4:  # ascend: not through the ceiling
            mask[:, 4] = altitude + self._setting("step_size", 0.25) <= f[:, 7] - m
        return mask

    # ------------------------------------------------------------ updates
    def _scan(self, depth):
        """Per image column: the nearest in-band depth (m; inf if none) and its bearing (rad)."""
        n, h, w = depth.shape
        f = (h / 2.0) / math.tan(math.radians(self._setting("fov_deg", 60.0)) / 2.0)
        v = torch.arange(h, device=depth.device, dtype=torch.float32) + 0.5
        u = torch.arange(w, device=depth.device, dtype=torch.float32) + 0.5
        up = (h / 2.0 - v)[None, :, None] / f * depth  # height of each pixel above the camera
        valid = (up.abs() <= self.band) & (depth > 0) & (depth < self.max_range)
        if self.scan_quantile > 0:  # a robust statistic of the column's in-band readings
            z = torch.nanquantile(torch.where(valid, depth, torch.full_like(depth, math.nan)),
                                  self.scan_quantile, dim=1)
            z = torch.nan_to_num(z, nan=math.inf)
        else:
            z = torch.where(valid, depth, torch.full_like(depth, math.inf)).amin(1)  # [n, w]
        tan_left = (w / 2.0 - u) / f  # [w]
        return z, tan_left

    def _write(self, st, idx, depth):
        if self.depth == "estimated":
            # this frame's hits and passes, then the log-odds update (a cell hit in this
            # frame is not also passed by a neighbouring column's ray)
            n = idx.numel()
            ar = torch.arange(n, device=idx.device)
            frame = {"pose": st["pose"][idx],
                     "occ": torch.zeros(n, self.cells, self.cells, dtype=torch.bool,
                                        device=idx.device)}
            frame["free"] = torch.zeros_like(frame["occ"])
            self._write_sticky(frame, ar, depth)
            hit, passed = frame["occ"], frame["free"] & ~frame["occ"]
            l_hit, l_pass, l_max = self.log_odds
            lo = (st["logodds"][idx] + l_hit * hit.float() - l_pass * passed.float()
                  ).clamp(-l_max, l_max)
            st["logodds"][idx] = lo
            st["occ"][idx] = (lo > 0) | hit if self.fresh_hits else lo > 0
            st["free"][idx] = (lo < 0) & ~st["occ"][idx]
            return
        self._write_sticky(st, idx, depth)

    def _write_sticky(self, st, idx, depth):
        z, tan_left = self._scan(depth)
        pose = st["pose"][idx]
        n, w = z.shape
        c, s = pose[:, 2].cos()[:, None, None], pose[:, 2].sin()[:, None, None]
        # free space: samples along each column's ray up to the hit (or max_range)
        reach = torch.where(torch.isfinite(z), z, torch.full_like(z, self.max_range))
        k = int(math.ceil(self.max_range / (self.resolution / 2)))
        t = torch.linspace(0.0, 1.0, k + 1, device=z.device)[:-1]  # [k]
        fwd = reach[:, :, None] * t[None, None, :] - self.resolution / 2  # stop short of the hit
        fwd = fwd.clamp(min=0.0)
        left = fwd * tan_left[None, :, None]
        self._mark(st["free"], idx, pose, fwd, left, c, s)
        hit = torch.isfinite(z)
        fwd_h = torch.where(hit, z, torch.zeros_like(z))[:, :, None]
        left_h = fwd_h * tan_left[None, :, None]
        self._mark(st["occ"], idx, pose, fwd_h, left_h, c, s, keep=hit[:, :, None])

    def _mark(self, grid, idx, pose, fwd, left, c, s, keep=None):
        x = pose[:, 0, None, None] + c * fwd - s * left
        y = pose[:, 1, None, None] + s * fwd + c * left
        half = self.cells / 2.0
        i = torch.floor(x / self.resolution + half).long()  # row: +x of the start frame
        j = torch.floor(y / self.resolution + half).long()  # column: +y
        ok = (i >= 0) & (i < self.cells) & (j >= 0) & (j < self.cells)
        if keep is not None:
            ok = ok & keep
        b = idx[:, None, None].expand_as(i)
        grid[b[ok], i[ok], j[ok]] = True

    def _update_goal(self, st, idx, sight, dist, angle, box, altitude, hw):
        h, w = hw
        if not sight.any():
            return
        f = (h / 2.0) / math.tan(math.radians(self._setting("fov_deg", 60.0)) / 2.0)
        tan_a = torch.tan(torch.deg2rad(angle))
        if box is not None:
            v = (box[:, 1] + box[:, 3]) / 2.0
            tan_e = (h / 2.0 - v) / f
        else:
            tan_e = torch.zeros_like(tan_a)
        fwd = dist / torch.sqrt(1.0 + tan_a ** 2 + tan_e ** 2)
        left, up = fwd * tan_a, fwd * tan_e
        pose = st["pose"][idx]
        c, s = pose[:, 2].cos(), pose[:, 2].sin()
        gx = pose[:, 0] + c * fwd - s * left
        gy = pose[:, 1] + s * fwd + c * left
        gz = altitude - st["alt0"][idx] + up
        new = torch.stack([gx, gy, gz], -1)
        if box is not None:
            # a box cut by the image border (the board overflows the view when close)
            # biases the centre's bearing / elevation: keep the remembered value
            known = st["known"][idx]
            cut_h = known & ((box[:, 0] <= 0.5) | (box[:, 2] >= w - 0.5))
            cut_v = known & ((box[:, 1] <= 0.5) | (box[:, 3] >= h - 0.5))
            old = st["goal"][idx]
            new[:, :2] = torch.where(cut_h[:, None], old[:, :2], new[:, :2])
            new[:, 2] = torch.where(cut_v, old[:, 2], new[:, 2])
        sel = idx[sight]
        st["goal"][sel] = new[sight]
        st["known"][sel] = True
        st["seen"][sel] = True
        st["since"][sel] = 0.0

    # ------------------------------------------------------------ outputs
    def _outputs(self, st, idx, altitude):
        pose = st["pose"][idx]
        n = idx.numel()
        world = torch.stack([st["occ"][idx], st["free"][idx]], 1).float()  # [n, 2, C, C]
        known = st["known"][idx]
        # egocentric window: output row r is ahead of the drone, column q to its left
        c, s = pose[:, 2].cos(), pose[:, 2].sin()
        span = self.size * self.resolution
        extent = self.cells * self.resolution
        lin = (torch.arange(self.size, device=world.device, dtype=torch.float32) + 0.5) / self.size
        ahead = (0.5 - lin) * span  # row 0 ahead
        leftw = (0.5 - lin) * span  # column 0 to the left
        a, l_ = ahead[:, None], leftw[None, :]
        wx = pose[:, 0, None, None] + c[:, None, None] * a - s[:, None, None] * l_
        wy = pose[:, 1, None, None] + s[:, None, None] * a + c[:, None, None] * l_
        # grid_sample: x indexes the last dim (world y), y the rows (world x), in [-1, 1]
        grid = torch.stack([wy / (extent / 2), wx / (extent / 2)], -1)
        ego = F.grid_sample(world, grid, mode="nearest", padding_mode="zeros", align_corners=False)
        # goal vector in the drone frame
        g = st["goal"][idx]
        dx, dy = g[:, 0] - pose[:, 0], g[:, 1] - pose[:, 1]
        fwd = c * dx + s * dy
        left = -s * dx + c * dy
        # goal channel: a 3x3 mark at the goal, or where its direction leaves the window
        reach = torch.maximum(fwd.abs(), left.abs()).clamp(min=1e-6)
        shrink = torch.clamp((0.5 * span - 1.5 * self.resolution) / reach, max=1.0)
        row = torch.floor((0.5 - fwd * shrink / span) * self.size).long()
        col = torch.floor((0.5 - left * shrink / span) * self.size).long()
        goal = torch.zeros(n, 1, self.size, self.size, device=ego.device)
        rows = torch.arange(n, device=ego.device)[known]
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                goal[rows, 0, (row[known] + di).clamp(0, self.size - 1),
                     (col[known] + dj).clamp(0, self.size - 1)] = 1.0
        ego = (torch.cat([ego, goal], 1) > 0.5).to(torch.uint8) * 255
        up = g[:, 2] - (altitude - st["alt0"][idx])
        k = known.float()
        vec = torch.stack([k, k * fwd / 5.0, k * left / 5.0, k * up,
                           k * torch.sqrt(fwd ** 2 + left ** 2) / 5.0,
                           (st["since"][idx] / 50.0).clamp(max=1.0)], -1)
        return ego, vec, self._clearance(st, idx)

    def _clearance(self, st, idx):
        """Free distance (m / 2, capped at 1) the drone's hull can move ahead, back, left, right."""
        out = torch.ones(idx.numel(), 4, device=st["pose"].device)
        half = self.cells / 2.0
        width = DRONE_HALF_WIDTH + self.resolution / 2
        for row, b in enumerate(idx.tolist()):
            cells = st["occ"][b].nonzero()
            if not len(cells):
                continue
            xy = (cells.float() - half + 0.5) * self.resolution
            x, y, yaw = st["pose"][b]
            dx, dy = xy[:, 0] - x, xy[:, 1] - y
            fwd = yaw.cos() * dx + yaw.sin() * dy
            left = -yaw.sin() * dx + yaw.cos() * dy
            for k, (along, across) in enumerate(((fwd, left), (-fwd, left), (left, fwd),
                                                 (-left, fwd))):
                if k < 2:
                    band = across.abs() <= width
                else:  # a sideways move: the hull's length and flank_margin behind it
                    band = (across <= width) & (across >= -width - self.flank_margin)
                hit = (along > 0) & band
                if hit.any():
                    gap = along[hit].min() - self.resolution / 2 - DRONE_HALF_WIDTH
                    out[row, k] = (gap.clamp(min=0.0) / 2.0).clamp(max=1.0)
        return out

    def _observe(self, td, idx, st, fresh=None):
        depth = td.get("depth")
        batch = td.batch_size
        depth = depth.reshape(-1, *depth.shape[len(batch):])[idx].float()
        hw = tuple(depth.shape[-2:])

        def flat(key):
            val = td.get(key, None)
            if val is None:
                return None
            return val.reshape(val.shape[: len(batch)].numel(), -1)[idx]

        altitude = flat("altitude")
        altitude = altitude[:, 0].float() if altitude is not None else torch.zeros(idx.numel())
        self._write(st, idx, depth)
        sight = flat("goal_in_sight")[:, 0].bool()
        dist = torch.nan_to_num(flat("goal_distance")[:, 0].float(), nan=0.0)
        angle = flat("goal_angle")[:, 0].float()
        box = flat("goal_box")
        self._update_goal(st, idx, sight, dist, angle, None if box is None else box.float(),
                          altitude, hw)
        if fresh is not None and self.goal_prior is not None:
            # just reset and the goal not in view: the guess straight ahead (see goal_prior)
            guess = fresh[~st["known"][fresh]]
            st["goal"][guess] = torch.tensor([self.goal_prior, 0.0, 0.0], device=st["goal"].device)
            st["known"][guess] = True
            st["since"][guess] = 50.0
        ego, vec, clear = self._outputs(st, idx, altitude)
        mask = torch.ones(idx.numel(), self.n_actions, dtype=torch.bool, device=clear.device)
        mask[:, :4] = 2.0 * clear >= self.min_clearance  # forward, backward, left, right
        if self.n_actions > 5 and self.min_clearance > 0:  # descend: not into the floor
            mask[:, 5] = altitude - self._setting("step_size", 0.25) >= FLOOR_MARGIN
        mask &= self._fence_mask(st, idx, altitude)
        return ego, vec, clear, mask, st["pose"][idx].clone(), st["seen"][idx, None].clone()

    def _set(self, td, ego, vec, clear, mask, pose, seen):
        batch = td.batch_size
        td.set("ego_pose", pose.reshape(*batch, 3).to(td.device or pose.device))
        td.set("goal_seen", seen.reshape(*batch, 1).to(td.device or seen.device))
        td.set("map_clearance", clear.reshape(*batch, 4).to(td.device or clear.device))
        td.set("action_mask", mask.reshape(*batch, self.n_actions).to(td.device or mask.device))
        td.set("ego_map", ego.reshape(*batch, *ego.shape[1:]).to(td.device or ego.device))
        td.set("goal_memory", vec.reshape(*batch, 6).to(td.device or vec.device))
        return td

    # -------------------------------------------------------- Transform API
    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
               ) -> TensorDictBase:
        batch = tensordict_reset.batch_size
        n = max(1, batch.numel())
        device = tensordict_reset.get("depth").device
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        if self._state is None or self._state["pose"].shape[0] != n:
            self._state = self._fresh(n, device)
            mask = None
        idx = torch.arange(n, device=device)
        if mask is not None and mask.numel() == n:
            sel = idx[mask.reshape(-1).to(device)]
            fresh = self._fresh(sel.numel(), device)
            for key, val in fresh.items():
                self._state[key][sel] = val
        else:
            self._state = self._fresh(n, device)
            sel = idx
        alt = tensordict_reset.get("altitude", None)
        if alt is not None:
            alt = alt.reshape(n, -1)[:, 0].float()
            if mask is not None and mask.numel() == n:
                m = mask.reshape(-1).to(device)
                self._state["alt0"][m] = alt[m]
            else:
                self._state["alt0"] = alt.clone()
        return self._set(tensordict_reset,
                         *self._observe(tensordict_reset, idx, self._state, fresh=sel))

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        batch = next_tensordict.batch_size
        n = max(1, batch.numel())
        device = next_tensordict.get("depth").device
        if self._state is None or self._state["pose"].shape[0] != n:
            raise RuntimeError("EgoMap: step before reset (call env.reset() first)")
        action = tensordict.get(self.action_key)
        if action.shape[len(batch):] == (self.n_actions,):  # one-hot action spec
            action = action.argmax(-1)
        action = action.reshape(n).long().to(device)
        d = self._deltas(device)[action]
        pose = self._state["pose"]
        c, s = pose[:, 2].cos(), pose[:, 2].sin()
        pose[:, 0] += c * d[:, 0] - s * d[:, 1]
        pose[:, 1] += s * d[:, 0] + c * d[:, 1]
        pose[:, 2] = torch.remainder(pose[:, 2] + d[:, 2] + math.pi, 2 * math.pi) - math.pi
        self._state["since"] += 1
        idx = torch.arange(n, device=device)
        return self._set(next_tensordict, *self._observe(next_tensordict, idx, self._state))

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict

    def transform_observation_spec(self, observation_spec):
        shape = observation_spec.shape
        observation_spec["ego_map"] = Bounded(0, 255, shape=(*shape, 3, self.size, self.size),
                                              dtype=torch.uint8, device=observation_spec.device)
        observation_spec["goal_memory"] = Bounded(-10.0, 10.0, shape=(*shape, 6),
                                                  dtype=torch.float32,
                                                  device=observation_spec.device)
        observation_spec["action_mask"] = Binary(n=self.n_actions,
                                                 shape=(*shape, self.n_actions),
                                                 dtype=torch.bool,
                                                 device=observation_spec.device)
        observation_spec["map_clearance"] = Bounded(0.0, 1.0, shape=(*shape, 4),
                                                    dtype=torch.float32,
                                                    device=observation_spec.device)
        observation_spec["ego_pose"] = Unbounded(shape=(*shape, 3), dtype=torch.float32,
                                                 device=observation_spec.device)
        observation_spec["goal_seen"] = Binary(n=1, shape=(*shape, 1), dtype=torch.bool,
                                               device=observation_spec.device)
        return observation_spec
