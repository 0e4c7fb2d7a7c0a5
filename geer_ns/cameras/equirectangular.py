"""Full-sphere equirectangular panorama (COLMAP and nerfstudio EQUIRECTANGULAR)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from geer_ns.cameras.base import CameraModel, _float_dtype


@dataclass(frozen=True)
class EquirectangularCamera(CameraModel):
    """Full-sphere equirectangular panorama; x = longitude, y = latitude.

    longitude = 2 pi (u / W - 0.5) (0 straight ahead, +x to the right),
    latitude = pi (0.5 - v / H) (+pi/2 = up = -y):
    direction = (cos lat sin lon, -sin lat, cos lat cos lon).
    This is COLMAP's EQUIRECTANGULAR and nerfstudio's EQUIRECTANGULAR (with fx = W/2, fy = H,
    cx = W/2, cy = H/2) after converting nerfstudio's OpenGL frame to OpenCV. ``max_angle`` = pi.
    Unprojection is valid for 0 <= v <= H (longitude wraps, so any u is accepted).
    """

    @cached_property
    def max_angle(self) -> float:
        return math.pi

    def project(self, points_cam: Tensor) -> tuple[Tensor, Tensor]:
        p = points_cam.to(_float_dtype(points_cam))
        x, y, z = p.unbind(-1)
        lon = torch.atan2(x, z)
        lat = torch.atan2(-y, torch.sqrt(x * x + z * z))
        u = (lon / (2 * math.pi) + 0.5) * self.width
        v = (0.5 - lat / math.pi) * self.height
        return torch.stack([u, v], dim=-1), (p * p).sum(-1) > 0

    def unproject(self, pixels: Tensor) -> tuple[Tensor, Tensor]:
        px = pixels.to(_float_dtype(pixels))
        finite = torch.isfinite(px).all(-1)
        px = torch.where(finite.unsqueeze(-1), px, torch.zeros_like(px))
        lon = 2 * math.pi * (px[..., 0] / self.width - 0.5)
        lat = math.pi * (0.5 - px[..., 1] / self.height)
        valid = finite & (px[..., 1] >= 0) & (px[..., 1] <= self.height)
        dirs = torch.stack([torch.cos(lat) * torch.sin(lon), -torch.sin(lat), torch.cos(lat) * torch.cos(lon)], -1)
        plus_z = torch.zeros_like(dirs)
        plus_z[..., 2] = 1
        return torch.where(valid.unsqueeze(-1), dirs, plus_z), valid
