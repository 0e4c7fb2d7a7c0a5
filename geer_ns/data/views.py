"""Per-camera ray grids, cached per intrinsics and shared by the datamanager and the model.

Camera models are frozen dataclasses (hashable, equal when their intrinsics are equal), so the
datamanager that resamples a training image into BEAP and the model that renders that view get the
very same `BeapView` object: one BEAP grid definition, no chance of the two drifting apart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import torch
from torch import Tensor

from nerfstudio.cameras.cameras import Cameras, CameraType

from geer_ns.cameras import CameraModel
from geer_ns.data.colmap_parser import MODEL_ID_KEY, NS_TYPE_KEY, camera_model_from_cameras
from geer_ns.data.nerfstudio_parser import CAMERA_MODEL_KEY, CAMERA_MODELS
from geer_ns.data.beap import BeapGrid, beap_grid_for_camera, camera_center_step
from geer_ns.render import RayGrid

TILE_SIZE = 16
# Distinct intrinsics seen in one run are few (one per physical camera and viewer size).
_CACHE_SIZE = 64


@dataclass(frozen=True, eq=False)
class BeapView:
    """The BEAP image a training camera is supervised in, at one downscale factor."""

    camera: CameraModel
    grid: BeapGrid
    rays: RayGrid  # valid = cells whose ray the camera can see
    downscale: int

    @property
    def size(self) -> tuple[int, int]:
        return self.grid.height, self.grid.width

    @property
    def center_solid_angle(self) -> float:
        """Solid angle of the cell on the optical axis (sr)."""
        return self.grid.step_theta * self.grid.step_phi

    @property
    def source_project(self):
        """The projection of the camera whose pixels the BEAP image is resampled from."""
        return self.camera.project

    def project(self, points_cam: Tensor) -> tuple[Tensor, Tensor]:
        """Camera-frame points [..., 3] -> BEAP cell coordinates [..., 2] (x along theta, y along phi) and
        whether the point lies in front of the camera inside the grid's angular range."""
        x, y, z = points_cam.unbind(-1)
        theta, phi = torch.atan2(x, z), torch.atan2(y, z)
        g = self.grid
        pixels = torch.stack([(theta - g.theta_min) / g.step_theta, (phi - g.phi_min) / g.step_phi], -1)
        valid = (z > 0) & (theta >= g.theta_min) & (theta <= g.theta_max) & (phi >= g.phi_min) & (phi <= g.phi_max)
        return pixels, valid


@dataclass(frozen=True, eq=False)
class NativeView:
    """A camera's own pixel rays (no undistortion), for eval, the viewer and native supervision."""

    camera: CameraModel
    rays: RayGrid
    step: float  # angular size of a pixel at the principal point (radians per pixel)

    @property
    def center_solid_angle(self) -> float:
        """Solid angle of a pixel at the principal point (sr)."""
        return self.step * self.step

    @property
    def source_project(self):
        """None: the view's pixels are the camera's own."""
        return None

    def project(self, points_cam: Tensor) -> tuple[Tensor, Tensor]:
        return self.camera.project(points_cam)

    @property
    def size(self) -> tuple[int, int]:
        return self.camera.height, self.camera.width


def camera_model(cameras: Cameras, index: int = 0) -> CameraModel:
    """The exact model of camera `index`: the COLMAP model when geer's COLMAP parser stored one (FOV,
    thin-prism, ... which nerfstudio cannot represent), else the model nerfstudio's camera describes."""
    return camera_model_from_cameras(cameras, index)


# Camera metadata key: the camera's model made on the host when the batch was made (datamanager.train_camera),
# so that a render on the GPU reads no camera parameter back from it (one host sync per float).
HOST_MODEL_KEY = "geer_host_camera_model"  # a CameraModel (not nerfstudio_parser.CAMERA_MODEL_KEY)


def host_camera_model(camera: Cameras) -> CameraModel:
    """The model of a one-camera batch: the one its datamanager attached, else read from the camera."""
    found = (camera.metadata or {}).get(HOST_MODEL_KEY)
    return found if found is not None else camera_model(camera, 0)


def camera_kind(cameras: Cameras, index: int = 0) -> str:
    """The name metrics and reports use for camera `index`'s model: the COLMAP model (geer-colmap), the
    transforms.json camera_model (geer's nerfstudio parser), else nerfstudio's camera type."""
    import pycolmap

    meta = cameras.metadata or {}
    ns_type = int(cameras.camera_type.reshape(-1)[index])
    if MODEL_ID_KEY in meta and int(meta.get(NS_TYPE_KEY, cameras.camera_type).reshape(-1)[index]) == ns_type:
        return pycolmap.CameraModelId(int(meta[MODEL_ID_KEY].reshape(-1)[index])).name
    if CAMERA_MODEL_KEY in meta:
        return CAMERA_MODELS[int(meta[CAMERA_MODEL_KEY].reshape(-1)[index])]
    return CameraType(ns_type).name


@lru_cache(maxsize=_CACHE_SIZE)
def full_beap_grid(camera: CameraModel) -> BeapGrid:
    """The full-resolution BEAP grid of a camera (square cells: one angular step in theta and phi)."""
    return beap_grid_for_camera(camera, tile_size=TILE_SIZE)


def downscaled_grid(grid: BeapGrid, factor: int) -> BeapGrid:
    """Same angular range, `factor` x fewer cells per axis (each cell = a factor x factor block)."""
    if grid.width % factor or grid.height % factor:
        raise ValueError(f"BEAP grid {grid.width}x{grid.height} is not divisible by downscale {factor}")
    return BeapGrid(grid.width // factor, grid.height // factor, grid.theta_min, grid.theta_max,
                    grid.phi_min, grid.phi_max)


def _camera_sees(camera: CameraModel, dirs: Tensor) -> Tensor:
    """[h, w] bool: the ray projects camera-validly inside the image rectangle."""
    px, ok = camera.project(dirs.to(torch.float64))
    inside = (px[..., 0] >= 0) & (px[..., 0] <= camera.width) & (px[..., 1] >= 0) & (px[..., 1] <= camera.height)
    return ok & inside


def beap_view(camera: CameraModel, downscale: int = 1) -> BeapView:
    """The (cached) BEAP view of a camera; `downscale` follows splatfacto's resolution schedule."""
    return _beap_view(camera, int(downscale))  # one cache key however the factor is passed


@lru_cache(maxsize=_CACHE_SIZE)
def _beap_view(camera: CameraModel, downscale: int) -> BeapView:
    grid = downscaled_grid(full_beap_grid(camera), downscale)
    dirs = grid.directions(torch.float32)
    rays = RayGrid.from_rays(dirs, _camera_sees(camera, dirs), TILE_SIZE)
    return BeapView(camera, grid, rays, downscale)


@lru_cache(maxsize=_CACHE_SIZE)
def native_view(camera: CameraModel) -> NativeView:
    """The (cached) per-pixel ray grid of a camera."""
    dirs, valid = camera.pixel_rays(torch.float32)
    return NativeView(camera, RayGrid.from_rays(dirs, valid, TILE_SIZE), _pixel_step(camera))


def _pixel_step(camera: CameraModel) -> float:
    try:
        return camera_center_step(camera)
    except ValueError:  # no invertible principal point: fall back to the mean angular pitch
        return camera.max_angle / max(camera.width, camera.height) if math.isfinite(camera.max_angle) else 1e-3


def clear_caches() -> None:
    for cached in (full_beap_grid, _beap_view, native_view):
        cached.cache_clear()
