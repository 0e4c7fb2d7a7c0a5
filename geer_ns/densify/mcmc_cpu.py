"""MCMC glue: gsplat's relocation and covariance ops are CUDA-only; CPU tensors use these torch versions."""

from __future__ import annotations

from typing import Tuple

import torch
import torch.nn.functional as F
from torch import Tensor


def relocation_torch(opacities: Tensor, scales: Tensor, ratios: Tensor, binoms: Tensor) -> Tuple[Tensor, Tensor]:
    """MCMC relocation (Kheradmand et al. 2024, Eq. 9): N copies of a Gaussian that together render like it."""
    shape = opacities.shape  # [N] or [N, 1]; the result keeps it
    opacities = opacities.reshape(-1)
    n_max = binoms.shape[0]
    n = ratios.reshape(-1).clamp(1, n_max).long()
    new_opacities = 1.0 - (1.0 - opacities) ** (1.0 / n.to(opacities.dtype))
    i = torch.arange(1, n_max + 1, device=opacities.device)  # [I]
    k = torch.arange(n_max, device=opacities.device)  # [K]
    coeff = binoms[(i - 1)[:, None], k[None, :]] * (-1.0) ** k / torch.sqrt(k + 1.0)  # [I, K]
    coeff = torch.where(k[None, :] <= (i - 1)[:, None], coeff, torch.zeros_like(coeff))
    powers = new_opacities[:, None] ** (k[None, :] + 1.0)  # [N, K]
    terms = powers @ coeff.T.to(powers.dtype)  # [N, I]: inner sums over k
    used = i[None, :] <= n[:, None]
    denom = torch.where(used, terms, torch.zeros_like(terms)).sum(-1)
    new_scales = (opacities / denom)[:, None] * scales
    return new_opacities.reshape(shape), new_scales


def install_mcmc_cpu_ops() -> None:
    """Route gsplat.strategy.ops' CUDA-only calls to torch implementations for CPU tensors."""
    import gsplat.strategy.ops as ops
    from geer_ns.gsplat_private import quat_scale_to_covar_preci as torch_covar

    if getattr(ops, "_geer_cpu_ops", False):
        return
    cuda_relocation, cuda_covar = ops.compute_relocation, ops.quat_scale_to_covar_preci

    def compute_relocation(opacities, scales, ratios, binoms):
        if opacities.is_cuda:
            return cuda_relocation(opacities, scales, ratios, binoms)
        return relocation_torch(opacities, scales, ratios, binoms)

    def quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=True, triu=False):
        fn = cuda_covar if quats.is_cuda else torch_covar
        return fn(F.normalize(quats, dim=-1), scales, compute_covar=compute_covar, compute_preci=compute_preci, triu=triu)

    ops.compute_relocation = compute_relocation
    ops.quat_scale_to_covar_preci = quat_scale_to_covar_preci
    ops._geer_cpu_ops = True
