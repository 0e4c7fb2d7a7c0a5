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


def _render_and_grads(grid, dtype=torch.float32, backend="auto", scene=None, absgrad=False):
    """Images, visibility, tile counts, max_weight, every parameter's gradient and, with absgrad, the sink's."""
    scene = [t.to(dtype).clone().requires_grad_(True) for t in (scene or random_scene(300, 7, around=True))]
    n = scene[0].shape[0]
    sink = torch.zeros(n, 2, dtype=dtype, requires_grad=True)
    lateral = torch.randn(n, 3, 2, generator=torch.Generator().manual_seed(4), dtype=torch.float64).to(dtype)
    out = render(*scene, torch.eye(4, dtype=dtype), grid, background=torch.full((3,), 0.3, dtype=dtype),
                 backend=backend, absgrad=(lateral, sink) if absgrad else None)
    (out.rgb.square().sum() + out.depth.sum() + out.accumulation.sum()).backward()
    return ([out.rgb, out.depth, out.accumulation, out.visible, out.tile_counts, out.max_weight]
            + [t.grad for t in scene] + ([sink.grad] if absgrad else []))


def test_auto_uses_the_cpu_build_on_cpu_tensors(ops):
    assert resolve_backend("auto", torch.device("cpu")) == "cpu"
    grid = reference_grids(torch.float32)["fisheye180"]
    for a, b in zip(_render_and_grads(grid), _render_and_grads(grid, backend="cpu")):
        assert torch.equal(a, b)


@pytest.mark.parametrize("grid_name", ["beap", "fisheye180", "equirect360"])
def test_cpu_build_is_deterministic_across_threads(ops, grid_name):
    """Bitwise equal over two runs with 2 threads and a run with 1: no order-dependent sums between threads
    (max_weight's and absgrad's included)."""
    grid = reference_grids(torch.float32)[grid_name]
    n = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        first, second = _render_and_grads(grid, absgrad=True), _render_and_grads(grid, absgrad=True)
        torch.set_num_threads(1)
        single = _render_and_grads(grid, absgrad=True)
    finally:
        torch.set_num_threads(n)
    assert float(first[2].detach().max()) > 0.5 and float(first[6].abs().max()) > 0  # something was rendered
    assert float(first[-1].max()) > 0  # absgrad too
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


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_lists_longer_than_a_batch_match_the_twin(ops, dtype):
    """Tile lists spanning several shared-memory batches (geer_blocks.h: 256 float32 / 128 float64 frames):
    the batch walk front to back, the backward's walk from the block's last blended Gaussian, and the warp
    sums of the CPU build all agree with the twin."""
    from geer_ns.render import RayGrid

    grid = RayGrid.beap(32, 32, 1.2, 1.2, tile_size=16, dtype=dtype)
    scene = [t.to(dtype) for t in random_scene(700, 5, spread=0.3, scale_range=(0.1, 0.3), opacity_range=(0.02, 0.05))]
    results = {}
    for backend in ("torch", "cpu"):
        leaves = [t.clone().requires_grad_(True) for t in scene]
        out = render(*leaves, torch.eye(4, dtype=dtype), grid, backend=backend)
        (out.rgb.square().sum() + out.depth.sum()).backward()
        results[backend] = (out, [t.grad for t in leaves])
    (ref, g_ref), (ours, g_ours) = results["torch"], results["cpu"]
    assert int(ref.tile_counts.min()) > 256  # every tile walks two float32 batches, four float64 ones
    tol = 1e-10 if dtype == torch.float64 else 1e-5
    for name in ("rgb", "depth", "accumulation"):
        assert (getattr(ours, name) - getattr(ref, name)).abs().max() <= tol * max(1.0, float(getattr(ref, name).abs().max()))
    for a, b in zip(g_ours, g_ref):
        assert (a - b).norm() <= (1e-8 if dtype == torch.float64 else 1e-3) * b.norm()


def _bit_case(name, dtype):
    """(grid, scene) of the bit test below. "stops": near-opaque layers on a 37x29 image in 12-pixel tiles, so
    that rays stop (T would fall below 1e-4) while pack-mates blend the same entry, tile lists cross the
    256 / 128-entry batch boundary, and the edge tiles overhang the image (lanes off the image inside packs);
    the reference grids with their scene have none of these (a pack that updates a stopped lane's T passes them)."""
    from geer_ns.render import RayGrid

    if name == "stops":
        grid = RayGrid.beap(37, 29, 1.2, 1.0, tile_size=12, dtype=dtype)
        return grid, random_scene(300, 1, spread=0.6, scale_range=(0.1, 0.5), opacity_range=(0.9, 1.0))
    return reference_grids(dtype)[name], None


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("grid_name", ["beap", "fisheye180", "equirect360", "stops"])
def test_the_kernels_one_ray_per_thread_path_gives_the_cpu_paths_bits(ops, monkeypatch, grid_name, dtype):
    """The CPU build renders packs of rays (csrc/geer_packs.h, where it has AVX2), and its backward visits only
    the lanes its forward recorded as blending each entry (blended_lanes). The kernels run one ray per thread,
    and their backward skips whole warps by the cull and lets every lane of the blended prefix evaluate the
    pair (render_forward_gpu_path / render_backward_gpu_path run that path on the CPU). Same images, max_weight,
    gradients and absgrad sums, bit for bit: packs, masks and the record change which lanes compute, never a
    lane's result."""
    grid, scene = _bit_case(grid_name, dtype)
    cpu_path = _render_and_grads(grid, dtype, backend="cpu", scene=scene, absgrad=True)
    monkeypatch.setattr(ops, "render_forward", ops.render_forward_gpu_path)
    monkeypatch.setattr(ops, "render_backward", ops.render_backward_gpu_path)
    gpu_path = _render_and_grads(grid, dtype, backend="cpu", scene=scene, absgrad=True)
    # The CPU's path one ray at a time (a build without AVX2): the record, no packs.
    monkeypatch.setattr(ops, "render_backward", ops.render_backward_one_ray)
    one_ray = _render_and_grads(grid, dtype, backend="cpu", scene=scene, absgrad=True)
    assert float(cpu_path[6].abs().max()) > 0 and float(cpu_path[5].max()) > 0 and float(cpu_path[-1].max()) > 0
    if grid_name == "stops":  # the walk crosses a batch; rays come within 10x of T_MIN
        assert int(cpu_path[4].max()) > 256 and float(cpu_path[2].max()) > 0.999
    assert len(cpu_path) == 12
    for a, b, c in zip(cpu_path, gpu_path, one_ray):
        assert torch.equal(a, b) and torch.equal(a, c)


def test_the_cpu_build_renders_packs_where_torch_dispatches_avx2(ops):
    """extensions.cpu_cflags adds -mavx2 where torch's CPU dispatch level has it; the build then renders
    8 float32 / 4 float64 rays per pack. A flag lost on the way shows here, not as a silent 1.6x slowdown."""
    if torch.backends.cpu.get_cpu_capability() not in ("AVX2", "AVX512"):
        assert ops.render_lanes(False) == 1 and ops.render_lanes(True) == 1
        return
    assert ops.render_lanes(False) == 8 and ops.render_lanes(True) == 4


def test_start_up_says_once_which_renderer_runs(ops):
    from geer_ns.render import backend as backend_module

    backend_module._announced.clear()
    said = []
    for _ in range(2):
        backend_module.announce_backend("auto", torch.device("cpu"), say=said.append)
    assert len(said) == 1, said
    lanes = "packs of 8 rays (AVX2)" if ops.render_lanes(False) == 8 else "one ray at a time"
    assert "compiled for the CPU" in said[0] and lanes in said[0], said
    assert "one compositing order per view (composite-order view)" in said[0], said
    backend_module.announce_backend("torch", torch.device("cpu"), say=said.append)
    assert said[-1] == "geer: renderer: the PyTorch renderer on cpu; one compositing order per view (composite-order view)"
    backend_module.announce_backend("auto", torch.device("cpu"), say=said.append, order="ray")
    assert said[-1].endswith("each ray in its own exact order (composite-order ray)"), said
    backend_module.announce_backend("torch", torch.device("cpu"), say=said.append, order="ray:16")
    assert said[-1].endswith("each ray in its own exact order (composite-order ray:16: the PyTorch renderer has no "
                             "window)"), said


def test_the_forward_records_blended_lanes_only_when_a_backward_will_run(ops, monkeypatch):
    """blended_lanes (32 bytes per list entry at 16-pixel tiles) is made for renders that need gradients only;
    the images are the same either way."""
    grid = reference_grids(torch.float32)["beap"]
    scene = random_scene(300, 7, around=True)
    forward, seen = ops.render_forward, []
    monkeypatch.setattr(ops, "render_forward", lambda *args: seen.append(forward(*args)) or seen[-1])
    with torch.no_grad():
        render(*scene, torch.eye(4), grid, backend="cpu")
    leaves = [t.clone().requires_grad_(True) for t in scene]
    out = render(*leaves, torch.eye(4), grid, backend="cpu")
    out.rgb.sum().backward()
    no_grad, with_grad = seen
    pairs = int(out.tile_counts.sum())  # one row per list entry, one word per warp of a 16x16 tile
    assert no_grad[5].numel() == 0 and with_grad[5].shape == (pairs, 8) and bool((with_grad[5] != 0).any())
    for a, b in zip(no_grad[:5] + no_grad[6:], with_grad[:5] + with_grad[6:]):  # max_weight too
        assert torch.equal(a, b)
