"""Theta-space fisheye models (Kannala-Brandt family): OpenCV / equidistant, COLMAP radial and thin-prism
fisheyes, Project Aria FISHEYE624."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from geer_ns.cameras.base import _safe_norm
from geer_ns.cameras.lens import _CentralLens, _radtan


class _ThetaSpaceFisheye(_CentralLens):
    """Fisheye models whose ideal radius is the angle itself (Kannala-Brandt family)."""

    _angle_cap: ClassVar[float] = math.pi

    def _ideal_radius(self, theta: Tensor) -> Tensor:
        return theta

    def _ideal_inverse(self, s: Tensor) -> Tensor:
        return s


@dataclass(frozen=True)
class OpenCVFisheyeCamera(_ThetaSpaceFisheye):
    """Kannala-Brandt / OpenCV fisheye (COLMAP OPENCV_FISHEYE, nerfstudio FISHEYE).

    theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8), d = theta_d * unit azimuth.
    theta = atan2(|xy|, z) so angles beyond 90 degrees are supported (unlike cv2.fisheye / COLMAP, which
    use atan(|xy|/z)); ``max_angle`` is where theta_d stops increasing (pi if it never does).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0

    _positive_fields: ClassVar[tuple[str, ...]] = ("fx", "fy")

    def _radial_coeffs(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        return (self.k1, self.k2, self.k3, self.k4), ()

    @classmethod
    def equidistant(cls, width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> OpenCVFisheyeCamera:
        """Ideal equidistant fisheye r = f * theta."""
        return cls(width, height, fx, fy, cx, cy)


def EquidistantCamera(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> OpenCVFisheyeCamera:
    """Equidistant fisheye (r = f theta): an :class:`OpenCVFisheyeCamera` with zero coefficients."""
    return OpenCVFisheyeCamera.equidistant(width, height, fx, fy, cx, cy)


@dataclass(frozen=True)
class RadialFisheyeCamera(_ThetaSpaceFisheye):
    """COLMAP SIMPLE_RADIAL_FISHEYE (k2 = 0) / RADIAL_FISHEYE: single focal length,
    theta_d = theta (1 + k1 theta^2 + k2 theta^4)."""

    f: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0

    _positive_fields: ClassVar[tuple[str, ...]] = ("f",)

    @property
    def fx(self) -> float:  # type: ignore[override]
        return self.f

    @property
    def fy(self) -> float:  # type: ignore[override]
        return self.f

    def _radial_coeffs(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        return (self.k1, self.k2), ()


@dataclass(frozen=True)
class ThinPrismFisheyeCamera(_ThetaSpaceFisheye):
    """COLMAP THIN_PRISM_FISHEYE (Weng et al. 1992 distortion applied in theta space).

    q = theta * unit azimuth, r2 = |q|^2 = theta^2,
    d = q (1 + k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4) + tangential(p1, p2) + (sx1 r2, sy1 r2).
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
    sx1: float = 0.0
    sy1: float = 0.0

    _positive_fields: ClassVar[tuple[str, ...]] = ("fx", "fy")
    _nonradial: ClassVar[bool] = True

    def _radial_coeffs(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        return (self.k1, self.k2, self.k3, self.k4), ()

    def _distort(self, q: Tensor) -> Tensor:
        r2 = (q * q).sum(-1)
        prism = torch.stack([self.sx1 * r2, self.sy1 * r2], dim=-1)
        return q * self._radial_factor(_safe_norm(q)).unsqueeze(-1) + _radtan(q, self.p1, self.p2) + prism


@dataclass(frozen=True)
class Fisheye624Camera(_ThetaSpaceFisheye):
    """Project Aria FISHEYE624 (nerfstudio FISHEYE624, COLMAP RAD_TAN_THIN_PRISM_FISHEYE).

    x_r = theta (1 + k0 theta^2 + ... + k5 theta^12) * unit azimuth, r2 = |x_r|^2,
    d = x_r + (p0 (r2 + 2 x^2) + 2 p1 x y, p1 (r2 + 2 y^2) + 2 p0 x y) + (s0 r2 + s1 r2^2, s2 r2 + s3 r2^2).
    Parameter order is nerfstudio's distortion_params order: k0..k5, p0, p1, s0..s3.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    k0: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    p0: float = 0.0
    p1: float = 0.0
    s0: float = 0.0
    s1: float = 0.0
    s2: float = 0.0
    s3: float = 0.0

    _positive_fields: ClassVar[tuple[str, ...]] = ("fx", "fy")
    _nonradial: ClassVar[bool] = True

    def _radial_coeffs(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        return (self.k0, self.k1, self.k2, self.k3, self.k4, self.k5), ()

    def _post_radial(self, xr: Tensor) -> Tensor:
        """Tangential + thin-prism terms, applied after the radial polynomial."""
        r2 = (xr * xr).sum(-1)
        prism = torch.stack([self.s0 * r2 + self.s1 * r2 * r2, self.s2 * r2 + self.s3 * r2 * r2], dim=-1)
        # Aria's p0 plays OpenCV's p2 role (couples to x) and p1 OpenCV's p1.
        return xr + _radtan(xr, self.p1, self.p0) + prism

    def _distort(self, q: Tensor) -> Tensor:
        return self._post_radial(q * self._radial_factor(_safe_norm(q)).unsqueeze(-1))

    def _undistort_detached(self, d: Tensor) -> Tensor:
        # The model is radial-then-tangential, so invert in that order: the small tangential/prism map
        # first (well conditioned), then the exact 1-D radial inversion. This stays robust near
        # max_angle, where the radial part flattens out.
        xr = self._newton2(self._post_radial, d, d)
        t = _safe_norm(xr)
        return xr * (self._solve_radial(t) / t).unsqueeze(-1)
