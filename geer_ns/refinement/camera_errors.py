"""How far estimated cameras are from the true ones, with the gauge that images cannot fix removed by the truth.

Images fix cameras only up to a similarity of the whole scene (a turn, a shift and a scale). Errors are read after
the similarity fitted *to the truth* (refined_frame.fit_similarity from the estimate onto the truth): its rotation
is the chordal mean of the cameras' rotation differences, then its scale and shift are the least-squares fit of
the turned centres to the true ones. Fitting the rotation from the orientations, not from the centres, matters
for captures whose path is nearly planar or straight: there the centres hardly fix a turn about the path, and a
centre fit adds noise rather than removing the gauge. The relative errors between neighbouring cameras need no
alignment (the scale aside, which the fit gives).

Poses are camera-to-world [N, 3, 4+] (any axes convention, the same for both), positions in the truth's units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from geer_ns.refinement.refined_frame import Similarity, fit_similarity


def rotation_angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[N] angles (degrees) of the rotations a_i^T b_i, a and b [N, 3, 3]: from the skew part and the trace
    together (atan2), exact to rounding at small angles where arccos of the trace alone loses half the digits."""
    rel = np.einsum("nji,njk->nik", a, b)
    skew = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1)
    return np.degrees(np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), 0.5 * (np.trace(rel, axis1=1, axis2=2) - 1.0)))


def _summary(values: np.ndarray) -> tuple[float, float, float]:
    return float(values.mean()), float(np.median(values)), float(values.max())


@dataclass(frozen=True)
class CameraErrors:
    """(mean, median, max) over the cameras: rotation (degrees) and position (% of `extent`) after the similarity
    fitted to the truth; the relative pose error of each camera to its nearest true neighbour (rotation degrees,
    translation % of `extent`, the fitted scale applied); and the fitted similarity itself (estimate -> truth)."""

    rotation_deg: tuple[float, float, float]
    position_pct: tuple[float, float, float]
    relative_rotation_deg: tuple[float, float, float]
    relative_position_pct: tuple[float, float, float]
    gauge: Similarity


def camera_errors(estimate: np.ndarray, truth: np.ndarray, extent: float) -> CameraErrors:
    """The estimated cameras' errors against the truth (module docstring). estimate, truth [N, 3, 4+]
    camera-to-worlds of the same N >= 2 cameras; extent, the scene's size in the truth's units."""
    estimate, truth = np.asarray(estimate, np.float64)[:, :3, :4], np.asarray(truth, np.float64)[:, :3, :4]
    if estimate.shape[0] != truth.shape[0] or estimate.shape[0] < 2:
        raise ValueError(f"camera_errors: expected the same N >= 2 cameras, got {estimate.shape[0]} and {truth.shape[0]}")
    gauge = fit_similarity(torch.from_numpy(estimate), torch.from_numpy(truth), guard_scale=False)
    aligned = gauge.apply(torch.from_numpy(estimate)).numpy()
    rot = rotation_angles_deg(aligned[:, :3, :3], truth[:, :3, :3])
    pos = 100.0 * np.linalg.norm(aligned[:, :3, 3] - truth[:, :3, 3], axis=-1) / extent
    # Each camera against its nearest neighbour in the truth: gauge-free (relative motions), scale from the fit.
    centres = truth[:, :3, 3]
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    j = dist.argmin(1)

    def relative(c2w: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
        r = np.einsum("nji,njk->nik", c2w[:, :3, :3], c2w[j, :3, :3])  # R_i^T R_j
        t = np.einsum("nji,nj->ni", c2w[:, :3, :3], scale * (c2w[j, :3, 3] - c2w[:, :3, 3]))  # in camera i's frame
        return r, t

    r_est, t_est = relative(estimate, gauge.scale)
    r_true, t_true = relative(truth, 1.0)
    rel_rot = rotation_angles_deg(r_est, r_true)
    rel_pos = 100.0 * np.linalg.norm(t_est - t_true, axis=-1) / extent
    return CameraErrors(_summary(rot), _summary(pos), _summary(rel_rot), _summary(rel_pos), gauge)
