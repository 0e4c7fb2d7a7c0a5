"""Levenberg-Marquardt solve of each training camera's lens (its lens-refinement deltas) against the current scene.

A pose solve (pose_solve.py) holds the lens. Where the lens is also wrong and only Adam moves it, each camera's
pose absorbs the lens error instead: on the dev room, poses 1 degree off with focal +2 % and k1 +0.02 moved
*away* from the truth in rounds of pose solves (docs/refinement.md). A lens is shared by every image taken with
it, so its deltas are solved on the residuals of several of its images at once, at their current poses, by the
same damped, coarse-to-fine Levenberg-Marquardt as a pose; the registration recipe then solves the poses under
the solved lens.
"""

from __future__ import annotations

from typing import Dict, Iterable, List, Sequence

import torch
from torch import Tensor

from geer_ns.refinement.pose_solve import BLUR_LEVELS_PX, coarse_to_fine, image_residual

# Central-difference step of every lens delta: relative focal (log), principal point in focal units, distortion
# coefficients. Far above float32 render noise, well inside the basin of percent-level lens errors.
DELTA_STEP = 1e-3
# Images per lens in a solve: enough views to separate the lens from any one pose, few enough that a solve costs
# about a pose solve of that many images (every delta takes two renders of each image).
IMAGES_PER_LENS = 12


def spread(indices: Sequence[int], count: int) -> List[int]:
    """At most `count` of `indices`, evenly spread over them (the images along a capture's path)."""
    if len(indices) <= count:
        return list(indices)
    return [indices[round(k * (len(indices) - 1) / (count - 1))] for k in range(count)] if count > 1 else [indices[0]]


def lens_residual(model, datamanager, group: int, indices: Sequence[int], blur: float):
    """x [deltas] -> the residuals of training images `indices` (all of lens `group`) stacked, rendered with the
    lens deltas of `group` set to x and each image at its current (adjusted) pose."""
    lens = model.lens
    views = [datamanager.train_view(i) for i in indices]
    parts = [image_residual(model, lambda _x, camera=camera: model.get_outputs(camera), batch, blur)
             for camera, batch in views]

    def residual(x: Tensor) -> Tensor:
        lens.deltas.data[group] = x.to(lens.deltas)
        return torch.cat([part(x) for part in parts])

    return residual


def solve_lens(model, datamanager, indices: Iterable[int], iterations: int,
               blur_levels: Sequence[float] = BLUR_LEVELS_PX, images_per_lens: int = IMAGES_PER_LENS
               ) -> Dict[str, float]:
    """Solve the lens deltas of every refined training camera against the model's current scene, on up to
    `images_per_lens` of its images among `indices` (a lens whose unblurred residuals would not fall keeps its
    deltas).

    Args:
        model: the GeerModel with lens refinement on and active at its step.
        datamanager: what gives `train_view(index)` (camera, batch).
        indices: the training images that may be used.
        iterations: Levenberg-Marquardt iterations per blur level.
        blur_levels: the residuals' blurs (pixels), coarse to fine.
        images_per_lens: the most images of one lens in its residuals.

    Returns:
        lenses solved, the largest relative focal change, and the relative change of the summed squared
        residuals.
    """
    lens = model.lens
    if lens is None or not lens.active(model.step):
        return {"lenses": 0, "focal_change": 0.0, "residual_change": 0.0}
    was_training = model.training
    model.train()  # the training render: the pose adjustments and the refined lens applied
    chosen = list(indices)
    solved, focal_change, before, after = 0, 0.0, 0.0, 0.0
    try:
        for group in range(len(lens.cameras)):
            images = spread([i for i in chosen if lens.image_camera[i] == group], images_per_lens)
            if not images or not lens.delta_fields[group]:
                continue
            start = x = lens.deltas[group].detach().double().cpu().clone()
            focal_before = lens.refined_camera(group)
            steps = torch.full_like(start, DELTA_STEP)
            try:
                x, cost0, cost1 = coarse_to_fine(
                    lambda blur: lens_residual(model, datamanager, group, images, blur), start, iterations,
                    blur_levels, steps=steps)
            finally:
                lens.deltas.data[group] = x.to(lens.deltas)  # never a trial value, also when a render raised
            after_camera = lens.refined_camera(group)
            if hasattr(after_camera, "fx"):
                focal_change = max(focal_change, abs(after_camera.fx / focal_before.fx - 1.0))
            solved, before, after = solved + 1, before + cost0, after + cost1
    finally:
        model.train(was_training)
    return {"lenses": solved, "focal_change": focal_change,
            "residual_change": (after - before) / before if before > 0 else 0.0}
