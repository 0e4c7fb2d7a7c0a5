"""The refined frame (geer_ns/refinement/refined_frame.py): the similarity fit on poses moved by a known one, its
degenerate cases, and a whole pipeline whose scene and training cameras drifted together by a rigid motion (the
gauge no image sees): ns-eval's test view then scores as before the drift, and the exported refined poses are the
given ones."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import copy_room, tiny_trainer_config
from geer_ns.refinement.refined_frame import RefinedFrame, fit_similarity

F64 = torch.float64


def _rotation(axis, degrees) -> torch.Tensor:
    """Rodrigues' rotation matrix (float64)."""
    k = torch.tensor(axis, dtype=F64)
    k = k / k.norm()
    cross = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=F64)
    a = math.radians(degrees)
    return torch.eye(3, dtype=F64) + math.sin(a) * cross + (1 - math.cos(a)) * cross @ cross


def _random_poses(n: int, seed: int) -> torch.Tensor:
    """[n, 3, 4] camera-to-worlds: rotations exp of random skew matrices, centres normal."""
    gen = torch.Generator().manual_seed(seed)
    v = 2.0 * torch.randn(n, 3, generator=gen, dtype=F64)
    zero = torch.zeros(n, dtype=F64)
    skew = torch.stack([torch.stack([zero, -v[:, 2], v[:, 1]], -1), torch.stack([v[:, 2], zero, -v[:, 0]], -1),
                        torch.stack([-v[:, 1], v[:, 0], zero], -1)], -2)
    return torch.cat([torch.linalg.matrix_exp(skew), torch.randn(n, 3, 1, generator=gen, dtype=F64)], dim=-1)


def _moved(poses: torch.Tensor, rot: torch.Tensor, shift: torch.Tensor, scale: float) -> torch.Tensor:
    return torch.cat([rot @ poses[:, :3, :3], scale * rot @ poses[:, :3, 3:] + shift[:, None]], dim=-1)


def test_the_fit_recovers_a_known_similarity_and_its_inverse_undoes_it():
    given = _random_poses(12, 0)
    rot, shift, scale = _rotation((0.3, -1.0, 0.5), 3.0), torch.tensor([0.2, -0.1, 0.05], dtype=F64), 1.03
    fitted = fit_similarity(given, _moved(given, rot, shift, scale))
    assert torch.allclose(fitted.rotation, rot, atol=1e-12)
    assert torch.allclose(fitted.translation, shift, atol=1e-12)
    assert fitted.scale == pytest.approx(scale, rel=1e-12)
    assert torch.allclose(fitted.inverse().apply(fitted.apply(given)), given, atol=1e-12)
    assert fitted.apply(given.float()).dtype == torch.float32


def test_noisy_cameras_average_out_in_the_fit():
    """Each of 400 cameras moved by the similarity and then on its own by 1 degree about a random axis and 0.05
    units: the fit's rotation is within a tenth of a degree, its scale and translation within 1 %."""
    given = _random_poses(400, 1)
    rot, shift, scale = _rotation((1.0, 0.0, 1.0), 2.0), torch.tensor([0.5, 0.0, -0.3], dtype=F64), 0.97
    moved = _moved(given, rot, shift, scale)
    gen = torch.Generator().manual_seed(2)
    for i in range(len(moved)):
        moved[i, :3, :3] = _rotation(torch.randn(3, generator=gen, dtype=F64).tolist(), 1.0) @ moved[i, :3, :3]
    moved[:, :3, 3] += 0.05 * torch.nn.functional.normalize(torch.randn(len(moved), 3, generator=gen, dtype=F64), dim=-1)
    fitted = fit_similarity(given, moved)
    turn = fitted.rotation @ rot.T
    assert math.degrees(math.acos(min(1.0, (float(torch.trace(turn)) - 1) / 2))) < 0.1
    assert fitted.scale == pytest.approx(scale, rel=1e-2)
    assert float((fitted.translation - shift).norm()) < 1e-2


@pytest.mark.parametrize("n,spread", [(1, 0.0), (5, 0.0), (5, 1e-3)])
def test_cameras_that_do_not_spread_beyond_their_moves_keep_the_scale(n, spread):
    """One camera, five at one place (a rotation-only capture), five within a millimetre whose centres moved by
    a centimetre each: the centres carry no scale (1), and the rotation is the cameras' turn."""
    given = _random_poses(n, 3)
    gen = torch.Generator().manual_seed(4)
    given[:, :3, 3] = torch.tensor([0.4, -0.2, 0.1], dtype=F64) + spread * torch.randn(n, 3, generator=gen, dtype=F64)
    rot, shift = _rotation((0.0, 1.0, 0.0), 5.0), torch.tensor([0.0, 0.1, 0.0], dtype=F64)
    moved = _moved(given, rot, shift, 1.0)
    if spread:
        moved[:, :3, 3] += 0.01 * torch.randn(n, 3, generator=gen, dtype=F64)
    fitted = fit_similarity(given, moved)
    assert fitted.scale == 1.0
    assert torch.allclose(fitted.rotation, rot, atol=1e-12)
    if not spread:
        assert torch.allclose(fitted.apply(given), moved, atol=1e-12)


def _rigid_drift(pipeline, rot: torch.Tensor, shift: torch.Tensor) -> None:
    """Move the scene (means, orientations) and every training camera's SO3xR3 adjustment by x -> rot x + shift:
    what a run's scene and cameras do together when they drift (nerfstudio's composition: rotation in world
    axes, translation added)."""
    from nerfstudio.cameras.lie_groups import exp_map_SO3xR3

    model = pipeline.model
    given = pipeline.datamanager.train_dataset.cameras.camera_to_worlds.double()
    log = _rot_log(rot)
    with torch.no_grad():
        params = model.gauss_params
        params["means"].copy_((params["means"].double() @ rot.T + shift).float())
        w, x, y, z = _quaternion(rot)
        a = params["quats"].double()  # (w, x, y, z): the rotation's quaternion times each Gaussian's
        params["quats"].copy_(torch.stack([
            w * a[:, 0] - x * a[:, 1] - y * a[:, 2] - z * a[:, 3],
            w * a[:, 1] + x * a[:, 0] + y * a[:, 3] - z * a[:, 2],
            w * a[:, 2] - x * a[:, 3] + y * a[:, 0] + z * a[:, 1],
            w * a[:, 3] + x * a[:, 2] - y * a[:, 1] + z * a[:, 0]], dim=-1).float())
        adjustment = model.camera_optimizer.pose_adjustment
        centres = given[:, :3, 3]
        adjustment[:, :3] = (centres @ rot.T + shift - centres).float()
        adjustment[:, 3:] = log.float()
        check = exp_map_SO3xR3(adjustment[:1]).double()[0, :3, :3]
    assert torch.allclose(check, rot, atol=1e-6)


def _rot_log(rot: torch.Tensor) -> torch.Tensor:
    angle = math.acos((float(torch.trace(rot)) - 1) / 2)
    axis = torch.tensor([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]], dtype=F64)
    return axis / (2 * math.sin(angle)) * angle


def _quaternion(rot: torch.Tensor):
    w = math.sqrt(1.0 + float(torch.trace(rot))) / 2
    return (w, float(rot[2, 1] - rot[1, 2]) / (4 * w), float(rot[0, 2] - rot[2, 0]) / (4 * w),
            float(rot[1, 0] - rot[0, 1]) / (4 * w))


@pytest.fixture(scope="module")
def drifted(tmp_path_factory):
    """A pipeline of the embedded room (3 training images, 1 test) with SO3xR3, its test view's PSNR before any
    drift, then the scene and training cameras drifted together by 2 degrees and 0.05 units."""
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig

    root = tmp_path_factory.mktemp("refined_frame")
    data = copy_room(root / "data", 4, n_eval=1)
    config = tiny_trainer_config(data, root / "out", "frame", 1)
    config.pipeline.model.camera_optimizer = CameraOptimizerConfig(mode="SO3xR3")
    pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    camera, batch = next(iter(pipeline.datamanager.fixed_indices_eval_dataloader))
    pipeline.eval()
    with torch.no_grad():
        before = pipeline.model.get_outputs_for_camera(camera)["rgb"].clone()
    _rigid_drift(pipeline, _rotation((0.2, 1.0, -0.4), 2.0), torch.tensor([0.05, -0.02, 0.03], dtype=F64))
    return pipeline, camera, before


def test_a_test_view_renders_as_before_the_scene_and_cameras_drifted_together(drifted):
    pipeline, camera, before = drifted
    model = pipeline.model
    assert isinstance(model.refined_frame, RefinedFrame)
    with torch.no_grad():
        after = model.get_outputs_for_camera(camera)["rgb"]
        frame, model.refined_frame = model.refined_frame, None
        try:
            as_given = model.get_outputs_for_camera(camera)["rgb"]
        finally:
            model.refined_frame = frame
    assert float((after - before).abs().max()) < 2e-3  # float32 means and poses
    assert float((as_given - before).abs().mean()) > 20 * float((after - before).abs().mean())


def test_the_exported_refined_poses_are_the_given_ones_when_only_the_gauge_moved(drifted):
    from geer_ns.refinement.refined_cameras import refined_poses
    from geer_ns.refinement.refined_frame import adjusted_poses

    pipeline = drifted[0]
    given = pipeline.datamanager.train_dataset.cameras.camera_to_worlds.double()
    assert float((adjusted_poses(pipeline.model.camera_optimizer, given) - given).abs().max()) > 0.01
    assert torch.allclose(refined_poses(pipeline), given, atol=1e-6)


def test_the_similarity_is_refitted_when_the_corrections_change_and_only_then(drifted):
    model = drifted[0].model
    frame, optimizer = model.refined_frame, model.camera_optimizer
    first = frame.similarity(optimizer)
    assert frame.similarity(optimizer) is first  # the viewer's frames between two steps reuse it
    adjustment = optimizer.pose_adjustment
    saved = adjustment.detach().clone()
    try:
        with torch.no_grad():
            adjustment[:, :3] += torch.tensor([0.1, 0.0, 0.0])  # an optimizer step writes in place
        moved = frame.similarity(optimizer)
        assert float((moved.translation - first.translation - torch.tensor([0.1, 0.0, 0.0], dtype=F64)).abs().max()) \
            < 1e-5
    finally:
        with torch.no_grad():
            adjustment.copy_(saved)
    assert torch.allclose(frame.similarity(optimizer).translation, first.translation)


def test_the_option_off_renders_cameras_as_given(tmp_path):
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig

    data = copy_room(tmp_path / "data", 2, n_eval=1)
    config = tiny_trainer_config(data, tmp_path / "out", "given", 1)
    config.pipeline.model.camera_optimizer = CameraOptimizerConfig(mode="SO3xR3")
    config.pipeline.model.refined_frame = False
    assert config.pipeline.setup(device="cpu", test_mode="val").model.refined_frame is None
