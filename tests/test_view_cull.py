"""The view cull (geer_ns/render/cull.py) keeps every Gaussian a view's association lists, on every reference grid
and a narrow pinhole-like one, with the camera among the Gaussians; and renders of the kept rows alone give the
image and gradients of all rows."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import random_scene, random_viewmat, reference_grids, stress_gaussians
from geer_ns.render import RayGrid, render
from geer_ns.render.cull import view_rows

F64 = torch.float64


def _grids():
    grids = dict(reference_grids())
    grids["narrow"] = RayGrid.beap(32, 24, math.radians(30), math.radians(20), tile_size=8, dtype=F64)
    return grids


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("grid_name", ["beap", "fisheye180", "equirect360", "narrow"])
def test_every_listed_gaussian_is_kept(cpu_ops, grid_name, backend):
    grid = _grids()[grid_name]
    means, quats, scales, opac, colors = random_scene(400, 3, around=True, scale_range=(1e-3, 0.8))
    sm, sq, ss, so = stress_gaussians()
    means, quats, scales = torch.cat([means, sm]), torch.cat([quats, sq]), torch.cat([scales, ss])
    opac, colors = torch.cat([opac, so]), torch.cat([colors, torch.rand(len(so), 3, dtype=F64)])
    for seed in range(3):
        vm = random_viewmat(seed, translation_scale=0.5)
        out = render(means, quats, scales, opac, colors, vm, grid, backend=backend)
        kept = torch.zeros(len(means), dtype=torch.bool)
        kept[view_rows(means, scales.amax(-1), opac, vm, grid)] = True
        listed = out.visible
        assert bool(listed.any()) and not bool((listed & ~kept).any()), int((listed & ~kept).sum())
        if grid_name == "narrow":
            assert int(kept.sum()) < len(means) // 2  # it culls


def test_rendering_the_kept_rows_equals_rendering_all(cpu_ops):
    grid = _grids()["narrow"]
    scene = random_scene(300, 5, around=True, scale_range=(1e-2, 0.5))
    vm = random_viewmat(2, translation_scale=0.3)
    rows = view_rows(scene[0], scene[2].amax(-1), scene[3], vm, grid)
    assert 0 < len(rows) < 150
    full = [t.clone().requires_grad_(True) for t in scene]
    part = [t.clone().requires_grad_(True) for t in scene]
    out_full = render(*full, vm, grid, backend="cpu")
    out_part = render(*(t[rows] for t in part), vm, grid, backend="cpu")
    weights = torch.rand(out_full.rgb.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    (weights * out_full.rgb).sum().backward()
    (weights * out_part.rgb).sum().backward()
    torch.testing.assert_close(out_part.rgb, out_full.rgb, rtol=0, atol=1e-13)
    for a, b in zip(part, full):
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-10, atol=1e-13)
