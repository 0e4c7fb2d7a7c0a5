"""Stage: view-dependent color from real spherical harmonics, degrees 0-3.

Same basis, ordering and +0.5 offset as 3DGS/gsplat, so splatfacto's `features_dc`/`features_rest`
are used unchanged. Bands above the active degree are never evaluated (skip what is not needed); a
Gaussian's bands above its own degree add nothing (the kernels skip them; geer_ns/sh_degrees).
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


def sh_basis(dirs: Tensor, degree: int) -> list:
    """The (degree+1)^2 real SH basis functions at the directions [N, 3] (need not be normalized): [N, 1] each
    (the constant first as a float), csrc/geer_math.h sh_basis's values and rounding."""
    basis: list = [_C0]
    if degree < 1:
        return basis
    d = dirs / floor_at(dirs.norm(dim=-1, keepdim=True), torch.finfo(dirs.dtype).tiny)
    x, y, z = (t[:, None] for t in d.unbind(-1))
    basis += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree < 2:
        return basis
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    basis += [_C2[0] * xy, _C2[1] * yz, _C2[2] * (2 * zz - xx - yy), _C2[3] * xz, _C2[4] * (xx - yy)]
    if degree < 3:
        return basis
    return basis + [_C3[0] * y * (3 * xx - yy), _C3[1] * xy * z, _C3[2] * y * (4 * zz - xx - yy),
                    _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy), _C3[5] * z * (xx - yy),
                    _C3[6] * x * (xx - 3 * yy)]


def sh_band_colors(coeffs: Tensor, dirs: Tensor, degree: int) -> Tensor:
    """[N, degree + 1, 3] each band's part of the color (before the +0.5 offset and the clamp), the bands of
    sh_to_color's sum."""
    basis = sh_basis(dirs, degree)
    bands = []
    for band in range(degree + 1):
        term = basis[band * band] * coeffs[:, band * band]
        for k in range(band * band + 1, (band + 1) ** 2):
            term = term + basis[k] * coeffs[:, k]
        bands.append(term)
    return torch.stack(bands, 1)


def sh_to_color(coeffs: Tensor, dirs: Tensor, degree: int | Tensor) -> Tensor:
    """RGB [N, 3] from SH coefficients [N, K, 3] (K >= (degree+1)^2) and view directions [N, 3].

    `degree`: one for every Gaussian, or each Gaussian's own ([N] integers, at most the degree K holds): a
    Gaussian's bands above its degree are not part of its color, and their coefficients get no gradient.
    Directions need not be normalized. Output is clamped at 0 from below (as gsplat does); a color exactly
    at 0 gets no gradient (subgradients.floor_at, as csrc/geer_math.h sh_backward).
    """
    if isinstance(degree, Tensor):
        coeffs, degree = _own_bands(coeffs, degree)
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    if coeffs.shape[1] < num_sh_bases(degree):
        raise ValueError(
            f"colors: SH degree {degree} needs {num_sh_bases(degree)} coefficients, got {coeffs.shape[1]}"
        )
    basis = sh_basis(dirs, degree)
    result = basis[0] * coeffs[:, 0]
    for k in range(1, len(basis)):  # csrc/geer_math.h sh_to_color's order of the sum
        result = result + basis[k] * coeffs[:, k]
    return floor_at(result + 0.5, 0.0)


def _own_bands(coeffs: Tensor, degrees: Tensor) -> tuple[Tensor, int]:
    """(coeffs with each Gaussian's bands above its degree multiplied by 0, the degree K holds). A zero term adds
    exactly nothing, in csrc/geer_math.h's order of the sum, and passes no gradient to its coefficients."""
    if degrees.shape != (coeffs.shape[0],) or degrees.dtype.is_floating_point or degrees.dtype == torch.bool:
        raise ValueError(f"sh_degree: expected an int or one integer per Gaussian ({coeffs.shape[0]}), got "
                         f"{degrees.dtype} {tuple(degrees.shape)}")
    band = torch.tensor([math.isqrt(k) for k in range(coeffs.shape[1])], device=coeffs.device)  # each basis' band
    mask = degrees.long()[:, None] >= band[None]
    return coeffs * mask[:, :, None].to(coeffs.dtype), int(math.isqrt(coeffs.shape[1]) - 1)
