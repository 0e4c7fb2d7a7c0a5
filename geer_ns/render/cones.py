"""The association's cone test: a tile test as tight at the fisheye rim as at the center (docs/association.md).

The (theta, phi) box test of the PBF compares intervals of atan(x/z) and atan(y/z); towards 90 degrees from the
axis a small patch of the sphere spans wide, skewed intervals of both, and box-against-box keeps Gaussians that
never reach the tile. The cone test does not depend on where the tile sits:

    Gaussian  its alpha >= 1/255 directions lie in the elliptic cone F(d) = (a.d)^2 - |B d|^2 >= 0, exact for the
              lambda-ellipsoid: lambda^2 |W d|^2 - |o_u x W d|^2 written without cancellation
              (gaussian_cone_form);
    tile      its rays lie within angle beta of its center ray c (tile_cones, from the rays themselves);
    test      max of F over the tile's disk on the plane c.d = 1, bounded through the exact Lagrangian dual of that
              trust-region problem (cone_meets_tile, the twin of csrc/geer_associate.h cone_meets_tile).

It runs on the box test's survivors (tiles, level 0 of the pyramid), so the pairs are the box test's minus those
the cone proves invisible.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .raygrid import RayGrid

GAUSS_CONE_VALUES = 9  # a, b1, b2
TILE_CONE_VALUES = 10  # e1, e2, c, tan(beta)
_NEWTON_STEPS = 3  # geer_associate.h kConeNewtonSteps
# Reject only below -tol x the magnitude of F's terms on the disk (geer_associate.h ConeTol).
_TOL = {torch.float32: 1e-5, torch.float64: 1e-12}
# Angular slack (radians) on a tile's radius: far above the rounding of its rays' directions in float32.
_TILE_RADIUS_SLACK = 1e-5
# Tiles wider than this (radians from their center ray) skip the cone test: the disk's tangent plane degenerates.
_MAX_TILE_RADIUS = 1.2


def _unit(v: Tensor) -> Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(v.dtype).tiny)


def _orthonormal_pair(n: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors [N,3] completing the unit vectors n [N,3] to an orthonormal frame."""
    helper = torch.zeros_like(n)
    use_x = n[:, 0].abs() < 0.6
    helper[:, 0] = use_x.to(n.dtype)
    helper[:, 1] = (~use_x).to(n.dtype)
    p1 = _unit(torch.linalg.cross(n, helper, dim=-1))
    return p1, torch.linalg.cross(n, p1, dim=-1)


@torch.no_grad()
def gaussian_cone_form(whiten: Tensor, o_u: Tensor, lam2: Tensor, camera_inside: Tensor) -> Tensor:
    """[N,9] rows (a, b1, b2) of each Gaussian's cone F(d) = (a.d)^2 - (b1.d)^2 - (b2.d)^2 >= 0, which holds for every
    view direction d whose half-line meets the lambda-ellipsoid. whiten [N,3,3] or [N,9] (d_u = W d), o_u [N,3], lam2
    [N] (pbf_lambda_sq, with slack), camera_inside [N]: all zeros there (F = 0: every tile passes).

    With o_hat = o_u / |o_u| and p1, p2 completing it: lambda^2 |W d|^2 - |o_u x W d|^2 = lambda^2 (o_hat . W d)^2 -
    (|o_u|^2 - lambda^2) |P W d|^2, so a = lambda W^T o_hat, b_i = sqrt((|o_u| - lambda)(|o_u| + lambda)) W^T p_i,
    scaled by 1 / |a| (the sign of F is all the test reads)."""
    w = whiten.reshape(-1, 3, 3)
    r = o_u.norm(dim=-1)
    o_hat = _unit(o_u)
    p1, p2 = _orthonormal_pair(o_hat)
    lam = lam2.sqrt()
    k = ((r - lam).clamp_min(0.0) * (r + lam)).sqrt()
    a = lam[:, None] * torch.einsum("nij,ni->nj", w, o_hat)
    b1 = k[:, None] * torch.einsum("nij,ni->nj", w, p1)
    b2 = k[:, None] * torch.einsum("nij,ni->nj", w, p2)
    form = torch.cat([a, b1, b2], -1) / a.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(w.dtype).tiny)
    inside = camera_inside | (r <= lam) | ~torch.isfinite(form).all(-1)
    return torch.where(inside[:, None], torch.zeros_like(form), form).contiguous()


def tile_cones(grid: RayGrid, dtype: torch.dtype | None = None) -> Tensor:
    """[n_tiles, 10] each tile's cone (e1, e2, c, tan(beta)), cached on the grid: c the normalized sum of the tile's
    valid rays, beta the largest angle from c to one of them (plus _TILE_RADIUS_SLACK); tan(beta) = inf (no cone test)
    for inactive tiles and tiles wider than _MAX_TILE_RADIUS."""
    dtype = grid.dirs.dtype if dtype is None else dtype
    key = ("tile_cones", dtype)
    if key not in grid._cache:
        ok = (grid.tile_rays >= 0) & grid.valid[grid.tile_rays.clamp_min(0)]
        d = grid.dirs.double()[grid.tile_rays.clamp_min(0)] * ok[..., None]  # [T, P, 3]
        c = _unit(d.sum(1))
        cos = (d * c[:, None]).sum(-1)
        sin = torch.linalg.cross(d, c[:, None].expand_as(d), dim=-1).norm(dim=-1)
        beta = torch.where(ok, torch.atan2(sin, cos), torch.zeros_like(cos)).amax(1) + _TILE_RADIUS_SLACK
        wide = (beta > _MAX_TILE_RADIUS) | ~ok.any(1)
        rho = torch.where(wide, torch.full_like(beta, math.inf), torch.tan(beta.clamp_max(_MAX_TILE_RADIUS)))
        e1, e2 = _orthonormal_pair(c)
        cones = torch.cat([e1, e2, c, rho[:, None]], -1)
        grid._cache[key] = cones.to(dtype=dtype, device=grid.dirs.device).contiguous()
    return grid._cache[key]


def cone_meets_tile(gauss: Tensor, tile: Tensor) -> Tensor:
    """[M] bool: whether Gaussian cones gauss [M,9] may meet tile cones tile [M,10] (False only where no ray of the
    tile sees alpha >= 1/255). The twin of csrc/geer_associate.h cone_meets_tile, operation for operation."""
    if gauss.shape[0] == 0:
        return torch.zeros(0, dtype=torch.bool, device=gauss.device)
    dtype = gauss.dtype
    zero = torch.zeros((), dtype=dtype, device=gauss.device)
    rho = tile[:, 9]
    p = torch.stack([torch.stack([(gauss[:, 3 * v: 3 * v + 3] * tile[:, 3 * j: 3 * j + 3]) for j in range(3)], 1)
                     for v in range(3)], 1)  # [M, 3 rows, 3 axes, 3]
    p = (p[..., 0] + p[..., 1]) + p[..., 2]  # x_dot's order

    def coef(i: int, j: int) -> Tensor:
        return (p[:, 0, i] * p[:, 0, j] - p[:, 1, i] * p[:, 1, j]) - p[:, 2, i] * p[:, 2, j]

    f0 = coef(2, 2)
    h11, h12, h22, g1, g2 = coef(0, 0), coef(0, 1), coef(1, 1), coef(0, 2), coef(1, 2)
    rho2 = rho * rho
    sq = p * p
    mag = zero
    for v in range(3):
        for j in range(3):
            mag = mag + sq[:, v, j]
    reject_below = -(_TOL[dtype] * (mag * (1.0 + rho2)))
    pa = p.abs()  # the pre-reject: F <= A^2 - B1^2 - B2^2 on the disk
    spread = rho[:, None] * (pa[:, :, 0] + pa[:, :, 1])
    ab = torch.cat([pa[:, :1, 2] + spread[:, :1], torch.clamp_min(pa[:, 1:, 2] - spread[:, 1:], 0.0)], 1)
    pre_keep = ~((ab[:, 0] * ab[:, 0] - ab[:, 1] * ab[:, 1]) - ab[:, 2] * ab[:, 2] < reject_below)
    gg = g1 * g1 + g2 * g2  # the cheap accept: F's maximum along g's direction, a point of the disk
    ng = torch.sqrt(gg)
    c = (((h11 * g1) * g1 + ((2.0 * h12) * g1) * g2) + (h22 * g2) * g2) / gg
    t = torch.where(c >= 0, rho, torch.minimum(rho, ng / -c))
    line_keep = (gg > 0) & (((f0 + (2.0 * t) * ng) + (t * t) * c) >= 0)
    hm, hd = 0.5 * (h11 + h22), 0.5 * (h11 - h22)
    dd = torch.sqrt(hd * hd + h12 * h12)
    h1, h2 = hm + dd, hm - dd
    v0 = torch.where(hd >= 0, hd + dd, h12)
    v1 = torch.where(hd >= 0, h12, dd - hd)
    vn = torch.sqrt(v0 * v0 + v1 * v1)
    gp = torch.where(vn > 0, (v0 * g1 + v1 * g2) / vn, g1)
    q1 = gp * gp
    q2 = torch.clamp_min(gg - q1, 0.0)
    mu_lo = torch.clamp_min(h1, 0.0)
    mu_a = torch.maximum(mu_lo, h1 + gp.abs() / rho)
    mu_b = torch.maximum(mu_lo, h1 + torch.sqrt(gg) / rho)
    mu = mu_a
    going = torch.ones_like(f0, dtype=torch.bool)
    for _ in range(_NEWTON_STEPS):
        t1, t2 = mu - h1, mu - h2
        s1, s2 = q1 / (t1 * t1), q2 / (t2 * t2)
        n2 = s1 + s2
        going = going & (t1 > 0) & (n2 > rho2) & (n2 < math.inf)
        n1 = torch.sqrt(n2)
        slope = (s1 / t1 + s2 / t2) / (n2 * n1)
        phi = 1.0 / n1 - 1.0 / rho
        mu = torch.where(going, torch.minimum(mu - phi / slope, mu_b), mu)
    t1, t2 = mu - h1, mu - h2
    pole = ~(t1 > 0) & (q1 > 0)
    u1 = torch.where(t1 > 0, q1 / t1, zero)
    u2 = torch.where(t2 > 0, q2 / t2, zero)
    bound = ((f0 + mu * rho2) + u1) + u2
    keep = bound >= reject_below
    return ~(rho < math.inf) | (f0 >= 0) | (pre_keep & (line_keep | pole | keep))
