"""Rays that do not all leave from one pose: a rolling-shutter view, each ray at its own time.

A view is rendered in the camera frame of one reference pose (its viewmat). A ray taken at another pose starts at
that pose's camera centre and points along the grid's direction turned by that pose's rotation; both are given in
the reference frame (`MovingRays`). The renderer evaluates each such ray exactly (transmittance.py
moving_ray_response, csrc/geer_ray.h eval_pair<kOrigin>); what the association needs is a bound.

The bound. The tiles and the per-ray cull take the rays' own directions (`tile_grid`: the grid's pixels and tiles,
the moved directions' angular bounds), so the rotations cost nothing. The origins remain: the ray (o, d) meets a
Gaussian G exactly when the ray d from the camera centre meets G - o, which lies in E (+) B(offset) (E: G's
lambda-ellipsoid, semi-axes a_i = lambda s_i; offset: the largest |o|), and that lies in the ellipsoid with
semi-axes c_i^2 = (1 + 1/p) a_i^2 + (1 + p) offset^2 for any p > 0 (support functions and Young's inequality;
docs/rolling_shutter.md). The association and the per-ray cull therefore run on Gaussians with scales
c_i / lambda (same mean, rotation, opacity): complete, and exactly a global-shutter view's bounds when no ray moves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from .cones import gaussian_cone_form
from .pbf import PBF, compute_pbf, pbf_lambda_sq
from .raygrid import RayGrid
from .transforms import MIN_SCALE, canonical_frame, covariance_factor


@dataclass
class MovingRays:
    """Each ray's origin and direction in the camera frame of the view's viewmat, where they differ from the
    grid's (camera centre, grid.dirs): origins [R,3], dirs [R,3] unit. `offset` bounds every |origin| (the
    association is complete for rays within it: module docstring). Gradients flow to origins and dirs."""

    origins: Tensor
    dirs: Tensor
    offset: float
    _tiles: RayGrid | None = field(default=None, init=False, repr=False, compare=False)

    def check(self, rays: int, like: Tensor) -> None:
        """ValueError unless origins and dirs are [rays, 3] on like's device, and offset finite >= 0."""
        for name, t in (("origins", self.origins), ("dirs", self.dirs)):
            if not isinstance(t, Tensor) or tuple(t.shape) != (rays, 3):
                got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
                raise ValueError(f"motion.{name}: expected [{rays}, 3] (one per ray of the grid), got {got}")
            if t.device != like.device:
                raise ValueError(f"motion.{name}: expected on {like.device}, got {t.device}")
        if not (float(self.offset) >= 0.0 and float(self.offset) < float("inf")):
            raise ValueError(f"motion.offset: expected a finite value >= 0, got {self.offset}")
        farthest = float(self.origins.detach().norm(dim=-1).max()) if rays else 0.0
        if farthest > float(self.offset) * (1.0 + 1e-6):  # the association's bound would not hold
            raise ValueError(f"motion.offset: {self.offset} is below the farthest origin's distance {farthest}")

    def tile_grid(self, grid: RayGrid) -> RayGrid:
        """`grid`'s pixels, tiles and validity with these rays' directions: what the association and the per-ray
        cull test (made once per MovingRays)."""
        if self._tiles is None:
            dirs = self.dirs.detach().reshape(grid.height, grid.width, 3)
            self._tiles = RayGrid.from_rays(dirs, grid.valid.reshape(grid.height, grid.width), grid.tile_size)
        return self._tiles


def motion_scales(scales: Tensor, lam2: Tensor, offset: float) -> Tensor:
    """[N,3] scales whose lambda-ellipsoid (lam2 [N], pbf.pbf_lambda_sq) contains each Gaussian's moved by up to
    `offset` (module docstring); scales [N,3]. No gradient: a bound for the association."""
    with torch.no_grad():
        lam = lam2.clamp_min(1e-6).sqrt()[:, None]  # 1e-6: Gaussians below 1/255 (never alive) stay finite
        a = scales.clamp_min(MIN_SCALE) * lam
        if offset <= 0.0:
            return a / lam
        # semi-axes^2 (1 + 1/p) a_i^2 + (1 + p) offset^2 for any p > 0; p = |a| / (sqrt(3) offset) minimises their sum
        p = a.norm(dim=-1, keepdim=True) / (math.sqrt(3.0) * offset)
        return torch.sqrt((1.0 + 1.0 / p) * a * a + (1.0 + p) * offset * offset) / lam


def motion_pbf(means_c: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, lambda_mode: str,
               motion: MovingRays) -> PBF:
    """The PyTorch renderer's PBF (with its cone form) for `motion`'s rays: pbf.compute_pbf of the Gaussians with
    motion_scales (means_c [N,3] in the reference camera frame, quats [N,4], scales [N,3], opacities [N], viewmat
    [4,4] the reference pose). No gradient."""
    with torch.no_grad():
        lam2, alive = pbf_lambda_sq(opacities.detach(), lambda_mode)
        scales_m = motion_scales(scales.detach(), lam2, motion.offset)
        rot_v, w, o_u = canonical_frame(means_c.detach(), quats.detach(), scales_m, viewmat.detach())
        pbf = compute_pbf(means_c.detach(), covariance_factor(rot_v, scales_m), lam2, alive, o_u)
        pbf.cone = gaussian_cone_form(w, o_u, lam2, pbf.camera_inside)
        return pbf
