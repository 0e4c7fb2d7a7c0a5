"""Gaussian-parallel training (`--pipeline.model.distributed gaussians`): each process holds a shard of the
Gaussians, its parameters and optimiser state; scenes are limited by the sum of the devices' memory.

* Shards: at start-up every process builds (or loads) the whole model, takes rank 0's values, and keeps every
  N-th Gaussian (shards.shard_rows: round robin, so each camera's work is spread evenly).
* A step is rounds of one camera per process: in round i every process renders its i-th image from every
  shard (shards.render_sharded) and backpropagates its loss, whose gradients come home by the reverse
  all-to-all. Every shard's gradients are then complete: no Gaussian gradient is reduced; the few replicated
  parameters (bilateral grids) are all-reduced as in image-parallel training.
* Densification per shard on its own Gaussians' statistics, which are complete too (every camera's gradient of
  a Gaussian reaches its owner); splits draw from each Gaussian's identity, so they equal one process's.
  After a refinement the shards are rebalanced when their sizes differ by more than REBALANCE_FRACTION.
* Checkpoints are gathered: rank 0 writes one ordinary checkpoint (the shards' rows in rank order) that one
  process, ns-eval, ns-export and the viewer read; resuming keeps every N-th row of it, for any N.
* Evaluation and the viewer on rank 0 render the gathered model (gathered at each evaluation, and every
  VIEWER_REFRESH_STEPS steps while a viewer runs): the scene must fit rank 0's memory for that, not its
  training state.
"""

from __future__ import annotations

from typing import Callable, Dict, Iterator, List, Optional, Tuple

import torch
import torch.distributed as dist
from gsplat.strategy.ops import _update_param_with_optimizer, remove
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.utils.misc import step_check
from torch import Tensor

from geer_ns.densify.signal import lateral_basis
from geer_ns.densify.strategy import GeerDefaultStrategy
from geer_ns.distributed.replicas import (
    broadcast_replica,
    check_consistent,
    fingerprint,
    optimised_parameters,
    reduce_gradients,
)
from geer_ns.distributed.shards import render_sharded, shard_rows
from geer_ns.distributed.world import World, all_gather_objects, on_backend_device
from geer_ns.render.sh import sh_to_color
from geer_ns.render.transforms import camera_offsets

REBALANCE_FRACTION = 0.1  # rebalance when the largest shard exceeds the smallest by more than this
VIEWER_REFRESH_STEPS = 100
GAUSS_PREFIX = "_model.gauss_params."


class GaussianParallel:
    """The engine of Gaussian-parallel training (module docstring), for geer_ns.distributed.trainer."""

    name = "gaussians"

    def __init__(self, trainer) -> None:
        self.trainer, self.world = trainer, trainer.world
        model = trainer.pipeline.model
        problems = []
        if not isinstance(model.strategy, GeerDefaultStrategy):
            problems.append("--pipeline.model.strategy mcmc (MCMC relocates by sampling the whole scene)")
        if model.config.densify_signal != "angular":
            problems.append("--pipeline.model.densify-signal pixels (its screen size comes from the render's PBF)")
        if model.config.camera_optimizer.mode != "off":
            problems.append("--pipeline.model.camera-optimizer.mode (pose gradients would reach one shard only)")
        if problems:
            raise ValueError("geer: --pipeline.model.distributed gaussians does not support " + "; ".join(problems))

    # ------------------------------------------------------------------------------------- start-up
    def start(self) -> None:
        """A fresh start: rank 0's model (the seed cloud), cut into shards here. A resumed run loaded its shard
        alone (trainer._load_checkpoint with shard_checkpoint)."""
        trainer, model = self.trainer, self.trainer.pipeline.model
        if self.world.distributed:
            check_consistent(self.world, fingerprint(trainer))
        if model.scene_gaussians is not None:  # loaded as a shard
            return
        if self.world.distributed:
            broadcast_replica(self.world, model, trainer.optimizers)  # one model, then cut into shards
        state = model.strategy_state
        if state.get("id") is None:
            state["id"] = torch.arange(model.num_points, device=model.device)
        total = model.num_points
        keep = torch.zeros(total, dtype=torch.bool, device=model.device)
        keep[shard_rows(self.world.rank, self.world.size)] = True
        remove(params=model.gauss_params, optimizers=trainer.optimizers.optimizers, state=state, mask=~keep)
        model.scene_gaussians = total

    def describe(self) -> List[str]:
        model = self.trainer.pipeline.model
        return [f"Gaussians sharded over {self.world.size} process(es): {model.num_points} of {model.scene_gaussians} "
                "here; rank 0 evaluates and serves the viewer from the gathered model"]

    # --------------------------------------------------------------------------------- the step
    def views(self, step: int) -> Iterator[Tuple[Dict, Callable[[], Dict[str, Tensor]]]]:
        """Rounds of one camera per process: this process's image of round i, and the collective render."""
        dm, model = self.trainer.pipeline.datamanager, self.trainer.pipeline.model
        per, size, me = self.trainer.batch.images_per_process, self.world.size, self.world.rank
        indices = dm.next_train_indices(self.trainer.batch.images)
        for i in range(per):
            cameras = [dm.train_camera(indices[q * per + i]) for q in range(size)]
            _, batch = dm.train_view(indices[me * per + i])
            yield batch, (lambda cameras=cameras: sharded_outputs(model, cameras, me))

    def reduce_gradients(self) -> None:
        model, optimizers = self.trainer.pipeline.model, self.trainer.optimizers
        own = {id(p) for p in model.gauss_params.values()}
        params = optimised_parameters(optimizers)
        reduce_gradients(self.world, [p for p in params if id(p) not in own], self.trainer.batch.images)
        reduce_gradients(World(), [p for p in params if id(p) in own], self.trainer.batch.images)

    def reduce_statistics(self, model) -> None:
        model.use_step_statistics(model.step_statistics())  # complete already: every camera's gradient came home

    def callbacks(self) -> List[TrainingCallback]:
        return [TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._after_step)]

    def _after_step(self, step: int) -> None:
        """After densification: the scene's size, and a rebalance where the shards drifted apart."""
        model = self.trainer.pipeline.model
        sizes = all_gather_objects(model.num_points)
        model.scene_gaussians = sum(sizes)
        if max(sizes) > (1.0 + REBALANCE_FRACTION) * max(min(sizes), 1):
            rebalance(self.world, model, self.trainer.optimizers.optimizers, sizes)

    # ------------------------------------------------------------------------- checkpoints, eval
    def checkpoint_state(self, step: int) -> Optional[dict]:
        """The gathered checkpoint on rank 0 (None elsewhere); every process takes part."""
        trainer = self.trainer
        model = trainer.pipeline.model
        pipeline = trainer.pipeline.state_dict()
        for key in [k for k in pipeline if k.startswith(GAUSS_PREFIX)]:
            pipeline[key] = gather_rows(self.world, pipeline[key])
        extra = pipeline.get("_model._extra_state")
        if extra is not None:
            extra["strategy_state"] = {k: gather_rows(self.world, v) if _per_gaussian(v, model) else v
                                       for k, v in extra["strategy_state"].items()}
        optimizers = {}
        for name, optimizer in trainer.optimizers.optimizers.items():
            saved = optimizer.state_dict()
            if name in model.gauss_params:
                for slot in saved["state"].values():
                    for key in list(slot):
                        if _per_gaussian(slot[key], model):
                            slot[key] = gather_rows(self.world, slot[key])
            optimizers[name] = saved
        if not self.world.is_main:
            return None
        return {"step": step, "pipeline": pipeline, "optimizers": optimizers,
                "schedulers": {k: v.state_dict() for k, v in trainer.optimizers.schedulers.items()},
                "scalers": trainer.grad_scaler.state_dict()}

    def evaluate(self, step: int, run: Callable[[], None]) -> None:
        """Gather the model to rank 0 when it evaluates (or its viewer is due a refresh), then run there."""
        config = self.trainer.user_config
        due = any(step_check(step, n) for n in (config.steps_per_eval_batch, config.steps_per_eval_image,
                                                 config.steps_per_eval_all_images))
        viewer = config.vis.startswith("viewer") and step_check(step, VIEWER_REFRESH_STEPS)
        if not (due or viewer):
            return
        model = self.trainer.pipeline.model
        gathered = {name: gather_rows(self.world, p.detach()) for name, p in model.gauss_params.items()}
        if self.world.is_main:
            model.display_gaussians = gathered
            if due:
                run()


def _per_gaussian(value, model) -> bool:
    return isinstance(value, Tensor) and value.dim() > 0 and value.shape[0] == model.num_points


def sharded_outputs(model, cameras, me: int) -> Dict[str, Tensor]:
    """GeerModel.get_outputs for camera `me` of `cameras` (one per process, this round's), rendered from every
    shard; records the densification view of this shard in every camera. Each camera's rows are made as one
    process makes a render's Gaussians (displaced, activated, coloured per view), so that every camera's
    gradient reaches the parameters through its own activations: the sums round as one process's do."""
    views = [model._view_for(camera) for camera in cameras]
    params = model._gaussians()
    means = params["means"]
    background = model._get_background_color().to(means)
    viewmats = torch.stack([model.viewmat(model.camera_optimizer.apply_to_camera(c)[0], means.device) for c in cameras])
    with torch.no_grad():
        scales, opacities = model.activated(params)
    record = model.training and torch.is_grad_enabled()
    probes = [model.probe(view, means, viewmats[q], scales, opacities) for q, view in enumerate(views)] if record \
        else []

    def rows_of(q: int, rows: Tensor):
        moved = probes[q].displace(means, viewmats[q]) if record else means
        part = {name: p[rows] for name, p in params.items()}
        s, o = model.activated(part)
        colors, sh_degree = model._colors(part)
        m = moved[rows]
        rgb = colors if colors.ndim == 2 else sh_to_color(colors, camera_offsets(m, viewmats[q]), sh_degree)
        return m, part["quats"], s, o, rgb

    absgrad = record and model.config.use_absgrad
    out, seen = render_sharded(
        means.detach(), params["quats"].detach(), scales, opacities, None, viewmats,
        [v.rays.to(means.device) for v in views], background=background, lambda_mode=model.config.lambda_mode,
        backend=model.config.renderer_backend, max_pairs=model.config.max_pairs,
        absgrad_sinks=[p.absgrad for p in probes] if absgrad else None, lateral=lateral_basis, rows_of=rows_of)
    for q, probe in enumerate(probes):
        model.views.append(probe.record(seen.seen[q], seen.max_weight[q]))
    return model.view_outputs(out, views[me], background, cameras[me])


# ----------------------------------------------------------------------------------------- rows
def shard_checkpoint(state: dict, rank: int, processes: int) -> Tuple[dict, int]:
    """A checkpoint (loaded on the CPU, memory-mapped) cut to rank `rank`'s rows before anything reaches the
    model, so that resuming never holds the whole scene on a device; returns it and the scene's size."""
    pipeline = dict(state["pipeline"])
    total = int(pipeline[GAUSS_PREFIX + "means"].shape[0])
    rows = shard_rows(rank, processes)

    def cut(value):
        is_rows = isinstance(value, Tensor) and value.dim() > 0 and value.shape[0] == total
        return value[rows].clone() if is_rows else value

    for key in [k for k in pipeline if k.startswith(GAUSS_PREFIX)]:
        pipeline[key] = cut(pipeline[key])
    extra = pipeline.get("_model._extra_state")
    if extra is not None:
        pipeline["_model._extra_state"] = {**extra, "strategy_state": {k: cut(v) for k, v in
                                                                       extra["strategy_state"].items()}}
    names = {k[len(GAUSS_PREFIX):] for k in pipeline if k.startswith(GAUSS_PREFIX)}
    optimizers = {}
    for group, saved in state["optimizers"].items():
        if group in names:
            saved = {**saved, "state": {i: {k: cut(v) for k, v in slot.items()} for i, slot in saved["state"].items()}}
        optimizers[group] = saved
    return {**state, "pipeline": pipeline, "optimizers": optimizers}, total


def gather_rows(world: World, tensor: Tensor) -> Optional[Tensor]:
    """Every shard's rows of `tensor`, in rank order, on rank 0 (None elsewhere; the tensor itself on one
    process). Uneven shards are padded for the collective and cut back."""
    if not world.distributed:
        return tensor
    sizes = all_gather_objects(int(tensor.shape[0]))
    padded = on_backend_device(tensor.new_zeros((max(sizes),) + tuple(tensor.shape[1:])))
    padded[: tensor.shape[0]] = tensor.detach()
    parts = [torch.empty_like(padded) for _ in sizes] if world.is_main else None
    dist.gather(padded, parts, dst=0)
    if not world.is_main:
        return None
    return torch.cat([part[:n] for part, n in zip(parts, sizes)]).to(tensor.device)


def rebalance(world: World, model, optimizers, sizes: List[int]) -> None:
    """Move rows from the largest shards to the smallest until their sizes differ by at most one: each shard
    gives away its last rows (the newest), received rows are appended in rank order; parameters, their
    optimiser state and the strategy's per-Gaussian state move together."""
    total, n = sum(sizes), len(sizes)
    targets = [total // n + (1 if r < total % n else 0) for r in range(n)]
    moves = _moves(sizes, targets)  # (from, to, count)
    me = world.rank
    send = [0] * n
    recv = [0] * n
    for src, dst, count in moves:
        if src == me:
            send[dst] += count
        if dst == me:
            recv[src] += count
    keep = sizes[me] - sum(send)

    def exchange(t: Tensor) -> Tensor:
        sending = on_backend_device(t[keep:])
        out = sending.new_empty((sum(recv),) + tuple(t.shape[1:]))
        dist.all_to_all_single(out, sending, recv, send)
        return torch.cat([t[:keep], out.to(t.device)])

    _update_param_with_optimizer(lambda name, p: torch.nn.Parameter(exchange(p.detach())),
                                 lambda key, v: exchange(v), model.gauss_params, optimizers,
                                 names=list(model.gauss_params.keys()))
    state = model.strategy_state
    for key in list(state):
        if isinstance(state[key], Tensor) and state[key].dim() > 0 and state[key].shape[0] == sizes[me]:
            state[key] = exchange(state[key])


def _moves(sizes: List[int], targets: List[int]) -> List[Tuple[int, int, int]]:
    """Transfers from ranks above their target to ranks below it, lowest ranks first (the same on every rank)."""
    give = [(r, s - t) for r, (s, t) in enumerate(zip(sizes, targets)) if s > t]
    take = [(r, t - s) for r, (s, t) in enumerate(zip(sizes, targets)) if t > s]
    moves, gi, ti = [], 0, 0
    while gi < len(give) and ti < len(take):
        (src, have), (dst, need) = give[gi], take[ti]
        count = min(have, need)
        moves.append((src, dst, count))
        give[gi], take[ti] = (src, have - count), (dst, need - count)
        gi += give[gi][1] == 0
        ti += take[ti][1] == 0
    return moves
