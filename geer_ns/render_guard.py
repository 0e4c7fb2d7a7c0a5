"""Cameras the model cannot render must not kill nerfstudio's viewer render thread.

nerfstudio's viewer renders in a thread whose loop catches only its own interrupt exception: any other
error ends the thread and the tab stays black from then on. Its cameras can be degenerate:
the render panel starts with `preview_fov = 0`, which gives an infinite focal length; a user can type a
zero resolution; a broken camera path can hold NaN poses. geer checks each camera first; a camera that
cannot be rendered gives the last good frame (or the background) and one log line per distinct problem.
"""

from __future__ import annotations

import math
import threading
from typing import Dict, Optional

import torch
from torch import Tensor

from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.utils.rich_utils import CONSOLE

# A pinhole whose half field of view reaches 90 degrees is no pinhole camera (fx -> 0).
MAX_PINHOLE_HALF_FOV_DEG = 89.9


def camera_problem(camera: Cameras) -> Optional[str]:
    """Why the (single) camera cannot be rendered, or None."""
    cam = camera.flatten()[0] if len(camera.shape) != 1 else camera[0]
    c2w = cam.camera_to_worlds
    if not bool(torch.isfinite(c2w).all()):
        return "the camera pose has NaN/Inf entries"
    width, height = int(cam.width.reshape(-1)[0]), int(cam.height.reshape(-1)[0])
    if width <= 0 or height <= 0:
        return f"image size {width}x{height} is empty"
    for name in ("fx", "fy", "cx", "cy"):
        value = float(getattr(cam, name).reshape(-1)[0])
        if not math.isfinite(value):
            hint = " (zero field of view)" if name in ("fx", "fy") and value == math.inf else ""
            return f"{name} = {value}{hint}"
        if name in ("fx", "fy") and value <= 0:
            return f"{name} = {value} (expected > 0)"
    if int(cam.camera_type.reshape(-1)[0]) == CameraType.PERSPECTIVE.value:
        fx, fy = float(cam.fx.reshape(-1)[0]), float(cam.fy.reshape(-1)[0])
        half = math.degrees(math.atan(max(width / fx, height / fy) / 2.0))
        if half >= MAX_PINHOLE_HALF_FOV_DEG:
            return f"a pinhole field of view of {2 * half:.1f} degrees (180 or more cannot be projected)"
    return None


class RenderGuard:
    """Last good frame and the problems already logged (one line each)."""

    def __init__(self) -> None:
        self.last: Optional[Dict[str, Tensor]] = None
        self.logged: set = set()

    def remember(self, outputs: Dict[str, Tensor]) -> Dict[str, Tensor]:
        self.last = outputs
        return outputs

    def fallback(self, problem: str, empty: Dict[str, Tensor]) -> Dict[str, Tensor]:
        if problem not in self.logged:
            self.logged.add(problem)
            what = "the last good frame" if self.last is not None else "the background"
            CONSOLE.log(f"[yellow]geer: cannot render this camera: {problem}; showing {what}")
        return self.last if self.last is not None else empty


def in_viewer_thread() -> bool:
    """True in nerfstudio's viewer render thread (not the main thread of ns-eval / ns-render)."""
    return threading.current_thread() is not threading.main_thread()


def is_viewer_interrupt(error: BaseException) -> bool:
    """The viewer's own interrupt (raised through a trace function inside our code) must pass through."""
    return type(error).__name__ == "IOChangeException"
