"""The gradient w.r.t. each ray's direction (lens refinement: rays are the camera model), from the CPU build of
the kernels (csrc/geer_ray.h ray_backward_step's kDirGrad) and from the PyTorch renderer (blend.py), against
each other and against float64 central differences, on the grids of tests/test_pose_gradients.py."""

from __future__ import annotations

import pytest
import torch
from test_pose_gradients import CASES, _case, _loss_map, _sh, backends_agree, with_dirs

from geer_ns.render import render

F64 = torch.float64
BG = (0.2, 0.3, 0.4)


@pytest.fixture(scope="module")
def ops(cpu_ops, single_thread):
    return cpu_ops


def _dir_grad(scene, viewmat, grid, backend, degree):
    dirs = grid.dirs.detach().clone().requires_grad_(True)
    out = render(*scene, viewmat, with_dirs(grid, dirs), backend=backend, sh_degree=degree,
                 background=torch.tensor(BG, dtype=F64))
    _loss_map(out).sum().backward()
    return dirs.grad


@pytest.mark.parametrize("degree", [None, 3])
@pytest.mark.parametrize("name", CASES)
def test_ray_direction_gradient_matches_the_pytorch_renderer(ops, name, degree):
    ours = backends_agree(_dir_grad, name, degree)
    assert bool((ours[~_case(name)[0].valid] == 0).all())  # invalid rays get none


@pytest.mark.parametrize("name", CASES)
def test_ray_direction_gradient_matches_finite_differences(ops, name):
    """Central differences of the float64 CPU build: every ray moved at once along a random field of directions
    (each ray's loss depends on its own direction only, so one directional derivative checks them all), and
    per ray for a handful of rays. Rays whose pairs cross the 1/255 skip inside the step are left out."""
    grid, scene, viewmat = _case(name)
    scene[4] = _sh(scene[0].shape[0])
    ours = _dir_grad(scene, viewmat, grid, "cpu", 3)
    gen = torch.Generator().manual_seed(3)
    field = torch.randn(grid.dirs.shape, generator=gen, dtype=F64)
    h = 1e-6

    def loss_map(dirs):
        with torch.no_grad():
            return _loss_map(render(*scene, viewmat, with_dirs(grid, dirs), backend="cpu", sh_degree=3,
                                    background=torch.tensor(BG, dtype=F64))).reshape(-1)

    base = grid.dirs.detach().to(F64)
    plus, minus, at = loss_map(base + h * field), loss_map(base - h * field), loss_map(base)
    smooth = (plus - 2 * at + minus).abs() <= 1e-8
    assert float((~smooth).float().mean()) <= 0.01
    fd = (plus - minus) / (2 * h)
    analytic = (ours * field).sum(-1)
    assert float((analytic - fd)[smooth].norm() / fd[smooth].norm()) <= 1e-5
