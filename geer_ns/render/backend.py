"""Backend selection: the CUDA kernels when they can run, the PyTorch twin otherwise.

`auto` never fails: it takes CUDA only for CUDA tensors, with kernels that have been verified on a GPU
(`cuda_backend.CUDA_VERIFIED`) and an extension that builds. An explicit `cuda` request that cannot be
honoured is an error, never a silent fallback. `cpu` (opt-in) runs the kernels' shared math compiled for
the CPU (csrc/cpu_ops.cpp, JIT-built on first use): single-threaded, analytic backward, ~3x faster than
the PyTorch twin for training on a CPU (benchmarks/cpu_training.md).
"""

from __future__ import annotations

import warnings
from typing import Literal

import torch

Backend = Literal["auto", "torch", "cuda", "cpu"]


def cuda_extension_available() -> bool:
    """Whether the geer CUDA extension can be used: a GPU, and csrc/ builds and loads (JIT, cached)."""
    from .cuda_backend import extension_available

    return extension_available()


_warned: set[str] = set()


def _warn_once(message: str) -> None:
    """auto's fallbacks are loud, once per process: slow silently is a bug report waiting to happen."""
    if message not in _warned:
        _warned.add(message)
        warnings.warn(message, RuntimeWarning, stacklevel=3)


def resolve_backend(backend: Backend, device: torch.device) -> Literal["torch", "cuda", "cpu"]:
    if backend == "torch":
        return "torch"
    if backend == "cpu":
        if device.type != "cpu":
            raise RuntimeError(f"backend='cpu' requested but the inputs live on {device}")
        from .cuda_backend import load_cpu_ops

        try:
            load_cpu_ops()  # built once, cached
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
        from .cuda_backend import CUDA_VERIFIED

        # Kernels not yet verified on a GPU are opt-in (backend="cuda"); auto never triggers a build for them.
        if device.type != "cuda":
            return "torch"
        if not CUDA_VERIFIED:
            _warn_once("geer: CUDA tensors are rendered by the PyTorch renderer: the CUDA kernels are not yet "
                       "verified on a GPU (pass backend='cuda' to use them anyway)")
            return "torch"
        if not cuda_extension_available():
            _warn_once("geer: the CUDA extension could not be built or loaded; rendering with the PyTorch renderer")
            return "torch"
        return "cuda"
    raise ValueError(f"backend must be 'auto', 'torch', 'cuda' or 'cpu', got {backend!r}")
