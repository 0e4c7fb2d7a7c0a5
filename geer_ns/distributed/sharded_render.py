"""Gaussian-parallel rendering: every process holds a shard of the Gaussians; a camera is rendered by the process
that supervises it, from every shard's Gaussians the camera can see.

Each process finds the rows of its shard each camera sees (render.associate.seen_by), sends them with their
evaluated color to the camera's process by a differentiable all-to-all (torch.distributed.nn: the backward is
the reverse all-to-all of the gradients), and the camera's process renders what it received exactly as one
process renders a scene. What travels per (Gaussian, camera) and why: docs/distributed.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, List, Optional, Sequence, Tuple

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


def shard_rows(rank: int, processes: int) -> slice:
    """Rank `rank`'s rows of a model: every `processes`-th row. Round robin spreads every region of the scene,
    and so every camera's work, evenly over the processes (docs/distributed.md)."""
    return slice(rank, None, processes)


@dataclass
class ShardViews:
    """What a process learns about its own shard in every camera of an exchange (for densification)."""

    seen: List[Tensor]  # per camera [N] bool: the rows it sent (the Gaussians the camera sees)
    max_weight: List[Tensor]  # per camera [N]: each row's largest blend weight there (0 where not seen)
    sent: int  # rows sent in all (payload rows: the traffic is sent x (14 or 16) numbers, both ways)


def render_sharded(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmats: Tensor,
    grids: Sequence[RayGrid],
    rows_of: Callable[[int, Tensor], Tuple[Tensor, Tensor, Tensor, Tensor, Tensor]],
    *,
    background: Optional[Tensor] = None,
    lambda_mode: str = "opacity",
    backend: str = "auto",
    max_pairs: int = 1 << 20,
    absgrad_sinks: Optional[Sequence[Tensor]] = None,
    lateral: Optional[Callable[[Tensor], Tensor]] = None,
) -> Tuple[RenderOutput, ShardViews]:
    """Render this process's camera from every process's shard. A collective: every process calls it with its
    shard and the same cameras.

    Args:
        means, quats, scales, opacities: this shard as render() takes them ([N,3], [N,4], [N,3], [N]); they only
            decide which rows each camera sees.
        viewmats: [C,4,4] every process's camera in rank order (C = the number of processes); grids: their rays.
        rows_of: (q, rows) -> camera q's payload of those rows (means, quats, scales, opacities, RGB),
            differentiable: a model evaluates its activations per camera, as one process does per image.
        absgrad_sinks: per camera a [N,2] leaf (render's absgrad); `lateral` turns the received view-space
            means into render's absgrad basis.

    Returns:
        The render of this process's camera (over the received Gaussians) and what each camera saw of this shard.
    """
    world = current_world()
    cams = viewmats.shape[0]
    if cams != world.size or len(grids) != world.size:
        raise ValueError(f"render_sharded: one camera per process expected ({world.size}), got {cams} viewmats "
                         f"and {len(grids)} grids")
    blocks, seen = [], []
    for q in range(cams):
        with torch.no_grad():
            pre = preprocess(means.detach(), quats.detach(), scales.detach(), opacities.detach(),
                             means.new_zeros(means.shape[0], 3), viewmats[q], lambda_mode=lambda_mode)
            rows = torch.nonzero(seen_by(pre.pbf, grids[q])).squeeze(1)
        m, q_rows, s_rows, o_rows, rgb = rows_of(q, rows)
        columns = [m, q_rows, s_rows, o_rows[:, None], rgb]
        if absgrad_sinks is not None:
            columns.append(absgrad_sinks[q][rows])
        blocks.append(torch.cat(columns, -1))
        mask = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
        mask[rows] = True
        seen.append(mask)
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
                 lambda_mode=lambda_mode, backend=backend, max_pairs=max_pairs, **extra)
    weights = _weights_home(out, send_counts, recv_counts, world.distributed, payload)
    max_weight = []
    for q, chunk in enumerate(weights.split(send_counts)):
        w = torch.zeros(means.shape[0], dtype=chunk.dtype, device=chunk.device)
        w[seen[q]] = chunk
        max_weight.append(w)
    return out, ShardViews(seen, max_weight, sum(send_counts))


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
