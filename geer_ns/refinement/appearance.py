"""Per-image exposure and white balance, per-camera vignetting: the sensor between the scene and an image.

A rendered color c (the scene as the Gaussians hold it, in the images' encoding) becomes what image i of
camera k recorded as

    srgb( gain_i * vignetting_k(theta) * linear(c) ),   gain_i = exp(g_i) per channel,
    vignetting_k(theta) = exp(a_k1 theta^2 + a_k2 theta^4 + a_k3 theta^6),

in linear light (the sRGB transfer curve), theta the ray's angle from the camera's optical axis: the same
falloff at any field of view, fisheye included. g_i's mean over the channels is the image's exposure (natural
log of the gain), its deviations the white balance. Images and cameras start neutral (all zero). The
gains' mean over the images is pulled to zero (`regularization`), so the scene keeps the images' average
exposure instead of drifting against the gains. Unknown images (evaluation views) get the neutral gain and
their camera's vignetting. docs/refinement.md says how to use it.
"""

from __future__ import annotations

from typing import Dict, Optional, Sequence

import torch
from torch import Tensor, nn


def srgb_to_linear(c: Tensor) -> Tensor:
    """The sRGB decoding curve (IEC 61966-2-1), values clamped to [0, 1] first."""
    c = c.clamp(0.0, 1.0)
    return torch.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055).clamp_min(1e-12) ** 2.4)


def linear_to_srgb(x: Tensor) -> Tensor:
    """The sRGB encoding curve; linear values clamped to [0, 1] first (a sensor saturates)."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-12) ** (1.0 / 2.4) - 0.055)


def ray_angles(dirs: Tensor) -> Tensor:
    """Angle of each ray [..., 3] (camera frame, z forward) from the optical axis, in radians, 0..pi."""
    return torch.atan2(dirs[..., :2].norm(dim=-1), dirs[..., 2])


class Appearance(nn.Module):
    """Exposure and white balance of `num_images` images, vignetting of `num_cameras` cameras."""

    def __init__(self, num_images: int, num_cameras: int = 1, vignetting_terms: int = 3):
        super().__init__()
        self.log_gains = nn.Parameter(torch.zeros(num_images, 3))
        self.vignetting = nn.Parameter(torch.zeros(num_cameras, vignetting_terms))
        self.image_camera: Sequence[int] = ()  # camera of each training image (set_cameras)
        self.camera_index: Dict[object, int] = {}  # camera model -> its vignetting

    def set_cameras(self, cameras: Sequence[object], image_camera: Sequence[int]) -> None:
        """One vignetting per distinct camera (`cameras`, hashable models), `image_camera[i]` the camera of
        training image i. Called before the optimizers are made (the vignetting Parameter is replaced)."""
        terms = self.vignetting.shape[1]
        self.vignetting = nn.Parameter(torch.zeros(max(1, len(cameras)), terms, device=self.vignetting.device))
        self.image_camera = [int(i) for i in image_camera]
        self.camera_index = {cam: i for i, cam in enumerate(cameras)}

    def camera_of(self, image: Optional[int], camera: object) -> int:
        """The vignetting of training image `image`, else of camera model `camera` (the first if unknown)."""
        if image is not None and 0 <= image < len(self.image_camera):
            return self.image_camera[image]
        return self.camera_index.get(camera, 0)

    def vignetting_factor(self, theta: Tensor, camera: int = 0) -> Tensor:
        """vignetting_k(theta), same shape as theta."""
        t2 = theta.to(self.vignetting.dtype) ** 2
        powers = torch.stack([t2 ** (k + 1) for k in range(self.vignetting.shape[1])], dim=-1)
        return torch.exp((powers * self.vignetting[camera]).sum(-1))

    def forward(self, rgb: Tensor, dirs: Tensor, image: Optional[int], camera: int = 0) -> Tensor:
        """rgb [H, W, 3] as image `image` of camera `camera` records it (None: an unknown image, neutral gain);
        dirs [H*W, 3] or [H, W, 3] the rays' directions in the camera frame."""
        theta = ray_angles(dirs.reshape(*rgb.shape[:2], 3).to(rgb.device))
        scale = self.vignetting_factor(theta, camera)[..., None]
        if image is not None:
            scale = scale * torch.exp(self.log_gains[image])
        return linear_to_srgb(srgb_to_linear(rgb) * scale.to(rgb.dtype))

    def regularization(self) -> Tensor:
        """The squared mean log gain over the images and channels (the scene's overall brightness is the
        images' average, not a free direction shared by the scene and every gain)."""
        return self.log_gains.mean() ** 2

    def exposure(self) -> Tensor:
        """[num_images] each image's exposure, the mean of its log gains (natural log)."""
        return self.log_gains.mean(dim=-1)
