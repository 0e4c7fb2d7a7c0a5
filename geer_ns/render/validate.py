"""Input checks: bad input fails here, with the tensor's name, not deep inside a stage.

Shapes, dtypes and devices are host facts (free): every tensor of a render call, the RayGrid's included, must
be on the Gaussians' device (render moves nothing, as torch does not). Value checks (finite, scales > 0,
opacities in [0, 1], non-zero quaternions, a rigid viewmat) are reductions on the device: they are all stacked
into one flag vector and read with a single host sync per render call (one per training step), and only when
a flag is set are the details computed for the error message.
"""

from __future__ import annotations

from dataclasses import fields, is_dataclass

import torch
from torch import Tensor
from torch._subclasses.fake_tensor import is_fake

SUPPORTED_DTYPES = (torch.float32, torch.float64)

# A viewmat's rotation block must be orthonormal within this, |R R^T - I| (Frobenius: the same for R and R^T, so
# for a camera-to-world pose and its world-to-camera inverse), in float32 and float64 alike: a float64 viewmat
# is usually built from float32 poses (nerfstudio keeps camera_to_worlds in float32, ~1e-7 off), and dataset
# files are refused beyond the same bound (data/dataset_checks.py), so every pose a dataset may hold renders.
# A scaled, sheared or singular matrix is far beyond it (a 1 % scale gives 3.5e-2).
ROTATION_TOLERANCE = 1e-3


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
    if is_fake(flags):  # shapes and devices without values (tests/test_fake_cuda_step.py): nothing to read
        return
    if not bool(flags.any()):  # the single sync
        return
    for ok_flag, (_, message) in zip(flags.tolist(), checks):
        if ok_flag:
            raise ValueError(message() if callable(message) else message)


def check_tensor(name: str, t: Tensor, shape: tuple[int | None, ...]) -> None:
    check_shape(name, t, shape)
    _raise_first([_non_finite(name, t)])


def check_same_device(device: torch.device, named: dict[str, Tensor]) -> None:
    """Every tensor on `device` (the means'); a host fact, no device work."""
    for name, t in named.items():
        if t.device != device:
            fix = "grid.to(means.device)" if name.startswith("grid.") else f"{name}.to(means.device)"
            raise ValueError(f"{name}: on {t.device}, but means are on {device}; every tensor of a render call "
                             f"must be on one device (pass {fix})")


def _rigid_viewmat(viewmat: Tensor) -> list[tuple[Tensor, object]]:
    """Flags (and messages) for a viewmat that is no rigid world-to-camera transform [R | t; 0 0 0 1]."""
    vm = viewmat.detach().to(torch.float64)
    rot = vm[:3, :3]
    off = torch.linalg.matrix_norm(rot @ rot.T - torch.eye(3, dtype=vm.dtype, device=vm.device))  # Frobenius
    det = torch.dot(rot[0], torch.linalg.cross(rot[1], rot[2]))
    last = (vm[3] - vm.new_tensor([0.0, 0.0, 0.0, 1.0])).abs().amax()
    fix = "pass a rigid world-to-camera transform (rotation and translation; scale the scene, not the camera)"

    def not_orthonormal() -> str:
        d, lengths = float(det), ", ".join(f"{float(n):.4g}" for n in rot.norm(dim=1))
        what = (f"singular (det {d:.3g})" if abs(d) < ROTATION_TOLERANCE else
                f"not orthonormal (|R R^T - I| = {float(off):.3g} > {ROTATION_TOLERANCE:g}; row lengths {lengths})")
        return f"viewmat: the rotation block viewmat[:3, :3] is {what}: a scaled, sheared or degenerate matrix; {fix}"

    return [
        (off > ROTATION_TOLERANCE, not_orthonormal),
        (det <= 0, lambda: f"viewmat: the rotation block viewmat[:3, :3] has det {float(det):.3g}, a reflection; "
                           "expected det +1 (a right-handed OpenCV camera frame: x right, y down, z forward)"),
        (last > ROTATION_TOLERANCE, lambda: f"viewmat: last row is {[round(float(v), 6) for v in vm[3]]}; expected "
                                            "[0, 0, 0, 1] (a 4x4 world-to-camera matrix; transposed?)"),
    ]


def _sh_degrees(degrees: Tensor, colors: Tensor, n: int) -> list:
    """Host checks of per-Gaussian SH degrees (raising here), and their value rule for the one reduction."""
    if colors.ndim != 3:
        raise ValueError("sh_degree: per-Gaussian degrees need SH colors [N, K, 3], got RGB [N, 3]")
    if not isinstance(degrees, Tensor) or degrees.dtype.is_floating_point or degrees.dtype in (torch.bool,
                                                                                               torch.complex64):
        raise ValueError(f"sh_degree: per-Gaussian degrees must be an integer tensor, got {degrees!r:.60}")
    if degrees.shape != (n,):
        raise ValueError(f"sh_degree: expected one degree per Gaussian, shape [{n}], got {list(degrees.shape)}")
    return [((degrees < 0).any(), "sh_degree: per-Gaussian degrees must be >= 0")]


def grid_tensors(grid) -> dict[str, Tensor]:
    """A RayGrid's tensors by name (grid.dirs, grid.valid, ...), for the device check."""
    if not is_dataclass(grid):
        return {}
    return {f"grid.{f.name}": v for f in fields(grid) if isinstance(v := getattr(grid, f.name), Tensor)}


def check_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    *,
    viewmat: Tensor | None = None,
    background: Tensor | None = None,
    grid=None,
    sh_degrees: Tensor | None = None,
) -> int:
    """The Gaussians (and, when given, the view's matrix, background, RayGrid and each Gaussian's own SH degree)
    of one render call: shapes, dtypes and devices on the host, every value rule in one device reduction read
    with one sync. Returns N."""
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
    degree_checks = [] if sh_degrees is None else _sh_degrees(sh_degrees, colors, n)
    check_same_device(means.device, {**named, **({} if grid is None else grid_tensors(grid)),
                                     **({} if sh_degrees is None else {"sh_degree": sh_degrees})})
    checks = [_non_finite(name, t) for name, t in named.items()] + degree_checks
    if viewmat is not None:
        checks += _rigid_viewmat(viewmat)
    checks += [
        ((scales <= 0).any(), "scales: must be > 0 (pass exp(log_scales))"),
        (((opacities < 0) | (opacities > 1)).any(), "opacities: must lie in [0, 1] (pass sigmoid(logits))"),
        ((quats.abs().amax(dim=-1) == 0).any(), "quats: zero-norm quaternion"),  # norm() under/overflows in float32
    ]
    _raise_first(checks)
    return n
