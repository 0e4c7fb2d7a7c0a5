"""Stage 0: ray grids. A camera's rays (unit directions in the camera frame) grouped into tiles, the
camera sub-frusta (CSFs) of paper Sec. 3.2, each with the angular bounds of its own rays.

Two constructors: `RayGrid.beap` samples rays uniformly in (theta, phi) = (atan(x/z), atan(y/z))
(paper Eq. 6 and 11), so image tiles and CSFs share one parameterization; `RayGrid.from_rays` takes
any camera model's per-pixel rays (fisheye, pinhole, equirectangular, ...). Both derive the tile
bounds from the tile's rays themselves, so the bounds are exact for the rays that are rendered.
Invalid rays (outside a fisheye circle, masked) are skipped; a tile without a valid ray is inactive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from .pbf import mirror_tangent

# Angular slack on tile bounds (radians): far below a pixel, far above atan2's rounding.
_TILE_BOUND_SLACK = 1e-6
# Rays this close to the axis of a bounding plane family have an undefined angle in that plane.
_AXIAL_EPS = 1e-7
# Extra slack (radians) of each ray's own bounds for the kernels' per-ray PBF cull: far above the PBF's
# float32 rounding, so the cull only skips pairs whose alpha is below 1/255 anyway (a pixel spans > 1e-3).
_RAY_CULL_SLACK = 1e-4


@dataclass
class RayGrid:
    dirs: Tensor  # [H*W, 3] unit directions, camera frame (OpenCV)
    valid: Tensor  # [H*W] bool
    height: int
    width: int
    tile_size: int
    tile_rays: Tensor  # [n_tiles, tile_size^2] long indices into dirs, -1 where the tile overhangs
    tile_theta: Tensor  # [n_tiles, 2] (lo, hi) of atan2(x, z) over the tile's valid rays
    tile_phi: Tensor  # [n_tiles, 2] (lo, hi) of atan2(y, z)
    tile_active: Tensor  # [n_tiles] bool: the tile has at least one valid ray
    # Per-grid facts derived once and reused by every render of this grid (tile pyramids by dtype/xi).
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def num_rays(self) -> int:
        return self.dirs.shape[0]

    @property
    def num_tiles(self) -> int:
        return self.tile_rays.shape[0]

    @property
    def tiles_y(self) -> int:
        return -(-self.height // self.tile_size)

    @property
    def tiles_x(self) -> int:
        return -(-self.width // self.tile_size)

    @property
    def num_valid(self) -> int:
        """The number of valid rays (counted once per grid: no host sync per render of a device grid)."""
        if "num_valid" not in self._cache:
            self._cache["num_valid"] = int(self.valid.sum())
        return self._cache["num_valid"]

    def to(self, device: torch.device | str) -> "RayGrid":
        """This grid on `device`: made on the first call for that device and kept, with the per-grid facts
        computed so far (pyramids, cull bounds, ray count) moved along; later calls upload nothing and the
        copy keeps its own facts (a training view renders the same grid every time it comes round)."""
        device = torch.device(device)
        if device == self.dirs.device:
            return self
        copies = self._cache.setdefault("on_device", {})
        if str(device) not in copies:
            copy = RayGrid(
                self.dirs.to(device), self.valid.to(device), self.height, self.width, self.tile_size,
                self.tile_rays.to(device), self.tile_theta.to(device), self.tile_phi.to(device),
                self.tile_active.to(device),
            )
            copy._cache.update({key: _moved(value, device) for key, value in self._cache.items()
                                if key != "on_device"})
            copies[str(device)] = copy
        return copies[str(device)]

    def tile_mirror_bounds(self, xi: float = 1.0) -> tuple[Tensor, Tensor]:
        """Tile bounds in the mirror-tangent domain (Eq. D.7): ([n_tiles, 2] theta, [n_tiles, 2] phi)."""
        return mirror_tangent(self.tile_theta, xi), mirror_tangent(self.tile_phi, xi)

    def tile_pyramid(self, dtype: torch.dtype | None = None, xi: float = 1.0) -> "TilePyramid":
        """The tile pyramid the association searches (cached per dtype and xi); see TilePyramid."""
        dtype = self.dirs.dtype if dtype is None else dtype
        key = ("pyramid", dtype, xi)
        if key not in self._cache:
            theta_m, phi_m = self.tile_mirror_bounds(xi)
            tiles = torch.cat([theta_m, phi_m], -1).to(dtype)
            self._cache[key] = TilePyramid.build(tiles, self.tile_active, self.tiles_x, self.tiles_y)
        return self._cache[key]

    def ray_cull_bounds(self, dtype: torch.dtype | None = None, xi: float = 1.0) -> Tensor:
        """[R, 4] each ray's own bounds (theta lo, hi, phi lo, hi; mirror domain, the tile bounds of a one-ray
        tile widened by _RAY_CULL_SLACK), cached: the kernels skip a (ray, Gaussian) pair of a tile's list whose
        ray bounds miss the Gaussian's PBF (csrc/geer_ray.h ray_meets_pbf). Invalid rays: empty intervals."""
        dtype = self.dirs.dtype if dtype is None else dtype
        key = ("ray_cull", dtype, xi)
        if key not in self._cache:
            x, y, z = (c[:, None] for c in self.dirs.unbind(-1))
            ok = self.valid[:, None]
            widen = self.dirs.new_tensor([-_RAY_CULL_SLACK, _RAY_CULL_SLACK])
            theta = mirror_tangent(_tile_angle_bounds(x, z, ok) + widen, xi)
            phi = mirror_tangent(_tile_angle_bounds(y, z, ok) + widen, xi)
            self._cache[key] = torch.cat([theta, phi], -1).to(dtype).contiguous()
        return self._cache[key]

    def warp_cull_bounds(self, dtype: torch.dtype | None = None, xi: float = 1.0) -> Tensor:
        """[n_tiles * warps per tile, 4] the union of ray_cull_bounds over each warp's rays (threads 32 w to
        32 w + 31 of a tile's block, csrc/geer_blocks.h ray_slot; empty where a warp has no valid ray), cached:
        the kernels skip a whole warp for a list entry whose PBF its bounds miss, before any ray's test."""
        dtype = self.dirs.dtype if dtype is None else dtype
        key = ("warp_cull", dtype, xi)
        if key not in self._cache:
            rays = self.ray_cull_bounds(dtype, xi)
            per_tile = self.tile_rays.shape[1]
            warps = -(-per_tile // 32)
            idx = torch.nn.functional.pad(self.tile_rays, (0, 32 * warps - per_tile), value=-1)
            empty = rays.new_tensor([math.inf, -math.inf, math.inf, -math.inf])
            b = torch.where((idx >= 0)[..., None], rays[idx.clamp_min(0)], empty)  # [T, 32 W, 4]
            b = b.unflatten(1, (warps, 32))
            lo, hi = b[..., 0::2].amin(2), b[..., 1::2].amax(2)  # [T, W, 2] each: theta, phi
            self._cache[key] = torch.stack([lo[..., 0], hi[..., 0], lo[..., 1], hi[..., 1]], -1).flatten(0, 1).contiguous()
        return self._cache[key]

    # ----------------------------------------------------------------------------------- builders
    @classmethod
    def from_rays(cls, dirs: Tensor, valid: Tensor | None = None, tile_size: int = 16) -> "RayGrid":
        """Grid from per-pixel rays dirs [H, W, 3] (any norm) and an optional validity mask [H, W]."""
        if dirs.ndim != 3 or dirs.shape[-1] != 3:
            raise ValueError(f"dirs: expected shape [H, W, 3], got {tuple(dirs.shape)}")
        if tile_size < 1:
            raise ValueError(f"tile_size: must be >= 1, got {tile_size}")
        height, width = dirs.shape[:2]
        norm = dirs.norm(dim=-1, keepdim=True)
        ok = torch.isfinite(dirs).all(-1) & (norm[..., 0] > 0)
        valid = ok if valid is None else (valid.to(torch.bool) & ok)
        unit = torch.where(ok[..., None], dirs / norm.clamp_min(torch.finfo(dirs.dtype).tiny), 0.0)
        unit = unit.reshape(-1, 3)
        valid = valid.reshape(-1)

        tile_rays = _tile_ray_indices(height, width, tile_size, dirs.device)
        ray_ok = (tile_rays >= 0) & valid[tile_rays.clamp_min(0)]
        d = unit[tile_rays.clamp_min(0)]  # [T, P, 3]
        x, y, z = d.unbind(-1)
        tile_theta = _tile_angle_bounds(x, z, ray_ok)
        tile_phi = _tile_angle_bounds(y, z, ray_ok)
        grid = cls(unit, valid, height, width, tile_size, tile_rays, tile_theta, tile_phi, ray_ok.any(-1))
        grid.num_valid  # counted where the grid is made (the host), carried to its device copies
        return grid

    @classmethod
    def beap(
        cls,
        width: int,
        height: int,
        fov_x: float,
        fov_y: float,
        tile_size: int = 16,
        valid: Tensor | None = None,
        center: tuple[float, float] = (0.0, 0.0),
        dtype: torch.dtype = torch.float32,
        device: torch.device | str = "cpu",
    ) -> "RayGrid":
        """BEAP grid (paper Eq. 11): w x h cells uniform in theta over fov_x and phi over fov_y (radians),
        centered on `center` = (theta, phi). Angles must stay inside (-pi/2, pi/2)."""
        dirs = beap_directions(width, height, fov_x, fov_y, center, dtype, device)
        return cls.from_rays(dirs, valid, tile_size)


def pyramid_levels(tiles_x: int, tiles_y: int) -> list[tuple[int, int]]:
    """(nx, ny) per level: level 0 the tiles, each level ceil(half) of the one below, up to a single node
    (csrc/geer_associate.h make_tile_pyramid computes the same)."""
    levels = [(tiles_x, tiles_y)]
    while levels[-1][0] > 1 or levels[-1][1] > 1:
        nx, ny = levels[-1]
        levels.append((-(-nx // 2), -(-ny // 2)))
    return levels


@dataclass
class TilePyramid:
    """Tiles grouped into 2x2 blocks, level by level, each node carrying the union of its active tiles'
    mirror-tangent bounds (a node with no active tile is inactive). Level 0 is the tiles themselves; the
    single top node holds the grid's overall bounds. A Gaussian whose PBF misses a node misses every tile
    below it, so the association only descends where it can hit (associate.py, csrc/geer_associate.h)."""

    bounds: Tensor  # [n_nodes, 4] theta lo, hi, phi lo, hi (mirror domain), level after level, row-major
    active: Tensor  # [n_nodes] bool
    levels: list[tuple[int, int]]  # (nx, ny) per level
    offsets: list[int]  # first node of each level

    @classmethod
    def build(cls, tiles: Tensor, active: Tensor, tiles_x: int, tiles_y: int) -> "TilePyramid":
        levels = pyramid_levels(tiles_x, tiles_y)
        inf = math.inf
        empty = torch.tensor([inf, -inf, inf, -inf], dtype=tiles.dtype, device=tiles.device)
        b = torch.where(active[:, None], tiles, empty).reshape(tiles_y, tiles_x, 4)
        a = active.reshape(tiles_y, tiles_x)
        all_b, all_a, offsets, off = [b.reshape(-1, 4)], [a.reshape(-1)], [0], tiles_x * tiles_y
        for nx, ny in levels[1:]:
            pad_y, pad_x = 2 * ny - b.shape[0], 2 * nx - b.shape[1]
            b = torch.cat([b, empty.expand(pad_y, b.shape[1], 4)], 0)
            b = torch.cat([b, empty.expand(b.shape[0], pad_x, 4)], 1)
            a = torch.nn.functional.pad(a, (0, pad_x, 0, pad_y))
            blocks = b.reshape(ny, 2, nx, 2, 4)
            lo, hi = blocks[..., 0::2].amin((1, 3)), blocks[..., 1::2].amax((1, 3))
            b = torch.stack([lo[..., 0], hi[..., 0], lo[..., 1], hi[..., 1]], -1)
            a = a.reshape(ny, 2, nx, 2).any(3).any(1)
            offsets.append(off)
            off += nx * ny
            all_b.append(b.reshape(-1, 4))
            all_a.append(a.reshape(-1))
        return cls(torch.cat(all_b).contiguous(), torch.cat(all_a).contiguous(), levels, offsets)


def beap_directions(
    width: int,
    height: int,
    fov_x: float,
    fov_y: float,
    center: tuple[float, float] = (0.0, 0.0),
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> Tensor:
    """Unit directions [h, w, 3] at BEAP cell centers: theta_j = c_x + fov_x * ((j + 0.5) / w - 0.5)."""
    theta = center[0] + fov_x * ((torch.arange(width, dtype=torch.float64) + 0.5) / width - 0.5)
    phi = center[1] + fov_y * ((torch.arange(height, dtype=torch.float64) + 0.5) / height - 0.5)
    limit = math.pi / 2
    if theta.abs().max() >= limit or phi.abs().max() >= limit:
        raise ValueError("BEAP angles must lie inside (-90, 90) degrees; use RayGrid.from_rays beyond that")
    t, p = torch.meshgrid(theta, phi, indexing="xy")  # [h, w]
    # Direction with x/z = tan(theta), y/z = tan(phi) (paper Eq. E.1-E.3).
    d = torch.stack([torch.tan(t), torch.tan(p), torch.ones_like(t)], -1)
    return (d / d.norm(dim=-1, keepdim=True)).to(dtype=dtype, device=device)


def _tile_ray_indices(height: int, width: int, tile_size: int, device) -> Tensor:
    ty, tx = -(-height // tile_size), -(-width // tile_size)
    oy = torch.arange(tile_size, device=device)
    rows = (torch.arange(ty, device=device)[:, None] * tile_size + oy[None])  # [ty, ts]
    cols = (torch.arange(tx, device=device)[:, None] * tile_size + oy[None])  # [tx, ts]
    r = rows[:, None, :, None].expand(ty, tx, tile_size, tile_size)
    c = cols[None, :, None, :].expand(ty, tx, tile_size, tile_size)
    idx = r * width + c
    idx = torch.where((r < height) & (c < width), idx, torch.full_like(idx, -1))
    return idx.reshape(ty * tx, tile_size * tile_size)


def _tile_angle_bounds(a: Tensor, z: Tensor, ok: Tensor) -> Tensor:
    """[T, 2] (lo, hi) of atan2(a, z) over the valid rays of each tile, conservatively widened.

    A tile whose rays straddle the +-pi seam, or that holds a ray along the plane family's axis
    (a = z = 0, angle undefined), gets the full range [-pi, pi].
    """
    ang = torch.atan2(a, z)
    inf = torch.tensor(math.inf, dtype=ang.dtype, device=ang.device)
    lo = torch.where(ok, ang, inf).amin(-1)
    hi = torch.where(ok, ang, -inf).amax(-1)
    axial = (ok & (torch.sqrt(a * a + z * z) < _AXIAL_EPS)).any(-1)
    full = axial | ((hi - lo) > math.pi)
    lo = torch.where(full, torch.full_like(lo, -math.pi), lo - _TILE_BOUND_SLACK)
    hi = torch.where(full, torch.full_like(hi, math.pi), hi + _TILE_BOUND_SLACK)
    return torch.stack([lo, hi], -1)


def _moved(value, device: torch.device):
    """A cached per-grid fact on `device` (tensors, tile pyramids, numbers)."""
    if isinstance(value, Tensor):
        return value.to(device)
    if isinstance(value, TilePyramid):
        return TilePyramid(value.bounds.to(device), value.active.to(device), value.levels, value.offsets)
    return value
