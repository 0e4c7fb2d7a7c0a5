"""Depth supervision targets: a frame's `depth_file_path` as the distance along each training ray.

Two kinds of file (docs/outputs.md, "Depth supervision"):

* a depth map (.png/.tif/.exr read by OpenCV unchanged, or a 2-D .npy), the image's size, values times the
  dataparser's `depth_unit_scale_factor` (nerfstudio's convention, default 1e-3: millimeters). A PERSPECTIVE
  camera's map holds camera-space z (nerfstudio's and most depth sensors' convention); every other camera
  model's (fisheye, equirectangular, ...) the radial distance along the pixel's ray, since z is undefined past
  90 degrees. 0, negative or non-finite values mean "no measurement".
* a point file (.ply, or a .npy of shape [M, 3]): LiDAR points in the frame of transforms.json's poses (as
  `ply_file_path`), in meters; each point supervises the ray of the view pixel it projects to with its distance
  from the camera (the nearest point where several fall on one pixel).

Both become one target per training ray: the radial distance in the dataparser's scaled world units, 0 where
unmeasured, on the grid the model renders (native pixels or the camera's BEAP grid).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import torch
from torch import Tensor

from nerfstudio.cameras.cameras import Cameras, CameraType

from geer_ns.cameras import CameraModel
from geer_ns.data.beap import resample_to_beap
from geer_ns.data.views import beap_view, native_view
from geer_ns.data.ply import read_ply_points

POINT_SUFFIXES = (".ply",)

# Batch key of the target: [h, w, 1] float32 radial distance, 0 where unmeasured.
TARGET_KEY = "sensor_distance"


def is_point_file(path: Path) -> bool:
    """Whether `path` holds LiDAR points rather than a depth map."""
    if path.suffix.lower() in POINT_SUFFIXES:
        return True
    if path.suffix.lower() == ".npy":
        shape = np.load(path, mmap_mode="r").shape
        return len(shape) == 2 and shape[1] == 3
    return False


def read_depth_map(path: Path, height: int, width: int) -> np.ndarray:
    """[H, W] float64 raw values of a depth map file (units as stored)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: depth_file_path does not exist")
    values = np.load(path) if path.suffix.lower() == ".npy" else cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if values is None:
        raise ValueError(f"{path}: depth_file_path could not be read as an image")
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 3:
        values = values[..., 0]
    if values.shape != (height, width):
        raise ValueError(f"{path}: depth_file_path is {values.shape[1]}x{values.shape[0]} (w x h), its image "
                         f"{width}x{height}")
    return values


def read_points(path: Path) -> np.ndarray:
    """[M, 3] float64 points of a LiDAR point file."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: depth_file_path does not exist")
    xyz = read_ply_points(path)[0] if path.suffix.lower() == ".ply" else np.load(path)
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"{path}: depth_file_path: expected points of shape [M, 3], got {xyz.shape}")
    return xyz[np.isfinite(xyz).all(axis=1)]


def map_distance(raw: np.ndarray, camera: CameraModel, perspective: bool, unit: float) -> Tensor:
    """[H, W] radial distance from a depth map's raw values: times `unit`, and for a perspective (z) map divided
    by each pixel ray's z. 0 where unmeasured."""
    values = torch.from_numpy(raw) * unit
    measured = torch.isfinite(values) & (values > 0)
    if perspective:
        dirs, ok = camera.pixel_rays(torch.float64)
        values = values / dirs[..., 2].clamp_min(1e-12)
        measured = measured & ok & (dirs[..., 2] > 0)
    return torch.where(measured, values, torch.zeros_like(values))


def world_to_camera_cv(camera_to_world: Tensor) -> tuple[Tensor, Tensor]:
    """(R [3, 3], t [3]) mapping world points into OpenCV camera axes, from a nerfstudio c2w [3, 4] (OpenGL)."""
    rot = camera_to_world[:3, :3].double() * camera_to_world.new_tensor([1.0, -1.0, -1.0]).double()
    return rot.T, -rot.T @ camera_to_world[:3, 3].double()


def points_distance(points_world: Tensor, camera_to_world: Tensor, view) -> Tensor:
    """[h, w] distance of the nearest point on each pixel of `view` (views.BeapView / NativeView), 0 where none.
    points_world [M, 3] in the dataparser's world frame, camera_to_world [3, 4] nerfstudio's."""
    rot, trans = world_to_camera_cv(camera_to_world)
    cam = points_world.double() @ rot.T + trans
    pixels, ok = view.project(cam)
    height, width = view.size
    col, row = pixels[..., 0].floor(), pixels[..., 1].floor()
    ok = ok & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    index = (row[ok] * width + col[ok]).long()
    nearest = torch.full((height * width,), float("inf"), dtype=torch.float64)
    nearest.scatter_reduce_(0, index, cam[ok].norm(dim=-1), reduce="amin")
    return torch.where(torch.isfinite(nearest), nearest, 0.0).reshape(height, width)


def to_view(distance: Tensor, camera: CameraModel, view_kind: str) -> Tensor:
    """A native [H, W] distance target on the grid of `view_kind` ("native" or "beap": resampled bilinearly
    where the whole footprint is measured, unmeasured elsewhere)."""
    if view_kind != "beap":
        return distance
    resampled, ok = resample_to_beap(distance[..., None].float(), camera, beap_view(camera).grid, distance > 0)
    return torch.where(ok, resampled[..., 0], torch.zeros_like(resampled[..., 0])).double()


def sensor_distance(cameras: Cameras, idx: int, camera: CameraModel, metadata: dict, scale: float,
                    to_dataparser: Tensor, view_kind: str) -> Optional[Tensor]:
    """The target [h, w, 1] float32 of frame `idx` (None when the dataset has no depth files): its
    `depth_file_path` read as described in the module docstring, in the dataparser's scaled units, on the grid
    of `view_kind`. to_dataparser [3, 4]: from transforms.json's pose frame to the dataparser's (points)."""
    files = metadata.get("depth_filenames")
    if not files:
        return None
    path = Path(files[idx])
    if is_point_file(path):
        pts = torch.from_numpy(read_points(path))
        pts = (torch.cat([pts, torch.ones_like(pts[:, :1])], -1) @ to_dataparser.double().T) * scale
        view = beap_view(camera) if view_kind == "beap" else native_view(camera)
        distance = points_distance(pts, cameras.camera_to_worlds[idx], view)
    else:
        perspective = int(cameras.camera_type.reshape(-1)[idx]) == CameraType.PERSPECTIVE.value
        raw = read_depth_map(path, camera.height, camera.width)
        unit = float(metadata.get("depth_unit_scale_factor", 1e-3)) * scale
        distance = to_view(map_distance(raw, camera, perspective, unit), camera, view_kind)
    return distance.float()[..., None]


def downscale_target(target: Tensor, factor: int) -> Tensor:
    """[H, W, 1] -> [H/f, W/f, 1]: the mean of each block's measured values (0 where none is measured)."""
    if factor == 1:
        return target
    blocks = target[..., 0][None, None]
    measured = (blocks > 0).to(blocks.dtype)
    total = torch.nn.functional.avg_pool2d(blocks * measured, factor, stride=factor)
    count = torch.nn.functional.avg_pool2d(measured, factor, stride=factor)
    return torch.where(count > 0, total / count.clamp_min(1e-12), 0.0)[0, 0, ..., None]
