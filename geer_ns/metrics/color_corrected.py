"""Color-corrected image metrics: psnr_cc and ssim_cc.

Before the metric, the prediction's colors are mapped by the affine color transform (3x3 matrix + offset)
that best fits the ground truth over the valid pixels, in least squares, one fit per image (as the bilateral-
grid and PPISP papers evaluate). A run that renders the scene right but at another exposure or white balance
than a test image scores as well as one that guessed the image's exposure: runs with and without appearance
compensation compare on the scene, plain psnr still on the images.
"""

from __future__ import annotations

from typing import Callable, Dict

import torch
from torch import Tensor


def affine_color_fit(pred: Tensor, gt: Tensor, valid: Tensor) -> Tensor:
    """pred [H, W, 3] mapped by the least-squares affine color transform to gt over valid [H, W] (float64 fit;
    the identity when fewer than 4 pixels are valid)."""
    x = pred[valid].double()
    if x.shape[0] < 4:
        return pred
    a = torch.cat([x, torch.ones_like(x[:, :1])], dim=-1)  # [P, 4]
    # Normal equations with a tiny ridge: a flat image (rank-deficient colors) still gets a finite fit.
    ata = a.T @ a + 1e-8 * torch.eye(4, dtype=a.dtype, device=a.device) * a.shape[0]
    coeffs = torch.linalg.solve(ata, a.T @ gt[valid].double())  # [4, 3]
    full = torch.cat([pred.double(), torch.ones_like(pred[..., :1]).double()], dim=-1)
    return (full @ coeffs).to(pred.dtype)


def color_corrected_metrics(pred: Tensor, gt: Tensor, valid: Tensor,
                            ssim: Callable[[Tensor, Tensor], Tensor]) -> Dict[str, float]:
    """{"psnr_cc", "ssim_cc"} of pred [H, W, 3] against gt [H, W, 3] over valid [H, W]; `ssim` takes
    (gt, pred) as [1, 3, H, W] (the model's SSIM module). Invalid pixels are set to gt before SSIM."""
    corrected = affine_color_fit(pred, gt, valid).clamp(0.0, 1.0)
    corrected = torch.where(valid[..., None], corrected, gt)
    found: Dict[str, float] = {}
    if bool(valid.any()):
        mse = ((corrected - gt) ** 2)[valid].mean().clamp_min(1e-10)
        found["psnr_cc"] = float(-10.0 * torch.log10(mse))
    found["ssim_cc"] = float(ssim(gt.permute(2, 0, 1)[None], corrected.permute(2, 0, 1)[None]))
    return found
