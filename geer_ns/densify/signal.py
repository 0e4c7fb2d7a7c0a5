"""The densification statistics of a training step: what each rendered view contributes, summed over views.

gsplat's DefaultStrategy thresholds, per Gaussian, the mean over views of |dL/d(image position)| and the largest
screen radius. geer renders along rays and has no 2-D splat, so each training view records a zero "offset" leaf
per Gaussian that turns its mean's direction from the camera (`ViewSignal.lateral`); its gradient after backward
is dL/d(that direction). The statistics count the view's own supervised pixels, so they mean the same at every
field of view, projection and resolution, in the units gsplat's thresholds were tuned on (a 60-degree pinhole
W_ref pixels across):

    gradient  = |dL_v/d alpha| * P_v * omega_v(u) / sqrt(max(omega_v, omega_camera)(u)) / (2 W_ref)
    screen    = rho / sqrt(max(omega_v, omega_camera)(u)) / W_ref

W_ref is REFERENCE_WIDTH_PIXELS (densify-units reference) or, as gsplat counts, the camera's own image sides
(densify-units image: the smaller for the gradient, the larger for the screen size; `statistic_widths`).

Derivation, calibration of W_ref and measurements: docs/densification.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Literal, Optional, Sequence, Tuple

import torch
from torch import Tensor

# The reference camera of gsplat's thresholds: a pinhole 60 degrees and W_ref pixels across (module docstring).
REFERENCE_WIDTH_PIXELS = 300.0
Projection = Callable[[Tensor], Tuple[Tensor, Tensor]]  # camera-frame points [N,3] -> (pixels [N,2], valid [N])
DensifyUnits = Literal["reference", "image"]


def statistic_widths(width: int, height: int, units: DensifyUnits) -> Tuple[float, float]:
    """W_ref of the gradient and of the screen-size statistic of a camera whose full-resolution images are
    width x height: the reference camera's for "reference"; gsplat's for "image" (a position gradient in halves
    of the image's smaller side, isotropic where gsplat halves each side per axis; a radius over its larger side).
    Views downscaled by the resolution schedule count the full image's sides, as thresholds scaled by them would."""
    if units == "image":
        return float(min(width, height)), float(max(width, height))
    return REFERENCE_WIDTH_PIXELS, REFERENCE_WIDTH_PIXELS


def tangent_basis(means_c: Tensor) -> Tensor:
    """[N,3,2] orthonormal directions across each mean's viewing ray u: e1 along increasing theta =
    atan2(x, z) (horizontal), e2 = u x e1 (downwards, increasing phi); e1 = x where the ray is vertical."""
    p = means_c.detach().double()
    u = p / p.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    e1 = torch.stack([u[:, 2], torch.zeros_like(u[:, 0]), -u[:, 0]], -1)
    norm = e1.norm(dim=-1, keepdim=True)
    e1 = torch.where(norm > 1e-12, e1 / norm.clamp_min(1e-300), p.new_tensor([1.0, 0.0, 0.0]).expand_as(e1))
    e2 = torch.linalg.cross(u, e1, dim=-1)
    return torch.stack([e1, e2], -1)


def pixel_solid_angle(project: Projection, means_c: Tensor, fallback: float, step: float = 1e-4) -> Tensor:
    """[N] solid angle (sr) of one pixel of a view at each mean's direction: 1 / |det d(pixel)/d(direction)|,
    by forward differences of `project` over `step` radians across the ray; `fallback` where the camera
    cannot project there (such a Gaussian's center is outside the view)."""
    p = means_c.detach().double()
    u = p / p.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    basis = tangent_basis(p)
    c, s = math.cos(step), math.sin(step)
    points = torch.cat([u, c * u + s * basis[..., 0], c * u + s * basis[..., 1]])
    pixels, valid = project(points)
    pixels, valid = pixels.double().reshape(3, -1, 2), valid.reshape(3, -1).all(0)
    d1, d2 = (pixels[1] - pixels[0]) / step, (pixels[2] - pixels[0]) / step
    det = (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]).abs()
    ok = valid & torch.isfinite(det) & (det > 0)
    return torch.where(ok, 1.0 / torch.where(ok, det, torch.ones_like(det)), torch.full_like(det, fallback))


def angular_radius(means_c: Tensor, scales: Tensor, lam2: Tensor) -> Tensor:
    """[N] half-angle (radians) of the sphere of radius lambda x the largest scale around each mean, as seen
    from the camera (pi/2 when the camera is inside it)."""
    reach = torch.sqrt(lam2.detach().double()) * scales.detach().double().amax(dim=-1)
    distance = means_c.detach().double().norm(dim=-1).clamp_min(1e-300)
    return torch.asin((reach / distance).clamp(max=1.0))


@dataclass
class ViewSignal:
    """How one view measures the statistics: the offsets' view-space moves, and the scale of their gradient."""

    lateral: Tensor  # [N, 3, 2] view-space move of each mean per unit offset (columns)
    scale: Tensor  # [N, 1]: offsets' gradient -> the statistic's units
    radius: Tensor  # [N] screen statistic before masking by visibility
    pixels: Tensor  # [N] the radius in the view's own pixels there


def angular_signal(project: Projection, supervised_pixels: int, center_solid_angle: float, means_c: Tensor,
                   scales: Tensor, lam2: Tensor, source: Optional[Projection],
                   widths: Tuple[float, float]) -> ViewSignal:
    """A view's statistics (module docstring), offsets in radians of direction.

    Args:
        project: the view's projection (camera-frame points -> its pixels or cells, valid).
        supervised_pixels: P_v, the view's supervised pixels (its loss is a mean over them).
        center_solid_angle: a pixel's solid angle on the axis (used where `project` cannot project).
        means_c, scales, lam2: [N,3] camera-frame means, [N,3] scales, [N] squared PBF extents.
        source: the camera whose pixels a resampled view (BEAP) was made from; None: the view's own.
        widths: W_ref of the gradient and of the screen size (`statistic_widths`).
    """
    lateral = lateral_basis(means_c)
    omega = pixel_solid_angle(project, means_c, center_solid_angle)
    resolved = omega if source is None else torch.maximum(omega, pixel_solid_angle(source, means_c, 0.0))
    side = torch.sqrt(resolved)  # the side of the pixel the supervision resolves there
    scale = (supervised_pixels * omega / side / (2.0 * widths[0]))[:, None]
    rho = angular_radius(means_c, scales, lam2)
    pixels = rho / side
    radius = pixels / widths[1]
    return ViewSignal(lateral, scale.to(means_c.dtype), radius.to(means_c.dtype), pixels.to(means_c.dtype))


def lateral_basis(means_c: Tensor) -> Tensor:
    """[N,3,2] angular_signal's lateral moves: a radian of direction across the ray is |mean| along it."""
    return (tangent_basis(means_c) * means_c.detach().double().norm(dim=-1)[:, None, None]).to(means_c.dtype)


@dataclass
class ViewProbe:
    """A training view's densification leaves before its render: zero offsets that move the means laterally
    (`displace`), and the sink the renderer fills with the per-pixel absolute gradients (absgrad). Over the
    model's `rows` the view sees (a sharded render: memory O(what the view sees)), or all of them (None)."""

    signal: ViewSignal
    offsets: Tensor  # [K, 2] zero leaf
    absgrad: Optional[Tensor]  # [K, 2] zero leaf, or None (the summed gradient is the statistic)
    rows: Optional[Tensor] = None  # [K] the model's rows these are, or None: all of them, in order

    @staticmethod
    def zeros(signal: ViewSignal, like: Tensor, absgrad: bool, rows: Optional[Tensor] = None) -> "ViewProbe":
        offsets = torch.zeros(like.shape[0], 2, dtype=like.dtype, device=like.device, requires_grad=True)
        return ViewProbe(signal, offsets, torch.zeros_like(offsets, requires_grad=True) if absgrad else None, rows)

    def displace(self, means: Tensor, viewmat: Tensor) -> Tensor:
        """means ([K,3], the probe's rows) + the offsets' move, in world axes (zero: the same means, with a
        gradient path to the offsets)."""
        move = torch.einsum("nij,nj->ni", self.signal.lateral, self.offsets)
        return means + move @ viewmat[:3, :3].to(means.dtype)

    def record(self, visible: Tensor, weight: Tensor) -> "ViewRecord":
        """The view's record once rendered: `visible` [K] bool, `weight` [K] largest blend weight."""
        radius, pixels = self.signal.radius, self.signal.pixels
        zero = torch.zeros_like(radius)
        return ViewRecord(self.offsets, self.absgrad, visible, self.signal.scale, torch.where(visible, radius, zero),
                          weight, torch.where(visible, pixels.to(zero), zero), self.rows)


@dataclass
class ViewRecord:
    """One rendered training view's part of the densification statistics, over its probe's rows (K of them)."""

    offsets: Tensor  # [K, 2] zero leaf; .grad after backward: dL/d(offsets)
    absgrad: Optional[Tensor]  # [K, 2] zero leaf whose .grad the renderer fills with sum_pixels |dL_p/d(offsets)|
    visible: Tensor  # [K] bool: the view rendered the Gaussian
    scale: Tensor  # [K, 1]: offsets' gradient -> the statistic's units (ViewSignal.scale)
    radius: Tensor  # [K] screen-size statistic; 0 where not visible
    weight: Tensor  # [K] the largest blend weight (transmittance x alpha) over the view's rays
    pixels: Tensor  # [K] the Gaussian's radius in this view's pixels; 0 where not visible
    rows: Optional[Tensor] = None  # [K] the model's rows of these values, or None: all of them, in order

    def gradient_norms(self) -> Tensor:
        """[K] the gradient statistic (AbsGS's per-pixel absolute sums where recorded); 0 where not visible."""
        leaf = self.absgrad if self.absgrad is not None else self.offsets
        if leaf.grad is None:
            return torch.zeros_like(self.radius)
        norms = (leaf.grad.detach() * self.scale).norm(dim=-1).to(self.radius.dtype)
        return torch.where(self.visible, norms, torch.zeros_like(norms))


@dataclass
class StepStatistics:
    """Per-Gaussian sums over a step's views: what DefaultStrategy accumulates between refinements."""

    grad: Tensor  # [N] sum over views of the gradient norm
    views: Tensor  # [N] float: number of views that rendered the Gaussian
    radius: Tensor  # [N] largest screen-size statistic over views
    weight: Tensor  # [N] largest blend weight over views
    pixels: Tensor  # [N] largest radius in a view's pixels over views (what the images resolve of it)

    @staticmethod
    def of_views(records: Sequence[ViewRecord], n: int, device) -> "StepStatistics":
        """The sums over `records` (view by view, in order: the same bits however views are split over
        processes whose partial sums are then added, for two processes or two views). Each record's values
        go to its rows: a Gaussian outside them gets nothing (where a dense record adds 0.0 exactly)."""
        grad = torch.zeros(n, device=device)
        views = torch.zeros(n, device=device)
        radius = torch.zeros(n, device=device)
        weight = torch.zeros(n, device=device)
        pixels = torch.zeros(n, device=device)
        for record in records:
            rows = record.rows if record.rows is not None else torch.arange(n, device=device)
            rows = rows.to(device)
            grad.index_add_(0, rows, record.gradient_norms().to(grad))
            views.index_add_(0, rows, record.visible.to(views.dtype))
            radius.scatter_reduce_(0, rows, record.radius.to(radius), reduce="amax")
            weight.scatter_reduce_(0, rows, record.weight.to(weight), reduce="amax")
            pixels.scatter_reduce_(0, rows, record.pixels.to(pixels), reduce="amax")
        return StepStatistics(grad, views, radius, weight, pixels)
