"""A copy of a nerfstudio-format dataset with noisy training poses and a perturbed lens, the truth beside it.

Every training frame's camera is turned by `rotation_deg` about a random axis through its center and moved by
`position_fraction` of the scene's extent (the diagonal of the seed points' bounding box) in a random
direction; frames in val_filenames / test_filenames keep their true pose (they score the scene). The lens
(top-level intrinsics, all frames) gets its focal lengths scaled by 1 + `focal_fraction` and k1 moved by
`k1_offset`. cameras_truth.json holds the true camera-to-world of every frame, the true intrinsics, the extent
and the perturbation.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np

TRUTH_NAME = "cameras_truth.json"


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: the rotation by `angle` radians about the unit `axis`."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def scene_extent(root: Path, meta: dict) -> float:
    """Diagonal of the bounding box of the dataset's seed points (ply_file_path), else of the camera centers."""
    from geer_ns.data.ply import read_ply_points

    if "ply_file_path" in meta:
        xyz, _ = read_ply_points(root / meta["ply_file_path"])
        points = np.asarray(xyz, dtype=np.float64)
    else:
        points = np.array([np.asarray(f["transform_matrix"])[:3, 3] for f in meta["frames"]])
    return float(np.linalg.norm(points.max(0) - points.min(0)))


def perturb_cameras(src: Path, out: Path, transforms: str = "transforms.json", rotation_deg: float = 1.0,
                    position_fraction: float = 0.01, focal_fraction: float = 0.0, k1_offset: float = 0.0,
                    seed: int = 0) -> dict:
    """Write the perturbed copy of src to out; returns the truth written to out/cameras_truth.json."""
    if out.exists():
        raise FileExistsError(f"{out}: exists; the perturbed copy is written to a new folder")
    shutil.copytree(src, out)
    path = out / transforms
    meta = json.loads(path.read_text())
    extent = scene_extent(out, meta)
    held_out = set(meta.get("val_filenames", [])) | set(meta.get("test_filenames", []))
    rng = np.random.default_rng(seed)
    truth = {"extent": extent, "perturbation": {"rotation_deg": rotation_deg, "position_fraction": position_fraction,
                                                 "focal_fraction": focal_fraction, "k1_offset": k1_offset},
             "intrinsics": {k: meta[k] for k in ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4") if k in meta},
             "frames": {}}
    for frame in meta["frames"]:
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
        truth["frames"][frame["file_path"]] = c2w.tolist()
        if frame["file_path"] in held_out:
            continue
        axis, move = rng.normal(size=3), rng.normal(size=3)
        c2w = c2w.copy()
        c2w[:3, :3] = _rotation(axis / np.linalg.norm(axis), math.radians(rotation_deg)) @ c2w[:3, :3]
        c2w[:3, 3] += position_fraction * extent * move / np.linalg.norm(move)
        frame["transform_matrix"] = c2w.tolist()
    for key in ("fl_x", "fl_y"):
        if key in meta:
            meta[key] *= 1.0 + focal_fraction
    if k1_offset:
        meta["k1"] = meta.get("k1", 0.0) + k1_offset
    path.write_text(json.dumps(meta, indent=2) + "\n")
    (out / TRUTH_NAME).write_text(json.dumps(truth, indent=2) + "\n")
    return truth


def pose_errors(c2w: np.ndarray, truth: np.ndarray) -> tuple:
    """(rotation error in degrees [N], position error [N]) between camera-to-worlds [N, 3+, 4]. The angle is read
    from the relative rotation's skew part and trace together (atan2): arccos of the trace alone turns the
    non-orthogonality of float32 rotations (~1e-7) into hundredths of a degree."""
    rel = np.einsum("nji,njk->nik", c2w[:, :3, :3], truth[:, :3, :3])
    skew = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1)
    angle = np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), 0.5 * (np.trace(rel, axis1=1, axis2=2) - 1.0))
    return np.degrees(angle), np.linalg.norm(c2w[:, :3, 3] - truth[:, :3, 3], axis=-1)
