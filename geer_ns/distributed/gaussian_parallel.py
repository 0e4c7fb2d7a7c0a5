"""Gaussian-parallel training (`--pipeline.model.distributed gaussians`): each process holds a shard of the
Gaussians with their optimizer state, so scenes are limited by the sum of the devices' memory.

A step is rounds of one camera per process, each rendered from every shard (sharded_render); densification runs
per shard on its own complete statistics; checkpoints are one ordinary file written by rank 0; rank 0 runs the
evaluation, every process rendering bands of each image's pixels (split_eval). How and why: docs/distributed.md.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager
from typing import Callable, Dict, Iterator, List, Optional, Tuple

import torch
import torch.distributed as dist
from gsplat.strategy.ops import remove
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.utils.misc import step_check
from torch import Tensor

from geer_ns.shutter_views import refuse_rolling_shutter
from geer_ns import resume
from geer_ns.densify.signal import lateral_basis
from geer_ns.densify.strategy import PER_GAUSSIAN_STATE, local_budget, strongest_first
from geer_ns.distributed.consistency import broadcast_replica, check_consistent, fingerprint
from geer_ns.distributed.engine import EngineState
from geer_ns.distributed.reductions import optimized_parameters, reduce_gradients
from geer_ns.distributed.sharded_render import render_sharded, shard_rows, visible_rows
from geer_ns.distributed.split_eval import split_outputs
from geer_ns.distributed.streamed_checkpoint import leaves, replaced, save_rows_streamed
from geer_ns.errors import OptionError
from geer_ns.gsplat_private import update_param_with_optimizer
from geer_ns.distributed.world import (
    World,
    all_gather_counts,
    all_gather_objects,
    broadcast_object,
    current_world,
    on_backend_device,
)
from geer_ns.render.sh import sh_to_color
from geer_ns.render.transforms import camera_offsets

REBALANCE_FRACTION = 0.1  # rebalance when the largest shard exceeds the smallest by more than this
VIEWER_REFRESH_STEPS = 100
PIPELINE_GAUSS_PREFIX = "_model." + resume.GAUSS_PREFIX  # a Gaussian parameter's key in the pipeline's state


class GaussianParallel:
    """The engine of Gaussian-parallel training (module docstring), for geer_ns.training.trainer."""

    name = "gaussians"

    def __init__(self, trainer) -> None:
        """Before the trainer builds its pipeline (the model attaches `state` then)."""
        self.trainer, self.world = trainer, trainer.world
        self.state = EngineState(images_per_step=trainer.batch.images)
        config = trainer.config.pipeline.model
        problems = []
        if config.strategy != "default":
            problems.append("--pipeline.model.strategy mcmc (MCMC relocates by sampling the whole scene)")
        if config.camera_optimizer.mode != "off":
            problems.append("--pipeline.model.camera-optimizer.mode (pose gradients would reach one shard only)")
        if problems:
            raise OptionError("geer: --pipeline.model.distributed gaussians does not support " + "; ".join(problems))

    # ------------------------------------------------------------------------------------- start-up
    def start(self) -> None:
        """A fresh start: rank 0's model (the seed cloud), cut into shards here. A resumed run loaded its shard
        alone (trainer._load_checkpoint with shard_checkpoint)."""
        trainer, model = self.trainer, self.trainer.pipeline.model
        if self.world.distributed:
            check_consistent(self.world, fingerprint(trainer))
        model.strategy.budget = scene_budget  # --pipeline.model.max-gaussians is the scene's
        model.strategy.totals = scene_totals  # refinement lines count the scene
        if self.state.scene_gaussians is not None:  # loaded as a shard
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
        self.state.scene_gaussians = total

    def describe(self) -> List[str]:
        model = self.trainer.pipeline.model
        return [f"Gaussians sharded over {self.world.size} process(es): {model.num_points} of "
                f"{self.state.scene_gaussians} here; evaluation images rendered in bands by every process; the "
                "viewer renders a gathered copy"]

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
        params = optimized_parameters(optimizers)
        reduce_gradients(self.world, [p for p in params if id(p) not in own], self.trainer.batch.images)
        reduce_gradients(World(), [p for p in params if id(p) in own], self.trainer.batch.images)

    def reduce_statistics(self, model) -> None:
        model.use_step_statistics(model.step_statistics())  # complete already: every camera's gradient came home

    def step_rows(self, model) -> Tensor:
        """This shard's rows any camera of the step saw: its records hold every camera's (sharded_outputs)."""
        return torch.nonzero(model.step_rows()).squeeze(1)

    def callbacks(self) -> List[TrainingCallback]:
        return [TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._after_step)]

    def _after_step(self, step: int) -> None:
        """After densification: the scene's size, and a rebalance where the shards drifted apart."""
        model = self.trainer.pipeline.model
        sizes = all_gather_counts(model.num_points)
        self.state.scene_gaussians = sum(sizes)
        if max(sizes) > (1.0 + REBALANCE_FRACTION) * max(min(sizes), 1):
            rebalance(self.world, model, self.trainer.optimizers.optimizers, sizes)

    # ------------------------------------------------------------------------- checkpoints, eval
    def write_checkpoint(self, step: int, path) -> bool:
        """This run's checkpoint at `path`, one ordinary file of every shard's rows in rank order, streamed to
        rank 0's file in bounded messages (streamed_checkpoint): nothing is gathered. A collective; True on
        the process that wrote the file (rank 0)."""
        state = resume.trainer_state(self.trainer, step)
        save_rows_streamed(self.world, state, per_gaussian(set(self.trainer.pipeline.model.gauss_params)), path)
        return self.world.is_main

    def evaluate(self, step: int, run: Callable[[], None]) -> None:
        """Rank 0 evaluates (nerfstudio's eval_iteration, on the scaled schedule), every process rendering bands
        of each camera's pixels (collective_renders, split_eval); the viewer's copy of the model is
        gathered to host memory every VIEWER_REFRESH_STEPS steps while a viewer runs."""
        config = self.trainer.config  # the scaled schedule, the one nerfstudio's loop evaluates on
        due = any(step_check(step, n) for n in (config.steps_per_eval_batch, config.steps_per_eval_image,
                                                 config.steps_per_eval_all_images))
        viewer = config.vis.startswith("viewer") and step_check(step, VIEWER_REFRESH_STEPS)
        model = self.trainer.pipeline.model
        if viewer:
            self.state.display_gaussians = None  # the last copy goes before the next is gathered
            gathered = {name: gather_rows(self.world, p.detach(), device=torch.device("cpu"))
                        for name, p in model.gauss_params.items()}
            self.state.display_gaussians = gathered if self.world.is_main else None
        if not due:
            return
        if not self.world.is_main:
            serve_renders(model)
            return
        with collective_renders(model):
            run()


def per_gaussian(groups) -> Callable[[Tuple], bool]:
    """Whether a checkpoint entry (its path of keys) is per Gaussian, by its name: the Gaussian parameters, the
    strategy's per-Gaussian statistics, and their optimizers' moments (`groups`: the Gaussian parameters'
    names). The same answer on every process, whatever the shards' sizes."""
    def test(path: Tuple) -> bool:
        if path[:1] == ("pipeline",) and len(path) > 1:
            if path[1].startswith(PIPELINE_GAUSS_PREFIX):
                return True
            return path[1:3] == ("_model._extra_state", "strategy_state") and path[3:] in (
                (k,) for k in PER_GAUSSIAN_STATE)
        return (path[:1] == ("optimizers",) and len(path) == 5 and path[1] in groups and path[2] == "state"
                and path[4] != "step")
    return test


@contextmanager
def collective_renders(model):
    """On rank 0, while evaluating: each camera the main thread renders is first sent to every process, and
    all render it together, band by band of its pixels from the rows of every shard each band sees
    (split_eval). The viewer's thread renders what it rendered before."""
    original = model.get_outputs

    def get_outputs(camera):
        if threading.current_thread() is not threading.main_thread() or model.training:
            return original(camera)
        broadcast_object(camera.to("cpu"))
        return split_outputs(model, camera)

    model.get_outputs = get_outputs
    try:
        yield
    finally:
        del model.get_outputs
        broadcast_object(None)  # the others stop serving


def serve_renders(model) -> None:
    """Rank > 0 while rank 0 evaluates: its part of each camera rank 0 renders, until it says stop."""
    while True:
        camera = broadcast_object(None)
        if camera is None:
            return
        split_outputs(model, camera.to(model.device))


def sharded_outputs(model, cameras, me: int) -> Dict[str, Tensor]:
    """GeerModel.get_outputs for camera `me` of `cameras` (one per process, this round's), rendered from every
    shard; records the densification view of this shard in every camera. Each camera's rows are made as one
    process makes a render's Gaussians (displaced, activated, colored per view), so that every camera's
    gradient reaches the parameters through its own activations: the sums round as one process's do.

    Everything per camera is over the rows of this shard it sees (found first): their parameters (one gather
    per parameter for all the cameras: its backward adds into one shard-sized gradient, camera by camera),
    the densification probe and record, the displacement. Memory per camera: O(what it sees)."""
    refuse_rolling_shutter(cameras, "--pipeline.model.distributed gaussians")
    views = [model.view_for(camera) for camera in cameras]
    params = model.render_gaussians()
    means = params["means"]
    background = model.render_background().to(means)
    viewmats = torch.stack([model.viewmat(model.render_pose(c), means.device) for c in cameras])
    grids = [v.rays.to(means.device) for v in views]
    rows = [visible_rows(params, viewmats[q], grid, model.config.lambda_mode, model.activated)
            for q, grid in enumerate(grids)]
    record = model.training and torch.is_grad_enabled()
    probes = [probe_rows(model, view, params, viewmats[q], rows[q]) for q, view in enumerate(views)] if record else []
    counts = [int(r.shape[0]) for r in rows]
    every = torch.cat(rows)
    gathered = {name: torch.index_select(p, 0, every).split(counts) for name, p in params.items()}
    parts = [{name: chunks[q] for name, chunks in gathered.items()} for q in range(len(cameras))]
    activated = [model.activated(part) for part in parts]

    def rows_of(q: int, _rows: Tensor):
        part, (s, o) = parts[q], activated[q]
        m = probes[q].displace(part["means"], viewmats[q]) if record else part["means"]
        colors, sh_degree = model.colors(part)
        rgb = colors if colors.ndim == 2 else sh_to_color(colors, camera_offsets(m, viewmats[q]), sh_degree)
        return m, part["quats"], s, o, rgb

    absgrad = record and model.config.use_absgrad
    out, seen = render_sharded(
        means, params["quats"], None, None, viewmats, grids, rows_of, rows=rows,
        background=background, **model.render_options(),
        absgrad_sinks=[p.absgrad for p in probes] if absgrad else None,
        lateral=lateral_basis)
    for q, probe in enumerate(probes):
        model.views.append(probe.record(torch.ones_like(seen.rows[q], dtype=torch.bool), seen.max_weight[q]))
    return model.view_outputs(out, views[me], background, cameras[me])


def probe_rows(model, view, params: Dict[str, Tensor], viewmat: Tensor, rows: Tensor):
    """A camera's densification probe (model.probe) over the `rows` of the shard `params` it sees, made from
    detached copies of their values before the rows are gathered for the render (so that the probe's float64
    temporaries and the gathered rows are not held together)."""
    seen = {name: params[name].detach()[rows] for name in ("means", "scales", "opacities")}
    scales, opacities = model.activated(seen)
    return model.probe(view, seen["means"], viewmat, scales, opacities, rows=rows)


# ----------------------------------------------------------------------------------------- rows
def shard_checkpoint(state: dict, rank: int, processes: int) -> Tuple[dict, int]:
    """A checkpoint (loaded on the CPU, memory-mapped) cut to rank `rank`'s rows before anything reaches the
    model, so that resuming never holds the whole scene on a device; returns it and the scene's size."""
    pipeline = state["pipeline"]
    total = int(pipeline[PIPELINE_GAUSS_PREFIX + "means"].shape[0])
    rows = shard_rows(rank, processes)
    is_rows = per_gaussian({k[len(PIPELINE_GAUSS_PREFIX):] for k in pipeline if k.startswith(PIPELINE_GAUSS_PREFIX)})
    cut = {path: value[rows].clone() for path, value in leaves(state) if isinstance(value, Tensor) and is_rows(path)}
    return replaced(state, cut), total


def scene_budget(wanted: Tensor, over: Tensor, ids: Tensor, n: int, budget: int) -> Tensor:
    """The strategy's budget (densify.strategy.Budget) over every shard: the scene's count against `budget`,
    the candidates of all shards ranked together (strength, then id: what one process holding the scene
    decides). A collective of every process, at refinements only; what travels is the candidates."""
    world = current_world()
    if not world.distributed:
        return local_budget(wanted, over, ids, n, budget)
    scene = sum(all_gather_counts(n))
    mine = torch.nonzero(wanted > 0).squeeze(1)
    every = [all_gather_rows(world, t[mine]) for t in (wanted, over, ids)]
    allowed = strongest_first(*every, room=max(budget - scene, 0))
    return (wanted > 0) & torch.isin(ids, every[2][allowed].to(ids.device))


def scene_totals(entry: Dict[str, int]) -> Dict[str, int]:
    """A refinement's counts (densify.strategy's log entry) summed over the shards; a collective at refinements."""
    every = all_gather_objects(entry)
    keys = dict.fromkeys(key for e in every for key in e)  # a rule that moved nothing here may be absent
    return {key: (entry["step"] if key == "step" else sum(e.get(key, 0) for e in every)) for key in keys}


def _padded(tensor: Tensor) -> Tuple[List[int], Tensor]:
    """(every process's row count, `tensor` on the backend's device padded to the largest: a collective's
    equal shapes). At least one row, so that a collective never moves empty tensors."""
    sizes = all_gather_counts(tensor.shape[0])
    padded = on_backend_device(tensor.new_zeros((max(max(sizes), 1),) + tuple(tensor.shape[1:])))
    padded[: tensor.shape[0]] = tensor.detach()
    return sizes, padded


def all_gather_rows(world: World, tensor: Tensor) -> Tensor:
    """Every shard's rows of `tensor`, in rank order, on every process (padded for the collective)."""
    if not world.distributed:
        return tensor
    sizes, padded = _padded(tensor)
    parts = [torch.empty_like(padded) for _ in sizes]
    dist.all_gather(parts, padded)
    return torch.cat([part[:k] for part, k in zip(parts, sizes)]).to(tensor.device)


def gather_rows(world: World, tensor: Tensor, device: Optional[torch.device] = None) -> Optional[Tensor]:
    """Every shard's rows of `tensor`, in rank order, on rank 0 (None elsewhere; the tensor itself on one
    process), on `device` (default: the tensor's). Uneven shards are padded for the collective and cut back."""
    if not world.distributed:
        return tensor if device is None else tensor.to(device)
    sizes, padded = _padded(tensor)
    parts = [torch.empty_like(padded) for _ in sizes] if world.is_main else None
    dist.gather(padded, parts, dst=0)
    if not world.is_main:
        return None
    return torch.cat([part[:n] for part, n in zip(parts, sizes)]).to(device or tensor.device)


def rebalance(world: World, model, optimizers, sizes: List[int]) -> None:
    """Move rows from the largest shards to the smallest until their sizes differ by at most one: each shard
    gives away its last rows (the newest), received rows are appended in rank order; parameters, their
    optimizer state and the strategy's per-Gaussian state move together."""
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

    update_param_with_optimizer(lambda name, p: torch.nn.Parameter(exchange(p.detach())),
                                 lambda key, v: exchange(v), model.gauss_params, optimizers,
                                 names=list(model.gauss_params.keys()))
    state = model.strategy_state
    for key in PER_GAUSSIAN_STATE:  # by name, the same on every rank: never by a tensor's length
        if isinstance(state.get(key), Tensor):
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
