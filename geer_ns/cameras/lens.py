"""Central lens models: point -> ideal point q (model specific) -> 2-D distortion D(q) -> affine K.

The shared machinery of every lens model (all but the equirectangular panorama): the maximum angle, closed-form
projection and the safeguarded Newton unprojection with implicit gradients.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import cached_property
from typing import ClassVar

import torch
from torch import Tensor

from geer_ns.cameras.base import CameraModel, _float_dtype, _is_zero, _safe_norm, _tol_px

# Samples used by the dense scan that locates the end of the monotonic part of theta -> radius.
_SCAN_SAMPLES = 20001
# Samples of the theta -> radius table that brackets the 1-D inversion.
_TABLE_SAMPLES = 4097


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
        if not all(_is_zero(c) for c in den):
            g, dg = _poly_even_grad(s, den)
            f, df = f / g, (df * g - f * dg) / (g * g)
        return f, df

    @cached_property
    def _radial_identity(self) -> bool:
        return all(_is_zero(c) for part in self._radial_coeffs() for c in part)

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
