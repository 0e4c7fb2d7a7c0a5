"""Association costs in proportion to its output on every grid: tile tests <= 4 x pairs + 64 x N.

Counted, not timed: the CPU build (csrc/geer_associate.h, the kernels' code) reports the tile tests of its
count pass (tile-pyramid search) and emit pass (each Gaussian's hit box only); the PyTorch twin reports its
own search's. The grids are the ones that used to cost N x tiles: the dev room's masked BEAP training view
and a 512x512 native equidistant fisheye (180 degrees across, more in the corners), with the trained donut and with 200k synthetic Gaussians around
the camera. Cases: benchmarks/cpu_association.py (which also times them against the old search).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest
import torch
from conftest import shared_data

from geer_ns.render import associate, cuda_backend
from geer_ns.render.pbf import PBF

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import cpu_association  # noqa: E402


@pytest.fixture(scope="module")
def ops():
    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler: cannot build csrc/cpu_ops.cpp")
    return cuda_backend.load_cpu_ops()


@pytest.fixture(scope="module")
def grid512():
    return cpu_association.fisheye_grid(512)


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
    shared_data("fisheye_room_dev", "transforms_fisheye.json")
    case = cpu_association.dev_room_case()
    assert bool(case[1].tile_active.all())
    _check(ops, case, twin=True)
    case = cpu_association.masked(case, 150.0)
    assert not bool(case[1].tile_active.all())
    _check(ops, case, twin=True)


def test_donut_native_fisheye512(ops, grid512):
    shared_data("donut_3dgs.ply")
    _check(ops, cpu_association.donut_case(grid512), twin=True)


def test_synthetic_200k_native_fisheye512(ops, grid512):
    _check(ops, cpu_association.synthetic_case(200_000, grid512), twin=False)
