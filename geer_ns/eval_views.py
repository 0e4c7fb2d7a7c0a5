"""geer-eval: score a trained run at the cameras of another transforms.json of the same scene.

    geer-eval --load-config outputs/.../config.yml --views scene/transforms_pinhole.json --output-path eval.json
    python -m geer_ns.eval_views ...   (the same, without the console script installed)

The model is loaded as ns-eval loads it; the other file is read by geer's nerfstudio parser (per-frame
camera models allowed) with its poses mapped through the run's ``dataparser_transforms.json`` (not oriented,
centered and scaled anew), so a file sharing the training world frame lands on the training scene. Its
``--split`` views (default: test) are rendered from their own pixel rays and scored exactly like ns-eval's
(valid pixels only, central / peripheral PSNR, metrics per camera kind); the JSON has ns-eval's layout plus
``views`` and ``split``. Typical use: train on a fisheye, score on pinhole views of the same poses, and the
reverse (paper Tab. 3).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import tyro

from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.utils.eval_utils import eval_setup
from nerfstudio.utils.rich_utils import CONSOLE

from geer_ns.data.datamanager import GeerDataManager
from geer_ns.data.nerfstudio_parser import GeerNerfstudioDataParserConfig


@dataclass
class EvalViews:
    """Render a trained geer model at the cameras of another transforms.json and write ns-eval's metrics JSON."""

    load_config: Path
    """The run's config.yml (as for ns-eval)."""
    views: Path
    """transforms.json (file, or a folder holding one) with the cameras to score, in the training world frame."""
    output_path: Path = Path("eval_views.json")
    """Metrics JSON (ns-eval's layout)."""
    split: Literal["train", "val", "test"] = "test"
    """Which of the file's splits to score."""
    render_output_path: Optional[Path] = None
    """Optional folder for the renders next to their ground truth (as ns-eval)."""

    def main(self) -> dict:
        if self.output_path.suffix != ".json":
            raise ValueError(f"--output-path {self.output_path} must end in .json")
        if not self.views.exists():
            raise FileNotFoundError(f"geer-eval: --views {self.views} does not exist")
        config, pipeline, checkpoint, _ = eval_setup(self.load_config, test_mode="test")
        transforms = config.get_base_dir() / "dataparser_transforms.json"
        if not transforms.is_file():
            raise FileNotFoundError(f"geer-eval: {transforms} (the run's pose transform) does not exist")
        datamanager = pipeline.datamanager
        if not isinstance(datamanager, GeerDataManager):
            raise ValueError(f"{self.load_config}: not a geer run (datamanager {type(datamanager).__name__})")
        parser = GeerNerfstudioDataParserConfig(data=self.views, dataparser_transforms=transforms)
        run_parser = config.pipeline.datamanager.dataparser
        if isinstance(run_parser, NerfstudioDataParserConfig):
            parser.downscale_factor = run_parser.downscale_factor
        datamanager.use_eval_views(parser, self.split)
        CONSOLE.log(f"geer-eval: scoring {len(datamanager.eval_dataset)} {self.split} views of {self.views}")
        metrics = pipeline.get_average_eval_image_metrics(output_path=self.render_output_path, get_std=True)
        result = {
            "experiment_name": config.experiment_name,
            "method_name": config.method_name,
            "checkpoint": str(checkpoint),
            "views": str(self.views),
            "split": self.split,
            "results": metrics,
        }
        self.output_path.parent.mkdir(parents=True, exist_ok=True)
        self.output_path.write_text(json.dumps(result, indent=2), "utf8")
        CONSOLE.print(f"Saved results to: {self.output_path}")
        return result


def entrypoint() -> None:
    tyro.extras.set_accent_color("bright_yellow")
    tyro.cli(EvalViews).main()


if __name__ == "__main__":
    entrypoint()
