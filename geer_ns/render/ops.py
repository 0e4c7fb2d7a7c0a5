"""The csrc/ kernels as torch operators (torch.library): `torch.ops.geer.*`.

Each operation of the extension (bindings.cpp) and of its CPU build (cpu_ops.cpp, same names and signatures)
is one operator with a schema, a fake (shape) implementation and, for the two forward stages, a registered
backward. The operator runs the build of its inputs' device: CUDA tensors the kernels (extension built on
first use), CPU tensors the CPU build. Registered, the kernels take part in torch's machinery like any aten
op: FakeTensorMode (shapes and devices without data; a training step on a fake `cuda:0` runs on a machine
without a GPU, and a CPU tensor among its CUDA tensors raises), torch.compile and opcheck.

    preprocess_forward    per Gaussian: (W, o_u, color, PBF bounds, alive, inside)
    associate             per tile: ids sorted by (tile, depth), ranges, counts, tests; len(ids) depends on
                          the data (a fake run needs a ShapeEnv: torch.library.get_ctx().new_dynamic_size)
    render_forward        per ray: rgb, depth, acc, T_final, n_contrib, blended lanes (CPU build), max_weight
    render_backward       per Gaussian gradient rows [N,16] (and absgrad [N,2], per-ray direction and origin
                          gradients)
    preprocess_backward   to means_c, quats, scales, SH, SH directions

`KERNELS` holds them under the extension's names, for the autograd wrappers of cuda_backend.py (which
also carry absgrad's sink, that an operator cannot). Why: docs/gpu_correctness.md.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Optional, Tuple

import torch
from torch import Tensor

from .extensions import load_cpu_ops, load_extension

T2 = Tuple[Tensor, Tensor]
T3 = Tuple[Tensor, Tensor, Tensor]
T4 = Tuple[Tensor, Tensor, Tensor, Tensor]
T6 = Tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]
T8 = Tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]
GRAD_VALUES, ABSGRAD_VALUES = 16, 2  # csrc/geer_blocks.h kGradValues, kAbsgradValues


def _build(like: Tensor):
    """The build that runs tensors on like's device: the CUDA extension or the CPU build."""
    return load_extension() if like.device.type == "cuda" else load_cpu_ops()


def _one_device(op: str, *tensors: Tensor) -> torch.device:
    """The inputs' one device; a tensor elsewhere is an error (the kernels would read a host pointer)."""
    device = tensors[0].device
    for t in tensors[1:]:
        if t.device != device and not (isinstance(t.numel(), int) and t.numel() == 0):  # numel: maybe symbolic
            raise RuntimeError(f"geer::{op}: expected all tensors on {device}, got one on {t.device} "
                               f"{tuple(t.shape)}")
    return device


# ------------------------------------------------------------------------------------------ stage 1
@torch.library.custom_op("geer::preprocess_forward", mutates_args=())
def preprocess_forward(means_c: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, sh: Tensor,
                       sh_dirs: Tensor, rot_c: Tensor, sh_degree: int, paper: bool,
                       sh_degrees: Optional[Tensor] = None) -> T6:
    """Per Gaussian -> (W [N,3,3], o_u [N,3], color [N,3], PBF bounds [N,4], alive [N], inside [N]). sh_degrees:
    uint8 [N] each Gaussian's own SH degree, capping sh_degree (None: every Gaussian at sh_degree)."""
    _one_device("preprocess_forward", means_c, quats, scales, opacities, sh, sh_dirs, rot_c, *_given(sh_degrees))
    return tuple(_build(means_c).preprocess_forward(means_c, quats, scales, opacities, sh, sh_dirs, rot_c,
                                                    sh_degree, paper, sh_degrees))


@preprocess_forward.register_fake
def _(means_c, quats, scales, opacities, sh, sh_dirs, rot_c, sh_degree, paper, sh_degrees=None):
    _one_device("preprocess_forward", means_c, quats, scales, opacities, sh, sh_dirs, rot_c, *_given(sh_degrees))
    n = means_c.shape[0]
    new = means_c.new_empty
    return (new(n, 3, 3), new(n, 3), new(n, 3), new(n, 4), new(n, dtype=torch.bool), new(n, dtype=torch.bool))


@torch.library.custom_op("geer::preprocess_backward", mutates_args=())
def preprocess_backward(means_c: Tensor, quats: Tensor, scales: Tensor, sh: Tensor, sh_dirs: Tensor, rot_c: Tensor,
                        sh_degree: int, g_whiten: Tensor, g_o_u: Tensor, g_rgb: Tensor, pose_grad: bool,
                        sh_degrees: Optional[Tensor] = None) -> T6:
    """-> gradients to (means_c, quats, scales, SH (empty without SH), SH directions) and, when `pose_grad`, each
    Gaussian's share of dL/dR_c [N,3,3] (else empty). g_whiten carries the canonical moment K (render_backward).
    sh_degrees: as preprocess_forward's; a Gaussian's bands above its degree get exactly zero."""
    _one_device("preprocess_backward", means_c, quats, scales, sh, sh_dirs, rot_c, g_whiten, g_o_u, g_rgb,
                *_given(sh_degrees))
    return tuple(_build(means_c).preprocess_backward(means_c, quats, scales, sh, sh_dirs, rot_c, sh_degree, g_whiten,
                                                     g_o_u, g_rgb, pose_grad, sh_degrees))


@preprocess_backward.register_fake
def _(means_c, quats, scales, sh, sh_dirs, rot_c, sh_degree, g_whiten, g_o_u, g_rgb, pose_grad, sh_degrees=None):
    _one_device("preprocess_backward", means_c, quats, scales, sh, sh_dirs, rot_c, g_whiten, g_o_u, g_rgb,
                *_given(sh_degrees))
    n = means_c.shape[0]
    on_cpu = means_c.device.type == "cpu"  # the CPU build returns zeros like sh also without SH
    g_sh = torch.empty_like(sh) if sh_degree >= 0 or on_cpu else means_c.new_empty(0)
    g_rot = means_c.new_empty(n, 3, 3) if pose_grad else means_c.new_empty(0)
    return (means_c.new_empty(n, 3), means_c.new_empty(n, 4), means_c.new_empty(n, 3), g_sh, means_c.new_empty(n, 3),
            g_rot)


def _preprocess_setup(ctx, inputs, output) -> None:
    means_c, quats, scales, _opacities, sh, sh_dirs, rot_c, sh_degree, _paper, *own = inputs
    ctx.save_for_backward(means_c, quats, scales, sh, sh_dirs, rot_c)
    ctx.sh_degree = sh_degree
    ctx.sh_degrees = own[0] if own else None


def preprocess_grads(kernels, saved, sh_degree: int, g_whiten, g_o_u, g_rgb, pose_grad: bool = False,
                     sh_degrees: Optional[Tensor] = None) -> T6:
    """The preprocess stage's backward (missing gradients are zeros): to (means_c, quats, scales, SH, SH
    directions, the camera rotation R_c), SH's two None without SH, R_c's None unless `pose_grad`.
    `kernels`: KERNELS or an extension module; sh_degrees: each Gaussian's own SH degree (None: all at sh_degree)."""
    means_c = saved[0]
    n = means_c.shape[0]
    g_whiten, g_o_u, g_rgb = (_zeros_if_none(g, shape, means_c) for g, shape in
                              ((g_whiten, (n, 3, 3)), (g_o_u, (n, 3)), (g_rgb, (n, 3))))
    g_mc, g_q, g_s, g_sh, g_dirs, g_rot = kernels.preprocess_backward(*saved, sh_degree, g_whiten, g_o_u, g_rgb,
                                                                      pose_grad, sh_degrees)
    has_sh = sh_degree >= 0
    g_rot_c = g_rot.sum(0) if pose_grad else None  # the Gaussians' shares of dL/dR_c
    return g_mc, g_q, g_s, g_sh if has_sh else None, g_dirs if has_sh else None, g_rot_c


def _preprocess_backward(ctx, g_whiten, g_o_u, g_rgb, *_):
    g_mc, g_q, g_s, g_sh, g_dirs, g_rot_c = preprocess_grads(KERNELS, ctx.saved_tensors, ctx.sh_degree, g_whiten,
                                                             g_o_u, g_rgb, ctx.needs_input_grad[6], ctx.sh_degrees)
    return g_mc, g_q, g_s, None, g_sh, g_dirs, g_rot_c, None, None, None  # opacities: the PBF only


torch.library.register_autograd("geer::preprocess_forward", _preprocess_backward, setup_context=_preprocess_setup)


# ------------------------------------------------------------------------------------------ stage 2
@torch.library.custom_op("geer::associate", mutates_args=())
def associate(bounds: Tensor, alive: Tensor, order: Tensor, node_bounds: Tensor, node_active: Tensor, tiles_x: int,
              tiles_y: int, gauss_cones: Tensor, tile_cones: Tensor) -> T4:
    """-> (ids [M] int32 by (tile, depth order), ranges [T,2] int32, counts [N] int32, tests [N] int32).
    gauss_cones [N,9] / tile_cones [T,10] (render/cones.py), both empty for the box test alone."""
    _one_device("associate", bounds, alive, order, node_bounds, node_active, gauss_cones, tile_cones)
    return tuple(_build(bounds).associate(bounds, alive, order, node_bounds, node_active, tiles_x, tiles_y,
                                          gauss_cones, tile_cones))


@associate.register_fake
def _(bounds, alive, order, node_bounds, node_active, tiles_x, tiles_y, gauss_cones, tile_cones):
    _one_device("associate", bounds, alive, order, node_bounds, node_active, gauss_cones, tile_cones)
    pairs = torch.library.get_ctx().new_dynamic_size()  # the number of (Gaussian, tile) pairs: data
    n, new = bounds.shape[0], bounds.new_empty
    return (new(pairs, dtype=torch.int32), new(tiles_x * tiles_y, 2, dtype=torch.int32), new(n, dtype=torch.int32),
            new(n, dtype=torch.int32))


# ------------------------------------------------------------------------------------------ stage 3
@torch.library.custom_op("geer::render_forward", mutates_args=())
def render_forward(whiten: Tensor, o_u: Tensor, rgb: Tensor, opacities: Tensor, pbf_pieces: Tensor, dirs: Tensor,
                   ray_bounds: Tensor, warp_bounds: Tensor, valid: Tensor, ids: Tensor, ranges: Tensor, height: int,
                   width: int, tile_size: int, record: bool, origins: Optional[Tensor] = None,
                   order_lower: Optional[Tensor] = None, order_window: int = 0) -> T8:
    """Per ray -> (rgb [R,3], depth [R], acc [R], T_final [R], n_contrib [R] int32, blended lanes int32 (the CPU
    build's record for its backward, when `record`: the lanes that blended each entry, or in the per-ray order the
    pairs each ray blended; empty from the kernels), max_weight [N], median distance [R]).
    Pass record=True when a backward will run. origins [R,3]: each ray's own origin in the camera frame (rolling
    shutter; None: every ray from the camera centre). order_lower [N]: each ray in its own order (order.py
    key_lower_bounds; None: the list's per-view order), holding at most order_window pending pairs (0: all)."""
    _one_device("render_forward", whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds, warp_bounds, valid, ids,
                ranges, *_given(origins), *_given(order_lower))
    return tuple(_build(whiten).render_forward(whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds,
                                               warp_bounds, valid, ids, ranges, height, width, tile_size, record,
                                               _or_empty(origins, whiten), _or_empty(order_lower, whiten),
                                               order_window))


@render_forward.register_fake
def _(whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds, warp_bounds, valid, ids, ranges, height, width,
      tile_size, record, origins=None, order_lower=None, order_window=0):
    _one_device("render_forward", whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds, warp_bounds, valid, ids,
                ranges, *_given(origins), *_given(order_lower))
    r, new = height * width, whiten.new_empty
    on_cpu = whiten.device.type == "cpu" and record
    if not on_cpu:
        lanes = new(0, dtype=torch.int32)
    elif order_lower is not None and order_lower.numel():  # the per-ray order's record: its length is data
        lanes = new(torch.library.get_ctx().new_dynamic_size(), dtype=torch.int32)
    else:
        lanes = new(ids.shape[0], warp_bounds.shape[0] // ranges.shape[0], dtype=torch.int32)
    return new(r, 3), new(r), new(r), new(r), new(r, dtype=torch.int32), lanes, new(whiten.shape[0]), new(r)


@torch.library.custom_op("geer::render_backward", mutates_args=())
def render_backward(whiten: Tensor, o_u: Tensor, rgb: Tensor, opacities: Tensor, pbf_pieces: Tensor, dirs: Tensor,
                    ray_bounds: Tensor, warp_bounds: Tensor, valid: Tensor, ids: Tensor, ranges: Tensor, height: int,
                    width: int, tile_size: int, t_final: Tensor, n_contrib: Tensor, blended_lanes: Tensor,
                    g_rgb: Tensor, g_depth: Tensor, g_acc: Tensor, absgrad_rows: Tensor, dir_grad: bool,
                    origins: Optional[Tensor] = None, order_lower: Optional[Tensor] = None, order_window: int = 0,
                    ray_totals: Optional[Tensor] = None) -> T4:
    """-> (gradient rows [N,16]: the canonical moment K = dL/dW W^T row-major (what the preprocess backward takes in
    W's slot), o_u, color, opacity; absgrad [N,2], empty when absgrad_rows is; dL/d(ray directions) [R,3] when
    `dir_grad`, else empty; dL/d(ray origins) [R,3] when `dir_grad` and `origins` (render_forward's), else empty).
    order_lower, order_window: render_forward's; with them ray_totals [R], each ray's gC . rgb + gZ depth + gA acc
    of the forward's sums."""
    _one_device("render_backward", whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds, warp_bounds, valid, ids,
                ranges, t_final, n_contrib, g_rgb, g_depth, g_acc, absgrad_rows, *_given(origins),
                *_given(order_lower), *_given(ray_totals))
    return tuple(_build(whiten).render_backward(whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds,
                                                warp_bounds, valid, ids, ranges, height, width, tile_size, t_final,
                                                n_contrib, blended_lanes, g_rgb, g_depth, g_acc, absgrad_rows,
                                                dir_grad, _or_empty(origins, whiten), _or_empty(order_lower, whiten),
                                                order_window, _or_empty(ray_totals, whiten)))


@render_backward.register_fake
def _(whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds, warp_bounds, valid, ids, ranges, height, width,
      tile_size, t_final, n_contrib, blended_lanes, g_rgb, g_depth, g_acc, absgrad_rows, dir_grad, origins=None,
      order_lower=None, order_window=0, ray_totals=None):
    _one_device("render_backward", whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds, warp_bounds, valid, ids,
                ranges, t_final, n_contrib, g_rgb, g_depth, g_acc, absgrad_rows, *_given(origins),
                *_given(order_lower), *_given(ray_totals))
    n = whiten.shape[0]
    # absgrad on: rows [N, 6] (N may be a symbolic count); off: an empty 1-D tensor
    absgrad = whiten.new_empty(n, ABSGRAD_VALUES) if absgrad_rows.dim() == 2 else whiten.new_empty(0)
    g_dirs = whiten.new_empty(dirs.shape[0], 3) if dir_grad else whiten.new_empty(0)
    g_origins = whiten.new_empty(dirs.shape[0], 3) if dir_grad and origins is not None else whiten.new_empty(0)
    return whiten.new_empty(n, GRAD_VALUES), absgrad, g_dirs, g_origins


def render_grads(kernels, saved, layout, g_rgb, g_depth, g_acc, rows: Tensor, dir_grad: bool = False,
                 origins: Optional[Tensor] = None, order: Optional[tuple] = None) -> Tuple[Tensor, ...]:
    """The render stage's backward (missing gradients are zeros): (W's slot (K), o_u, color, opacity, absgrad or
    None, ray directions or None, ray origins or None (without `origins` or `dir_grad`)). saved: the forward's 11
    inputs from whiten to ranges, then T_final, n_contrib, blended lanes; origins: the forward's, if it had them;
    order: (order_lower, order_window, (rgb, depth, acc) sums of the forward) where it ran in each ray's order."""
    whiten, dirs = saved[0], saved[5]
    r = dirs.shape[0]
    g_rgb, g_depth, g_acc = (_zeros_if_none(g, shape, whiten) for g, shape in
                             ((g_rgb, (r, 3)), (g_depth, (r,)), (g_acc, (r,))))
    lower, window, totals = None, 0, None
    if order is not None:
        lower, window, (rgb, depth, acc) = order
        totals = (g_rgb * rgb).sum(-1) + g_depth * depth + g_acc * acc  # V of geer_order.h
    grads, absgrad, g_dirs, g_origins = kernels.render_backward(*saved[:11], *layout, *saved[11:], g_rgb, g_depth,
                                                                g_acc, rows, dir_grad, _or_empty(origins, whiten),
                                                                _or_empty(lower, whiten), window,
                                                                _or_empty(totals, whiten))
    gw, go, gc, gs = grads.split([9, 3, 3, 1], dim=1)
    return (gw.unflatten(1, (3, 3)), go, gc, gs.squeeze(1), (absgrad if rows.dim() == 2 else None),
            (g_dirs if dir_grad else None), (g_origins if dir_grad and origins is not None else None))


def _render_setup(ctx, inputs, output) -> None:
    origins = inputs[15] if len(inputs) > 15 else None
    lower = inputs[16] if len(inputs) > 16 and inputs[16] is not None and inputs[16].numel() else None
    ctx.with_origins, ctx.with_order = origins is not None, lower is not None
    ctx.order_window = inputs[17] if len(inputs) > 17 else 0
    ctx.save_for_backward(*inputs[:11], *output[3:6], *_given(origins), *_given(lower),
                          *(output[:3] if lower is not None else ()))
    ctx.layout = tuple(inputs[11:14])


def _render_backward(ctx, g_rgb, g_depth, g_acc, *_):
    saved = ctx.saved_tensors
    rest = list(saved[14:])
    origins = rest.pop(0) if ctx.with_origins else None
    order = (rest[0], ctx.order_window, tuple(rest[1:4])) if ctx.with_order else None
    ray_grad = ctx.needs_input_grad[5] or (ctx.with_origins and ctx.needs_input_grad[15])
    grads = render_grads(KERNELS, saved[:14], ctx.layout, g_rgb, g_depth, g_acc, saved[0].new_zeros(0), ray_grad,
                         origins, order)
    return grads[:4] + (None, grads[5]) + (None,) * 9 + (grads[6], None, None)[:len(ctx.needs_input_grad) - 15]


torch.library.register_autograd("geer::render_forward", _render_backward, setup_context=_render_setup)


def _given(t: Optional[Tensor]) -> Tuple[Tensor, ...]:
    """An optional tensor argument, for _one_device: itself, or nothing."""
    return () if t is None else (t,)


def _or_empty(t: Optional[Tensor], like: Tensor) -> Tensor:
    """An optional tensor argument for the builds: itself (contiguous), or an empty one of like's dtype."""
    return like.new_zeros(0) if t is None else t.contiguous()


def _zeros_if_none(g, shape, like: Tensor) -> Tensor:
    return like.new_zeros(shape) if g is None else g.contiguous()


# The operators under the extension's names: what cuda_backend's autograd wrappers call.
KERNELS = SimpleNamespace(preprocess_forward=torch.ops.geer.preprocess_forward, associate=torch.ops.geer.associate,
                          render_forward=torch.ops.geer.render_forward, render_backward=torch.ops.geer.render_backward,
                          preprocess_backward=torch.ops.geer.preprocess_backward)
