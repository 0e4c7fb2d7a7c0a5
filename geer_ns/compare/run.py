"""Train one geer-compare method with nerfstudio's own trainer (in this process), then render and score its
test views on the capture's own pixels."""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import torch
from torch import Tensor

from geer_ns.metrics.regions import masked_psnr as psnr_where
from geer_ns.cameras import CameraModel, EquidistantCamera, PinholeCamera
from geer_ns.compare.capture import Capture
from geer_ns.compare.methods import Method, config_digest
from geer_ns.compare.resample import resample
from geer_ns.training.horizon import stretch_schedules


@dataclass
class Result:
    name: str
    description: str
    rasterizer: str
    steps: int
    seed: int
    train_seconds: float
    gaussians: int
    metrics: Dict[str, float]  # averaged over the test views
    render_ms: float  # median per test view
    renders: List[Tensor] = field(default_factory=list)  # [H, W, 3] on the capture's pixels
    config_digest: str = ""  # methods.config_digest: which options and defaults made the run


def train(method: Method, steps: int, out_dir: Path, seed: int):
    """nerfstudio's Trainer on a copy of the method's config with the common schedule and `seed`; returns
    (pipeline, seconds)."""
    config = copy.deepcopy(method.config)
    config.machine.seed = seed
    config.data = config.pipeline.datamanager.data = method.data
    config.pipeline.datamanager.dataparser.data = method.data
    config.pipeline.datamanager.dataparser.downscale_factor = 1  # every method at the capture's resolution
    config.output_dir, config.experiment_name, config.timestamp = out_dir / "runs", method.name, f"seed{seed}"
    config.vis = "tensorboard"
    config.max_num_iterations = steps
    config.steps_per_eval_image = config.steps_per_eval_batch = config.steps_per_eval_all_images = 0
    config.steps_per_save = 10**9
    config.viewer.quit_on_train_completion = True
    stretch_schedules(config, steps)  # every method: splatfacto's 30000-step shape stretched to the run (horizon.py)
    if hasattr(config, "schedules_written_for"):  # geer's trainer: already following the run
        config.schedules_written_for = steps
    trainer, seconds = train_timed(config)
    return trainer.pipeline, seconds


def train_timed(config):
    """nerfstudio's Trainer on `config` in this process, seeded as ns-train seeds it; returns (the trained
    trainer, seconds of training). The writers of an earlier run in this process are dropped first."""
    from nerfstudio.scripts.train import _set_random_seed
    from nerfstudio.utils import writer

    writer.EVENT_WRITERS.clear()
    _set_random_seed(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    start = time.perf_counter()
    trainer.train()
    return trainer, time.perf_counter() - start


def _render_camera(kind: str, cameras, index: int) -> CameraModel:
    """The camera splatfacto rendered a test view in: a pinhole or an equidistant fisheye with its intrinsics."""
    cam = cameras[index]
    w, h = int(cam.width), int(cam.height)
    k = [float(getattr(cam, n)) for n in ("fx", "fy", "cx", "cy")]
    return PinholeCamera(w, h, *k) if kind == "pinhole" else EquidistantCamera(w, h, *k)


def masked_psnr(pred: Tensor, gt: Tensor, mask: Tensor) -> float:
    """PSNR over the pixels where mask [H,W] is set; NaN where there are none."""
    psnr = psnr_where(pred, gt, mask)
    return float("nan") if psnr is None else psnr


def score(pred: Tensor, gt: Tensor, valid: Tensor, central: Tensor, covered: Tensor, lpips) -> Dict[str, float]:
    """Metrics of one view over its valid pixels (see docs/compare.md for the protocol)."""
    from pytorch_msssim import ssim

    filled = torch.where(valid[..., None], pred, gt)  # pixels outside the valid set are equal: no error, no edge
    a, b = filled.permute(2, 0, 1)[None].float(), gt.permute(2, 0, 1)[None].float()
    metrics = {
        "psnr": masked_psnr(pred, gt, valid),
        "ssim": float(ssim(a, b, data_range=1.0, size_average=True)),
        "central_psnr": masked_psnr(pred, gt, valid & central),
        "peripheral_psnr": masked_psnr(pred, gt, valid & ~central),
        "covered": float((valid & covered).sum()) / max(int(valid.sum()), 1),
        "covered_psnr": masked_psnr(pred, gt, valid & covered),
    }
    if lpips is not None:
        metrics["lpips"] = float(lpips(a.clamp(0, 1), b.clamp(0, 1)))
    return metrics


@torch.no_grad()
def evaluate(method: Method, pipeline, capture: Capture, lpips) -> Dict[str, object]:
    """Render the method's test views, bring them to the capture's pixels, score them; averages and renders."""
    model = pipeline.model
    model.eval()
    cameras = test_cameras(method, pipeline, capture)
    per_view, renders, times = [], [], []
    for i, view in enumerate(capture.views):
        camera = cameras[i:i + 1].to(model.device)
        start = time.perf_counter()
        outputs = model.get_outputs_for_camera(camera)
        times.append(time.perf_counter() - start)
        rgb = outputs["rgb"].detach().cpu().double()
        if method.render_camera is None:
            covered = torch.ones(rgb.shape[:2], dtype=torch.bool)
        else:
            background = outputs["background"].detach().cpu().double().reshape(-1, 3)[0]
            rgb, covered = resample(rgb, _render_camera(method.render_camera, cameras, i), view.camera, background)
        if rgb.shape[:2] != view.image.shape[:2]:
            raise RuntimeError(f"{method.name}: a {tuple(rgb.shape[:2])} render for a {tuple(view.image.shape[:2])} view")
        per_view.append(score(rgb, view.image.double(), view.valid, view.central, covered, lpips))
        renders.append(rgb.float())
    keys = per_view[0].keys()
    averages = {k: _mean([m[k] for m in per_view]) for k in keys}
    return {"metrics": averages, "renders": renders, "render_ms": 1000 * sorted(times)[len(times) // 2]}


def test_cameras(method: Method, pipeline, capture: Capture):
    """The method's cameras of the capture's test split (nerfstudio's eval dataset is the val split, which
    need not be the same images), checked to be the capture's test poses in the transforms file's frame."""
    parser = pipeline.datamanager.dataparser
    outputs = parser.get_dataparser_outputs("test")
    cameras = outputs.cameras
    poses = outputs.transform_poses_to_original_space(cameras.camera_to_worlds)
    if poses.shape != capture.test_poses.shape or not torch.allclose(poses, capture.test_poses, atol=1e-4):
        raise RuntimeError(f"{method.name}: the test split of {parser.config.data} is not the capture's ({len(cameras)} "
                           f"views, {len(capture.views)} in {capture.transforms}, or other poses)")
    return cameras


def _mean(values: List[float]) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return sum(finite) / len(finite) if finite else float("nan")


def run_method(method: Method, steps: int, capture: Capture, out_dir: Path, lpips, seed: int = 42,
               say=print) -> Result:
    """Train `method` with `seed` and score its test views."""
    say(f"[geer-compare] {method.name}, seed {seed}: training {steps} steps on {method.data}")
    pipeline, seconds = train(method, steps, out_dir, seed)
    say(f"[geer-compare] {method.name}, seed {seed}: trained in {seconds:.1f} s, {pipeline.model.num_points} "
        "Gaussians; scoring")
    found = evaluate(method, pipeline, capture, lpips)
    rasterizer = getattr(pipeline.model, "rasterizer_label", "geer_ns.render (3DGEER)")
    return Result(method.name, method.description, rasterizer, steps, seed, seconds, int(pipeline.model.num_points),
                  found["metrics"], found["render_ms"], found["renders"], config_digest(method))


def lpips_metric(device: Optional[torch.device] = None):
    """torchmetrics' LPIPS (AlexNet) when its weights are cached, else None (no download)."""
    from geer_ns.metrics import perceptual

    metric = perceptual.build_lpips_if_cached()
    return None if metric is None else metric.to(device or "cpu")
