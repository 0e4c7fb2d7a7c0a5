"""Input checks: bad input fails here, with the tensor's name, not deep inside a stage.

Shapes and dtypes are host facts (free). Value checks (finite, scales > 0, opacities in [0, 1], non-zero
quaternions) are reductions on the device: they are all stacked into one flag vector and read with a single
host sync per render call (one per training step), and only when a flag is set are the details computed
for the error message.
"""

from __future__ import annotations

import torch
from torch import Tensor

SUPPORTED_DTYPES = (torch.float32, torch.float64)


def check_shape(name: str, t: Tensor, shape: tuple[int | None, ...]) -> None:
    """Type, shape (None: any size) and dtype (float32 or float64); no device work."""
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


def _non_finite(name: str, t: Tensor) -> tuple[Tensor, object]:
    def message() -> str:
        bad = int((~torch.isfinite(t)).sum())
        return f"{name}: contains {bad} non-finite value(s) (NaN or Inf)"

    return ~torch.isfinite(t).all(), message


def _raise_first(checks: list[tuple[Tensor, object]]) -> None:
    """checks: (0-d bool tensor, True when bad; message or a function making it). One host sync in all."""
    if not checks:
        return
    flags = torch.stack([flag.reshape(()) for flag, _ in checks])
    if not bool(flags.any()):  # the single sync
        return
    for ok_flag, (_, message) in zip(flags.tolist(), checks):
        if ok_flag:
            raise ValueError(message() if callable(message) else message)


def check_tensor(name: str, t: Tensor, shape: tuple[int | None, ...]) -> None:
    check_shape(name, t, shape)
    _raise_first([_non_finite(name, t)])


def check_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    *,
    viewmat: Tensor | None = None,
    background: Tensor | None = None,
) -> int:
    """The Gaussians (and, when given, the view's matrix and background) of one render call: shapes and
    dtypes on the host, every value rule in one device reduction read with one sync. Returns N."""
    check_shape("means", means, (None, 3))
    n = means.shape[0]
    check_shape("quats", quats, (n, 4))
    check_shape("scales", scales, (n, 3))
    check_shape("opacities", opacities, (n,))
    check_shape("colors", colors, (n, 3) if colors.ndim == 2 else (n, None, 3))
    dtypes = {t.dtype for t in (means, quats, scales, opacities, colors)}
    if len(dtypes) != 1:
        raise ValueError(f"means/quats/scales/opacities/colors: mixed dtypes {sorted(map(str, dtypes))}")
    named = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors}
    if viewmat is not None:
        check_shape("viewmat", viewmat, (4, 4))
        named["viewmat"] = viewmat
    if background is not None:
        check_shape("background", background, (3,))
        named["background"] = background
    checks = [_non_finite(name, t) for name, t in named.items()]
    # Viewmat and background may live elsewhere (a CPU pose for CUDA Gaussians): their flags join on means' device.
    checks = [(flag.to(means.device), message) for flag, message in checks]
    checks += [
        ((scales <= 0).any(), "scales: must be > 0 (pass exp(log_scales))"),
        (((opacities < 0) | (opacities > 1)).any(), "opacities: must lie in [0, 1] (pass sigmoid(logits))"),
        ((quats.abs().amax(dim=-1) == 0).any(), "quats: zero-norm quaternion"),  # norm() under/overflows in float32
    ]
    _raise_first(checks)
    return n
