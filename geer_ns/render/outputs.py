"""What a render returns, and the last step both backends share: background, expected distance, image shape;
the per-ray quantities derived from them (camera-space z). What each output means: docs/outputs.md."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .associate import TileLists
from .pbf import PBF
from .subgradients import floor_at

# Expected depth divides by the accumulation; below this a ray saw nothing and its depth is 0.
MIN_ACCUMULATION = 1e-10


@dataclass
class RenderOutput:
    rgb: Tensor  # [H, W, 3], background composited
    depth: Tensor  # [H, W, 1] expected distance along the ray (0 where nothing was hit); also `.distance`
    accumulation: Tensor  # [H, W, 1]
    visible: Tensor  # [N] bool: associated with at least one active tile
    tile_counts: Tensor  # [n_tiles] Gaussians per tile
    means_c: Tensor  # [N, 3] view-space means; .grad is the densification signal
    pbf: PBF
    tiles: TileLists | None  # None for the brute-force reference and the kernels
    # [N] no gradient: each Gaussian's largest blend weight T_before alpha over the view's rays; 0 where it
    # never blended (not associated, below 1/255 everywhere, only after the rays' early stop)
    max_weight: Tensor
    # [H, W, 1] no gradient: max(t*, 0) of the Gaussian whose blend takes the ray's transmittance below 0.5
    # (0 where it never falls below 0.5)
    median_distance: Tensor | None = None

    @property
    def distance(self) -> Tensor:
        """[H, W, 1] the expected distance along the ray, sum_i w_i t_i / sum_i w_i (0 where nothing was hit)."""
        return self.depth


def images(height: int, width: int, rgb: Tensor, depth_sum: Tensor, acc: Tensor,
           background: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """Per-ray sums [R, 3], [R], [R] -> (rgb with background [H, W, 3], expected depth [H, W, 1],
    accumulation [H, W, 1])."""
    if background is not None:
        rgb = rgb + (1.0 - acc)[:, None] * background.to(rgb.dtype)
    expected_depth = depth_sum / floor_at(acc, MIN_ACCUMULATION)
    return rgb.reshape(height, width, 3), expected_depth.reshape(height, width, 1), acc.reshape(height, width, 1)


def z_depth(distance: Tensor, dirs: Tensor, hit: Tensor) -> tuple[Tensor, Tensor]:
    """Camera-space z of the expected hit point, as splatfacto's `depth`: distance [H, W, 1] times each unit ray
    direction's z (dirs [H*W, 3], camera frame, OpenCV axes); hit [H, W, 1] bool the rays that saw something.

    Returns (depth [H, W, 1], defined [H, W, 1] bool): z is defined where the ray points in front of the image
    plane (d_z > 0, i.e. less than 90 degrees off the optical axis) and hit something; 0 elsewhere (no NaN)."""
    dz = dirs[:, 2].reshape(distance.shape).to(distance.dtype)
    defined = (dz > 0) & hit
    return torch.where(defined, distance * dz, torch.zeros_like(distance)), defined
