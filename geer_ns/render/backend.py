"""Backend selection: the CUDA kernels when they can run, the PyTorch twin otherwise.

`auto` never fails: it takes CUDA only for CUDA tensors, with kernels that have been verified on a GPU
(`cuda_backend.CUDA_VERIFIED`) and an extension that builds. An explicit `cuda` request that cannot be
honoured is an error, never a silent fallback.
"""

from __future__ import annotations

from typing import Literal

import torch

Backend = Literal["auto", "torch", "cuda"]


def cuda_extension_available() -> bool:
    """Whether the geer CUDA extension can be used: a GPU, and csrc/ builds and loads (JIT, cached)."""
    from .cuda_backend import extension_available

    return extension_available()


def resolve_backend(backend: Backend, device: torch.device) -> Literal["torch", "cuda"]:
    if backend == "torch":
        return "torch"
    if backend == "cuda":
        if device.type != "cuda":
            raise RuntimeError(f"backend='cuda' requested but the inputs live on {device}")
        if not cuda_extension_available():
            raise RuntimeError("backend='cuda' requested but the geer CUDA extension could not be built or loaded")
        return "cuda"
    if backend == "auto":
        from .cuda_backend import CUDA_VERIFIED

        # Kernels not yet verified on a GPU are opt-in (backend="cuda"); auto never triggers a build for them.
        return "cuda" if device.type == "cuda" and CUDA_VERIFIED and cuda_extension_available() else "torch"
    raise ValueError(f"backend must be 'auto', 'torch' or 'cuda', got {backend!r}")
