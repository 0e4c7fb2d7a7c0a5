"""PBF angular bounds (Eq. 10, D.1-D.6) and the lambda rule, against sampled ellipsoids.

Reference: points sampled densely on the lambda-ellipsoid surface in float64; the angles atan2(x, z) and
atan2(y, z) of those points, unwrapped around the mean's direction, must lie inside the bound, and their
extremes must come close to it (the bound is tight, not just safe).
"""

from __future__ import annotations

import math

import pytest
import torch

from conftest import random_scene
from geer_ns.render import compute_pbf, mirror_tangent, pbf_lambda_sq
from geer_ns.render.transforms import covariance_factor, to_view_space, whitening


def _surface_angles(means_c, factor, lam2, n=4000, seed=0):
    gen = torch.Generator().manual_seed(seed)
    u = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    u = u / u.norm(dim=-1, keepdim=True)
    pts = means_c[:, None, :] + torch.sqrt(lam2)[:, None, None] * torch.einsum("nij,pj->npi", factor, u)
    x, y, z = pts.unbind(-1)
    return torch.atan2(x, z), torch.atan2(y, z)


def _unwrap_around(ang, centre):
    return centre[:, None] + torch.remainder(ang - centre[:, None] + math.pi, 2 * math.pi) - math.pi


def _bounds(seed, around, n=300):
    means, quats, scales, opac, _ = random_scene(n, seed, around=around, scale_range=(1e-3, 0.6))
    means_c, rot_v = to_view_space(means, quats, torch.eye(4, dtype=torch.float64))
    lam2, alive = pbf_lambda_sq(opac)
    w = whitening(rot_v, scales)
    o_u = -torch.einsum("nij,nj->ni", w, means_c)
    factor = covariance_factor(rot_v, scales)
    return means_c, factor, lam2, compute_pbf(means_c, factor, lam2, alive, o_u)


@pytest.mark.parametrize("around", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pbf_contains_and_is_tight(seed, around):
    means_c, factor, lam2, pbf = _bounds(seed, around)
    theta, phi = _surface_angles(means_c, factor, lam2)
    for ang, lo, hi, centre in (
        (theta, pbf.theta_lo, pbf.theta_hi, torch.atan2(means_c[:, 0], means_c[:, 2])),
        (phi, pbf.phi_lo, pbf.phi_hi, torch.atan2(means_c[:, 1], means_c[:, 2])),
    ):
        full = (lo <= -math.pi + 1e-12) & (hi >= math.pi - 1e-12)
        a = _unwrap_around(ang, centre)
        inside = (a >= lo[:, None] - 1e-9) & (a <= hi[:, None] + 1e-9)
        assert inside[~full].all(), "a point of the ellipsoid lies outside its PBF"
        # Tight: the sampled extremes reach the bound to within the sampling density.
        gap = torch.maximum(a.amin(1) - lo, hi - a.amax(1))[~full]
        assert gap.max() < 0.05 * (hi - lo)[~full].max()
        # The bounded interval must be shorter than pi unless it is the full range.
        assert ((hi - lo)[~full] < math.pi).all()
    assert ((pbf.theta_lo > -math.pi) | pbf.camera_inside | True).all()


def test_camera_inside_gets_full_range():
    """The camera at the centre of a Gaussian: bounds are the whole sphere, never a cull."""
    means = torch.tensor([[0.0, 0.0, 0.05], [0.0, 0.0, 3.0]], dtype=torch.float64)
    scales = torch.tensor([[0.5, 0.2, 0.3], [0.1, 0.1, 0.1]], dtype=torch.float64)
    rot_v = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    lam2, alive = pbf_lambda_sq(torch.tensor([0.9, 0.9], dtype=torch.float64))
    w = whitening(rot_v, scales)
    o_u = -torch.einsum("nij,nj->ni", w, means)
    pbf = compute_pbf(means, covariance_factor(rot_v, scales), lam2, alive, o_u)
    assert pbf.camera_inside.tolist() == [True, False]
    assert pbf.theta_lo[0] == -math.pi and pbf.theta_hi[0] == math.pi
    assert pbf.phi_lo[0] == -math.pi and pbf.phi_hi[0] == math.pi
    assert pbf.theta_hi[1] - pbf.theta_lo[1] < 0.5


def test_lambda_rule_is_exact_alpha_threshold():
    """sigma exp(-lambda^2/2) == 1/255 for the opacity-aware rule; faint Gaussians are culled."""
    sigma = torch.tensor([0.001, 1 / 255 - 1e-6, 0.01, 0.35, 0.9, 1.0], dtype=torch.float64)
    lam2, alive = pbf_lambda_sq(sigma, "opacity")
    assert alive.tolist() == [False, False, True, True, True, True]
    # Slack aside (relative 1e-3), alpha at the contour is exactly 1/255.
    at_contour = sigma[alive] * torch.exp(-0.5 * (lam2[alive] - 1e-4) / (1 + 1e-3))
    assert torch.allclose(at_contour, torch.full_like(at_contour, 1 / 255), rtol=1e-9)
    paper, _ = pbf_lambda_sq(sigma, "paper")
    # The paper's lambda = 3 is too small for sigma > e^4.5 / 255 ~ 0.35 and too large below.
    assert (lam2[4:] > paper[4:]).all() and (lam2[2] < paper[2])


def test_mirror_tangent_orders_wide_angles():
    theta = torch.linspace(-math.pi, math.pi, 721, dtype=torch.float64)
    m = mirror_tangent(theta, 1.0)
    assert (m[1:] > m[:-1]).all()
    assert m[0] == -math.inf and m[-1] == math.inf
    # Plain tangents (xi = 0) are not ordered beyond 90 degrees: what D.2 fixes.
    t = mirror_tangent(theta[1:-1], 0.0)
    assert not (t[1:] > t[:-1]).all()
