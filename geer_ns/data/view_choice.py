"""Which view each training image is supervised in (BEAP or native rays), and how many pixels that keeps.

BEAP (paper Sec. 3.3) is the paper's training view: rays uniform in (theta, phi) = (atan(x/z), atan(y/z)),
so every tile is a camera sub-frustum (tight PBF association) and the loss weighs every solid angle alike
whatever the lens compresses. Its angles exist only for rays in front of the camera (z > 0): a lens whose
valid rays reach or pass 90 degrees from the axis cannot be put into one BEAP image. Splitting such a view
into two BEAP hemispheres would add a seam through the field of view (cells on either side of it cover
different solid angles, and a Gaussian straddling it is rendered twice at half its footprint each) and a
second resampling. geer's renderer already traces any ray exactly, with the PBF mirror transform keeping
the association right beyond +-90 degrees, so those cameras are supervised on their own pixel rays
instead: nothing is resampled and every valid pixel enters the loss; the price is the lens's uneven
angular sampling in the loss, which BEAP would have evened out.

``auto`` (the default): native rays for a camera whose valid rays reach 90 degrees, BEAP otherwise. A BEAP
camera may still lose a thin rim (rays between BEAP's +-89.5 degree limit and 90 degrees); the start-up
report says how many pixels, and ``--pipeline.datamanager.supervision native`` keeps them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Literal

import torch
from torch import Tensor

from geer_ns.cameras import CameraModel
from geer_ns.data.beap import BeapGrid, directions_to_angles
from geer_ns.data.views import beap_view, native_view

Supervision = Literal["auto", "beap", "native"]
View = Literal["beap", "native"]


def reaches_90_degrees(camera: CameraModel, valid: Tensor) -> bool:
    """True when a valid pixel's ray is at or beyond 90 degrees from the optical axis (z <= 0)."""
    dirs = native_view(camera).rays.dirs.reshape(camera.height, camera.width, 3)
    return bool((valid.to(dirs.device) & (dirs[..., 2] <= 0)).any())


def choose_view(supervision: Supervision, camera: CameraModel, valid: Tensor) -> View:
    if supervision != "auto":
        return supervision
    return "native" if reaches_90_degrees(camera, valid) else "beap"


def beap_covered(camera: CameraModel, valid: Tensor, beap_valid: Tensor) -> Tensor:
    """[H, W] bool: valid native pixels whose ray falls into a valid cell of the camera's BEAP image."""
    grid: BeapGrid = beap_view(camera).grid
    dirs = native_view(camera).rays.dirs.reshape(camera.height, camera.width, 3).double()
    theta, phi = directions_to_angles(dirs)
    cells = grid.angles_to_cells(theta, phi).floor()
    col, row = cells[..., 0], cells[..., 1]
    inside = (dirs[..., 2] > 0) & (col >= 0) & (col < grid.width) & (row >= 0) & (row < grid.height)
    flat = (row.clamp(0, grid.height - 1) * grid.width + col.clamp(0, grid.width - 1)).long()
    hit = beap_valid.reshape(-1).cpu()[flat]
    return valid.cpu() & inside.cpu() & hit


@dataclass
class CameraSupervision:
    """What the training cache kept of one camera's images (summed over them)."""

    view: View
    images: int = 0
    valid_pixels: int = 0  # native pixels the camera saw (camera-valid, inside mask and image circle)
    supervised_pixels: int = 0  # of those, pixels whose ray is in the loss
    max_angle_deg: float = 0.0  # largest angle of a valid ray from the optical axis


@dataclass
class SupervisionReport:
    """Per camera (one entry per distinct intrinsics and view), said once at start-up."""

    cameras: Dict[tuple, CameraSupervision] = field(default_factory=dict)
    names: Dict[tuple, str] = field(default_factory=dict)

    def add(self, name: str, camera: CameraModel, view: View, valid: Tensor, supervised: Tensor) -> None:
        key = (camera, view)
        entry = self.cameras.setdefault(key, CameraSupervision(view))
        self.names[key] = name
        dirs = native_view(camera).rays.dirs.reshape(camera.height, camera.width, 3)
        cos = dirs[..., 2][valid.to(dirs.device)]
        if cos.numel():
            entry.max_angle_deg = max(entry.max_angle_deg, float(torch.rad2deg(torch.acos(cos.min().clamp(-1, 1)))))
        entry.images += 1
        entry.valid_pixels += int(valid.sum())
        entry.supervised_pixels += int(supervised.sum())

    def lines(self, verb: str = "supervised") -> List[str]:
        out = []
        for key, e in self.cameras.items():
            view = "BEAP" if e.view == "beap" else "native rays"
            pct = 100.0 * e.supervised_pixels / max(e.valid_pixels, 1)
            line = (f"{self.names[key]}: {e.images} image(s), {view}, {e.supervised_pixels} of {e.valid_pixels} "
                    f"valid pixels {verb} ({pct:.2f}%), rays up to {e.max_angle_deg:.1f} deg off-axis")
            lost = e.valid_pixels - e.supervised_pixels
            if lost:
                line += (f"; {lost} pixels fall outside BEAP's valid cells (rays beyond its +-89.5 deg limit) and "
                         f"are NOT {verb} (--pipeline.datamanager.supervision native keeps them)")
            out.append(line)
        return out

    @property
    def supervised_fraction(self) -> float:
        valid = sum(e.valid_pixels for e in self.cameras.values())
        return sum(e.supervised_pixels for e in self.cameras.values()) / max(valid, 1)
