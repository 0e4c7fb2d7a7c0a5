"""Backend selection: the compiled pipeline when it can run, the PyTorch twin otherwise.

`auto` never fails. CPU tensors: `cpu`, the kernels' code compiled for the CPU (csrc/cpu_ops.cpp, JIT-built
on first use, multi-threaded, analytic backward, checked against the twin by tests/test_csrc_math.py;
benchmarks/cpu_training.md). CUDA tensors: `cuda` when the kernels passed their self-test on this GPU
(verdict.py: run once per GPU, driver, torch and build, in a child process, recorded beside the extension
cache). When auto cannot use them (a failed self-test or build) it renders with the PyTorch twin and says so in
one line, once. GEER_VERIFY_CPU_BUILD=1 makes auto ask the same of the CPU build. Every backend gives camera pose
and ray-direction gradients (docs/refinement.md). An explicit `cpu` or `cuda` request that cannot be honored is
an error, never a silent fallback; an explicit request runs no self-test.
"""

from __future__ import annotations

import os
import sys
import warnings
from typing import Literal

import torch

from . import extensions, verdict

Backend = Literal["auto", "torch", "cuda", "cpu"]


def cuda_extension_available() -> bool:
    """Whether the geer CUDA extension can be used: a GPU, and csrc/ builds and loads (JIT, cached)."""
    return extensions.extension_available()


_warned: set[str] = set()


def _warn_once(message: str) -> None:
    """auto's fallbacks are loud, once per process: slow silently is a bug report waiting to happen."""
    if message not in _warned:
        _warned.add(message)
        warnings.warn(message, RuntimeWarning, stacklevel=3)


def _say_once(message: str) -> None:
    """One line on stderr, once per process (the self-test fallback: why, and where the report is)."""
    if message not in _warned:
        _warned.add(message)
        print(message, file=sys.stderr, flush=True)


def kernels_verified(backend: Literal["cuda", "cpu"], device: torch.device) -> bool:
    """Whether auto may render on `device` with `backend`: its self-test verdict passed (run now, in a child
    process, when none is recorded). Otherwise says once why, and where the report is."""
    found = verdict.verify(backend, device)
    if not found.passed:
        what = "CUDA kernels" if backend == "cuda" else "compiled CPU renderer"
        _say_once(f"geer: not using the {what} on {device}: {found.reason}; rendering with the PyTorch renderer "
                  f"(report: {found.report})")
    return found.passed


def cpu_ops_available() -> bool:
    """Whether csrc/cpu_ops.cpp builds and loads here (built once per process, cached on disk)."""
    try:
        extensions.load_cpu_ops()
    except Exception:  # noqa: BLE001 - any build/load failure means "not available"; the cause is kept
        return False
    return True


def resolve_backend(backend: Backend, device: torch.device) -> Literal["torch", "cuda", "cpu"]:
    """The backend that renders tensors on `device`."""
    if backend == "torch":
        return "torch"
    if backend == "cpu":
        if device.type != "cpu":
            raise RuntimeError(f"backend='cpu' requested but the inputs live on {device}")
        try:
            extensions.load_cpu_ops()  # built once, cached
        except Exception as exc:
            raise RuntimeError("backend='cpu' requested but csrc/cpu_ops.cpp could not be built or loaded") from exc
        return "cpu"
    if backend == "cuda":
        if device.type != "cuda":
            raise RuntimeError(f"backend='cuda' requested but the inputs live on {device}")
        if not cuda_extension_available():
            raise RuntimeError("backend='cuda' requested but the geer CUDA extension could not be built or loaded")
        return "cuda"
    if backend == "auto":
        if device.type == "cpu":
            if cpu_ops_available():
                verify = os.environ.get("GEER_VERIFY_CPU_BUILD", "") not in ("", "0")
                return "cpu" if not verify or kernels_verified("cpu", device) else "torch"
            why = extensions.build_error("geer_cpu_ops")
            _warn_once(f"geer: csrc/cpu_ops.cpp could not be built or loaded ({why}); "
                       "rendering with the much slower PyTorch renderer")
            return "torch"
        if device.type != "cuda":
            return "torch"
        if not torch.cuda.is_available():
            _warn_once("geer: CUDA tensors but no usable CUDA device; rendering with the PyTorch renderer")
            return "torch"
        if not kernels_verified("cuda", device):
            return "torch"
        if not cuda_extension_available():
            _warn_once("geer: the CUDA extension could not be built or loaded; rendering with the PyTorch renderer")
            return "torch"
        return "cuda"
    raise ValueError(f"backend must be 'auto', 'torch', 'cuda' or 'cpu', got {backend!r}")


_announced: set[tuple[str, str]] = set()


def announce_backend(backend: Backend, device: torch.device, say=print, order: str = "view") -> None:
    """Say once per process (and backend request, device type and compositing order) what `backend` renders
    tensors on `device` with, and in which order (order.py): the start-up line of a training run. Fallbacks are
    announced by resolve_backend itself."""
    key = (backend, device.type, str(order))
    if key in _announced:
        return
    _announced.add(key)
    chosen = resolve_backend(backend, device)
    if chosen == "cpu":
        lanes = extensions.load_cpu_ops().render_lanes(False)
        how = f"packs of {lanes} rays (AVX2)" if lanes > 1 else "one ray at a time (no AVX2 in this build)"
        what = f"the kernels' code compiled for the CPU ({torch.get_num_threads()} threads, {how})"
    else:
        what = f"{'the CUDA kernels' if chosen == 'cuda' else 'the PyTorch renderer'} on {device}"
    say(f"geer: renderer: {what}; {order_line(str(order), chosen)}")


def order_line(order: str, chosen: str) -> str:
    """The compositing order's part of the start-up line (composite-order)."""
    if order == "view":
        return "one compositing order per view (composite-order view)"
    window = order.partition(":")[2]
    if chosen == "cuda":
        return f"each ray in its own order, holding 64 pending pairs (composite-order {order})"
    if window and chosen == "torch":  # the PyTorch renderer has no window: it sorts each ray's whole list
        return f"each ray in its own exact order (composite-order {order}: the PyTorch renderer has no window)"
    if window:
        return f"each ray in its own order, holding {window} pending pairs (composite-order {order})"
    return f"each ray in its own exact order (composite-order {order})"
