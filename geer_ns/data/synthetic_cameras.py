"""The synthetic room's cameras: the 180-degree equidistant fisheye, the 90-degree pinhole, a 220-degree
Kannala-Brandt fisheye and a 360 x 180 panorama.

All share the same poses (geer_ns.data.synthetic_room). Rays are built here in numpy,
float64, from the models' textbook definitions (OpenCV camera frame: x right, y down, z forward), not
from geer_ns.cameras, so that the dataset stays an independent ground truth for them.

* KB fisheye (nerfstudio ``OPENCV_FISHEYE``, OpenCV's cv2.fisheye model continued past 90 degrees):
  r = f * theta_d, theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8), all k non-zero;
  the 220-degree circle (theta = 110 degrees) exactly fits the image.
* Equirectangular (nerfstudio ``EQUIRECTANGULAR``, width = 2 height): longitude 2 pi (u / W - 0.5) (0 along
  +z, +x to the right), latitude pi (0.5 - v / H) (up = -y).
"""

from __future__ import annotations

from typing import Dict, Tuple

import numpy as np

__all__ = ["KB220_COEFFS", "KB220_HALF_FOV", "equirect_intrinsics", "equirect_pixel_dirs", "fisheye_intrinsics",
           "fisheye_pixel_dirs", "kb220_intrinsics", "kb220_pixel_dirs", "kb_theta_d", "pinhole_intrinsics",
           "pinhole_pixel_dirs"]

#: Kannala-Brandt k1..k4 of the 220-degree lens: theta -> theta_d is increasing up to (well past) 110 degrees.
KB220_COEFFS = (-0.02, 0.003, -0.0005, 0.00003)
KB220_HALF_FOV = np.deg2rad(110.0)


def kb_theta_d(theta: np.ndarray, coeffs=KB220_COEFFS) -> np.ndarray:
    t2 = theta * theta
    k1, k2, k3, k4 = coeffs
    return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


def kb220_intrinsics(size: int) -> Dict[str, float]:
    """Focal length such that the 220-degree circle has radius size / 2 (square image)."""
    f = (size / 2.0) / float(kb_theta_d(np.array(KB220_HALF_FOV)))
    k1, k2, k3, k4 = KB220_COEFFS
    return {"fl_x": f, "fl_y": f, "cx": size / 2.0, "cy": size / 2.0, "w": size, "h": size,
            "k1": k1, "k2": k2, "k3": k3, "k4": k4}


def fisheye_intrinsics(size: int) -> Dict[str, float]:
    """Ideal equidistant fisheye whose 180 deg circle exactly fits a size x size image."""
    f = size / np.pi  # r = f * theta, r(90 deg) = size / 2
    return {"fl_x": f, "fl_y": f, "cx": size / 2.0, "cy": size / 2.0, "w": size, "h": size}


def pinhole_intrinsics(size: int) -> Dict[str, float]:
    """Pinhole with a 90 deg horizontal/vertical FoV."""
    f = (size / 2.0) / np.tan(np.deg2rad(45.0))
    return {"fl_x": f, "fl_y": f, "cx": size / 2.0, "cy": size / 2.0, "w": size, "h": size}


def _pixel_grid(width: int, height: int) -> Tuple[np.ndarray, np.ndarray]:
    """Pixel-center coordinates (u = j + 0.5, v = i + 0.5), each [height, width]."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64) + 0.5, np.arange(height, dtype=np.float64) + 0.5,
                       indexing="xy")
    return u, v


def fisheye_pixel_dirs(size: int) -> Tuple[np.ndarray, np.ndarray]:
    """Unit OpenCV-camera directions [size, size, 3] of the equidistant fisheye pixel centers,
    and the validity mask (theta <= 90 deg, i.e. inside the 180 deg circle)."""
    k = fisheye_intrinsics(size)
    u, v = _pixel_grid(size, size)
    a = (u - k["cx"]) / k["fl_x"]
    b = (v - k["cy"]) / k["fl_y"]
    theta = np.sqrt(a * a + b * b)
    # sin(theta)/theta -> 1 at the center; theta never exactly 0 for pixel centers, but be safe.
    s = np.where(theta > 1e-12, np.sin(theta) / np.maximum(theta, 1e-12), 1.0)
    dirs = np.stack([a * s, b * s, np.cos(theta)], axis=-1)
    return dirs, theta <= np.pi / 2.0


def pinhole_pixel_dirs(size: int) -> np.ndarray:
    """Unit OpenCV-camera directions [size, size, 3] of the pinhole pixel centers."""
    k = pinhole_intrinsics(size)
    u, v = _pixel_grid(size, size)
    d = np.stack([(u - k["cx"]) / k["fl_x"], (v - k["cy"]) / k["fl_y"], np.ones_like(u)], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def kb220_pixel_dirs(size: int) -> Tuple[np.ndarray, np.ndarray]:
    """Unit directions [size, size, 3] of the pixel centers and the mask of the 220-degree circle."""
    k = kb220_intrinsics(size)
    u, v = _pixel_grid(size, size)
    a, b = (u - k["cx"]) / k["fl_x"], (v - k["cy"]) / k["fl_y"]
    theta_d = np.sqrt(a * a + b * b)
    # Invert theta_d(theta) by bisection: monotone on [0, 110 deg], 60 halvings reach float64 resolution.
    lo, hi = np.zeros_like(theta_d), np.full_like(theta_d, KB220_HALF_FOV)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        below = kb_theta_d(mid) < theta_d
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    theta = 0.5 * (lo + hi)
    inside = theta_d <= float(kb_theta_d(np.array(KB220_HALF_FOV)))
    s = np.where(theta_d > 1e-12, np.sin(theta) / np.maximum(theta_d, 1e-12), 1.0)
    return np.stack([a * s, b * s, np.cos(theta)], axis=-1), inside


def equirect_intrinsics(size: int) -> Dict[str, float]:
    """nerfstudio's standard equirectangular intrinsics for a 2 size x size panorama."""
    w, h = 2 * size, size
    return {"fl_x": w / 2.0, "fl_y": float(h), "cx": w / 2.0, "cy": h / 2.0, "w": w, "h": h}


def equirect_pixel_dirs(size: int) -> np.ndarray:
    """Unit directions [size, 2 size, 3] of the panorama's pixel centers (every pixel is valid)."""
    w, h = 2 * size, size
    u, v = _pixel_grid(w, h)
    lon = 2.0 * np.pi * (u / w - 0.5)
    lat = np.pi * (0.5 - v / h)
    return np.stack([np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)], axis=-1)
