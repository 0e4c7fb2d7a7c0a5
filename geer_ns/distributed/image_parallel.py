"""Image-parallel training: every process holds the whole model (a replica); they stay identical.

At start-up rank 0's parameters, buffers and random-number states are broadcast (the replicas then draw the
same random numbers: backgrounds, split samples, MCMC relocation) after a check that every process read the
same dataset and configuration. Each step, after every process's backward over its own images, the gradients and the densification statistics
are all-reduced (reductions.py), so every replica makes the same densification decisions.

Nothing else is exchanged: the optimizers step identical replicas with identical gradients.
"""

from __future__ import annotations

from pathlib import Path
from typing import List

import torch

from geer_ns import resume
from geer_ns.distributed.consistency import (
    broadcast_replica,
    check_consistent,
    check_replicas_identical,
    fingerprint,
)
from geer_ns.distributed.engine import EngineState
from geer_ns.distributed.reductions import optimized_parameters, reduce_gradients, reduce_statistics
from geer_ns.distributed.world import all_reduce_
from geer_ns.errors import OptionError


class ImageParallel:
    """The engine of image-parallel training (module docstring), for geer_ns.training.trainer."""

    name = "images"

    def __init__(self, trainer) -> None:
        """Before the trainer builds its pipeline (the model attaches `state` then)."""
        self.trainer, self.world = trainer, trainer.world
        self.state = EngineState(images_per_step=trainer.batch.images)
        if self.world.distributed and trainer.config.pipeline.model.pose_solve_every > 0:
            raise OptionError("geer: --pipeline.model.pose-solve-every runs in one process only (each process would "
                              "solve every camera); leave it at 0 with --machine.num-devices > 1")

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
        reduce_gradients(self.world, optimized_parameters(self.trainer.optimizers), self.trainer.batch.images)

    def reduce_statistics(self, model) -> None:
        model.use_step_statistics(reduce_statistics(self.world, model.step_statistics()))

    def step_rows(self, model):
        """Every replica's views' rows: the same rows step on every replica."""
        seen = model.step_rows().to(torch.uint8)
        if self.world.distributed:
            all_reduce_([seen], op="max")
        return torch.nonzero(seen).squeeze(1)

    def callbacks(self):
        from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

        every = getattr(self.trainer.config.machine, "check_replicas_every", 0)
        if not (every and self.world.distributed):
            return []
        return [TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                                 lambda step: check_replicas_identical(self.world, self.trainer.pipeline.model, step),
                                 update_every_num_iters=every)]

    def write_checkpoint(self, step: int, path: Path) -> bool:
        """Rank 0's replica at `path`, as nerfstudio saves it, with the RNG states; True on rank 0 (which wrote)."""
        if not self.world.is_main:
            return False
        torch.save(resume.trainer_state(self.trainer, step), path)
        return True

    def evaluate(self, step: int, run) -> None:
        if self.world.is_main:
            run()
