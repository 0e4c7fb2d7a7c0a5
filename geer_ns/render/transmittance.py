"""Stage 4: exact ray-Gaussian transmittance (paper Eq. B.7-B.9, Theorem 1), on the half-line a ray travels.

In a Gaussian's canonical frame the ray is r_u(t) = o_u + t d_u with o_u = W (o - mu), d_u = W d, and the
integral of the isotropic density along the whole line (the Jacobian absorbed into the measure, Eq. B.5)
is exp(-D^2 / 2) with D = |o_u x d_u| / |d_u| the distance from the center to the line. D is evaluated in
exactly that cross-product form, with d_u normalized first: the expanded |o|^2 |d|^2 - (o.d)^2 (Eq. C.16)
cancels catastrophically for needles, disks and far-away Gaussians (paper App. C.7), and squaring
|o_u x d_u| before normalizing would overflow float32 for 1e-8 scales at 1e4 m.

The half-line rule. A ray is the half-line t >= 0, and the paper's closed form is the response at the
line's closest point t*, which lies behind the camera when t* < 0 (App. B.2 sidesteps this by culling
Gaussians around the camera, a jump as the camera moves through one). Every pair here responds with the
peak on the half-line, sigma exp(-q(max(t*, 0)) / 2), q(t) = |o_u + t d_u|^2: q = D^2 where t* > 0 (the
paper's value, unchanged) and q = |o_u|^2, the response at the camera center, otherwise. Why this and not
the integral over t >= 0 (the closed form times an erfc factor): it equals the paper's value whenever the
peak is in front of the camera (the erfc form departs from it for every t* > 0 too), it is continuous in
the camera position and ray direction (q is even C^1 across t* = 0: both branches are |o_u|^2 with
gradient 2 o_u there), it is bounded by the same lambda-ellipsoid as the PBF (complete with no new
bounds), and it costs one comparison. Depth uses the same clamped t.

Gradients at the clamps follow csrc/geer_ray.h (half_line_backward, ray_backward_step) exactly, with the one
rule of subgradients.py (a value exactly on its clamp gets the clamped side's derivative, 0); they are written
out below with explicit masks rather than left to how torch differentiates clamp/max.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .subgradients import cap_at, floor_at

ALPHA_MAX = 0.99


def ray_frame(o_u: Tensor, w: Tensor) -> Tensor:
    """Per-Gaussian rows that turn a camera-frame ray direction d into the canonical ray [K, 7, 3]:
    rows 0-2 give d_u = W d, rows 3-5 the moment m_u = o_u x d_u = ([o_u]_x W) d, row 6 gives o_u . d_u.

    Stacking them lets one batched matmul produce every (ray, Gaussian) pair's canonical ray; the moment
    is still the cross product (regrouped, with the same rounding order of magnitude), never C.16.
    """
    moment = torch.linalg.cross(o_u[..., :, None].expand_as(w), w, dim=-2)  # columns: o_u x W e_j
    along = torch.einsum("...i,...ij->...j", o_u, w)[..., None, :]
    return torch.cat([w, moment, along], dim=-2)


def canonical_ray_response(o_u: Tensor, w: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
    """Squared canonical distance D^2 of the whole line and the ray parameter of its maximum response t*.

    o_u [..., K, 3] camera center in each Gaussian's canonical frame, w [..., K, 3, 3] whitening matrices,
    dirs [..., P, 3] unit ray directions (camera frame). Returns D^2 and t* of shape [..., P, K]; t* is the
    distance along the unit ray to the point of maximum response (negative: behind the camera).
    """
    frame = ray_frame(o_u, w)  # [..., K, 7, 3]
    rows = frame.flatten(-3, -2) @ dirs.transpose(-1, -2)  # [..., K*7, P]
    rows = rows.unflatten(-2, (frame.shape[-3], 7)).transpose(-1, -3)  # [..., P, 7, K]
    d_u, moment, along = rows[..., 0:3, :], rows[..., 3:6, :], rows[..., 6, :]
    inv_norm = torch.rsqrt(floor_at((d_u * d_u).sum(-2), torch.finfo(d_u.dtype).tiny))
    m_hat = moment * inv_norm[..., None, :]  # normalize before squaring: no overflow for 1e-8 scales
    dist_sq = (m_hat * m_hat).sum(-2)
    t_star = -along * inv_norm * inv_norm
    return dist_sq, t_star


def moving_ray_response(o_u: Tensor, w: Tensor, dirs: Tensor, origins: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """canonical_ray_response for rays with their own origins (rolling shutter): origins [..., P, 3] in the camera
    frame, so each pair's canonical origin is o_u + W origin = W (origin - mean). Returns D^2, t* and that
    origin's |.|^2 (half_line_sq's `o_sq`), each [..., P, K]. The same cross-product form, per pair."""
    d_u = torch.einsum("...kij,...pj->...pki", w, dirs)
    o_pair = o_u[..., None, :, :] + torch.einsum("...kij,...pj->...pki", w, origins)
    inv_norm = torch.rsqrt(floor_at((d_u * d_u).sum(-1), torch.finfo(d_u.dtype).tiny))
    m_hat = torch.linalg.cross(o_pair, d_u) * inv_norm[..., None]
    t_star = -(o_pair * d_u).sum(-1) * inv_norm * inv_norm
    return (m_hat * m_hat).sum(-1), t_star, (o_pair * o_pair).sum(-1)


def half_line_sq(dist_sq: Tensor, t_star: Tensor, o_u: Tensor,
                 o_sq: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """(q, depth, front) of the half-line rule, from canonical_ray_response's [..., P, K] and o_u [..., K, 3]
    (or each pair's |o_u|^2 `o_sq` [..., P, K]: moving_ray_response).

    q = q(max(t*, 0)): D^2 where t* > 0 (`front`), |o_u|^2 (the camera center's own q) otherwise; depth =
    max(t*, 0). Where t* <= 0 neither depends on the ray: no gradient to W, and depth's derivative is 0
    (also at t* = 0 exactly, the kink of max).
    """
    front = t_star > 0
    o_sq = (o_u * o_u).sum(-1)[..., None, :] if o_sq is None else o_sq
    q = torch.where(front, dist_sq, o_sq)
    depth = torch.where(front, t_star, torch.zeros_like(t_star))
    return q, depth, front


def alpha_level_sq(opacity: Tensor) -> Tensor:
    """q_max = 2 ln(255 sigma): alpha = sigma exp(-q/2) >= 1/255 exactly when q <= q_max (-inf for sigma = 0).
    The pair is accepted or rejected on q, before the exponential (no gradient: a threshold)."""
    return 2.0 * torch.log(255.0 * opacity.detach())


def pair_alpha(q: Tensor, opacity: Tensor, mask: Tensor) -> Tensor:
    """Compositing alpha of each (ray, Gaussian) pair: min(0.99, sigma exp(-q/2)) where q <= q_max and
    `mask`, else 0 (q from half_line_sq; opacity broadcast to q's shape).

    Subgradients: the cap passes the derivative where raw < 0.99 and none from 0.99 up (subgradients.cap_at);
    the 1/255 skip is a threshold on q (a kept pair, also one exactly on it, gets its ordinary derivative, a
    skipped one none).
    """
    keep = mask & (q <= alpha_level_sq(opacity))
    raw = opacity * torch.exp(-0.5 * q)
    alpha = cap_at(raw, ALPHA_MAX)
    return torch.where(keep, alpha, torch.zeros_like(alpha))
