"""The CUDA kernels on a GPU against the PyTorch twin (skipped without CUDA).

tests/test_csrc_math.py already checks the kernels' math on the CPU; this adds what only a GPU exercises:
the JIT build, shared-memory batches (lists longer than one batch), warp padding (tile sizes that are not
a multiple of 32 rays), both render builds (blocks up to 256 and up to 1024 threads, in both precisions),
warp-reduced atomics (max_weight's and absgrad's too), the radix sort and tile ranges, launch errors raised at
their own call, and float64 backward repeatability. backend="auto" chooses the kernels on a GPU where their
self-test passed (geer_ns/render/verdict.py, docs/cuda.md).
"""

from __future__ import annotations

import math
import time

import pytest
import torch
from conftest import (
    random_scene,
    random_viewmat,
    reference_grids,
    WIDE_GRIDS,
)

from geer_ns.render import RayGrid, cuda_backend, render

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")

F32, F64 = torch.float32, torch.float64
FIELDS = ("means", "quats", "scales", "opacities", "colors", "means_c")
DEV = "cuda"


@pytest.fixture(scope="module")
def cuda_ops():
    t0 = time.time()
    ops = cuda_backend.load_extension(verbose=True)
    print(f"geer_cuda built/loaded in {time.time() - t0:.1f} s")
    return ops


def _grids(dtype):
    """{name: (grid on the GPU, whether the scene should surround the camera)}."""
    return {name: (grid.to(DEV), name in WIDE_GRIDS) for name, grid in reference_grids(dtype).items()}


def _scene(n, seed, around, dtype, **kw):
    return [t.to(DEV, dtype) for t in random_scene(n, seed, around=around, **kw)]


def _image_close(ours, ref, dtype, name):
    err = (ours - ref).abs().amax(-1).reshape(-1).double()
    scale = max(1.0, float(ref.abs().max()))
    if dtype == F64:
        assert float(err.max()) <= 1e-10 * scale, f"{name}: {float(err.max()):.3e}"
        return
    bad = err > 1e-5 * scale  # float32: pairs exactly on the 1/255 threshold may round either way
    assert int(bad.sum()) <= max(2, err.numel() // 500), f"{name}: {int(bad.sum())} pixels off"
    assert float(err.max()) <= 1e-2 * scale, f"{name}: {float(err.max()):.3e}"


def _grads(fn, inputs, seed):
    leaves = [t.detach().clone().requires_grad_(True) for t in inputs]
    out = fn(*leaves)
    gen = torch.Generator().manual_seed(seed)
    h, w = out.rgb.shape[:2]
    tr, td, ta = (torch.rand(h, w, c, generator=gen, dtype=F64).to(out.rgb) for c in (3, 1, 1))
    loss = ((out.rgb - tr) ** 2).sum() + 0.1 * ((out.depth - 3 * td) ** 2).sum() + ((out.accumulation - ta) ** 2).sum()
    loss.backward()
    return [t.grad for t in leaves] + [out.means_c.grad]


def _rel(a, b):
    return float((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-300))


@pytest.mark.parametrize("dtype", [F32, F64])
@pytest.mark.parametrize("grid_name", ["beap", "fisheye180", "equirect360"])
def test_forward_matches_twin(cuda_ops, grid_name, dtype):
    grid, around = _grids(dtype)[grid_name]
    scene = _scene(300, 11, around, dtype)
    vm = (random_viewmat(3, translation_scale=0.2) if around else torch.eye(4, dtype=F64)).to(DEV, dtype)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype, device=DEV)
    ref = render(*scene, vm, grid, background=bg, backend="torch")
    ours = cuda_backend.render_cuda(*scene, vm, grid, background=bg, ops=cuda_ops)
    for name in ("rgb", "depth", "accumulation"):
        _image_close(getattr(ours, name), getattr(ref, name), dtype, name)
    assert torch.equal(ours.visible, ref.visible)
    if grid_name != "beap":
        assert torch.equal(ours.tile_counts, ref.tile_counts)
    # Same math on the CPU (geer_math.h in plain loops): isolates GPU plumbing from math.
    if dtype == F64:
        cpu = cuda_backend.render_cuda(*[t.cpu() for t in scene], vm.cpu(), grid, background=bg.cpu(),
                                       ops=cuda_backend.load_cpu_ops())
        for name in ("rgb", "depth", "accumulation"):
            assert float((getattr(ours, name).cpu() - getattr(cpu, name)).abs().max()) <= 1e-12, name
        assert torch.equal(ours.tile_counts.cpu(), cpu.tile_counts)


@pytest.mark.parametrize("grid_name", ["beap", "fisheye180", "equirect360"])
@pytest.mark.parametrize("degree", [None, 3])
def test_gradients_match_twin_float64(cuda_ops, grid_name, degree):
    grid, around = _grids(F64)[grid_name]
    means, quats, scales, opac, colors = _scene(120, 5, around, F64, spread=0.8)
    if degree is not None:
        colors = torch.randn(120, 16, 3, generator=torch.Generator().manual_seed(1), dtype=F64).to(DEV) * 0.4
    vm = (random_viewmat(2, translation_scale=0.1) if around else torch.eye(4, dtype=F64)).to(DEV)
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=F64, device=DEV)
    inputs = (means, quats, scales, opac, colors)
    ref = _grads(lambda *a: render(*a, vm, grid, sh_degree=degree, background=bg, backend="torch"), inputs, 0)
    ours = _grads(lambda *a: cuda_backend.render_cuda(*a, vm, grid, sh_degree=degree, background=bg, ops=cuda_ops),
                  inputs, 0)
    for name, a, b in zip(FIELDS, ours, ref):
        assert _rel(a, b) <= 1e-8, f"{name}: {_rel(a, b):.3e}"


def test_float32_gradients_close_to_float64(cuda_ops):
    grid = RayGrid.beap(64, 64, math.radians(60), math.radians(60), tile_size=16).to(DEV)
    scene = random_scene(200, 8, spread=0.5, scale_range=(0.05, 0.3), opacity_range=(0.1, 0.8))
    g64 = _grads(lambda *a: render(*a, torch.eye(4, dtype=F64, device=DEV), grid, backend="torch"),
                 [t.to(DEV) for t in scene], 1)
    g32 = _grads(lambda *a: cuda_backend.render_cuda(*a, torch.eye(4, device=DEV), grid, ops=cuda_ops),
                 [t.to(DEV, F32) for t in scene], 1)
    for name, a, b in zip(FIELDS, g32, g64):
        assert _rel(a, b) <= 1e-3, f"{name}: {_rel(a, b):.3e}"


@pytest.mark.parametrize("tile_size", [1, 4, 7, 8, 16, 17, 32])
def test_tile_sizes_and_long_lists(cuda_ops, tile_size):
    """Warp padding (tile_size^2 not a multiple of 32), the 1024-thread build (tiles 17 and 32; float64's
    backward spills there), and lists much longer than one shared-memory batch (256 float32 / 128 float64
    Gaussians), with rays stopping inside a batch."""
    for dtype in (F32, F64):
        grid = RayGrid.beap(40, 36, math.radians(50), math.radians(45), tile_size=tile_size, dtype=dtype).to(DEV)
        scene = _scene(1500, 3, False, dtype, spread=0.3, scale_range=(0.05, 0.2), opacity_range=(0.02, 0.3))
        vm = torch.eye(4, dtype=dtype, device=DEV)
        ref = render(*scene, vm, grid, backend="torch")
        ours = cuda_backend.render_cuda(*scene, vm, grid, ops=cuda_ops)
        assert int(ref.tile_counts.max()) > 600
        for name in ("rgb", "depth", "accumulation"):
            _image_close(getattr(ours, name), getattr(ref, name), dtype, name)
        if dtype == F64:
            g_ref = _grads(lambda *a, g=grid, v=vm: render(*a, v, g, backend="torch"), scene, 2)
            g_ours = _grads(lambda *a, g=grid, v=vm: cuda_backend.render_cuda(*a, v, g, ops=cuda_ops), scene, 2)
            for name, a, b in zip(FIELDS, g_ours, g_ref):
                assert _rel(a, b) <= 1e-8, f"{name}: {_rel(a, b):.3e}"


@pytest.mark.parametrize("tile_size", [7, 16, 32])
def test_absgrad_and_max_weight_match_the_cpu_build(cuda_ops, tile_size):
    """max_weight (a warp max, one atomicMax on the weight's bits per warp and entry) and absgrad (the kAbsgrad
    backward build: the 2-value butterfly, lane 0's atomics), in both render builds (tile 32: 1024 threads),
    against the CPU build, which runs the same headers: float64 to rounding (atomics add in any order), float32
    close (the GPU's __expf, rsqrtf and FMAs; a pair exactly on the 1/255 threshold may round either way)."""
    cpu_ops = cuda_backend.load_cpu_ops()
    for dtype in (F32, F64):
        grid = RayGrid.beap(40, 36, math.radians(60), math.radians(50), tile_size=tile_size, dtype=dtype)
        scene = random_scene(400, 6, spread=0.5, scale_range=(0.05, 0.3))
        lateral = torch.randn(400, 3, 2, generator=torch.Generator().manual_seed(1), dtype=F64)
        results = []
        for device, ops in ((DEV, cuda_ops), ("cpu", cpu_ops)):
            leaves = [t.to(device, dtype).requires_grad_(True) for t in scene]
            sink = torch.zeros(400, 2, dtype=dtype, device=device, requires_grad=True)
            out = cuda_backend.render_cuda(*leaves, torch.eye(4, dtype=dtype, device=device), grid.to(device),
                                           ops=ops, absgrad=(lateral.to(device, dtype), sink))
            (out.rgb.square().sum() + out.depth.sum()).backward()
            results.append((out.max_weight.cpu(), sink.grad.cpu()))
        (weight, absgrad), (weight_cpu, absgrad_cpu) = results
        assert float(weight_cpu.max()) > 0.5 and float(absgrad_cpu.abs().max()) > 0
        if dtype == F64:
            assert float((weight - weight_cpu).abs().max()) <= 1e-12
            assert _rel(absgrad, absgrad_cpu) <= 1e-12
        else:
            assert int(((weight - weight_cpu).abs() > 1e-5).sum()) <= 2
            assert _rel(absgrad, absgrad_cpu) <= 1e-3


def test_deterministic_forward(cuda_ops):
    grid, _ = _grids(F32)["fisheye180"]
    scene = _scene(2000, 4, True, F32)
    vm = torch.eye(4, device=DEV)
    a = cuda_backend.render_cuda(*scene, vm, grid, ops=cuda_ops)
    b = cuda_backend.render_cuda(*scene, vm.cpu(), grid, ops=cuda_ops)  # a host pose works too (copied over)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth)


def test_float64_backward_repeatable(cuda_ops):
    """The backward sums per-pair gradients with atomics, whose order varies between runs: in float64 two runs
    may differ by that rounding only (relative 1e-12), never by a race. Prints the observed difference."""
    grid, _ = _grids(F64)["fisheye180"]
    means, quats, scales, opac, _ = _scene(400, 9, True, F64)
    colors = torch.randn(400, 16, 3, generator=torch.Generator().manual_seed(2), dtype=F64).to(DEV) * 0.4
    vm = torch.eye(4, dtype=F64, device=DEV)
    run = lambda: _grads(lambda *a: cuda_backend.render_cuda(*a, vm, grid, sh_degree=3, ops=cuda_ops),
                         (means, quats, scales, opac, colors), 3)
    first, second = run(), run()
    worst = max(_rel(a, b) for a, b in zip(first, second))
    same = all(torch.equal(a, b) for a, b in zip(first, second))
    print(f"float64 backward, two runs: max relative difference {worst:.3e} (bitwise equal: {same})")
    assert worst <= 1e-12


def test_failed_launch_raises_at_its_own_call(cuda_ops):
    """Every launch is checked where it happens: a block the hardware refuses (2048 threads) raises from that
    call, naming the kernel, and leaves no error behind for the next, unrelated operation."""
    like = torch.zeros(1, device=DEV)
    assert int(cuda_ops.launch_probe(like, 1024)) == 1024
    with pytest.raises(RuntimeError, match=r"launch of probe_kernel failed: cudaErrorInvalidConfiguration"):
        cuda_ops.launch_probe(like, 2048)
    assert float((torch.arange(4.0, device=DEV) * 2).sum()) == 12.0
    torch.cuda.synchronize()
    assert int(cuda_ops.launch_probe(like, 33)) == 33



@pytest.mark.parametrize("tile_size", [16, 32])
def test_rolling_shutter_matches_the_cpu_build(cuda_ops, tile_size):
    """Per-ray origins (rolling shutter, render.cu kOrigin): images and the Gaussians', origins' and directions'
    gradients of the kernels against the CPU build, float64, both block builds."""
    from geer_ns.cameras.shutter import rolling_rays
    from geer_ns.render import MovingRays
    from geer_ns.render.extensions import load_cpu_ops

    grid_cpu = RayGrid.beap(48, 40, math.radians(80), math.radians(70), tile_size=tile_size)
    times = torch.linspace(0, 1, grid_cpu.height, dtype=F64).repeat_interleave(grid_cpu.width)
    start, end = torch.eye(4, dtype=F64), torch.eye(4, dtype=F64)
    end[:3, :3] = torch.linalg.matrix_exp(torch.tensor([[0, -0.08, 0.05], [0.08, 0, -0.02], [-0.05, 0.02, 0]], dtype=F64))
    end[:3, 3] = torch.tensor([0.15, -0.05, 0.1], dtype=F64)
    viewmat, origins, dirs, offset = rolling_rays(grid_cpu.dirs.double(), times, start, end)
    scene = random_scene(150, 9, spread=0.6)
    results = []
    for device, ops in (("cpu", load_cpu_ops()), (DEV, cuda_ops)):
        leaves = [t.to(device, F64).requires_grad_(True) for t in scene]
        org, dr = origins.to(device).requires_grad_(True), dirs.to(device).requires_grad_(True)
        out = cuda_backend.render_cuda(*leaves, viewmat.to(device), grid_cpu.to(device), ops=ops,
                                       motion=MovingRays(org, dr, offset))
        weights = torch.rand(out.rgb.shape, generator=torch.Generator().manual_seed(2), dtype=F64).to(device)
        (out.rgb * weights).sum().backward()
        results.append([out.rgb.detach().cpu()] + [t.grad.cpu() for t in leaves + [org, dr]])
    for name, a, b in zip(("rgb", "means", "quats", "scales", "opacities", "colors", "origins", "dirs"), *results):
        assert _rel(b, a) <= 1e-9, f"{name}: {_rel(b, a):.3e}"


@pytest.mark.parametrize("tile_size", [16, 32])
@pytest.mark.parametrize("dtype", [F32, F64])
def test_per_ray_order_matches_the_cpu_build(cuda_ops, tile_size, dtype):
    """Each ray in its own order (render_order.cu, a window of 64 pending pairs): images, max_weight and every
    gradient of the kernels against the CPU build's window of 64 (the same walk, geer_order.h), both blocks; float64
    to 1e-9, float32 to 1e-4 (the kernels' atomics sum in another order)."""
    from geer_ns.render.extensions import load_cpu_ops

    grid_cpu = RayGrid.beap(48, 40, math.radians(80), math.radians(70), tile_size=tile_size, dtype=dtype)
    scene = random_scene(150, 9, spread=0.6, scale_range=(0.05, 0.6))
    results = []
    for device, ops in (("cpu", load_cpu_ops()), (DEV, cuda_ops)):
        leaves = [t.to(device, dtype).requires_grad_(True) for t in scene]
        out = cuda_backend.render_cuda(*leaves, torch.eye(4, dtype=dtype, device=device), grid_cpu.to(device), ops=ops,
                                       order="ray:64")
        weights = torch.rand(out.rgb.shape, generator=torch.Generator().manual_seed(2), dtype=F64).to(device, dtype)
        ((out.rgb * weights).sum() + out.depth.sum()).backward()
        results.append([out.rgb.detach().cpu(), out.max_weight.cpu()] + [t.grad.cpu() for t in leaves])
    tol = 1e-9 if dtype == F64 else 1e-4
    for name, a, b in zip(("rgb", "max_weight", "means", "quats", "scales", "opacities", "colors"), *results):
        assert _rel(b, a) <= tol, f"{name}: {_rel(b, a):.3e}"
