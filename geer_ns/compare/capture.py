"""The capture every method of geer-compare is scored on: its test views at their own cameras and pixels (ground
truth, valid pixels, central region), and copies of it resampled to another camera for splatfacto's variants."""

from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

import cv2
import numpy as np
import torch
from torch import Tensor

from geer_ns.cameras import CameraModel, OpenCVFisheyeCamera, PinholeCamera
from geer_ns.compare.resample import landing, resample, to_uint8
from geer_ns.errors import DatasetError
from geer_ns.metrics.regions import central_region

_SPLITS = ("train_filenames", "val_filenames", "test_filenames")
_CAMERA_KEYS = ("camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2",
                "distortion_params", "fisheye_crop_radius")


@dataclass
class TestView:
    name: str
    camera: CameraModel  # the capture's own camera
    image: Tensor  # [H, W, 3] float in [0, 1]
    valid: Tensor  # [H, W] bool: pixels the camera saw (its model, mask, crop circle)
    central: Tensor  # [H, W] bool: inside the central region


@dataclass
class Capture:
    transforms: Path
    meta: dict
    camera: CameraModel  # the capture's camera (one for every frame)
    views: List[TestView]
    test_poses: Tensor  # [V, 3, 4] the test views' camera-to-world in the transforms file's frame

    @property
    def is_fisheye(self) -> bool:
        return self.meta.get("camera_model") in ("OPENCV_FISHEYE", "FISHEYE")

    @property
    def is_equidistant(self) -> bool:
        return self.is_fisheye and all(float(self.meta.get(k, 0.0)) == 0.0 for k in ("k1", "k2", "k3", "k4"))


def transforms_path(data: Path) -> Path:
    data = Path(data)
    path = data if data.suffix == ".json" else data / "transforms.json"
    if not path.is_file():
        raise DatasetError(f"geer-compare: --data {data}: no transforms file at {path}")
    return path


def camera_of(meta: dict, path: Path) -> CameraModel:
    """The one camera of a transforms file (top-level fields): OPENCV or OPENCV_FISHEYE."""
    for frame in meta.get("frames", []):
        if any(k in frame for k in _CAMERA_KEYS if k not in ("fisheye_crop_radius",)):
            raise DatasetError(f"{path}: frame {frame.get('file_path')} has its own camera fields; geer-compare "
                             "needs one camera for the whole capture (top-level fields)")
    model = meta.get("camera_model", "OPENCV")
    try:
        w, h, fx, fy, cx, cy = (meta[k] for k in ("w", "h", "fl_x", "fl_y", "cx", "cy"))
    except KeyError as missing:
        raise DatasetError(f"{path}: top-level field {missing} is missing") from None
    get = lambda k: float(meta.get(k, 0.0))  # noqa: E731
    if model == "OPENCV_FISHEYE":
        return OpenCVFisheyeCamera(w, h, fx, fy, cx, cy, k1=get("k1"), k2=get("k2"), k3=get("k3"), k4=get("k4"))
    if model == "OPENCV":
        return PinholeCamera(w, h, fx, fy, cx, cy, k1=get("k1"), k2=get("k2"), p1=get("p1"), p2=get("p2"),
                             k3=get("k3"))
    raise DatasetError(f"{path}: camera_model {model!r}: geer-compare handles OPENCV and OPENCV_FISHEYE captures")


def read_image(path: Path) -> Tensor:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise DatasetError(f"geer-compare: cannot read image {path}")
    return torch.from_numpy(cv2.cvtColor(image, cv2.COLOR_BGR2RGB)).float() / 255.0


def read_mask(path: Optional[Path], shape) -> Tensor:
    if path is None:
        return torch.ones(shape, dtype=torch.bool)
    mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        raise DatasetError(f"geer-compare: cannot read mask {path}")
    return torch.from_numpy(mask >= 128)


def central_of(camera: CameraModel, half_angle_deg: float) -> Tensor:
    """Rays within +-half_angle of the optical axis horizontally and vertically (the paper's App. G rectangle)."""
    dirs, _ = camera.pixel_rays(torch.float64)
    half = math.radians(half_angle_deg)
    return central_region(camera, dirs, (half, half))


def load_capture(data: Path, central_half_angle_deg: float) -> Capture:
    """The capture's test views (nerfstudio's split of the file: its test_filenames, else every 8th frame)."""
    from geer_ns.data.nerfstudio_parser import GeerNerfstudioDataParserConfig

    path = transforms_path(data)
    meta = json.loads(path.read_text())
    camera = camera_of(meta, path)
    parser = GeerNerfstudioDataParserConfig(data=path, load_3D_points=False, downscale_factor=1).setup()
    outputs = parser.get_dataparser_outputs("test")
    masks = outputs.mask_filenames or [None] * len(outputs.image_filenames)
    crop = meta.get("fisheye_crop_radius")
    rays_valid = camera.pixel_rays(torch.float64)[1]
    central = central_of(camera, central_half_angle_deg)
    views = []
    for image_path, mask_path in zip(outputs.image_filenames, masks):
        image = read_image(image_path)
        if image.shape[:2] != (camera.height, camera.width):
            raise DatasetError(f"{image_path}: {image.shape[1]}x{image.shape[0]} pixels, the camera in {path} says "
                             f"{camera.width}x{camera.height}")
        valid = rays_valid & read_mask(mask_path, image.shape[:2])
        if crop is not None:
            uv = camera.pixel_centers(torch.float64)
            valid &= (uv[..., 0] - camera.cx) ** 2 + (uv[..., 1] - camera.cy) ** 2 <= float(crop) ** 2
        views.append(TestView(Path(image_path).name, camera, image, valid, central))
    if not views:
        raise DatasetError(f"geer-compare: {path} has no test images")
    poses = outputs.transform_poses_to_original_space(outputs.cameras.camera_to_worlds)
    return Capture(path, meta, camera, views, poses)


def write_resampled(capture: Capture, target: CameraModel, camera_model: str, out_dir: Path) -> Path:
    """A copy of the capture as `target` sees it from the same poses (same splits, poses, point cloud): images
    resampled by rays, masks where the target sees what the capture did not. Returns its transforms.json."""
    out_dir.mkdir(parents=True, exist_ok=True)
    src_root = capture.transforms.parent
    meta = {k: v for k, v in copy.deepcopy(capture.meta).items() if k not in _CAMERA_KEYS}
    meta.update(camera_model=camera_model, w=target.width, h=target.height, fl_x=target.fx, fl_y=target.fy,
                cx=target.cx, cy=target.cy, k1=0.0, k2=0.0, k3=0.0, k4=0.0)
    if camera_model == "OPENCV":
        meta.update(p1=0.0, p2=0.0)
    if "ply_file_path" in meta:
        meta["ply_file_path"] = str((src_root / meta["ply_file_path"]).resolve())
    _, covered = landing(capture.camera, target)
    renamed = {}
    for i, frame in enumerate(meta["frames"]):
        image = read_image(src_root / frame["file_path"])
        mask = read_mask(src_root / frame["mask_path"] if "mask_path" in frame else None, image.shape[:2])
        warped, _ = resample(image, capture.camera, target)
        seen, _ = resample(mask[..., None].float(), capture.camera, target)
        seen = (seen[..., 0] > 0.5) & covered
        name = f"images/frame_{i:05d}.png"
        renamed[frame["file_path"]] = name
        cv2.imwrite(str(_parent(out_dir / name)), cv2.cvtColor(to_uint8(warped), cv2.COLOR_RGB2BGR))
        frame["file_path"] = name
        frame.pop("mask_path", None)
        if not bool(seen.all()):
            frame["mask_path"] = f"masks/frame_{i:05d}.png"
            cv2.imwrite(str(_parent(out_dir / frame["mask_path"])), seen.numpy().astype(np.uint8) * 255)
    for key in _SPLITS:
        if key in meta:
            meta[key] = [renamed.get(name, name) for name in meta[key]]
    out = out_dir / "transforms.json"
    out.write_text(json.dumps(meta, indent=1))
    return out


def _parent(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return path
