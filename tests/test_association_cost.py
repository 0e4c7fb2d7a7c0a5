"""Association costs in proportion to its output on every grid: tile tests <= 4 x pairs + 64 x N.

Counted, not timed: the CPU build (csrc/geer_associate.h, the kernels' code) reports the tile tests of its
count pass (tile-pyramid search) and emit pass (each Gaussian's hit box only); the PyTorch twin reports its
own search's. The grids are the ones that used to cost N x tiles: the dev room's masked BEAP training view
and a 512x512 native equidistant fisheye (180 degrees across, more in the corners), with the trained donut and with 200k synthetic Gaussians around
the camera.
"""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch
from conftest import shared_data

from geer_ns.render import RayGrid, associate, cuda_backend, preprocess
from geer_ns.render.pbf import PBF


def _pbf_inputs(means, quats, scales, opac, viewmat, grid, name):
    """(name, grid, bounds [N,4], alive, depth) from the twin's preprocess (the specification)."""
    with torch.no_grad():
        pre = preprocess(means, quats, scales, opac, means.new_zeros(means.shape[0], 3), viewmat)
    p = pre.pbf
    return name, grid, torch.stack([p.theta_lo, p.theta_hi, p.phi_lo, p.phi_hi], -1).contiguous(), p.alive, pre.depth


def fisheye_grid(size: int = 512):
    from geer_ns.cameras import EquidistantCamera

    f = (size / 2) / (math.pi / 2)  # 180 degrees across the inscribed circle, more in the corners
    dirs, valid = EquidistantCamera(size, size, f, f, size / 2, size / 2).pixel_rays(torch.float32)
    return RayGrid.from_rays(dirs, valid, tile_size=16)


def masked(case, crop_deg: float):
    """The same Gaussians and view, rays beyond crop_deg / 2 off the optical axis invalid."""
    name, grid, bounds, alive, depth = case
    valid = (grid.dirs[:, 2] >= math.cos(math.radians(crop_deg / 2))).reshape(grid.height, grid.width)
    grid = RayGrid.from_rays(grid.dirs.reshape(grid.height, grid.width, 3), valid, grid.tile_size)
    return f"{name}-masked", grid, bounds, alive, depth


def dev_room_case():
    """The dev room's BEAP training view of its first frame, its 20k seed points as Gaussians (kNN scales,
    nerfstudio's initial opacity 0.1)."""
    from scipy.spatial import cKDTree

    from geer_ns.cameras import EquidistantCamera
    from geer_ns.data.ply import read_ply_points
    from geer_ns.data.views import beap_view
    from geer_ns.render.transforms import world_to_camera_opencv

    room = shared_data("fisheye_room_dev")
    meta = json.loads((room / "transforms_fisheye.json").read_text())
    camera = EquidistantCamera(meta["w"], meta["h"], meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"])
    xyz, _ = read_ply_points(room / meta["ply_file_path"])
    dist, _ = cKDTree(xyz.astype(np.float64)).query(xyz.astype(np.float64), k=4)
    scales = torch.from_numpy(np.sqrt((dist[:, 1:] ** 2).mean(-1))).float().clamp_min(1e-7)[:, None].repeat(1, 3)
    n = xyz.shape[0]
    c2w = torch.tensor(meta["frames"][0]["transform_matrix"], dtype=torch.float32)[:3]
    return _pbf_inputs(torch.from_numpy(xyz), torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1), scales,
                       torch.full((n,), 0.1), world_to_camera_opencv(c2w), beap_view(camera).rays, "dev-room-beap")


def donut_case(grid):
    """The trained donut (3DGS PLY) seen from -z at 2.2 times its 95 % radius."""
    from plyfile import PlyData

    v = PlyData.read(str(shared_data("donut_3dgs.ply")))["vertex"]
    col = lambda *names: torch.tensor(np.stack([np.asarray(v[n]) for n in names], -1))  # noqa: E731
    means = col("x", "y", "z")
    centre = means.median(0).values
    viewmat = torch.eye(4)
    viewmat[:3, 3] = -(centre - torch.tensor([0.0, 0.0, 2.2 * float((means - centre).norm(dim=-1).quantile(0.95))]))
    return _pbf_inputs(means, col("rot_0", "rot_1", "rot_2", "rot_3"), col("scale_0", "scale_1", "scale_2").exp(),
                       torch.sigmoid(col("opacity")[:, 0]), viewmat, grid, "donut-fisheye512")


def synthetic_case(n: int, grid):
    """n Gaussians on all sides of the camera, log-uniform distances 2-30, sizes 0.2-1 % of the distance."""
    gen = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)
    r = torch.exp(math.log(2.0) + math.log(15.0) * torch.rand(n, 1, generator=gen))
    scales = r * torch.exp(math.log(0.002) + math.log(5.0) * torch.rand(n, 3, generator=gen))
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1)
    return _pbf_inputs(d * r, quats, scales, 0.5 + 0.5 * torch.rand(n, generator=gen), torch.eye(4), grid,
                       f"synth{n // 1000}k-fisheye512")


@pytest.fixture(scope="module")
def ops():
    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler: cannot build csrc/cpu_ops.cpp")
    return cuda_backend.load_cpu_ops()


@pytest.fixture(scope="module")
def grid512():
    return fisheye_grid(512)


def _bound(pairs: int, n: int) -> int:
    return 4 * pairs + 64 * n


def _check(ops, case, twin: bool):
    name, grid, bounds, alive, depth = case
    ids, ranges, counts, tests = cuda_backend.associate_pairs(ops, bounds, alive, depth, grid)
    n, pairs, n_tests = bounds.shape[0], int(counts.sum()), int(tests.sum())
    assert pairs > 10 * n // 100, f"{name}: too few pairs ({pairs}) for a meaningful bound"
    assert n_tests <= _bound(pairs, n), f"{name}: {n_tests} tile tests > 4 x {pairs} pairs + 64 x {n}"
    # Far below what testing every active tile would cost.
    assert n_tests < int(alive.sum()) * int(grid.tile_active.sum()) // 4
    if twin:
        pbf = PBF(*bounds.unbind(-1), alive, torch.zeros_like(alive))
        ref = associate(pbf, grid, depth)
        assert int(ref.counts.sum()) == pairs
        assert ref.tile_tests <= _bound(pairs, n)
        assert n_tests - ref.tile_tests >= pairs  # same search; the emit pass tests each pair's tile at least once


def test_dev_room_beap(ops):
    """The dev room's BEAP training view as is, and masked to a 150-degree circle (inactive tiles)."""
    case = dev_room_case()
    assert bool(case[1].tile_active.all())
    _check(ops, case, twin=True)
    case = masked(case, 150.0)
    assert not bool(case[1].tile_active.all())
    _check(ops, case, twin=True)


def test_donut_native_fisheye512(ops, grid512):
    _check(ops, donut_case(grid512), twin=True)


def test_synthetic_200k_native_fisheye512(ops, grid512):
    _check(ops, synthetic_case(200_000, grid512), twin=False)
