"""Procedural albedo of the synthetic room's surfaces (geer_ns.data.synthetic_room): the room box's walls,
floor and ceiling, and the textures of its spheres and boxes, mixing high-frequency (fine checkers/stripes) and
low-frequency (gradients) content so reconstruction quality is measurable. Each texture maps hit data to an
albedo [M, 3] in [0, 1]."""

from __future__ import annotations

from typing import Tuple

import numpy as np

# Room interior (an axis-aligned box, 5 x 4 x 2.4 m).
ROOM_MIN = np.array([-2.5, -2.0, 0.0])
ROOM_MAX = np.array([2.5, 2.0, 2.4])




def _mix(c0, c1, w: np.ndarray) -> np.ndarray:
    """Blend two RGB colors with weights w in [0, 1] (w=1 -> c1)."""
    c0 = np.asarray(c0, dtype=np.float64)
    c1 = np.asarray(c1, dtype=np.float64)
    return c0[None] * (1.0 - w[:, None]) + c1[None] * w[:, None]


def _checker(u: np.ndarray, v: np.ndarray, period: float) -> np.ndarray:
    """1.0 / 0.0 checkerboard with squares of side ``period``."""
    return ((np.floor(u / period) + np.floor(v / period)) % 2.0).astype(np.float64)


def _stripes(u: np.ndarray, period: float) -> np.ndarray:
    """Hard 1.0 / 0.0 stripes of width period/2."""
    return (np.floor(2.0 * u / period) % 2.0).astype(np.float64)


def _room_albedo(p: np.ndarray, axis: np.ndarray, side: np.ndarray) -> np.ndarray:
    """Albedo of the room's inner faces. axis: 0/1/2 face normal axis, side: -1 (min) / +1 (max)."""
    out = np.zeros((p.shape[0], 3))
    x, y, z = p[:, 0], p[:, 1], p[:, 2]

    # Floor: 0.5 m checker (mid frequency) with a faint 0.1 m stripe modulation (high frequency).
    m = (axis == 2) & (side < 0)
    if m.any():
        c = _mix((0.82, 0.74, 0.58), (0.30, 0.20, 0.12), _checker(x[m], y[m], 0.5))
        c *= (0.9 + 0.1 * _stripes(x[m] + y[m], 0.2))[:, None]
        out[m] = c
    # Ceiling: smooth radial gradient (low frequency).
    m = (axis == 2) & (side > 0)
    if m.any():
        r = np.sqrt(x[m] ** 2 + y[m] ** 2) / 3.2
        out[m] = _mix((0.95, 0.95, 0.85), (0.45, 0.55, 0.75), np.clip(r, 0, 1))
    # Wall x = max: vertical blue/white stripes, 0.25 m period (high frequency).
    m = (axis == 0) & (side > 0)
    if m.any():
        out[m] = _mix((0.92, 0.92, 0.95), (0.15, 0.30, 0.70), _stripes(y[m], 0.25))
    # Wall x = min: fine green/white checker, 0.15 m (highest frequency).
    m = (axis == 0) & (side < 0)
    if m.any():
        out[m] = _mix((0.90, 0.95, 0.88), (0.20, 0.55, 0.25), _checker(y[m], z[m], 0.15))
    # Wall y = max: smooth horizontal color gradient + one soft sine band (low frequency).
    m = (axis == 1) & (side > 0)
    if m.any():
        t = (x[m] - ROOM_MIN[0]) / (ROOM_MAX[0] - ROOM_MIN[0])
        c = _mix((0.85, 0.35, 0.30), (0.30, 0.40, 0.85), t)
        c *= (0.8 + 0.2 * np.sin(np.pi * z[m] / ROOM_MAX[2]))[:, None]
        out[m] = c
    # Wall y = min: diagonal orange/gray stripes, 0.4 m period.
    m = (axis == 1) & (side < 0)
    if m.any():
        out[m] = _mix((0.55, 0.55, 0.55), (0.95, 0.60, 0.15), _stripes(x[m] + z[m], 0.4))
    return out


def _sphere_latlong(p_local: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Longitude in [-pi, pi] and latitude in [-pi/2, pi/2] of a point relative to a sphere center."""
    r = np.linalg.norm(p_local, axis=-1)
    lon = np.arctan2(p_local[:, 1], p_local[:, 0])
    lat = np.arcsin(np.clip(p_local[:, 2] / np.maximum(r, 1e-12), -1.0, 1.0))
    return lon, lat


def _tex_sphere_checker(pl: np.ndarray, face: np.ndarray) -> np.ndarray:
    lon, lat = _sphere_latlong(pl)
    w = _checker(lon, lat, np.pi / 6.0)  # 12 x 6 lat-long checker
    return _mix((0.95, 0.85, 0.20), (0.80, 0.15, 0.15), w)


def _tex_sphere_smooth(pl: np.ndarray, face: np.ndarray) -> np.ndarray:
    n = pl / np.linalg.norm(pl, axis=-1, keepdims=True)
    return np.clip(0.5 + 0.4 * n[:, [0, 1, 2]] * np.array([1.0, -1.0, 0.8]), 0.0, 1.0)


def _tex_sphere_bands(pl: np.ndarray, face: np.ndarray) -> np.ndarray:
    return _mix((0.95, 0.95, 0.95), (0.35, 0.10, 0.55), _stripes(pl[:, 2], 0.12))


def _box_face_uv(pl: np.ndarray, face: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """The two in-face local coordinates of a box hit (face = normal axis 0/1/2)."""
    u = np.where(face == 0, pl[:, 1], pl[:, 0])
    v = np.where(face == 2, pl[:, 1], pl[:, 2])
    return u, v


def _tex_box_checker(pl: np.ndarray, face: np.ndarray) -> np.ndarray:
    u, v = _box_face_uv(pl, face)
    base = _mix((0.95, 0.95, 0.92), (0.10, 0.45, 0.45), _checker(u, v, 0.15))
    # Per-face tint so the faces are distinguishable even at the same light level.
    tint = np.array([[1.0, 0.9, 0.9], [0.9, 1.0, 0.9], [0.9, 0.9, 1.0]])[face]
    return base * tint


def _tex_box_diagonal(pl: np.ndarray, face: np.ndarray) -> np.ndarray:
    u, v = _box_face_uv(pl, face)
    return _mix((0.98, 0.55, 0.10), (0.40, 0.15, 0.50), _stripes(u + v, 0.2))
