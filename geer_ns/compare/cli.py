"""geer-compare: train geer and splatfacto's variants on one capture, score them on the same test images.

    geer-compare --data scene/transforms.json [--steps 2000] [--methods geer splatfacto ...] [--output-dir DIR]
    python -m geer_ns.compare ...   (the same, without the console script installed)

Writes DIR/compare.md (table, methods, protocol), DIR/compare.json and DIR/compare.png (test views: ground
truth, each method, each method's error map), and prints the table. See docs/compare.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Tuple

import tyro

from geer_ns.compare.methods import DEFAULT_METHODS
from geer_ns.errors import OptionError, report_input_errors_in_one_line


@dataclass
class Compare:
    """Train each method on the same capture, split and schedule; score all on the same test images."""

    data: Path
    """The capture: a nerfstudio transforms.json (or a folder holding one), one OPENCV or OPENCV_FISHEYE camera."""
    steps: int = 2000
    """Training steps of every method (30000 and more: splatfacto's own schedule; fewer: docs/compare.md)."""
    methods: Tuple[str, ...] = DEFAULT_METHODS
    """Any of geer (its default supervision), geer-native, geer-beap (supervision forced), geer-gsplat-units
    (splatfacto's density), geer-reference-units (geer's former densification units), geer-capped (at most
    --max-gaussians), geer-mcmc, splatfacto, splatfacto-pinhole, splatfacto-fisheye (the last two: fisheye
    captures)."""
    seeds: Tuple[int, ...] = (42,)
    """Every method trains once per seed; the tables give the mean and, with two seeds or more, the 95 % interval
    of the mean (Student's t over the seeds)."""
    output_dir: Path = Path("outputs/compare")
    """Where the table, the picture, the training runs and the resampled captures go."""
    pinhole_fov_deg: float = 120.0
    """Field of view across the width of the pinhole splatfacto-pinhole's capture is undistorted to."""
    central_half_angle_deg: float = 45.0
    """The central region: rays within this angle of the optical axis, horizontally and vertically."""
    max_gaussians: int = 0
    """geer-capped's cap: geer's defaults with densification stopped at this many Gaussians (a comparison at
    equal counts: e.g. the fewest Gaussians of splatfacto's runs)."""
    keep_finished: bool = False
    """Keep the table already in --output-dir, without training, when it holds exactly these methods, steps and
    seeds made with today's options and defaults (each run's config digest); otherwise train as usual."""

    def main(self) -> str:
        from nerfstudio.utils.rich_utils import CONSOLE

        from geer_ns.compare import report
        from geer_ns.compare.capture import load_capture
        from geer_ns.compare.methods import plan
        from geer_ns.compare.run import lpips_metric, run_method
        from geer_ns.metrics.perceptual import alexnet_weights_path

        if self.steps < 1:
            raise OptionError(f"--steps {self.steps}: must be at least 1")
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise OptionError(f"--seeds {' '.join(map(str, self.seeds))}: give one or more distinct seeds")
        capture = load_capture(self.data, self.central_half_angle_deg)
        self.output_dir.mkdir(parents=True, exist_ok=True)
        methods, skipped = plan(capture, tuple(self.methods), self.output_dir, self.pinhole_fov_deg,
                                self.max_gaussians)
        lpips = lpips_metric()
        lpips_reason = ("torchmetrics' LPIPS (AlexNet), the same for every method" if lpips is not None else
                        f"not computed: AlexNet's weights are not cached at {alexnet_weights_path()} (no download)")
        lines = report.protocol(capture, self.central_half_angle_deg, self.steps, lpips_reason, self.seeds)
        if self.keep_finished and self._finished(methods, lines):
            text = (self.output_dir / "compare.md").read_text()
            print(f"[geer-compare] kept the table in {self.output_dir}: the same runs, configs and protocol")
            return text
        self._build_geer_kernels(methods)
        say = lambda text: CONSOLE.print(f"[bold yellow]{text}")  # noqa: E731
        results = [run_method(m, self.steps, capture, self.output_dir, lpips, seed, say)
                   for m in methods for seed in self.seeds]
        text = report.write(self.output_dir, capture, results, skipped, lines)
        print(text)
        print(f"[geer-compare] wrote {self.output_dir / 'compare.md'}, compare.json and compare.png")
        return text

    def _finished(self, methods, lines) -> bool:
        """Whether --output-dir holds a table of exactly these runs, each made with today's config, under this
        protocol (`lines`: the capture, steps, seeds, central region and LPIPS)."""
        import json

        from geer_ns.compare.methods import config_digest

        path = self.output_dir / "compare.json"
        if not path.is_file() or not (self.output_dir / "compare.md").is_file():
            return False
        table = json.loads(path.read_text())
        made = sorted((r["method"], r["seed"], r["steps"], r.get("config_digest")) for r in table["results"])
        planned = sorted((m.name, seed, self.steps, config_digest(m)) for m in methods for seed in self.seeds)
        return made == planned and table["protocol"] == lines

    @staticmethod
    def _build_geer_kernels(methods) -> None:
        """Build geer's CPU kernels (once, cached) before any timed training."""
        import torch

        if any(m.name.startswith("geer") for m in methods):
            from geer_ns.render.backend import resolve_backend

            resolve_backend("auto", torch.device("cuda" if torch.cuda.is_available() else "cpu"))


def entrypoint() -> None:
    report_input_errors_in_one_line()  # a bad option or capture ends the command in one line
    tyro.extras.set_accent_color("bright_yellow")
    tyro.cli(Compare).main()


if __name__ == "__main__":
    entrypoint()
