"""Stage 5: front-to-back alpha compositing (paper Eq. B.3), with 3DGS's early termination: a ray
stops before the Gaussian that would bring its transmittance below 1e-4."""

from __future__ import annotations

import torch
from torch import Tensor

T_MIN = 1e-4


def composite(alpha: Tensor, colors: Tensor, depths: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """alpha [..., P, K] (front to back, 0 = no contribution), colors [..., K, 3], depths [..., P, K].

    Returns (rgb [..., P, 3] without background, accumulated depth [..., P], accumulation [..., P]).
    """
    one_minus = 1.0 - alpha  # >= 0.01, so cumprod's backward never divides by zero
    t_after = torch.cumprod(one_minus, dim=-1)
    t_before = torch.cat([torch.ones_like(t_after[..., :1]), t_after[..., :-1]], dim=-1)
    weights = torch.where(t_after >= T_MIN, alpha * t_before, torch.zeros_like(alpha))
    rgb = torch.einsum("...pk,...kc->...pc", weights, colors)
    return rgb, (weights * depths).sum(-1), weights.sum(-1)
