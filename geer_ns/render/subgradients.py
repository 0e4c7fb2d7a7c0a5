"""The one rule at every clamp of the renderer, in both backends: a value exactly on its clamp (a tie) gets the
clamped side's derivative, 0. So max(x, lo) passes the gradient where x > lo, min(x, hi) where x < hi.

Why this side: it is torch's own rule (clamp_min, clamp_max, relu, where(x > lo, ...) all give 0 at the tie;
checked on torch 2.14.1), so any clamp written with torch agrees with the kernels without a second thought;
both sides are valid subgradients, and a tie is a single point of the parameter space. The kernels spell the
same comparisons (csrc/geer_math.h sh_backward, preprocess_backward_gaussian; csrc/geer_ray.h eval_pair,
ray_backward_step). Written as explicit masks here, not left to how a torch version differentiates clamp.

Where the renderer clamps (twin / kernels): the SH color at 0 and the SH direction's norm at tiny (sh.py /
sh_backward), scales at MIN_SCALE (transforms.whitening / preprocess_backward_gaussian), |d_u|^2 at tiny and
alpha at 0.99 (transmittance.py / eval_pair, ray_backward_step), depth = max(t*, 0) (half_line_sq /
half_line_backward), the accumulation under the expected depth (outputs.images, shared). normalize_quats' clamps
only guard the zero quaternion, which render refuses (q / |q| does not depend on them); the PBF has no gradient.
tests/test_clamp_ties.py probes the ties against one-sided finite differences.

Thresholds are not clamps: the 1/255 skip and the 1e-4 stop switch a pair off (a jump, not a kink), and a pair
exactly on a threshold is kept with its ordinary derivative (transmittance.pair_alpha, composite).
"""

from __future__ import annotations

import torch
from torch import Tensor


def floor_at(x: Tensor, lo: float) -> Tensor:
    """max(x, lo); the derivative of x where x > lo, 0 elsewhere (also at x == lo)."""
    return torch.where(x > lo, x, lo)


def cap_at(x: Tensor, hi: float) -> Tensor:
    """min(x, hi); the derivative of x where x < hi, 0 elsewhere (also at x == hi)."""
    return torch.where(x < hi, x, hi)
