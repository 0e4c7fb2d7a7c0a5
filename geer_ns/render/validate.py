"""Input checks: bad input fails here, with the tensor's name, not deep inside a stage."""

from __future__ import annotations

import torch
from torch import Tensor

SUPPORTED_DTYPES = (torch.float32, torch.float64)


def check_tensor(name: str, t: Tensor, shape: tuple[int | None, ...]) -> None:
    if not isinstance(t, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    if t.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name}: expected shape {want}, got {list(t.shape)}")
    if t.dtype not in SUPPORTED_DTYPES:
        # float16/bfloat16 overflow in the exact transmittance (exp of squared distances) and give
        # non-finite depth; integers and complex numbers are no geometry.
        raise ValueError(
            f"{name}: dtype {t.dtype} is not supported; expected torch.float32 or torch.float64 "
            "(cast with .float())"
        )
    if not bool(torch.isfinite(t).all()):
        bad = int((~torch.isfinite(t)).sum())
        raise ValueError(f"{name}: contains {bad} non-finite value(s) (NaN or Inf)")


def check_gaussians(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor) -> int:
    check_tensor("means", means, (None, 3))
    n = means.shape[0]
    check_tensor("quats", quats, (n, 4))
    check_tensor("scales", scales, (n, 3))
    check_tensor("opacities", opacities, (n,))
    if colors.ndim == 2:
        check_tensor("colors", colors, (n, 3))
    else:
        check_tensor("colors", colors, (n, None, 3))
    if bool((scales <= 0).any()):
        raise ValueError("scales: must be > 0 (pass exp(log_scales))")
    if bool(((opacities < 0) | (opacities > 1)).any()):
        raise ValueError("opacities: must lie in [0, 1] (pass sigmoid(logits))")
    if bool((quats.abs().amax(dim=-1) == 0).any()):  # not norm(): it under/overflows in float32
        raise ValueError("quats: zero-norm quaternion")
    dtypes = {t.dtype for t in (means, quats, scales, opacities, colors)}
    if len(dtypes) != 1:
        raise ValueError(f"means/quats/scales/opacities/colors: mixed dtypes {sorted(map(str, dtypes))}")
    return n
