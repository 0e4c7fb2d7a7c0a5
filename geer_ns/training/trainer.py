"""geer's training step on 1..N processes: nerfstudio's Trainer with the step made of images, and an engine.

A step renders this process's `images_per_step` training images one at a time (each its own backward, so only
one image's graph is alive), reduces the gradients and divides them by the step's images (the effective batch),
adds the regularizers' gradient once, reduces the densification statistics and steps the optimizers;
nerfstudio's callbacks (densification, the SH schedule) run around it as before. How images and Gaussians are
shared out is the engine's (`--pipeline.model.distributed`): image_parallel.ImageParallel (every process holds the
scene, gradients all-reduced) or gaussian_parallel.GaussianParallel (every process a shard, cameras rendered from all
of them). Everything else is nerfstudio's Trainer: rank 0 alone logs, evaluates, writes checkpoints (atomically)
and serves the viewer.

The launch (one process per device, the process group) is nerfstudio's `--machine.*` launcher, made to work
on CPU machines by geer_ns.distributed.launch.
"""

from __future__ import annotations

import functools
import os
import traceback
from dataclasses import dataclass, field
from typing import Dict, Type

import torch
from nerfstudio.configs.base_config import MachineConfig
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils import profiler
from nerfstudio.utils.rich_utils import CONSOLE

from geer_ns import compat, resume
from geer_ns.distributed.gate import GateError, StepGate, registered_store
from geer_ns.distributed.launch import install_launch_router
from geer_ns.distributed.consistency import ReplicaMismatchError
from geer_ns.distributed.engine import Engine
from geer_ns.distributed.image_parallel import ImageParallel
from geer_ns.distributed.schedule import (
    EffectiveBatch,
    apply_optimizer_hyperparameters,
    describe,
    optimizer_hyperparameters,
    scaled_config,
)
from geer_ns.distributed.gaussian_parallel import GaussianParallel, shard_checkpoint
from geer_ns.distributed.world import current_world
from geer_ns.errors import report_input_errors_in_one_line
from geer_ns.optim.selective_adam import offer_rows
from geer_ns.refinement import registration
from geer_ns.refinement.refined_cameras import write_refined_cameras
from geer_ns.training.horizon import REFERENCE_STEPS, Schedules, follow_run
from geer_ns.sh_degrees.packing import unpacked_checkpoint


@dataclass
class GeerMachineConfig(MachineConfig):
    timeout_s: float = 600.0
    """Seconds a process waits for a late one that is training (at each step's start, and in each collective)
    before it stops with one line naming it. A process paused in the viewer, evaluating or saving is waited for
    without limit; one that died is noticed within min(this, 120) s (distributed/gate.py)."""
    check_replicas_every: int = 0
    """Every this many steps, compare the replicas' parameter checksums over the processes and stop if they
    differ (0: never; the replicas are identical by construction)."""


def install_run_fixes() -> None:
    """What a geer training run changes in its process, and only a geer run: the host fixes (geer_ns.compat),
    DatasetError and OptionError in one line (errors.py), nerfstudio's launcher routed for geer configs (launch.py)."""
    compat.install()
    report_input_errors_in_one_line()
    install_launch_router()


@dataclass
class GeerTrainerConfig(TrainerConfig):
    _target: Type = field(default_factory=lambda: GeerTrainer)
    schedules: Schedules = "follow-run"
    """follow-run: every step-valued schedule (learning rates, densification, opacity reset, SH degree,
    resolution, lens and pose refinement) is stretched from the run length it is written for
    (--schedules-written-for) to --max-num-iterations, splatfacto's shape at any length
    (geer_ns/training/horizon.py); fixed: the step counts as written."""
    schedules_written_for: int = REFERENCE_STEPS
    """The run length the step-valued options are written for (splatfacto's: 30000 steps). A run's saved config
    holds its stretched schedules and its own length here."""

    def set_timestamp(self) -> None:
        """nerfstudio's `ns-train` main calls this first, before it saves the config and launches the run's
        processes: the one point where a method's own code runs ahead of the launch, so geer's run fixes are
        installed here, and the schedules stretched to the run (so that config.yml, which ns-eval and the viewer
        read, holds the schedules the run used)."""
        install_run_fixes()
        follow_run(self, resume.images_seen(self))
        registration.apply(self)
        super().set_timestamp()


class GeerTrainer(Trainer):
    config: GeerTrainerConfig
    gate = None  # StepGate: the processes meet at each step's start (gate.py); None in one process

    def __init__(self, config: GeerTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        install_run_fixes()  # also for trainers built without ns-train's main (scripts, tests, spawned processes)
        self.world = current_world()
        images = config.pipeline.datamanager.images_per_step
        if images < 1:
            raise ValueError(f"geer: --pipeline.datamanager.images-per-step must be >= 1, got {images}")
        self.batch = EffectiveBatch(self.world.size, images)
        # a no-op where ns-train's set_timestamp stretched them already
        self.schedule_said = follow_run(config, resume.images_seen(config))
        self.registration_said = registration.apply(config)
        self.user_config = config
        config = scaled_config(config, self.batch)
        if not self.world.is_main:  # rank 0 alone speaks, and serves the viewer (the writers are rank 0's already)
            CONSOLE.quiet = True
            if config.vis.startswith("viewer"):
                config.vis = "tensorboard"
        super().__init__(config, local_rank, world_size)

    # ------------------------------------------------------------------------------------- set-up
    def setup(self, test_mode="val") -> None:
        try:
            self._setup(test_mode)
        except Exception as error:  # noqa: BLE001 - said once, then the process ends
            if not self.world.distributed:
                raise
            self._stop(error)

    def _setup(self, test_mode) -> None:
        engines = {"images": ImageParallel, "gaussians": GaussianParallel}
        self.engine: Engine = engines[self.config.pipeline.model.distributed](self)
        super().setup(test_mode)  # pipeline, optimizers, viewer, checkpoint (the model attaches the engine there)
        if not self.world.is_main:
            self.pipeline.model.strategy.verbose = False  # rank 0 says what densification did
        self.engine.start()
        self.callbacks.extend(self.engine.callbacks())  # after the model's own: densification included
        self._forget_replaced_parameters()
        self.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                                               self._forget_replaced_parameters))
        store = registered_store()
        if self.world.distributed and store is not None:
            self.gate = StepGate(store, self.world.rank, self.world.size, self.config.machine.timeout_s)
            self.gate.set_state(self.training_state)
        elif self.world.distributed and self.world.is_main:  # say it: pauses and long evaluations then time out
            CONSOLE.log(f"geer: no step gate (--machine.dist-url {self.config.machine.dist_url} is not "
                        "tcp://host:port): a process paused in the viewer, evaluating or saving past "
                        "--machine.timeout-s stops the run")
        self._say_start()

    def _say_start(self) -> None:
        if not self.world.is_main:
            return
        for line in (self.schedule_said, self.registration_said, *self.engine.describe()):
            if line:
                CONSOLE.log(f"geer: {line}")
        if self.batch.images == 1:
            return
        how = f"{self.world.size} process(es) ({self.world.backend}"
        if self.device.startswith("cpu"):
            how += f", {torch.get_num_threads()} CPU thread(s) each"
        CONSOLE.log(f"geer: training on {how}), {self.batch.images_per_process} image(s) per process per step: "
                    f"an effective batch of {self.batch.images} images")
        for line in describe(self.config, self.user_config, self.batch):
            CONSOLE.log(f"geer: {line}")

    def _load_checkpoint(self) -> None:
        """First the model attaches the engine's state (nerfstudio's setup calls this right after it built the
        pipeline, optimizers and viewer), so that its strategy and a checkpoint's steps are in this run's batch.
        Then nerfstudio's load (the checkpoint named by --load-dir / --load-step or --load-checkpoint),
        memory-mapped, cut to this process's shard first when the Gaussians are sharded; steps converted to this
        run's effective batch, and this run's optimizer hyper-parameters (its kappa's) put back over the saved."""
        self.pipeline.model.attach(self.engine.state)
        path = self._checkpoint_path()
        if path is None:
            CONSOLE.print("No Nerfstudio checkpoint to load, so training from scratch.")
            return
        state = unpacked_checkpoint(torch.load(path, map_location="cpu", mmap=True),
                                    self.pipeline.model.gauss_params["features_rest"].shape[1])
        if self.config.pipeline.model.distributed == "gaussians":
            state, total = shard_checkpoint(state, self.world.rank, self.world.size)
        self._start_step = state["step"] + 1
        self.pipeline.load_pipeline(state["pipeline"], state["step"])
        fresh = optimizer_hyperparameters(self.optimizers)
        self.optimizers.load_optimizers(state["optimizers"])
        schedulers = "schedulers" in state and self.config.load_scheduler
        if schedulers:
            self.optimizers.load_schedulers(state["schedulers"])
        self.grad_scaler.load_state_dict(state["scalers"])
        rng = resume.checkpoint_rng_state(state)
        if rng is not None:
            resume.restore_rng_state(rng)
        if self.config.pipeline.model.distributed == "gaussians":
            self.engine.state.scene_gaussians = total
        CONSOLE.print(f"Done loading Nerfstudio checkpoint from {path}")
        self._convert_steps(fresh, schedulers, resume.checkpoint_images_per_step(state))

    def _checkpoint_path(self):
        return resume.checkpoint_path(self.config)

    def _convert_steps(self, fresh, schedulers: bool, saved: int) -> None:
        """The loaded state in this run's effective batch: the step, Adam's step counts and the schedulers'
        positions converted (the images seen carry over), and this run's learning rates, betas, epsilon and
        the schedulers' base learning rates (the batch rule's, geer_ns/distributed/schedule.py) in place of
        the checkpoint's (`saved`: its images per step), so that a resume equals a fresh run at this kappa."""
        now = self.batch.images
        apply_optimizer_hyperparameters(self.optimizers, fresh, saved, now, schedulers)
        if self._start_step == 0 or saved == now:
            return
        start = resume.convert_step(self._start_step - 1, saved, now) + 1
        CONSOLE.log(f"geer: the checkpoint's steps saw {saved} image(s) each, this run's see {now}: step "
                    f"{self._start_step} there is step {start} here (the images seen carry over; learning rates, "
                    f"betas and epsilon are this run's)")
        self._start_step = start

    def _forget_replaced_parameters(self, step: int = 0) -> None:
        """nerfstudio's Optimizers keeps the parameter lists it was built with (`parameters`, for clip_grad_norm);
        densification and the shard cut replace the Parameters, so those lists would keep the replaced tensors
        alive (a whole seed model on every process) and clip stale gradients. Point them at what is stepped."""
        for name, optimizer in self.optimizers.optimizers.items():
            self.optimizers.parameters[name] = [p for group in optimizer.param_groups for p in group["params"]]

    # --------------------------------------------------------------------------------- the step
    @property
    def training_state(self) -> str:
        return self._training_state

    @training_state.setter
    def training_state(self, state: str) -> None:
        """nerfstudio's state ("training", "paused" by the viewer, "completed"), told to the other processes'
        gate so that they wait for a paused rank 0 without limit."""
        self._training_state = state
        if self.gate is not None and state in ("training", "paused"):
            try:
                self.gate.set_state(state)
            except Exception:  # noqa: BLE001 - the viewer's thread must survive; the training loop will say why
                pass

    @profiler.time_function
    def train_iteration(self, step: int):
        if self.gate is not None:
            self.gate.wait(step)
        accumulate = self.gradient_accumulation_steps
        self.optimizers.zero_grad_some([g for g in self.optimizers.parameters if step % accumulate[g] == 0])
        device_type = "cpu" if self.device.split(":")[0] in ("cpu", "mps") else self.device.split(":")[0]
        model = self.pipeline.model
        image_losses: Dict[str, torch.Tensor] = {}
        metrics: Dict[str, torch.Tensor] = {}
        per = self.batch.images_per_process
        for batch, forward in self.engine.views(step):
            with torch.autocast(device_type=device_type, enabled=self.mixed_precision):
                outputs = forward()
                for k, v in model.get_metrics_dict(outputs, batch).items():
                    metrics[k] = metrics.get(k, 0) + (v.detach() if torch.is_tensor(v) else v) / per
                losses = model.get_image_loss_dict(outputs, batch)
                loss = functools.reduce(torch.add, losses.values())
            self.grad_scaler.scale(loss).backward()
            for k, v in losses.items():
                image_losses[k] = image_losses.get(k, 0) + v.detach() / per
            del outputs, loss, losses
        self.engine.reduce_gradients()
        with torch.autocast(device_type=device_type, enabled=self.mixed_precision):
            step_losses = model.get_step_loss_dict()
        step_loss = functools.reduce(torch.add, step_losses.values())
        if step_loss.requires_grad:
            self.grad_scaler.scale(step_loss).backward()
        if model.needs_step_statistics:
            self.engine.reduce_statistics(model)
        if model.config.optimizer_rows == "visible":  # Adam steps the Gaussians the step's views saw
            offer_rows(self.optimizers.optimizers, lambda: self.engine.step_rows(model))
        self.optimizers.optimizer_scaler_step_some(
            self.grad_scaler, [g for g in self.optimizers.parameters if step % accumulate[g] == accumulate[g] - 1])
        if self.config.log_gradients:
            for tag, value in model.named_parameters():
                if value.grad is not None:
                    metrics[f"Gradients/{tag}"] = value.grad.norm()
        scale = self.grad_scaler.get_scale()
        self.grad_scaler.update()
        if scale <= self.grad_scaler.get_scale():  # no step was skipped: the schedules move on
            self.optimizers.scheduler_step_all(step)
        loss_dict = {**image_losses, **{k: v.detach() for k, v in step_losses.items()}}
        return functools.reduce(torch.add, loss_dict.values()), loss_dict, metrics

    def train(self) -> None:
        try:
            super().train()
        except Exception as error:  # noqa: BLE001 - said once, then the process ends
            if not self.world.distributed:
                raise
            self._stop(error)
        finally:
            if self.gate is not None:
                self.gate.close()

    def _stop(self, error: BaseException) -> None:
        """One line naming this rank and the cause, then exit status 1 (the launcher stops the others)."""
        lost = _communication_failure(error)
        if lost is None and not isinstance(error, (ReplicaMismatchError, GateError)):
            traceback.print_exc()
        if isinstance(error, GateError):
            what = str(error)
        elif lost is not None:
            what = (f"lost the other processes ({lost}: one died, hung past --machine.timeout-s or was "
                    "unreachable; the first to fail says why)")
        else:
            cause = str(error).strip().splitlines()[0] if str(error).strip() else ""
            what = f"failed: {type(error).__name__}: {cause}"
        print(f"geer: rank {self.world.rank} of {self.world.size} stopped at step {self.step}: {what}", flush=True)
        raise SystemExit(1)

    def eval_iteration(self, step: int) -> None:
        """On rank 0 (image-parallel: its replica; Gaussian-parallel: the gathered model, every rank helping)."""
        if self.gate is not None:
            self.gate.set_state("evaluating")  # the others wait for it at the next step's gate, without limit
        self.engine.evaluate(step, lambda: Trainer.eval_iteration(self, step))

    def save_checkpoint(self, step: int) -> None:
        """nerfstudio's checkpoint (of the whole model: a sharded one streamed to rank 0's file, every rank
        helping, nothing gathered), written by rank 0 whole or not at all (a temporary file renamed into place)."""
        path = self.checkpoint_dir / f"step-{step:09d}.ckpt"
        partial = self.base_dir / f".{path.name}.partial"  # not in the folder --load-dir lists
        if self.gate is not None:
            self.gate.set_state("saving")
        if self.world.is_main:
            self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        if not self.engine.write_checkpoint(step, partial):
            return
        os.replace(partial, path)
        if self.world.is_main:  # the refined cameras beside it (geer_ns/refinement/refined_cameras.py; refinement runs only)
            write_refined_cameras(self.pipeline, self.base_dir)
        if self.config.save_only_latest_checkpoint:
            for old in self.checkpoint_dir.glob("*.ckpt"):
                if old != path:
                    old.unlink()


_LOST = ("Connection closed by peer", "Connection reset by peer", "Broken pipe", "Timed out", "timed out",
         "Socket Timeout", "NCCL communicator was aborted", "NCCL error")


def _communication_failure(error: BaseException):
    """The short cause when a collective failed because another process went away or timed out, else None."""
    text = str(error)
    for marker in _LOST:
        if marker in text:
            return f"{dist_backend_name()}: {marker.lower()}"
    if isinstance(error, getattr(torch.distributed, "DistError", ())):
        return f"{dist_backend_name()}: {text.strip().splitlines()[0][:120] if text.strip() else type(error).__name__}"
    return None


def dist_backend_name() -> str:
    return str(torch.distributed.get_backend()) if torch.distributed.is_initialized() else "torch.distributed"
