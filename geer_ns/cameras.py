"""Central camera models (pinhole, fisheye, omnidirectional, equirectangular) in batched torch.

Conventions
-----------
* Camera frame: OpenCV, x right, y down, z forward (nerfstudio uses OpenGL, x right, y up, z backward;
  :func:`from_nerfstudio` only converts intrinsics, rays from nerfstudio must be flipped as (x, -y, -z)).
* Pixel coordinates: continuous, (u, v) = (column, row), the top-left image corner is (0, 0) and the
  bottom-right corner is (width, height); pixel (i, j) (row i, column j) has its centre at
  (j + 0.5, i + 0.5). This is COLMAP's convention and nerfstudio's (``get_image_coords`` adds 0.5).
* ``max_angle`` is the largest angle from the optical axis for which the model is a bijection between
  directions and image points. It is derived from the model alone (where the radial mapping
  theta -> distorted radius stops increasing, where a Mei/pinhole projection hits its pole, pi for the
  full sphere); it is NOT limited to what the image shows (that is the caller's job, e.g. BEAP).
  Tangential / thin-prism terms are not radially symmetric and are left out of ``max_angle``; their
  failures are caught by the convergence test of :meth:`CameraModel.unproject`.
* dtype follows the input (float32 or float64; other inputs are converted to float32). Projection is
  closed form and differentiable; unprojection solves with a fixed number of (safeguarded) Newton
  iterations under ``no_grad`` and re-attaches gradients with one final Newton step (implicit
  differentiation), so it is differentiable w.r.t. the pixels too.
* Nothing returns NaN/Inf: invalid points get finite placeholder pixels, invalid pixels get +z.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import ClassVar

import torch
from torch import Tensor

__all__ = [
    "CameraModel",
    "EquidistantCamera",
    "EquirectangularCamera",
    "FOVCamera",
    "Fisheye624Camera",
    "MeiCamera",
    "OpenCVFisheyeCamera",
    "PinholeCamera",
    "RadialFisheyeCamera",
    "ThinPrismFisheyeCamera",
    "from_nerfstudio",
    "from_pycolmap",
]

# Samples used by the dense scan that locates the end of the monotonic part of theta -> radius.
_SCAN_SAMPLES = 20001
# Samples of the theta -> radius table that brackets the 1-D inversion.
_TABLE_SAMPLES = 4097


def _float_dtype(x: Tensor) -> torch.dtype:
    return x.dtype if x.dtype in (torch.float32, torch.float64) else torch.float32


def _safe_norm(v: Tensor) -> Tensor:
    """Euclidean norm over the last dim, never exactly 0 (finite gradients at the origin)."""
    return torch.sqrt(torch.clamp((v * v).sum(-1), min=torch.finfo(v.dtype).tiny))


def _tol_px(dtype: torch.dtype) -> float:
    """Residual (pixels) below which an inversion counts as converged."""
    return 1e-5 if dtype == torch.float64 else 2e-2


@dataclass(frozen=True)
class CameraModel:
    """Base class: an image of ``width`` x ``height`` pixels and a central projection."""

    width: int
    height: int

    # Float fields that must be > 0 (checked in __post_init__).
    _positive_fields: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name in ("width", "height"):
                if isinstance(value, bool) or int(value) != value or value <= 0:
                    raise ValueError(f"{type(self).__name__}.{f.name} must be a positive integer, got {value!r}")
                object.__setattr__(self, f.name, int(value))
                continue
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"{type(self).__name__}.{f.name} must be a real number, got {value!r}") from None
            if not math.isfinite(value):
                raise ValueError(f"{type(self).__name__}.{f.name} must be finite, got {value!r}")
            if f.name in self._positive_fields and value <= 0:
                raise ValueError(f"{type(self).__name__}.{f.name} must be > 0, got {value!r}")
            object.__setattr__(self, f.name, value)
        self._check_params()

    def _check_params(self) -> None:
        """Model-specific range checks (raise ValueError naming the field)."""

    # --- interface -------------------------------------------------------------------------------
    @cached_property
    def max_angle(self) -> float:
        """Largest valid angle (radians) from the optical axis; see module docstring."""
        raise NotImplementedError

    def project(self, points_cam: Tensor) -> tuple[Tensor, Tensor]:
        """Project camera-frame points ``[..., 3]`` to pixels ``[..., 2]``; also returns ``valid [...]``."""
        raise NotImplementedError

    def unproject(self, pixels: Tensor) -> tuple[Tensor, Tensor]:
        """Lift pixels ``[..., 2]`` to unit directions ``[..., 3]``; also returns ``valid [...]``."""
        raise NotImplementedError

    def pixel_centers(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """``[H, W, 2]`` pixel-centre coordinates (u, v) = (j + 0.5, i + 0.5)."""
        v, u = torch.meshgrid(
            torch.arange(self.height, dtype=dtype, device=device) + 0.5,
            torch.arange(self.width, dtype=dtype, device=device) + 0.5,
            indexing="ij",
        )
        return torch.stack([u, v], dim=-1)

    def pixel_rays(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
    ) -> tuple[Tensor, Tensor]:
        """Unit rays through all pixel centres: ``dirs [H, W, 3]`` and ``valid [H, W]``.

        Solved in float64 and cast to ``dtype`` so that float32 callers get accurate rays.
        """
        dirs, valid = self.unproject(self.pixel_centers(torch.float64, device))
        return dirs.to(dtype), valid


# ==================================================================================================
# Central lens models: point -> ideal point q (model specific) -> 2-D distortion D(q) -> affine K.
# ==================================================================================================


class _CentralLens(CameraModel):
    """Shared machinery of the lens models (everything except the equirectangular panorama).

    A lens model is defined by
      * ``_ideal_radius(theta)``: the undistorted radius ``s`` of a ray at angle ``theta`` from the axis
        (tan for perspective-like, theta for theta-space fisheye models, ...), increasing on
        ``[0, _angle_cap)``;
      * ``_radial_coeffs()``: the even radial factor f(s) = (1 + a1 s^2 + ...) / (1 + b1 s^2 + ...);
      * ``_distort(q)``: the 2-D distortion of the ideal point ``q = s * (cos a, sin a)``; its radially
        symmetric part is ``q * f(|q|)``, any remainder (tangential, thin prism) is only present when
        ``_nonradial`` is True;
      * the affine map to pixels ``u = fx * d_x + skew * d_y + cx``, ``v = fy * d_y + cy``.
    """

    _angle_cap: ClassVar[float] = math.pi  # where the ideal projection itself ends
    _nonradial: ClassVar[bool] = False  # D has terms that are not radially symmetric
    NEWTON_ITERS_1D: ClassVar[int] = 20
    NEWTON_ITERS_2D: ClassVar[int] = 20

    # fx, fy, cx, cy are fields or properties of the subclasses.
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def skew(self) -> float:
        return 0.0

    # --- model hooks (override) ------------------------------------------------------------------
    def _cap(self) -> float:
        return self._angle_cap

    def _ideal_radius(self, theta: Tensor) -> Tensor:
        raise NotImplementedError

    def _ideal_inverse(self, s: Tensor) -> Tensor:
        """theta from the ideal radius s (closed form for every model)."""
        raise NotImplementedError

    def _radial_coeffs(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(numerator, denominator) coefficients of the even radial factor
        (1 + a1 s^2 + a2 s^4 + ...) / (1 + b1 s^2 + ...)."""
        return (), ()

    def _radial_factor(self, s: Tensor) -> Tensor:
        if self._radial_identity:
            return torch.ones_like(s)
        return self._radial_factor_grad(s)[0]

    def _radial_factor_grad(self, s: Tensor) -> tuple[Tensor, Tensor]:
        """Radial factor and its derivative w.r.t. s (closed form: the 1-D solver's hot loop)."""
        num, den = self._radial_coeffs()
        f, df = _poly_even_grad(s, num)
        if any(c != 0 for c in den):
            g, dg = _poly_even_grad(s, den)
            f, df = f / g, (df * g - f * dg) / (g * g)
        return f, df

    @cached_property
    def _radial_identity(self) -> bool:
        return not any(c != 0 for part in self._radial_coeffs() for c in part)

    def _distort(self, q: Tensor) -> Tensor:
        return q * self._radial_factor(_safe_norm(q)).unsqueeze(-1)

    # --- max angle ---------------------------------------------------------------------------------
    def _monotone_ok(self, theta: Tensor) -> Tensor:
        """True where theta -> distorted radius is finite, positive and strictly increasing."""
        s, ds = torch.func.jvp(self._ideal_radius, (theta,), (torch.ones_like(theta),))
        factor, dfactor = self._radial_factor_grad(s)
        g, dg = s * factor, factor + s * dfactor
        finite = torch.isfinite(s) & torch.isfinite(g) & torch.isfinite(ds) & torch.isfinite(dg)
        return finite & (ds > 0) & (dg > 0) & (factor > 0)

    @cached_property
    def max_angle(self) -> float:
        """First angle where the radial mapping stops being invertible: a dense scan, then two
        refinement scans of the first failing interval (resolution ~cap / 2e10)."""
        cap = self._cap()
        with torch.no_grad():
            # Samples strictly inside (0, cap): the cap itself may be a pole.
            theta = torch.arange(1, _SCAN_SAMPLES, dtype=torch.float64) * (cap / _SCAN_SAMPLES)
            lo = 0.0
            for _ in range(3):
                ok = self._monotone_ok(theta)
                if bool(ok.all()):
                    return cap if lo == 0.0 else float(theta[-1])
                i = int(torch.nonzero(~ok)[0])
                lo = float(theta[i - 1]) if i > 0 else lo
                hi = float(theta[i])
                theta = torch.linspace(lo, hi, 1001, dtype=torch.float64)[1:]
            return lo

    @cached_property
    def _s_max(self) -> float:
        """Ideal radius at max_angle (upper bracket of the radial inversion)."""
        s = float(self._ideal_radius(torch.tensor(self.max_angle, dtype=torch.float64)))
        return s if math.isfinite(s) and s > 0 else 1e12

    @cached_property
    def _radial_table(self) -> tuple[Tensor, Tensor]:
        """(ideal radius s_k, distorted radius g_k) on a dense angle grid over [0, max_angle): brackets
        the 1-D inversion so that every pixel starts within one table interval of its root."""
        with torch.no_grad():
            theta = torch.linspace(0, self.max_angle, _TABLE_SAMPLES, dtype=torch.float64)[:-1]
            s = self._ideal_radius(theta)
            g = s * self._radial_factor(s)
            keep = torch.isfinite(g) & torch.isfinite(s)
            s = torch.cat([s[keep], torch.tensor([self._s_max], dtype=torch.float64)])
            g_top = self._s_max * self._radial_factor(torch.tensor(self._s_max, dtype=torch.float64))
            g_top = float(g_top) if bool(torch.isfinite(g_top)) else math.inf
            g = torch.cat([g[keep], torch.tensor([max(g_top, float(g[keep][-1]))], dtype=torch.float64)])
            return s, torch.cummax(g, 0).values  # guard against round-off wiggles

    # --- projection --------------------------------------------------------------------------------
    def _ideal_point(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Ideal point q [..., 2] and validity for camera-frame points (generic, via theta)."""
        xy = points[..., :2]
        rho = _safe_norm(xy)
        theta = torch.atan2(rho, points[..., 2])
        valid = (theta < self.max_angle) & ((points * points).sum(-1) > 0)
        theta = torch.clamp(theta, max=self.max_angle)  # finite placeholder beyond max_angle
        q = xy * (self._ideal_radius(theta) / rho).unsqueeze(-1)
        return q, valid

    def _to_pixels(self, d: Tensor) -> Tensor:
        u = self.fx * d[..., 0] + self.skew * d[..., 1] + self.cx
        v = self.fy * d[..., 1] + self.cy
        return torch.stack([u, v], dim=-1)

    def _from_pixels(self, px: Tensor) -> Tensor:
        dy = (px[..., 1] - self.cy) / self.fy
        dx = (px[..., 0] - self.cx - self.skew * dy) / self.fx
        return torch.stack([dx, dy], dim=-1)

    def project(self, points_cam: Tensor) -> tuple[Tensor, Tensor]:
        points = points_cam.to(_float_dtype(points_cam))
        q, valid = self._ideal_point(points)
        px = self._to_pixels(self._distort(q))
        valid = valid & torch.isfinite(px).all(-1)
        px = torch.where(valid.unsqueeze(-1), px, torch.nan_to_num(px, nan=0.0, posinf=0.0, neginf=0.0))
        return px, valid

    # --- unprojection ------------------------------------------------------------------------------
    def _solve_radial(self, t: Tensor) -> Tensor:
        """Solve s * factor(s) = t for s in [0, s_max] (safeguarded Newton, fixed iterations)."""
        if self._radial_identity:
            return torch.clamp(t, max=self._s_max)

        def radius(x: Tensor) -> tuple[Tensor, Tensor]:
            f, df = self._radial_factor_grad(x)
            return x * f, f + x * df

        s_tab, g_tab = (x.to(dtype=t.dtype, device=t.device) for x in self._radial_table)
        k = torch.searchsorted(g_tab, t.contiguous()).clamp(1, len(g_tab) - 1)
        lo, hi = s_tab[k - 1], s_tab[k]
        g_lo, g_hi = g_tab[k - 1], g_tab[k]
        frac = ((t - g_lo) / (g_hi - g_lo)).nan_to_num(0.5).clamp(0, 1)
        s = lo + frac * (hi - lo)  # linear interpolation in the table
        last_step = hi.clone()
        best, best_f = s, torch.full_like(t, math.inf)
        round_off = 8 * torch.finfo(t.dtype).eps * (1 + t)
        for _ in range(self.NEWTON_ITERS_1D):
            g, dg = radius(s)
            f = g - t
            better = f.abs() < best_f
            best = torch.where(better, s, best)
            best_f = torch.where(better, f.abs(), best_f)
            hi = torch.where(f > 0, s, hi)
            lo = torch.where(f <= 0, s, lo)
            newton = s - f / dg
            # Bisect when Newton leaves the bracket or stalls (flat, near-inflection regions converge
            # only linearly under Newton): the "rtsafe" safeguard.
            fast = ((2 * f).abs() <= (last_step * dg).abs()) | (f.abs() <= round_off)
            good = torch.isfinite(newton) & (newton >= lo) & (newton <= hi) & fast
            new_s = torch.where(good, newton, 0.5 * (lo + hi))
            last_step = (new_s - s).abs()
            s = new_s
        f = s * self._radial_factor(s) - t
        return torch.where(f.abs() < best_f, s, best)

    def _jacobian(self, q: Tensor, fn: Callable[[Tensor], Tensor] | None = None) -> tuple[Tensor, Tensor]:
        """fn(q) (default: D) and its 2x2 Jacobian [..., 2(out), 2(in)] by forward-mode AD."""
        fn = self._distort if fn is None else fn
        e0 = torch.zeros_like(q)
        e0[..., 0] = 1
        e1 = torch.zeros_like(q)
        e1[..., 1] = 1
        val, j0 = torch.func.jvp(fn, (q,), (e0,))
        _, j1 = torch.func.jvp(fn, (q,), (e1,))
        return val, torch.stack([j0, j1], dim=-1)

    @staticmethod
    def _solve2(J: Tensor, r: Tensor) -> Tensor:
        """J^-1 r for batched 2x2 J; zero where J is singular."""
        det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        ok = det.abs() > torch.finfo(J.dtype).tiny ** 0.5
        det = torch.where(ok, det, torch.ones_like(det))
        x = (J[..., 1, 1] * r[..., 0] - J[..., 0, 1] * r[..., 1]) / det
        y = (-J[..., 1, 0] * r[..., 0] + J[..., 0, 0] * r[..., 1]) / det
        step = torch.stack([x, y], dim=-1)
        return torch.where(ok.unsqueeze(-1), step, torch.zeros_like(step))

    def _newton2(self, fn: Callable[[Tensor], Tensor], target: Tensor, x: Tensor) -> Tensor:
        """Solve fn(x) = target for batched 2-D x: Newton with a trust region and backtracking."""
        for _ in range(self.NEWTON_ITERS_2D):
            val, J = self._jacobian(x, fn)
            res = (val - target).norm(dim=-1)
            step = self._solve2(J, val - target)
            # Trust region: never jump further than a fraction of the current radius.
            limit = 0.5 * (_safe_norm(x) + 0.05)
            step = step * torch.clamp(limit / _safe_norm(step), max=1.0).unsqueeze(-1)
            # Backtracking: halve the step until the residual decreases (or give up for this round).
            best, best_res = x, res
            for alpha in (1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125):
                cand = x - alpha * step
                cand_res = (fn(cand) - target).norm(dim=-1)
                take = (cand_res < best_res) & (best_res == res)  # first alpha that improves
                best = torch.where(take.unsqueeze(-1), cand, best)
                best_res = torch.where(take, cand_res, best_res)
            x = best
        return x

    def _undistort_detached(self, d: Tensor) -> Tensor:
        """Ideal point q with D(q) = d (no gradient): exact 1-D radial inversion, then (if D has
        non-radial terms) 2-D Newton started from it."""
        t = _safe_norm(d)
        s = self._solve_radial(t)
        q = d * (s / t).unsqueeze(-1)  # exact when D is radially symmetric
        if self._nonradial:
            q = self._newton2(self._distort, d, q)
        return q

    def _undistort(self, d: Tensor) -> tuple[Tensor, Tensor]:
        """Ideal point q with D(q) = d, and convergence flag."""
        with torch.no_grad():
            q = self._undistort_detached(d.detach())
            val = self._distort(q)
            res = (val - d.detach()) * torch.tensor([self.fx, self.fy], dtype=d.dtype, device=d.device)
            converged = torch.isfinite(res).all(-1) & (_safe_norm(res) < _tol_px(d.dtype))
            converged &= _safe_norm(q) <= self._s_max * (1 + 1e-9)
            q = torch.where(converged.unsqueeze(-1), q, torch.zeros_like(q))
        if torch.is_grad_enabled() and d.requires_grad:
            # One Newton step from the detached root re-attaches d(q)/d(d) = J^-1 (implicit function).
            with torch.no_grad():
                J = self._jacobian(q)[1]
            step = self._solve2(J, self._distort(q) - d)
            q = q - torch.where(converged.unsqueeze(-1), step, torch.zeros_like(step))
        return q, converged

    def _dirs_from_ideal(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Unit directions and angle-validity from ideal points (generic, via theta)."""
        s = _safe_norm(q)
        theta = self._ideal_inverse(s)
        valid = theta < self.max_angle
        xy = q * (torch.sin(theta) / s).unsqueeze(-1)
        return torch.cat([xy, torch.cos(theta).unsqueeze(-1)], dim=-1), valid

    def unproject(self, pixels: Tensor) -> tuple[Tensor, Tensor]:
        px = pixels.to(_float_dtype(pixels))
        d = self._from_pixels(px)
        finite = torch.isfinite(d).all(-1)
        d = torch.where(finite.unsqueeze(-1), d, torch.zeros_like(d))
        q, converged = self._undistort(d)
        dirs, valid = self._dirs_from_ideal(q)
        valid = valid & converged & finite & torch.isfinite(dirs).all(-1)
        plus_z = torch.zeros_like(dirs)
        plus_z[..., 2] = 1
        return torch.where(valid.unsqueeze(-1), dirs, plus_z), valid


def _radtan(q: Tensor, p1: float, p2: float) -> Tensor:
    """OpenCV/Brown tangential offset for point q (p1 couples to y, p2 to x as in OpenCV)."""
    x, y = q[..., 0], q[..., 1]
    r2 = x * x + y * y
    dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack([dx, dy], dim=-1)


def _poly_even_grad(s: Tensor, coeffs: tuple[float, ...]) -> tuple[Tensor, Tensor]:
    """p(s) = 1 + c0 s^2 + c1 s^4 + ... and dp/ds (Horner in s^2)."""
    s2 = s * s
    p = torch.zeros_like(s)
    dp = torch.zeros_like(s)
    n = len(coeffs)
    for i, c in enumerate(reversed(coeffs)):
        power = n - i  # coefficient of s^(2 power)
        p = (p + c) * s2
        dp = dp * s2 + 2 * power * c
    return 1 + p, dp * s


# --------------------------------------------------------------------------------------------------
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
        return self.p1 != 0 or self.p2 != 0

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


# --------------------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------------------
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
        if self.omega == 0:
            return torch.tan(theta)
        a = 2 * math.tan(self.omega / 2)
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
        return self.p1 != 0 or self.p2 != 0

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


# ==================================================================================================
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


# ==================================================================================================
# Conversions
# ==================================================================================================


def from_nerfstudio(cameras, index: int) -> CameraModel:
    """Camera ``index`` of a ``nerfstudio.cameras.cameras.Cameras`` (flattened batch).

    nerfstudio's ``distortion_params`` are (k1, k2, k3, k4, p1, p2):
    * PERSPECTIVE: radial 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8 and OpenCV tangential. The r^8 term has no
      OpenCV counterpart, so k4 != 0 raises ValueError.
    * FISHEYE: the same polynomial applied in theta space, i.e. Kannala-Brandt (k1..k4); with p1/p2 != 0
      it is COLMAP's THIN_PRISM_FISHEYE with zero prism terms.
    * FISHEYE624: 12 parameters (k0..k5, p0, p1, s0..s3).
    * EQUIRECTANGULAR: must have nerfstudio's standard intrinsics (fx = W/2, fy = H, c = image centre).
    """
    from nerfstudio.cameras.cameras import CameraType

    cams = cameras.flatten() if len(cameras.shape) != 1 else cameras
    cam = cams[int(index)]

    def scalar(t, name: str) -> float:
        value = float(t.reshape(-1)[0])
        if not math.isfinite(value):
            raise ValueError(f"nerfstudio camera {index}: {name} must be finite, got {value!r}")
        return value

    fx, fy, cx, cy = (scalar(getattr(cam, n), n) for n in ("fx", "fy", "cx", "cy"))
    width, height = int(cam.width.reshape(-1)[0]), int(cam.height.reshape(-1)[0])
    ctype = CameraType(int(cam.camera_type.reshape(-1)[0]))
    dist = [0.0] * 6
    if cam.distortion_params is not None:
        dist = [float(v) for v in cam.distortion_params.reshape(-1)]
        for i, v in enumerate(dist):
            if not math.isfinite(v):
                raise ValueError(f"nerfstudio camera {index}: distortion_params[{i}] must be finite, got {v!r}")

    if ctype == CameraType.PERSPECTIVE:
        k1, k2, k3, k4, p1, p2 = (dist + [0.0] * 6)[:6]
        if k4 != 0:
            raise ValueError(
                f"nerfstudio camera {index}: PERSPECTIVE distortion k4 (r^8 term) = {k4} has no OpenCV equivalent"
            )
        return PinholeCamera(width, height, fx, fy, cx, cy, k1=k1, k2=k2, p1=p1, p2=p2, k3=k3)
    if ctype == CameraType.FISHEYE:
        k1, k2, k3, k4, p1, p2 = (dist + [0.0] * 6)[:6]
        if p1 != 0 or p2 != 0:
            return ThinPrismFisheyeCamera(width, height, fx, fy, cx, cy, k1=k1, k2=k2, p1=p1, p2=p2, k3=k3, k4=k4)
        return OpenCVFisheyeCamera(width, height, fx, fy, cx, cy, k1=k1, k2=k2, k3=k3, k4=k4)
    if ctype == CameraType.FISHEYE624:
        if len(dist) != 12:
            raise ValueError(f"nerfstudio camera {index}: FISHEYE624 needs 12 distortion_params, got {len(dist)}")
        names = ("k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3")
        return Fisheye624Camera(width, height, fx, fy, cx, cy, **dict(zip(names, dist)))
    if ctype == CameraType.EQUIRECTANGULAR:
        expected = {"fx": width / 2, "fy": height, "cx": width / 2, "cy": height / 2}
        for name, want in expected.items():
            got = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}[name]
            if abs(got - want) > 1e-3 * max(1.0, abs(want)):
                raise ValueError(
                    f"nerfstudio camera {index}: EQUIRECTANGULAR {name} = {got} differs from the standard {want}"
                )
        return EquirectangularCamera(width, height)
    raise ValueError(f"nerfstudio camera {index}: camera type {ctype.name} is not supported")


# COLMAP model name -> (builder from the parameter dict, parameter names in COLMAP order).
_COLMAP_MODELS: dict[str, tuple[tuple[str, ...], Callable[[int, int, dict], CameraModel]]] = {
    "SIMPLE_PINHOLE": (("f", "cx", "cy"), lambda w, h, p: PinholeCamera(w, h, p["f"], p["f"], p["cx"], p["cy"])),
    "PINHOLE": (("fx", "fy", "cx", "cy"), lambda w, h, p: PinholeCamera(w, h, **p)),
    "SIMPLE_RADIAL": (
        ("f", "cx", "cy", "k"),
        lambda w, h, p: PinholeCamera(w, h, p["f"], p["f"], p["cx"], p["cy"], k1=p["k"]),
    ),
    "RADIAL": (
        ("f", "cx", "cy", "k1", "k2"),
        lambda w, h, p: PinholeCamera(w, h, p["f"], p["f"], p["cx"], p["cy"], k1=p["k1"], k2=p["k2"]),
    ),
    "OPENCV": (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"), lambda w, h, p: PinholeCamera(w, h, **p)),
    "FULL_OPENCV": (
        ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
        lambda w, h, p: PinholeCamera(w, h, **p),
    ),
    "OPENCV_FISHEYE": (
        ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
        lambda w, h, p: OpenCVFisheyeCamera(w, h, **p),
    ),
    "SIMPLE_FISHEYE": (("f", "cx", "cy"), lambda w, h, p: EquidistantCamera(w, h, p["f"], p["f"], p["cx"], p["cy"])),
    "FISHEYE": (("fx", "fy", "cx", "cy"), lambda w, h, p: EquidistantCamera(w, h, **p)),
    "SIMPLE_RADIAL_FISHEYE": (
        ("f", "cx", "cy", "k"),
        lambda w, h, p: RadialFisheyeCamera(w, h, p["f"], p["cx"], p["cy"], k1=p["k"]),
    ),
    "RADIAL_FISHEYE": (("f", "cx", "cy", "k1", "k2"), lambda w, h, p: RadialFisheyeCamera(w, h, **p)),
    "FOV": (("fx", "fy", "cx", "cy", "omega"), lambda w, h, p: FOVCamera(w, h, **p)),
    "THIN_PRISM_FISHEYE": (
        ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1"),
        lambda w, h, p: ThinPrismFisheyeCamera(w, h, **p),
    ),
    "RAD_TAN_THIN_PRISM_FISHEYE": (
        ("fx", "fy", "cx", "cy", "k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3"),
        lambda w, h, p: Fisheye624Camera(w, h, **p),
    ),
    "EQUIRECTANGULAR": (("w", "h"), lambda w, h, p: _colmap_equirect(w, h, p)),
}


def _colmap_equirect(width: int, height: int, p: dict) -> CameraModel:
    if p["w"] != width or p["h"] != height:
        raise ValueError(f"COLMAP EQUIRECTANGULAR params (w, h) = ({p['w']}, {p['h']}) differ from the image size")
    return EquirectangularCamera(width, height)


def from_pycolmap(camera) -> CameraModel:
    """Convert a ``pycolmap.Camera``; supported models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL,
    OPENCV, FULL_OPENCV, OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, FOV, THIN_PRISM_FISHEYE,
    plus RAD_TAN_THIN_PRISM_FISHEYE (= FISHEYE624), SIMPLE_FISHEYE / FISHEYE (equidistant) and EQUIRECTANGULAR.
    """
    name = camera.model.name if hasattr(camera.model, "name") else str(camera.model_name)
    if name not in _COLMAP_MODELS:
        raise ValueError(f"COLMAP camera model {name} is not supported (supported: {', '.join(_COLMAP_MODELS)})")
    names, build = _COLMAP_MODELS[name]
    params = [float(v) for v in camera.params]
    if len(params) != len(names):
        raise ValueError(f"COLMAP {name} expects {len(names)} params ({', '.join(names)}), got {len(params)}")
    for n, v in zip(names, params):
        if not math.isfinite(v):
            raise ValueError(f"COLMAP {name} parameter {n} must be finite, got {v!r}")
    return build(int(camera.width), int(camera.height), dict(zip(names, params)))
