"""Stage: view-dependent color from real spherical harmonics, degrees 0-3.

Same basis, ordering and +0.5 offset as 3DGS/gsplat, so splatfacto's `features_dc`/`features_rest`
are used unchanged. Bands above the active degree are never evaluated (skip what is not needed).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .subgradients import floor_at

_C0 = 0.5 / math.sqrt(math.pi)  # 0.28209479177387814
_C1 = math.sqrt(3.0 / (4.0 * math.pi))
_C2 = (
    0.5 * math.sqrt(15.0 / math.pi),
    -0.5 * math.sqrt(15.0 / math.pi),
    0.25 * math.sqrt(5.0 / math.pi),
    -0.5 * math.sqrt(15.0 / math.pi),
    0.25 * math.sqrt(15.0 / math.pi),
)
_C3 = (
    -0.25 * math.sqrt(35.0 / (2.0 * math.pi)),
    0.5 * math.sqrt(105.0 / math.pi),
    -0.25 * math.sqrt(21.0 / (2.0 * math.pi)),
    0.25 * math.sqrt(7.0 / math.pi),
    -0.25 * math.sqrt(21.0 / (2.0 * math.pi)),
    0.25 * math.sqrt(105.0 / math.pi),
    -0.25 * math.sqrt(35.0 / (2.0 * math.pi)),
)


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def sh_to_color(coeffs: Tensor, dirs: Tensor, degree: int) -> Tensor:
    """RGB [N, 3] from SH coefficients [N, K, 3] (K >= (degree+1)^2) and view directions [N, 3].

    Directions need not be normalized. Output is clamped at 0 from below (as gsplat does); a color exactly
    at 0 gets no gradient (subgradients.floor_at, as csrc/geer_math.h sh_backward).
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    if coeffs.shape[1] < num_sh_bases(degree):
        raise ValueError(
            f"colors: SH degree {degree} needs {num_sh_bases(degree)} coefficients, got {coeffs.shape[1]}"
        )
    result = _C0 * coeffs[:, 0]
    if degree >= 1:
        d = dirs / floor_at(dirs.norm(dim=-1, keepdim=True), torch.finfo(dirs.dtype).tiny)
        x, y, z = (t[:, None] for t in d.unbind(-1))
        result = result - _C1 * y * coeffs[:, 1] + _C1 * z * coeffs[:, 2] - _C1 * x * coeffs[:, 3]
        if degree >= 2:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            result = (
                result
                + _C2[0] * xy * coeffs[:, 4]
                + _C2[1] * yz * coeffs[:, 5]
                + _C2[2] * (2 * zz - xx - yy) * coeffs[:, 6]
                + _C2[3] * xz * coeffs[:, 7]
                + _C2[4] * (xx - yy) * coeffs[:, 8]
            )
            if degree >= 3:
                result = (
                    result
                    + _C3[0] * y * (3 * xx - yy) * coeffs[:, 9]
                    + _C3[1] * xy * z * coeffs[:, 10]
                    + _C3[2] * y * (4 * zz - xx - yy) * coeffs[:, 11]
                    + _C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * coeffs[:, 12]
                    + _C3[4] * x * (4 * zz - xx - yy) * coeffs[:, 13]
                    + _C3[5] * z * (xx - yy) * coeffs[:, 14]
                    + _C3[6] * x * (xx - 3 * yy) * coeffs[:, 15]
                )
    return floor_at(result + 0.5, 0.0)
