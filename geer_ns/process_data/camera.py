"""Per-camera set-up before SfM: the mask (image circle) and the starting or fixed intrinsics.

Why a focal-length prior for fisheye lenses: COLMAP cannot recover a fisheye focal length from a fundamental
matrix and marks such pairs degenerate ("Provide a focal length prior"). An equidistant lens maps the edge of
its image circle (radius R) to half its field of view, so f ~= R / (fov / 2) is a good start; bundle adjustment
refines it together with k1..k4.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import cv2
import numpy as np
from nerfstudio.utils.rich_utils import CONSOLE

from geer_ns.data.image_circle import ImageCircle, detect_image_circle_from_files
from geer_ns.process_data.frames import CameraGroup, ProcessDataError

FISHEYE_MODELS = {"OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "SIMPLE_FISHEYE", "FISHEYE",
                  "THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE"}


@dataclass(frozen=True)
class Calibration:
    """A COLMAP camera given by the user."""

    model: str
    width: int
    height: int
    params: Tuple[float, ...]
    source: str  # where it came from, for messages


@dataclass(frozen=True)
class CameraSetup:
    """What the SfM needs per camera group."""

    model: str
    params: Optional[Tuple[float, ...]]  # None: COLMAP's own guess
    fixed: bool  # held fixed during mapping (user calibration)
    circle: Optional[ImageCircle]
    mask_file: Optional[Path]  # dataset mask (255 = use), relative to the output folder
    feature_mask_file: Optional[Path]  # absolute: where SIFT keypoints are allowed (eroded mask)


def _param_names(model: str) -> List[str]:
    import pycolmap

    try:
        cam = pycolmap.Camera.create_from_model_name(0, model, 1.0, 2, 2)
    except Exception:
        raise ValueError(f"unknown COLMAP camera model {model}") from None
    return [n.strip() for n in cam.params_info.split(",")]


def read_cameras_txt(path: Path) -> List[Calibration]:
    """Cameras of a COLMAP cameras.txt (CAMERA_ID MODEL WIDTH HEIGHT PARAMS...), in file order."""
    cams = []
    for lineno, line in enumerate(path.read_text(encoding="utf8").splitlines(), 1):
        tok = line.split("#", 1)[0].replace(",", " ").split()
        if not tok:
            continue
        where = f"{path}:{lineno}"
        if len(tok) < 5:
            raise ProcessDataError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got {line.strip()!r}")
        try:
            names = _param_names(tok[1])
            values = [float(v) for v in tok[4:]]
            width, height = int(tok[2]), int(tok[3])
        except ValueError as e:
            raise ProcessDataError(f"{where}: {e}") from None
        if len(values) != len(names):
            raise ProcessDataError(f"{where}: {tok[1]} expects {len(names)} params ({', '.join(names)}), "
                                   f"got {len(values)}")
        if not all(math.isfinite(v) for v in values):
            raise ProcessDataError(f"{where}: a parameter is not finite")
        cams.append(Calibration(tok[1], width, height, tuple(values), where))
    if not cams:
        raise ProcessDataError(f"{path}: no camera lines")
    return cams


def read_nerfstudio_intrinsics(path: Path) -> Calibration:
    """The camera of a nerfstudio transforms.json (top-level intrinsics, else the first frame's)."""
    try:
        meta = json.loads(path.read_text(encoding="utf8"))
    except (OSError, json.JSONDecodeError) as e:
        raise ProcessDataError(f"{path}: not a readable JSON file: {e}") from None
    src = meta if "fl_x" in meta else (meta.get("frames") or [{}])[0]
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        if key not in src:
            raise ProcessDataError(f"{path}: field '{key}' is missing (needed for --calibration)")
    model = src.get("camera_model", meta.get("camera_model", "OPENCV"))
    d = {k: float(src.get(k, 0.0)) for k in ("k1", "k2", "k3", "k4", "p1", "p2")}
    f = (float(src["fl_x"]), float(src["fl_y"]), float(src["cx"]), float(src["cy"]))
    if model == "OPENCV_FISHEYE":
        params = (*f, d["k1"], d["k2"], d["k3"], d["k4"])
    elif model == "OPENCV":
        if d["k3"] or d["k4"]:
            params, model = (*f, d["k1"], d["k2"], d["p1"], d["p2"], d["k3"], d["k4"], 0.0, 0.0), "FULL_OPENCV"
        else:
            params = (*f, d["k1"], d["k2"], d["p1"], d["p2"])
    else:
        raise ProcessDataError(f"{path}: camera_model '{model}' is not supported for --calibration "
                               "(OPENCV or OPENCV_FISHEYE; or give a COLMAP cameras.txt)")
    return Calibration(model, int(src["w"]), int(src["h"]), params, str(path))


def read_calibration(path: Path) -> List[Calibration]:
    if not path.is_file():
        raise ProcessDataError(f"--calibration {path} does not exist")
    if path.suffix.lower() == ".json":
        return [read_nerfstudio_intrinsics(path)]
    return read_cameras_txt(path)


def _fit_to_size(cal: Calibration, width: int, height: int, group: str) -> Tuple[float, ...]:
    """The calibration's params at the images' size (scaled when only the resolution differs)."""
    if (cal.width, cal.height) == (width, height):
        return cal.params
    s = width / cal.width
    if abs(height / cal.height - s) > 1e-3:
        raise ProcessDataError(
            f"{cal.source}: calibration size {cal.width}x{cal.height} does not match the images of "
            f"{group or 'the input'} ({width}x{height}) and has another aspect ratio"
        )
    CONSOLE.print(f"[yellow]{cal.source}: calibration at {cal.width}x{cal.height}, images {width}x{height}: "
                  f"focal length and principal point scaled by {s:.4g}")
    import pycolmap

    cam = pycolmap.Camera.create_from_model_name(0, cal.model, 1.0, cal.width, cal.height)
    params = list(cal.params)
    for i in list(cam.focal_length_idxs()) + list(cam.principal_point_idxs()):
        params[i] *= s
    return tuple(params)


def _initial_params(model: str, group: CameraGroup, circle: Optional[ImageCircle],
                    fov_deg: Optional[float]) -> Optional[Tuple[float, ...]]:
    """Starting intrinsics (refined by bundle adjustment): see the module docstring."""
    w, h = group.width, group.height
    names = _param_names(model)
    if model in FISHEYE_MODELS:
        half_fov = math.radians((fov_deg or 180.0) / 2)
        radius = circle.radius if circle is not None else math.hypot(w, h) / 2  # full frame: the diagonal
        f = radius / half_fov
        cx, cy = (circle.cx, circle.cy) if circle is not None else (w / 2, h / 2)
    elif fov_deg is not None:
        if not 0 < fov_deg < 180:
            raise ProcessDataError(f"--fov-deg {fov_deg}: a {model} camera needs a field of view below 180")
        f = (w / 2) / math.tan(math.radians(fov_deg) / 2)
        cx, cy = w / 2, h / 2
    else:
        return None  # COLMAP's guess (1.2 x the larger side) works for narrow lenses
    values = {"f": f, "fx": f, "fy": f, "cx": cx, "cy": cy}
    return tuple(float(values.get(n, 0.0)) for n in names)


def _read_mask(path: Path, group: CameraGroup) -> np.ndarray:
    mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        raise ProcessDataError(f"--mask {path}: not a readable image")
    if mask.shape != (group.height, group.width):
        raise ProcessDataError(f"--mask {path}: size {mask.shape[1]}x{mask.shape[0]} differs from the images "
                               f"({group.width}x{group.height})")
    return mask > 127


def setup_cameras(
    groups: Sequence[CameraGroup],
    out_dir: Path,
    work_dir: Path,
    model: str,
    calibration: Optional[Path],
    mask: Optional[Path],
    auto_mask: bool,
    fov_deg: Optional[float],
) -> List[CameraSetup]:
    """Masks and intrinsics of every camera group (masks written to ``out_dir/masks``)."""
    cals = read_calibration(calibration) if calibration is not None else None
    if cals is not None and len(cals) not in (1, len(groups)):
        raise ProcessDataError(f"--calibration {calibration}: {len(cals)} cameras for {len(groups)} camera "
                               "folders; give one camera, or one per folder in sorted folder order")
    setups = []
    for gi, group in enumerate(groups):
        stem = group.name.replace("/", "_") or "mask"
        label = f"camera '{group.name}'" if group.name else "the camera"
        circle = None
        keep = None
        if mask is not None:
            mask_path = mask / f"{stem}.png" if mask.is_dir() else mask
            keep = _read_mask(mask_path, group)
        elif auto_mask:
            paths = [out_dir / "images" / n for n in group.image_names]
            circle = detect_image_circle_from_files(paths)
            if circle is not None:
                keep = circle.mask(group.width, group.height)
                CONSOLE.print(f"{label}: image circle center ({circle.cx:.1f}, {circle.cy:.1f}), radius "
                              f"{circle.radius:.1f} px; pixels outside it are masked")
            else:
                CONSOLE.print(f"{label}: no black border around the image: no mask, every pixel is used")
        mask_file = feature_mask = None
        if keep is not None:
            mask_file = Path("masks") / f"{stem}.png"
            (out_dir / "masks").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(out_dir / mask_file), keep.astype(np.uint8) * 255)
            # SIFT descriptors span several pixels: keep keypoints off the rim, whose edge is the same in
            # every frame and would match itself.
            margin = max(3, int(round(0.015 * min(group.width, group.height))))
            eroded = cv2.erode(keep.astype(np.uint8), np.ones((2 * margin + 1,) * 2, np.uint8))
            feature_mask = work_dir / "feature_masks" / f"{stem}.png"
            feature_mask.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(feature_mask), eroded * 255)
        if cals is not None:
            cal = cals[gi if len(cals) > 1 else 0]
            setups.append(CameraSetup(cal.model, _fit_to_size(cal, group.width, group.height, group.name), True,
                                      circle, mask_file, feature_mask))
        else:
            params = _initial_params(model, group, circle, fov_deg)
            setups.append(CameraSetup(model, params, False, circle, mask_file, feature_mask))
    return setups
