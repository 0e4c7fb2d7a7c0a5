"""The densification statistics of a training step: what each rendered view contributes, summed over views.

gsplat's DefaultStrategy thresholds, per Gaussian, the mean over views of |dL/d(image position)| and the
largest screen radius. geer renders along rays and has no 2-D splat, so each training view records a zero
"offset" leaf per Gaussian that moves its mean laterally (`ViewSignal.lateral`): the render depends on it only
through the Gaussian's direction from the camera, and its gradient after backward is dL/d(that direction).
`ViewRecord` keeps the leaf and what turns its gradient into the statistic; `StepStatistics` sums a step's
views (the views of every process, once reduced).

One meaning at every field of view and projection (`angular_signal`, the default), at any resolution: both
statistics count the view's own pixels, the units its supervision resolves. A view's loss is a mean over its
P supervised pixels, so dL/d(direction) of one Gaussian is (1/P) x the sum of its pixels' error gradients:
wider views dilute it, and BEAP cells stretch it (by up to 1/cos of the off-axis angle, x11 at 85 degrees).
The statistics undo both:

    gradient  = |dL_v/d alpha| * P_v * sqrt(omega_v(u)) / (2 W_ref)     alpha: the direction, radians
    screen    = rho / sqrt(omega_v(u)) / W_ref                           rho: the angular radius, radians

omega_v(u) is the solid angle of one pixel of the view at the Gaussian's direction u, sqrt(omega) the pixel's
side there: P_v dL_v/d alpha is the gradient of the view's error summed over its pixels, and times
sqrt(omega) it is that sum's gradient per pixel of movement; rho / sqrt(omega) is the Gaussian's radius in
those pixels. A BEAP view is resampled from the camera's own pixels, and its cells are finer than them in
places (1.1x on the axis of a 180-degree fisheye, more toward the rim, where BEAP cells shrink as
cos(off-axis angle)); what it resolves there is the coarser of the two, so the pixel's side is
sqrt(max(omega_v, omega_camera)), while the sum over the view's cells stays P_v omega_v dL_v/d alpha:

    gradient  = |dL_v/d alpha| * P_v * omega_v(u) / sqrt(max(omega_v, omega_camera)(u)) / (2 W_ref)

Neither depends on the field of view or on the projection (BEAP, native fisheye, pinhole), only
on what the pixels see. The reference camera is a 60-degree pinhole W_ref pixels across; for it, at its image
centre, both statistics are gsplat's own (|dL/d position| in units of half the image, radius / image width),
so gsplat's thresholds keep their meaning.

Why pixels and not radians: under splatfacto's L1 loss each pixel's error gradient has the same size whatever
its residual, so the AbsGS statistic of a Gaussian is about 1.9 c sigma / (2 W_ref) for a footprint of sigma
pixels and contrast c (alpha x colour step): a threshold on it is a floor on the Gaussian's size in pixels
(c sigma >~ 0.25 px at 0.0008 and W_ref = 300). In radians, the same threshold is a fixed angle, 0.1 degree,
whatever the images resolve: a 128-pixel 180-degree view (1.4 degrees a pixel) then splits its Gaussians far
below its pixels, and a screen size in radians splits every Gaussian a wide view of a room sees from close by;
the former statistic, in image units, did the same (x1.5 per refinement, 20k -> 290k Gaussians by step 1000
on the dev room at 128^2, where these statistics give 27.5k and 0.9 dB more by step 3000). W_ref = 300 sets the floor at
about a pixel at contrasts of 0.1-0.25 (benchmarks/densification.md, the embedded room at step 800: W_ref
1000 grows it to 4.5k Gaussians and 26.7 dB, 500 to 8.1k and 27.0 dB, 300 to 15.7k and 28.0 dB, each
refinement adding fewer). rho is where the Gaussian's alpha falls to 1/255 as seen from the camera (its
bounding sphere's half-angle, lambda = the PBF's). `pixel_signal` is the former definition (BEAP pixels,
gsplat's normalisation by the image size), kept for comparisons.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Tuple

import torch
from torch import Tensor

# The reference camera of gsplat's thresholds: a pinhole 60 degrees and W_ref pixels across (module docstring).
REFERENCE_WIDTH_PIXELS = 300.0
Projection = Callable[[Tensor], Tuple[Tensor, Tensor]]  # camera-frame points [N,3] -> (pixels [N,2], valid [N])


def angle_jacobian_pinv(means_c: Tensor) -> Tensor:
    """[N,3,2] pseudo-inverse of d(theta, phi)/d(mean_c), theta = atan2(x, z), phi = atan2(y, z).

    Its columns are the smallest view-space moves that shift a mean's BEAP angles by one radian in theta
    (resp. phi) and leave the other angle unchanged; they are orthogonal to the viewing ray (the
    Jacobian's null space), so the distance to the camera is kept. Zero where the angles are undefined.
    """
    p = means_c.detach().double()
    x, y, z = p.unbind(-1)
    a, b = x * x + z * z, y * y + z * z
    zero = torch.zeros_like(x)
    jac = torch.stack(
        [torch.stack([z / a, zero, -x / a], -1), torch.stack([zero, z / b, -y / b], -1)], -2
    )  # [N, 2, 3]
    gram = jac @ jac.transpose(-1, -2)
    det = gram[:, 0, 0] * gram[:, 1, 1] - gram[:, 0, 1] * gram[:, 1, 0]
    ok = (a > 1e-12) & (b > 1e-12) & torch.isfinite(det) & (det > 1e-30)
    safe_gram = torch.where(ok[:, None, None], gram, torch.eye(2, dtype=p.dtype, device=p.device))
    pinv = jac.transpose(-1, -2) @ torch.linalg.inv(safe_gram)
    pinv = torch.where(ok[:, None, None] & torch.isfinite(pinv), pinv, torch.zeros_like(pinv))
    return pinv.to(means_c.dtype)


def pbf_radii(pbf, visible: Tensor, steps: Tuple[float, float]) -> Tensor:
    """[N] image half-extent in pixels from the PBF's angular bounds; 0 when not rendered."""
    half_theta = (pbf.theta_hi - pbf.theta_lo) / (2.0 * steps[0])
    half_phi = (pbf.phi_hi - pbf.phi_lo) / (2.0 * steps[1])
    radii = torch.maximum(half_theta, half_phi)
    return torch.where(visible, radii, torch.zeros_like(radii)).detach()


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
    cannot project there (such a Gaussian's centre is outside the view)."""
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
    scale: Tensor  # [N, 1] or [1, 2]: offsets' gradient -> the statistic's units
    radius: Optional[Tensor]  # [N] screen statistic before masking by visibility (None: from the render's PBF)
    pixels: Optional[Tensor]  # [N] the radius in the view's own pixels there (None: from the render's PBF)


def angular_signal(project: Projection, supervised_pixels: int, center_solid_angle: float, means_c: Tensor,
                   scales: Tensor, lam2: Tensor, source: Optional[Projection] = None) -> ViewSignal:
    """The statistics of the module docstring; offsets in radians of direction. `source`: the camera whose
    pixels a resampled view (BEAP) was made from, where they differ from the view's own cells."""
    lateral = lateral_basis(means_c)
    omega = pixel_solid_angle(project, means_c, center_solid_angle)
    resolved = omega if source is None else torch.maximum(omega, pixel_solid_angle(source, means_c, 0.0))
    side = torch.sqrt(resolved)  # the side of the pixel the supervision resolves there
    scale = (supervised_pixels * omega / side / (2.0 * REFERENCE_WIDTH_PIXELS))[:, None]
    rho = angular_radius(means_c, scales, lam2)
    pixels = rho / side
    radius = pixels / REFERENCE_WIDTH_PIXELS
    return ViewSignal(lateral, scale.to(means_c.dtype), radius.to(means_c.dtype), pixels.to(means_c.dtype))


def pixel_signal(means_c: Tensor, steps: Tuple[float, float], size: Tuple[int, int]) -> ViewSignal:
    """The former statistics: offsets in BEAP pixels (theta, phi steps), gsplat's normalisation by half the
    image's height and width, the screen radius from the PBF in pixels / the image's larger side."""
    height, width = size
    lateral = angle_jacobian_pinv(means_c) * means_c.new_tensor(steps)
    return ViewSignal(lateral, means_c.new_tensor([[width / 2.0, height / 2.0]]), None, None)


def lateral_basis(means_c: Tensor) -> Tensor:
    """[N,3,2] angular_signal's lateral moves: a radian of direction across the ray is |mean| along it."""
    return (tangent_basis(means_c) * means_c.detach().double().norm(dim=-1)[:, None, None]).to(means_c.dtype)


@dataclass
class ViewProbe:
    """A training view's densification leaves before its render: zero offsets that move the means laterally
    (`displace`), and the sink the renderer fills with the per-pixel absolute gradients (absgrad)."""

    signal: ViewSignal
    offsets: Tensor  # [N, 2] zero leaf
    absgrad: Optional[Tensor]  # [N, 2] zero leaf, or None (the summed gradient is the statistic)

    @staticmethod
    def zeros(signal: ViewSignal, like: Tensor, absgrad: bool) -> "ViewProbe":
        offsets = torch.zeros(like.shape[0], 2, dtype=like.dtype, device=like.device, requires_grad=True)
        return ViewProbe(signal, offsets, torch.zeros_like(offsets, requires_grad=True) if absgrad else None)

    def displace(self, means: Tensor, viewmat: Tensor) -> Tensor:
        """means + the offsets' move, in world axes (zero: the same means, with a gradient path to the offsets)."""
        move = torch.einsum("nij,nj->ni", self.signal.lateral, self.offsets)
        return means + move @ viewmat[:3, :3].to(means.dtype)

    def record(self, visible: Tensor, weight: Tensor, radius: Optional[Tensor] = None,
               pixels: Optional[Tensor] = None) -> "ViewRecord":
        """The view's record once rendered: `radius` and `pixels` where the signal has none of its own
        (pixel_signal's, from the render's PBF)."""
        radius = self.signal.radius if radius is None else radius
        pixels = self.signal.pixels if pixels is None else pixels
        zero = torch.zeros_like(radius)
        return ViewRecord(self.offsets, self.absgrad, visible, self.signal.scale, torch.where(visible, radius, zero),
                          weight, torch.where(visible, pixels.to(zero), zero))


@dataclass
class ViewRecord:
    """One rendered training view's part of the densification statistics."""

    offsets: Tensor  # [N, 2] zero leaf; .grad after backward: dL/d(offsets)
    absgrad: Optional[Tensor]  # [N, 2] zero leaf whose .grad the renderer fills with sum_pixels |dL_p/d(offsets)|
    visible: Tensor  # [N] bool: the view rendered the Gaussian
    scale: Tensor  # [N, 1] or [1, 2]: offsets' gradient -> the statistic's units (ViewSignal.scale)
    radius: Tensor  # [N] screen-size statistic; 0 where not visible
    weight: Tensor  # [N] the largest blend weight (transmittance x alpha) over the view's rays
    pixels: Tensor  # [N] the Gaussian's radius in this view's pixels; 0 where not visible

    def gradient_norms(self) -> Tensor:
        """[N] the gradient statistic (AbsGS's per-pixel absolute sums where recorded); 0 where not visible."""
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
        processes whose partial sums are then added, for two processes or two views)."""
        grad = torch.zeros(n, device=device)
        views = torch.zeros(n, device=device)
        radius = torch.zeros(n, device=device)
        weight = torch.zeros(n, device=device)
        pixels = torch.zeros(n, device=device)
        for record in records:
            grad = grad + record.gradient_norms().to(grad)
            views = views + record.visible.to(views.dtype)
            radius = torch.maximum(radius, record.radius.to(radius))
            weight = torch.maximum(weight, record.weight.to(weight))
            pixels = torch.maximum(pixels, record.pixels.to(pixels))
        return StepStatistics(grad, views, radius, weight, pixels)
