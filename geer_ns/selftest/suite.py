"""The self-test suite: the compiled renderer (`cuda` or `cpu`) against the PyTorch renderer on fixed scenes.

Every case renders forward and backward with both renderers on the same inputs and compares with the
tolerances the CPU-build tests use (tests/test_csrc_math.py):
  images (rgb, depth, accumulation)  float64 1e-10; float32 1e-5, except up to 1/500 of the pixels (a pair
                                      exactly on the 1/255 threshold may round either way) and at most 1e-2;
  max_weight                          the same rule, per Gaussian;
  gradients (every parameter, absgrad's sums)
                                      float64 1e-8 relative (1e-7 on the degenerate scenes); float32: no further
                                      from the float64 gradient than 10x the PyTorch renderer's float32 one.
The capacity case (>= 1M Gaussians at 1920 x 1080, CUDA only) renders the whole view with the compiled renderer
and a loss on a 64 x 64 window of it; the PyTorch renderer renders that window's rays alone (rays are
independent, so the window's images and the loss's gradients are the same), compared in float32 with 1e-3 on
the gradients (a float64 or full-view PyTorch reference of that size costs more than the whole test).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from geer_ns.cameras.shutter import rolling_rays
from geer_ns.render import MovingRays, RayGrid, render

from .scenes import Scene, camera, gap_scene, random_gaussians, stress_scene

F32, F64 = torch.float32, torch.float64
FIELDS = ("means", "quats", "scales", "opacities", "colors")
BACKGROUND = (0.2, 0.3, 0.4)


@dataclass(frozen=True)
class Case:
    """One self-test render: a scene seen by one camera in one precision, absgrad on or off."""

    name: str
    scene: Callable[[], Scene]
    camera: str
    size: int
    dtype: torch.dtype
    absgrad: bool = False
    degenerate: bool = False  # the float64 gradient tolerance of the stress scenes (1e-7)
    capacity: bool = False
    rolling: bool = False  # every ray at its own pose (a rolling shutter: per-ray origins, moved directions)
    order: str = "view"  # the compositing order (render/order.py): "ray", each ray's own (the kernels: a window of 64)


def _mixed(seed: int) -> Scene:
    """The stress Gaussians among random ones all around the camera."""
    return tuple(torch.cat([a, b]) for a, b in zip(stress_scene(), random_gaussians(40, seed, around=True)))  # type: ignore


def capacity_scene(n: int = 1 << 20) -> Scene:
    """n small random Gaussians in front of the camera (the capacity case)."""
    return random_gaussians(n, 7, around=False, scale_range=(0.003, 0.05))


def suite(device_type: str) -> list[Case]:
    """The fixed suite. On the CPU (what CI runs against the CPU build) the same cases at a few seconds of
    compute; on a GPU at larger sizes, and the capacity case."""
    big = device_type == "cuda"
    s = 64 if big else 24
    cases = []
    for dtype in (F32, F64):
        tag = "f32" if dtype == F32 else "f64"
        cases += [
            Case(f"stress-fisheye200-{tag}", _mixed_0, "fisheye200", s, dtype, absgrad=True, degenerate=True),
            Case(f"stress-panorama-{tag}", _mixed_0, "panorama", s, dtype, degenerate=True),
            Case(f"random-beap-{tag}", _front, "beap", 2 * s if big else s, dtype, absgrad=True),
            Case(f"gap-beap1px-{tag}", _gap_0, "beap1", s // 2, dtype, absgrad=True, degenerate=True),
            Case(f"rolling-fisheye200-{tag}", _mixed_0, "fisheye200", s, dtype, absgrad=True, degenerate=True,
                 rolling=True),
        ]
        if dtype == F64:  # float32 near-ties of two keys would flip a pixel's order between the builds
            cases.append(Case("ray-order-beap-f64", _front, "beap", 2 * s if big else s, dtype, absgrad=True,
                              order="ray"))
    if big:
        cases.append(Case("capacity-1M-1920x1080-f32", capacity_scene, "pinhole1080", 1920, F32, capacity=True))
    return cases


def _mixed_0() -> Scene:
    return _mixed(2)


def _front() -> Scene:
    return random_gaussians(120, 11, around=False)


def _gap_0() -> Scene:
    return gap_scene(1370)  # the CPU build's float32 scale gradient was 8.4 (relative) off before the fix


WINDOW = (slice(500, 564), slice(900, 964))  # the capacity case's compared rays (rows, columns)


def _grid(case: Case, dtype, window: bool = False) -> RayGrid:
    if case.camera == "pinhole1080":
        full = RayGrid.beap(1920, 1080, math.radians(90), math.radians(60), tile_size=16, dtype=dtype)
        return RayGrid.from_rays(full.dirs.reshape(1080, 1920, 3)[WINDOW], None, tile_size=16) if window else full
    return camera(case.camera, case.size, dtype)


@dataclass
class Rendered:
    """What a case compares: images, max_weight, gradients (per field, then absgrad's sums)."""

    images: list[Tensor]
    max_weight: Tensor
    grads: list[Tensor]


def render_case(case: Case, backend: str, device: torch.device, dtype, perturb: float = 0.0) -> Rendered:
    """Forward and backward of `case` with `backend` in `dtype` (float64 inputs rounded to it); `perturb`
    scales the rgb output (a planted disagreement)."""
    window = case.capacity and backend == "torch"  # the PyTorch renderer: the window's rays only
    grid = _grid(case, dtype, window).to(device)
    leaves = [t.to(device, dtype).clone().requires_grad_(True) for t in case.scene()]
    n = leaves[0].shape[0]
    absgrad = None
    if case.absgrad:
        lateral = torch.randn(n, 3, 2, generator=torch.Generator().manual_seed(20), dtype=F64).to(device, dtype)
        absgrad = (lateral, torch.zeros(n, 2, dtype=dtype, device=device, requires_grad=True))
    viewmat, motion = torch.eye(4, dtype=dtype, device=device), None
    if case.rolling:
        viewmat, motion = _rolling(grid, dtype, device)
    out = render(*leaves, viewmat, grid, backend=backend, motion=motion, order=case.order,
                 background=torch.tensor(BACKGROUND, dtype=dtype, device=device), absgrad=absgrad)
    rgb = out.rgb * (1.0 + perturb) if perturb else out.rgb
    gen = torch.Generator().manual_seed(1)
    h, w = rgb.shape[:2]
    wh, ww = (64, 64) if case.capacity else (h, w)
    wr, wd, wa = (torch.randn(wh, ww, c, generator=gen, dtype=F64) for c in (3, 1, 1))
    if case.capacity and not window:  # the same loss on the window, zero elsewhere
        wr, wd, wa = (_embed(x, h, w) for x in (wr, wd, wa))
    wr, wd, wa = (x.to(device, dtype) for x in (wr, wd, wa))
    ((wr * rgb).sum() + 0.1 * (wd * out.depth).sum() + (wa * out.accumulation).sum()).backward()
    grads = [t.grad.detach() for t in leaves] + ([absgrad[1].grad.detach()] if absgrad else [])
    images = [rgb.detach(), out.depth.detach(), out.accumulation.detach()]
    if case.capacity and not window:
        images = [x[WINDOW] for x in images]
    return Rendered(images, out.max_weight.detach(), grads)


def _rolling(grid: RayGrid, dtype, device) -> tuple[Tensor, MovingRays]:
    """A fast readout over the grid's rows (6 degrees of turn, 0.2 units of travel), as rolling_rays gives it."""
    times = torch.linspace(0.0, 1.0, grid.height, dtype=F64).repeat_interleave(grid.width)
    end = torch.eye(4, dtype=F64)
    end[:3, :3] = torch.linalg.matrix_exp(torch.tensor([[0, -0.08, 0.06], [0.08, 0, -0.03], [-0.06, 0.03, 0]],
                                                       dtype=F64))
    end[:3, 3] = torch.tensor([0.12, -0.1, 0.12], dtype=F64)
    viewmat, origins, dirs, offset = rolling_rays(grid.dirs.cpu().double(), times, torch.eye(4, dtype=F64), end)
    return viewmat.to(device, dtype), MovingRays(origins.to(device, dtype), dirs.to(device, dtype), offset)


def _embed(x: Tensor, h: int, w: int) -> Tensor:
    full = torch.zeros(h, w, x.shape[-1], dtype=x.dtype)
    full[WINDOW] = x
    return full


def image_error(ours: Tensor, ref: Tensor, dtype) -> tuple[bool, str]:
    """The CPU-build tests' image rule (module docstring): (passed, what was measured)."""
    err = (ours.double() - ref.double()).abs()
    err = err.reshape(-1, ref.shape[-1]).amax(-1) if ref.ndim > 1 else err  # per pixel: its worst channel
    scale = max(1.0, float(ref.abs().max())) if ref.numel() else 1.0
    worst = float(err.max()) if err.numel() else 0.0
    if dtype == F64:
        return worst <= 1e-10 * scale, f"max {worst:.2e} (limit {1e-10 * scale:.0e})"
    off = int((err > 1e-5 * scale).sum())
    allowed = max(2, err.numel() // 500)
    return off <= allowed and worst <= 1e-2 * scale, f"{off} values off by > 1e-5 (allowed {allowed}), max {worst:.2e}"


def rel(a: Tensor, b: Tensor) -> float:
    """|a - b| / |b| (Frobenius), 0 when both are 0."""
    a, b = a.double(), b.double()
    return float((a - b).norm() / b.norm().clamp_min(1e-300)) if float(b.norm()) > 0 else float(a.norm())


def grad_error(ours: Tensor, twin: Tensor, truth: Tensor | None, dtype, degenerate: bool) -> tuple[bool, str]:
    """float64: relative to the twin; float32: relative to the float64 truth, at most 10x the twin's plus 1e-5
    (relative errors: the floor keeps a twin whose rounding errors happened to cancel from failing the kernels);
    without a truth (capacity, the sentinel), 1e-3 relative to the twin's float32 gradient."""
    if not bool(torch.isfinite(ours).all()):
        return False, "not finite"
    if dtype == F64:
        limit = 1e-7 if degenerate else 1e-8
        e = rel(ours, twin)
        return e <= limit, f"{e:.2e} relative (limit {limit:.0e})"
    if truth is None:
        e = rel(ours, twin)
        return e <= 1e-3, f"{e:.2e} relative to the float32 twin (limit 1e-3)"
    ours_e, twin_e = rel(ours, truth), rel(twin, truth)
    return ours_e <= 10 * twin_e + 1e-5, f"{ours_e:.2e} from float64 (the twin's float32: {twin_e:.2e})"


def run_case(case: Case, backend: str, device: torch.device, perturb: float = 0.0) -> dict:
    """One case: {"case", "passed", "checks": {what: measured}, "failed": [what], "seconds"}."""
    start = time.perf_counter()
    ours = render_case(case, backend, device, case.dtype, perturb)
    twin = render_case(case, "torch", device, case.dtype)
    truth = None if case.dtype == F64 or case.capacity else render_case(case, "torch", device, F64)
    checks, failed = {}, []
    compared = ("rgb", "depth", "accumulation") + (() if case.capacity else ("max_weight",))  # per ray: the window
    for name, a, b in zip(compared, ours.images + [ours.max_weight], twin.images + [twin.max_weight]):
        ok, what = image_error(a, b, case.dtype)
        checks[name] = what
        failed += [] if ok else [name]
    names = FIELDS + (("absgrad",) if case.absgrad else ())
    for k, name in enumerate(names):
        ok, what = grad_error(ours.grads[k], twin.grads[k], None if truth is None else truth.grads[k], case.dtype,
                              case.degenerate)
        checks[f"grad {name}"] = what
        failed += [] if ok else [f"grad {name}"]
    return {"case": case.name, "passed": not failed, "checks": checks, "failed": failed,
            "seconds": round(time.perf_counter() - start, 3)}
