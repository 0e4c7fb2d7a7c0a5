"""Which view each training image is supervised in (BEAP or native rays), and how many pixels that keeps.

BEAP (paper Sec. 3.3) is the paper's training view: rays uniform in (theta, phi) = (atan(x/z), atan(y/z)),
so every tile is a camera sub-frustum and the loss weighs every solid angle alike whatever the lens
compresses. Its images are resampled from the captured ones (a low-pass: the target loses detail the test
pixels still have), its cells cover the scored pixels unevenly (a fisheye's centre gets fewer cells than
pixels, a pinhole's corners fewer than its edges) and it holds only rays in front of the camera (z > 0).
Native rays train on the captured pixels themselves, which are also what every evaluation scores; geer's
renderer traces any ray exactly, with the PBF mirror transform keeping the association right beyond +-90
degrees.

``auto`` (the default) is native rays for every camera, chosen by measurement: on the dev room at 128^2,
1000 steps, three seeds, native supervision scored 2.1 dB (pinhole) and 1.4 dB (180-degree fisheye; 1.6 dB in
its centre) above BEAP on the same test pixels (benchmarks/vs_splatfacto.md). ``beap`` (the paper's setting)
and ``native`` force one view; a BEAP camera may lose a rim (rays beyond BEAP's +-89.5 degree limit), and the
start-up report says how many pixels.
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


AUTO_REASON = ("supervision auto: native rays, every valid pixel as captured (BEAP training images, resampled, "
               "scored 1.4-2.1 dB lower on the dev room: benchmarks/vs_splatfacto.md; "
               "--pipeline.datamanager.supervision beap for the paper's setting)")


def choose_view(supervision: Supervision) -> View:
    """The view a camera's training images are supervised in: `supervision`, "auto" being native rays (the
    module docstring says why)."""
    return "native" if supervision == "auto" else supervision


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
