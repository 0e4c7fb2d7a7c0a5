"""splatfacto (nerfstudio 1.1.5) for geer-compare's runs: the model, schedule and strategy unchanged, with the
host pitfalls (../shared/HOST-PITFALLS.md) worked around only inside these runs:

* `.cuda()` hard-coded in splatfacto's `populate_modules` and `get_outputs`: without CUDA, `Tensor.cuda` is the
  identity while those two methods run;
* gsplat's rasterizer needs CUDA: without it, `nerfstudio.models.splatfacto.rasterization` is
  geer_ns.compare.ewa_cpu's while `get_outputs` runs (labeled in the results);
* splatfacto never passes `camera_model` to gsplat: `gsplat_camera_model` ("fisheye": gsplat's EWA with the
  equidistant fisheye Jacobian, FisheyeGS-like) is added to its call;
* torchmetrics' LPIPS downloads AlexNet when the model is built: it is built only from cached weights
  (geer_ns.metrics.perceptual.build_lpips_if_cached), else a NaN stand-in (geer-compare scores LPIPS itself);
* nerfstudio-data's point cloud is read with open3d (needs libusb): read with plyfile instead;
* `cache_images="cpu"` pins memory (fails without a GPU): the images are cached on the training device.

Nothing is patched outside these calls, and ordinary `ns-train splatfacto` never imports this module.
"""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Type

import numpy as np
import torch

from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig
from nerfstudio.models import splatfacto as splatfacto_module
from nerfstudio.models.splatfacto import SplatfactoModel, SplatfactoModelConfig

from geer_ns.metrics import perceptual
from geer_ns.data.ply import read_ply_points
from geer_ns.compare import ewa_cpu


@contextlib.contextmanager
def _cuda_calls_stay_put():
    """Tensor.cuda() returns the tensor itself (no CUDA here: splatfacto's hard-coded .cuda())."""
    if torch.cuda.is_available():
        yield
        return
    original = torch.Tensor.cuda
    torch.Tensor.cuda = lambda self, *args, **kwargs: self  # type: ignore[assignment]
    try:
        yield
    finally:
        torch.Tensor.cuda = original  # type: ignore[assignment]


@contextlib.contextmanager
def _patched(module, name: str, value):
    original = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, original)


class _NoLpips(torch.nn.Module):
    """Stands in for torchmetrics' LPIPS when AlexNet's weights are not cached: NaN, no download."""

    def forward(self, *args, **kwargs):
        return torch.tensor(float("nan"))


def _lpips_factory(*args, **kwargs):
    metric = perceptual.build_lpips_if_cached()
    return metric if metric is not None else _NoLpips()


def uses_cpu_rasterizer(device: torch.device) -> bool:
    return torch.device(device).type != "cuda"


@dataclass
class CompareSplatfactoModelConfig(SplatfactoModelConfig):
    """splatfacto's config, plus the camera model handed to gsplat (splatfacto never passes one)."""

    _target: Type = field(default_factory=lambda: CompareSplatfactoModel)
    gsplat_camera_model: Literal["pinhole", "fisheye"] = "pinhole"


class CompareSplatfactoModel(SplatfactoModel):
    """SplatfactoModel with the scoped work-arounds of the module docstring; no behavior of its own."""

    config: CompareSplatfactoModelConfig

    def populate_modules(self):
        import torchmetrics.image.lpip as lpip_module

        with _cuda_calls_stay_put(), _patched(lpip_module, "LearnedPerceptualImagePatchSimilarity", _lpips_factory):
            super().populate_modules()

    def _rasterizer(self):
        gsplat_call = splatfacto_module.rasterization
        if uses_cpu_rasterizer(self.device):
            gsplat_call = ewa_cpu.rasterization
        return functools.partial(gsplat_call, camera_model=self.config.gsplat_camera_model)

    def get_outputs(self, camera):
        with _cuda_calls_stay_put(), _patched(splatfacto_module, "rasterization", self._rasterizer()):
            return super().get_outputs(camera)

    @property
    def rasterizer_label(self) -> str:
        return ewa_cpu.LABEL if uses_cpu_rasterizer(self.device) else "gsplat CUDA"


@dataclass
class PlyfileNerfstudioDataParserConfig(NerfstudioDataParserConfig):
    """nerfstudio-data, with the seed point cloud read by plyfile (nerfstudio's open3d needs libusb here)."""

    _target: Type = field(default_factory=lambda: PlyfileNerfstudio)


@dataclass
class PlyfileNerfstudio(Nerfstudio):
    config: PlyfileNerfstudioDataParserConfig

    def _load_3D_points(self, ply_file_path: Path, transform_matrix: torch.Tensor, scale_factor: float):
        xyz, rgb = read_ply_points(ply_file_path)
        if len(xyz) == 0:
            return None
        points = torch.from_numpy(np.concatenate([xyz, np.ones_like(xyz[:, :1])], axis=1)) @ transform_matrix.T
        return {"points3D_xyz": points * scale_factor, "points3D_rgb": torch.from_numpy(rgb)}


def splatfacto_trainer_config(camera_model: str = "pinhole"):
    """nerfstudio's registered `splatfacto` method config, with the model and dataparser classes above."""
    import copy

    from nerfstudio.configs.method_configs import method_configs

    config = copy.deepcopy(method_configs["splatfacto"])
    model = config.pipeline.model
    config.pipeline.model = CompareSplatfactoModelConfig(
        **{k: getattr(model, k) for k in model.__dataclass_fields__ if k != "_target"},
        gsplat_camera_model=camera_model)
    parser = config.pipeline.datamanager.dataparser
    config.pipeline.datamanager.dataparser = PlyfileNerfstudioDataParserConfig(
        **{k: getattr(parser, k) for k in parser.__dataclass_fields__ if k != "_target"})
    if not torch.cuda.is_available():
        config.machine.device_type = "cpu"
        config.pipeline.datamanager.cache_images = "gpu"  # "cpu" pins memory; "gpu" caches on the device
    return config
