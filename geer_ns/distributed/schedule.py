"""The effective batch: N processes x B images per step, and what it does to the schedule.

Rule (applied by default, said once at start-up): a step of kappa = N x B images replaces kappa steps of one.

* Step counts count images. Every step-valued option (--max-num-iterations, the densification schedule, the
  SH degree and resolution schedules, the learning-rate schedules, saving and evaluation) is divided by kappa,
  so a run with kappa = 4 reaches the same point of its schedule in a quarter of the steps; refinements see
  the same number of images' statistics as with kappa = 1.
* Adam follows the square-root scaling rule (Malladi et al. 2022, "On the SDEs and Scaling Rules for Adaptive
  Gradient Algorithms", the rule gsplat's trainer uses for its batch size): learning rate x sqrt(kappa),
  epsilon / sqrt(kappa), beta_i ** kappa. The gradient of a kappa-image step is the mean over its images, whose
  noise is 1/sqrt(kappa) of one image's; the rule keeps the optimizer's trajectory (its SDE) the same.
* beta ** kappa, not Malladi et al.'s 1 - kappa (1 - beta): both agree to first order in (1 - beta), but a moving
  average that decays by beta per image decays by exactly beta ** kappa over a step of kappa images, so the
  averages' memory, measured in images, is the same at every kappa (and Adam's bias correction 1 - beta ** t
  is the same function of the images seen); the linear rule reaches 0 at kappa = 1 / (1 - beta) (beta_1 = 0.9:
  kappa = 10, 8 GPUs x 2 images) and then forgets the moment altogether. docs/distributed.md has the numbers.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Dict, List, Tuple

import torch

from nerfstudio.engine.optimizers import AdamOptimizerConfig

from geer_ns import resume
from geer_ns.optim.selective_adam import SelectiveAdamOptimizerConfig

# Step-valued options of the model config (splatfacto's, which geer keeps). reset_alpha_every counts
# refinements, so it scales through refine_every.
MODEL_STEP_FIELDS = ("warmup_length", "refine_every", "stop_split_at", "stop_screen_size_at",
                     "sh_degree_interval", "resolution_schedule")
TRAINER_STEP_FIELDS = ("max_num_iterations", "steps_per_save", "steps_per_eval_batch", "steps_per_eval_image",
                       "steps_per_eval_all_images")


@dataclass
class AdamBetasOptimizerConfig(AdamOptimizerConfig):
    """nerfstudio's Adam config with its betas, which the scaling rule changes."""

    betas: Tuple[float, float] = (0.9, 0.999)


@dataclass(frozen=True)
class EffectiveBatch:
    processes: int = 1
    images_per_process: int = 1

    @property
    def images(self) -> int:
        return self.processes * self.images_per_process

    def steps(self, images: int) -> int:
        """A count of images as a count of steps (0 stays 0: "never"; anything else at least 1)."""
        if images <= 0 or self.images == 1:
            return images
        return max(1, round(images / self.images))

    def adam(self, lr: float, eps: float, betas: Tuple[float, float] = (0.9, 0.999)) -> Tuple[float, float, Tuple[float, float]]:
        k = self.images
        scaled_betas = tuple(b**k for b in betas)
        return lr * math.sqrt(k), eps / math.sqrt(k), scaled_betas  # type: ignore[return-value]


def scaled_config(config, batch: EffectiveBatch):
    """A copy of the TrainerConfig `config` with its schedule in steps of `batch.images` images (the rule above).
    The batch itself is the engine's (engine.EngineState.images_per_step), which checkpoints keep."""
    config = copy.deepcopy(config)
    model = config.pipeline.model
    if batch.images == 1:
        return config
    for name in TRAINER_STEP_FIELDS:
        setattr(config, name, batch.steps(getattr(config, name)))
    for name in MODEL_STEP_FIELDS:
        if hasattr(model, name):
            setattr(model, name, batch.steps(getattr(model, name)))
    for group, entry in config.optimizers.items():
        optimizer, scheduler = entry["optimizer"], entry.get("scheduler")
        if type(optimizer) in (AdamOptimizerConfig, AdamBetasOptimizerConfig, SelectiveAdamOptimizerConfig):
            lr, eps, betas = batch.adam(optimizer.lr, optimizer.eps, getattr(optimizer, "betas", (0.9, 0.999)))
            if type(optimizer) is SelectiveAdamOptimizerConfig:  # the Gaussian groups' (config.py)
                entry["optimizer"] = dataclasses.replace(optimizer, lr=lr, eps=eps, betas=betas)
            else:
                entry["optimizer"] = AdamBetasOptimizerConfig(lr=lr, eps=eps, betas=betas, max_norm=optimizer.max_norm,
                                                              weight_decay=optimizer.weight_decay)
            if scheduler is not None:
                root = math.sqrt(batch.images)
                for name in ("lr_final", "lr_pre_warmup"):
                    if getattr(scheduler, name, None) is not None:
                        setattr(scheduler, name, getattr(scheduler, name) * root)
        if scheduler is not None:
            for name in ("max_steps", "warmup_steps"):
                if hasattr(scheduler, name):
                    setattr(scheduler, name, batch.steps(getattr(scheduler, name)))
    return config


def describe(config, original, batch: EffectiveBatch) -> List[str]:
    """What the rule did, for the start-up lines."""
    if batch.images == 1:
        return []
    lr, eps, betas = batch.adam(1.0, 1.0)
    model, was = config.pipeline.model, original.pipeline.model
    return [
        f"step counts are images / {batch.images}: --max-num-iterations {original.max_num_iterations} -> "
        f"{config.max_num_iterations} steps, refine every {was.refine_every} -> {model.refine_every}, "
        f"splits until {was.stop_split_at} -> {model.stop_split_at}, SH degree every {was.sh_degree_interval} -> "
        f"{model.sh_degree_interval}",
        f"Adam (square-root rule): learning rates x{lr:.3g}, epsilon x{eps:.3g}, betas "
        f"({betas[0]:.3g}, {betas[1]:.4g})",
    ]


# ------------------------------------------------------------------------------------------- resume
HYPERPARAMETERS = ("lr", "initial_lr", "betas", "eps", "weight_decay")


def optimizer_hyperparameters(optimizers) -> Dict[str, Any]:
    """This run's optimizer hyper-parameters (nerfstudio's Optimizers: each group's param_groups and its
    scheduler's base learning rates), taken before a checkpoint's state replaces them."""
    return {
        "groups": {name: [{k: group[k] for k in HYPERPARAMETERS if k in group} for group in opt.param_groups]
                   for name, opt in optimizers.optimizers.items()},
        "base_lrs": {name: list(s.base_lrs) for name, s in optimizers.schedulers.items()},
    }


def apply_optimizer_hyperparameters(optimizers, fresh: Dict[str, Any], saved_images: int, images: int,
                                    schedulers_loaded: bool) -> None:
    """After Optimizer/LRScheduler.load_state_dict (which restore the saved run's learning rates, betas,
    epsilon and base_lrs): this run's `fresh` ones back; Adam's step counts and the loaded schedulers'
    positions converted from steps of `saved_images` images to steps of `images`; each scheduled learning
    rate set to its schedule's value there. The result equals a fresh run of this batch at the same point."""
    for name, opt in optimizers.optimizers.items():
        for group, values in zip(opt.param_groups, fresh["groups"].get(name, [])):
            group.update(values)
        if saved_images != images:
            for slot in opt.state.values():
                step = slot.get("step")
                if step is not None:  # Adam's bias correction 1 - beta ** t: t counts this run's steps
                    converted = round(float(step) * saved_images / images)
                    slot["step"] = torch.full_like(step, converted) if torch.is_tensor(step) else converted
    for name, scheduler in optimizers.schedulers.items():
        scheduler.base_lrs = list(fresh["base_lrs"][name])
        if schedulers_loaded:  # last_epoch counts the steps taken (else the schedule restarts: fresh already)
            scheduler.last_epoch = resume.convert_step(scheduler.last_epoch - 1, saved_images, images)
            scheduler.step()
