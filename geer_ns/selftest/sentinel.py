"""The training sentinel: every `every` steps one training view is also rendered by the PyTorch renderer and
compared with the compiled renderer's (image, and the gradient of a fixed random loss w.r.t. the means and
opacities), at the self-test's float32-vs-twin tolerances (suite.py). A disagreement switches the run to the
PyTorch renderer, says so once, and writes the view's inputs and what was measured to a file for a bug report.

Cost: one compiled and one PyTorch render (forward and backward) per check; the PyTorch renderer is up to ~40x
slower than the kernels' code (geer-doctor's step times, docs/cuda.md), so checking every 5000 steps costs < 1 % of a run.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor

from geer_ns.render.moving import MovingRays
from geer_ns.render import RayGrid, render, resolve_backend
from geer_ns.render.verdict import verdict_dir

from .suite import grad_error, image_error

DEFAULT_EVERY = 5000


@dataclass
class ViewInputs:
    """Everything one render of a training view takes (detached copies are made at check time)."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    viewmat: Tensor
    grid: RayGrid
    sh_degree: int | None
    background: Tensor
    lambda_mode: str
    motion: MovingRays | None = None  # a rolling-shutter view's rays


def _render(inputs: ViewInputs, backend: str) -> tuple[Tensor, list[Tensor]]:
    """(rgb, [dL/dmeans, dL/dopacities]) of a fixed random loss on the image, composited in the per-view order
    whatever the run's (per-ray order: its float32 near-ties and the kernels' window would make the comparison
    flaky; every per-pair function it runs is the per-view order's, and tests/test_render_order.py checks it)."""
    means = inputs.means.detach().clone().requires_grad_(True)
    opacities = inputs.opacities.detach().clone().requires_grad_(True)
    motion = inputs.motion
    if motion is not None:
        motion = MovingRays(motion.origins.detach(), motion.dirs.detach(), motion.offset)
    out = render(means, inputs.quats.detach(), inputs.scales.detach(), opacities, inputs.colors.detach(),
                 inputs.viewmat.detach(), inputs.grid, sh_degree=inputs.sh_degree,
                 background=inputs.background.detach(), lambda_mode=inputs.lambda_mode, backend=backend,
                 motion=motion)
    gen = torch.Generator().manual_seed(0)
    weights = torch.randn(out.rgb.shape, generator=gen, dtype=torch.float64).to(out.rgb)
    (weights * out.rgb).sum().backward()
    return out.rgb.detach(), [means.grad, opacities.grad]


class KernelSentinel:
    """Compares the compiled renderer with the PyTorch renderer on one training view every `every` steps (0:
    never). `say` prints its one line."""

    def __init__(self, every: int = DEFAULT_EVERY, say: Callable[[str], None] = print):
        self.every = every
        self.say = say
        self.last_step = -1
        self.report: Path | None = None  # the disagreement file, once one was found

    def backend(self, configured: str) -> str:
        """The backend renders use: the configured one, or the PyTorch renderer once a check found the compiled
        renderer disagreeing (the run's configuration stays as the user gave it)."""
        return "torch" if self.report is not None else configured

    def due(self, step: int) -> bool:
        return self.every > 0 and step > 0 and step % self.every == 0 and step != self.last_step and self.report is None

    def check(self, step: int, backend: str, inputs: ViewInputs) -> bool:
        """At a due step, compare `backend` (when it resolves to a compiled renderer) with the PyTorch renderer
        on `inputs`. Returns True when they disagree (said once, inputs written to self.report)."""
        if not self.due(step):
            return False
        self.last_step = step
        device = inputs.means.device
        chosen = resolve_backend(backend, device)  # type: ignore[arg-type]
        if chosen == "torch":
            return False
        ours_rgb, ours_grads = _render(inputs, chosen)
        twin_rgb, twin_grads = _render(inputs, "torch")
        dtype = inputs.means.dtype
        checks = {"rgb": image_error(ours_rgb, twin_rgb, dtype)}
        for name, a, b in zip(("grad means", "grad opacities"), ours_grads, twin_grads):
            checks[name] = grad_error(a, b, None, dtype, degenerate=False)
        failed = [name for name, (ok, _) in checks.items() if not ok]
        if not failed:
            return False
        self.report = self._write(step, chosen, inputs, checks)
        what = "; ".join(f"{name} {checks[name][1]}" for name in failed)
        self.say(f"geer: at step {step} the {chosen} renderer disagreed with the PyTorch renderer ({what}); the run "
                 f"continues with the PyTorch renderer. Inputs for a bug report: {self.report}")
        return True

    @staticmethod
    def _write(step: int, backend: str, inputs: ViewInputs, checks: dict) -> Path:
        folder = verdict_dir() / "disagreements"
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"step{step}_{backend}_{time.strftime('%Y%m%d-%H%M%S')}.pt"
        grid = inputs.grid
        torch.save({
            "step": step, "backend": backend, "checks": {k: v[1] for k, v in checks.items()},
            "torch": torch.__version__, "sh_degree": inputs.sh_degree, "lambda_mode": inputs.lambda_mode,
            **{name: getattr(inputs, name).detach().cpu() for name in
               ("means", "quats", "scales", "opacities", "colors", "viewmat", "background")},
            "grid": {"dirs": grid.dirs.cpu(), "valid": grid.valid.cpu(), "height": grid.height, "width": grid.width,
                     "tile_size": grid.tile_size},
            "motion": None if inputs.motion is None else {
                "origins": inputs.motion.origins.detach().cpu(), "dirs": inputs.motion.dirs.detach().cpu(),
                "offset": inputs.motion.offset},
        }, path)
        return path
