"""One rule at every clamp tie, in both backends (geer_ns/render/subgradients.py): a value exactly on its clamp
gets the clamped side's derivative. Each probe puts one value exactly on a clamp and compares the gradient of
the PyTorch twin and of the CPU build of the kernels with float64 one-sided finite differences of the twin's
forward: the difference from the clamped side is what both must give, the one from the live side shows that
the probe sits on a real kink (the two differ).

Probes: an SH colour exactly 0 (degree 0: C0 c + 0.5 == 0 in float64), alpha exactly at its 0.99 cap (a ray
through the centre of a Gaussian of opacity 0.99: q = 0), a depth max(t*, 0) with t* exactly 0 (a Gaussian in
the camera's plane), and a scale exactly at MIN_SCALE (the per-Gaussian stage; no render shows it).
"""

from __future__ import annotations

import math
import shutil

import pytest
import torch

from geer_ns.render import RayGrid, cuda_backend, render
from geer_ns.render.transforms import MIN_SCALE, quat_to_rotmat, whitening

F64 = torch.float64
BACKENDS = ("torch", "cpu")
H = 1e-7  # one-sided step in the probed parameter (float64)


@pytest.fixture(scope="module")
def ops():
    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler: cannot build csrc/cpu_ops.cpp")
    return cuda_backend.load_cpu_ops()


def _one_ray() -> RayGrid:
    """A single ray along the optical axis, exactly (0, 0, 1)."""
    return RayGrid.from_rays(torch.tensor([[[0.0, 0.0, 1.0]]], dtype=F64), tile_size=8)


def _gaussian(mean, opacity=0.8, colors=None):
    """One isotropic Gaussian (scale 0.5, identity rotation) as render's inputs, float64."""
    return [torch.tensor([mean], dtype=F64), torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64),
            torch.full((1, 3), 0.5, dtype=F64), torch.tensor([opacity], dtype=F64),
            torch.tensor([[0.3, 0.5, 0.7]], dtype=F64) if colors is None else colors]


def _probe(scene, field: int, index, loss, backend: str, sh_degree=None):
    """(gradient of loss w.r.t. scene[field][index] from `backend`, one-sided differences (below, above) of
    the twin's forward)."""
    grid, vm = _one_ray(), torch.eye(4, dtype=F64)

    def value(delta: float) -> float:
        moved = [t.clone() for t in scene]
        moved[field][index] += delta
        with torch.no_grad():
            return float(loss(render(*moved, vm, grid, sh_degree=sh_degree, backend="torch")))

    leaves = [t.clone().requires_grad_(True) for t in scene]
    loss(render(*leaves, vm, grid, sh_degree=sh_degree, backend=backend)).backward()
    at = value(0.0)
    return float(leaves[field].grad[index]), ((at - value(-H)) / H, (value(H) - at) / H)


def _assert_clamped_side(grad: float, below: float, above: float, clamped: str, backend: str) -> None:
    want, live = (below, above) if clamped == "below" else (above, below)
    assert abs(live - want) > 1e-2, f"not a kink: one-sided differences {below} and {above}"
    assert abs(grad - want) <= 1e-5 * max(1.0, abs(live)), (
        f"{backend}: gradient {grad} at the tie; the clamped side ({clamped}) gives {want}, the live side {live}")


def _sh_coefficient_on_the_clamp() -> float:
    """c with C0 c + 0.5 == 0 exactly in float64 (sh.py's and geer_math.h's arithmetic)."""
    c0 = 0.5 / math.sqrt(math.pi)
    c = -0.5 / c0
    for _ in range(64):
        raw = torch.tensor(c0, dtype=F64) * torch.tensor(c, dtype=F64) + 0.5
        if float(raw) == 0.0:
            return c
        c = math.nextafter(c, math.inf if float(raw) < 0 else -math.inf)
    raise AssertionError("no float64 coefficient puts the colour exactly on 0")


@pytest.mark.parametrize("backend", BACKENDS)
def test_sh_colour_exactly_zero(ops, backend):
    """Red is C0 c + 0.5 = 0: raising c brightens it, lowering c leaves it clamped at 0 (the clamped side)."""
    sh = torch.tensor([[[_sh_coefficient_on_the_clamp(), 0.2, 0.1]]], dtype=F64)  # [N, 1, 3]: degree 0
    scene = _gaussian([0.0, 0.0, 2.0], colors=sh)
    grad, (below, above) = _probe(scene, 4, (0, 0, 0), lambda out: out.rgb[..., 0].sum(), backend, sh_degree=0)
    assert above > 0.1  # the probe: 0.141 from the CPU build, 0 from torch's clamp_min
    _assert_clamped_side(grad, below, above, "below", backend)


@pytest.mark.parametrize("backend", BACKENDS)
def test_alpha_exactly_at_its_cap(ops, backend):
    """Opacity 0.99 seen through its centre: alpha = min(0.99, 0.99 exp(0)) sits on the cap; more opacity
    changes nothing (the clamped side), less lowers alpha."""
    scene = _gaussian([0.0, 0.0, 2.0], opacity=0.99)
    grad, (below, above) = _probe(scene, 3, 0, lambda out: out.rgb.sum(), backend)
    assert above == 0.0 and below > 1.0
    _assert_clamped_side(grad, below, above, "above", backend)


@pytest.mark.parametrize("backend", BACKENDS)
def test_depth_exactly_at_the_half_line_kink(ops, backend):
    """A Gaussian in the camera's plane (z = 0) beside the ray: t* = 0, depth = max(t*, 0) = 0. Moving it
    forward puts its peak in front (depth grows), moving it back keeps depth 0 (the clamped side); q is C^1
    there, so the accumulation has no kink."""
    scene = _gaussian([0.3, 0.0, 0.0])
    grad, (below, above) = _probe(scene, 0, (0, 2), lambda out: out.depth.sum(), backend)
    assert above == pytest.approx(1.0, abs=1e-5) and below == 0.0
    _assert_clamped_side(grad, below, above, "below", backend)


def test_scale_exactly_at_min_scale(ops):
    """W = S^-1 R^T with the scale clamped at MIN_SCALE: one scale exactly on it, against one-sided differences
    of the twin's whitening (the per-Gaussian stage; a render never resolves a 1e-12 scale)."""
    gen = torch.Generator().manual_seed(0)
    quats = torch.randn(1, 4, generator=gen, dtype=F64)
    scales = torch.tensor([[0.3, MIN_SCALE, 0.2]], dtype=F64)
    g_w = torch.randn(1, 3, 3, generator=gen, dtype=F64)
    rot = quat_to_rotmat(quats)
    step = 1e-8 * MIN_SCALE

    def value(delta: float) -> float:
        s = scales.clone()
        s[0, 1] += delta
        return float((g_w * whitening(rot, s)).sum())

    at = value(0.0)
    below, above = (at - value(-step)) / step, (value(step) - at) / step
    leaf = scales.clone().requires_grad_(True)
    (g_w * whitening(rot, leaf)).sum().backward()
    means_c = torch.tensor([[0.1, 0.2, 3.0]], dtype=F64)
    zeros = torch.zeros(1, 3, dtype=F64)
    k = g_w @ whitening(rot, scales).transpose(-1, -2)  # the kernels' canonical moment K = dL/dW W^T
    kernels = ops.preprocess_backward(means_c, quats, scales, torch.zeros(1, 0, 3, dtype=F64), zeros,
                                      torch.eye(3, dtype=F64), -1, k.contiguous(), zeros, zeros, False)[2]
    for name, grad in (("torch", leaf.grad[0, 1]), ("cpu", kernels[0, 1])):
        _assert_clamped_side(float(grad), below, above, "below", name)
