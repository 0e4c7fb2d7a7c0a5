"""Perspective camera with OpenCV distortion (COLMAP SIMPLE_PINHOLE ... FULL_OPENCV)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from geer_ns.cameras.base import _is_zero, _safe_norm
from geer_ns.cameras.lens import _CentralLens, _radtan


@dataclass(frozen=True)
class PinholeCamera(_CentralLens):
    """Perspective camera with OpenCV distortion (COLMAP SIMPLE_PINHOLE ... FULL_OPENCV).

    Undistorted point q = (x/z, y/z), r2 = |q|^2,
    d = q * (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3) + tangential(p1, p2).
    ``max_angle`` <= pi/2 (points behind the camera are invalid).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    k6: float = 0.0

    _positive_fields: ClassVar[tuple[str, ...]] = ("fx", "fy")
    _angle_cap: ClassVar[float] = math.pi / 2

    @property
    def _nonradial(self) -> bool:  # type: ignore[override]
        return not (_is_zero(self.p1) and _is_zero(self.p2))

    def _ideal_radius(self, theta: Tensor) -> Tensor:
        return torch.tan(theta)

    def _ideal_inverse(self, s: Tensor) -> Tensor:
        return torch.atan(s)

    def _radial_coeffs(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        return (self.k1, self.k2, self.k3), (self.k4, self.k5, self.k6)

    def _distort(self, q: Tensor) -> Tensor:
        out = q * self._radial_factor(_safe_norm(q)).unsqueeze(-1)
        return out + _radtan(q, self.p1, self.p2) if self._nonradial else out

    def _ideal_point(self, points: Tensor) -> tuple[Tensor, Tensor]:
        # x/z directly: exact, and avoids tan(atan()) round-off.
        z = points[..., 2]
        theta = torch.atan2(_safe_norm(points[..., :2]), z)
        valid = (z > 0) & (theta < self.max_angle)
        z = torch.where(valid, z, torch.ones_like(z))
        q = points[..., :2] / z.unsqueeze(-1)
        if self.max_angle < math.pi / 2:  # keep invalid placeholders inside the monotonic range
            q = torch.where(valid.unsqueeze(-1), q, torch.zeros_like(q))
        return q, valid

    def _dirs_from_ideal(self, q: Tensor) -> tuple[Tensor, Tensor]:
        v = torch.cat([q, torch.ones_like(q[..., :1])], dim=-1)
        n = _safe_norm(v)
        return v / n.unsqueeze(-1), torch.atan(_safe_norm(q)) < self.max_angle
