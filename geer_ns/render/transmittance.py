"""Stage 4: exact ray-Gaussian transmittance (paper Eq. B.7-B.9, Theorem 1).

In a Gaussian's canonical frame the ray is r_u(t) = o_u + t d_u with o_u = W (o - mu), d_u = W d, and the
integral of the isotropic density along it (the Jacobian absorbed into the measure, Eq. B.5) is
exp(-D^2 / 2) with D = |o_u x d_u| / |d_u| the distance from the centre to the ray. D is evaluated in
exactly that cross-product form, with d_u normalised first: the expanded |o|^2 |d|^2 - (o.d)^2 (Eq. C.16)
cancels catastrophically for needles, disks and far-away Gaussians (paper App. C.7), and squaring
|o_u x d_u| before normalising would overflow float32 for 1e-8 scales at 1e4 m.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .pbf import ALPHA_MIN

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
    """Squared canonical distance D^2 and the ray parameter of maximum response t*.

    o_u [..., K, 3] camera centre in each Gaussian's canonical frame, w [..., K, 3, 3] whitening matrices,
    dirs [..., P, 3] unit ray directions (camera frame). Returns D^2 and t* of shape [..., P, K]; t* is the
    distance along the unit ray to the point of maximum response (negative: behind the camera).
    """
    frame = ray_frame(o_u, w)  # [..., K, 7, 3]
    rows = frame.flatten(-3, -2) @ dirs.transpose(-1, -2)  # [..., K*7, P]
    rows = rows.unflatten(-2, (frame.shape[-3], 7)).transpose(-1, -3)  # [..., P, 7, K]
    d_u, moment, along = rows[..., 0:3, :], rows[..., 3:6, :], rows[..., 6, :]
    inv_norm = torch.rsqrt((d_u * d_u).sum(-2).clamp_min(torch.finfo(d_u.dtype).tiny))
    m_hat = moment * inv_norm[..., None, :]  # normalise before squaring: no overflow for 1e-8 scales
    dist_sq = (m_hat * m_hat).sum(-2)
    t_star = -along * inv_norm * inv_norm
    return dist_sq, t_star


def pair_alpha(
    dist_sq: Tensor, t_star: Tensor, opacity: Tensor, camera_inside: Tensor, mask: Tensor
) -> Tensor:
    """Compositing alpha of each (ray, Gaussian) pair, 0 for pairs that do not contribute.

    alpha = min(0.99, sigma exp(-D^2/2)), skipped below 1/255. A pair contributes only if its point
    of maximum response is in front of the camera (t* > 0) or the camera is inside the Gaussian's
    PBF ellipsoid: the PBF bounds half-lines, and with the camera outside the ellipsoid a half-line
    with t* <= 0 has D above the bound, so the gate never cuts a visible response.
    """
    alpha = (opacity * torch.exp(-0.5 * dist_sq)).clamp_max(ALPHA_MAX)
    keep = mask & (alpha >= ALPHA_MIN) & ((t_star > 0) | camera_inside)
    return torch.where(keep, alpha, torch.zeros_like(alpha))
