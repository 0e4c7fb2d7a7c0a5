"""backend="auto" on CPU tensors: the multi-threaded CPU build (csrc/cpu_ops.cpp), deterministic, with a loud
fallback to the PyTorch twin when it cannot be used. Its agreement with the twin: tests/test_csrc_math.py."""

from __future__ import annotations

import shutil
import warnings

import pytest
import torch
from conftest import reference_grids, random_scene

from geer_ns.render import cuda_backend, render
from geer_ns.render.backend import _warned, resolve_backend


@pytest.fixture(scope="module")
def ops():
    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler: cannot build csrc/cpu_ops.cpp")
    return cuda_backend.load_cpu_ops()


def _render_and_grads(grid, dtype=torch.float32, backend="auto"):
    scene = [t.to(dtype).requires_grad_(True) for t in random_scene(300, 7, around=True)]
    out = render(*scene, torch.eye(4, dtype=dtype), grid, background=torch.full((3,), 0.3, dtype=dtype),
                 backend=backend)
    (out.rgb.square().sum() + out.depth.sum() + out.accumulation.sum()).backward()
    return [out.rgb, out.depth, out.accumulation, out.visible, out.tile_counts] + [t.grad for t in scene]


def test_auto_uses_the_cpu_build_on_cpu_tensors(ops):
    assert resolve_backend("auto", torch.device("cpu")) == "cpu"
    grid = reference_grids(torch.float32)["fisheye180"]
    for a, b in zip(_render_and_grads(grid), _render_and_grads(grid, backend="cpu")):
        assert torch.equal(a, b)


@pytest.mark.parametrize("grid_name", ["beap", "fisheye180", "equirect360"])
def test_cpu_build_is_deterministic_across_threads(ops, grid_name):
    """Bitwise equal over two runs with 2 threads and a run with 1: no order-dependent sums between threads."""
    grid = reference_grids(torch.float32)[grid_name]
    n = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        first, second = _render_and_grads(grid), _render_and_grads(grid)
        torch.set_num_threads(1)
        single = _render_and_grads(grid)
    finally:
        torch.set_num_threads(n)
    assert float(first[2].detach().max()) > 0.5 and float(first[5].abs().max()) > 0  # something was rendered
    for a, b, c in zip(first, second, single):
        assert torch.equal(a, b) and torch.equal(a, c)


def test_auto_falls_back_loudly_once_when_the_cpu_build_fails(ops, monkeypatch):
    monkeypatch.delitem(cuda_backend._modules, "geer_cpu_ops")
    monkeypatch.setitem(cuda_backend._errors, "geer_cpu_ops", RuntimeError("compiler exploded"))
    _warned.clear()
    with pytest.warns(RuntimeWarning, match="compiler exploded"):
        assert resolve_backend("auto", torch.device("cpu")) == "torch"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert resolve_backend("auto", torch.device("cpu")) == "torch"  # said once
    with pytest.raises(RuntimeError, match="cpu_ops"):
        resolve_backend("cpu", torch.device("cpu"))  # an explicit request is an error


def test_auto_renders_pose_gradients_with_the_twin(ops):
    grid = reference_grids(torch.float32)["beap"]
    scene = random_scene(50, 2, dtype=torch.float32)
    viewmat = torch.eye(4).requires_grad_(True)
    _warned.clear()
    with pytest.warns(RuntimeWarning, match="pose gradients"):
        out = render(*scene, viewmat, grid)
    out.rgb.sum().backward()
    assert viewmat.grad is not None and float(viewmat.grad.abs().sum()) > 0
