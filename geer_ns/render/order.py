"""The compositing order: one per view (the tile list's, by the distance to each Gaussian's mean) or each ray's own
(its pairs by their peak's position on the ray, max(t*, 0), ties in list order): csrc/geer_order.h.

A ray blends a pending pair once no list entry still to come can have a smaller key. `key_lower_bounds` gives
each Gaussian the bound its entries carry: a pair is kept only where q <= q_max, so the closest point p of the
ray's line lies in the Gaussian's q_max-ellipsoid and its key |p - origin| is at least the ellipsoid's distance
from the camera centre less |origin|. Derivation and measurements: docs/renderer.md, "Compositing order".
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .transforms import MIN_SCALE

# Relative slack on the bound, far above the rounding of a float32 t* (a looser bound only delays blends).
_SLACK = 1e-4


@dataclass(frozen=True)
class CompositeOrder:
    """How each ray composites its tile's pairs.

    mode: "view" (the list's per-view order) or "ray" (each ray's own order). window: the pending pairs a ray holds
    in "ray" mode; 0 = as many as it needs (the exact order; the CPU build), K > 0 = a window of K, exact while a
    ray holds at most K, the smallest of K + 1 blended first beyond (the CUDA kernels hold 64).
    """

    mode: str = "view"
    window: int = 0

    def __post_init__(self):
        if self.mode not in ("view", "ray"):
            raise ValueError(f"composite order: mode must be 'view' or 'ray', got {self.mode!r}")
        if self.window < 0:
            raise ValueError(f"composite order: window must be >= 0 (0: exact), got {self.window}")

    @property
    def per_ray(self) -> bool:
        return self.mode == "ray"

    @classmethod
    def parse(cls, text: "str | CompositeOrder | None") -> "CompositeOrder":
        """'view', 'ray' (exact) or 'ray:K' (a window of K pending pairs); a CompositeOrder passes through."""
        if text is None:
            return cls()
        if isinstance(text, CompositeOrder):
            return text
        mode, _, window = str(text).partition(":")
        try:
            return cls(mode, int(window) if window else 0)
        except ValueError as err:
            if "composite order" in str(err):
                raise
            raise ValueError(f"composite order: expected 'view', 'ray' or 'ray:K', got {text!r}") from None

    def __str__(self) -> str:
        return self.mode if self.mode == "view" or self.window == 0 else f"ray:{self.window}"


def key_lower_bounds(means_c: Tensor, scales: Tensor, opacities: Tensor, o_u: Tensor,
                     origin_offset: float | Tensor = 0.0) -> Tensor:
    """[N] the smallest key max(t*, 0) any kept pair of each Gaussian can have: the distance from the camera centre
    to the Gaussian's q_max-ellipsoid (q_max = 2 ln(255 opacity), transmittance.alpha_level_sq: a kept pair's
    closest point lies in it) bounded from below two ways, the larger taken: |mean_c| - k s_max (the ellipsoid in
    the ball of radius k s_max, k = sqrt(q_max)) and s_min (|o_u| - k) (|x| = |S' (y - o_u)| >= s_min |y - o_u|
    for a point y of the canonical ball of radius k, o_u the camera there: tight for a wall seen face on), less
    the rays' largest origin offset, at least 0, shrunk by a relative slack. means_c [N,3] camera frame, scales
    [N,3], opacities [N], o_u [N,3] the camera centre in each Gaussian's canonical frame (the preprocess's);
    origin_offset: the largest distance of a ray's origin from the camera centre (moving.MovingRays.offset)."""
    with torch.no_grad():
        f64 = torch.float64
        k = (2.0 * torch.log(255.0 * opacities.detach().to(f64))).clamp_min(0).sqrt()
        s = scales.detach().to(f64).clamp_min(MIN_SCALE)
        ball = means_c.detach().to(f64).norm(dim=-1) - k * s.amax(-1) * (1 + _SLACK)
        facing = s.amin(-1) * (o_u.detach().to(f64).norm(dim=-1) - k * (1 + _SLACK))
        offset = torch.as_tensor(origin_offset, dtype=f64, device=means_c.device)
        lower = torch.maximum(ball, facing) * (1 - _SLACK) - offset * (1 + _SLACK)
        return lower.clamp_min(0).to(means_c.dtype).contiguous()

