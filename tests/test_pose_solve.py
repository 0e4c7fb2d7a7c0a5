"""The Levenberg-Marquardt pose solve (geer_ns/refinement/pose_solve.py): the solver on least-squares problems of known
minimum, and the solve of a geer model's training poses (and of a held-out view's pose) against images rendered
at ground-truth poses."""

from __future__ import annotations

import math

import pytest
import torch

from geer_ns.refinement.pose_solve import adjusted_camera, coarse_to_fine, levenberg_marquardt, solve_poses, solve_view_pose

F64 = torch.float64


def test_solver_finds_the_rosenbrock_minimum_from_the_classic_start():
    """Rosenbrock's residuals (10 (y - x^2), 1 - x): minimum 0 at (1, 1), a curved valley from (-1.2, 1)."""
    def residual(p):
        return torch.stack([10.0 * (p[1] - p[0] ** 2), 1.0 - p[0]])

    x, start, cost = levenberg_marquardt(residual, torch.tensor([-1.2, 1.0], dtype=F64),
                                         torch.full((2,), 1e-6, dtype=F64), iterations=60)
    assert start == pytest.approx(24.2)
    assert cost < 1e-16
    assert torch.allclose(x, torch.tensor([1.0, 1.0], dtype=F64), atol=1e-8)


def test_solver_never_raises_the_cost_and_stops_at_a_minimum():
    """Started at the minimum of an exponential fit (noise-free data of a = 2, b = 0.5), no step lowers the
    cost: x stays where it was. Started away from it, each extra iteration ends at a cost no higher."""
    t = torch.linspace(0.0, 4.0, 30, dtype=F64)
    data = 2.0 * torch.exp(-0.5 * t) + 0.01 * torch.sin(7.0 * t)  # not exactly the model: cost > 0 at the minimum

    def residual(p):
        return p[0] * torch.exp(-p[1] * t) - data

    steps = torch.full((2,), 1e-6, dtype=F64)
    best, _, best_cost = levenberg_marquardt(residual, torch.tensor([1.0, 1.0], dtype=F64), steps, iterations=50)
    assert best_cost > 0
    again, start, cost = levenberg_marquardt(residual, best, steps, iterations=5)
    assert cost <= start and torch.allclose(again, best, atol=1e-7)
    costs = [levenberg_marquardt(residual, torch.tensor([5.0, 3.0], dtype=F64), steps, k)[2] for k in range(6)]
    assert all(b <= a for a, b in zip(costs, costs[1:]))
    assert abs(float(best[0]) - 2.0) < 0.02 and abs(float(best[1]) - 0.5) < 0.02


def test_coarse_to_fine_keeps_the_start_when_the_blurred_levels_lead_away_from_the_unblurred_minimum():
    """Blurred residuals whose minimum (x = 5) the unblurred ones fit worse than the start: x0 is kept, with
    equal costs. When the blurred minimum is the unblurred one too, the solve gets there."""
    def levels(blurred_target):
        def residual_at(blur):
            target = blurred_target if blur > 0 else 0.0
            return lambda x: torch.cat([x - target, 2.0 * (x - target)])
        return residual_at

    x0 = torch.full((6,), 0.5, dtype=F64)
    x, before, after = coarse_to_fine(levels(5.0), x0, iterations=3, blur_levels=(2.0, 1.0))
    assert torch.equal(x, x0) and before == after == pytest.approx(6 * 0.25 * (1 + 4))
    x, before, after = coarse_to_fine(levels(0.0), x0, iterations=3, blur_levels=(2.0, 0.0))
    assert after < 1e-12 * before and float(x.abs().max()) < 1e-6


def _turn(axis, degrees):
    axis = torch.tensor(axis, dtype=torch.float32)
    return axis / axis.norm() * math.radians(degrees)


@pytest.mark.parametrize("mode", ["SO3xR3", "SE3"])
def test_solve_brings_perturbed_training_poses_back_to_the_ground_truth(cpu_ops, mode):
    """Four 180-degree fisheye training images rendered from known poses; each camera's pose adjustment set to
    a 2-degree turn and a 0.06-unit move; four solve iterations put every camera within 0.02 degree and 0.002
    units of its ground-truth pose (the zero adjustment) and lower the residuals."""
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
    from test_nerfstudio_model import four_fisheye_views, make_model

    model = make_model(n=80, camera_optimizer=CameraOptimizerConfig(mode=mode), pose_solve_every=100,
                       renderer_backend="cpu")
    poses, images, views = four_fisheye_views(model)

    adjustment = model.camera_optimizer.pose_adjustment
    with torch.no_grad():
        for i, axis in enumerate([(1, 0, 0), (0, 1, 1), (1, -1, 0), (0.3, 0.2, 1)]):
            adjustment[i, 3:] = _turn(axis, 2.0)  # both tangents: translation first, rotation last
            adjustment[i, :3] = torch.tensor([0.05, -0.03, 0.0])
    summary = solve_poses(model, views, range(4), iterations=4)
    rotation = torch.rad2deg(adjustment[:, 3:].detach().double().norm(dim=-1))
    translation = adjustment[:, :3].detach().double().norm(dim=-1)
    assert float(rotation.max()) < 0.02, rotation
    assert float(translation.max()) < 2e-3, translation
    assert summary["cameras"] == 4 and summary["residual_change"] < -0.99
    assert summary["rotation_deg"] == pytest.approx(2.0, abs=0.05)
    assert model.views == []  # the solve's renders are not training views

    # a held-out view given 1.5 degrees and 0.04 units off its true pose: solved back to it
    truth = poses[2].camera_to_worlds
    given = adjusted_camera(poses[2], torch.cat([torch.tensor([0.0, 0.04, 0.0]), _turn((1, 1, 0), 1.5)]).double())
    solved = solve_view_pose(model, given, {"image": images[2]}, iterations=4).camera_to_worlds
    turn = solved[0, :3, :3] @ truth[0, :3, :3].T
    angle = math.degrees(math.acos(min(1.0, (float(torch.trace(turn)) - 1) / 2)))
    assert angle < 0.02 and float((solved[0, :3, 3] - truth[0, :3, 3]).norm()) < 2e-3
    assert model.training  # the solve restores the mode it found


def test_pose_solve_without_pose_refinement_is_refused():
    from test_nerfstudio_model import make_model

    with pytest.raises(ValueError, match="pose-solve-every: needs --pipeline.model.camera-optimizer.mode"):
        make_model(pose_solve_every=100)


def test_adjusted_camera_moves_as_nerfstudios_camera_optimizer():
    """solve_view_pose's composition is nerfstudio 1.1.5's CameraOptimizer.apply_to_camera (SO3xR3)."""
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
    from test_nerfstudio_model import fisheye_camera

    c2w = torch.tensor([[0.0, -1.0, 0.0, 0.3], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, 1.0, 1.5]])
    camera = fisheye_camera(16, c2w)
    camera.metadata = {**camera.metadata, "cam_idx": 0}
    x = torch.tensor([0.02, -0.05, 0.01, 0.03, -0.01, 0.02], dtype=F64)
    optimizer = CameraOptimizerConfig(mode="SO3xR3").setup(num_cameras=1, device="cpu")
    with torch.no_grad():
        optimizer.pose_adjustment[0] = x.float()
    expected = optimizer.apply_to_camera(camera)
    assert torch.allclose(adjusted_camera(camera, x).camera_to_worlds, expected, atol=1e-6)


def test_blurred_is_the_identity_at_zero_and_a_normalised_gaussian_inside_the_mask():
    from geer_ns.refinement.pose_solve import blurred

    image = torch.zeros(31, 31, 1, dtype=F64)  # a delta far enough from the edges that the mask is all ones
    image[15, 15] = 1.0
    everywhere = torch.ones(31, 31, 1, dtype=torch.bool)
    assert torch.equal(blurred(image, everywhere, 0.0), image)
    out = blurred(image, everywhere, 1.5)[..., 0]
    i = torch.arange(31, dtype=F64) - 15
    gauss = torch.exp(-0.5 * (i / 1.5) ** 2) * (i.abs() <= 5)  # the kernel's radius: ceil(3 sigma) = 5
    gauss = gauss / gauss.sum()
    assert torch.allclose(out, gauss[:, None] * gauss[None, :], atol=1e-12)
    constant = torch.full((31, 31, 1), 0.25, dtype=F64)  # a constant stays constant up to the mask's edge
    half = everywhere.clone()
    half[:, 16:] = False
    assert torch.allclose(blurred(constant, half, 2.0)[:, :16], constant[:, :16], atol=1e-12)


def test_solver_survives_a_coordinate_the_residuals_ignore():
    """A residual that does not depend on x[1] (a camera whose image one adjustment cannot change): no singular
    system, x[1] stays, x[0] goes to its minimum."""
    def residual(p):
        return torch.stack([p[0] - 3.0, torch.zeros((), dtype=F64) * p[1]])

    x, _, cost = levenberg_marquardt(residual, torch.tensor([0.0, 0.5], dtype=F64), torch.full((2,), 1e-4, dtype=F64),
                                     iterations=5)
    assert cost < 1e-12 and float(x[1]) == 0.5


@pytest.mark.parametrize("start, solved_at", [(0, [50, 100, 150]), (100, [100, 150])])
def test_the_callback_solves_at_multiples_of_every_and_resets_the_momentum(monkeypatch, start, solved_at):
    from types import SimpleNamespace

    import geer_ns.refinement.pose_solve as pose_solve

    calls, steps = [], []
    monkeypatch.setattr(pose_solve, "solve_poses", lambda model, dm, indices, iterations: calls.append(
        (list(indices), iterations)) or {"cameras": 3, "rotation_deg": 0.0, "translation": 0.0, "residual_change": 0.0})
    adjustment = torch.nn.Parameter(torch.zeros(3, 6))
    adam = torch.optim.Adam([adjustment], lr=1e-3)
    adjustment.grad = torch.ones(3, 6)
    adam.step()
    model = SimpleNamespace(camera_optimizer=SimpleNamespace(pose_adjustment=adjustment),
                            config=SimpleNamespace(pose_refinement_start=start))
    solver = pose_solve.PoseSolver(SimpleNamespace(model=model, datamanager=None),
                                   SimpleNamespace(optimizers={"camera_opt": adam}), every=50, iterations=2,
                                   say=lambda line: None)
    for step in range(0, 160):
        solver(step)
        steps += [step] * (len(calls) - len(steps))
    assert calls == [([0, 1, 2], 2)] * len(solved_at) and steps == solved_at  # never step 0 nor before the start
    state = adam.state[adjustment]
    assert float(state["exp_avg"].abs().max()) == 0 and float(state["exp_avg_sq"].min()) > 0


def test_invalid_pose_solve_options_are_refused():
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
    from test_nerfstudio_model import make_model

    with pytest.raises(ValueError, match="pose-solve-iterations"):
        make_model(camera_optimizer=CameraOptimizerConfig(mode="SO3xR3"), pose_solve_every=10, pose_solve_iterations=0)


@pytest.mark.parametrize("mode, start", [("SO3xR3", -1), ("off", 100)])
def test_invalid_pose_refinement_start_is_refused(mode, start):
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
    from test_nerfstudio_model import make_model

    with pytest.raises(ValueError, match="pose-refinement-start"):
        make_model(camera_optimizer=CameraOptimizerConfig(mode=mode), pose_refinement_start=start)
