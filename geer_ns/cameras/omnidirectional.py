"""Wide-angle models that are not theta-space fisheyes: COLMAP FOV and the Mei unified omnidirectional model."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from geer_ns.cameras.base import _is_zero, _safe_norm
from geer_ns.cameras.lens import _CentralLens, _radtan


@dataclass(frozen=True)
class FOVCamera(_CentralLens):
    """COLMAP FOV model (Devernay & Faugeras): r_d = atan(2 tan(omega/2) tan(theta)) / omega.

    Written with atan2 so it continues past 90 degrees; then theta -> r_d is increasing on [0, pi), so
    ``max_angle`` = pi for omega > 0 (COLMAP itself only projects z > 0). omega = 0 is the pinhole limit
    (``max_angle`` = pi/2). Requires 0 <= omega < pi.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    omega: float = 0.0

    _positive_fields: ClassVar[tuple[str, ...]] = ("fx", "fy")

    def _check_params(self) -> None:
        if not 0.0 <= self.omega < math.pi:
            raise ValueError(f"FOVCamera.omega must be in [0, pi), got {self.omega!r}")

    def _cap(self) -> float:
        return math.pi if self.omega > 0 else math.pi / 2

    def _ideal_radius(self, theta: Tensor) -> Tensor:
        if _is_zero(self.omega):
            return torch.tan(theta)
        a = 2 * torch.tan(torch.as_tensor(self.omega / 2, dtype=theta.dtype))  # a tensor while refined
        return torch.atan2(a * torch.sin(theta), torch.cos(theta)) / self.omega

    def _ideal_inverse(self, s: Tensor) -> Tensor:
        if self.omega == 0:
            return torch.atan(s)
        a = 2 * math.tan(self.omega / 2)
        w = torch.clamp(s * self.omega, max=math.pi)  # beyond pi is outside the model (invalid anyway)
        return torch.atan2(torch.sin(w), a * torch.cos(w))


# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MeiCamera(_CentralLens):
    """Mei unified omnidirectional model as in cv2.omnidir.

    X_s = P/|P|, q = (X_s.x, X_s.y) / (X_s.z + xi), then OpenCV radial-tangential (k1, k2, p1, p2) on q,
    then u = fx d_x + skew d_y + cx, v = fy d_y + cy. The ideal projection ends at acos(-xi) for xi <= 1
    (pole) and turns back at acos(-1/xi) for xi > 1; distortion can lower ``max_angle`` further.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    xi: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    skew: float = 0.0  # type: ignore[assignment]

    _positive_fields: ClassVar[tuple[str, ...]] = ("fx", "fy")

    def _check_params(self) -> None:
        if self.xi < 0:
            raise ValueError(f"MeiCamera.xi must be >= 0, got {self.xi!r}")

    @property
    def _nonradial(self) -> bool:  # type: ignore[override]
        return not (_is_zero(self.p1) and _is_zero(self.p2))

    def _cap(self) -> float:
        return math.acos(-self.xi) if self.xi < 1 else math.pi

    def _ideal_radius(self, theta: Tensor) -> Tensor:
        return torch.sin(theta) / (torch.cos(theta) + self.xi)

    def _ideal_inverse(self, s: Tensor) -> Tensor:  # used only through _dirs_from_ideal below
        lam = self._lift(s)
        return torch.atan2(lam * s, lam - self.xi)

    def _lift(self, s: Tensor) -> Tensor:
        """Scale mapping (q, 1) onto the unit sphere shifted by xi (standard Mei lifting)."""
        disc = torch.clamp(1 + (1 - self.xi**2) * s * s, min=0)
        return (self.xi + torch.sqrt(disc)) / (1 + s * s)

    def _radial_coeffs(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        return (self.k1, self.k2), ()

    def _distort(self, q: Tensor) -> Tensor:
        out = q * self._radial_factor(_safe_norm(q)).unsqueeze(-1)
        return out + _radtan(q, self.p1, self.p2) if self._nonradial else out

    def _ideal_point(self, points: Tensor) -> tuple[Tensor, Tensor]:
        n = _safe_norm(points)
        theta = torch.atan2(_safe_norm(points[..., :2]), points[..., 2])
        valid = (theta < self.max_angle) & ((points * points).sum(-1) > 0)
        den = points[..., 2] + self.xi * n
        den = torch.where(valid, den, torch.ones_like(den))
        q = points[..., :2] / den.unsqueeze(-1)
        return torch.where(valid.unsqueeze(-1), q, torch.zeros_like(q)), valid

    def _dirs_from_ideal(self, q: Tensor) -> tuple[Tensor, Tensor]:
        s = _safe_norm(q)
        lam = self._lift(s)
        dirs = torch.cat([lam.unsqueeze(-1) * q, (lam - self.xi).unsqueeze(-1)], dim=-1)
        dirs = dirs / _safe_norm(dirs).unsqueeze(-1)
        disc_ok = 1 + (1 - self.xi**2) * s * s >= 0
        theta = torch.atan2(_safe_norm(dirs[..., :2]), dirs[..., 2])
        return dirs, disc_ok & (theta < self.max_angle)
