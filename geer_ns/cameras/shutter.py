"""Rolling shutters: when each ray of an image was taken, and from which pose.

A rolling-shutter sensor reads its rows (or columns) one after the other; an image carries the camera's pose at the
start and at the end of the readout (gsplat's convention), and a pixel's time is its position along the readout
direction on the *sensor*, i.e. in the raw image, before any undistortion or resampling. A ray of any grid
(native pixels or BEAP cells) gets its time by projecting its direction through the camera model to the sensor.
The pose at time s in [0, 1] interpolates the two: rotation along the geodesic (R0 exp(s log(R0^T R1))),
camera centre linearly. Rays are then expressed in the camera frame of the pose at mid-readout, the image's own
pose for everything that shows the static scene (viewer, exports): what render/moving.MovingRays takes.
Conventions and file fields: docs/rolling_shutter.md.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .base import CameraModel

READOUTS = ("top-to-bottom", "bottom-to-top", "left-to-right", "right-to-left")
# Relative slack on the motion bounds: the renderer's rounding of the rays, far below any motion that matters.
_BOUND_SLACK = 1e-6


def check_readout(readout: str, where: str = "readout") -> str:
    """`readout` if it is one of READOUTS, else ValueError naming `where`."""
    if readout not in READOUTS:
        raise ValueError(f"{where}: expected one of {', '.join(READOUTS)}, got {readout!r}")
    return readout


def sensor_times(pixels: Tensor, width: int, height: int, readout: str) -> Tensor:
    """[...] readout fraction in [0, 1] of sensor pixels [..., 2] (u, v), pixel centres at (j + 0.5, i + 0.5): the
    first row (column) read is at 0, the last at 1, linear in between."""
    check_readout(readout)
    along_rows = readout in ("top-to-bottom", "bottom-to-top")
    coord, size = (pixels[..., 1], height) if along_rows else (pixels[..., 0], width)
    s = ((coord - 0.5) / max(size - 1, 1)).clamp(0.0, 1.0)
    return 1.0 - s if readout in ("bottom-to-top", "right-to-left") else s


def ray_times(camera: CameraModel, dirs: Tensor, readout: str) -> Tensor:
    """[R] readout fraction of each ray dirs [R, 3] (camera frame): its sensor pixel's (sensor_times). A ray the
    model cannot project (outside its field of view: an invalid ray) gets mid-readout."""
    pixels, valid = camera.project(dirs.detach().double())
    times = sensor_times(pixels, camera.width, camera.height, readout)
    return torch.where(valid, times, torch.full_like(times, 0.5)).to(dirs.dtype)


# ------------------------------------------------------------------------------------------ SO(3)
def _rotation_to_quaternion(r: Tensor) -> Tensor:
    """[..., 4] unit quaternion (w, x, y, z), w >= 0, of rotation matrices [..., 3, 3] (the largest-pivot branch)."""
    m = r
    t = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = torch.stack([
        torch.stack([1 + t, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + 2 * m[..., 0, 0] - t, m[..., 0, 1] + m[..., 1, 0],
                     m[..., 0, 2] + m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 + 2 * m[..., 1, 1] - t,
                     m[..., 1, 2] + m[..., 2, 1]], -1),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                     1 + 2 * m[..., 2, 2] - t], -1),
    ], -2)  # [..., 4, 4]: row k is 4 q_k q (q_k the pivot component)
    pivot = torch.stack([t, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1).argmax(-1)
    q = torch.gather(cands, -2, pivot[..., None, None].expand(*pivot.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def so3_log(r: Tensor) -> Tensor:
    """[..., 3] rotation vector of rotation matrices [..., 3, 3] (angle in [0, pi]); differentiable, also at 0."""
    q = _rotation_to_quaternion(r)
    w, v = q[..., 0], q[..., 1:]
    n = v.norm(dim=-1)
    small = n < 1e-6
    safe_n = torch.where(small, torch.ones_like(n), n)
    # angle / |v| = 2 atan2(|v|, w) / |v|, whose limit at |v| -> 0 is 2 / w (w -> 1)
    factor = torch.where(small, 2.0 / w * (1.0 - n * n / (3.0 * w * w)), 2.0 * torch.atan2(n, w) / safe_n)
    return v * factor[..., None]


def so3_exp(omega: Tensor) -> Tensor:
    """[..., 3, 3] rotation matrices of rotation vectors [..., 3] (Rodrigues, series near 0)."""
    theta2 = (omega * omega).sum(-1)
    theta = theta2.clamp_min(0).sqrt()
    small = theta < 1e-4
    safe = torch.where(small, torch.ones_like(theta), theta)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(safe) / safe)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(safe)) / (safe * safe))
    x, y, z = omega.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1), torch.stack([-y, x, zero], -1)], -2)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


# ------------------------------------------------------------------------------------------ poses
def interpolate_poses(c2w_start: Tensor, c2w_end: Tensor, times: Tensor) -> tuple[Tensor, Tensor]:
    """(rotations [..., 3, 3], centres [..., 3]) of the camera-to-world poses at readout fractions `times` [...]
    between c2w_start and c2w_end ([3, 4] or [4, 4], OpenCV axes): R0 exp(s log(R0^T R1)), (1 - s) c0 + s c1."""
    r0, r1 = c2w_start[:3, :3], c2w_end[:3, :3]
    c0, c1 = c2w_start[:3, 3], c2w_end[:3, 3]
    omega = so3_log(r0.transpose(0, 1) @ r1)
    s = times[..., None]
    return r0 @ so3_exp(s * omega), (1.0 - s) * c0 + s * c1


def rolling_rays(dirs: Tensor, times: Tensor, c2w_start: Tensor,
                 c2w_end: Tensor) -> tuple[Tensor, Tensor, Tensor, float]:
    """A rolling-shutter image's rays: (world-to-camera viewmat [4, 4] of the mid-readout pose, and in its camera
    frame each ray's origin [R, 3] and direction [R, 3], and a bound on every origin's distance from the mid-readout
    centre: render.moving.MovingRays' fields). dirs [R, 3] the grid's directions (camera frame), times [R] their
    readout fractions (ray_times), c2w_start / c2w_end the poses at the start and end of the readout ([3, 4] or
    [4, 4]). Differentiable w.r.t. both poses."""
    rot, centre = interpolate_poses(c2w_start, c2w_end, times)
    r_mid, c_mid = interpolate_poses(c2w_start, c2w_end, times.new_full((), 0.5))
    to_mid = r_mid.transpose(0, 1)
    moved = torch.einsum("ij,rjk,rk->ri", to_mid, rot, dirs.to(rot.dtype))
    origins = (centre - c_mid) @ to_mid.transpose(0, 1)
    # From the poses (not the rays: a bound for every time in [0, 1]): the centre at time s is |s - 0.5| times its
    # path from the mid-readout one.
    with torch.no_grad():
        offset = float((c2w_end[:3, 3] - c2w_start[:3, 3]).norm()) * 0.5 * (1.0 + _BOUND_SLACK)
    viewmat = torch.eye(4, dtype=rot.dtype, device=rot.device)
    viewmat = torch.cat([torch.cat([to_mid, -(to_mid @ c_mid)[:, None]], 1), viewmat[3:]], 0)
    return viewmat, origins, moved, offset + 1e-12
