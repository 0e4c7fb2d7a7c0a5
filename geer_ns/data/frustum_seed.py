"""Seed points for a dataset without a point cloud: random points inside the camera frusta.

splatfacto's fallback (50k points uniform in a 10-unit cube) puts most Gaussians where no camera looks and
costs every step for them. Here each camera gets an equal share of points along its own valid pixel rays
(fisheye rays beyond 90 degrees included), at depths log-uniform between `near` and `far` times the scene
size (the largest distance of a camera from the cameras' centroid, at least 1 in nerfstudio's scaled
units), so every point is seen by at least one camera. The count grows with the number of cameras and
is capped: a few thousand per camera fit a start without SfM points.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence, Tuple

import torch

from geer_ns.cameras import CameraModel

POINTS_PER_CAMERA = 1000
MIN_POINTS, MAX_POINTS = 2000, 20000


def seed_count(n_cameras: int) -> int:
    return int(min(MAX_POINTS, max(MIN_POINTS, POINTS_PER_CAMERA * n_cameras)))


def frustum_points(
    cameras: Sequence[CameraModel],
    camera_to_worlds: torch.Tensor,
    count: int,
    near: float = 0.05,
    far: float = 2.0,
    seed: int = 0,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """(xyz float32 [count, 3], rgb uint8 [count, 3] mid-gray) inside the frusta.

    camera_to_worlds [N, 3, 4] are nerfstudio's (OpenGL camera axes); the camera models use OpenCV's.
    """
    gen = torch.Generator().manual_seed(seed)
    c2w = camera_to_worlds.double()
    centers = c2w[:, :3, 3]
    extent = max(1.0, float((centers - centers.mean(0)).norm(dim=-1).max()))
    per = [count // len(cameras) + (i < count % len(cameras)) for i in range(len(cameras))]
    points = []
    for cam, pose, n in zip(cameras, c2w, per):
        dirs = _random_rays(cam, n, gen)
        depth = torch.exp(math.log(near * extent) + math.log(far / near) * torch.rand(len(dirs), generator=gen,
                                                                                      dtype=torch.float64))
        local = dirs * depth[:, None] * dirs.new_tensor([1.0, -1.0, -1.0])  # OpenCV -> OpenGL camera axes
        points.append(local @ pose[:, :3].T + pose[:, 3])
    xyz = torch.cat(points).float()
    return xyz, torch.full_like(xyz, 128, dtype=torch.uint8)


def _random_rays(cam: CameraModel, n: int, gen: torch.Generator) -> torch.Tensor:
    """n unit rays [n, 3] (OpenCV axes) through uniformly random valid pixels of the camera."""
    unproject: Callable = cam.unproject
    found = []
    total = 0
    for _ in range(20):  # rejection of invalid pixels (outside a fisheye's circle); 20 rounds suffice
        uv = torch.rand(2 * n + 16, 2, generator=gen, dtype=torch.float64) * torch.tensor(
            [float(cam.width), float(cam.height)], dtype=torch.float64)
        dirs, valid = unproject(uv)
        valid = valid & torch.isfinite(dirs).all(-1)
        dirs = dirs[valid]
        found.append(dirs / dirs.norm(dim=-1, keepdim=True))
        total += len(dirs)
        if total >= n:
            break
    dirs = torch.cat(found)[:n]
    if len(dirs) < n:
        raise ValueError(f"camera {cam}: too few valid pixels to seed points in its frustum")
    return dirs
