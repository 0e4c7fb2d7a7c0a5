"""nerfstudio method configs: `geer` (DefaultStrategy densification) and `geer-mcmc` (MCMCStrategy).

Registered through the `nerfstudio.method_configs` entry points in pyproject.toml. Schedules and
learning rates are splatfacto's (nerfstudio 1.1.5), so results compare one to one.
"""

from __future__ import annotations

import torch
from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.plugins.types import MethodSpecification

from geer_ns.data.datamanager import GeerDataManagerConfig
from geer_ns.training.trainer import GeerMachineConfig, GeerTrainerConfig
from geer_ns.model import GeerModelConfig
from geer_ns.optim.selective_adam import SelectiveAdamOptimizerConfig
from geer_ns.options import OWN_OPTIONS_HELP
from geer_ns.pipeline import GeerPipelineConfig

MAX_STEPS = 30000


def _adam(lr: float, scheduler=None) -> dict:
    return {"optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15), "scheduler": scheduler}


def _gaussian_adam(lr: float, scheduler=None) -> dict:
    """A Gaussian parameter group's Adam: torch's, stepping only the rows a step's views see when the model offers
    them (--pipeline.model.optimizer-rows, geer_ns/optim/selective_adam.py)."""
    return {"optimizer": SelectiveAdamOptimizerConfig(lr=lr, eps=1e-15), "scheduler": scheduler}


def splatfacto_optimizers(max_steps: int = MAX_STEPS) -> dict:
    """splatfacto's per-parameter optimizers (nerfstudio 1.1.5 method_configs), and geer's appearance model's."""
    warm = dict(warmup_steps=1000, lr_pre_warmup=0)
    return {
        "means": _gaussian_adam(1.6e-4, ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=max_steps)),
        "features_dc": _gaussian_adam(0.0025),
        "features_rest": _gaussian_adam(0.0025 / 20),
        "opacities": _gaussian_adam(0.05),
        "scales": _gaussian_adam(0.005),
        "quats": _gaussian_adam(0.001),
        "camera_opt": _adam(1e-4, ExponentialDecaySchedulerConfig(lr_final=5e-7, max_steps=max_steps, **warm)),
        "bilateral_grid": _adam(2e-3, ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=max_steps, **warm)),
        # geer's appearance model (--pipeline.model.appearance exposure; docs/refinement.md)
        "appearance": _adam(5e-3, ExponentialDecaySchedulerConfig(lr_final=5e-4, max_steps=max_steps, **warm)),
        # geer's lens refinement (--pipeline.model.lens-refinement; docs/refinement.md): relative deltas
        "lens_opt": _adam(5e-4, ExponentialDecaySchedulerConfig(lr_final=1e-5, max_steps=max_steps, **warm)),
        # geer's rolling-shutter motion refinement (--pipeline.model.readout-refinement; docs/rolling_shutter.md)
        "readout_opt": _adam(1e-3, ExponentialDecaySchedulerConfig(lr_final=1e-5, max_steps=max_steps, **warm)),
    }


def geer_trainer_config(method_name: str, model: GeerModelConfig) -> GeerTrainerConfig:
    return GeerTrainerConfig(
        method_name=method_name,
        steps_per_eval_image=100,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=1000,
        max_num_iterations=MAX_STEPS,
        mixed_precision=False,
        pipeline=GeerPipelineConfig(datamanager=GeerDataManagerConfig(), model=model),
        optimizers=splatfacto_optimizers(),
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
        # nerfstudio defaults to "cuda" even where there is none; geer runs on either.
        machine=GeerMachineConfig(device_type="cuda" if torch.cuda.is_available() else "cpu"),
    )


geer_method = MethodSpecification(
    config=geer_trainer_config("geer", GeerModelConfig()),
    description="3DGEER: exact Gaussian ray tracing for any camera (fisheye, 360), BEAP or native-ray supervision, "
    "splatfacto schedule with gsplat DefaultStrategy densification. " + OWN_OPTIONS_HELP,
)

geer_mcmc_method = MethodSpecification(
    config=geer_trainer_config("geer-mcmc", GeerModelConfig(strategy="mcmc")),
    description="3DGEER with gsplat's MCMCStrategy (relocation + noise) instead of split/clone/prune. "
    + OWN_OPTIONS_HELP,
)
