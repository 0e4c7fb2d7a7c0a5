"""Images moved between two central cameras at the same pose, by rays: a pixel of the destination takes the
source's color where its ray lands (bilinear), and is marked uncovered where the source cannot see it.

Used by geer-compare both ways: the capture undistorted to the widest sensible pinhole (splatfacto's usual
work-around), and that pinhole's renders brought back to the capture's own pixels to be scored there.
"""

from __future__ import annotations

import math
from typing import Tuple

import numpy as np
import torch
from torch import Tensor

from geer_ns.cameras import CameraModel, EquidistantCamera, PinholeCamera
from geer_ns.errors import OptionError


def landing(src: CameraModel, dst: CameraModel) -> Tuple[Tensor, Tensor]:
    """Where each destination pixel center's ray lands in the source: (pixels [H, W, 2] float64, covered [H, W])."""
    dirs, valid = dst.pixel_rays(torch.float64)
    pixels, ok = src.project(dirs)
    inside = (pixels[..., 0] >= 0) & (pixels[..., 0] <= src.width) & (pixels[..., 1] >= 0) & \
        (pixels[..., 1] <= src.height)
    return pixels, valid & ok & inside


def resample(image: Tensor, src: CameraModel, dst: CameraModel, fill: Tensor | float = 0.0) -> Tuple[Tensor, Tensor]:
    """image [h, w, C] seen by `src` -> (image [H, W, C] as `dst` sees it, covered [H, W] bool); uncovered
    pixels get `fill`. Bilinear, with pixel centers at (j + 0.5, i + 0.5) and edge pixels clamped."""
    pixels, covered = landing(src, dst)
    grid = torch.stack([pixels[..., 0] / src.width * 2 - 1, pixels[..., 1] / src.height * 2 - 1], dim=-1)
    out = torch.nn.functional.grid_sample(image.permute(2, 0, 1)[None].double(), grid[None], mode="bilinear",
                                          padding_mode="border", align_corners=False)[0].permute(1, 2, 0)
    fill_t = torch.as_tensor(fill, dtype=out.dtype).expand_as(out)
    out = torch.where(covered[..., None], out, fill_t)
    return out.to(image.dtype), covered


def widest_pinhole(native: CameraModel, fov_deg: float) -> PinholeCamera:
    """A pinhole of the native image's size and center with `fov_deg` across its width (square pixels)."""
    if not 0 < fov_deg < 180:
        raise OptionError(f"--pinhole-fov-deg {fov_deg}: a pinhole's field of view is between 0 and 180 degrees")
    f = 0.5 * native.width / math.tan(math.radians(fov_deg) / 2)
    return PinholeCamera(native.width, native.height, f, f, native.width / 2, native.height / 2)


def equidistant_like(native: CameraModel) -> CameraModel:
    """The ideal equidistant fisheye (gsplat's `camera_model="fisheye"`) with the native focal and center."""
    return EquidistantCamera(native.width, native.height, native.fx, native.fy, native.cx, native.cy)


def to_uint8(image: Tensor) -> np.ndarray:
    return (image.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).numpy()
