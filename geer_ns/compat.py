"""Narrow fixes for bugs of the host stack (nerfstudio 1.1.5, torch >= 2.6, splines 0.3.0, no system ffmpeg).

Nothing here runs at import: `install()` is called by geer's own entries only, so nerfstudio's other methods
never see these fixes. GeerTrainerConfig calls it before ns-train launches a geer run, GeerModel's constructor
before ns-eval / ns-viewer / ns-render load a geer checkpoint. Each fix takes effect only where the host would
fail and is tested where the host bug shows (tests/test_compat.py).
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Optional

import numpy as np
import torch

_LOG = logging.getLogger("geer_ns")


def install() -> None:
    """Every fix below, for the geer run of this process. Idempotent."""
    allow_nerfstudio_checkpoints()
    install_two_keyframe_spline_fix()
    provide_ffmpeg()
    quiet_known_warnings()


def allow_nerfstudio_checkpoints() -> bool:
    """A nerfstudio bug: torch >= 2.6 loads with weights_only=True and nerfstudio's checkpoint loaders
    pass no weights_only. Allow-lists exactly the non-tensor globals a nerfstudio checkpoint holds (numpy
    scalars and dtypes of the optimizer / scheduler state). False on a torch without add_safe_globals (< 2.4),
    which does not default to weights_only either."""
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:
        return False
    try:
        from numpy._core import multiarray as np_multiarray  # numpy >= 2
    except ImportError:  # pragma: no cover - numpy 1.x
        from numpy.core import multiarray as np_multiarray
    found = [np_multiarray.scalar, np.dtype]
    for name in ("Float64DType", "Float32DType", "Int64DType", "Int32DType", "BoolDType"):
        dtype_class = getattr(np.dtypes, name, None)
        if dtype_class is not None:
            found.append(dtype_class)
    add(found)
    return True


def install_two_keyframe_spline_fix() -> bool:
    """splines 0.3.0's quaternion KochanekBartels (the viewer's camera path) raises for exactly two open
    keyframes under numpy 2 (`assert not tcb` on an empty array). Two rotations need no TCB values: the
    spline is their slerp, built as a one-segment De Casteljau curve (splines' own class). False if splines
    is absent."""
    try:
        import splines.quaternion as sq
    except ImportError:  # pragma: no cover - nerfstudio depends on it
        return False
    cls = sq.KochanekBartels
    if getattr(cls, "_geer_two_keyframes", False):
        return True
    original = cls.__init__

    def __init__(self, quaternions, grid=None, *, tcb=(0, 0, 0), alpha=None, endconditions="natural"):
        if endconditions != "closed" and len(quaternions) == 2:
            quaternions = sq._check_quaternions(quaternions, closed=False)  # same hemisphere
            sq.DeCasteljau.__init__(self, [quaternions], sq._check_grid(grid, alpha, quaternions))
            return
        original(self, quaternions, grid, tcb=tcb, alpha=alpha, endconditions=endconditions)

    cls.__init__ = __init__
    cls._geer_two_keyframes = True
    return True


def provide_ffmpeg() -> Optional[str]:
    """ns-render exits with "Could not find ffmpeg" without an `ffmpeg` on PATH, even for image output
    (install_checks.check_ffmpeg_installed), and mediapy writes videos through it. Where the system has none,
    a link named `ffmpeg` to imageio-ffmpeg's binary goes first on PATH. Returns the program, None if none."""
    found = shutil.which("ffmpeg")
    if found is not None:
        return found
    try:
        import imageio_ffmpeg

        exe = Path(imageio_ffmpeg.get_ffmpeg_exe())
    except Exception:  # not installed, or no binary for this platform
        return None
    link = _ffmpeg_link(exe)
    os.environ["PATH"] = f"{link.parent}{os.pathsep}{os.environ.get('PATH', '')}"
    try:
        import mediapy

        mediapy.set_ffmpeg(str(link))
    except ImportError:  # pragma: no cover - nerfstudio depends on it
        pass
    _LOG.info("no system ffmpeg: using imageio-ffmpeg's %s", exe)
    return str(link)


def _ffmpeg_link(exe: Path) -> Path:
    """A folder holding `ffmpeg` -> exe: in geer's cache, else in a fresh temporary folder."""
    candidates = [Path(os.environ.get("GEER_NS_CACHE", "~/.cache/geer_ns")).expanduser() / "ffmpeg_bin"]
    for folder in candidates + [Path(tempfile.mkdtemp(prefix="geer_ffmpeg_"))]:
        link = folder / "ffmpeg"
        try:
            folder.mkdir(parents=True, exist_ok=True)
            if link.is_symlink() and Path(os.readlink(link)) != exe:
                link.unlink()
            if not link.is_symlink():
                link.symlink_to(exe)
            return link
        except OSError:
            continue
    return exe  # unreachable in practice: a fresh temporary folder is writable


# torch deprecation warnings raised by nerfstudio's own code in every run (torch.jit.script in camera_utils,
# custom_fwd / custom_bwd in activations, the trainer's GradScaler) and nerfstudio's writer turning loss tensors
# into floats. Each filter is one message, category and module: the same text from other modules still shows.
KNOWN_NOISE = (  # (category, message, module): regular expressions matched at the start
    (FutureWarning, r"`torch\.jit\.script` is deprecated", r"torch\.jit\._script\Z"),
    (FutureWarning, r"`torch\.cuda\.amp\.custom_(fwd|bwd)\(args\.\.\.\)` is deprecated",
     r"nerfstudio\.field_components\.activations\Z"),
    (FutureWarning, r"`torch\.cuda\.amp\.GradScaler\(args\.\.\.\)` is deprecated", r"nerfstudio\.engine\.trainer\Z"),
    (UserWarning, r"Converting a tensor with requires_grad=True to a scalar may lead to unexpected behavior",
     r"nerfstudio\."),
)


def quiet_known_warnings() -> None:
    """Filter exactly the KNOWN_NOISE warnings (a geer run's console shows what is news)."""
    for category, message, module in KNOWN_NOISE:
        warnings.filterwarnings("ignore", message=message, category=category, module=module)
