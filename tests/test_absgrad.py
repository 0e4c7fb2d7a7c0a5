"""absgrad (geer_ns/render/absgrad.py), both backends (the PyTorch twin and the CPU build, which runs the
kernels' code): sink.grad = sum over pixels p of |dL_p/d offsets|, the offsets moving each view-space mean
along its `lateral` columns. Reference, sharing none of absgrad's code: autograd, one pixel at a time, of a
float64 twin render whose means are displaced by the offsets (means + (lateral offsets) R, R the viewmat's
rotation). Scenes are small (tens of Gaussians, 12 x 12 rays): every test runs in seconds.
"""

from __future__ import annotations


import pytest
import torch
from conftest import equidistant_fisheye_rays, equirect_rays, random_scene, small_grid, small_scene, stress_gaussians

from geer_ns.render import RayGrid, render

F32, F64 = torch.float32, torch.float64
BACKENDS = ("torch", "cpu")
GRIDS = ("beap", "fisheye")

pytestmark = pytest.mark.usefixtures("single_thread", "cpu_ops")  # backend="cpu" needs the build


def _scene(grid_name: str, seed: int = 0, n: int = 40):
    """conftest.small_scene's Gaussians and viewmat, and lateral [N, 3, 2]."""
    scene, viewmat = small_scene(grid_name, seed, n)
    lateral = torch.randn(n, 3, 2, generator=torch.Generator().manual_seed(seed + 20), dtype=F64)
    return scene, viewmat, lateral


def _pixel_losses(out, weights):
    """[H * W] loss of each pixel: random weights on its rgb, expected depth and accumulation."""
    w_rgb, w_depth, w_acc = weights
    return ((w_rgb * out.rgb).sum(-1) + (w_depth * out.depth)[..., 0] + (w_acc * out.accumulation)[..., 0]).reshape(-1)


def _weights(grid: RayGrid, dtype, seed: int = 5):
    gen = torch.Generator().manual_seed(seed)
    h, w = grid.height, grid.width
    return [torch.randn(h, w, c, generator=gen, dtype=F64).to(dtype) for c in (3, 1, 1)]


def _displaced(means, lateral, offsets, viewmat):
    """The means moved by lateral offsets in view space: world moves (lateral offsets) R."""
    return means + torch.einsum("nij,nj->ni", lateral, offsets) @ viewmat[:3, :3].to(means.dtype)


def _per_pixel_reference(scene, viewmat, lateral, grid, weights):
    """(sum_p |dL_p/d offsets|, sum_p dL_p/d offsets, dL/d offsets) from the float64 twin, one pixel at a time."""
    scene = [t.double() for t in scene]
    offsets = torch.zeros(scene[0].shape[0], 2, dtype=F64, requires_grad=True)
    out = render(_displaced(scene[0], lateral, offsets, viewmat), *scene[1:], viewmat, grid,
                 background=torch.full((3,), 0.25, dtype=F64), backend="torch")
    losses = _pixel_losses(out, [w.double() for w in weights])
    abs_sum, signed_sum = torch.zeros_like(offsets), torch.zeros_like(offsets)
    for p in torch.nonzero(grid.valid.reshape(-1)).flatten().tolist():
        (g,) = torch.autograd.grad(losses[p], offsets, retain_graph=True)
        abs_sum += g.abs()
        signed_sum += g
    (full,) = torch.autograd.grad(losses.sum(), offsets)
    return abs_sum, signed_sum, full


_references: dict = {}


def _reference(grid_name: str):
    """The per-pixel reference of a grid's scene, computed once per test run (the slowest part here)."""
    if grid_name not in _references:
        scene, viewmat, lateral = _scene(grid_name)
        grid = small_grid(grid_name)
        _references[grid_name] = _per_pixel_reference(scene, viewmat, lateral, grid, _weights(grid, F64))
    return _references[grid_name]


def _render(scene, viewmat, grid, dtype, backend, lateral=None, sh_degree=None):
    """Render and backpropagate the weighted pixel loss; with lateral, through absgrad's sink. Returns the
    output, the leaves' gradients, means_c's gradient and the sink's gradient (None without absgrad). The twin
    blends each tile's list in pieces of 5 Gaussians (max_pairs), the transmittance and its gradient carried."""
    leaves = [t.to(dtype).clone().requires_grad_(True) for t in scene]
    sink = torch.zeros(scene[0].shape[0], 2, dtype=dtype, requires_grad=True)
    absgrad = None if lateral is None else (lateral.to(dtype), sink)
    out = render(*leaves, viewmat, grid, background=torch.full((3,), 0.25, dtype=dtype), backend=backend,
                 absgrad=absgrad, sh_degree=sh_degree, max_pairs=5 * 36)
    _pixel_losses(out, _weights(grid, dtype)).sum().backward()
    return out, [t.grad for t in leaves], out.means_c.grad, (sink.grad if lateral is not None else None)


# ------------------------------------------------------------------------------------------ absgrad
@pytest.mark.parametrize("grid_name", GRIDS)
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [F64, F32])
def test_absgrad_is_the_sum_of_per_pixel_absolute_gradients(backend, grid_name, dtype):
    """sink.grad against the per-pixel loop: float64 to 1e-11 relative plus 1e-13 of the largest entry (seen:
    1e-14, 3e-15); float32 to 2e-4 relative plus 2e-5 of the largest entry (seen: 3e-5, 2e-6)."""
    scene, viewmat, lateral = _scene(grid_name)
    abs_ref, _, _ = _reference(grid_name)
    _, _, _, sink_grad = _render(scene, viewmat, small_grid(grid_name, dtype), dtype, backend, lateral)
    assert int((abs_ref > 0).any(-1).sum()) >= 10  # many Gaussians blended somewhere
    scale = float(abs_ref.abs().max())
    rtol, atol = (1e-11, 1e-13) if dtype == F64 else (2e-4, 2e-5)
    err = (sink_grad.double() - abs_ref).abs()
    assert bool((err <= rtol * abs_ref + atol * scale).all()), float((err / (abs_ref + scale * 1e-6)).max())


@pytest.mark.parametrize("grid_name", GRIDS)
def test_the_per_pixel_reference_sums_to_the_offsets_gradient(grid_name):
    """The reference's sanity: its signed per-pixel gradients add up to the whole loss's offsets gradient, and
    absolute sums bound it. A pixel loop that missed or doubled pixels (or rays of one pixel) fails here."""
    abs_ref, signed_ref, full = _reference(grid_name)
    scale = float(full.abs().max())
    assert scale > 0
    assert torch.allclose(signed_ref, full, rtol=1e-10, atol=1e-12 * scale)
    assert bool((abs_ref >= full.abs() - 1e-12 * scale).all())
    assert float((abs_ref - full.abs()).max()) > 1e-3 * scale  # pixels disagree in sign somewhere: abs matters


@pytest.mark.parametrize("grid_name", GRIDS)
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [F32, F64])
def test_absgrad_changes_no_output_and_no_other_gradient(backend, grid_name, dtype):
    """With and without absgrad, bit for bit: images, max_weight, every parameter's and means_c's gradient (SH
    colours here, so that the colour path is covered too)."""
    scene, viewmat, lateral = _scene(grid_name, seed=1)
    scene[4] = torch.rand(scene[0].shape[0], 4, 3, generator=torch.Generator().manual_seed(2), dtype=F64) - 0.3
    grid = small_grid(grid_name, dtype)
    off = _render(scene, viewmat, grid, dtype, backend, sh_degree=1)
    on = _render(scene, viewmat, grid, dtype, backend, lateral, sh_degree=1)
    assert float(on[3].abs().max()) > 0
    for name in ("rgb", "depth", "accumulation", "max_weight", "visible"):
        assert torch.equal(getattr(off[0], name), getattr(on[0], name)), name
    for a, b in zip(off[1] + [off[2]], on[1] + [on[2]]):
        assert torch.equal(a, b)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [F32, F64])
def test_absgrad_is_finite_on_the_stress_scenes(backend, dtype):
    """Camera inside a Gaussian, Gaussians behind and straddling the camera, disks and needles, a scale below
    MIN_SCALE, rays up to 100 degrees off axis and all around: finite absgrad and max_weight, and the backends
    agree (float64)."""
    means, quats, scales, opac = stress_gaussians()
    m2, q2, s2, o2, _ = random_scene(30, 2, around=True)
    scene = [torch.cat([means, m2]), torch.cat([quats, q2]), torch.cat([scales, s2]), torch.cat([opac, o2])]
    n = scene[0].shape[0]
    scene.append(torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=F64))
    lateral = torch.randn(n, 3, 2, generator=torch.Generator().manual_seed(1), dtype=F64)
    fd, fv = equidistant_fisheye_rays(16, 200.0, dtype=dtype)
    for grid in (RayGrid.from_rays(fd, fv, tile_size=8), RayGrid.from_rays(equirect_rays(16, 8, dtype=dtype), None,
                                                                           tile_size=8)):
        out, _, _, sink_grad = _render(scene, torch.eye(4, dtype=F64), grid, dtype, backend, lateral)
        assert torch.isfinite(sink_grad).all() and torch.isfinite(out.max_weight).all()
        assert float(sink_grad[:9].abs().max()) > 0  # the stress Gaussians themselves contribute
        if dtype == F64 and backend == "cpu":
            ref, _, _, ref_grad = _render(scene, torch.eye(4, dtype=F64), grid, dtype, "torch", lateral)
            assert torch.allclose(sink_grad, ref_grad, rtol=1e-11, atol=1e-13 * float(ref_grad.abs().max()))
            assert torch.allclose(out.max_weight, ref.max_weight, rtol=1e-9, atol=1e-12)


def test_absgrad_arguments_are_checked():
    scene, viewmat, lateral = _scene("beap", n=5)
    grid = small_grid("beap")
    sink = torch.zeros(5, 2, dtype=F64, requires_grad=True)
    bad = {
        "lateral": ((lateral[:, :, :1], sink), ValueError),
        "sink": ((lateral, torch.zeros(5, 2, dtype=F64)), ValueError),  # no grad: nowhere to put the sums
        "sink dtype": ((lateral, torch.zeros(5, 2, dtype=F32, requires_grad=True)), ValueError),
        "pair": (lateral, TypeError),
    }
    for name, (absgrad, error) in bad.items():
        with pytest.raises(error, match="absgrad"):
            render(*scene, viewmat, grid, absgrad=absgrad)
