"""gsplat's classic EWA compositing of projected Gaussians (conics), in PyTorch for a CPU.

Same conventions as gsplat 1.4.0's `isect_tiles` and `rasterize_to_pixels` CUDA kernels (docs/compare.md):

* a Gaussian lands in the 16 x 16 tiles its square of half-side `radius` (gsplat's 3-sigma radius) touches:
  tiles floor((mean - radius) / 16) .. ceil((mean + radius) / 16) - 1, clamped to the image's tiles;
* each tile's Gaussians are blended front to back by depth; a pixel's center is (j + 0.5, i + 0.5);
* sigma = 0.5 (a dx^2 + c dy^2) + b dx dy with conic (a, b, c) and d = mean2d - center,
  alpha = min(0.999, opacity exp(-sigma)); a pair with sigma < 0 or alpha < 1/255 is skipped;
* a pixel stops before the Gaussian that would bring its transmittance to 1e-4 or below;
* color = sum alpha T c + T_final background; alpha = 1 - T_final.

Differentiable with respect to means2d, conics, colors and opacities; the discrete decisions (tiles, skips,
the stop) carry no gradient, as in gsplat's backward. With `absgrad`, the per-pixel absolute gradients of
means2d are summed into `means2d.absgrad` (gsplat's AbsGS statistic). Tiles are evaluated in chunks of at most
`max_pairs` (pixel, Gaussian) pairs, each recomputed in the backward pass (activation checkpointing), so memory
stays bounded by one chunk.

Speed without changing a result: each tile is blended as `block` x `block` pixel blocks, and a block gets only its
tile's Gaussians whose region alpha >= 1/255 (sigma <= ln(255 opacity), an ellipse; its bounding box widened by a
margin) reaches one of the block's pixel centres. The pairs left out are the ones the kernel skips (alpha < 1/255:
no colour, no transmittance, no gradient), so the blend, the stop and the gradients are those of the whole tile.
"""

from __future__ import annotations

import functools
from typing import Optional, Tuple

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

ALPHA_MAX = 0.999  # gsplat 1.4.0 rasterize_to_pixels_fwd.cu: min(0.999f, opac * exp(-sigma))
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4


def _cells(x0: Tensor, y0: Tensor, w: Tensor, h: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """Every cell of M integer boxes (corner x0, y0, sizes w, h; a size <= 0 is an empty box), box by box, rows
    in order: (owner [K] index of the box, x [K], y [K])."""
    w, h = w.clamp_min(0), h.clamp_min(0)
    count = w * h
    owner = torch.repeat_interleave(torch.arange(count.numel(), device=count.device), count)
    start = torch.cumsum(count, 0) - count
    offset = torch.arange(owner.numel(), device=count.device) - start[owner]
    wo = w[owner].clamp_min(1)
    return owner, x0[owner] + offset % wo, y0[owner] + offset // wo


def tile_intersections(means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, tile_width: int,
                       tile_height: int) -> Tuple[Tensor, Tensor]:
    """The (tile, Gaussian) pairs of gsplat's isect_tiles, sorted by camera, tile, then depth.

    Args:
        means2d: [C, N, 2] pixel positions; radii: [C, N] (0 = not drawn); depths: [C, N].
    Returns:
        (tile_ids [M] int64 in [0, C * tile_height * tile_width), flat_ids [M] int64 into C * N).
    """
    C, N = radii.shape
    cam, gid = torch.nonzero(radii > 0, as_tuple=True)
    if cam.numel() == 0:
        empty = torch.zeros(0, dtype=torch.long, device=radii.device)
        return empty, empty
    m = means2d.detach()[cam, gid].double() / tile_size
    r = radii[cam, gid].double() / tile_size
    xmin = torch.floor(m[:, 0] - r).clamp(0, tile_width).long()
    xmax = torch.ceil(m[:, 0] + r).clamp(0, tile_width).long()
    ymin = torch.floor(m[:, 1] - r).clamp(0, tile_height).long()
    ymax = torch.ceil(m[:, 1] + r).clamp(0, tile_height).long()
    owner, tx, ty = _cells(xmin, ymin, xmax - xmin, ymax - ymin)
    tile_ids = cam[owner] * (tile_width * tile_height) + ty * tile_width + tx
    flat_ids = cam[owner] * N + gid[owner]
    order = torch.argsort(depths.detach().reshape(-1)[flat_ids], stable=True)
    tile_ids, flat_ids = tile_ids[order], flat_ids[order]
    order = torch.argsort(tile_ids, stable=True)
    return tile_ids[order], flat_ids[order]


def block_intersections(tile_ids: Tensor, flat_ids: Tensor, means2d: Tensor, conics: Tensor, opacities: Tensor,
                        tile_size: int, tile_width: int, tile_height: int, block: int) -> Tuple[Tensor, Tensor]:
    """The (tile, Gaussian) pairs refined to (block, Gaussian) pairs that can draw (see the module docstring).

    Args:
        tile_ids, flat_ids: tile_intersections' pairs (sorted by tile, then depth); means2d [C, N, 2],
        conics [C, N, 3], opacities [C, N]; block: pixels per block side, dividing tile_size.
    Returns:
        (block_ids [M'] int64 in [0, C * tile_height * tile_width * (tile_size / block)^2), block rows of
        width tile_width * tile_size / block; flat_ids [M']), sorted by block, then depth.
    """
    per = tile_size // block  # blocks per tile side
    bw, bh = tile_width * per, tile_height * per
    if flat_ids.numel() == 0:
        return tile_ids, flat_ids
    xy = means2d.detach().reshape(-1, 2)[flat_ids].double()
    a, b, c = conics.detach().reshape(-1, 3)[flat_ids].double().unbind(-1)
    opac = opacities.detach().reshape(-1)[flat_ids].double()
    # alpha >= 1/255  <=>  sigma = 0.5 d^T Q d <= ln(255 o); the ellipse d^T Q d <= 2t has half-widths
    # sqrt(2t (Q^-1)_xx), sqrt(2t (Q^-1)_yy); a margin for the float32 blend; no culling where Q is not positive
    t = torch.log(255.0 * opac.clamp_min(0)).clamp_min(0) * (1 + 1e-3) + 1e-3
    det = a * c - b * b
    pd = (det > 0) & (a > 0) & (c > 0)
    inf = torch.full_like(det, float("inf"))
    ex = torch.where(pd, torch.sqrt(2 * t * c.abs() / det.abs().clamp_min(1e-300)), inf) + 1e-3
    ey = torch.where(pd, torch.sqrt(2 * t * a.abs() / det.abs().clamp_min(1e-300)), inf) + 1e-3
    cam, t_in_cam = tile_ids // (tile_width * tile_height), tile_ids % (tile_width * tile_height)
    tx0, ty0 = (t_in_cam % tile_width) * per, (t_in_cam // tile_width) * per
    # block column bx holds pixel centres bx * block + 0.5 .. bx * block + block - 0.5
    lo_x = torch.ceil((xy[:, 0] - ex - block + 0.5) / block)
    hi_x = torch.floor((xy[:, 0] + ex - 0.5) / block)
    lo_y = torch.ceil((xy[:, 1] - ey - block + 0.5) / block)
    hi_y = torch.floor((xy[:, 1] + ey - 0.5) / block)
    bx0 = torch.maximum(lo_x.nan_to_num(-1.0, -1.0, -1.0).clamp(-1, bw), tx0.double()).long()
    bx1 = torch.minimum(hi_x.nan_to_num(bw, bw, -1.0).clamp(-1, bw), (tx0 + per - 1).double()).long()
    by0 = torch.maximum(lo_y.nan_to_num(-1.0, -1.0, -1.0).clamp(-1, bh), ty0.double()).long()
    by1 = torch.minimum(hi_y.nan_to_num(bh, bh, -1.0).clamp(-1, bh), (ty0 + per - 1).double()).long()
    owner, bx, by = _cells(bx0, by0, bx1 - bx0 + 1, by1 - by0 + 1)
    block_ids = cam[owner] * (bw * bh) + by * bw + bx
    order = torch.argsort(block_ids, stable=True)  # the tile's depth order within each block
    return block_ids[order], flat_ids[owner][order]


class _BroadcastWithAbsGrad(torch.autograd.Function):
    """xy [B, K, 2] -> [B, P, K, 2] (one copy per pixel); the backward also adds each pixel's |gradient| of its
    pair into `abs_sum` [C * N, 2] at the pair's Gaussian `ids` [B, K] (gsplat's AbsGS statistic)."""

    @staticmethod
    def forward(ctx, xy: Tensor, pixels: int, ids: Tensor, abs_sum: Tensor):
        ctx.save_for_backward(ids)
        ctx.abs_sum = abs_sum
        return xy[:, None].expand(-1, pixels, -1, -1)

    @staticmethod
    def backward(ctx, grad: Tensor):
        (ids,) = ctx.saved_tensors
        ctx.abs_sum.index_add_(0, ids.reshape(-1), grad.abs().sum(1).reshape(-1, grad.shape[-1]))
        return grad.sum(1), None, None, None


def _blend_tiles(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, ids: Tensor, valid: Tensor,
                 pixels: Tensor, abs_sum: Optional[Tensor]) -> Tuple[Tensor, Tensor]:
    """Blend B tiles: ids/valid [B, K] (front to back, padded), pixels [B, P, 2] pixel centers.

    Returns (color sums [B, P, D] without background, final transmittance [B, P])."""
    xy, conic, opac, color = means2d[ids], conics[ids], opacities[ids], colors[ids]  # [B, K, ...]
    xy = xy[:, None] if abs_sum is None else _BroadcastWithAbsGrad.apply(xy, pixels.shape[1], ids, abs_sum)
    d = xy - pixels[:, :, None, :]  # [B, P, K, 2]
    dx, dy = d[..., 0], d[..., 1]
    sigma = 0.5 * (conic[:, None, :, 0] * dx * dx + conic[:, None, :, 2] * dy * dy) + conic[:, None, :, 1] * dx * dy
    alpha = torch.clamp_max(opac[:, None, :] * torch.exp(-sigma), ALPHA_MAX)
    drawn = (sigma >= 0) & (alpha >= ALPHA_MIN) & valid[:, None, :]
    with torch.no_grad():  # the stop: before the first pair whose transmittance after it is <= 1e-4
        t_after = torch.cumprod(1.0 - torch.where(drawn, alpha, torch.zeros_like(alpha)), dim=-1)
        drawn &= t_after > T_MIN
    a = torch.where(drawn, alpha, torch.zeros_like(alpha))
    t_after = torch.cumprod(1.0 - a, dim=-1)  # >= 1e-4 everywhere: no underflow in the backward
    t_before = torch.cat([torch.ones_like(t_after[..., :1]), t_after[..., :-1]], dim=-1)
    rgb = torch.einsum("bpk,bkd->bpd", a * t_before, color)
    return rgb, t_after[..., -1]


def rasterize_to_pixels(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, radii: Tensor,
                        depths: Tensor, width: int, height: int, tile_size: int = 16,
                        backgrounds: Optional[Tensor] = None, absgrad: bool = False,
                        max_pairs: int = 1 << 21, recompute_above: int = 1 << 22, block: int = 4
                        ) -> Tuple[Tensor, Tensor]:
    """gsplat's classic rasterization of projected Gaussians (see the module docstring).

    Args:
        means2d [C, N, 2], conics [C, N, 3], colors [C, N, D], opacities [C, N], radii [C, N], depths [C, N];
        backgrounds [C, D] or None; absgrad: fill `means2d.absgrad` [C, N, 2] in the backward pass;
        max_pairs: (pixel, Gaussian) pairs blended at once; recompute_above: with more pairs than this in all,
        each chunk is recomputed in the backward pass instead of kept (memory against time);
        block: the side of the pixel blocks blended at once (dividing tile_size; the result does not depend on it).
    Returns:
        (render_colors [C, H, W, D], render_alphas [C, H, W, 1]).
    """
    C, N, D = colors.shape
    device, dtype = means2d.device, means2d.dtype
    if block < 1 or tile_size % block:
        raise ValueError(f"rasterize_to_pixels: block {block} must divide tile_size {tile_size}")
    tw, th = -(-width // tile_size), -(-height // tile_size)
    bw, bh = tw * (tile_size // block), th * (tile_size // block)
    n_tiles = C * bh * bw  # the blocks
    tile_ids, flat_ids = tile_intersections(means2d, radii, depths, tile_size, tw, th)
    tile_ids, flat_ids = block_intersections(tile_ids, flat_ids, means2d, conics, opacities, tile_size, tw, th,
                                             block)
    counts = torch.bincount(tile_ids, minlength=n_tiles)
    starts = torch.cumsum(counts, 0) - counts
    abs_sum = None
    if absgrad:
        abs_sum = torch.zeros(C * N, 2, dtype=dtype, device=device)
        means2d.absgrad = abs_sum.view(C, N, 2)  # type: ignore[attr-defined]
    flat = (means2d.reshape(C * N, 2), conics.reshape(C * N, 3), colors.reshape(C * N, D), opacities.reshape(C * N))
    # pixel centers of one block, [P, 2]
    iy, ix = torch.meshgrid(torch.arange(block, device=device), torch.arange(block, device=device), indexing="ij")
    local = torch.stack([ix.reshape(-1), iy.reshape(-1)], dim=-1).to(dtype) + 0.5
    P = block * block
    tile_order = torch.argsort(counts, descending=True, stable=True)
    recompute = torch.is_grad_enabled() and any(t.requires_grad for t in flat) and \
        P * int(counts.sum()) > recompute_above
    sums, transmittance, done = [], [], []
    i = 0
    while i < n_tiles:
        k = max(int(counts[tile_order[i]]), 1)
        b = max(1, min(n_tiles - i, max_pairs // (P * k)))
        tiles = tile_order[i:i + b]
        slot = torch.arange(k, device=device)
        ids = starts[tiles, None] + slot[None, :]
        valid = slot[None, :] < counts[tiles, None]
        ids = flat_ids[ids.clamp_max(max(flat_ids.numel() - 1, 0))] if flat_ids.numel() else \
            torch.zeros_like(ids)
        t_in_cam = tiles % (bh * bw)
        origin = torch.stack([t_in_cam % bw, t_in_cam // bw], dim=-1).to(dtype) * block  # [B, 2]
        pixels = origin[:, None, :] + local[None]
        # abs_sum is bound, not an argument: the checkpoint would refuse it once an earlier chunk's backward
        # has added into it
        blend = functools.partial(_blend_tiles, abs_sum=abs_sum)
        if recompute:
            rgb, t_final = checkpoint(blend, *flat, ids, valid, pixels, use_reentrant=False)
        else:
            rgb, t_final = blend(*flat, ids, valid, pixels)
        sums.append(rgb)
        transmittance.append(t_final)
        done.append(tiles)
        i += b
    order = torch.argsort(torch.cat(done))
    rgb = torch.cat(sums)[order].reshape(C, bh, bw, block, block, D)
    t_final = torch.cat(transmittance)[order].reshape(C, bh, bw, block, block)
    rgb = rgb.permute(0, 1, 3, 2, 4, 5).reshape(C, bh * block, bw * block, D)[:, :height, :width]
    t_final = t_final.permute(0, 1, 3, 2, 4).reshape(C, bh * block, bw * block)[:, :height, :width, None]
    if backgrounds is not None:
        rgb = rgb + t_final * backgrounds[:, None, None, :]
    return rgb, 1.0 - t_final
