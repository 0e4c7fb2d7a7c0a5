"""The densification statistics of a training step: what each rendered view contributes, summed over views.

gsplat's DefaultStrategy thresholds, per Gaussian, the mean over views of |dL/d(image position)| (in units of
half the image, gsplat's normalisation) and the largest screen radius as a fraction of the image. geer renders
along rays and has no 2-D splat, so each training view records a zero "offset" leaf per Gaussian that moves
its mean laterally (see `lateral_displacement`): the render depends on it only through the image position, and
its gradient after backward is dL/d(image position). `ViewRecord` keeps that leaf and what turns its gradient
into the statistic; `StepStatistics` sums the views of a step (the views of every process, once reduced).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence, Tuple

import torch
from torch import Tensor


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


def lateral_displacement(means_c: Tensor, means2d: Tensor, steps: Tuple[float, float]) -> Tensor:
    """View-space move [N,3] that shifts each mean's BEAP position by means2d [N,2] pixels (to first order).

    Adding it to the means (zero when means2d = 0) makes means2d.grad = dL/d(image position in pixels),
    the quantity gsplat's DefaultStrategy thresholds.
    """
    angles = means2d * means2d.new_tensor(steps)
    return torch.einsum("nij,nj->ni", angle_jacobian_pinv(means_c), angles)


def pbf_radii(pbf, visible: Tensor, steps: Tuple[float, float]) -> Tensor:
    """[N] image half-extent in pixels from the PBF's angular bounds; 0 when not rendered."""
    half_theta = (pbf.theta_hi - pbf.theta_lo) / (2.0 * steps[0])
    half_phi = (pbf.phi_hi - pbf.phi_lo) / (2.0 * steps[1])
    radii = torch.maximum(half_theta, half_phi)
    return torch.where(visible, radii, torch.zeros_like(radii)).detach()


@dataclass
class ViewRecord:
    """One rendered training view's part of the densification statistics."""

    offsets: Tensor  # [N, 2] zero leaf; .grad after backward: dL/d(image position) in pixels
    visible: Tensor  # [N] bool: the view rendered the Gaussian
    grad_scale: Tuple[float, float]  # pixels -> the statistic's units (gsplat: half the image width, height)
    radius: Tensor  # [N] screen-size statistic (gsplat: radius / max(width, height)); 0 where not visible
    width: int
    height: int

    def gradient_norms(self) -> Tensor:
        """[N] |dL/d(image position)| in the statistic's units; 0 where not visible or never reached."""
        if self.offsets.grad is None:
            return torch.zeros_like(self.radius)
        grad = self.offsets.grad.detach() * self.offsets.new_tensor(self.grad_scale)
        norms = grad.norm(dim=-1).to(self.radius.dtype)
        return torch.where(self.visible, norms, torch.zeros_like(norms))


@dataclass
class StepStatistics:
    """Per-Gaussian sums over a step's views: what DefaultStrategy accumulates between refinements."""

    grad: Tensor  # [N] sum over views of the gradient norm
    views: Tensor  # [N] float: number of views that rendered the Gaussian
    radius: Tensor  # [N] largest screen-size statistic over views

    @staticmethod
    def of_views(records: Sequence[ViewRecord], n: int, device) -> "StepStatistics":
        """The sums over `records` (view by view, in order: the same bits however views are split over
        processes whose partial sums are then added, for two processes or two views)."""
        grad = torch.zeros(n, device=device)
        views = torch.zeros(n, device=device)
        radius = torch.zeros(n, device=device)
        for record in records:
            grad = grad + record.gradient_norms().to(grad)
            views = views + record.visible.to(views.dtype)
            radius = torch.maximum(radius, record.radius.to(radius))
        return StepStatistics(grad, views, radius)

    def tensors(self) -> Tuple[Tensor, Tensor, Tensor]:
        return self.grad, self.views, self.radius
