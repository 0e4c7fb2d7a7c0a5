"""Stage 3: PBF-CSF association (paper Sec. 3.2, App. D.2).

A Gaussian goes to every active tile whose theta and phi ranges both overlap its PBF. Comparisons
happen in the mirror-tangent domain tan(angle / 2) (Eq. D.7 with xi = 1), which keeps angles in
(-pi, pi) ordered; a PBF interval that crosses the +-pi seam (Gaussians behind a >180 degree camera)
is split into its two pieces. Within a tile, Gaussians are ordered front to back by the Euclidean
distance of their mean (ties: lower index first), as the renderer composites them.

Where the PBF carries its cone (pbf.PBF.cone), a tile that passes the box test must also pass the cone test
(cones.py, docs/association.md), whose tightness does not depend on where the tile sits.

The overlapping tiles are found by descending the grid's tile pyramid (raygrid.TilePyramid) level by
level, testing a node's four children only where the node itself overlaps: O(N log T + pairs) tile
tests on any grid instead of N x T, and the same search, test for test, as csrc/geer_associate.h.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .cones import cone_meets_tile, tile_cones
from .pbf import PBF, mirror_tangent
from .raygrid import RayGrid


@dataclass
class TileLists:
    gaussians: Tensor  # [n_tiles, K] long, Gaussian ids front to back, -1 padding
    counts: Tensor  # [n_tiles] long
    tile_tests: int = 0  # (Gaussian, pyramid node) overlap tests the search made

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


def pbf_cull_pieces(bounds: Tensor, xi: float = 1.0) -> Tensor:
    """[N, 8] the PBFs' pieces as the render kernels' per-ray cull reads them (csrc/geer_ray.h GaussFrame.pbf):
    theta (a_lo, a_hi, b_lo, b_hi), phi (the same), mirror domain; bounds [N, 4] (theta lo, hi, phi lo, hi)."""
    theta = _interval_pieces(bounds[:, 0], bounds[:, 1], xi)
    phi = _interval_pieces(bounds[:, 2], bounds[:, 3], xi)
    return torch.stack(theta + phi, -1).contiguous()


def _overlaps(lo: Tensor, hi: Tensor, pieces: tuple[Tensor, Tensor, Tensor, Tensor]) -> Tensor:
    """Whether intervals [lo, hi] overlap either piece (all broadcast together)."""
    a_lo, a_hi, b_lo, b_hi = pieces
    return ((a_lo <= hi) & (lo <= a_hi)) | ((b_lo <= hi) & (lo <= b_hi))


@torch.no_grad()
def associate(pbf: PBF, grid: RayGrid, depth: Tensor, xi: float = 1.0) -> TileLists:
    """Per-tile Gaussian lists sorted front to back by `depth` [N] (Euclidean distance of the mean)."""
    device = depth.device
    g, tiles, tests = _tile_pairs(pbf, grid, xi)

    # Sort by (tile, depth rank): rank from a stable depth sort, so ties keep the lower index first.
    order = torch.sort(depth, stable=True).indices
    rank = torch.empty_like(order)
    rank[order] = torch.arange(order.numel(), device=device)
    key = tiles * max(1, order.numel()) + rank[g]
    perm = torch.sort(key).indices
    tiles, g = tiles[perm], g[perm]

    counts = torch.bincount(tiles, minlength=grid.num_tiles)
    k = int(counts.max()) if counts.numel() else 0
    offsets = torch.cumsum(counts, 0) - counts
    pos = torch.arange(tiles.numel(), device=device) - offsets[tiles]
    gaussians = torch.full((grid.num_tiles, k), -1, dtype=torch.long, device=device)
    gaussians[tiles, pos] = g
    return TileLists(gaussians, counts, tests)


@torch.no_grad()
def seen_by(pbf: PBF, grid: RayGrid, xi: float = 1.0) -> Tensor:
    """[N] bool: the Gaussians the association lists in at least one of the grid's active tiles (the ones a
    render of the view can blend), without building the lists."""
    g, _, _ = _tile_pairs(pbf, grid, xi)
    seen = torch.zeros(pbf.alive.shape[0], dtype=torch.bool, device=pbf.alive.device)
    seen[g] = True
    return seen


def _tile_pairs(pbf: PBF, grid: RayGrid, xi: float) -> tuple[Tensor, Tensor, int]:
    """(Gaussian ids, tile ids, tests): every (Gaussian, active tile) whose ranges overlap (and cones meet, where the
    PBF has its cone), by the pyramid search."""
    device = pbf.alive.device
    theta_pieces = _interval_pieces(pbf.theta_lo, pbf.theta_hi, xi)
    phi_pieces = _interval_pieces(pbf.phi_lo, pbf.phi_hi, xi)
    pyr = grid.tile_pyramid(xi=xi)
    # Candidates (Gaussian g, node idx within the level), from the single top node down to the tiles.
    g = torch.nonzero(pbf.alive).squeeze(1) if grid.num_tiles else torch.zeros(0, dtype=torch.long, device=device)
    idx = torch.zeros_like(g)
    tests = 0
    for level in range(len(pyr.levels) - 1, -1, -1):
        node = pyr.offsets[level] + idx
        b = pyr.bounds[node]
        hit = pyr.active[node] & _overlaps(b[:, 0], b[:, 1], tuple(p[g] for p in theta_pieces))
        hit &= _overlaps(b[:, 2], b[:, 3], tuple(p[g] for p in phi_pieces))
        tests += g.numel()
        g, idx = g[hit], idx[hit]
        if level == 0:
            if pbf.cone is not None:  # the box test's survivors, tile by tile
                keep = cone_meets_tile(pbf.cone[g], tile_cones(grid, pbf.cone.dtype)[idx])
                g, idx = g[keep], idx[keep]
            break
        nx = pyr.levels[level][0]
        cnx, cny = pyr.levels[level - 1]
        cx = 2 * (idx % nx)[:, None] + torch.tensor([0, 1, 0, 1], device=device)
        cy = 2 * (idx // nx)[:, None] + torch.tensor([0, 0, 1, 1], device=device)
        ok = (cx < cnx) & (cy < cny)
        g, idx = g[:, None].expand(-1, 4)[ok], (cy * cnx + cx)[ok]
    return g, idx, tests
