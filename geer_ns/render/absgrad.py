"""AbsGS's densification signal: per-pixel absolute positional gradients, requested with render(absgrad=...).

The caller passes `(lateral, sink)`: lateral [N, 3, 2], per Gaussian two view-space directions (columns), how
its view-space mean moves per unit of two "offset" coordinates; sink [N, 2], a zero tensor that requires grad.
After backward

    sink.grad[n, j] = sum over the view's blended (ray p, Gaussian n) pairs of |dL_p/d offsets[n, j]|,

L_p the part of the loss flowing through ray p's outputs, the offsets' gradient taken through the geometry only
(o_u = -W means_c; the SH color's view dependence is left out, as gsplat's means2d leaves it out). With the
offset rows A_n = -lateral_n^T W_n^T (2 x 3) and g_p = dL_p/d o_u[n], the pair's gradient w.r.t. the camera
center in the Gaussian's canonical frame, that is sum_p |A_n g_p| componentwise: the render backward has every
pair's g_p (csrc/geer_ray.h ray_backward_step: PairGrad.o; the twin: pair_o_u_grad) and sums |A_n g_p| beside
the sum of g_p. The sink is an input of the render's autograd Function and this is the gradient its backward returns, so
it reaches wherever the sink came from (a differentiable all-to-all, say). Nothing else changes: outputs and
all other gradients are the same bits with and without absgrad (tests/test_absgrad.py).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .subgradients import floor_at
from .validate import check_shape


def check_absgrad(absgrad, means: Tensor) -> None:
    """The absgrad argument of render: (lateral [N, 3, 2], sink [N, 2] requiring grad), means' dtype and device."""
    if not (isinstance(absgrad, (tuple, list)) and len(absgrad) == 2):
        raise TypeError("absgrad: expected a pair (lateral [N, 3, 2], sink [N, 2])")
    lateral, sink = absgrad
    n = means.shape[0]
    for name, t, shape in (("lateral", lateral, (n, 3, 2)), ("sink", sink, (n, 2))):
        check_shape(f"absgrad {name}", t, shape)
        if t.dtype != means.dtype or t.device != means.device:
            raise ValueError(f"absgrad {name}: expected {means.dtype} on {means.device} (as means), got {t.dtype} "
                             f"on {t.device}")
    if not sink.requires_grad:
        raise ValueError("absgrad sink: must require grad (its .grad receives the sums)")


def offset_rows(lateral: Tensor, whiten: Tensor) -> Tensor:
    """A_n = -lateral_n^T W_n^T [N, 2, 3] (no gradient): A_n dL/do_u is the gradient w.r.t. the two offsets,
    since d o_u = -W d means_c and d means_c = lateral d offsets."""
    return -torch.einsum("nij,njk->nki", whiten.detach(), lateral.detach())


def pair_o_u_grad(g_q: Tensor, g_depth: Tensor, o_u: Tensor, whiten: Tensor, dirs: Tensor, depth: Tensor) -> Tensor:
    """Per-pair dL/do_u [..., P, K, 3] from dL/dq and dL/d(depth) [..., P, K] of the half-line rule
    (transmittance.half_line_sq; o_u [..., K, 3] or each pair's [..., P, K, 3] (rays with their own origins),
    whiten [..., K, 3, 3], dirs [..., P, 3], depth its output).

    Where t* > 0 (depth > 0): q = D^2 = |m_hat|^2, m_hat = o_u x d_hat, d_hat = d_u / |d_u| (|d_u|^2 floored at
    tiny as in canonical_ray_response), so dq/do_u = 2 d_hat x m_hat, and depth = t* = -(o_u . d_u) / |d_u|^2
    gives -d_hat / |d_u|: csrc/geer_ray.h pair_response_backward's o_u part. Elsewhere q = |o_u|^2 (2 o_u) and
    depth = 0. The cross products, not o_u + t* d_u (the same vector): for needles and disks o_u and t* d_u are
    huge along the thin axis and cancel there, where A_n is huge too (tests/test_absgrad.py's stress scenes).
    """
    d_u = torch.einsum("...kij,...pj->...pki", whiten, dirs)
    inv_norm = torch.rsqrt(floor_at((d_u * d_u).sum(-1, keepdim=True), torch.finfo(d_u.dtype).tiny))
    d_hat = d_u * inv_norm
    o_pair = o_u if o_u.dim() == d_u.dim() else o_u[..., None, :, :].expand_as(d_u)
    m_hat = torch.linalg.cross(o_pair, d_u) * inv_norm
    front = (depth > 0)[..., None]
    g_front = (2.0 * g_q[..., None]) * torch.linalg.cross(d_hat, m_hat) - (g_depth[..., None] * inv_norm) * d_hat
    return torch.where(front, g_front, (2.0 * g_q[..., None]) * o_pair)


def pair_absgrad(rows: Tensor, g_o: Tensor, blended: Tensor) -> Tensor:
    """|A_n g_p| [..., P, K, 2] of each pair (rows [..., K, 2, 3], g_o [..., P, K, 3]), 0 where not `blended`."""
    a = torch.einsum("...kjc,...pkc->...pkj", rows, g_o).abs()
    return torch.where(blended[..., None], a, torch.zeros_like(a))
