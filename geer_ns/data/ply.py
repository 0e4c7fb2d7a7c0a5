"""Seed point clouds as PLY files, read and written with plyfile.

nerfstudio-data reads `ply_file_path` with open3d, whose import fails on machines without Debian's
libusb-1.0-0; plyfile reads the same files with no system library.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(xyz float32 [N,3], rgb uint8 [N,3]) from a PLY point cloud (white where it has no color)."""
    from plyfile import PlyData

    vertex = PlyData.read(str(path))["vertex"]
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=-1).astype(np.float32)
    names = vertex.data.dtype.names
    if all(c in names for c in ("red", "green", "blue")):
        rgb = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=-1)
        rgb = rgb if rgb.dtype == np.uint8 else np.clip(np.round(rgb * 255.0), 0, 255)
    else:
        rgb = np.full_like(xyz, 255.0)
    return xyz, rgb.astype(np.uint8)


def write_ply_points(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """A binary little-endian PLY point cloud: x y z float from `xyz` [N,3], red green blue uchar from `rgb`
    [N,3] uint8 (what ns-process-data writes and `read_ply_points` reads)."""
    from plyfile import PlyData, PlyElement

    vertex = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, axis in enumerate("xyz"):
        vertex[axis] = xyz[:, i]
    for i, channel in enumerate(("red", "green", "blue")):
        vertex[channel] = rgb[:, i]
    PlyData([PlyElement.describe(vertex, "vertex")], byte_order="<").write(str(path))
