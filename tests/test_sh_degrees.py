"""Each Gaussian's own SH degree: the kernels (CPU build of csrc/geer_math.h) and the twin (render/sh.py) evaluate
only the bands a Gaussian keeps, forward and backward. References: each Gaussian evaluated alone at its own
degree with only its kept coefficients (no zeroed bands), exact zeros for the dropped bands' gradients, and
float64 central differences for the kept ones."""

from __future__ import annotations

import pytest
import torch

from conftest import random_scene, random_viewmat, reference_grids
from geer_ns.render import render
from geer_ns.render.sh import sh_to_color
from geer_ns.render.transforms import camera_offsets

F64 = torch.float64


def _colors(n: int, seed: int, dtype=F64):
    gen = torch.Generator().manual_seed(seed)
    coeffs = torch.randn(n, 16, 3, generator=gen, dtype=dtype) * 0.4
    dirs = torch.randn(n, 3, generator=gen, dtype=dtype)
    degrees = torch.randint(0, 4, (n,), generator=gen).to(torch.uint8)
    return coeffs, dirs, degrees


def _scene(dtype):
    """(means, quats, scales, opacities, viewmat) of Gaussians all around a camera."""
    m, q, s, o, _ = random_scene(50, 0, around=True, scale_range=(1e-3, 0.6))
    return m.to(dtype), q.to(dtype), s.to(dtype), o.to(dtype), random_viewmat(1, translation_scale=0.3).to(dtype)


def _alone(coeffs, dirs, degrees, active: int):
    """Each Gaussian alone at min(own, active), given only its kept coefficients."""
    rows = []
    for i in range(coeffs.shape[0]):
        d = min(int(degrees[i]), active)
        rows.append(sh_to_color(coeffs[i : i + 1, : (d + 1) ** 2], dirs[i : i + 1], d))
    return torch.cat(rows)


@pytest.mark.parametrize("active", [3, 2, 0])
def test_twin_equals_each_gaussian_alone(active):
    coeffs, dirs, degrees = _colors(40, active)
    k = (active + 1) ** 2
    ours = sh_to_color(coeffs[:, :k], dirs, degrees.clamp(max=active))
    assert torch.equal(ours, _alone(coeffs, dirs, degrees, active))


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("active", [3, 1])
def test_kernel_forward_matches_twin(cpu_ops, dtype, active):
    means, quats, scales, opac, vm = _scene(dtype)
    n = means.shape[0]
    coeffs, _, degrees = _colors(n, 5, dtype)
    dirs, rot_c = camera_offsets(means, vm), vm[:3, :3].contiguous()
    means_c = (means.double() @ vm[:3, :3].double().T + vm[:3, 3].double()).to(dtype)
    rgb = cpu_ops.preprocess_forward(means_c, quats, scales, opac, coeffs, dirs, rot_c, active, False, degrees)[2]
    ref = _alone(coeffs.double(), dirs.double(), degrees, active)
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    torch.testing.assert_close(rgb.double(), ref, rtol=tol, atol=tol)
    full = cpu_ops.preprocess_forward(means_c, quats, scales, opac, coeffs, dirs, rot_c, active, False)[2]
    assert not torch.allclose(full, rgb)  # the degrees were applied


def test_kernel_backward_dropped_bands_zero_kept_bands_finite_differences(cpu_ops):
    means, quats, scales, opac, vm = _scene(F64)
    n = means.shape[0]
    coeffs, _, degrees = _colors(n, 7)
    coeffs[:, 0] += 2.0  # colours away from the clamp at 0: a smooth loss for the differences
    dirs, rot_c = camera_offsets(means, vm), vm[:3, :3].contiguous()
    means_c = means @ vm[:3, :3].T + vm[:3, 3]
    g_rgb = torch.randn(n, 3, generator=torch.Generator().manual_seed(2), dtype=F64)
    zeros = torch.zeros(n, 3, 3, dtype=F64)
    _, _, _, g_sh, g_dirs, _ = cpu_ops.preprocess_backward(means_c, quats, scales, coeffs, dirs, rot_c, 3, zeros,
                                                           torch.zeros(n, 3, dtype=F64), g_rgb, False, degrees)
    band = torch.tensor([int(k ** 0.5) for k in range(16)])
    dropped = band[None, :] > degrees.long()[:, None]
    assert bool(dropped.any()) and bool((~dropped).any())
    assert bool((g_sh[dropped] == 0).all())  # exactly: the kernel never writes them

    def loss(c, d):
        return (g_rgb * _alone(c, d, degrees, 3)).sum()

    h = 1e-6
    for i in range(0, n, 7):  # a sample of Gaussians, each kept coefficient and each direction component
        for k in range(int(degrees[i] + 1) ** 2):
            for ch in range(3):
                up, down = coeffs.clone(), coeffs.clone()
                up[i, k, ch] += h
                down[i, k, ch] -= h
                fd = (loss(up, dirs) - loss(down, dirs)) / (2 * h)
                assert abs(float(g_sh[i, k, ch] - fd)) <= 1e-7 * max(1.0, abs(float(fd)))
        for ax in range(3):
            up, down = dirs.clone(), dirs.clone()
            up[i, ax] += h
            down[i, ax] -= h
            fd = (loss(coeffs, up) - loss(coeffs, down)) / (2 * h)
            assert abs(float(g_dirs[i, ax] - fd)) <= 1e-6 * max(1.0, abs(float(fd)))
    assert bool((g_dirs[degrees == 0] == 0).all())  # degree 0: no view dependence


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_render_per_gaussian_degrees(cpu_ops, backend):
    """Through render: the image of per-Gaussian degrees equals the image of the same coefficients with the
    dropped bands set to zero at full degree; the dropped bands' gradients are exactly zero."""
    grid = reference_grids()["beap"]
    means, quats, scales, opac, _ = random_scene(60, 4)
    coeffs, _, degrees = _colors(60, 8)
    band = torch.tensor([int(k ** 0.5) for k in range(16)])
    dropped = band[None, :] > degrees.long()[:, None]
    zeroed = torch.where(dropped[..., None], 0.0, coeffs)
    vm = torch.eye(4, dtype=F64)
    leaf = coeffs.clone().requires_grad_(True)
    out = render(means, quats, scales, opac, leaf, vm, grid, sh_degree=degrees, backend=backend)
    ref = render(means, quats, scales, opac, zeroed, vm, grid, sh_degree=3, backend=backend)
    torch.testing.assert_close(out.rgb, ref.rgb, rtol=0, atol=1e-14)
    (out.rgb * torch.linspace(0, 1, out.rgb.numel(), dtype=F64).reshape(out.rgb.shape)).sum().backward()
    assert bool((leaf.grad[dropped] == 0).all()) and float(leaf.grad[~dropped].abs().max()) > 0


def test_bad_degrees_are_refused():
    grid = reference_grids()["beap"]
    means, quats, scales, opac, _ = random_scene(5, 1)
    coeffs = torch.zeros(5, 16, 3, dtype=F64)
    vm = torch.eye(4, dtype=F64)
    with pytest.raises(ValueError, match="sh_degree"):
        render(means, quats, scales, opac, coeffs, vm, grid, sh_degree=torch.zeros(4, dtype=torch.uint8))
    with pytest.raises(ValueError, match="sh_degree"):
        render(means, quats, scales, opac, coeffs, vm, grid, sh_degree=torch.zeros(5))
    with pytest.raises(ValueError, match="sh_degree"):
        render(means, quats, scales, opac, coeffs, vm, grid, sh_degree=torch.full((5,), -1))


@pytest.mark.parametrize("rows", ["all", "visible"])
def test_dropped_bands_stay_zero_while_training(cpu_ops, rows):
    """Coefficients set to zero with zero Adam moments (sh_degrees.choice.keep_degrees) get exactly zero gradients
    from the kernels, so Adam leaves them at zero; the kept ones train."""
    from geer_ns.optim.selective_adam import SelectiveAdam

    grid = reference_grids(torch.float32)["beap"]
    means, quats, scales, opac, _ = (t.float() for t in random_scene(60, 4))
    coeffs, _, degrees = _colors(60, 8, torch.float32)
    band = torch.tensor([int(k ** 0.5) for k in range(16)])
    dropped = band[None, :] > degrees.long()[:, None]
    leaf = torch.where(dropped[..., None], 0.0, coeffs).requires_grad_(True)
    start = leaf.detach().clone()
    opt = SelectiveAdam([leaf], lr=1e-2, eps=1e-15)
    target = torch.rand(grid.height, grid.width, 3, generator=torch.Generator().manual_seed(0))
    for _ in range(5):
        out = render(means, quats, scales, opac, leaf, torch.eye(4), grid, sh_degree=degrees, backend="cpu")
        opt.zero_grad()
        (out.rgb - target).abs().mean().backward()
        opt.use_rows(None if rows == "all" else torch.nonzero(out.visible).squeeze(1))
        opt.step()
    assert bool((leaf.detach()[dropped] == 0).all())
    assert bool((leaf.detach()[~dropped] != start[~dropped]).any())
