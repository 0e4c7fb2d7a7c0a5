"""Depth supervision: a robust loss between the rendered `distance` and the sensor's (geer_ns/data/depth.py),
and the geometry metrics ns-eval reports when a view has a target.

The residual is relative, (distance - target) / target: scale-free (a dataparser's scaling changes nothing) and
as strict for near walls as for far ones, which is how depth sensors' errors grow. Its gradient reaches the
Gaussians through the renderer's depth and accumulation sums (every backend). Options, their defaults and the
measured effect: docs/outputs.md and benchmarks/depth_supervision.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Literal

import torch
from torch import Tensor

from geer_ns.data.depth import TARGET_KEY, downscale_target

RobustLoss = Literal["l1", "huber", "cauchy"]


@dataclass
class DepthSupervisionOptions:
    """Model options of depth supervision (frames with `depth_file_path`; without them nothing changes)."""

    depth_loss_weight: float = 0.2
    """Weight of the depth loss for frames with depth_file_path (0: off)."""
    depth_loss: RobustLoss = "huber"
    """Robust loss on the relative distance error r: l1, huber (quadratic below depth-loss-scale, |r| above) or
    cauchy (logarithmic beyond depth-loss-scale: outliers such as LiDAR points through glass barely count)."""
    depth_loss_scale: float = 0.05
    """Scale of the robust loss in relative error (0.05: 5% of the measured distance)."""


def robust(residual: Tensor, kind: RobustLoss, scale: float) -> Tensor:
    """rho(r) elementwise, all with slope at most 1 (so that the weight alone sets the gradient's size): l1 |r|,
    huber r^2 / (2 s) below s and |r| - s / 2 above, cauchy (s / 2) log(1 + (r / s)^2)."""
    if kind == "l1":
        return residual.abs()
    if kind == "huber":
        a = residual.abs()
        return torch.where(a <= scale, 0.5 * residual * residual / scale, a - 0.5 * scale)
    if kind == "cauchy":
        return 0.5 * scale * torch.log1p((residual / scale) ** 2)
    raise ValueError(f"depth_loss must be 'l1', 'huber' or 'cauchy', got {kind!r}")


def target_of(batch: Dict[str, Tensor], factor: int, device) -> Tensor | None:
    """The batch's distance target [h, w, 1] at the render's downscale factor (None without one)."""
    target = batch.get(TARGET_KEY)
    return None if target is None else downscale_target(target.to(device), factor)


def depth_loss(distance: Tensor, accumulation: Tensor, target: Tensor, valid: Tensor,
               options: DepthSupervisionOptions) -> Tensor:
    """Weighted mean robust relative error over the measured, valid rays. distance [h, w, 1] (the renderer's
    expected distance, with its gradient), accumulation [h, w, 1], target [h, w, 1] (0: unmeasured), valid
    [h, w, 1] bool. The rendered distance is composited over the target, acc D + (1 - acc) target: a ray that
    is partly transparent where the sensor saw a surface is pulled both ways (nearer/farther Gaussians, more
    opacity), and no gradient divides by a small accumulation as D = sum w t / sum w would."""
    measured = valid & (target > 0)
    n = measured.sum().clamp_min(1)
    composited = accumulation * distance + (1.0 - accumulation) * target
    residual = (composited - target) / target.clamp_min(1e-12)
    per_ray = torch.where(measured, robust(residual, options.depth_loss, options.depth_loss_scale), 0.0)
    return options.depth_loss_weight * per_ray.sum() / n


def depth_metrics(outputs: Dict[str, Tensor], batch: Dict[str, Tensor], valid: Tensor) -> Dict[str, float]:
    """ns-eval's geometry errors of a view with a target, in the dataparser's scaled units: `distance_rmse`
    (rendered distance against the sensor's) and `depth_rmse` (rendered z against the target's z, on rays where
    z is defined); {} without a target. valid [h, w] bool."""
    target = batch.get(TARGET_KEY)
    if target is None:
        return {}
    target = target.to(outputs["distance"].device)
    measured = valid & (target[..., 0] > 0)
    if not bool(measured.any()):
        return {}
    err = (outputs["distance"][..., 0] - target[..., 0])[measured]
    found = {"distance_rmse": float(err.square().mean().sqrt())}
    distance, depth = outputs["distance"][..., 0], outputs["depth"][..., 0]
    z_ok = measured & outputs["depth_defined"][..., 0] & (distance > 0)
    if bool(z_ok.any()):  # the target's z: its distance times the ray's unit z, depth / distance
        z_err = depth - target[..., 0] * depth / distance.clamp_min(1e-12)
        found["depth_rmse"] = float(z_err[z_ok].square().mean().sqrt())
    return found
