"""Stage 3: PBF-CSF association (paper Sec. 3.2, App. D.2).

A Gaussian goes to every active tile whose theta and phi ranges both overlap its PBF. Comparisons
happen in the mirror-tangent domain tan(angle / 2) (Eq. D.7 with xi = 1), which keeps angles in
(-pi, pi) ordered; a PBF interval that crosses the +-pi seam (Gaussians behind a >180 degree camera)
is split into its two pieces. Within a tile, Gaussians are ordered front to back by the Euclidean
distance of their mean (ties: lower index first), as the renderer composites them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .pbf import PBF, mirror_tangent
from .raygrid import RayGrid


@dataclass
class TileLists:
    gaussians: Tensor  # [n_tiles, K] long, Gaussian ids front to back, -1 padding
    counts: Tensor  # [n_tiles] long

    @property
    def max_count(self) -> int:
        return self.gaussians.shape[1]


def _interval_pieces(lo: Tensor, hi: Tensor, xi: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Split unwrapped [lo, hi] (hi - lo <= 2 pi) at the +-pi seam; returns two mirror-tangent pieces.
    The second piece is empty (lo = +inf) when there is no wrap."""
    pi = math.pi
    a_lo, a_hi = lo.clamp(-pi, pi), hi.clamp(-pi, pi)
    wraps_up, wraps_down = hi > pi, lo < -pi
    b_lo = torch.where(wraps_up, torch.full_like(lo, -pi), lo + 2 * pi)
    b_hi = torch.where(wraps_up, hi - 2 * pi, torch.full_like(hi, pi))
    has_b = wraps_up | wraps_down
    m = lambda t: mirror_tangent(t, xi)  # noqa: E731
    b_lo_m = torch.where(has_b, m(b_lo), torch.full_like(lo, math.inf))
    b_hi_m = torch.where(has_b, m(b_hi), torch.full_like(hi, -math.inf))
    return m(a_lo), m(a_hi), b_lo_m, b_hi_m


def _overlaps(tile_bounds: Tensor, pieces: tuple[Tensor, Tensor, Tensor, Tensor]) -> Tensor:
    """[T, N] whether tile intervals [T, 2] overlap either piece of the Gaussians' intervals."""
    t_lo, t_hi = tile_bounds[:, 0:1], tile_bounds[:, 1:2]
    a_lo, a_hi, b_lo, b_hi = (p[None] for p in pieces)
    return ((a_lo <= t_hi) & (t_lo <= a_hi)) | ((b_lo <= t_hi) & (t_lo <= b_hi))


@torch.no_grad()
def associate(pbf: PBF, grid: RayGrid, depth: Tensor, xi: float = 1.0, tile_chunk: int = 256) -> TileLists:
    """Per-tile Gaussian lists sorted front to back by `depth` [N] (Euclidean distance of the mean)."""
    device = depth.device
    order = torch.sort(depth, stable=True).indices  # front to back
    theta_pieces = tuple(p[order] for p in _interval_pieces(pbf.theta_lo, pbf.theta_hi, xi))
    phi_pieces = tuple(p[order] for p in _interval_pieces(pbf.phi_lo, pbf.phi_hi, xi))
    alive = pbf.alive[order]
    tile_theta_m, tile_phi_m = grid.tile_mirror_bounds(xi)

    rows, cols = [], []
    for start in range(0, grid.num_tiles, tile_chunk):
        sl = slice(start, start + tile_chunk)
        hit = _overlaps(tile_theta_m[sl], theta_pieces) & _overlaps(tile_phi_m[sl], phi_pieces)
        hit &= alive[None] & grid.tile_active[sl, None]
        r, c = torch.nonzero(hit, as_tuple=True)  # row-major: sorted by tile, then by depth rank
        rows.append(r + start)
        cols.append(c)
    rows, cols = torch.cat(rows), torch.cat(cols)

    counts = torch.bincount(rows, minlength=grid.num_tiles)
    k = int(counts.max()) if counts.numel() else 0
    offsets = torch.cumsum(counts, 0) - counts
    rank = torch.arange(rows.numel(), device=device) - offsets[rows]
    gaussians = torch.full((grid.num_tiles, k), -1, dtype=torch.long, device=device)
    gaussians[rows, rank] = order[cols]
    return TileLists(gaussians, counts)
