"""Rendered normals: each Gaussian's shortest axis, turned toward the camera, blended with the render's weights.

The kernels blend three color channels per Gaussian; a normal is three numbers per Gaussian, so the normal
image is one more forward render with the normals in place of the colors (any backend, no kernel of its own).
What the normal means and why it is oriented per Gaussian: docs/outputs.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .backend import Backend
from .order import CompositeOrder
from .pbf import LambdaMode
from .rasterize import render
from .raygrid import RayGrid
from .transforms import quat_to_rotmat


@dataclass
class NormalImages:
    world: Tensor  # [H, W, 3] unit normal in world axes (0 where the ray hit nothing)
    camera: Tensor  # [H, W, 3] the same normal in camera axes (OpenCV: x right, y down, z forward)


def camera_center(viewmat: Tensor) -> Tensor:
    """[3] the camera's position in world coordinates from a world-to-camera matrix [4, 4]."""
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    return -rot.T @ trans


def gaussian_normals(means: Tensor, quats: Tensor, scales: Tensor, center: Tensor) -> Tensor:
    """[N, 3] unit world-frame normals: the rotation's column of each Gaussian's smallest scale, with its sign
    chosen so that it points toward `center` [3] (n . (center - mean) >= 0). quats [N, 4] wxyz, scales [N, 3]."""
    rot = quat_to_rotmat(quats)
    shortest = scales.argmin(dim=-1)
    axis = torch.gather(rot, 2, shortest[:, None, None].expand(-1, 3, 1))[..., 0]
    facing = ((center.to(means.dtype) - means) * axis).sum(-1, keepdim=True)
    return torch.where(facing < 0, -axis, axis)


def blended_normals(normal_sum: Tensor, viewmat: Tensor) -> NormalImages:
    """NormalImages from the blended world normals sum_i w_i n_i [H, W, 3]: normalized per ray (0 where the
    sum vanishes), and rotated into the camera frame by viewmat [4, 4]."""
    length = normal_sum.norm(dim=-1, keepdim=True)
    world = torch.where(length > 0, normal_sum / length.clamp_min(torch.finfo(normal_sum.dtype).tiny), 0.0)
    camera = world @ viewmat[:3, :3].to(world.dtype).T
    return NormalImages(world, camera)


@torch.no_grad()
def render_normals(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    grid: RayGrid,
    *,
    lambda_mode: LambdaMode = "opacity",
    backend: Backend = "auto",
    max_pairs: int = 1 << 20,
    order: CompositeOrder | str | None = None,
) -> NormalImages:
    """The normal images of one view, inputs as rasterize.render's (no colors). Forward only: no loss of geer
    uses normals."""
    normals = gaussian_normals(means, quats, scales, camera_center(viewmat.to(means.dtype)))
    out = render(means, quats, scales, opacities, normals, viewmat, grid, background=None, lambda_mode=lambda_mode,
                 backend=backend, max_pairs=max_pairs, order=order)
    return blended_normals(out.rgb, viewmat)
