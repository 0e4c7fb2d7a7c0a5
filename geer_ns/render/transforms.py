"""Stage 1: Gaussians to view space and to each Gaussian's canonical (whitened) frame.

Conventions: quaternions are wxyz and are normalized here; the camera frame is OpenCV's
(x right, y down, z forward); `viewmat` maps world to camera.

A Gaussian is x = R S u + mu with u ~ N(0, I) (paper Eq. B.4). Its canonical frame is reached with
the whitening matrix W = S^-1 R^T, so that the covariance Sigma = R S S^T R^T becomes the identity.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .subgradients import floor_at

# Scales below this are clamped: they would push W = S^-1 R^T past float32's range (1/1e-12 * 1e4 m
# stays far below 3e38 even squared). A 1e-12 scale is already a perfect needle/disk in practice.
MIN_SCALE = 1e-12


def normalize_quats(quats: Tensor) -> Tensor:
    """Unit quaternions [..., 4] from any non-zero ones. Dividing by the largest |component| first keeps
    the norm's squares in range: a float32 quaternion of norm 1e19 (or 1e-25) normalizes exactly."""
    tiny = torch.finfo(quats.dtype).tiny
    q = quats / quats.abs().amax(dim=-1, keepdim=True).clamp_min(tiny)
    return q / q.norm(dim=-1, keepdim=True).clamp_min(tiny)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] from quaternions [..., 4] (wxyz, any norm)."""
    q = normalize_quats(quats)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def view_transform(means: Tensor, viewmat: Tensor) -> Tensor:
    """means_c = R_c mu + t [N, 3], computed in float64 and returned in means' dtype.

    Far from the origin R_c mu and t are two large, nearly opposite numbers: in float32 a scene at 1e4
    loses ~1e-3 of its view-space position (the cancellation), in float64 the result is correctly rounded.
    """
    vm = viewmat.to(torch.float64)
    m = means.to(torch.float64)
    # Written out, not a matmul: a BLAS kernel rounds a row by where it falls in its blocks (FMA in the body, not
    # at the edges), so the same Gaussian would get other bits in another tensor (a shard, a subset); every
    # element here is the same IEEE operations in the same order wherever it sits.
    rot = vm[:3, :3]
    out = m[:, 0:1] * rot[:, 0] + m[:, 1:2] * rot[:, 1] + m[:, 2:3] * rot[:, 2] + vm[:3, 3]
    return out.to(means.dtype)


def world_to_camera_opencv(camera_to_world: Tensor) -> Tensor:
    """nerfstudio c2w [3,4] (OpenGL axes) -> world-to-camera [4,4] with OpenCV axes (x right, y down, z fwd)."""
    rot = camera_to_world[:3, :3] * camera_to_world.new_tensor([1.0, -1.0, -1.0])
    viewmat = torch.eye(4, dtype=camera_to_world.dtype, device=camera_to_world.device)
    viewmat[:3, :3] = rot.T
    viewmat[:3, 3] = -rot.T @ camera_to_world[:3, 3]
    return viewmat


def camera_offsets(means: Tensor, viewmat: Tensor) -> Tensor:
    """mu - camera center [N, 3] in world axes (SH view directions), in float64 for the same reason."""
    vm = viewmat.to(torch.float64)
    center = -vm[:3, :3].T @ vm[:3, 3]
    return (means.to(torch.float64) - center).to(means.dtype)


def view_rotations(quats: Tensor, viewmat: Tensor, dtype: torch.dtype) -> Tensor:
    """R_v = R_c R(q) [N, 3, 3] in float64, with R_c rounded to `dtype` first (the kernels read it so)."""
    return viewmat[:3, :3].to(dtype).to(torch.float64) @ quat_to_rotmat(quats.to(torch.float64))


def to_view_space(means: Tensor, quats: Tensor, viewmat: Tensor) -> tuple[Tensor, Tensor]:
    """View-space means [N, 3] and view-space rotations R_v = R_c R [N, 3, 3] (made in float64, in means' dtype)."""
    return view_transform(means, viewmat), view_rotations(quats, viewmat, means.dtype).to(means.dtype)


def canonical_frame(means_c: Tensor, quats: Tensor, scales: Tensor, viewmat: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Each Gaussian's frame for one view: (R_v [N, 3, 3], W = S^-1 R_v^T [N, 3, 3], o_u = -W mu_c [N, 3]), made in
    float64 and returned in means_c's dtype (differentiable; geer_math.h canonical_frame is the kernels' twin).

    Why float64: the squared distance q = D^2 that every pair is kept or skipped on is ill-conditioned in W and o_u
    (by ~|o_u|^2 / D^2), and the roundings of a float32 chain move it by ~1e-6 relative, enough to put a pair on
    the other side of the 1/255 threshold (docs/cuda.md, "The frame in float64"). Rounded once, W and o_u are
    as exact as float32 can hold them; the per-Gaussian cost is negligible.
    """
    rot_v = view_rotations(quats, viewmat, means_c.dtype)
    w = whitening(rot_v, scales.to(torch.float64))
    o_u = -torch.einsum("nij,nj->ni", w, means_c.to(torch.float64))
    return rot_v.to(means_c.dtype), w.to(means_c.dtype), o_u.to(means_c.dtype)


def whitening(rot_v: Tensor, scales: Tensor) -> Tensor:
    """W = S^-1 R_v^T [N, 3, 3]: maps view-space offsets into the canonical frame."""
    inv_s = 1.0 / floor_at(scales, MIN_SCALE)  # no gradient at or below MIN_SCALE
    return inv_s[:, :, None] * rot_v.transpose(-1, -2)


def covariance_factor(rot_v: Tensor, scales: Tensor) -> Tensor:
    """M = R_v S [N, 3, 3], with view-space covariance Sigma_c = M M^T (kept factored for stability)."""
    return rot_v * floor_at(scales, MIN_SCALE)[:, None, :]
