"""Image metrics over the valid pixels of a view, and the paper's central / peripheral split (App. G).

geer scores a rendering only where its camera has rays and the dataset's mask allows (a fisheye's corners, a
masked rig): PSNR over those pixels, and separately over the central rectangle of (theta, phi) and the rest.
"""

from __future__ import annotations

from typing import Dict, Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor

from geer_ns.cameras import CameraModel


def central_region(camera: CameraModel, dirs: Tensor, half_angles: Optional[Tuple[float, float]]) -> Optional[Tensor]:
    """[H,W] bool: rays whose (theta, phi) lie inside the central rectangle (paper App. G), None if undefined.

    Args: the camera, its ray directions [H,W,3], the rectangle's half-extents (theta, phi) in radians (None:
    the paper's rule, +-w/(2 fx) by +-h/(2 fy), defined for cameras with a focal length only)."""
    if half_angles is None:
        if not hasattr(camera, "fx"):
            return None
        half_angles = (camera.width / (2.0 * camera.fx), camera.height / (2.0 * camera.fy))
    theta = torch.atan2(dirs[..., 0], dirs[..., 2])
    phi = torch.atan2(dirs[..., 1], dirs[..., 2])
    return (theta.abs() <= half_angles[0]) & (phi.abs() <= half_angles[1])


def downscale_mask(mask: Tensor, factor: int) -> Tensor:
    """[H,W,1] bool -> [H/f,W/f,1]: a coarse cell is valid only if its whole block is."""
    if factor == 1:
        return mask.bool()
    pooled = F.avg_pool2d(mask.float().permute(2, 0, 1)[None], factor, stride=factor)
    return (pooled[0].permute(1, 2, 0) > 1.0 - 1e-6)


def masked_psnr(pred: Tensor, gt: Tensor, mask: Tensor) -> Optional[float]:
    """PSNR over the pixels where mask [H,W] is set (None when there are none)."""
    n = int(mask.sum())
    if n == 0:
        return None
    mse = ((pred - gt) ** 2)[mask].mean().clamp_min(1e-10)
    return float(-10.0 * torch.log10(mse))


def region_psnr(pred: Tensor, gt: Tensor, valid: Tensor, central: Optional[Tensor]) -> Dict[str, float]:
    """central_psnr / peripheral_psnr of pred against gt [H,W,3] over valid [H,W] inside / outside `central`
    [H,W,1]; each omitted when its region has no valid pixel in this view, both when `central` is None."""
    if central is None:
        return {}
    central = central[..., 0].to(valid.device)
    found = {}
    for name, region in (("central_psnr", valid & central), ("peripheral_psnr", valid & ~central)):
        value = masked_psnr(pred, gt, region)
        if value is not None:
            found[name] = value
    return found
