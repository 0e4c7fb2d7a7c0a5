"""Stages 4-5 over the tile lists, in pieces of at most `max_pairs` (ray, Gaussian) pairs, forward and backward.

Each group of rays (a tile) is blended against its front-to-back Gaussian list. Groups with similar list
lengths are batched into one piece; a group whose rays x list exceeds `max_pairs` is blended in pieces
along its list, each entering with the transmittance the previous piece left (composite's t_start).

Memory model. The per-pair work never holds more than one piece: the forward runs under no_grad and
keeps, besides its inputs and the three per-ray outputs, only the transmittance each piece starts from
([rays of the piece], a few per ray); the backward recomputes one piece at a time with autograd (a custom
Function, so nothing per pair is saved between forward and backward), walking each group's pieces back
to front and passing dL/d(transmittance) from one piece to the previous. Peak memory is therefore

    O(N) per-Gaussian inputs and gradients + O(tile lists) + O(rays) + c * max_pairs,

with c the bytes one pair costs inside a piece (the backward's autograd graph of one piece: measured about
300 bytes in float32, 520 in float64), independent of how many Gaussians each
ray sees (tests/test_blend_memory.py). The default max_pairs = 2^20 thus bounds the per-pair part at about
0.3 GB (float32).

Two per-Gaussian by-products. max_weight: each Gaussian's largest blend weight over the rays, from the
forward's pieces (no gradient). absgrad (absgrad.py): when the sink is given, the backward also asks autograd
for each piece's per-pair dL/dq and dL/d(depth), forms each pair's dL/do_u from them (absgrad.pair_o_u_grad)
and sums |A_n dL/do_u| over the piece's rays: more per-pair tensors inside a piece, still O(max_pairs).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .absgrad import pair_absgrad, pair_o_u_grad
from .composite import composite, median_crossing
from .transmittance import canonical_ray_response, half_line_sq, moving_ray_response, pair_alpha


def _plan(counts: Tensor, rays_per_group: int, max_pairs: int,
          whole_lists: bool = False) -> list[tuple[Tensor, list[tuple[int, int]]]]:
    """[(groups, [(k0, k1), ...])]: groups batched by similar list length (longest first), each batch with
    the list ranges it is blended in. Groups without Gaussians (empty or inactive tiles) are left out.
    whole_lists: never split a group's list (the per-ray order sorts a ray's whole list; max_pairs then bounds
    the batching only)."""
    by_count = torch.sort(counts, descending=True, stable=True).indices
    by_count = by_count[counts[by_count] > 0]
    plan, start, p = [], 0, rays_per_group
    while start < by_count.numel():
        k = int(counts[by_count[start]])
        if p * k <= max_pairs or whole_lists:
            n_groups, pieces = max(1, max_pairs // (p * k)), [(0, k)]
        else:  # one group alone exceeds the budget: blend its list in pieces
            step = max(1, max_pairs // p)
            n_groups, pieces = 1, [(k0, min(k0 + step, k)) for k0 in range(0, k, step)]
        plan.append((by_count[start : start + n_groups], pieces))
        start += n_groups
    return plan


def _blend_piece(o_u, whiten, opacities, colors, dirs, r_ok, g_ok, t_start, median=False, origins=None,
                 per_ray=False):
    """One piece: o_u [G,K,3], whiten [G,K,3,3], opacities [G,K], colors [G,K,3] of the listed Gaussians,
    dirs [G,P,3] (origins [G,P,3]: the rays' own origins, None: the camera centre); r_ok [G,P] / g_ok [G,K] mask
    padding and invalid rays. Returns (rgb, depth sum, accumulation, t_end) per ray and the pairs' q, depth and
    blend weight [G,P,K] (list order); with `median`, the per-ray depth where the piece takes the transmittance
    below 0.5 (composite.median_crossing) after them. per_ray: each ray composites its pairs in its own order
    (order.py: by depth = max(t*, 0), ties in list order), the piece being a whole list."""
    if origins is None:
        dist_sq, t_star = canonical_ray_response(o_u, whiten, dirs)
        o_sq = None
    else:
        dist_sq, t_star, o_sq = moving_ray_response(o_u, whiten, dirs, origins)
    q, depth, _ = half_line_sq(dist_sq, t_star, o_u, o_sq)
    alpha = pair_alpha(q, opacities[:, None, :], r_ok[:, :, None] & g_ok[:, None, :])
    ordered_alpha, ordered_depth, ordered_colors = alpha, depth, colors
    if per_ray:  # pairs not kept (alpha 0) blend nothing: last
        key = torch.where(alpha > 0, depth, torch.full_like(depth, float("inf"))).detach()
        perm = torch.sort(key, dim=-1, stable=True).indices
        ordered_alpha, ordered_depth = alpha.gather(-1, perm), depth.gather(-1, perm)
        ordered_colors = colors[:, None].expand(*perm.shape, 3).gather(-2, perm[..., None].expand(*perm.shape, 3))
    *sums, weights = composite(ordered_alpha, ordered_colors, ordered_depth, t_start)
    crossed = median_crossing(ordered_alpha, ordered_depth, weights, t_start) if median else None
    if per_ray:
        weights = torch.zeros_like(weights).scatter(-1, perm, weights)
    if median:
        return sums, q, depth, weights, crossed
    return sums, q, depth, weights


class _BlendLists(torch.autograd.Function):
    """(o_u, W, opacity, color per Gaussian) -> (rgb [R,3], depth sum [R], accumulation [R]) per ray,
    max_weight [N] and the median distance [R] (neither with a gradient); with absgrad's (rows, sink), the
    sink's gradient is the absgrad sums; origins [R,3] (or None): the rays' own origins."""

    @staticmethod
    def forward(ctx, o_u, whiten, opacities, colors, dirs, ray_valid, ray_index, lists, counts, max_pairs, rows,
                sink, origins=None, per_ray=False):
        n_rays, p = dirs.shape[0], ray_index.shape[1]
        out = (o_u.new_zeros(n_rays, 3), o_u.new_zeros(n_rays), o_u.new_zeros(n_rays))
        max_weight = o_u.new_zeros(o_u.shape[0])
        median = o_u.new_zeros(n_rays)
        plan = _plan(counts, p, max_pairs, per_ray)
        starts = []
        for sel, pieces in plan:
            r_idx = ray_index[sel]
            r_ok = (r_idx >= 0) & ray_valid[r_idx.clamp_min(0)]
            d = dirs[r_idx.clamp_min(0)]
            org = None if origins is None else origins[r_idx.clamp_min(0)]
            t = o_u.new_ones(r_idx.shape)
            sums = [0.0, 0.0, 0.0, 0.0]
            for k0, k1 in pieces:
                starts.append(t)
                g_idx = lists[sel, k0:k1]
                g, listed = g_idx.clamp_min(0), g_idx >= 0
                (*piece, t), _, _, weights, crossed = _blend_piece(o_u[g], whiten[g], opacities[g], colors[g], d,
                                                                   r_ok, listed, t, median=True, origins=org,
                                                                   per_ray=per_ray)
                sums = [s + x for s, x in zip(sums, (*piece, crossed))]
                max_weight.scatter_reduce_(0, g[listed], weights.amax(dim=-2)[listed], reduce="amax")
            keep = r_idx >= 0
            for o, s in zip((*out, median), sums):
                o[r_idx[keep]] = s[keep]
        t_starts = torch.cat([s.reshape(-1) for s in starts]) if starts else o_u.new_zeros(0)
        ctx.save_for_backward(o_u, whiten, opacities, colors, dirs, ray_valid, ray_index, lists, counts, t_starts,
                              rows, origins)
        ctx.max_pairs, ctx.per_ray = max_pairs, per_ray
        ctx.mark_non_differentiable(max_weight, median)
        return (*out, max_weight, median)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_rgb, g_depth, g_acc, _g_max_weight, _g_median):
        (o_u, whiten, opacities, colors, dirs, ray_valid, ray_index, lists, counts, t_starts, rows,
         origins) = ctx.saved_tensors
        params = (o_u, whiten, opacities, colors)
        grads = [x.new_zeros(x.shape) for x in params]  # contiguous, whatever the inputs' strides
        with_dirs = ctx.needs_input_grad[4]
        g_dirs = dirs.new_zeros(dirs.shape) if with_dirs else None
        with_origins = origins is not None and ctx.needs_input_grad[12]
        g_origins = origins.new_zeros(origins.shape) if with_origins else None
        with_absgrad = rows is not None and ctx.needs_input_grad[11]
        absgrad = o_u.new_zeros(o_u.shape[0], 2) if with_absgrad else None
        offset = 0
        for sel, pieces in _plan(counts, ray_index.shape[1], ctx.max_pairs, ctx.per_ray):
            r_idx = ray_index[sel]
            keep = r_idx >= 0
            r_ok = keep & ray_valid[r_idx.clamp_min(0)]
            d = dirs[r_idx.clamp_min(0)]
            org = None if origins is None else origins[r_idx.clamp_min(0)]
            m = keep.to(o_u.dtype)
            g_out = (g_rgb[r_idx.clamp_min(0)] * m[..., None], g_depth[r_idx.clamp_min(0)] * m,
                     g_acc[r_idx.clamp_min(0)] * m)
            size = r_idx.numel()
            first = offset
            offset += size * len(pieces)
            g_t = torch.zeros_like(d[..., 0])  # dL/d(transmittance leaving the piece)
            for i in reversed(range(len(pieces))):
                k0, k1 = pieces[i]
                t0 = t_starts[first + i * size : first + (i + 1) * size].reshape(r_idx.shape)
                g_idx = lists[sel, k0:k1]
                g = g_idx.clamp_min(0)
                with torch.enable_grad():
                    leaves = [x[g].detach().requires_grad_(True) for x in params]
                    t0 = t0.detach().requires_grad_(True)
                    d_leaf = d.detach().requires_grad_(with_dirs)
                    o_leaf = None if org is None else org.detach().requires_grad_(with_origins)
                    (*outs, t_end), q, depth, weights = _blend_piece(*leaves, d_leaf, r_ok, g_idx >= 0, t0,
                                                                     origins=o_leaf, per_ray=ctx.per_ray)
                    loss = sum((go * o).sum() for go, o in zip(g_out, outs)) + (g_t * t_end).sum()
                    wanted = leaves + [t0] + ([q, depth] if with_absgrad else []) + ([d_leaf] if with_dirs else []) \
                        + ([o_leaf] if with_origins else [])
                    piece_grads = torch.autograd.grad(loss, wanted, allow_unused=True)
                if with_origins:
                    if piece_grads[-1] is not None:
                        g_origins.index_add_(0, r_idx[keep], piece_grads[-1][keep])
                    piece_grads = piece_grads[:-1]
                if with_dirs and piece_grads[-1] is not None:
                    g_dirs.index_add_(0, r_idx[keep], piece_grads[-1][keep])
                g_ok = (g_idx >= 0).reshape(-1)
                for acc, pg in zip(grads, piece_grads[:4]):
                    if pg is not None:
                        flat = pg.reshape(g.numel(), -1)[g_ok]
                        acc.view(acc.shape[0], -1).index_add_(0, g.reshape(-1)[g_ok], flat)
                g_t = piece_grads[4] if piece_grads[4] is not None else torch.zeros_like(g_t)
                if with_absgrad:
                    o_pair = leaves[0].detach()
                    if org is not None:  # each pair's own canonical origin o_u + W origin
                        o_pair = o_pair[..., None, :, :] + torch.einsum("gkij,gpj->gpki", leaves[1].detach(), org)
                    g_o = pair_o_u_grad(*piece_grads[5:7], o_pair, leaves[1].detach(), d, depth.detach())
                    over_rays = pair_absgrad(rows[g], g_o, weights.detach() > 0).sum(-3)  # [G, K, 2]
                    absgrad.index_add_(0, g.reshape(-1)[g_ok], over_rays.reshape(-1, 2)[g_ok])
        return (*grads, g_dirs, None, None, None, None, None, None, absgrad, g_origins, None)


def blend_lists(o_u, whiten, opacities, colors, dirs, ray_valid, ray_index, lists, counts, max_pairs, absgrad=None,
                origins=None, per_ray=False):
    """Blend each group of rays ray_index [G, P] (-1 padded) against its Gaussian list lists [G, K] (-1
    padded, counts [G] entries), at most max_pairs pairs at a time (see the module's memory model).

    Returns per-ray rgb [R, 3] (no background), depth sum [R] and accumulation [R], rays in no group (empty or
    inactive tiles) 0, max_weight [N], each Gaussian's largest blend weight (0: never blended; no gradient), and
    the median distance [R], where the transmittance crosses 0.5 (0: it never does; no gradient).
    Differentiable w.r.t. o_u, whiten, opacities, colors and dirs [R, 3]; absgrad: (offset rows [N, 2, 3], sink [N, 2])
    (absgrad.py), whose sink gets the absgrad sums as its gradient; origins [R, 3] (None: every ray from the camera
    centre): each ray's own origin in the camera frame (rolling shutter), differentiable too. per_ray: each ray
    composites its pairs in its own order (order.py), not the list's; its groups' lists are then never split.
    """
    rows, sink = absgrad if absgrad is not None else (None, None)
    return _BlendLists.apply(o_u, whiten, opacities, colors, dirs, ray_valid, ray_index, lists, counts, max_pairs,
                             rows, sink, origins, per_ray)
