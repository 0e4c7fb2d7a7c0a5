"""float32 far from the origin, unsupported dtypes, quaternions of any magnitude.

References: the brute-force renderer in float64 on the same (float32-valued) inputs, and rotation matrices of
unit quaternions.
"""

from __future__ import annotations

import math

import pytest
import torch

from geer_ns.render import RayGrid, quat_to_rotmat, render
from geer_ns.render.rasterize import render_brute_force
from geer_ns.render.transforms import view_transform

from conftest import random_scene, random_viewmat


def _far_scene(offset: float, seed: int = 3):
    """Gaussians of scale ~0.1-1 around a point `offset` away from the origin, seen from 5 m."""
    means, quats, scales, opacities, colors = random_scene(
        60, seed, center=(0.0, 0.0, 5.0), spread=1.2, scale_range=(0.1, 1.0), opacity_range=(0.2, 0.9)
    )
    viewmat = random_viewmat(seed + 1, translation_scale=0.0)  # rotation only: camera at the origin
    rot = viewmat[:3, :3]
    centre = torch.tensor([offset, -0.7 * offset, 0.4 * offset], dtype=torch.float64)
    world_means = means @ rot + centre  # camera frame -> world, camera centre at `centre`
    viewmat[:3, 3] = -rot @ centre
    grid = RayGrid.beap(40, 32, math.radians(100), math.radians(80), tile_size=8, dtype=torch.float64)
    f32 = [t.float() for t in (world_means, quats, scales, opacities, colors, viewmat)]
    return f32, grid


@pytest.mark.parametrize("backend", ["torch", "cpu"])  # cpu: the CUDA kernels' math, view transform in PyTorch
@pytest.mark.parametrize("offset", [0.0, 1e4])
def test_float32_far_from_the_origin_matches_float64(offset, backend):
    (means, quats, scales, opacities, colors, viewmat), grid = _far_scene(offset)
    got = render(means, quats, scales, opacities, colors, viewmat, grid, backend=backend)
    ref = render_brute_force(*(t.double() for t in (means, quats, scales, opacities, colors, viewmat)), grid)
    assert float(ref.accumulation.max()) > 0.5  # the scene is in view
    err = (got.rgb.double() - ref.rgb).abs().max()
    assert float(err) < 1e-4, float(err)
    assert float((got.accumulation.double() - ref.accumulation).abs().max()) < 1e-4


@pytest.mark.parametrize("backend", ["torch", "cpu"])  # cpu: the CUDA kernels' SH code compiled for the CPU
@pytest.mark.parametrize("offset", [0.0, 1e4])
def test_float32_sh_colours_far_from_the_origin_match_float64(offset, backend):
    """View-dependent colour: the SH direction (mean - camera centre) must not lose float32's ~1e-3 at 1e4."""
    (means, quats, scales, opacities, _rgb, viewmat), grid = _far_scene(offset)
    gen = torch.Generator().manual_seed(7)
    sh = torch.randn(means.shape[0], 16, 3, generator=gen, dtype=torch.float64) * 0.5
    sh[:, 0] = 1.0 + 0.3 * sh[:, 0]  # colours well above the clamp at 0, where the direction matters everywhere
    got = render(means, quats, scales, opacities, sh.float(), viewmat, grid, sh_degree=3, backend=backend)
    ref = render_brute_force(*(t.double() for t in (means, quats, scales, opacities, sh.float(), viewmat)), grid,
                             sh_degree=3)
    assert float(ref.accumulation.max()) > 0.5
    assert float(ref.rgb.std()) > 0.05  # the colours vary with the view direction, not just the DC term
    err = (got.rgb.double() - ref.rgb).abs().max()
    assert float(err) < 1e-4, float(err)


def test_view_transform_is_correctly_rounded_in_float32():
    gen = torch.Generator().manual_seed(0)
    means = (1e4 + torch.randn(1000, 3, generator=gen, dtype=torch.float64)).float()
    viewmat = random_viewmat(5).float()
    viewmat[:3, 3] = -(viewmat[:3, :3].double() @ torch.full((3,), 1e4, dtype=torch.float64)).float()
    exact = means.double() @ viewmat[:3, :3].double().T + viewmat[:3, 3].double()
    got = view_transform(means, viewmat)
    assert got.dtype == torch.float32
    # within one float32 rounding of the exact value (~4e-7 relative of values of ~10)
    assert float((got.double() - exact).abs().max()) <= 2e-6


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.int32])
def test_unsupported_dtypes_are_rejected(dtype):
    (means, quats, scales, opacities, colors, viewmat), grid = _far_scene(0.0)
    with pytest.raises(ValueError, match=rf"means: dtype {dtype} is not supported; expected torch.float32"):
        render(means.to(dtype), quats.to(dtype), scales.to(dtype), opacities.to(dtype), colors.to(dtype),
               viewmat, grid, backend="torch")
    with pytest.raises(ValueError, match=rf"viewmat: dtype {dtype} is not supported"):
        render(means, quats, scales, opacities, colors, viewmat.to(dtype), grid, backend="torch")


@pytest.mark.parametrize("magnitude", [1e19, 1e30, 1e-25, 1e-40])
def test_quaternions_of_any_magnitude_normalise(magnitude):
    gen = torch.Generator().manual_seed(1)
    q = torch.randn(64, 4, generator=gen, dtype=torch.float64)
    unit = q / q.norm(dim=-1, keepdim=True)
    scaled = (unit * magnitude).float()
    assert bool(torch.isfinite(scaled).all()) and bool((scaled.abs().amax(-1) > 0).all())
    got = quat_to_rotmat(scaled)
    assert bool(torch.isfinite(got).all())
    # subnormal magnitudes keep fewer significant bits: compare against the rounded input
    ref = quat_to_rotmat(scaled.double())
    assert float((got.double() - ref).abs().max()) < 1e-6
    if magnitude >= 1e-30:
        assert float((got.double() - quat_to_rotmat(unit)).abs().max()) < 1e-5


def test_render_with_huge_quaternions_equals_unit_ones():
    (means, quats, scales, opacities, colors, viewmat), grid = _far_scene(0.0)
    unit = quats / quats.norm(dim=-1, keepdim=True)
    a = render(means, unit, scales, opacities, colors, viewmat, grid, backend="torch")
    b = render(means, unit * 1e19, scales, opacities, colors, viewmat, grid, backend="torch")
    assert bool(torch.isfinite(b.rgb).all())
    assert float((a.rgb - b.rgb).abs().max()) < 1e-5
