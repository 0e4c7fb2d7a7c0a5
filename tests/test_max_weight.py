"""RenderOutput.max_weight, both backends (the PyTorch twin and the CPU build, which runs the kernels' code) and
the brute-force renderer: each Gaussian's largest blend weight T_before x alpha over the view's rays, 0 where it
never blended. Reference, sharing none of the blending code: every ray against every Gaussian in depth order, T
and alpha written out per pair with transmittance.py's functions, float64.
"""

from __future__ import annotations

import math

import pytest
import torch
from conftest import equidistant_fisheye_rays, random_scene, small_grid, small_scene, stress_gaussians

from geer_ns.render import RayGrid, render, render_brute_force
from geer_ns.render.composite import T_MIN
from geer_ns.render.rasterize import preprocess
from geer_ns.render.transmittance import canonical_ray_response, half_line_sq, pair_alpha

F32, F64 = torch.float32, torch.float64
BACKENDS = ("torch", "cpu")

pytestmark = pytest.mark.usefixtures("single_thread", "cpu_ops")  # backend="cpu" needs the build


def _max_weight_reference(scene, viewmat, grid):
    """[N] float64: every valid ray against every Gaussian front to back (stable depth order, as the renderer
    sorts), T and alpha per pair (transmittance.py), a ray stopping before T would fall below T_MIN."""
    scene = [t.double() for t in scene]
    pre = preprocess(*scene, viewmat.double())
    dirs = grid.dirs.double()[grid.valid.reshape(-1)]
    trans = torch.ones(dirs.shape[0], dtype=F64)
    open_ = torch.ones(dirs.shape[0], dtype=torch.bool)
    best = torch.zeros(scene[0].shape[0], dtype=F64)
    for k in torch.sort(pre.depth, stable=True).indices.tolist():
        dist_sq, t_star = canonical_ray_response(pre.o_u[k : k + 1], pre.whiten[k : k + 1], dirs)
        q, _, _ = half_line_sq(dist_sq, t_star, pre.o_u[k : k + 1])
        alpha = pair_alpha(q[:, 0], pre.opacities[k], torch.ones_like(open_))
        after = trans * (1.0 - alpha)
        blend = open_ & (alpha > 0) & (after >= T_MIN)
        open_ &= ~((alpha > 0) & (after < T_MIN))
        if bool(blend.any()):
            best[k] = (trans * alpha)[blend].max()
        trans = torch.where(blend, after, trans)
    return best


def _case(name: str, dtype):
    """(scene, viewmat, grid): conftest's small scenes with every third Gaussian near-opaque (rays stop early),
    or the stress Gaussians (camera inside one, disks, needles, behind the camera) in a 200-degree fisheye."""
    if name == "stress":
        means, quats, scales, opac = stress_gaussians()
        m2, q2, s2, o2, c2 = random_scene(30, 2, around=True)
        colors = torch.rand(9, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
        scene = [torch.cat([means, m2]), torch.cat([quats, q2]), torch.cat([scales, s2]), torch.cat([opac, o2]),
                 torch.cat([colors, c2])]
        dirs, valid = equidistant_fisheye_rays(16, 200.0, dtype=dtype)
        return scene, torch.eye(4, dtype=F64), RayGrid.from_rays(dirs, valid, tile_size=8)
    scene, viewmat = small_scene(name, seed=3, n=60)
    scene[3] = torch.where(torch.arange(60) % 3 == 0, torch.full_like(scene[3], 0.999), scene[3])
    return scene, viewmat, small_grid(name, dtype)


@pytest.mark.parametrize("name", ["beap", "fisheye", "stress"])
@pytest.mark.parametrize("dtype", [F64, F32])
def test_max_weight_matches_a_per_ray_reference(name, dtype):
    """Both backends and the brute-force renderer against the per-ray reference: float64 to 1e-12, float32 to
    1e-5 (weights are at most 0.99)."""
    scene, viewmat, grid = _case(name, dtype)
    ref = _max_weight_reference(scene, viewmat, grid)
    assert int((ref > 0).sum()) >= 15 and int((ref == 0).sum()) >= 1
    cast = [t.to(dtype) for t in scene]
    outs = [render(*cast, viewmat, grid, backend=b) for b in BACKENDS]
    outs.append(render_brute_force(*cast, viewmat, grid))
    tol = 1e-12 if dtype == F64 else 1e-5
    for out in outs:
        assert out.max_weight.dtype == dtype and not out.max_weight.requires_grad
        assert float((out.max_weight.double() - ref).abs().max()) <= tol


@pytest.mark.parametrize("backend", BACKENDS)
def test_max_weight_of_hidden_and_unseen_gaussians(backend):
    """A Gaussian behind an opaque one gets at most 1 % of its alpha (the opaque one passes T = 0.01), one behind
    more opaque layers none at all (the rays stop first), one outside the view exactly 0; seen alone, the hidden
    ones weigh over 0.5."""
    grid = RayGrid.beap(12, 12, math.radians(40), math.radians(40), tile_size=6, dtype=F64)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, 3.2], [0.0, 0.0, 3.4], [0.0, 0.0, 5.0],
                          [0.0, 0.0, -3.0], [6.0, 0.0, 0.5]], dtype=F64)
    scales = torch.tensor([[30.0, 30.0, 0.05]] * 4 + [[0.3, 0.3, 0.3]] * 3, dtype=F64)  # 4 sheets, 3 blobs
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 7, dtype=F64)
    opac = torch.tensor([1.0, 0.9, 1.0, 1.0, 0.9, 0.9, 0.9], dtype=F64)
    colors = torch.full((7, 3), 0.5, dtype=F64)
    vm = torch.eye(4, dtype=F64)
    both = render(means, quats, scales, opac, colors, vm, grid, backend=backend).max_weight
    assert float(both[0]) == 0.99  # the opaque sheet at z = 2: alpha at its cap on every ray, T = 1
    assert 0 < float(both[1]) <= 0.0101 * 0.9  # the sheet at z = 3 behind it
    alone = [render(means[i : i + 1], quats[i : i + 1], scales[i : i + 1], opac[i : i + 1], colors[i : i + 1], vm,
                    grid, backend=backend).max_weight for i in (1, 4)]
    assert float(alone[0]) > 0.5 and float(alone[1]) > 0.5
    assert float(both[4]) == 0.0  # behind the sheets at z = 2, 3.2 and 3.4: T < 1e-4 before it, the rays stopped
    assert float(both[5]) == 0.0 and float(both[6]) == 0.0  # behind the camera; far outside the 40-degree view
