"""`geer-export` (or `python -m geer_ns.export`): write a trained geer scene in the formats viewers read.

    geer-export --load-config outputs/room/geer/<run>/config.yml --output-dir export/ [--formats ply glb spz]

Loads the checkpoint as ns-export does, says how far an EWA splatting viewer's image will be from geer's on
pinhole views at training poses (geer_ns/export/ewa.py), and writes each format with a metadata entry saying
that the scene was trained with exact ray evaluation (and that figure).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Literal

import numpy as np
import torch
import tyro

from geer_ns.export.ewa import EwaReport, compare, pinhole_at
from geer_ns.export.formats import WRITERS, Splats
from geer_ns.sh_degrees.packing import DEGREES

Format = Literal["ply", "glb", "spz"]
TRAINED_WITH = ("3DGEER exact ray evaluation (geer-ns): each Gaussian's closed-form response along every ray, "
                "not EWA splatting; a splatting viewer shows an approximation of it")


@dataclass
class ExportConfig:
    """Export a trained geer scene."""

    load_config: Path
    """The run's config.yml (as for ns-export / ns-eval)."""
    output_dir: Path
    """Folder the files are written to (splat.ply, splat.glb, splat.spz)."""
    formats: List[Format] = field(default_factory=lambda: ["ply", "glb", "spz"])
    """Which formats to write."""
    ewa_views: int = 4
    """Training poses the EWA-vs-exact difference is measured at (0: skip the measurement)."""
    ewa_size: int = 96
    """Width and height of those pinhole views (90-degree field of view), in pixels."""


def splats_of(model) -> Splats:
    """The model's Gaussians (splatfacto's parameters) as float32 numpy arrays."""
    p = {name: value.detach().float().cpu().numpy() for name, value in model.gauss_params.items()}
    degrees = model.strategy_state.get(DEGREES)  # each Gaussian's own SH degree, where chosen
    return Splats(p["means"], p["scales"], p["quats"], p["opacities"].reshape(-1), p["features_dc"],
                  p["features_rest"], None if degrees is None else degrees.cpu().numpy())


def measure_ewa(model, cameras, views: int, size: int) -> EwaReport:
    """EwaReport of the model at `views` training poses spread over the training cameras."""
    params = model.gauss_params
    count = cameras.camera_to_worlds.shape[0]
    picks = sorted({round(i * (count - 1) / max(1, views - 1)) for i in range(views)}) if count else []
    poses = [pinhole_at(cameras.camera_to_worlds[i].cpu(), size, size) for i in picks]
    sh = torch.cat([params["features_dc"][:, None], params["features_rest"]], dim=1).detach()
    degree = model.config.sh_degree
    return compare(params["means"].detach(), params["quats"].detach(), torch.exp(params["scales"].detach()),
                   torch.sigmoid(params["opacities"].detach()).reshape(-1), sh, degree, poses)


def export(config: ExportConfig) -> dict:
    """Load, measure, write; returns the metadata written (and prints it)."""
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, step = eval_setup(config.load_config, test_mode="inference")
    model = pipeline.model
    splats = splats_of(model)
    metadata = {"trained_with": TRAINED_WITH, "renderer": "exact_ray_evaluation", "generator": "geer-ns",
                "gaussians": splats.count, "sh_degree": splats.sh_degree, "step": step}
    if splats.sh_degrees is not None:  # how many Gaussians keep each degree (the files store sh_degree for all)
        metadata["sh_degree_counts"] = np.bincount(splats.sh_degrees, minlength=4).tolist()
    if config.ewa_views > 0:
        report = measure_ewa(model, pipeline.datamanager.train_dataset.cameras, config.ewa_views, config.ewa_size)
        print(f"geer-export: {report.line()}")
        metadata["ewa_vs_exact_psnr_db"] = round(report.mean_psnr_db, 3)
        metadata["ewa_vs_exact_method"] = report.method
    if splats.sh_degrees is not None:
        print(f"geer-export: Gaussians by their own SH degree 0-3: {metadata['sh_degree_counts']}; each format stores "
              f"one degree for all, {splats.sh_degree} (lower-degree Gaussians store zeros above theirs)")
    config.output_dir.mkdir(parents=True, exist_ok=True)
    for name in config.formats:
        path = config.output_dir / f"splat.{name}"
        WRITERS[name](splats, path, metadata)
        print(f"geer-export: wrote {path} ({splats.count} Gaussians, SH degree {splats.sh_degree})")
    return metadata


def entrypoint() -> None:
    export(tyro.cli(ExportConfig))


if __name__ == "__main__":
    entrypoint()
