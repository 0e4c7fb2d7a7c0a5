"""Backend selection: the CUDA kernels when they can run, the PyTorch twin otherwise.

`auto` never fails: it takes CUDA only for CUDA tensors with a built extension. An explicit `cuda`
request that cannot be honoured is an error, never a silent fallback.
"""

from __future__ import annotations

from typing import Literal

import torch

Backend = Literal["auto", "torch", "cuda"]


def cuda_extension_available() -> bool:
    """Whether the compiled geer CUDA extension can be loaded (it is not part of this build yet)."""
    try:
        from geer_ns import _C  # type: ignore[attr-defined]  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_backend(backend: Backend, device: torch.device) -> Literal["torch", "cuda"]:
    if backend == "torch":
        return "torch"
    if backend == "cuda":
        if device.type != "cuda":
            raise RuntimeError(f"backend='cuda' requested but the inputs live on {device}")
        if not cuda_extension_available():
            raise RuntimeError("backend='cuda' requested but the geer CUDA extension is not built")
        return "cuda"
    if backend == "auto":
        return "cuda" if device.type == "cuda" and cuda_extension_available() else "torch"
    raise ValueError(f"backend must be 'auto', 'torch' or 'cuda', got {backend!r}")
