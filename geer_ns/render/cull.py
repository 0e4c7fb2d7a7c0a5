"""The Gaussians a view can list at all: a cheap, conservative test before a render's per-Gaussian work.

The association lists a Gaussian in a tile only where its PBF (the angular box of its lambda-ellipsoid, pbf.py)
overlaps the tile's box, and every active tile lies inside the tile pyramid's top node (raygrid.TilePyramid). The
lambda-ellipsoid lies in the ball of radius lambda x its largest scale around its mean; seen from the camera,
the ball's angular intervals (in the xz- and yz-planes, as the PBF's) contain the ellipsoid's, those of a subset.
A Gaussian whose ball misses the top node is therefore never listed: it adds nothing to the view's image, gets no
gradient from it and no densification record. Rendering only the other rows (the model gathers them) gives the
same image, gradients and records, for O(N) work of a few operations per Gaussian instead of the preprocess,
the association's set-up and the densification probe of every Gaussian. A view that sees a tenth of the scene
then costs about a tenth (benchmarks/skip_unneeded.md).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .associate import _interval_pieces, _overlaps
from .pbf import ALPHA_MIN, LambdaMode, pbf_lambda_sq
from .raygrid import RayGrid
from .transforms import view_transform

# Margins that keep the test conservative against the renderer's own rounding (its activations in float64, its
# PBF in float32): a larger ball, wider intervals and a lower opacity floor than the renderer's.
_REACH_SLACK = 1e-3
_ANGLE_SLACK = 1e-5
_ALPHA_SLACK = 1e-4


@torch.no_grad()
def view_rows(means: Tensor, largest_scales: Tensor, opacities: Tensor, viewmat: Tensor, grid: RayGrid,
              lambda_mode: LambdaMode = "opacity") -> Tensor:
    """[K] long, ascending: the rows whose Gaussians the view's association may list (module docstring).

    Args:
        means: [N, 3] world positions; largest_scales: [N] each Gaussian's largest scale (> 0);
        opacities: [N] in [0, 1]; viewmat: [4, 4] world-to-camera (OpenCV axes); grid: the view's rays.
    Returns:
        the row indices on means' device; every row whose Gaussian a render of the view lists is among them.
    """
    device = means.device
    pyramid = grid.to(device).tile_pyramid(torch.float64)
    top = pyramid.bounds[-1]
    sigma = opacities.detach().double()
    alive = sigma >= ALPHA_MIN * (1.0 - _ALPHA_SLACK)
    lam2, _ = pbf_lambda_sq(sigma.clamp_min(ALPHA_MIN), lambda_mode)
    reach = torch.sqrt(lam2) * largest_scales.detach().double() * (1.0 + _REACH_SLACK)
    x, y, z = view_transform(means.detach().double(), viewmat.to(device)).unbind(-1)
    inside = x * x + y * y + z * z <= reach * reach
    theta = _ball_interval(x, z, reach, inside)
    phi = _ball_interval(y, z, reach, inside)
    hit = _overlaps(top[0], top[1], theta) & _overlaps(top[2], top[3], phi)
    return torch.nonzero(alive & hit & pyramid.active[-1]).squeeze(1)


def _ball_interval(a: Tensor, z: Tensor, reach: Tensor, full: Tensor):
    """Mirror-domain pieces (associate._interval_pieces) of the angle atan2(a, z) interval of a disk of radius
    `reach` around (a, z) seen from the origin of the (a, z) plane; the whole circle where the origin is in the
    disk or `full`."""
    rho = torch.sqrt(a * a + z * z)
    center = torch.atan2(a, z)
    half = torch.asin((reach / rho.clamp_min(torch.finfo(rho.dtype).tiny)).clamp(max=1.0)) + _ANGLE_SLACK
    whole = full | (rho <= reach)
    lo = torch.where(whole, torch.full_like(center, -math.pi), center - half)
    hi = torch.where(whole, torch.full_like(center, math.pi), center + half)
    return _interval_pieces(lo, hi, 1.0)
