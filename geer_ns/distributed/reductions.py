"""The per-step reductions of both engines: every process's gradients and densification statistics summed.

Each step, after every process's backward over its own images: one all-reduce of every parameter's gradient, in
buckets (world.all_reduce_), then the mean over the step's images (the effective batch); and one all-reduce of the
densification statistics (sum, sum, max: densify.signal.StepStatistics), so that every process makes the same
split / duplicate / prune / reset decisions.
"""

from __future__ import annotations

from typing import List, Sequence

import torch

from geer_ns.densify.signal import StepStatistics
from geer_ns.distributed.world import World, all_reduce_


def optimized_parameters(optimizers) -> List[torch.nn.Parameter]:
    """Every parameter the optimizers step, in one order on every process (nerfstudio's group order).
    Read from the optimizers, not the model: densification replaces the Parameter objects in both."""
    return [p for opt in optimizers.optimizers.values() for group in opt.param_groups for p in group["params"]]


def reduce_gradients(world: World, params: Sequence[torch.nn.Parameter], images: int) -> None:
    """Every parameter's gradient summed over the processes, then divided by the step's `images`. A gradient
    that no process produced stays None; one that only some did counts as zero on the others."""
    if world.distributed:
        has = torch.tensor([p.grad is not None for p in params], dtype=torch.int32)
        all_reduce_([has], op="max")
        for p, flag in zip(params, has.tolist()):
            if flag and p.grad is None:
                p.grad = torch.zeros_like(p)
        all_reduce_([p.grad for p in params if p.grad is not None])
    if images != 1:
        for p in params:
            if p.grad is not None:
                p.grad.div_(images)


def reduce_statistics(world: World, stats: StepStatistics) -> StepStatistics:
    """The step's densification statistics over every process's views."""
    all_reduce_([stats.grad, stats.views])
    all_reduce_([stats.radius, stats.weight, stats.pixels], op="max")
    return stats


# ----------------------------------------------------------------------------------------- start-up
