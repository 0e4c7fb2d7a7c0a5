"""The 3DGEER pipeline in PyTorch: the specification for the CUDA kernels and the CPU renderer.

    preprocess (per Gaussian)  view transform, whitening, PBF, color        transforms/pbf/sh
    associate (per tile)       PBF x CSF overlap, front-to-back lists        associate
    render (per ray)           exact transmittance, front-to-back blending   transmittance/composite/blend

Everything is differentiable with autograd w.r.t. means, quats, scales, opacities and colors; the
discrete steps (association, skipping, early termination) are piecewise constant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from .absgrad import check_absgrad, offset_rows
from .associate import associate
from .cones import gaussian_cone_form
from .backend import Backend, resolve_backend
from .blend import blend_lists
from .cuda_backend import render_cuda
from .extensions import load_cpu_ops
from .moving import MovingRays, motion_pbf
from .order import CompositeOrder
from .outputs import RenderOutput, images
from .pbf import PBF, LambdaMode, compute_pbf, pbf_lambda_sq
from .raygrid import RayGrid
from .sh import sh_to_color
from .transforms import camera_offsets, canonical_frame, covariance_factor, view_transform
from .validate import check_gaussians, check_shape


@dataclass
class Preprocessed:
    """Per-Gaussian quantities shared by every ray of one view."""

    means_c: Tensor  # [N, 3] view-space means (read .grad after backward for densification)
    whiten: Tensor  # [N, 3, 3] W = S^-1 R_v^T
    o_u: Tensor  # [N, 3] camera center in each canonical frame
    colors: Tensor  # [N, 3]
    opacities: Tensor  # [N]
    depth: Tensor  # [N] Euclidean distance of the mean, the sort key
    pbf: PBF


def preprocess(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    sh_degree: int | Tensor | None = None,
    lambda_mode: LambdaMode = "opacity",
) -> Preprocessed:
    means_c = view_transform(means, viewmat)
    if means_c.requires_grad:
        means_c.retain_grad()
    rot_v, w, o_u = canonical_frame(means_c, quats, scales, viewmat)
    lam2, alive = pbf_lambda_sq(opacities.detach(), lambda_mode)
    pbf = compute_pbf(means_c.detach(), covariance_factor(rot_v, scales).detach(), lam2, alive, o_u.detach())
    pbf.cone = gaussian_cone_form(w.detach(), o_u.detach(), lam2, pbf.camera_inside)
    if colors.ndim == 2:
        rgb = colors
    else:
        degree = int(math.isqrt(colors.shape[1]) - 1) if sh_degree is None else sh_degree
        rgb = sh_to_color(colors, camera_offsets(means, viewmat), degree)
    return Preprocessed(means_c, w, o_u, rgb, opacities, means_c.detach().norm(dim=-1), pbf)


def _check_inputs(means, quats, scales, opacities, colors, viewmat, grid, background, sh_degree=None) -> None:
    if not isinstance(grid, RayGrid):
        raise TypeError(f"grid: expected a RayGrid, got {type(grid).__name__}")
    check_gaussians(means, quats, scales, opacities, colors, viewmat=viewmat, background=background,
                    grid=grid, sh_degrees=sh_degree if isinstance(sh_degree, Tensor) else None)  # one sync


def render(
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
    backend: Backend = "auto",
    max_pairs: int = 1 << 20,
    absgrad: tuple[Tensor, Tensor] | None = None,
    motion: MovingRays | None = None,
    order: CompositeOrder | str | None = None,
) -> RenderOutput:
    """Render one view with 3DGEER.

    means [N,3], quats [N,4] (wxyz), scales [N,3] (> 0), opacities [N] in [0,1], colors [N,3] (RGB) or
    [N,K,3] (SH coefficients, degree `sh_degree`, default the largest K allows; a [N] integer tensor gives each
    Gaussian its own degree, at most K's: bands above it are not evaluated and get no gradient), viewmat [4,4]
    world-to-camera (OpenCV axes, rigid: validate.ROTATION_TOLERANCE), grid: the view's rays. float32 or float64
    (everything follows means); every tensor, the grid's too, on the means' device.
    `max_pairs` caps the (ray, Gaussian) pairs the PyTorch renderer holds at once, forward and backward
    (memory model: blend.py); the kernels need no such cap.
    `absgrad` = (lateral [N,3,2], sink [N,2] requiring grad): after backward, sink.grad holds AbsGS's per-pixel
    absolute sums of the gradient w.r.t. lateral offsets of the view-space means (absgrad.py); outputs and
    every other gradient are unchanged by it.
    `motion` (moving.MovingRays): each ray's own origin and direction in this view's camera frame (a rolling-shutter
    view: every ray at its own time); the grid still gives the rays' pixels, tiles and validity. SH colours are
    evaluated from the view's camera centre.
    `order` (order.CompositeOrder or 'view' / 'ray' / 'ray:K'): the compositing order, the tile list's per view
    (default) or each ray's own; the PyTorch renderer composites every per-ray order exactly (it has no window).
    """
    _check_inputs(means, quats, scales, opacities, colors, viewmat, grid, background, sh_degree)
    order = CompositeOrder.parse(order)
    if absgrad is not None:
        check_absgrad(absgrad, means)
    if motion is not None:
        motion.check(grid.num_rays, means)
    chosen = resolve_backend(backend, means.device)
    if chosen != "torch":  # the kernels (CUDA), or their math compiled for the CPU
        return render_cuda(means, quats, scales, opacities, colors, viewmat, grid, sh_degree=sh_degree,
                           background=background, lambda_mode=lambda_mode,
                           ops=load_cpu_ops() if chosen == "cpu" else None, absgrad=absgrad, motion=motion,
                           order=order)
    dirs = grid.dirs.to(means.dtype) if motion is None else motion.dirs.to(means.dtype)
    origins = None if motion is None else motion.origins.to(means.dtype)
    # viewmat keeps its dtype: the view transform runs in float64 (transforms.view_transform)
    pre = preprocess(means, quats, scales, opacities, colors, viewmat, sh_degree, lambda_mode)
    if motion is not None:
        pre.pbf = motion_pbf(pre.means_c, quats, scales, opacities, viewmat, lambda_mode, motion)
    tiles = associate(pre.pbf, grid if motion is None else motion.tile_grid(grid), pre.depth)
    rows = (offset_rows(absgrad[0], pre.whiten), absgrad[1]) if absgrad is not None else None
    rgb, depth, acc, max_weight, median = blend_lists(pre.o_u, pre.whiten, pre.opacities, pre.colors, dirs,
                                                      grid.valid, grid.tile_rays, tiles.gaussians, tiles.counts,
                                                      max_pairs, rows, origins, per_ray=order.per_ray)
    out_rgb, out_depth, out_acc = images(grid.height, grid.width, rgb, depth, acc, background)
    visible = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
    listed = tiles.gaussians[grid.tile_active]
    visible[listed[listed >= 0]] = True
    return RenderOutput(out_rgb, out_depth, out_acc, visible, tiles.counts, pre.means_c, pre.pbf, tiles, max_weight,
                        median.reshape(grid.height, grid.width, 1))


def render_batch(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    grids: RayGrid | Sequence[RayGrid],
    *,
    sh_degree: int | Tensor | None = None,
    background: Tensor | None = None,
    lambda_mode: LambdaMode = "opacity",
    backend: Backend = "auto",
    max_pairs: int = 1 << 20,
    absgrad: Sequence[tuple[Tensor, Tensor] | None] | None = None,
    order: CompositeOrder | str | None = None,
) -> list[RenderOutput]:
    """Render C cameras of one scene: viewmats [C,4,4], grids one RayGrid for every camera or one per camera
    (mixed rigs); `absgrad` one (lateral, sink) pair (or None) per camera, as `render`'s, each view's statistics
    its own. Each view is what `render` gives for it (checks included), outputs and gradients. Views are
    rendered one after the other: their lists and pairs differ, and one view's pairs at a time is what bounds
    the memory (a training step with several images also runs each image's backward before the next image's
    forward: geer_ns/training/trainer.py)."""
    check_shape("viewmats", viewmats, (None, 4, 4))
    views = viewmats.shape[0]
    grids = [grids] * views if isinstance(grids, RayGrid) else list(grids)
    if len(grids) != views:
        raise ValueError(f"grids: expected one RayGrid or {views} (one per viewmat), got {len(grids)}")
    absgrad = [None] * views if absgrad is None else list(absgrad)
    if len(absgrad) != views:
        raise ValueError(f"absgrad: expected {views} (lateral, sink) pairs or None (one per viewmat), got {len(absgrad)}")
    return [render(means, quats, scales, opacities, colors, viewmats[c], grids[c], sh_degree=sh_degree,
                   background=background, lambda_mode=lambda_mode, backend=backend, max_pairs=max_pairs,
                   absgrad=absgrad[c], order=order)
            for c in range(views)]


def render_brute_force(
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
    rays_per_group: int = 64,
    max_pairs: int = 1 << 20,
    order: CompositeOrder | str | None = None,
) -> RenderOutput:
    """Reference renderer: every valid ray against every Gaussian, no PBF, no tiles, same ordering (`order`:
    render's, the exact per-ray order or the per-view one).

    The tiled renderer must match it exactly whenever association is complete.
    """
    order = CompositeOrder.parse(order)
    _check_inputs(means, quats, scales, opacities, colors, viewmat, grid, background, sh_degree)
    dirs = grid.dirs.to(means.dtype)
    pre = preprocess(means, quats, scales, opacities, colors, viewmat.to(means.dtype), sh_degree)
    by_depth = torch.sort(pre.depth, stable=True).indices
    n_rays = grid.num_rays
    pad = (-n_rays) % rays_per_group
    ray_index = torch.cat([torch.arange(n_rays, device=means.device), means.new_full((pad,), -1).long()])
    ray_index = ray_index.reshape(-1, rays_per_group)
    lists = by_depth[None].expand(ray_index.shape[0], -1)
    counts = torch.full((ray_index.shape[0],), by_depth.numel(), dtype=torch.long, device=means.device)
    rgb, depth, acc, max_weight, median = blend_lists(pre.o_u, pre.whiten, pre.opacities, pre.colors, dirs,
                                                      grid.valid, ray_index, lists, counts, max_pairs,
                                                      per_ray=order.per_ray)
    out_rgb, out_depth, out_acc = images(grid.height, grid.width, rgb, depth, acc, background)
    visible = torch.ones(means.shape[0], dtype=torch.bool, device=means.device)
    return RenderOutput(out_rgb, out_depth, out_acc, visible, means.new_zeros(0).long(), pre.means_c, pre.pbf, None,
                        max_weight, median.reshape(grid.height, grid.width, 1))
