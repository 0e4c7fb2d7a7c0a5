"""The PyTorch twin's memory is bounded by `max_pairs`, forward and backward (geer_ns/render/blend.py).

Peak memory is measured as the growth of the process's peak resident set over a render and its backward
(the peak, VmHWM, reset just before the render through /proc/self/clear_refs), each in a fresh subprocess:
torch has no CPU allocator statistics, and RSS sees everything, autograd's saved tensors included. A dense scene: every Gaussian overlaps every tile, so the (ray, Gaussian) pairs
grow as rays x N.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import torch

from geer_ns.render import RayGrid, render

_SCRIPT = """
import json, resource, sys, torch
from geer_ns.render import RayGrid, render
n, max_pairs, absgrad = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "absgrad"


def status_kib(key):
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith(key))


def peak_reset():  # the peak (VmHWM) reset to the current RSS: only what follows counts
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    return status_kib("VmRSS")


def peak_kib():
    return status_kib("VmHWM")


torch.set_num_threads(1)
gen = torch.Generator().manual_seed(0)
means = torch.randn(n, 3, generator=gen) * 0.1 + torch.tensor([0.0, 0.0, 3.0])
quats = torch.randn(n, 4, generator=gen)
scales, opac, colors = torch.full((n, 3), 0.6), torch.full((n,), 0.02), torch.rand(n, 3, generator=gen)
grid = RayGrid.beap(32, 32, 0.5, 0.5, tile_size=16)
leaves = [t.requires_grad_(True) for t in (means, quats, scales, opac, colors)]
sink = torch.zeros(n, 2, requires_grad=True)
extra = {"absgrad": (torch.randn(n, 3, 2, generator=gen), sink)} if absgrad else {}
base = peak_reset()
out = render(*leaves, torch.eye(4), grid, max_pairs=max_pairs, backend="torch", **extra)
(out.rgb.sum() + out.depth.sum() + out.accumulation.sum()).backward()
print(json.dumps({"pairs": int(out.tile_counts.sum()) * 256, "mib": (peak_kib() - base) / 1024}))
"""


def _peak(n: int, max_pairs: int, absgrad: bool = False) -> dict:
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root))
    args = [str(n), str(max_pairs), "absgrad" if absgrad else "-"]
    res = subprocess.run([sys.executable, "-c", _SCRIPT, *args], env=env, cwd=root,
                         capture_output=True, text=True, timeout=300, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_peak_memory_does_not_grow_with_pairs_at_fixed_max_pairs():
    small, dense = _peak(1000, 1 << 15), _peak(4000, 1 << 15)
    assert small["pairs"] == 1000 * 1024 and dense["pairs"] == 4000 * 1024  # every Gaussian on every ray
    # 3.1M more pairs: ~300 bytes each if they were held at once (the unbounded twin), 0.9 GB. What may grow
    # is O(N): inputs, gradients, PBF, tile lists (about 1 KB per Gaussian with the preprocess graph).
    assert dense["mib"] - small["mib"] <= 16, (small, dense)
    # The measurement sees per-pair memory: a 32x larger budget holds 1M pairs at once and costs far more.
    big = _peak(1000, 1 << 20)
    assert big["mib"] - small["mib"] >= 100, (small, big)


def test_absgrad_keeps_the_memory_bound():
    """absgrad's per-pair tensors (dL/dq, dL/d(depth), each pair's dL/do_u) live inside one piece: at a fixed
    max_pairs the peak does not grow with the pairs either."""
    small, dense = _peak(1000, 1 << 15, absgrad=True), _peak(4000, 1 << 15, absgrad=True)
    assert dense["mib"] - small["mib"] <= 16, (small, dense)


def test_autograd_saves_nothing_per_pair():
    """Everything autograd keeps between forward and backward is O(N + rays + tile lists)."""
    def saved_bytes(n):
        scene = [t.requires_grad_(True) for t in _dense_scene(n)]
        grid = RayGrid.beap(16, 16, 0.5, 0.5, tile_size=8, dtype=torch.float64)
        storages = {}

        def pack(t):
            storages[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
            return t

        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            render(*scene, torch.eye(4, dtype=torch.float64), grid, max_pairs=1 << 12, backend="torch")
        return sum(storages.values())

    small, large = saved_bytes(200), saved_bytes(800)
    # 600 more Gaussians on all 256 rays: 154k more pairs, 1.2 MB per float64 saved per pair.
    assert large - small <= 600 * 1024, (small, large)


def _dense_scene(n):
    gen = torch.Generator().manual_seed(1)
    f = torch.float64
    means = torch.randn(n, 3, generator=gen, dtype=f) * 0.1 + torch.tensor([0.0, 0.0, 3.0], dtype=f)
    scales = 0.6 * (0.5 + torch.rand(n, 3, generator=gen, dtype=f))
    return (means, torch.randn(n, 4, generator=gen, dtype=f), scales,
            torch.full((n,), 0.02, dtype=f), torch.rand(n, 3, generator=gen, dtype=f))


def test_pieces_equal_one_piece():
    """Blending lists in pieces of a few pairs (with the transmittance carried) is the same image, max_weight,
    gradient and absgrad as one piece."""
    grid = RayGrid.beap(16, 16, 0.8, 0.8, tile_size=8, dtype=torch.float64)
    results = []
    lateral = torch.randn(150, 3, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    for max_pairs in (1 << 22, 64 * 7):  # 7 Gaussians x 64 rays per piece
        leaves = [t.clone().requires_grad_(True) for t in _dense_scene(150)]
        leaves[3] = (leaves[3].detach() * 10).requires_grad_(True)  # opaque enough for early termination
        sink = torch.zeros(150, 2, dtype=torch.float64, requires_grad=True)
        out = render(*leaves, torch.eye(4, dtype=torch.float64), grid, max_pairs=max_pairs, backend="torch",
                     absgrad=(lateral, sink))
        (out.rgb.square().sum() + out.depth.sum() + out.accumulation.sum()).backward()
        results.append((out, [t.grad for t in leaves] + [sink.grad]))
    (a, ga), (b, gb) = results
    assert float(a.accumulation.detach().max()) > 0.999  # some rays stopped early
    assert torch.equal(a.max_weight, b.max_weight)
    for name in ("rgb", "depth", "accumulation"):
        assert float((getattr(a, name) - getattr(b, name)).detach().abs().max()) <= 1e-12, name
    for x, y in zip(ga, gb):
        assert float((x - y).norm()) <= 1e-10 * float(x.norm())
