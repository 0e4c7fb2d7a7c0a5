"""Gaussian-parallel rendering: every process holds a shard of the Gaussians; a camera is rendered by the process
that supervises it, from every shard's Gaussians the camera can see.

Each process finds the rows of its shard each camera sees (render.associate.seen_by), sends them with their
evaluated color to the camera's process by a differentiable all-to-all (torch.distributed.nn: the backward is
the reverse all-to-all of the gradients), and the camera's process renders what it received exactly as one
process renders a scene. What travels per (Gaussian, camera) and why: docs/distributed.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import torch
import torch.distributed as dist
import torch.distributed.nn.functional as dist_nn
from torch import Tensor

from geer_ns.distributed.world import current_world, exchange_counts, on_backend_device
from geer_ns.render import RayGrid, render
from geer_ns.render.associate import seen_by
from geer_ns.render.outputs import RenderOutput
from geer_ns.render.rasterize import preprocess
from geer_ns.render.transforms import view_transform

PAYLOAD = 14  # mean 3, quaternion 4, scale 3, opacity 1, RGB 3
SEARCH_ROWS = 1 << 18  # a camera's visibility search goes through a shard this many rows at a time


def shard_rows(rank: int, processes: int) -> slice:
    """Rank `rank`'s rows of a model: every `processes`-th row. Round robin spreads every region of the scene,
    and so every camera's work, evenly over the processes (docs/distributed.md)."""
    return slice(rank, None, processes)


def visible_rows(gaussians: Dict[str, Tensor], viewmat: Tensor, grid: RayGrid, lambda_mode: str = "opacity",
                 activate: Optional[Callable[[Dict[str, Tensor]], Tuple[Tensor, Tensor]]] = None) -> Tensor:
    """[k] the rows of `gaussians` (means, quats, scales, opacities) a camera's grid sees (its association's
    tile search, render.associate.seen_by), searched SEARCH_ROWS rows at a time so that the search's
    temporaries are a chunk's. `activate`: a chunk's (scales, opacities) as the renderer takes them from its
    raw parameters (a model's `activated`); None: `gaussians` holds them already."""
    means = gaussians["means"]
    found = []
    with torch.no_grad():
        for start in range(0, means.shape[0], SEARCH_ROWS):
            part = {name: p[start : start + SEARCH_ROWS].detach() for name, p in gaussians.items()}
            scales, opacities = (part["scales"], part["opacities"]) if activate is None else activate(part)
            pre = preprocess(part["means"], part["quats"], scales, opacities, part["means"].new_zeros(len(scales), 3),
                             viewmat, lambda_mode=lambda_mode)
            found.append(torch.nonzero(seen_by(pre.pbf, grid)).squeeze(1) + start)
            del pre, part
    return torch.cat(found) if found else torch.zeros(0, dtype=torch.long, device=means.device)


@dataclass
class ShardViews:
    """What a process learns about its own shard in every camera of an exchange (for densification)."""

    rows: List[Tensor]  # per camera [k] the rows it sent (the Gaussians of this shard the camera sees)
    max_weight: List[Tensor]  # per camera [k]: each of those rows' largest blend weight there
    sent: int  # rows sent in all (payload rows: the traffic is sent x (14 or 16) numbers, both ways)


def render_sharded(
    means: Tensor,
    quats: Tensor,
    scales: Optional[Tensor],
    opacities: Optional[Tensor],
    viewmats: Tensor,
    grids: Sequence[RayGrid],
    rows_of: Callable[[int, Tensor], Tuple[Tensor, Tensor, Tensor, Tensor, Tensor]],
    *,
    rows: Optional[Sequence[Tensor]] = None,
    background: Optional[Tensor] = None,
    lambda_mode: str = "opacity",
    backend: str = "auto",
    max_pairs: int = 1 << 20,
    order: Optional[str] = None,
    absgrad_sinks: Optional[Sequence[Tensor]] = None,
    lateral: Optional[Callable[[Tensor], Tensor]] = None,
) -> Tuple[RenderOutput, ShardViews]:
    """Render this process's camera from every process's shard. A collective: every process calls it with its
    shard and the same cameras.

    Args:
        means, quats, scales, opacities: this shard as render() takes them ([N,3], [N,4], [N,3], [N]); they only
            decide which rows each camera sees (scales and opacities may be None when `rows` are given).
        viewmats: [C,4,4] every process's camera in rank order (C = the number of processes); grids: their rays.
        rows_of: (q, rows) -> camera q's payload of those rows (means, quats, scales, opacities, RGB),
            differentiable: a model evaluates its activations per camera, as one process does per image.
        rows: per camera the rows of this shard it sees (visible_rows), when the caller found them already.
        absgrad_sinks: per camera a [k,2] leaf over its rows (render's absgrad); `lateral` turns the received
            view-space means into render's absgrad basis.

    Returns:
        The render of this process's camera (over the received Gaussians) and what each camera saw of this shard.
    """
    world = current_world()
    cams = viewmats.shape[0]
    if cams != world.size or len(grids) != world.size:
        raise ValueError(f"render_sharded: one camera per process expected ({world.size}), got {cams} viewmats "
                         f"and {len(grids)} grids")
    if rows is None:
        shard = {"means": means, "quats": quats, "scales": scales, "opacities": opacities}
        rows = [visible_rows(shard, viewmats[q], grids[q], lambda_mode) for q in range(cams)]
    blocks = []
    for q in range(cams):
        m, q_rows, s_rows, o_rows, rgb = rows_of(q, rows[q])
        columns = [m, q_rows, s_rows, o_rows[:, None], rgb]
        if absgrad_sinks is not None:
            columns.append(absgrad_sinks[q])
        blocks.append(torch.cat(columns, -1))
    send_counts = [b.shape[0] for b in blocks]
    payload = torch.cat(blocks)
    if world.distributed:
        recv_counts = exchange_counts(send_counts)
        sending = on_backend_device(payload)
        received = sending.new_empty(sum(recv_counts), payload.shape[1])
        received = dist_nn.all_to_all_single(received, sending, recv_counts, send_counts).to(payload.device)
    else:
        recv_counts, received = send_counts, payload
    me = world.rank
    r_means, r_quats, r_scales, r_opac, r_rgb = received[:, :PAYLOAD].split([3, 4, 3, 1, 3], dim=1)
    extra = {}
    if absgrad_sinks is not None:
        basis = lateral(view_transform(r_means.detach(), viewmats[me]))
        extra["absgrad"] = (basis, received[:, PAYLOAD:])
    out = render(r_means, r_quats, r_scales, r_opac.squeeze(1), r_rgb, viewmats[me], grids[me], background=background,
                 lambda_mode=lambda_mode, backend=backend, max_pairs=max_pairs, order=order, **extra)
    weights = _weights_home(out, send_counts, recv_counts, world.distributed, payload)
    return out, ShardViews(list(rows), list(weights.split(send_counts)), sum(send_counts))


def _weights_home(out: RenderOutput, send_counts: List[int], recv_counts: List[int], distributed: bool,
                  like: Tensor) -> Tensor:
    """Each sent row's largest blend weight in its camera, back at its owner (the reverse exchange)."""
    weight = out.max_weight.to(like.dtype)
    if not distributed:
        return weight
    sending = on_backend_device(weight)
    home = sending.new_empty(sum(send_counts))
    dist.all_to_all_single(home, sending, send_counts, recv_counts)
    return home.to(like.device)
