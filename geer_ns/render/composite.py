"""Stage 5: front-to-back alpha compositing (paper Eq. B.3), with 3DGS's early termination: a ray
stops before the Gaussian that would bring its transmittance below 1e-4 (a pair exactly at 1e-4 is
still blended). The stop is piecewise constant: blended pairs get their ordinary derivative, the rest
none, as in csrc/geer_ray.h (ray_forward_step)."""

from __future__ import annotations

import torch
from torch import Tensor

T_MIN = 1e-4


def composite(
    alpha: Tensor, colors: Tensor, depths: Tensor, t_start: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """alpha [..., P, K] (front to back, 0 = no contribution), colors [..., K, 3] (or [..., P, K, 3]: each ray's
    own), depths [..., P, K], and the
    transmittance each ray enters with, t_start [..., P] (1 when None): a list may be blended in pieces.

    Returns (rgb [..., P, 3] without background, accumulated depth [..., P], accumulation [..., P],
    transmittance after the piece [..., P], and the pairs' blend weights T_before alpha [..., P, K], 0 where a
    pair is not blended). The running product starts from t_start, so blending a list in pieces rounds exactly
    as blending it at once (and as the kernels' sequential product).
    """
    one_minus = 1.0 - alpha  # >= 0.01, so cumprod's backward never divides by zero
    if t_start is None:
        t_start = torch.ones_like(one_minus[..., 0])
    t_after = torch.cumprod(torch.cat([t_start[..., None], one_minus], dim=-1), dim=-1)
    t_before, t_after = t_after[..., :-1], t_after[..., 1:]
    weights = torch.where(t_after >= T_MIN, alpha * t_before, torch.zeros_like(alpha))
    if colors.dim() == alpha.dim() + 1:  # per-ray colours [..., P, K, 3] (each ray's own order)
        rgb = torch.einsum("...pk,...pkc->...pc", weights, colors)
    else:
        rgb = torch.einsum("...pk,...kc->...pc", weights, colors)
    # The last transmittance as its own tensor: a view would keep the piece's whole product alive.
    return rgb, (weights * depths).sum(-1), weights.sum(-1), t_after[..., -1].clone(), weights


def median_crossing(alpha: Tensor, depths: Tensor, weights: Tensor, t_start: Tensor | None = None) -> Tensor:
    """[..., P] the depth of the blended pair that takes a ray's transmittance from >= 0.5 to < 0.5 (0 where no
    pair of this piece does), from composite's inputs and its weights (no gradient: an arg-threshold)."""
    one_minus = 1.0 - alpha
    if t_start is None:
        t_start = torch.ones_like(one_minus[..., 0])
    t_after = torch.cumprod(torch.cat([t_start[..., None], one_minus], dim=-1), dim=-1)
    t_before, t_after = t_after[..., :-1], t_after[..., 1:]
    crossing = (weights > 0) & (t_before >= 0.5) & (t_after < 0.5)
    return torch.where(crossing, depths, torch.zeros_like(depths)).sum(-1)
