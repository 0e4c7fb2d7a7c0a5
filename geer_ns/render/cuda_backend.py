"""The CUDA backend: csrc/ kernels behind the same API and outputs as the PyTorch twin (rasterize.render).

Two autograd Functions carry the paper's two-stage backward (App. C.2): `_Preprocess` (per Gaussian) and
`_Rasterize` (per tile / ray). Every operation also exists on the CPU (csrc/cpu_ops.cpp, `load_cpu_ops`), so
`render_cuda(..., ops=load_cpu_ops())` runs this whole module without a GPU. Importing it builds nothing.
Stages, kernels and the differences from the twin: docs/renderer.md.
"""

from __future__ import annotations

import math
from types import ModuleType

import torch
from torch import Tensor

from .absgrad import offset_rows
from .associate import pbf_cull_pieces
from .cones import gaussian_cone_form, tile_cones
from .moving import MovingRays, motion_scales
from .order import CompositeOrder, key_lower_bounds
from .extensions import (  # noqa: F401 - the loaders, re-exported where callers have always found them
    _errors,
    _modules,
    build_error,
    extension_available,
    load_cpu_ops,
    load_extension,
)
from .ops import KERNELS, preprocess_grads, render_grads
from .outputs import RenderOutput, images
from .pbf import PBF, LambdaMode, pbf_lambda_sq
from .raygrid import RayGrid
from .transforms import camera_offsets, view_transform

# ----------------------------------------------------------------------------------------- autograd
class _Preprocess(torch.autograd.Function):
    """Per Gaussian: (means_c, quats, scales, SH, SH view directions, camera rotation R_c) -> (W, o_u, color)
    + PBF (no grad). R_c gets a gradient when it requires one (camera pose refinement)."""

    @staticmethod
    def forward(ctx, means_c, quats, scales, sh, sh_dirs, opacities, rot_c, sh_degree, paper, ops, sh_degrees=None):
        whiten, o_u, rgb, bounds, alive, inside = ops.preprocess_forward(
            means_c, quats, scales, opacities, sh, sh_dirs, rot_c, sh_degree, paper, sh_degrees
        )
        ctx.save_for_backward(means_c, quats, scales, sh, sh_dirs, rot_c)
        ctx.sh_degree, ctx.sh_degrees = sh_degree, sh_degrees
        ctx.ops = ops
        ctx.mark_non_differentiable(bounds, alive, inside)
        return whiten, o_u, rgb, bounds, alive, inside

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_whiten, g_o_u, g_rgb, *_):
        pose_grad = ctx.needs_input_grad[6]
        g_mc, g_q, g_s, g_sh, g_dirs, g_rot_c = preprocess_grads(ctx.ops, ctx.saved_tensors, ctx.sh_degree, g_whiten,
                                                                 g_o_u, g_rgb, pose_grad, ctx.sh_degrees)
        return (g_mc, g_q, g_s, g_sh, g_dirs, None, g_rot_c) + (None,) * 4


class _Rasterize(torch.autograd.Function):
    """Per tile / ray: (W, o_u, color, opacity) -> (rgb sum, depth sum, accumulation) per ray, max_weight [N]
    and the median distance [R] (neither with a gradient); with absgrad's offset rows [N,6] and sink [N,2], the
    sink's gradient is the absgrad sums. The ray directions get their gradient when they require one (lens
    refinement; the cull has none); origins [R,3] (or None): each ray's own origin (rolling shutter), with its
    gradient when it or the directions require one."""

    @staticmethod
    def forward(ctx, whiten, o_u, rgb, opacities, pieces, dirs, ray_bounds, warp_bounds, valid, ids, ranges, height,
                width, tile_size, ops, absgrad_rows, sink, origins=None, order_lower=None, order_window=0):
        # pieces [N,8] (associate.pbf_cull_pieces), ray_bounds [R,4] and warp_bounds (RayGrid.ray/warp_cull_bounds):
        # the cull.
        geometry = (pieces, dirs, ray_bounds, warp_bounds, valid, ids, ranges)
        # blended_lanes: the CPU build's record of the lanes that blended each list entry, which its backward
        # visits; made only when a backward will run (empty from the kernels, whose backward re-derives them).
        ctx.ray_grad = ctx.needs_input_grad[5] or (origins is not None and ctx.needs_input_grad[17])
        record = any(ctx.needs_input_grad[:4]) or ctx.ray_grad or ctx.needs_input_grad[16]
        origins = whiten.new_zeros(0) if origins is None else origins.contiguous()
        order_lower = whiten.new_zeros(0) if order_lower is None else order_lower.contiguous()
        out_rgb, depth, acc, t_final, n_contrib, blended_lanes, max_weight, median = ops.render_forward(
            whiten, o_u, rgb, opacities, *geometry, height, width, tile_size, record, origins, order_lower,
            order_window
        )
        # Off, the backward gets an empty tensor for the rows (csrc: the build without absgrad runs).
        rows = absgrad_rows if absgrad_rows is not None and ctx.needs_input_grad[16] else whiten.new_zeros(0)
        sums = (out_rgb, depth, acc) if order_lower.numel() else ()  # the per-ray order's totals (ops.render_grads)
        ctx.save_for_backward(whiten, o_u, rgb, opacities, *geometry, t_final, n_contrib, blended_lanes, rows, origins,
                              order_lower, *sums)
        ctx.layout = (height, width, tile_size)
        ctx.ops, ctx.order_window = ops, order_window
        ctx.mark_non_differentiable(max_weight, median)
        return out_rgb, depth, acc, max_weight, median

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_rgb, g_depth, g_acc, _g_max_weight, _g_median):
        saved = list(ctx.saved_tensors)
        rows, origins, order_lower, *sums = saved[14:]
        origins = origins if origins.numel() else None
        order = (order_lower, ctx.order_window, tuple(sums)) if order_lower.numel() else None
        *grads, absgrad, g_dirs, g_origins = render_grads(ctx.ops, saved[:14], ctx.layout, g_rgb, g_depth, g_acc, rows,
                                                          ctx.ray_grad, origins, order)
        return (tuple(grads) + (None, g_dirs) + (None,) * 10 + (absgrad, g_origins, None, None)
                )[:len(ctx.needs_input_grad)]


# ----------------------------------------------------------------------------------------- helpers
def _sh_setup(colors: Tensor, sh_degree: int | Tensor | None) -> tuple[int, Tensor | None]:
    """(active SH degree (-1: colors are RGB), each Gaussian's own as uint8 [N] or None), with sh.py's errors. A
    per-Gaussian sh_degree (validated by render) caps the degree colors' K holds."""
    if colors.ndim == 2:
        return -1, None
    own = sh_degree if isinstance(sh_degree, Tensor) else None
    degree = int(math.isqrt(colors.shape[1]) - 1) if sh_degree is None or own is not None else sh_degree
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    if colors.shape[1] < (degree + 1) ** 2:
        raise ValueError(f"colors: SH degree {degree} needs {(degree + 1) ** 2} coefficients, got {colors.shape[1]}")
    return degree, None if own is None else own.clamp(max=degree).to(torch.uint8).contiguous()


def depth_order_key(depth: Tensor) -> Tensor:
    """[N] int32 low half of the association's sort key (csrc/geer_associate.h pair_key): the twin's
    front-to-back order. float32: the depth's bits (non-negative floats order like their bits; equal
    depths stay in index order through the stable sort), no global sort. float64: the stable-sort rank."""
    if depth.dtype == torch.float32:
        return depth.contiguous().view(torch.int32)
    order = torch.sort(depth, stable=True).indices
    rank = torch.empty(depth.shape[0], dtype=torch.int32, device=depth.device)
    rank[order] = torch.arange(depth.shape[0], dtype=torch.int32, device=depth.device)
    return rank


def associate_pairs(ops: ModuleType, bounds: Tensor, alive: Tensor, depth: Tensor, grid: RayGrid,
                    cone: Tensor | None = None):
    """Stage 2 on the kernels: (ids [M] int32 sorted by (tile, depth), ranges [T, 2], counts [N] tiles per
    Gaussian, tests [N] tile tests of the count and emit passes). bounds [N, 4] PBF (theta_lo, theta_hi,
    phi_lo, phi_hi), alive [N], depth [N] the Euclidean distances the twin sorts by, cone [N, 9] the Gaussians'
    cone forms (cones.gaussian_cone_form; None: the box test alone, the association before the cone test)."""
    pyr = grid.tile_pyramid(bounds.dtype)
    if cone is None:
        gauss_cones = tiles = bounds.new_zeros(0)
    else:
        gauss_cones, tiles = cone.to(bounds.dtype).contiguous(), tile_cones(grid, bounds.dtype).to(bounds.device)
    return ops.associate(bounds.contiguous(), alive.contiguous(), depth_order_key(depth), pyr.bounds.to(bounds.device),
                         pyr.active.to(bounds.device), grid.tiles_x, grid.tiles_y, gauss_cones, tiles)


# ----------------------------------------------------------------------------------------- pipeline
def render_cuda(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    grid: RayGrid,
    *,
    sh_degree: int | Tensor | None = None,
    background: Tensor | None = None,
    lambda_mode: LambdaMode = "opacity",
    ops: ModuleType | None = None,
    absgrad: tuple[Tensor, Tensor] | None = None,
    motion: MovingRays | None = None,
    order: CompositeOrder | None = None,
):
    """rasterize.render on the kernels (inputs already validated by render). `ops` defaults to the torch
    operators (ops.KERNELS: the kernels for CUDA tensors, the CPU build for CPU ones); an extension module
    (load_cpu_ops(), load_extension()) is called directly."""
    order = CompositeOrder.parse(order)
    if ops is None:
        ops = KERNELS
    if lambda_mode not in ("opacity", "paper"):
        raise ValueError(f"lambda_mode must be 'opacity' or 'paper', got {lambda_mode!r}")
    if not 1 <= grid.tile_size <= 32 and means.device.type == "cuda":
        raise ValueError(f"the CUDA backend needs tile_size in 1..32 (one thread per ray), got {grid.tile_size}")
    dtype, device = means.dtype, means.device
    n = means.shape[0]
    grid = grid.to(device)
    dirs = grid.dirs.to(dtype).contiguous()
    # The pose goes to the Gaussians' device (no host round trip); the kernels read rot_c there.
    # Stage 1. View transform and SH view directions in PyTorch (transforms.view_transform and camera_offsets,
    # float64 inside, as the twin), the rest per Gaussian in the kernel. A pose that requires grad gets its
    # gradient through all three: means_c and sh_dirs by autograd, rot_c from the preprocess backward.
    viewmat = viewmat.to(device=device)
    means_c = view_transform(means, viewmat)
    degree, own_degrees = _sh_setup(colors, sh_degree)
    sh_dirs = camera_offsets(means, viewmat) if degree >= 0 else means.new_zeros(n, 3)
    rot_c = viewmat.to(dtype)[:3, :3]
    if means_c.requires_grad:
        means_c.retain_grad()
    sh = colors.contiguous() if degree >= 0 else means.new_zeros(n, 0, 3)
    whiten, o_u, rgb_sh, bounds, alive, inside = _Preprocess.apply(
        means_c.contiguous(), quats.contiguous(), scales.contiguous(), sh, sh_dirs.contiguous(),
        opacities.detach().contiguous(), rot_c.contiguous(), degree, lambda_mode == "paper", ops, own_degrees,
    )
    rgb = colors.contiguous() if degree < 0 else rgb_sh
    lam2 = pbf_lambda_sq(opacities.detach(), lambda_mode)[0]
    w_pbf, o_u_pbf = whiten, o_u
    if motion is not None:  # the bounds of every pose's view of each Gaussian (moving.py)
        with torch.no_grad():
            scales_m = motion_scales(scales.detach(), lam2, motion.offset)
            w_pbf, o_u_pbf, _, bounds, alive, inside = ops.preprocess_forward(
                means_c.detach().contiguous(), quats.detach().contiguous(), scales_m.contiguous(),
                opacities.detach().contiguous(), means.new_zeros(n, 0, 3), means.new_zeros(n, 3),
                rot_c.detach().contiguous(), -1, lambda_mode == "paper", None)

    # Stage 2. Lists in the twin's front-to-back order (depth as the twin computes it).
    cone = gaussian_cone_form(w_pbf, o_u_pbf, lam2, inside)
    tiles = grid if motion is None else motion.tile_grid(grid).to(device)  # the tests take the rays' directions
    ids, ranges, counts, _tests = associate_pairs(ops, bounds, alive, means_c.detach().norm(dim=-1), tiles, cone)
    order_lower = None
    if order.per_ray:  # each ray in its own order: the Gaussians' key bounds (order.py)
        order_lower = key_lower_bounds(means_c, scales, opacities, o_u, 0.0 if motion is None else motion.offset)

    # Stage 3. Per tile / ray. absgrad's offset rows per Gaussian here (absgrad.offset_rows, an [N] einsum), so
    # that the kernels only take dot products with them (no W x lateral product in their registers).
    rows, sink = (None, None) if absgrad is None else (offset_rows(absgrad[0], whiten).reshape(n, 6).contiguous(),
                                                        absgrad[1])
    origins = None
    if motion is not None:
        dirs, origins = motion.dirs.to(dtype).contiguous(), motion.origins.to(dtype).contiguous()
    rgb_sum, depth_sum, acc, max_weight, median = _Rasterize.apply(
        whiten, o_u, rgb, opacities.contiguous(), pbf_cull_pieces(bounds), dirs, tiles.ray_cull_bounds(dtype),
        tiles.warp_cull_bounds(dtype), grid.valid.contiguous(), ids, ranges, grid.height, grid.width, grid.tile_size, ops,
        rows, sink, origins, order_lower, order.window,
    )
    out_rgb, out_depth, out_acc = images(grid.height, grid.width, rgb_sum, depth_sum, acc, background)

    visible = counts > 0
    tile_counts = (ranges[:, 1] - ranges[:, 0]).long()
    pbf = PBF(bounds[:, 0], bounds[:, 1], bounds[:, 2], bounds[:, 3], alive, inside, cone)
    return RenderOutput(out_rgb, out_depth, out_acc, visible, tile_counts, means_c, pbf, None, max_weight,
                        median.reshape(grid.height, grid.width, 1))
