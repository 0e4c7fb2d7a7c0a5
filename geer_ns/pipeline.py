"""geer's pipeline: nerfstudio's VanillaPipeline with eval metrics split by camera kind.

A mixed rig (fisheye + pinhole, or a panorama) is scored per camera model as well as over all images:
ns-eval's JSON gets ``psnr/OPENCV_FISHEYE``, ``psnr/OPENCV``, ... next to ``psnr`` (and ``images/<kind>``,
the number of images behind each split). A metric an image does not have (``central_psnr`` of a panorama,
whose central region is undefined) is averaged over the images that have it; nerfstudio's own loop takes the
key set of the first image and fails on the others.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from time import time
from typing import Dict, Iterable, List, Literal, Optional, Tuple, Type

import torch
import torchvision.utils as vutils

from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils.rich_utils import CONSOLE

from geer_ns.data.views import camera_kind
from geer_ns.refinement.lens import attach
from geer_ns.refinement.refined_frame import RefinedFrame

# Per-image timings are not split by camera kind (ns-eval's fps is not a render speed anyway).
_NOT_SPLIT = ("num_rays_per_sec", "fps")


@dataclass
class GeerPipelineConfig(VanillaPipelineConfig):
    _target: Type = field(default_factory=lambda: GeerPipeline)


def average_metrics(per_image: List[Dict[str, float]], get_std: bool) -> Dict[str, float]:
    """Mean (and std) of every metric over the images that report it."""
    keys = list(dict.fromkeys(k for metrics in per_image for k in metrics))
    out: Dict[str, float] = {}
    for key in keys:
        values = torch.tensor([m[key] for m in per_image if key in m], dtype=torch.float64)
        out[key] = float(values.mean())
        if get_std:
            out[f"{key}_std"] = float(values.std()) if len(values) > 1 else 0.0
    return out


def split_by_kind(per_image: List[Tuple[str, Dict[str, float]]]) -> Dict[str, float]:
    """``metric/KIND`` means and ``images/KIND`` counts, one set per camera kind."""
    out: Dict[str, float] = {}
    for kind in sorted({kind for kind, _ in per_image}):
        group = [m for k, m in per_image if k == kind]
        out[f"images/{kind}"] = float(len(group))
        for key, value in average_metrics(group, get_std=False).items():
            if key not in _NOT_SPLIT:
                out[f"{key}/{kind}"] = value
    return out


class GeerPipeline(VanillaPipeline):
    def __init__(self, config: GeerPipelineConfig, device: str, test_mode: Literal["test", "val", "inference"] = "val",
                 world_size: int = 1, local_rank: int = 0, grad_scaler=None):
        # nerfstudio wraps the model in DistributedDataParallel when world_size > 1: DDP registers the parameters
        # once, while densification replaces them every refinement, and its barrier takes NCCL-only device_ids.
        # geer's training engine keeps the replicas identical itself (geer_ns/distributed), so no wrap.
        super().__init__(config, device, test_mode=test_mode, world_size=1, local_rank=local_rank,
                         grad_scaler=grad_scaler)
        self.world_size = world_size
        cameras = self.datamanager.train_dataset.cameras
        attach(self.model, cameras)  # per-camera state: lens, vignetting
        if self.model.camera_optimizer.config.mode != "off" and self.model.config.refined_frame:
            self.model.refined_frame = RefinedFrame(cameras.camera_to_worlds)

    def get_average_image_metrics(
        self,
        data_loader: Iterable,
        image_prefix: str,
        step: Optional[int] = None,
        output_path: Optional[Path] = None,
        get_std: bool = False,
    ) -> Dict[str, float]:
        """nerfstudio's per-image loop (same metrics, same saved images), averaged per key and per camera kind."""
        self.eval()
        frame = self.model.refined_frame
        if frame is not None:
            CONSOLE.log("geer: scoring in the refined frame: the given test poses follow the scene, which with its "
                        f"refined cameras {frame.similarity(self.model.camera_optimizer).describe()} "
                        "(--pipeline.model.refined-frame False: as given)")
        if output_path is not None:
            output_path.mkdir(exist_ok=True, parents=True)
        per_image: List[Tuple[str, Dict[str, float]]] = []
        for idx, (camera, batch) in enumerate(data_loader):
            start = time()
            outputs = self.model.get_outputs_for_camera(camera=camera)
            metrics, images = self.model.get_image_metrics_and_images(outputs, batch)
            if output_path is not None:
                for key, image in images.items():
                    vutils.save_image(image.permute(2, 0, 1).cpu(), output_path / f"{image_prefix}_{key}_{idx:04d}.png")
            num_rays = int(camera.height.reshape(-1)[0]) * int(camera.width.reshape(-1)[0])
            metrics["num_rays_per_sec"] = num_rays / (time() - start)
            metrics["fps"] = metrics["num_rays_per_sec"] / num_rays
            per_image.append((camera_kind(camera, 0), metrics))
        result = average_metrics([m for _, m in per_image], get_std)
        result.update(split_by_kind(per_image))
        self.train()
        return result
