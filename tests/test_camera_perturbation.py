"""Perturbed cameras beside their truth (geer_ns/data/camera_perturbation.py)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
from conftest import copy_room

from geer_ns.data.camera_perturbation import TRUTH_NAME, perturb_cameras, pose_errors


def test_training_cameras_move_by_the_asked_amounts_and_the_truth_is_kept(tmp_path):
    src = copy_room(tmp_path / "room", 5, n_eval=1)
    truth = perturb_cameras(src, tmp_path / "noisy", rotation_deg=1.0, position_fraction=0.01, focal_fraction=0.02,
                            k1_offset=0.02)
    meta = json.loads((tmp_path / "noisy" / "transforms.json").read_text())
    original = json.loads((src / "transforms.json").read_text())
    assert json.loads((tmp_path / "noisy" / TRUTH_NAME).read_text()) == truth
    assert math.isclose(meta["fl_x"], original["fl_x"] * 1.02) and math.isclose(meta["k1"], original["k1"] + 0.02)
    for frame in meta["frames"]:
        c2w, true = np.asarray(frame["transform_matrix"]), np.asarray(truth["frames"][frame["file_path"]])
        angle = np.degrees(np.linalg.norm(cv2.Rodrigues(c2w[:3, :3] @ true[:3, :3].T)[0]))  # OpenCV's, independent
        shift = np.linalg.norm(c2w[:3, 3] - true[:3, 3]) / truth["extent"]
        if frame["file_path"] in meta["test_filenames"]:
            assert angle < 1e-9 and shift == 0
        else:
            assert math.isclose(angle, 1.0, rel_tol=1e-6) and math.isclose(shift, 0.01, rel_tol=1e-9)
        rot, pos = pose_errors(c2w[None], true[None])
        assert math.isclose(float(rot[0]), angle, abs_tol=1e-6)
        assert math.isclose(float(pos[0]), shift * truth["extent"], rel_tol=1e-9)


def test_rotation_errors_are_exact_for_small_turns_of_float32_rotations():
    """Turns of 0.001-120 degrees against OpenCV's Rodrigues, and float32-rounded rotations (not quite orthogonal)
    read as no turn: the errors a refined run's poses are scored by sit at hundredths of a degree."""
    rng = np.random.default_rng(1)
    for degrees in (0.001, 0.01, 0.1, 1.0, 120.0):
        base = cv2.Rodrigues(rng.normal(size=3))[0]
        axis = rng.normal(size=3)
        turn = cv2.Rodrigues(axis / np.linalg.norm(axis) * math.radians(degrees))[0]
        a, b = np.zeros((1, 3, 4)), np.zeros((1, 3, 4))
        a[0, :, :3], b[0, :, :3] = turn @ base, base
        assert math.isclose(float(pose_errors(a, b)[0][0]), degrees, rel_tol=1e-6)
    rotations = np.stack([cv2.Rodrigues(rng.normal(size=3))[0] for _ in range(50)])
    poses = np.concatenate([rotations, np.zeros((50, 3, 1))], -1)
    rounded = poses.astype(np.float32).astype(np.float64)
    assert float(pose_errors(rounded, poses)[0].max()) < 1e-4
