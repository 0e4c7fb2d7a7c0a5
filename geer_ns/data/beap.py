"""Bipolar Equiangular Projection (BEAP) images (3DGEER, Sec. 3.3, Eq. 6 and 11, App. E).

A BEAP image samples rays uniformly in the two "bipolar" angles of a camera-frame direction d (OpenCV
frame, z forward):

    theta = atan(d_x / d_z),  phi = atan(d_y / d_z),  both in (-pi/2, pi/2)            (Eq. 6)
    d  ~  (tan theta, tan phi, 1) / |(tan theta, tan phi, 1)|                       (App. E, E.1-E.3)

Cell (i, j) (row i, column j) of a ``BeapGrid`` has its center at
``theta = theta_min + (j + 0.5) * step_theta``, ``phi = phi_min + (i + 0.5) * step_phi``, i.e. the same
"center at +0.5" convention as camera pixels. With a symmetric range this is the paper's Eq. 11
(``x = w theta / FoV_x + (w + 1) / 2`` in 1-based cell units). Only directions with d_z > 0 exist in BEAP,
so every range is kept strictly inside +-90 degrees.

Sampling (both directions) is bilinear with a strict footprint rule: a sample is valid only if all four
pixels of its bilinear footprint are valid (inside the image, camera-valid, inside the mask), so no
invalid pixel ever bleeds in. Samples in the outer half pixel of an image use edge replication (their
footprint is the edge pixel itself), so the whole image rectangle is usable.

Antialiasing (native -> BEAP): each BEAP cell is supersampled k x k and averaged (box filter over the
cell), with k = round(median native-pixel distance between neighboring BEAP cell centers), clamped to
[1, max_supersample]; i.e. k > 1 only where a BEAP cell spans about two or more source pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from geer_ns.cameras import CameraModel

__all__ = [
    "DEFAULT_MAX_HALF_ANGLE",
    "BeapGrid",
    "beap_grid_for_camera",
    "beap_to_native",
    "camera_angular_extent",
    "camera_center_step",
    "directions_to_angles",
    "resample_to_beap",
]

#: BEAP cannot represent directions at or beyond 90 degrees; ranges are clipped here by default.
DEFAULT_MAX_HALF_ANGLE = math.radians(89.5)


def directions_to_angles(dirs: Tensor) -> tuple[Tensor, Tensor]:
    """Eq. 6: (theta, phi) = (atan2(x, z), atan2(y, z)); values beyond +-pi/2 mean z <= 0."""
    return torch.atan2(dirs[..., 0], dirs[..., 2]), torch.atan2(dirs[..., 1], dirs[..., 2])


@dataclass(frozen=True)
class BeapGrid:
    """A ``height`` x ``width`` BEAP image covering [theta_min, theta_max] x [phi_min, phi_max] (radians)."""

    width: int
    height: int
    theta_min: float
    theta_max: float
    phi_min: float
    phi_max: float

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value <= 0:
                raise ValueError(f"BeapGrid.{name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("theta_min", "theta_max", "phi_min", "phi_max"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or not -math.pi / 2 < value < math.pi / 2:
                raise ValueError(f"BeapGrid.{name} must be finite and strictly inside (-pi/2, pi/2), got {value!r}")
            object.__setattr__(self, name, value)
        if self.theta_max <= self.theta_min:
            raise ValueError("BeapGrid.theta_max must be > theta_min")
        if self.phi_max <= self.phi_min:
            raise ValueError("BeapGrid.phi_max must be > phi_min")

    @classmethod
    def from_fov(
        cls, width: int, height: int, fov_x: float, fov_y: float, center: tuple[float, float] = (0.0, 0.0)
    ) -> BeapGrid:
        """Grid of the paper's Eq. 11: FoV (radians) centered on ``center`` = (theta, phi)."""
        return cls(
            width,
            height,
            center[0] - fov_x / 2,
            center[0] + fov_x / 2,
            center[1] - fov_y / 2,
            center[1] + fov_y / 2,
        )

    @property
    def step_theta(self) -> float:
        return (self.theta_max - self.theta_min) / self.width

    @property
    def step_phi(self) -> float:
        return (self.phi_max - self.phi_min) / self.height

    @property
    def step(self) -> tuple[float, float]:
        """(step_theta, step_phi) in radians per cell."""
        return self.step_theta, self.step_phi

    @property
    def fov(self) -> tuple[float, float]:
        return self.theta_max - self.theta_min, self.phi_max - self.phi_min

    def angles(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None, supersample: int = 1
    ) -> Tensor:
        """(theta, phi) of cell centers, ``[h, w, 2]``; with ``supersample`` = k the k x k sub-cell
        centers, ``[h, w, k, k, 2]`` (sub-row index before sub-column index)."""
        k = int(supersample)
        sub = (torch.arange(k, dtype=torch.float64) + 0.5) / k  # in cell units, 0.5 = cell center
        cols = torch.arange(self.width, dtype=torch.float64)[:, None] + sub[None, :]  # [w, k]
        rows = torch.arange(self.height, dtype=torch.float64)[:, None] + sub[None, :]  # [h, k]
        theta = self.theta_min + cols * self.step_theta
        phi = self.phi_min + rows * self.step_phi
        # [h, w, k(sub-row), k(sub-col)]
        th = theta[None, :, None, :].expand(self.height, self.width, k, k)
        ph = phi[:, None, :, None].expand(self.height, self.width, k, k)
        out = torch.stack([th, ph], dim=-1)
        if k == 1:
            out = out[:, :, 0, 0]
        return out.to(dtype=dtype, device=device)

    def directions(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None, supersample: int = 1
    ) -> Tensor:
        """Unit camera-frame rays (App. E, Eq. E.1-E.3) at the cell centers, ``[h, w, 3]``
        (``[h, w, k, k, 3]`` when supersampled)."""
        ang = self.angles(torch.float64, None, supersample)
        v = torch.stack([torch.tan(ang[..., 0]), torch.tan(ang[..., 1]), torch.ones_like(ang[..., 0])], dim=-1)
        return (v / v.norm(dim=-1, keepdim=True)).to(dtype=dtype, device=device)

    def angles_to_cells(self, theta: Tensor, phi: Tensor) -> Tensor:
        """Continuous grid coordinates (x, y) (cell centers at +0.5) of the given angles."""
        return torch.stack([(theta - self.theta_min) / self.step_theta, (phi - self.phi_min) / self.step_phi], -1)


# ==================================================================================================
# Grid construction
# ==================================================================================================


def _angle_between(a: Tensor, b: Tensor) -> Tensor:
    return torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))


def camera_center_step(camera: CameraModel) -> float:
    """Angular size (radians) of one pixel at the principal point: the finer of the horizontal and
    vertical angle between rays through points half a pixel either side of it."""
    if hasattr(camera, "cx"):
        cx, cy = float(camera.cx), float(camera.cy)
    else:  # equirectangular: image center looks along +z
        cx, cy = camera.width / 2, camera.height / 2
    pts = torch.tensor(
        [[cx - 0.5, cy], [cx + 0.5, cy], [cx, cy - 0.5], [cx, cy + 0.5]],
        dtype=torch.float64,
    )
    dirs, valid = camera.unproject(pts)
    if not bool(valid.all()):
        raise ValueError("camera is not invertible around its principal point; pass an explicit BEAP step")
    step = min(float(_angle_between(dirs[0], dirs[1])), float(_angle_between(dirs[2], dirs[3])))
    if not step > 0:
        raise ValueError("could not derive the angular resolution at the principal point")
    return step


def _boundary_pixels(width: int, height: int) -> Tensor:
    """Points on the image border (pixel-center spacing along each edge, corners included)."""
    us = torch.cat([torch.tensor([0.0]), torch.arange(width, dtype=torch.float64) + 0.5, torch.tensor([float(width)])])
    vs = torch.cat(
        [torch.tensor([0.0]), torch.arange(height, dtype=torch.float64) + 0.5, torch.tensor([float(height)])]
    )
    top = torch.stack([us, torch.zeros_like(us)], -1)
    bottom = torch.stack([us, torch.full_like(us, float(height))], -1)
    left = torch.stack([torch.zeros_like(vs), vs], -1)
    right = torch.stack([torch.full_like(vs, float(width)), vs], -1)
    return torch.cat([top, bottom, left, right]).to(torch.float64)


def camera_angular_extent(
    camera: CameraModel, max_half_angle: float = DEFAULT_MAX_HALF_ANGLE, mask: Tensor | np.ndarray | None = None
) -> tuple[float, float, float, float]:
    """(theta_min, theta_max, phi_min, phi_max) spanned by the camera's valid rays, clipped to
    +-``max_half_angle``.

    All pixel centers and points on the image border are unprojected; invalid ones (beyond the model's
    ``max_angle``, non-converged) and, if given, pixels outside ``mask`` are ignored. Rays at or beyond 90
    degrees from the axis give angles beyond +-90 degrees, which the clip maps to the limit.
    """
    if not 0 < max_half_angle < math.pi / 2:
        raise ValueError(f"max_half_angle must be in (0, pi/2), got {max_half_angle!r}")
    dirs, valid = camera.pixel_rays(torch.float64)
    dirs, valid = dirs.reshape(-1, 3), valid.reshape(-1)
    if mask is not None:
        valid = valid & _as_mask(mask, camera).reshape(-1)
    else:
        bdirs, bvalid = camera.unproject(_boundary_pixels(camera.width, camera.height))
        dirs, valid = torch.cat([dirs, bdirs]), torch.cat([valid, bvalid])
    if not bool(valid.any()):
        raise ValueError("camera has no valid pixel")
    theta, phi = directions_to_angles(dirs[valid])
    lim = max_half_angle
    theta, phi = theta.clamp(-lim, lim), phi.clamp(-lim, lim)
    return float(theta.min()), float(theta.max()), float(phi.min()), float(phi.max())


def _fit_axis(lo: float, hi: float, step: float, tile: int, lim: float) -> tuple[int, float, float]:
    """Cells covering [lo, hi] at ``step``, rounded up to a multiple of ``tile``; the extra range is added
    symmetrically, shifted (or the step refined) so the axis stays inside [-lim, lim]."""
    n = max(1, math.ceil((hi - lo) / step - 1e-9))
    n = math.ceil(n / tile) * tile
    span = n * step
    span = min(span, 2 * lim)  # refine the step rather than leave the representable range
    center = 0.5 * (lo + hi)
    a, b = center - span / 2, center + span / 2
    if a < -lim:
        a, b = -lim, -lim + span
    if b > lim:
        a, b = lim - span, lim
    return n, a, b


def beap_grid_for_camera(
    camera: CameraModel,
    step: float | None = None,
    tile_size: int = 16,
    max_half_angle: float = DEFAULT_MAX_HALF_ANGLE,
    mask: Tensor | np.ndarray | None = None,
) -> BeapGrid:
    """BEAP grid covering everything the camera sees (within +-``max_half_angle``).

    ``step`` (radians per cell) defaults to the camera's angular resolution at its principal point
    (:func:`camera_center_step`); the grid size is rounded up to a multiple of ``tile_size``.
    """
    if tile_size < 1:
        raise ValueError(f"tile_size must be >= 1, got {tile_size!r}")
    step = camera_center_step(camera) if step is None else float(step)
    if not (math.isfinite(step) and step > 0):
        raise ValueError(f"step must be a positive finite angle, got {step!r}")
    t0, t1, p0, p1 = camera_angular_extent(camera, max_half_angle, mask)
    w, t0, t1 = _fit_axis(t0, t1, step, tile_size, max_half_angle)
    h, p0, p1 = _fit_axis(p0, p1, step, tile_size, max_half_angle)
    return BeapGrid(w, h, t0, t1, p0, p1)


# ==================================================================================================
# Sampling
# ==================================================================================================


def _as_image(image: Tensor | np.ndarray) -> Tensor:
    """[H, W, C] float32 in [0, 1] (uint8 is divided by 255, float is taken as is)."""
    t = torch.as_tensor(np.ascontiguousarray(image)) if isinstance(image, np.ndarray) else image
    if t.ndim == 2:
        t = t[..., None]
    if t.ndim != 3:
        raise ValueError(f"image must be [H, W, C] or [H, W], got shape {tuple(t.shape)}")
    if t.dtype == torch.uint8:
        return t.to(torch.float32) / 255.0
    if not t.is_floating_point():
        raise ValueError(f"image must be uint8 or floating point, got {t.dtype}")
    return t.to(torch.float32)


def _as_mask(mask: Tensor | np.ndarray, camera: CameraModel) -> Tensor:
    m = torch.as_tensor(np.ascontiguousarray(mask)) if isinstance(mask, np.ndarray) else mask
    if m.ndim == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if tuple(m.shape) != (camera.height, camera.width):
        raise ValueError(f"mask must be [{camera.height}, {camera.width}], got {tuple(m.shape)}")
    return m != 0


def _bilinear(image: Tensor, valid: Tensor, uv: Tensor) -> tuple[Tensor, Tensor]:
    """Sample ``image [H, W, C]`` at continuous coords ``uv [..., 2]`` (pixel centers at +0.5).

    Returns values ``[..., C]`` and ``ok [...]``: inside the image rectangle and all (edge-clamped) pixels
    of the bilinear footprint valid.
    """
    H, W = valid.shape
    u, v = uv[..., 0], uv[..., 1]
    finite = torch.isfinite(u) & torch.isfinite(v)
    inside = finite & (u >= 0) & (u <= W) & (v >= 0) & (v <= H)
    x = torch.where(inside, u, torch.zeros_like(u)) - 0.5
    y = torch.where(inside, v, torch.zeros_like(v)) - 0.5
    x0f, y0f = torch.floor(x), torch.floor(y)
    wx, wy = (x - x0f).to(image.dtype), (y - y0f).to(image.dtype)
    x0 = x0f.long().clamp(0, W - 1)
    x1 = (x0f.long() + 1).clamp(0, W - 1)
    y0 = y0f.long().clamp(0, H - 1)
    y1 = (y0f.long() + 1).clamp(0, H - 1)
    flat = image.reshape(H * W, -1)
    vflat = valid.reshape(-1)
    out = 0
    ok = inside
    for yi, xi, wgt in (
        (y0, x0, (1 - wx) * (1 - wy)),
        (y0, x1, wx * (1 - wy)),
        (y1, x0, (1 - wx) * wy),
        (y1, x1, wx * wy),
    ):
        idx = yi * W + xi
        out = out + flat[idx] * wgt.unsqueeze(-1)
        ok = ok & vflat[idx]
    out = torch.where(ok.unsqueeze(-1), out, torch.zeros_like(out))
    return out, ok


def _auto_supersample(px: Tensor, ok: Tensor, max_supersample: int) -> int:
    """k from the median native-pixel distance between projections of neighboring BEAP cell centers."""
    dx = (px[:, 1:] - px[:, :-1]).norm(dim=-1)
    dy = (px[1:] - px[:-1]).norm(dim=-1)
    okx = ok[:, 1:] & ok[:, :-1]
    oky = ok[1:] & ok[:-1]
    d = torch.cat([dx[okx], dy[oky]])
    if d.numel() == 0:
        return 1
    return int(min(max(round(float(d.median())), 1), max_supersample))


def resample_to_beap(
    image: Tensor | np.ndarray,
    camera: CameraModel,
    grid: BeapGrid,
    mask: Tensor | np.ndarray | None = None,
    supersample: int | None = None,
    max_supersample: int = 4,
) -> tuple[Tensor, Tensor]:
    """Resample a native image ``[H, W, C]`` (or ``[H, W]``) into the BEAP grid.

    Returns ``beap_image [h, w, C]`` (float32, [0, 1] for uint8 input, zeros where invalid) and
    ``valid [h, w]``: every sub-sample of the cell projects camera-validly inside the image with a bilinear
    footprint fully inside ``mask`` (HxW bool/uint8, nonzero = valid). ``supersample`` = k overrides the
    automatic antialiasing factor (see module docstring).
    """
    img = _as_image(image)
    if tuple(img.shape[:2]) != (camera.height, camera.width):
        raise ValueError(f"image is {tuple(img.shape[:2])}, camera expects ({camera.height}, {camera.width})")
    pix_valid = (
        _as_mask(mask, camera) if mask is not None else torch.ones(camera.height, camera.width, dtype=torch.bool)
    )

    if supersample is None:
        px, cam_ok = camera.project(grid.directions(torch.float64))
        supersample = _auto_supersample(px, cam_ok, max_supersample)
    k = int(supersample)
    if k < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample!r}")

    dirs = grid.directions(torch.float64, supersample=k)
    if k == 1:
        dirs = dirs[:, :, None, None]
    px, cam_ok = camera.project(dirs)  # [h, w, k, k, 2]
    values, ok = _bilinear(img, pix_valid, px)
    ok = ok & cam_ok
    valid = ok.flatten(2).all(-1)
    beap = values.flatten(2, 3).mean(2)  # box filter over the k x k sub-samples
    beap = torch.where(valid.unsqueeze(-1), beap, torch.zeros_like(beap))
    return beap, valid


def beap_to_native(
    beap_image: Tensor | np.ndarray,
    grid: BeapGrid,
    camera: CameraModel,
    beap_valid: Tensor | np.ndarray | None = None,
) -> tuple[Tensor, Tensor]:
    """Map a BEAP image ``[h, w, C]`` back to the camera's pixels (to score renders natively).

    Each native pixel center is unprojected, converted to (theta, phi) and sampled bilinearly in the BEAP
    image. ``valid [H, W]``: camera-valid, in front of the camera, inside the BEAP grid and (if
    ``beap_valid`` is given) with a fully valid bilinear footprint.
    """
    img = _as_image(beap_image)
    if tuple(img.shape[:2]) != (grid.height, grid.width):
        raise ValueError(f"BEAP image is {tuple(img.shape[:2])}, grid is ({grid.height}, {grid.width})")
    if beap_valid is None:
        cell_ok = torch.ones(grid.height, grid.width, dtype=torch.bool)
    else:
        cell_ok = (
            torch.as_tensor(np.ascontiguousarray(beap_valid)) if isinstance(beap_valid, np.ndarray) else beap_valid
        )
        cell_ok = cell_ok != 0
    dirs, cam_ok = camera.pixel_rays(torch.float64)
    theta, phi = directions_to_angles(dirs)
    front = dirs[..., 2] > 0
    cells = grid.angles_to_cells(theta, phi)
    values, ok = _bilinear(img, cell_ok, cells)
    valid = ok & cam_ok & front
    values = torch.where(valid.unsqueeze(-1), values, torch.zeros_like(values))
    return values, valid
