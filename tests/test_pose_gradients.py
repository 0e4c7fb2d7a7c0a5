"""Camera pose gradients from the compiled backend (the CPU build of csrc/, the CUDA kernels' code).

The world-to-camera transform reaches the image three ways: the view-space means (autograd through
transforms.view_transform), the rotated covariances (the preprocess backward's dL/dR_c, csrc/geer_math.h
preprocess_backward_gaussian) and the SH view directions (autograd through transforms.camera_offsets). Checked
against the PyTorch renderer's autograd and against float64 central differences of a 6-dof pose perturbation,
on a BEAP grid, a 200-degree fisheye, a 360-degree equirectangular camera and a camera inside a Gaussian.
"""

from __future__ import annotations

import copy
import math
import warnings

import pytest
import torch
from conftest import equidistant_fisheye_rays, equirect_rays, random_scene, random_viewmat, stress_gaussians

from geer_ns.render import RayGrid, render
from geer_ns.render.backend import resolve_backend

F64 = torch.float64


@pytest.fixture(scope="module")
def ops(cpu_ops, single_thread):
    return cpu_ops


def _case(name: str):
    """(grid, [means, quats, scales, opacities, colours] in world space, viewmat) of one test camera."""
    gen = torch.Generator().manual_seed(7)
    if name == "beap":
        grid = RayGrid.beap(32, 24, math.radians(100), math.radians(80), tile_size=8, dtype=F64)
        means_c, quats, scales, opac, colors = random_scene(60, 5, spread=0.8)
    elif name == "inside":  # stress_gaussians' third one holds the camera; the rest all around it
        fd, fv = equidistant_fisheye_rays(32, 200.0)
        grid = RayGrid.from_rays(fd, fv, tile_size=8)
        m1, q1, s1, o1 = stress_gaussians()
        m2, q2, s2, o2, _ = random_scene(40, 3, around=True)
        means_c, quats, scales, opac = (torch.cat(p) for p in ((m1, m2), (q1, q2), (s1, s2), (o1, o2)))
        colors = torch.rand(means_c.shape[0], 3, generator=gen, dtype=F64)
    else:
        if name == "fisheye200":
            fd, fv = equidistant_fisheye_rays(32, 200.0)
            grid = RayGrid.from_rays(fd, fv, tile_size=8)
        else:
            grid = RayGrid.from_rays(equirect_rays(40, 20), None, tile_size=8)
        means_c, quats, scales, opac, colors = random_scene(60, 5, around=True, spread=0.8)
    viewmat = random_viewmat(4, translation_scale=0.3)
    rot, t = viewmat[:3, :3], viewmat[:3, 3]
    return grid, [(means_c - t) @ rot, quats, scales, opac, colors], viewmat


def _sh(n: int) -> torch.Tensor:
    return torch.randn(n, 16, 3, generator=torch.Generator().manual_seed(1), dtype=F64) * 0.4


def _loss_map(out) -> torch.Tensor:
    """Per-pixel loss [H, W] against fixed random targets: colour, expected depth and accumulation."""
    gen = torch.Generator().manual_seed(0)
    h, w = out.rgb.shape[:2]
    tr, td, ta = (torch.rand(h, w, c, generator=gen, dtype=F64).to(out.rgb.dtype) for c in (3, 1, 1))
    return (((out.rgb - tr) ** 2).sum(-1) + 0.1 * ((out.depth - 3 * td) ** 2)[..., 0]
            + ((out.accumulation - ta) ** 2)[..., 0])


def with_dirs(grid, dirs):
    """The grid with its rays' directions replaced (the cull's bounds stay those of the grid's own rays)."""
    out = copy.copy(grid)
    out.dirs = dirs
    return out


def _twist(xi: torch.Tensor) -> torch.Tensor:
    """exp of the se(3) twist xi = (omega, v) [6] as a 4 x 4 matrix (left-multiplied onto a world-to-camera)."""
    wx, wy, wz = xi[0], xi[1], xi[2]
    zero = xi.new_zeros(())
    a = torch.stack([
        torch.stack([zero, -wz, wy, xi[3]]),
        torch.stack([wz, zero, -wx, xi[4]]),
        torch.stack([-wy, wx, zero, xi[5]]),
        torch.stack([zero, zero, zero, zero]),
    ])
    return torch.linalg.matrix_exp(a)


def _pose_loss(scene, viewmat0, grid, backend, xi, degree, mask=None):
    out = render(*scene, _twist(xi) @ viewmat0, grid, backend=backend, sh_degree=degree,
                 background=torch.tensor([0.2, 0.3, 0.4], dtype=F64))
    loss = _loss_map(out)
    return loss.sum() if mask is None else loss[mask].sum()


def _pose_grad(scene, viewmat0, grid, backend, degree, mask=None):
    xi = torch.zeros(6, dtype=F64, requires_grad=True)
    _pose_loss(scene, viewmat0, grid, backend, xi, degree, mask).backward()
    return xi.grad


CASES = ["beap", "fisheye200", "equirect360", "inside"]


def backends_agree(gradient, name: str, degree) -> torch.Tensor:
    """gradient(scene, viewmat, grid, backend, degree) of the CPU build and of the PyTorch renderer on case `name`
    agree to 1e-8 (float64); returns the CPU build's."""
    grid, scene, viewmat = _case(name)
    if degree is not None:
        scene[4] = _sh(scene[0].shape[0])
    ours = gradient(scene, viewmat, grid, "cpu", degree)
    ref = gradient(scene, viewmat, grid, "torch", degree)
    assert float(ref.norm()) > 0 and torch.isfinite(ours).all()
    assert float((ours - ref).norm() / ref.norm()) <= 1e-8, (ours, ref)
    return ours


@pytest.mark.parametrize("degree", [None, 3])
@pytest.mark.parametrize("name", CASES)
def test_pose_gradient_matches_the_pytorch_renderer(ops, name, degree):
    backends_agree(_pose_grad, name, degree)


@pytest.mark.parametrize("name", CASES)
def test_pose_gradient_matches_finite_differences(ops, name):
    """Central differences of the float64 CPU build along each of the 6 pose directions. A pixel whose pair
    crosses the 1/255 skip inside the step jumps (the renderer is piecewise smooth): such pixels, found by their
    second difference, are left out of both sides; they must be rare."""
    grid, scene, viewmat = _case(name)
    scene[4] = _sh(scene[0].shape[0])
    h = 1e-6
    maps = []
    with torch.no_grad():
        at = _loss_map(render(*scene, viewmat, grid, backend="cpu", sh_degree=3,
                              background=torch.tensor([0.2, 0.3, 0.4], dtype=F64)))
        for k in range(6):
            step = torch.zeros(6, dtype=F64)
            step[k] = h
            maps.append([_loss_map(render(*scene, _twist(sign * step) @ viewmat, grid, backend="cpu", sh_degree=3,
                                          background=torch.tensor([0.2, 0.3, 0.4], dtype=F64)))
                         for sign in (1.0, -1.0)])
    smooth = torch.ones_like(at, dtype=torch.bool)
    for plus, minus in maps:
        smooth &= (plus - 2 * at + minus).abs() <= 1e-8
    assert float((~smooth).float().mean()) <= 0.01
    fd = torch.stack([(plus - minus)[smooth].sum() / (2 * h) for plus, minus in maps])
    ours = _pose_grad(scene, viewmat, grid, "cpu", 3, smooth)
    assert float((ours - fd).norm() / fd.norm()) <= 1e-5, (ours, fd)


def test_auto_keeps_the_compiled_backend_for_pose_gradients(ops):
    """No fallback and no warning: auto renders a pose that requires grad with the CPU build, in float32 too."""
    grid, scene, viewmat = _case("beap")
    scene = [t.float() for t in scene]
    viewmat = viewmat.float().requires_grad_(True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert resolve_backend("auto", torch.device("cpu")) == "cpu"
        out = render(*scene, viewmat, grid.to(torch.device("cpu")), backend="auto")
    out.rgb.square().sum().backward()
    ref_vm = viewmat.detach().clone().requires_grad_(True)
    render(*scene, ref_vm, grid, backend="torch").rgb.square().sum().backward()
    assert torch.isfinite(viewmat.grad).all()
    assert float((viewmat.grad - ref_vm.grad).norm() / ref_vm.grad.norm()) <= 1e-4


@pytest.mark.parametrize("kind", ["beap", "native"])
def test_model_refines_poses_through_the_cpu_build(ops, kind):
    """nerfstudio's SO3xR3 camera optimizer inside geer's model: its parameters get the compiled backend's
    gradient (the PyTorch renderer's, to float32 rounding), and auto says nothing about a fallback."""
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
    from test_nerfstudio_model import fisheye_camera, make_model

    grads = {}
    for backend in ("cpu", "torch"):
        torch.manual_seed(0)
        model = make_model(n=60, camera_optimizer=CameraOptimizerConfig(mode="SO3xR3"), renderer_backend=backend)
        model.train()
        with torch.no_grad():
            model.camera_optimizer.pose_adjustment[1] = torch.tensor([0.01, -0.02, 0.01, 0.002, 0.003, -0.001])
        camera = fisheye_camera(32, kind=kind)
        camera.metadata["cam_idx"] = 1
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            rgb = model.get_outputs(camera)["rgb"]
        ((rgb - 0.5) ** 2).mean().backward()
        grads[backend] = model.camera_optimizer.pose_adjustment.grad.clone()
    assert float(grads["torch"][1].norm()) > 0 and float(grads["torch"][[0, 2, 3]].abs().max()) == 0
    assert float((grads["cpu"] - grads["torch"]).norm() / grads["torch"].norm()) <= 1e-3


def test_poses_are_neither_rendered_nor_trained_before_pose_refinement_start(ops):
    """Before --pipeline.model.pose-refinement-start a training render uses the given pose and leaves the pose
    adjustments without a gradient (no regularizer either); from that step on it renders and trains them."""
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
    from test_nerfstudio_model import fisheye_camera, make_model

    torch.manual_seed(0)
    model = make_model(n=60, camera_optimizer=CameraOptimizerConfig(mode="SO3xR3"), pose_refinement_start=5)
    model.train()
    adjustment = model.camera_optimizer.pose_adjustment
    camera = fisheye_camera(32)
    camera.metadata["cam_idx"] = 1
    with torch.no_grad():
        given = model.get_outputs(camera)["rgb"].clone()  # no adjustment yet: the given pose
        adjustment[1] = torch.tensor([0.05, -0.02, 0.01, 0.02, 0.03, -0.01])
    rgbs = {}
    for step in (4, 5):
        model.step, adjustment.grad = step, None
        rgbs[step] = model.get_outputs(camera)["rgb"]
        loss = ((rgbs[step] - 0.5) ** 2).mean() + sum(model.get_step_loss_dict().values())
        loss.backward()
        assert (adjustment.grad is None) == (step == 4)
    assert torch.equal(rgbs[4].detach(), given)
    assert float((rgbs[5].detach() - given).abs().max()) > 0.01
    assert float(adjustment.grad[1].norm()) > 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (the kernels' pose and ray gradients)")
@pytest.mark.parametrize("name", CASES)
def test_cuda_kernels_give_pose_and_ray_gradients(name):
    """The CUDA kernels' pose and ray-direction gradients against the PyTorch renderer's, on the GPU (float64)."""
    grid, scene, viewmat = _case(name)
    scene = [t.cuda() for t in scene[:4]] + [_sh(scene[0].shape[0]).cuda()]
    viewmat, grid = viewmat.cuda(), grid.to("cuda")
    found = {}
    for backend in ("cuda", "torch"):
        xi = torch.zeros(6, dtype=F64, device="cuda", requires_grad=True)
        dirs = grid.dirs.detach().clone().requires_grad_(True)
        out = render(*scene, _twist(xi) @ viewmat, with_dirs(grid, dirs), backend=backend, sh_degree=3)
        _loss_map(out).sum().backward()
        found[backend] = (xi.grad, dirs.grad)
    for ours, ref in zip(found["cuda"], found["torch"]):
        assert float((ours - ref).norm() / ref.norm()) <= 1e-8
