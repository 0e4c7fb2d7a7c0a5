"""A copy of a nerfstudio-format dataset whose images have per-frame exposure / white balance and vignetting.

Each image is decoded to linear light (sRGB curve), multiplied by its frame's gains and the camera's
vignetting, clipped (the sensor saturates) and encoded again, as a camera records before its tone curve:

    gain_frame = 2^e * (exp(w_r), 1, exp(w_b)),  e ~ U(-stops, stops),  w ~ N(0, white_balance)
    vignetting(theta) = cos(theta / 2)^k,  theta the pixel ray's angle from the optical axis (the camera model
                                          of the transforms file, so right on a fisheye)

Frames listed in the file's val_filenames / test_filenames keep the neutral gain (the scene as evaluated) and
get the vignetting (a property of the camera). The truth is written beside the images to
appearance_truth.json: per frame its log gains (natural log, per channel) and the vignetting law.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Dict, Sequence

import cv2
import numpy as np
import torch

TRUTH_NAME = "appearance_truth.json"


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def pixel_angles(meta: dict, frame: dict, transforms: Path) -> np.ndarray:
    """[H, W] angle of each pixel center's ray from the optical axis, for the frame's camera model."""
    from nerfstudio.cameras.cameras import CAMERA_MODEL_TO_TYPE, Cameras

    from geer_ns.cameras import from_nerfstudio
    from geer_ns.data.nerfstudio_parser import _frame_camera

    name, (fx, fy, cx, cy, w, h), dist, _ = _frame_camera(meta, frame, transforms)
    cam = Cameras(camera_to_worlds=torch.eye(4)[None, :3], fx=fx, fy=fy, cx=cx, cy=cy, width=int(w), height=int(h),
                  distortion_params=dist[None], camera_type=CAMERA_MODEL_TO_TYPE[name])
    dirs, _valid = from_nerfstudio(cam, 0).pixel_rays(torch.float64)
    return torch.atan2(dirs[..., :2].norm(dim=-1), dirs[..., 2]).numpy()


def apply_sensor(image: np.ndarray, log_gains: Sequence[float], theta: np.ndarray, falloff: float) -> np.ndarray:
    """image [H, W, 3] in [0, 1] (sRGB-encoded) as the sensor records it: gains and vignetting in linear light."""
    lin = _srgb_to_linear(image) * np.exp(np.asarray(log_gains))[None, None, :]
    lin = lin * (np.cos(theta / 2.0) ** falloff)[..., None]
    return _linear_to_srgb(lin)


def make_variant(src: Path, out: Path, transforms: str = "transforms.json", exposure_stops: float = 0.7,
                 white_balance: float = 0.15, vignetting: float = 4.0, seed: int = 0) -> Dict[str, list]:
    """Write the variant of src/transforms to out (a copy of src; images of the file re-encoded as PNG);
    returns the truth written to out/appearance_truth.json."""
    if out.exists():
        raise FileExistsError(f"{out}: exists; the variant is written to a new folder")
    shutil.copytree(src, out)
    path = out / transforms
    meta = json.loads(path.read_text())
    neutral = set(meta.get("val_filenames", [])) | set(meta.get("test_filenames", []))
    rng = np.random.default_rng(seed)
    truth = {"vignetting": f"cos(theta / 2)^{vignetting}", "exposure_stops": exposure_stops,
             "white_balance": white_balance, "frames": {}}
    renamed = {}
    angles: Dict[tuple, np.ndarray] = {}
    for frame in meta["frames"]:
        image_path = out / frame["file_path"]
        image = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
        if image is None:
            raise ValueError(f"{path}: frame {frame['file_path']!r}: the image cannot be read")
        key = tuple(sorted((k, v) for k, v in frame.items() if k not in ("file_path", "transform_matrix", "mask_path")
                           and not isinstance(v, list)))
        if key not in angles:
            angles[key] = pixel_angles(meta, frame, path)
        if frame["file_path"] in neutral:
            log_gains = [0.0, 0.0, 0.0]
        else:
            e = rng.uniform(-exposure_stops, exposure_stops) * math.log(2.0)
            w_r, w_b = rng.normal(0.0, white_balance, 2)
            log_gains = [e + w_r, e, e + w_b]
        rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB).astype(np.float64) / 255.0
        recorded = apply_sensor(rgb, log_gains, angles[key], vignetting)
        new_name = str(Path(frame["file_path"]).with_suffix(".png"))
        u8 = np.clip(np.round(recorded * 255.0), 0, 255).astype(np.uint8)
        cv2.imwrite(str(out / new_name), cv2.cvtColor(u8, cv2.COLOR_RGB2BGR))
        if new_name != frame["file_path"]:
            image_path.unlink()
        renamed[frame["file_path"]] = new_name
        frame["file_path"] = new_name
        truth["frames"][new_name] = [float(g) for g in log_gains]
    for split in ("train_filenames", "val_filenames", "test_filenames"):
        if split in meta:
            meta[split] = [renamed.get(name, name) for name in meta[split]]
    path.write_text(json.dumps(meta, indent=2) + "\n")
    (out / TRUTH_NAME).write_text(json.dumps(truth, indent=2) + "\n")
    return truth
