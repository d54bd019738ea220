"""Minimum depth in the five image sections of thesis Fig. 4.2.

Section geometry (``center_frac = 0.5``, the default)::

        0        W/4        W/2        3W/4        W
      0 +----------+----------+----------+----------+
        |                     |                     |
        |   2: top-left       |   3: top-right      |
    H/4 +          +----------+----------+          +
        |          |                     |          |
        |          |      1: center      |          |
    H/2 +----------+                     +----------+
        |          |                     |          |
        |          |                     |          |
   3H/4 +          +----------+----------+          +
        |   4: bottom-left    |   5: bottom-right   |
        |                     |                     |
      H +----------+----------+----------+----------+

The centre section is the central box of ``center_frac * H`` by
``center_frac * W`` pixels; each corner section is the image quadrant minus
the centre box (an L shape). The five sections are disjoint and cover the
whole image, so every obstacle in view falls into exactly one section.

Invalid depth rule: a reading that is NaN, ``-inf`` or ``<= 0`` carries no
information and is ignored; a reading that is ``+inf`` or beyond ``max_depth``
means "nothing within range" and is clipped to ``max_depth``. A section without
any valid sampled reading reports ``invalid_value`` (default ``max_depth``).
The output is therefore always finite and in ``[0, max_depth]``.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Composite
from torchrl.envs.transforms import Transform

__all__ = ["DepthSections", "SECTION_NAMES", "section_masks"]

#: Section names, in the order of the last dim of ``depth_sections`` (thesis Fig. 4.2 order).
SECTION_NAMES: tuple[str, ...] = (
    "depth_center",
    "depth_top_left",
    "depth_top_right",
    "depth_bottom_left",
    "depth_bottom_right",
)


def section_masks(
    height: int, width: int, center_frac: float = 0.5, device=None
) -> torch.Tensor:
    """Boolean masks ``[5, height, width]`` of the five sections (see module docs).

    Args:
        height: image height in pixels.
        width: image width in pixels.
        center_frac: side of the centre box as a fraction of the image side.
        device: device of the returned tensor.

    Example:
        >>> m = section_masks(84, 84)
        >>> m.shape, int(m.sum()), bool((m.sum(0) == 1).all())
        (torch.Size([5, 84, 84]), 7056, True)
        >>> m[0].nonzero().min(0).values.tolist(), m[0].nonzero().max(0).values.tolist()
        ([21, 21], [62, 62])
    """
    if height < 2 or width < 2:
        raise ValueError(f"image must be at least 2x2 pixels, got height={height}, width={width}")
    if not 0.0 < center_frac < 1.0:
        raise ValueError(f"center_frac must be in (0, 1), got {center_frac!r}")
    ch = max(1, int(round(center_frac * height)))
    cw = max(1, int(round(center_frac * width)))
    y0 = (height - ch) // 2
    x0 = (width - cw) // 2
    ys = torch.arange(height, device=device).view(height, 1)
    xs = torch.arange(width, device=device).view(1, width)
    center = (ys >= y0) & (ys < y0 + ch) & (xs >= x0) & (xs < x0 + cw)
    top = ys < height // 2
    left = xs < width // 2
    rest = ~center
    return torch.stack(
        [
            center,
            rest & top & left,
            rest & top & ~left,
            rest & ~top & left,
            rest & ~top & ~left,
        ]
    )


class DepthSections(Transform):
    """Minimum depth of the five image sections of thesis Fig. 4.2.

    Reads a metric depth map ``[..., H, W]`` and writes ``float32 [..., 5]``
    (order: centre, top-left, top-right, bottom-left, bottom-right; see
    :data:`SECTION_NAMES` and the module docs for the geometry). Per frame and
    section the value is the minimum over ``n_points`` pixels drawn uniformly
    at random from the section (thesis: at least 20), or the exact section
    minimum with ``exact=True``. Invalid readings follow the module's invalid
    depth rule, so the output never holds NaN or inf.

    The random pixels come from the transform's own :class:`torch.Generator`,
    seeded with ``seed``; give each env of a batched env its own seed
    (e.g. ``seed=base_seed + worker_index``) or call :meth:`set_seed`.
    Sampling is fully vectorised: index tables are precomputed once per image
    size, pixel indices are drawn in blocks of at least 256 frames (one
    ``rand``), and each call costs one ``gather`` over its batch.

    Args:
        n_points: random pixels per section and frame (>= 20). Ignored when
            ``exact`` is True.
        exact: use the exact section minimum instead of random points.
        max_depth: sensor range in metres; readings beyond are clipped.
        invalid_value: value of a section without any valid reading
            (default: ``max_depth``, i.e. "nothing seen").
        center_frac: side of the centre section as a fraction of the image.
        seed: seed of the sampling generator (None: drawn from torch's global RNG).
        in_key: depth key.
        out_key: output key.
        device: device of the index tables and generator (default: CPU).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> t = DepthSections(n_points=20, seed=0)
        >>> depth = torch.full((84, 84), 3.0)
        >>> depth[30:50, 30:50] = 0.4          # something close in the centre
        >>> depth[0, 0] = float("nan")         # an invalid reading
        >>> out = t(TensorDict({"depth": depth}, []))
        >>> out["depth_sections"].shape
        torch.Size([5])
        >>> DepthSections(exact=True)(TensorDict({"depth": depth}, []))["depth_sections"].tolist()
        [0.4000000059604645, 3.0, 3.0, 3.0, 3.0]
    """

    def __init__(
        self,
        n_points: int = 20,
        *,
        exact: bool = False,
        max_depth: float = 10.0,
        invalid_value: float | None = None,
        center_frac: float = 0.5,
        seed: int | None = None,
        in_key="depth",
        out_key="depth_sections",
        device=None,
    ):
        if isinstance(n_points, bool) or not isinstance(n_points, int) or n_points < 20:
            raise ValueError(f"n_points must be an int >= 20 (thesis sec. 4.2), got {n_points!r}")
        if not (math.isfinite(max_depth) and max_depth > 0):
            raise ValueError(f"max_depth must be a positive finite number, got {max_depth!r}")
        if invalid_value is None:
            invalid_value = max_depth
        if not (math.isfinite(invalid_value) and 0.0 <= invalid_value <= max_depth):
            raise ValueError(
                f"invalid_value must be in [0, max_depth={max_depth}], got {invalid_value!r}"
            )
        if not 0.0 < center_frac < 1.0:
            raise ValueError(f"center_frac must be in (0, 1), got {center_frac!r}")
        super().__init__(in_keys=[in_key], out_keys=[out_key])
        self.n_points = n_points
        self.exact = bool(exact)
        self.max_depth = float(max_depth)
        self.invalid_value = float(invalid_value)
        self.center_frac = float(center_frac)
        self._device = torch.device("cpu") if device is None else torch.device(device)
        self._cache: dict = {}
        self.generator = torch.Generator(device=self._device)
        self.set_seed(seed)

    _BLOCK = 256

    def set_seed(self, seed: int | None) -> int:
        """(Re)seeds the pixel sampler (dropping pre-drawn pixels); returns the seed used."""
        if seed is None:
            seed = int(torch.randint(0, 2**62, ()).item())
        self.seed = int(seed)
        self.generator.manual_seed(self.seed)
        for tab in self._cache.values():
            tab.pop("pool", None)
            tab.pop("pos", None)
        return self.seed

    def _tables(self, H: int, W: int, device):
        key = (H, W, device)
        tab = self._cache.get(key)
        if tab is None:
            masks = section_masks(H, W, self.center_frac, device=device)
            flat = [m.reshape(-1).nonzero().squeeze(-1) for m in masks]
            sizes = torch.tensor([len(f) for f in flat], device=device)
            if (sizes == 0).any():
                raise ValueError(
                    f"image {H}x{W} too small for five non-empty sections "
                    f"(center_frac={self.center_frac})"
                )
            offsets = torch.cumsum(sizes, 0) - sizes
            tab = {
                "masks": masks,
                "flat": torch.cat(flat),
                "sizes": sizes.to(torch.float32).view(5, 1),
                "offsets": offsets.view(5, 1),
                "last": (offsets + sizes - 1).view(5, 1),
                "inf": torch.tensor(float("inf"), device=device),
            }
            self._cache[key] = tab
        return tab

    def _draw(self, B: int, tab) -> torch.Tensor:
        """Flat pixel indices ``[B, 5 * n_points]`` for the next ``B`` frames.

        Indices are drawn in blocks of ``_BLOCK`` frames (one vectorised draw per
        block) and consumed frame by frame, so the stream of sampled pixels
        depends only on the seed, not on how frames are batched.
        """
        pool, pos = tab.get("pool"), tab.get("pos", 0)
        if pool is not None and pos + B <= pool.shape[0]:  # fast path
            tab["pos"] = pos + B
            return pool[pos : pos + B]
        parts, need = [], B
        while need > 0:
            pool = tab.get("pool")
            pos = tab.get("pos", 0)
            if pool is None or pos >= pool.shape[0]:
                n = max(self._BLOCK, need)
                u = torch.rand(
                    (n, 5, self.n_points), generator=self.generator, device=self.generator.device
                ).to(tab["flat"].device)
                idx = torch.minimum((u * tab["sizes"]).long() + tab["offsets"], tab["last"])
                pool, pos = tab["flat"][idx].view(n, 5 * self.n_points), 0
                tab["pool"] = pool
            take = min(need, pool.shape[0] - pos)
            parts.append(pool[pos : pos + take])
            tab["pos"] = pos + take
            need -= take
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    def sections(self, depth: torch.Tensor) -> torch.Tensor:
        """Section minima of a depth tensor ``[..., H, W]`` -> ``[..., 5]``."""
        H, W = depth.shape[-2], depth.shape[-1]
        batch = depth.shape[:-2]
        depth = depth.reshape(-1, H * W)
        if depth.dtype != torch.float32:
            depth = depth.to(torch.float32)
        tab = self._tables(H, W, depth.device)
        B = depth.shape[0]
        if self.exact:
            vals = depth.unsqueeze(1)
            ok = (vals > 0) & tab["masks"].reshape(1, 5, H * W)
        else:
            idx = self._draw(B, tab)
            vals = depth.gather(1, idx).view(B, 5, self.n_points)
            ok = vals > 0  # False for NaN and <= 0 (incl. -inf)
        # invalid rule: NaN, -inf, <= 0 ignored; +inf and beyond range -> max_depth
        if self.invalid_value == self.max_depth:
            # no valid reading -> inf -> max_depth; min-then-clip == clip-then-min
            out = torch.where(ok, vals, tab["inf"]).amin(-1).clamp(max=self.max_depth)
        else:
            vals = torch.where(ok, vals.clamp(max=self.max_depth), tab["inf"]).amin(-1)
            out = torch.where(vals == float("inf"), self.invalid_value, vals)
        return out.reshape(*batch, 5)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        depth = next_tensordict.get(self.in_keys[0])
        next_tensordict.set(self.out_keys[0], self.sections(depth))
        return next_tensordict

    forward = _call

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase):
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        in_spec = observation_spec[self.in_keys[0]]
        observation_spec[self.out_keys[0]] = Bounded(
            low=0.0,
            high=self.max_depth,
            shape=(*observation_spec.shape, 5),
            dtype=torch.float32,
            device=in_spec.device,
        )
        return observation_spec
