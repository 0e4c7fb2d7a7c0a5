"""Levenberg-Marquardt solve of the training cameras' poses against the current scene
(`--pipeline.model.pose-solve-every`).

nerfstudio's camera optimizer moves each camera's six pose adjustments (SO3xR3 or SE3 tangent) by Adam steps on
the training loss, one image a step: a camera's adjustments move only when its image is drawn, by steps the
learning-rate schedule shrinks before they arrive (docs/refinement.md). Here, every
`every` steps the scene is held fixed and each training camera's adjustments are solved for: Gauss-Newton on
the image's photometric residuals with a central-difference Jacobian (twelve renders of the image an iteration;
the renderers give reverse-mode gradients, and a Jacobian needs one derivative per adjustment), damped
Levenberg-Marquardt style so that the cost never rises, coarse to fine over blurred residuals. Adam then
continues from the solved poses, its momentum of the adjustments reset.
"""

from __future__ import annotations

import copy
import math
import time
from typing import Callable, Dict, Iterable, Optional, Sequence, Tuple

import torch
from torch import Tensor

# Central-difference steps of the six adjustments: translation (the dataparser's units, a scene scaled into
# the unit cube) and rotation (radians). Well inside the solve's basin and far above float32 render noise.
TRANSLATION_STEP = 1e-3
ROTATION_STEP = 1e-3
# Coarse to fine, as image alignment goes: the residuals of both images blurred by these standard deviations
# (pixels of the rendered image), `iterations` each. A sharp image's Jacobian holds only within a fraction of a
# pixel; blurred, it holds over the pose error, and the last level is the unblurred images. A first level of
# 2 px left 3 of 42 cameras in local minima where 4 px left none (against a frozen scene: docs/refinement.md).
BLUR_LEVELS_PX = (4.0, 2.0, 1.0, 0.0)


def difference_steps() -> Tensor:
    """[6] float64: the central-difference step of each adjustment (translation first, as the tangents)."""
    return torch.tensor([TRANSLATION_STEP] * 3 + [ROTATION_STEP] * 3, dtype=torch.float64)


def levenberg_marquardt(residual: Callable[[Tensor], Tensor], x0: Tensor, steps: Tensor, iterations: int,
                        damping: float = 1e-3) -> Tuple[Tensor, float, float]:
    """Minimise |residual(x)|^2 from x0 by Levenberg-Marquardt with a central-difference Jacobian.

    Args:
        residual: x [D] float64 (CPU) -> residual vector [M] (float64, on any device).
        x0: [D] float64 start.
        steps: [D] the difference step of each coordinate.
        iterations: Jacobian evaluations (each 2 D residuals, plus one per tried step).
        damping: the starting multiple of diag(J^T J) added to J^T J.

    Returns:
        (x, the cost at x0, the cost at x); the cost never rises (a step that would raise it is refused with
        more damping, and the solve ends when no damping finds a lower cost).
    """
    x = x0.clone()
    r = residual(x)
    start = cost = float(r.square().sum())
    for _ in range(iterations):
        columns = []
        for k in range(len(x)):
            step = torch.zeros_like(x)
            step[k] = steps[k]
            columns.append((residual(x + step) - residual(x - step)) / (2.0 * steps[k]))
        jacobian = torch.stack(columns, dim=1)
        normal, gradient = (jacobian.T @ jacobian).cpu(), (jacobian.T @ r).cpu()
        # a coordinate the residuals do not depend on has a zero diagonal: the floor keeps the system solvable
        floor = torch.full_like(gradient, 1e-12 * max(float(torch.diagonal(normal).max()), 1e-30))
        while True:
            scaled = torch.diag(torch.maximum(torch.diagonal(normal), floor))
            delta = -torch.linalg.solve(normal + damping * scaled, gradient)
            trial = residual(x + delta)
            trial_cost = float(trial.square().sum())
            if math.isfinite(trial_cost) and trial_cost < cost:
                x, r, cost, damping = x + delta, trial, trial_cost, max(damping / 10.0, 1e-9)
                break
            damping *= 10.0
            if damping > 1e6:  # no step lowers the cost: a minimum as far as this Jacobian can tell
                return x, start, cost
    return x, start, cost


def blurred(image: Tensor, valid: Tensor, sigma: float) -> Tensor:
    """image [H,W,C] blurred by a Gaussian of `sigma` pixels over its valid [H,W,1] pixels only (normalised by
    the blurred mask, so the invalid pixels around a fisheye's circle do not darken its rim)."""
    if sigma <= 0:
        return image
    radius = max(1, int(math.ceil(3 * sigma)))
    offsets = torch.arange(-radius, radius + 1, dtype=image.dtype, device=image.device)
    kernel = torch.exp(-0.5 * (offsets / sigma) ** 2)
    kernel = kernel / kernel.sum()
    weight = valid.to(image.dtype)
    stack = torch.cat([image * weight, weight], dim=-1).permute(2, 0, 1)[:, None]  # [C+1,1,H,W]
    stack = torch.nn.functional.conv2d(stack, kernel.view(1, 1, 1, -1), padding=(0, radius))
    stack = torch.nn.functional.conv2d(stack, kernel.view(1, 1, -1, 1), padding=(radius, 0))
    stack = stack[:, 0].permute(1, 2, 0)
    return stack[..., :-1] / stack[..., -1:].clamp_min(1e-6)


def image_residual(model, render: Callable[[Tensor], Dict], batch: Dict, blur: float = 0.0
                   ) -> Callable[[Tensor], Tensor]:
    """x [6] -> the photometric residuals [3 * valid pixels] (float64) of `render(x)`'s image (nerfstudio
    outputs) against the batch's, both blurred by `blur` pixels."""

    def residual(x: Tensor) -> Tensor:
        with torch.no_grad():
            outputs = render(x)
            gt = model.composite_with_background(model.get_gt_img(batch["image"]), outputs["background"])
            valid = model.supervised_mask(outputs, batch)
            difference = blurred(outputs["rgb"], valid, blur) - blurred(gt, valid, blur)
            difference = torch.where(valid, difference, 0.0)
        return difference.reshape(-1).double()

    return residual


def camera_residual(model, datamanager, index: int, adjustment: Tensor, blur: float = 0.0
                    ) -> Callable[[Tensor], Tensor]:
    """image_residual of training image `index` rendered with its pose adjustment row set to x, under the
    training render (appearance and bilateral grid included)."""
    camera, batch = datamanager.train_view(index)

    def render(x: Tensor) -> Dict:
        adjustment[index] = x.to(adjustment)
        return model.get_outputs(camera)

    return image_residual(model, render, batch, blur)


def adjusted_camera(camera, x: Tensor):
    """A copy of one-camera `camera` whose camera-to-world is moved by the SO3xR3 tangent x [6] (translation
    first) as nerfstudio's camera optimizer moves it: rotation applied in world axes, translation added."""
    from nerfstudio.cameras.lie_groups import exp_map_SO3xR3

    c2w = camera.camera_to_worlds
    adj = exp_map_SO3xR3(x.to(c2w)[None])
    moved = torch.cat([torch.bmm(adj[:, :3, :3], c2w[:, :3, :3]), c2w[:, :3, 3:] + adj[:, :3, 3:]], dim=-1)
    out = copy.copy(camera)
    out.camera_to_worlds = moved
    return out


def coarse_to_fine(residual_at: Callable[[float], Callable[[Tensor], Tensor]], x0: Tensor, iterations: int,
                   blur_levels: Sequence[float] = BLUR_LEVELS_PX, steps: Optional[Tensor] = None
                   ) -> Tuple[Tensor, float, float]:
    """Levenberg-Marquardt from x0 over residuals blurred by each of `blur_levels` in turn, `iterations` each.

    Args:
        residual_at: blur (pixels) -> the residual function x [D] -> [M] at that blur.
        x0: [D] float64, the start.
        iterations: per level.
        blur_levels: the blurs, coarse to fine.
        steps: [D] the central-difference steps (default: a pose's, difference_steps()).

    Returns:
        (x, the unblurred cost at x0, at x). No level's own cost rises, but a blurred level can lead where the
        image itself fits worse: then x is x0 (the two costs equal).
    """
    sharp = residual_at(0.0)
    cost0 = float(sharp(x0).square().sum())
    x = x0
    for blur in blur_levels:
        x, _, cost1 = levenberg_marquardt(residual_at(blur), x, difference_steps() if steps is None else steps,
                                          iterations)
    if not blur_levels or blur_levels[-1] > 0:  # the last level was blurred: its cost is not the image's
        cost1 = float(sharp(x).square().sum())
    if not cost1 < cost0:
        return x0, cost0, cost0
    return x, cost0, cost1


def solve_view_pose(model, camera, batch: Dict, iterations: int, blur_levels: Sequence[float] = BLUR_LEVELS_PX):
    """`camera` (one held-out view, not trained) with its pose solved against the model's scene for the batch's
    image: the test-time pose alignment of pose-refinement benchmarks, whose refined scene may sit a small rigid
    motion away from the frame the held-out poses are given in. Returns a copy of `camera` at the solved pose (at
    its given pose when no move makes its image fit better)."""
    was_training = model.training
    model.eval()
    try:
        x = coarse_to_fine(lambda blur: image_residual(
            model, lambda y: model.get_outputs(adjusted_camera(camera, y)), batch, blur),
            torch.zeros(6, dtype=torch.float64), iterations, blur_levels)[0]
    finally:
        model.train(was_training)
    return adjusted_camera(camera, x)


def solve_poses(model, datamanager, indices: Iterable[int], iterations: int,
                blur_levels: Sequence[float] = BLUR_LEVELS_PX) -> Dict[str, float]:
    """Solve the pose adjustments of training images `indices` one by one against the model's current scene,
    writing them into model.camera_optimizer.pose_adjustment (a camera whose unblurred residuals would not fall
    keeps its adjustment).

    Args:
        model: the GeerModel (its camera optimizer SO3xR3 or SE3).
        datamanager: what gives `train_view(index)` (camera, batch).
        indices: the training images to solve.
        iterations: Levenberg-Marquardt iterations per blur level.
        blur_levels: the residuals' blurs (pixels), coarse to fine.

    Returns:
        cameras, the mean rotation (degrees) and translation (scene units) each moved, and the relative change
        of the summed squared residuals.
    """
    adjustment = model.camera_optimizer.pose_adjustment
    was_training = model.training
    model.train()  # the training render: the pose adjustments applied
    moved_rotation, moved_translation, before, after, count = 0.0, 0.0, 0.0, 0.0, 0
    try:
        for index in indices:
            start = x = adjustment[index].detach().double().cpu()
            try:
                x, cost0, cost1 = coarse_to_fine(
                    lambda blur: camera_residual(model, datamanager, index, adjustment.data, blur), start,
                    iterations, blur_levels)
            finally:
                adjustment.data[index] = x.to(adjustment)  # never a trial value, also when a render raised
            moved_translation += float((x[:3] - start[:3]).norm())
            moved_rotation += math.degrees(float((x[3:] - start[3:]).norm()))
            before, after, count = before + cost0, after + cost1, count + 1
    finally:
        model.train(was_training)
    count = max(count, 1)
    return {"cameras": count, "rotation_deg": moved_rotation / count, "translation": moved_translation / count,
            "residual_change": (after - before) / before if before > 0 else 0.0}


class PoseSolver:
    """The training callback: every `every` steps (from step `every` and pose-refinement-start on), solve every
    training camera's pose adjustments and restart Adam's moments of them."""

    def __init__(self, pipeline, optimizers, every: int, iterations: int, say: Callable[[str], None]) -> None:
        """pipeline: the training pipeline (its model and datamanager); optimizers: nerfstudio's Optimizers
        (camera_opt's moments are reset after a solve); every, iterations: the options; say: the log."""
        self.pipeline, self.optimizers, self.say = pipeline, optimizers, say
        self.every, self.iterations = every, iterations

    def __call__(self, step: int) -> None:
        """Solve at this step if it is a positive multiple of `every`, from pose-refinement-start on."""
        model = self.pipeline.model
        if step == 0 or step % self.every or step < model.config.pose_refinement_start:
            return
        count = len(model.camera_optimizer.pose_adjustment)
        self.say(f"geer: pose solve at step {step}: {count} training cameras, {self.iterations} "
                 "Levenberg-Marquardt iterations each")
        solve_every_camera(self.pipeline, self.optimizers, self.iterations, f"pose solve at step {step}", self.say)


def restart_momentum(optimizers, name: str) -> None:
    """Zero Adam's momentum of nerfstudio optimizer `name` (if it exists) after a solve moved its parameters: stale
    momentum would carry them on along their old steps."""
    optimizer = optimizers.optimizers.get(name)
    for state in ([] if optimizer is None else optimizer.state.values()):
        if "exp_avg" in state:
            state["exp_avg"].zero_()


def solve_every_camera(pipeline, optimizers, iterations: int, label: str, say: Callable[[str], None]) -> None:
    """solve_poses for every training camera of `pipeline`, then Adam's momentum of the poses restarted (optimizers:
    nerfstudio's Optimizers); says what moved, after `label`."""
    start = time.perf_counter()
    model = pipeline.model
    count = len(model.camera_optimizer.pose_adjustment)
    summary = solve_poses(model, pipeline.datamanager, range(count), iterations)
    restart_momentum(optimizers, "camera_opt")
    say(f"geer: {label}: {count} cameras moved {summary['rotation_deg']:.3f} deg and {summary['translation']:.2e} "
        f"scene units on average, residuals {100 * summary['residual_change']:+.1f} %, "
        f"{time.perf_counter() - start:.0f} s")
