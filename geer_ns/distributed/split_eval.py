"""Gaussian-parallel evaluation split by pixels: every process renders bands of the evaluation image's tile rows
from the rows of every shard that band sees, so that no process holds the scene, or all a camera sees of it.

A camera's tile rows are cut into at most BANDS_PER_PROCESS x R bands (R processes), dealt out round by round:
in round k process q renders band k R + q. In each round every process finds, for every band of the round, the
rows of its shard that band sees (the association's own tile search, sharded_render.visible_rows), evaluates
their color for the camera and sends them (PAYLOAD numbers a row) to the band's process by one all-to-all; each
process renders its band (colors, then normals) and lets the rows go. Rank 0 receives the bands' pixels at the
end and makes nerfstudio's outputs of the whole image. A band's pixels are those of the whole image's render:
each tile blends the Gaussians its own search finds, sorted by depth, whichever other tiles are rendered with
it. Peak memory and why pixels, not Gaussians, are split: docs/distributed.md, "Memory".
"""

from __future__ import annotations

from typing import Dict, List, Optional, Tuple

import torch
import torch.distributed as dist
from torch import Tensor

from geer_ns.shutter_views import refuse_rolling_shutter
from geer_ns.distributed.sharded_render import PAYLOAD, visible_rows
from geer_ns.distributed.world import World, backend_device, current_world, exchange_counts, on_backend_device
from geer_ns.render import RayGrid, render
from geer_ns.render.normals import NormalImages, render_normals
from geer_ns.render.sh import sh_to_color
from geer_ns.render.transforms import camera_offsets

BANDS_PER_PROCESS = 4  # an evaluation image is cut into at most this many bands per process
CHANNELS = 12  # a band's pixels: rgb 3, distance 1, accumulation 1, median distance 1, normals world 3, camera 3


class PixelImages:
    """The per-pixel part of a RenderOutput (what model.view_outputs reads) of a whole image made of bands."""

    def __init__(self, rgb: Tensor, depth: Tensor, accumulation: Tensor, median_distance: Optional[Tensor]):
        self.rgb, self.depth, self.accumulation, self.median_distance = rgb, depth, accumulation, median_distance

    @property
    def distance(self) -> Tensor:
        return self.depth


def band_grid(grid: RayGrid, first: int, stop: int) -> RayGrid:
    """The rays of tile rows [first, stop) of `grid` as a grid of their own: the same tiles (rays, bounds,
    activity) over the band's pixel rows, so that its render is those rows of the whole grid's render."""
    width, size = grid.width, grid.tile_size
    top, bottom = first * size, min(stop * size, grid.height)
    tiles = slice(first * grid.tiles_x, stop * grid.tiles_x)
    rays = grid.tile_rays[tiles]
    band = RayGrid(grid.dirs[top * width : bottom * width], grid.valid[top * width : bottom * width], bottom - top,
                   width, size, torch.where(rays >= 0, rays - top * width, rays), grid.tile_theta[tiles],
                   grid.tile_phi[tiles], grid.tile_active[tiles])
    band.num_valid  # counted once, where the grid is
    return band


def bands(tile_rows: int, processes: int) -> List[Tuple[int, int]]:
    """(first, stop) tile rows of each band: at most BANDS_PER_PROCESS a process, as even as the rows allow."""
    count = max(1, min(tile_rows, BANDS_PER_PROCESS * processes))
    edges = [round(i * tile_rows / count) for i in range(count + 1)]
    return list(zip(edges[:-1], edges[1:]))


@torch.no_grad()
def split_outputs(model, camera) -> Optional[Dict[str, Tensor]]:
    """nerfstudio's evaluation outputs of `camera` (GeerModel.get_outputs in eval mode) rendered band by band
    over every process's shard (module docstring). A collective: every process calls it with the same camera
    (on its device); the outputs on rank 0, None elsewhere."""
    refuse_rolling_shutter([camera], "split evaluation (--pipeline.model.distributed gaussians)")
    world = current_world()
    training = model.training
    model.eval()
    try:
        view = model.view_for(camera)
        background = model.render_background()
        pose = model.render_pose(camera)
    finally:
        model.train(training)
    params = {name: p.detach() for name, p in model.gauss_params.items()}
    device = params["means"].device
    viewmat, grid = model.viewmat(pose, device), view.rays.to(device)
    background = background.to(params["means"])
    cut = bands(grid.tiles_y, world.size)
    pixels: List[Tensor] = []  # this process's bands' pixels, in its bands' order
    median = True  # whether the renders gave a median distance (every backend's does)
    for start in range(0, len(cut), world.size):
        grids = [band_grid(grid, *cut[i]) if i < len(cut) else None for i in range(start, start + world.size)]
        blocks = [_payload(model, params, viewmat, g) for g in grids]
        received = _exchange(world, blocks)
        mine = grids[world.rank]
        if mine is not None:
            band, median = _render_band(model, received, viewmat, mine, background)
            pixels.append(band)
        del blocks, received
    images = _gather_bands(world, pixels, [(b - a) for a, b in cut], grid, params["means"].dtype)
    if images is None:
        return None
    height, width = view.size
    rgb, distance, acc, median_distance, world_n, camera_n = images.reshape(height, width, CHANNELS).split(
        [3, 1, 1, 1, 3, 3], dim=-1)
    out = PixelImages(rgb, distance, acc, median_distance if median else None)
    return model.view_outputs(out, view, background, camera, NormalImages(world_n, camera_n))


def _payload(model, params: Dict[str, Tensor], viewmat: Tensor, grid: Optional[RayGrid]) -> Tensor:
    """[k, PAYLOAD] the rows of this shard `grid` sees (none without a grid): means, quaternions, activated
    scales and opacity, and their color in this camera."""
    if grid is None:
        return params["means"].new_zeros(0, PAYLOAD)
    rows = visible_rows(params, viewmat, grid, model.config.lambda_mode, model.activated)
    part = {name: p[rows] for name, p in params.items()}
    scales, opacities = model.activated(part)
    colors, degree = model.colors(part)
    rgb = colors if colors.ndim == 2 else sh_to_color(colors, camera_offsets(part["means"], viewmat), degree)
    return torch.cat([part["means"], part["quats"], scales, opacities[:, None], rgb], -1)


def _exchange(world: World, blocks: List[Tensor]) -> Tensor:
    """Block q to process q; what every process sent this one, in rank order."""
    if not world.distributed:
        return blocks[0]
    send_counts = [b.shape[0] for b in blocks]
    recv_counts = exchange_counts(send_counts)
    sending = on_backend_device(torch.cat(blocks))
    received = sending.new_empty(sum(recv_counts), PAYLOAD)
    dist.all_to_all_single(received, sending, recv_counts, send_counts)
    return received.to(blocks[0].device)


def _render_band(model, rows: Tensor, viewmat: Tensor, grid: RayGrid, background: Tensor) -> Tuple[Tensor, bool]:
    """([h W, CHANNELS] a band's pixels rendered from the rows it sees, whether the render gave a median)."""
    means, quats, scales, opacities, rgb = rows.split([3, 4, 3, 1, 3], dim=1)
    opacities = opacities.squeeze(1)
    options = model.render_options()
    out = render(means, quats, scales, opacities, rgb, viewmat, grid, background=background, **options)
    normals = render_normals(means, quats, scales, opacities, viewmat, grid, **options)
    median = out.median_distance if out.median_distance is not None else torch.zeros_like(out.depth)
    return torch.cat([out.rgb, out.depth, out.accumulation, median, normals.world, normals.camera],
                     -1).reshape(-1, CHANNELS), out.median_distance is not None


def _gather_bands(world: World, pixels: List[Tensor], tile_rows: List[int], grid: RayGrid,
                  dtype: torch.dtype) -> Optional[Tensor]:
    """[H W, CHANNELS] every band's pixels in image order on rank 0 (None elsewhere): band i is process
    i mod R's (i // R)-th."""
    if not world.distributed:
        return torch.cat(pixels)
    if not world.is_main:
        for band in pixels:
            dist.send(band.contiguous().to(backend_device(band)), dst=0)
        return None
    out, size = [], grid.tile_size
    top = 0
    for i, rows in enumerate(tile_rows):
        height = min((top + rows) * size, grid.height) - top * size
        owner, nth = i % world.size, i // world.size
        if owner == 0:
            out.append(pixels[nth])
        else:
            buffer = torch.empty(height * grid.width, CHANNELS, dtype=dtype, device=backend_device(grid.dirs))
            dist.recv(buffer, src=owner)
            out.append(buffer.to(grid.dirs.device))
        top += rows
    return torch.cat(out)
