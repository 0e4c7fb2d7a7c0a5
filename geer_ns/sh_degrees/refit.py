"""A Gaussian's kept bands refit to the colours its training views saw, instead of the higher bands cut off.

The SH bands are orthogonal over the whole sphere, so cutting a Gaussian's colour off at degree d is its best
degree-d fit only for directions spread over the whole sphere. Most Gaussians are seen from a cone of directions;
on that cone the bands up to d, solved again, reproduce the colour far better. Per Gaussian i and degree d this
solves the weighted least squares
    min_c  sum_v W_iv |Y_d(u_iv) c - f_iv|^2  +  rho_i |c - c_i,d|^2
over the training views v (W_iv its blend weight in view v, u_iv its view direction, f_iv its every-band colour
before the +0.5 offset, Y_d the basis up to degree d, c_i,d its current coefficients up to d). The ridge rho_i
(RIDGE times the Gaussian's mean basis energy) keeps what the views do not determine (a Gaussian seen from one
direction) where it was. What is accumulated over the views is the sufficient statistics (the Gram matrix of the
basis, its moment with f, the energy of f), so one pass gives every degree's fit and its residual; they take 93
float64 values per Gaussian (0.7 GB at 1M Gaussians) for the one pass at the choice step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List

import torch
from torch import Tensor

from geer_ns.render.sh import sh_basis

FIT_DEGREE = 2  # the highest degree refit (degree 3 keeps every band as trained)
FIT_BASES = (FIT_DEGREE + 1) ** 2
RIDGE = 1e-3  # relative to the Gaussian's weighted mean basis energy


def basis_up_to_fit(dirs: Tensor) -> Tensor:
    """[K, FIT_BASES] the SH basis up to FIT_DEGREE at view directions dirs [K, 3] (need not be unit)."""
    values = sh_basis(dirs, FIT_DEGREE)  # [K, 1] each, the constant first as a float
    return torch.cat([torch.full_like(values[1], values[0]), *values[1:]], -1)


@dataclass
class SeenColours:
    """Each Gaussian's sufficient statistics over the views that blend it (float64)."""

    gram: Tensor  # [N, FIT_BASES, FIT_BASES] sum_v W_iv y y^T
    moment: Tensor  # [N, FIT_BASES, 3] sum_v W_iv y f^T
    energy: Tensor  # [N] sum_v W_iv |f|^2

    @classmethod
    def zeros(cls, n: int, device) -> "SeenColours":
        z = dict(dtype=torch.float64, device=device)
        return cls(torch.zeros(n, FIT_BASES, FIT_BASES, **z), torch.zeros(n, FIT_BASES, 3, **z), torch.zeros(n, **z))

    def add(self, rows: Tensor, weights: Tensor, basis: Tensor, colours: Tensor) -> None:
        """One view: rows [K] (Gaussian indices), weights [K] their blend weights W_iv, basis [K, FIT_BASES] at
        their view directions, colours [K, 3] their every-band colours f_iv (before +0.5)."""
        y, f, w = basis.double(), colours.double(), weights.double()[:, None]
        self.gram.index_add_(0, rows, (w * y)[:, :, None] * y[:, None, :])
        self.moment.index_add_(0, rows, (w * y)[:, :, None] * f[:, None, :])
        self.energy.index_add_(0, rows, w[:, 0] * f.square().sum(-1))

    def tensors(self) -> List[Tensor]:
        """What a distributed run sums over its processes."""
        return [self.gram, self.moment, self.energy]


def refit(seen: SeenColours, coeffs: Tensor, degree: int) -> tuple[Tensor, Tensor]:
    """Each Gaussian's coefficients up to `degree` (<= FIT_DEGREE) refit to its seen colours (module docstring),
    and the weighted squared colour change that keeping them leaves, sum_v W_iv |Y_d c - f_iv|^2.

    seen: the views' statistics; coeffs [N, K, 3] the current SH coefficients (K >= (degree + 1)^2).
    Returns (coefficients [N, (degree + 1)^2, 3] in coeffs' dtype, errors [N] float64)."""
    n = (degree + 1) ** 2
    gram, moment = seen.gram[:, :n, :n], seen.moment[:, :n]
    current = coeffs[:, :n].double()
    rho = RIDGE * gram.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-300)[:, None, None]
    eye = torch.eye(n, dtype=torch.float64, device=gram.device)
    fit = torch.linalg.solve(gram + rho * eye, moment + rho * current)
    # sum_v W |Y c - f|^2 = c^T G c - 2 c . m + E (each colour channel), never below 0 after rounding
    errors = ((fit * (gram @ fit)).sum((-2, -1)) - 2.0 * (fit * moment).sum((-2, -1)) + seen.energy).clamp_min(0.0)
    return fit.to(coeffs.dtype), errors
