"""Camera errors against the truth (geer_ns/refinement/camera_errors.py): the gauge fitted to the truth removes
exactly a similarity and nothing else; the numbers are checked against scipy's rotations and known perturbations."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from geer_ns.refinement.camera_errors import camera_errors, rotation_angles_deg


def _path(n: int, rng: np.random.Generator, planar: bool = True) -> np.ndarray:
    """n camera-to-worlds on a nearly planar loop (like a walk through a room: z spread 5 % of x, y)."""
    angle = np.linspace(0, 2 * np.pi, n, endpoint=False)
    centres = np.stack([1.3 * np.cos(angle), 0.9 * np.sin(angle), (0.03 if planar else 0.8) * rng.normal(size=n)], -1)
    c2w = np.zeros((n, 3, 4))
    c2w[:, :, :3] = Rotation.random(n, random_state=rng.integers(1 << 30)).as_matrix()
    c2w[:, :, 3] = centres
    return c2w


def _similarity(c2w: np.ndarray, rotation: np.ndarray, scale: float, shift: np.ndarray) -> np.ndarray:
    out = c2w.copy()
    out[:, :, :3] = rotation @ c2w[:, :, :3]
    out[:, :, 3] = scale * c2w[:, :, 3] @ rotation.T + shift
    return out


def test_a_whole_scene_similarity_is_no_error_at_all():
    rng = np.random.default_rng(0)
    truth = _path(40, rng)
    turn = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    estimate = _similarity(truth, turn, 2.5, np.array([4.0, -1.0, 0.5]))
    errors = camera_errors(estimate, truth, extent=3.0)
    for summary in (errors.rotation_deg, errors.position_pct, errors.relative_rotation_deg, errors.relative_position_pct):
        assert max(summary) < 1e-9
    np.testing.assert_allclose(errors.gauge.rotation.numpy(), turn.T, atol=1e-12)
    assert errors.gauge.scale == pytest.approx(1 / 2.5, rel=1e-12)


def test_known_per_camera_turns_read_as_themselves_after_the_gauge():
    """Each camera turned by exactly 0.3 degree about a random axis, the whole in another gauge: the truth-fitted
    errors read 0.3 degree per camera (the chordal mean absorbs only the turns' tiny common part); a centre fit
    on this nearly planar path would not (see the module docstring)."""
    rng = np.random.default_rng(1)
    truth = _path(48, rng)
    axes = rng.normal(size=(48, 3))
    turns = Rotation.from_rotvec(np.radians(0.3) * axes / np.linalg.norm(axes, axis=1, keepdims=True)).as_matrix()
    noisy = truth.copy()
    noisy[:, :, :3] = turns @ truth[:, :, :3]
    turn = Rotation.from_rotvec([0.0, 0.4, 0.0]).as_matrix()
    estimate = _similarity(noisy, turn, 0.7, np.array([0.0, 2.0, 0.0]))
    errors = camera_errors(estimate, truth, extent=3.0)
    # The fitted gauge differs from the true one (turn^T) by the turns' common part, ~0.3 / sqrt(48) degree; each
    # camera's error is 0.3 degree give or take that (triangle inequality on rotation angles).
    common = rotation_angles_deg(errors.gauge.rotation.numpy()[None], turn.T[None])[0]
    assert common < 2 * 0.3 / np.sqrt(48)
    per_camera = rotation_angles_deg(errors.gauge.apply(torch.from_numpy(estimate)).numpy()[:, :, :3], truth[:, :, :3])
    assert np.all(np.abs(per_camera - 0.3) <= common + 1e-9)
    assert errors.rotation_deg[1] == pytest.approx(np.median(per_camera), abs=1e-12)
    # Only orientations were changed: the centres move only by the residual turn (at most radius x its angle).
    radius = np.linalg.norm(truth[:, :, 3] - truth[:, :, 3].mean(0), axis=1).max()
    assert errors.position_pct[2] <= 100 * 2 * radius * np.radians(common) / 3.0 + 1e-9


def test_positions_in_percent_of_the_extent_and_the_relative_error_needs_no_gauge():
    rng = np.random.default_rng(2)
    truth = _path(30, rng, planar=False)
    estimate = truth.copy()
    estimate[7, :, 3] += np.array([0.0, 0.03, 0.0])  # one camera moved by 1 % of an extent of 3
    errors = camera_errors(_similarity(estimate, np.eye(3), 1.0, np.array([5.0, 5.0, 5.0])), truth, extent=3.0)
    assert errors.position_pct[2] == pytest.approx(1.0, rel=0.05)  # the fit moves the others by ~1/30 of it
    assert errors.relative_position_pct[2] == pytest.approx(1.0, rel=2e-3)  # the fitted scale: one camera of 30 moved
    assert errors.relative_rotation_deg[2] < 1e-9


def test_rotation_angles_match_scipy_down_to_tiny_angles():
    rng = np.random.default_rng(3)
    a = Rotation.random(64, random_state=4)
    angles = np.concatenate([np.full(16, 1e-7), np.full(16, 1e-3), rng.uniform(0, np.pi - 1e-3, 32)])
    axes = rng.normal(size=(64, 3))
    delta = Rotation.from_rotvec(angles[:, None] * axes / np.linalg.norm(axes, axis=1, keepdims=True))
    b = a * delta
    got = rotation_angles_deg(a.as_matrix(), b.as_matrix())
    np.testing.assert_allclose(got, np.degrees(delta.magnitude()), rtol=1e-6, atol=1e-12)


def test_bad_input_names_what_is_wrong():
    truth = _path(5, np.random.default_rng(5))
    with pytest.raises(ValueError, match="same N >= 2"):
        camera_errors(truth[:4], truth, 1.0)
    with pytest.raises(ValueError, match="same N >= 2"):
        camera_errors(truth[:1], truth[:1], 1.0)
