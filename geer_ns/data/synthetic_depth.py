"""Ground-truth depth files for the synthetic room (geer_ns/data/synthetic_room.py), for depth supervision.

`write_depth_variant(room, "fisheye")` writes each frame's radial distance map (float32 .npy) beside a
generated room and `transforms_fisheye_depth.json`, transforms.json with a `depth_file_path` per frame;
`"pinhole"` writes 16-bit PNG z maps and `transforms_pinhole_depth.json`. Both in millimeters, nerfstudio's
default depth unit (depth_unit_scale_factor 1e-3). Distances come from the room's analytic ray caster at the pixel
centers, not from any Gaussian renderer. The room's own files are not touched.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from geer_ns.data.synthetic_cameras import fisheye_pixel_dirs, pinhole_pixel_dirs
from geer_ns.data.synthetic_room import render_room_rays

# variant: (source transforms, written transforms, folder, unit of the stored values per meter)
VARIANTS = {
    "fisheye": ("transforms.json", "transforms_fisheye_depth.json", "depths_fisheye", 1000.0),
    "pinhole": ("transforms_pinhole.json", "transforms_pinhole_depth.json", "depths_pinhole", 1000.0),
}


def frame_distances(c2w_nerfstudio: np.ndarray, dirs_cam: np.ndarray) -> np.ndarray:
    """[H, W] distance along each unit pixel ray (camera frame, OpenCV axes) to the room's nearest surface."""
    c2w = np.asarray(c2w_nerfstudio, dtype=np.float64)
    rot = c2w[:3, :3] * np.array([1.0, -1.0, -1.0])  # nerfstudio (OpenGL) -> OpenCV camera axes
    unit = dirs_cam / np.linalg.norm(dirs_cam, axis=-1, keepdims=True)
    d = unit.reshape(-1, 3) @ rot.T
    _, distance, hit = render_room_rays(np.broadcast_to(c2w[:3, 3], d.shape), d)
    return np.where(hit, distance, 0.0).reshape(dirs_cam.shape[:2])


def write_depth_variant(room: Path, variant: str = "fisheye") -> Path:
    """Write `variant`'s depth files and transforms file into `room` (a generated room); returns the latter."""
    source, written, folder, unit = VARIANTS[variant]
    meta = json.loads((room / source).read_text())
    size = int(meta["w"])
    if variant == "fisheye":
        dirs, inside = fisheye_pixel_dirs(size)
    else:
        dirs, inside = pinhole_pixel_dirs(size), np.ones((size, size), bool)
    (room / folder).mkdir(exist_ok=True)
    for frame in meta["frames"]:
        distance = np.where(inside, frame_distances(np.array(frame["transform_matrix"]), dirs), 0.0)
        name = Path(frame["file_path"]).stem
        if variant == "fisheye":
            path = f"{folder}/{name}.npy"
            np.save(room / path, (distance * unit).astype(np.float32))
        else:
            z = distance * dirs[..., 2] / np.linalg.norm(dirs, axis=-1)
            path = f"{folder}/{name}.png"
            cv2.imwrite(str(room / path), np.clip(np.rint(z * unit), 0, 65535).astype(np.uint16))
        frame["depth_file_path"] = path
    (room / written).write_text(json.dumps(meta, indent=2) + "\n")
    return room / written
