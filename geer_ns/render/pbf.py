"""Stage 2: Particle Bounding Frustum (PBF), paper Sec. 3.2, Eq. 7-10 and App. D.1-D.2.

For each Gaussian we bound the set of ray directions (half-lines from the camera center) that pass
through its lambda-ellipsoid {p : (p - mu_c)^T Sigma_c^-1 (p - mu_c) <= lambda^2}. The bound is two
angular intervals: theta = atan2(x, z) in the xz-plane and phi = atan2(y, z) in the yz-plane.

The planes of Eq. 7 contain the camera's y (resp. x) axis, so the theta bound is a 2-D problem in the
xz-plane: the tangent lines from the origin to the ellipse that is the ellipsoid projected along y.
Its tangent slopes c = tan(theta) solve T22 c^2 - 2 T02 c + T00 = 0 with T = lambda^2 Sigma_c - mu_c mu_c^T
(Eq. 10 / D.3-D.5). We solve it in a frame rotated so that the projected mean lies on +z, with the
discriminant written as lambda^2 r^2 S'_xx - lambda^4 det(S'), every term a sum of squares of the
covariance factor M = R_v S (no mu mu^T - lambda^2 Sigma cancellation, which loses everything in
float32 at coordinates ~1e4).

Each tangent line x = c z carries two candidate angles, atan(c) and atan(c) +- pi; for wide FoV only
one of them bounds the Gaussian (App. D.2, Fig. D.1). The paper picks the candidates nearest the
mean's direction in the mirror-transformed domain (Eq. D.7, xi = 1, i.e. tan(theta / 2)). We use the
exact form of that rule: the interval of a convex set seen from outside contains the mean's
direction and is shorter than pi, so the lower bound is the larger of the candidates in
(theta_mu - pi, theta_mu] and the upper bound the smaller of those in [theta_mu, theta_mu + pi).
("Nearest" fails for elongated Gaussians grazing the camera, whose interval is far from symmetric.)
Intervals are then compared with camera sub-frusta in the mirror-tangent domain, where angles in
(-pi, pi) stay ordered (associate.py).

Lambda. The paper fixes lambda = 3, which misses visible tails of opaque Gaussians: alpha = sigma *
exp(-D^2 / 2) >= 1/255 holds exactly for D^2 <= 2 ln(255 sigma). The default "opacity" rule uses that
distance (complete, and tighter for faint Gaussians); sigma < 1/255 can never be visible and is culled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

LambdaMode = Literal["opacity", "paper"]

ALPHA_MIN = 1.0 / 255.0
PAPER_LAMBDA = 3.0
# Relative and absolute slack on lambda^2 so that float rounding in the bound never drops a pair
# that the renderer (same threshold, other rounding) keeps.
_LAMBDA_SQ_REL_SLACK = 1e-3
_LAMBDA_SQ_ABS_SLACK = 1e-4


def pbf_lambda_sq(opacities: Tensor, mode: LambdaMode = "opacity") -> tuple[Tensor, Tensor]:
    """(lambda^2 [N], alive [N]): contour level of each Gaussian's PBF and whether it can be seen at all."""
    alive = opacities >= ALPHA_MIN
    if mode == "opacity":
        lam2 = 2.0 * torch.log((255.0 * opacities).clamp_min(1.0))
    elif mode == "paper":
        lam2 = torch.full_like(opacities, PAPER_LAMBDA**2)
    else:
        raise ValueError(f"lambda_mode must be 'opacity' or 'paper', got {mode!r}")
    return lam2 * (1.0 + _LAMBDA_SQ_REL_SLACK) + _LAMBDA_SQ_ABS_SLACK, alive


def mirror_tangent(theta: Tensor, xi: float = 1.0) -> Tensor:
    """Mirror transform of Eq. D.7: tan(theta_xi) = sin(theta) / (cos(theta) + xi).

    With xi = 1 it is tan(theta / 2), increasing on (-pi, pi); theta = +-pi maps to +-inf (the
    closed ends of the angular domain). Other xi are kept for experiments only: xi < 1 is not
    monotone beyond +-90 degrees, which is exactly what breaks naive tan comparisons.
    """
    if xi == 1.0:
        pi = torch.tensor(math.pi, dtype=theta.dtype, device=theta.device)
        inf = torch.full_like(theta, math.inf)
        return torch.where(theta >= pi, inf, torch.where(theta <= -pi, -inf, torch.tan(0.5 * theta)))
    return torch.sin(theta) / (torch.cos(theta) + xi)


@dataclass
class PBF:
    """Angular bounds per Gaussian. lo/hi are unwrapped angles (lo <= mean's angle <= hi, hi - lo < pi),
    or [-pi, pi] where `full_*` (camera inside the Gaussian or inside its projected ellipse)."""

    theta_lo: Tensor
    theta_hi: Tensor
    phi_lo: Tensor
    phi_hi: Tensor
    alive: Tensor  # [N] alpha can reach 1/255 at all
    camera_inside: Tensor  # [N] camera center inside the lambda-ellipsoid
    cone: Tensor | None = None  # [N, 9] the cone test's form (cones.gaussian_cone_form); None: the box test alone

    @property
    def num_gaussians(self) -> int:
        return self.alive.shape[0]


def _plane_bounds(
    mu_a: Tensor, mu_z: Tensor, row_a: Tensor, row_z: Tensor, lam2: Tensor, force_full: Tensor
) -> tuple[Tensor, Tensor]:
    """Angular interval of the ellipse (mean (mu_a, mu_z), covariance factor rows row_a, row_z) seen from
    the origin of the (a, z) plane, angle = atan2(a, z). Returns unwrapped (lo, hi)."""
    r = torch.sqrt(mu_a * mu_a + mu_z * mu_z)
    tiny = torch.finfo(r.dtype).tiny
    r_safe = r.clamp_min(tiny)
    theta_mu = torch.atan2(mu_a, mu_z)
    # Rotate so that the mean is on +z: x' is the across direction, z' the along direction.
    cos_t, sin_t = (mu_z / r_safe)[:, None], (mu_a / r_safe)[:, None]
    row_x = cos_t * row_a - sin_t * row_z
    row_zp = sin_t * row_a + cos_t * row_z
    s_xx = (row_x * row_x).sum(-1)
    s_xz = (row_x * row_zp).sum(-1)
    s_zz = (row_zp * row_zp).sum(-1)
    det = torch.linalg.cross(row_x, row_zp, dim=-1).pow(2).sum(-1)  # Lagrange identity: det(S')
    disc = lam2 * (r * r) * s_xx - lam2 * lam2 * det
    t00, t02, t22 = lam2 * s_xx, lam2 * s_xz, lam2 * s_zz - r * r
    sq = torch.sqrt(disc.clamp_min(0.0))

    lows, highs = [], []
    for sign in (1.0, -1.0):
        # The same tangent line written two ways; take the better-conditioned one.
        va = torch.stack([t02 + sign * sq, t22], -1)
        vb = torch.stack([t00, t02 - sign * sq], -1)
        use_a = va.abs().sum(-1) >= vb.abs().sum(-1)
        v = torch.where(use_a[:, None], va, vb)
        delta = torch.atan2(v[:, 0], v[:, 1])  # relative to the mean's direction, in (-pi, pi]
        lows.append(torch.where(delta > 0, delta - math.pi, delta))
        highs.append(torch.where(delta < 0, delta + math.pi, delta))
    lo = theta_mu + torch.maximum(lows[0], lows[1])
    hi = theta_mu + torch.minimum(highs[0], highs[1])

    degenerate = (torch.maximum(va.abs().sum(-1), vb.abs().sum(-1)) <= tiny) | (r <= tiny)
    full = force_full | (disc < 0) | degenerate
    lo = torch.where(full, torch.full_like(lo, -math.pi), lo)
    hi = torch.where(full, torch.full_like(hi, math.pi), hi)
    return lo, hi


@torch.no_grad()
def compute_pbf(means_c: Tensor, cov_factor: Tensor, lam2: Tensor, alive: Tensor, o_u: Tensor) -> PBF:
    """PBF angular bounds from view-space means [N,3], covariance factors M = R_v S [N,3,3] (Sigma_c = M M^T),
    lambda^2 [N] and the camera center in each canonical frame o_u [N,3].

    Complete for the half-line rule (transmittance.py): a ray is visible only where its half-line t >= 0
    meets the lambda-ellipsoid. With the camera outside it, a ray whose line peaks behind the camera has
    q = |o_u|^2 > lambda^2 (alpha < 1/255), and any other visible ray passes through the ellipsoid in front
    of the camera, inside these bounds. With the camera inside, every half-line starts in the ellipsoid:
    every direction sees the Gaussian, and the bounds are the full range."""
    camera_inside = (o_u * o_u).sum(-1) <= lam2
    x, y, z = means_c.unbind(-1)
    theta_lo, theta_hi = _plane_bounds(x, z, cov_factor[:, 0], cov_factor[:, 2], lam2, camera_inside)
    phi_lo, phi_hi = _plane_bounds(y, z, cov_factor[:, 1], cov_factor[:, 2], lam2, camera_inside)
    return PBF(theta_lo, theta_hi, phi_lo, phi_hi, alive, camera_inside)
