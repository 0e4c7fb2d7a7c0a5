"""Image-parallel training: every process holds the whole model (a replica); they stay identical.

At start-up rank 0's parameters, buffers and random-number states are broadcast (the replicas then draw the
same random numbers: backgrounds, split samples, MCMC relocation) after a check that every process read the
same dataset and configuration. Each step, after every process's backward over its own images:

* one all-reduce of every parameter's gradient, in buckets (world.all_reduce_), then the mean over the
  step's images (the effective batch);
* one all-reduce of the densification statistics (sum, sum, max: densify.signal.StepStatistics), so that
  every replica makes the same split / duplicate / prune / reset decisions.

Nothing else is exchanged: the optimisers step identical replicas with identical gradients.
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import PurePath
from typing import Dict, List, Optional, Sequence

import torch
from torch import Tensor

from geer_ns import resume
from geer_ns.densify.signal import StepStatistics
from geer_ns.distributed.world import World, all_gather_objects, all_reduce_, broadcast_, broadcast_object


class ReplicaMismatchError(RuntimeError):
    """A process read another dataset or configuration than rank 0, or its replica drifted: said on every rank."""


def optimised_parameters(optimizers) -> List[torch.nn.Parameter]:
    """Every parameter the optimisers step, in one order on every process (nerfstudio's group order).
    Read from the optimisers, not the model: densification replaces the Parameter objects in both."""
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
def _digest(values) -> str:
    h = hashlib.sha256()
    for v in values:
        if isinstance(v, Tensor):
            h.update(v.detach().cpu().contiguous().numpy().tobytes())
        else:
            h.update(repr(v).encode())
    return h.hexdigest()[:16]


def _flat_config(obj, prefix: str = "") -> Dict[str, str]:
    """Config fields as 'a.b.c' -> repr, without paths (a dataset may sit elsewhere on every machine)."""
    out: Dict[str, str] = {}
    if dataclasses.is_dataclass(obj):
        items = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}.items()
    elif isinstance(obj, dict):
        items = obj.items()
    else:
        return {prefix: repr(obj)} if not isinstance(obj, PurePath) else {}
    for name, value in items:
        key = f"{prefix}.{name}" if prefix else str(name)
        if name == "_target":
            out[key] = repr(getattr(value, "__qualname__", value))
        elif isinstance(value, PurePath) or name in ("data", "output_dir"):
            continue
        else:
            out.update(_flat_config(value, key))
    return out


def fingerprint(trainer) -> Dict[str, str]:
    """What every process must agree on, each entry short enough to print."""
    dm, model = trainer.pipeline.datamanager, trainer.pipeline.model
    cams = dm.train_dataset.cameras
    found = {
        "train images": f"{len(dm.train_dataset)} ({_digest([str(PurePath(f).name) for f in dm.train_dataset.image_filenames])})",
        "train cameras": _digest([cams.camera_to_worlds, cams.fx, cams.fy, cams.cx, cams.cy, cams.width, cams.height,
                                  cams.camera_type, cams.distortion_params if cams.distortion_params is not None else 0]),
        "eval images": f"{len(dm.eval_dataset)} ({_digest([str(PurePath(f).name) for f in dm.eval_dataset.image_filenames])})",
        "Gaussians": str(model.scene_gaussians or model.num_points),  # a shard's: the scene's
        "start step": str(trainer._start_step),
    }
    if trainer._start_step > 0 and model.scene_gaussians is None:  # resumed replicas must already agree
        found["loaded parameters"] = _digest(list(model.gauss_params.values()))
    config = getattr(trainer, "user_config", trainer.config)  # the values as given (before the batch rule)
    found.update({f"config {k}": v for k, v in _flat_config(config.pipeline, "pipeline").items()})
    found.update({f"config {k}": v for k, v in _flat_config(config.optimizers, "optimizers").items()})
    found["config max_num_iterations"] = str(config.max_num_iterations)
    return found


def check_consistent(world: World, mine: Dict[str, str]) -> None:
    """Raise ReplicaMismatchError on every rank when any rank's fingerprint differs from rank 0's."""
    every = all_gather_objects(mine)
    problems = []
    for rank, theirs in enumerate(every[1:], start=1):
        for key in sorted(set(every[0]) | set(theirs)):
            if every[0].get(key) != theirs.get(key):
                problems.append(f"rank {rank} has {key} = {theirs.get(key)!s:.80} where rank 0 has "
                                f"{every[0].get(key)!s:.80}")
    if problems:
        more = f" (+{len(problems) - 3} more)" if len(problems) > 3 else ""
        raise ReplicaMismatchError("geer: the processes of this run disagree: " + "; ".join(problems[:3]) + more +
                                   ". Every process must read the same dataset with the same configuration.")


def broadcast_replica(world: World, model, optimizers) -> None:
    """Rank 0's model state (parameters, buffers), optimiser state and random-number states on every rank."""
    if not world.distributed:
        return
    broadcast_([t for t in model.state_dict().values() if isinstance(t, Tensor)])
    for opt in optimizers.optimizers.values():
        for state in opt.state.values():
            broadcast_([v for v in state.values() if isinstance(v, Tensor) and v.ndim > 0])
    resume.restore_rng_state(broadcast_object(resume.rng_state()))
    resume.restore_strategy_state(model.strategy_state, broadcast_object(resume.strategy_state(model.strategy_state)),
                                  model.device)


def replica_checksum(model) -> str:
    """An exact digest of the model's parameters (for replicas that must be bit for bit the same)."""
    return _digest(list(model.gauss_params.values()))


def check_replicas_identical(world: World, model, step: int) -> List[str]:
    """Every rank's checksum; raises ReplicaMismatchError when they differ."""
    sums = all_gather_objects(replica_checksum(model))
    if len(set(sums)) > 1:
        raise ReplicaMismatchError(f"geer: the replicas differ after step {step}: parameter checksums {sums} "
                                   "(a non-deterministic reduction or a process that skipped an update)")
    return sums


class ImageParallel:
    """The engine of image-parallel training (module docstring), for geer_ns.distributed.trainer."""

    name = "images"

    def __init__(self, trainer) -> None:
        self.trainer, self.world = trainer, trainer.world

    def start(self) -> None:
        if self.world.distributed:
            check_consistent(self.world, fingerprint(self.trainer))
            broadcast_replica(self.world, self.trainer.pipeline.model, self.trainer.optimizers)

    def describe(self) -> List[str]:
        return []

    def views(self, step: int):
        """This process's images of the step: its share of the next effective batch of the shared queue."""
        dm, model = self.trainer.pipeline.datamanager, self.trainer.pipeline.model
        per = self.trainer.batch.images_per_process
        indices = dm.next_train_indices(self.trainer.batch.images)
        for index in indices[self.world.rank * per : (self.world.rank + 1) * per]:
            camera, batch = dm.train_view(index)
            yield batch, (lambda camera=camera: model.get_outputs(camera))

    def reduce_gradients(self) -> None:
        reduce_gradients(self.world, optimised_parameters(self.trainer.optimizers), self.trainer.batch.images)

    def reduce_statistics(self, model) -> None:
        model.use_step_statistics(reduce_statistics(self.world, model.step_statistics()))

    def callbacks(self):
        from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

        every = getattr(self.trainer.config.machine, "check_replicas_every", 0)
        if not (every and self.world.distributed):
            return []
        return [TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                                 lambda step: check_replicas_identical(self.world, self.trainer.pipeline.model, step),
                                 update_every_num_iters=every)]

    def checkpoint_state(self, step: int) -> Optional[dict]:
        """Rank 0's replica, as nerfstudio saves it (None elsewhere)."""
        trainer = self.trainer
        if not self.world.is_main:
            return None
        return {"step": step, "pipeline": trainer.pipeline.state_dict(),
                "optimizers": {k: v.state_dict() for k, v in trainer.optimizers.optimizers.items()},
                "schedulers": {k: v.state_dict() for k, v in trainer.optimizers.schedulers.items()},
                "scalers": trainer.grad_scaler.state_dict()}

    def evaluate(self, step: int, run) -> None:
        if self.world.is_main:
            run()
