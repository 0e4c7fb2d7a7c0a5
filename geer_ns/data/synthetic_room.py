"""Procedural synthetic room rendered by analytic ray casting (numpy only).

The scene is the ground truth for tests and the demo training run. It is independent of any
Gaussian renderer: a ray's color is the shaded albedo at its nearest analytic hit, and a pixel is
the mean of SUPERSAMPLE^2 rays spread uniformly over its square (a sensor's box filter), so any
renderer/camera model can be checked against :func:`render_room_rays` for arbitrary rays.

World frame: meters, +z up. The room is an axis-aligned box seen from the inside; inside it sit
spheres and boxes (axis-aligned and rotated) with procedural textures mixing high-frequency
(fine checkers/stripes) and low-frequency (gradients) content so reconstruction quality is
measurable. Shading is Lambertian, one directional light + ambient, no shadows, deterministic.

Dataset layout written by :func:`generate_room` (nerfstudio "nerfstudio-data" format)::

    OUT_DIR/
      transforms.json            # OPENCV_FISHEYE (k1..k4 = 0): ideal equidistant 180 deg fisheye
      transforms_pinhole.json    # OPENCV (zero distortion), 90 deg FoV, same poses and splits
      transforms_fisheye220.json # OPENCV_FISHEYE, Kannala-Brandt k1..k4 != 0, 220 deg circle (synthetic_cameras)
      transforms_equirect.json   # EQUIRECTANGULAR 2S x S panorama
      transforms_rig.json        # mixed rig: per-frame camera_model, the 220 deg fisheye + the pinhole
      images_fisheye/ images_pinhole/ images_fisheye220/ images_equirect/   frame_XXXXX.png
      masks/fisheye_mask.png     # 255 where the pixel center is inside the 180 deg circle
      masks/fisheye220_mask.png  # the same for the 220 deg circle; masks/pinhole_mask.png: all 255 (rig)
      points3d.ply               # seed point cloud (binary PLY, xyz float + rgb uchar)
      .geer_ns_synthetic_room.json  # marker: proves this directory was made by this generator

CLI: ``python -m geer_ns.data.synthetic_room OUT_DIR [--n-views N --size S --seed K --overwrite]``
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Callable, Dict, List, Tuple

import cv2
import numpy as np

from geer_ns.data.ply import write_ply_points
from geer_ns.data.synthetic_materials import (  # noqa: F401 (ROOM_MIN/ROOM_MAX: part of this module's API)
    ROOM_MAX,
    ROOM_MIN,
    _room_albedo,
    _tex_box_checker,
    _tex_box_diagonal,
    _tex_sphere_bands,
    _tex_sphere_checker,
    _tex_sphere_smooth,
)
from geer_ns.data.synthetic_cameras import (
    equirect_intrinsics,
    equirect_pixel_dirs,
    fisheye_intrinsics,
    fisheye_pixel_dirs,
    kb220_intrinsics,
    kb220_pixel_dirs,
    pinhole_intrinsics,
    pinhole_pixel_dirs,
)

__all__ = [
    "SCENE_VERSION",
    "ROOM_MIN",
    "ROOM_MAX",
    "generate_room",
    "default_scene_dir",
    "render_room_rays",
    "is_inside_free_space",
    "camera_poses",
    "fisheye_intrinsics",
    "pinhole_intrinsics",
    "fisheye_pixel_dirs",
    "pinhole_pixel_dirs",
    "opencv_to_nerfstudio_c2w",
]

SCENE_VERSION = 3  # 2: + the 220-degree KB fisheye, the panorama and the mixed rig; 3: box-filtered pixels
MARKER_NAME = ".geer_ns_synthetic_room.json"

# Light: direction the light travels (downwards, slanted so every room face gets a distinct level).
_LIGHT_DIR = np.array([0.35, -0.25, -0.9])
_LIGHT_DIR = _LIGHT_DIR / np.linalg.norm(_LIGHT_DIR)
_AMBIENT = 0.4
_DIFFUSE = 0.6


# --------------------------------------------------------------------------------------------
# Scene description (fixed: the seed only changes camera poses and point-cloud sampling).
# --------------------------------------------------------------------------------------------


def _rot_zx(yaw_deg: float, tilt_deg: float) -> np.ndarray:
    """Rotation R_world_from_local = Rz(yaw) @ Rx(tilt)."""
    a, b = np.deg2rad(yaw_deg), np.deg2rad(tilt_deg)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return rz @ rx


# (center, radius, texture)
_SPHERES: List[Tuple[np.ndarray, float, Callable]] = [
    (np.array([0.0, 0.0, 0.5]), 0.5, _tex_sphere_checker),  # centerpiece the orbit looks at
    (np.array([1.9, 1.4, 0.35]), 0.35, _tex_sphere_smooth),  # corner ball, low frequency
    (np.array([-1.8, -1.3, 1.6]), 0.3, _tex_sphere_bands),  # floating ball, high frequency
]
# (center, half extents, R_world_from_local, texture)
_BOXES: List[Tuple[np.ndarray, np.ndarray, np.ndarray, Callable]] = [
    (np.array([-1.85, 1.35, 0.45]), np.array([0.4, 0.3, 0.45]), np.eye(3), _tex_box_checker),
    (np.array([1.75, -1.25, 0.6]), np.array([0.3, 0.45, 0.5]), _rot_zx(35.0, 12.0), _tex_box_diagonal),
]


# --------------------------------------------------------------------------------------------
# Ray casting
# --------------------------------------------------------------------------------------------


def _safe_dirs(d: np.ndarray) -> np.ndarray:
    """Replace exact zeros by a tiny signed value so slab tests never divide 0 by 0."""
    return np.where(np.abs(d) < 1e-30, 1e-30, d)


def _slab(o: np.ndarray, d: np.ndarray, half: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Entry/exit distances of rays (box-local frame) through the box [-half, half]."""
    inv = 1.0 / _safe_dirs(d)
    t1 = (-half[None] - o) * inv
    t2 = (half[None] - o) * inv
    return np.max(np.minimum(t1, t2), axis=1), np.min(np.maximum(t1, t2), axis=1)


def _face_axis(pl: np.ndarray, half: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Face (normal axis, side) of points lying on a box surface, in the box-local frame."""
    rel = np.abs(pl) / half[None]
    axis = np.argmax(rel, axis=1)
    side = np.sign(pl[np.arange(pl.shape[0]), axis])
    side[side == 0] = 1.0
    return axis, side


def render_room_rays(origins: np.ndarray, dirs: np.ndarray, eps: float = 1e-9):
    """Ray-cast the ground-truth scene for arbitrary rays.

    Args:
        origins: [N, 3] ray origins (world frame, meters). Any float array / tensor-like.
        dirs: [N, 3] ray directions; need not be normalized.
    Returns:
        rgb [N, 3] float64 in [0, 1] (0 where nothing is hit),
        depth [N] distance from the origin to the hit along the *normalized* direction
        (inf where nothing is hit), hit [N] bool. Rays starting inside the room always hit.
    """
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    n_rays = o.shape[0]

    best_t = np.full(n_rays, np.inf)
    best_id = np.full(n_rays, -1, dtype=np.int64)  # 0 = room, 1.. = objects

    # Room: seen from the inside, so the visible surface is the slab exit.
    center = 0.5 * (ROOM_MIN + ROOM_MAX)
    half_room = 0.5 * (ROOM_MAX - ROOM_MIN)
    t_in, t_out = _slab(o - center, d, half_room)
    ok = (t_out > np.maximum(t_in, eps))
    best_t[ok] = t_out[ok]
    best_id[ok] = 0

    objects: List[Tuple[str, tuple]] = [("sphere", s) for s in _SPHERES] + [("box", b) for b in _BOXES]
    for k, (kind, prm) in enumerate(objects, start=1):
        if kind == "sphere":
            c, r, _ = prm
            oc = o - c[None]
            b = np.einsum("ij,ij->i", oc, d)
            disc = b * b - (np.einsum("ij,ij->i", oc, oc) - r * r)
            sq = np.sqrt(np.maximum(disc, 0.0))
            t0, t1 = -b - sq, -b + sq
            t = np.where(t0 > eps, t0, t1)  # nearest positive root
            ok = (disc >= 0) & (t > eps)
        else:
            c, half, rot, _ = prm
            ol = (o - c[None]) @ rot  # == R^T (o - c) row-wise
            dl = d @ rot
            t_in, t_out = _slab(ol, dl, half)
            t = np.where(t_in > eps, t_in, t_out)
            ok = (t_out >= np.maximum(t_in, eps))
        closer = ok & (t < best_t)
        best_t[closer] = t[closer]
        best_id[closer] = k

    hit = best_id >= 0
    rgb = np.zeros((n_rays, 3))
    normal = np.zeros((n_rays, 3))
    p = o + d * np.where(hit, best_t, 0.0)[:, None]

    sel = best_id == 0
    if sel.any():
        pl = p[sel] - center[None]
        axis, side = _face_axis(pl, half_room)
        rgb[sel] = _room_albedo(p[sel], axis, side)
        nrm = np.zeros((axis.shape[0], 3))
        nrm[np.arange(axis.shape[0]), axis] = -side  # room normals point inwards
        normal[sel] = nrm
    for k, (kind, prm) in enumerate(objects, start=1):
        sel = best_id == k
        if not sel.any():
            continue
        if kind == "sphere":
            c, r, tex = prm
            pl = p[sel] - c[None]
            normal[sel] = pl / np.linalg.norm(pl, axis=1, keepdims=True)
            rgb[sel] = tex(pl, np.zeros(pl.shape[0], dtype=np.int64))
        else:
            c, half, rot, tex = prm
            pl = (p[sel] - c[None]) @ rot
            axis, side = _face_axis(pl, half)
            nl = np.zeros_like(pl)
            nl[np.arange(pl.shape[0]), axis] = side
            normal[sel] = nl @ rot.T
            rgb[sel] = tex(pl, axis)

    # Two-sided Lambert: flip normals towards the viewer so shading never depends on winding.
    flip = np.einsum("ij,ij->i", normal, d) > 0
    normal[flip] *= -1.0
    lambert = np.maximum(normal @ (-_LIGHT_DIR), 0.0)
    rgb = np.clip(rgb * (_AMBIENT + _DIFFUSE * lambert)[:, None], 0.0, 1.0)
    rgb[~hit] = 0.0
    depth = np.where(hit, best_t, np.inf)
    return rgb, depth, hit


def is_inside_free_space(points: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """True for points inside the room and at least ``margin`` away from every object."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ok = np.all((pts > ROOM_MIN + margin) & (pts < ROOM_MAX - margin), axis=1)
    for c, r, _ in _SPHERES:
        ok &= np.linalg.norm(pts - c[None], axis=1) > r + margin
    for c, half, rot, _ in _BOXES:
        pl = (pts - c[None]) @ rot
        # Distance from a point to an oriented box (0 inside).
        q = np.maximum(np.abs(pl) - half[None], 0.0)
        ok &= np.linalg.norm(q, axis=1) > margin
        ok &= ~np.all(np.abs(pl) <= half[None], axis=1)
    return ok


# --------------------------------------------------------------------------------------------
# Cameras. Rays are built in the OpenCV camera frame (x right, y down, z forward); the json
# stores nerfstudio/OpenGL camera-to-world matrices (x right, y up, z back).
# --------------------------------------------------------------------------------------------


def _look_rotation(forward: np.ndarray, roll: float) -> np.ndarray:
    """R_world_from_cv with columns (right, down, forward) for a +z-up world, then rolled."""
    fwd = forward / np.linalg.norm(forward)
    right = np.cross(fwd, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    cr, sr = np.cos(roll), np.sin(roll)
    # Roll about the optical axis keeps the frame right-handed (right x down = forward).
    right, down = cr * right + sr * down, -sr * right + cr * down
    return np.stack([right, down, fwd], axis=1)


def camera_poses(n_views: int, seed: int = 0) -> List[np.ndarray]:
    """OpenCV-convention camera-to-world 4x4 poses: a jittered elliptical loop around the room
    center with height, yaw (inward / outward / tangential) and pitch variation."""
    rng = np.random.default_rng(seed)
    poses = []
    for k in range(n_views):
        phi = 2.0 * np.pi * k / n_views
        for _ in range(100):  # re-draw jitter until the camera is safely in free space
            pos = np.array(
                [
                    1.45 * np.cos(phi) + rng.uniform(-0.1, 0.1),
                    1.05 * np.sin(phi) + rng.uniform(-0.1, 0.1),
                    1.25 + 0.3 * np.sin(2.0 * phi) + rng.uniform(-0.1, 0.1),
                ]
            )
            if is_inside_free_space(pos[None], margin=0.2)[0]:
                break
        else:  # pragma: no cover - the loop is designed to stay clear of all objects
            raise RuntimeError("could not place a camera in free space")
        # Cycle looking inward, tangential, outward, tangential so walls and objects all get seen.
        yaw = phi + np.pi + (k % 4) * (np.pi / 2.0) + rng.uniform(-0.3, 0.3)
        pitch = np.deg2rad(25.0) * np.sin(3.0 * phi) + rng.uniform(-0.15, 0.15)
        fwd = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
        c2w = np.eye(4)
        c2w[:3, :3] = _look_rotation(fwd, roll=rng.uniform(-0.15, 0.15))
        c2w[:3, 3] = pos
        poses.append(c2w)
    return poses


def opencv_to_nerfstudio_c2w(c2w_cv: np.ndarray) -> np.ndarray:
    """OpenCV (x right, y down, z fwd) -> nerfstudio/OpenGL (x right, y up, z back) camera axes."""
    out = np.array(c2w_cv, dtype=np.float64, copy=True)
    out[:3, 1:3] *= -1.0
    return out


# --------------------------------------------------------------------------------------------
# Dataset writing
# --------------------------------------------------------------------------------------------


# Sub-pixel rays per pixel side: a sensor integrates light over each pixel's footprint (a box filter), so
# each pixel is the mean of SUPERSAMPLE^2 rays on a uniform sub-pixel grid, not one ray through its center
# (which would alias the fine checkers into patterns no 3D scene reproduces from another viewpoint).
SUPERSAMPLE = 4


def _render_view(c2w_cv: np.ndarray, dirs_cam: np.ndarray, supersample: int = 1) -> np.ndarray:
    """Image of rays ``dirs_cam`` [h*s, w*s, 3] (sub-pixel grid of an h x w camera whose intrinsics scale
    with the image size), box-averaged to [h, w, 3]."""
    hs, ws, _ = dirs_cam.shape
    d = dirs_cam.reshape(-1, 3) @ c2w_cv[:3, :3].T
    o = np.broadcast_to(c2w_cv[:3, 3], d.shape)
    rgb, _, _ = render_room_rays(o, d)
    s = supersample
    return rgb.reshape(hs // s, s, ws // s, s, 3).mean(axis=(1, 3))


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)


def _write_png(path: Path, img_u8: np.ndarray) -> None:
    if img_u8.ndim == 3:
        img_u8 = cv2.cvtColor(img_u8, cv2.COLOR_RGB2BGR)
    # Fixed compression level: identical bytes for identical pixels.
    if not cv2.imwrite(str(path), img_u8, [cv2.IMWRITE_PNG_COMPRESSION, 6]):
        raise OSError(f"failed to write {path}")


def _seed_points(poses_cv: List[np.ndarray], n_points: int, rng: np.random.Generator):
    """Surface points visible from the cameras (like an SfM cloud): cast random rays from
    random camera centers and keep the hits with their exact shaded colors."""
    centers = np.stack([p[:3, 3] for p in poses_cv])
    o = centers[rng.integers(0, len(poses_cv), size=n_points)]
    d = rng.normal(size=(n_points, 3))
    rgb, depth, hit = render_room_rays(o, d)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    xyz = o[hit] + d[hit] * depth[hit, None]
    return xyz, _to_u8(rgb[hit])


def _splits(n_views: int, names: List[str]) -> Dict[str, List[str]]:
    """Every 8th frame (index % 8 == 0) is held out as val/test; the rest is train."""
    held = [names[i] for i in range(n_views) if i % 8 == 0]
    train = [names[i] for i in range(n_views) if i % 8 != 0]
    return {"train_filenames": train, "val_filenames": held, "test_filenames": held}


def _variant_meta(camera_model: str, intrinsics: Dict[str, float], frames: List[dict], names: List[str],
                  n_views: int, **extra) -> dict:
    return {
        "camera_model": camera_model,
        **intrinsics,
        **extra,
        # Poses are already in the final world frame; tell nerfstudio not to re-orient them.
        "orientation_override": "none",
        "ply_file_path": "points3d.ply",
        **_splits(n_views, names),
        "frames": frames,
    }


def _write_dataset(root: Path, n_views: int, size: int, seed: int) -> None:
    rng = np.random.default_rng(seed + 1_000_003)  # separate stream from the pose jitter
    poses_cv = camera_poses(n_views, seed)
    _, fe_mask = fisheye_pixel_dirs(size)
    _, kb_mask = kb220_pixel_dirs(size)
    # Every camera's intrinsics scale with the image size, so the pixel-center rays of the image SUPERSAMPLE
    # times larger are the uniform sub-pixel rays of this one. The circle masks stay per pixel center.
    s = SUPERSAMPLE
    # (image folder, sub-pixel ray directions, circle mask or None): the 180-degree fisheye, the pinhole, the
    # 220-degree KB fisheye and the panorama, all from the same poses.
    cameras = {
        "fisheye": ("images_fisheye", fisheye_pixel_dirs(size * s)[0], fe_mask),
        "pinhole": ("images_pinhole", pinhole_pixel_dirs(size * s), None),
        "fisheye220": ("images_fisheye220", kb220_pixel_dirs(size * s)[0], kb_mask),
        "equirect": ("images_equirect", equirect_pixel_dirs(size * s), None),
    }
    masks = {"fisheye": "masks/fisheye_mask.png", "fisheye220": "masks/fisheye220_mask.png",
             "pinhole": "masks/pinhole_mask.png"}
    (root / "masks").mkdir()
    _write_png(root / masks["fisheye"], (fe_mask * 255).astype(np.uint8))
    _write_png(root / masks["fisheye220"], (kb_mask * 255).astype(np.uint8))
    _write_png(root / masks["pinhole"], np.full((size, size), 255, np.uint8))

    frames: Dict[str, List[dict]] = {name: [] for name in cameras}
    for name, (folder, dirs, mask) in cameras.items():
        (root / folder).mkdir()
        for i, c2w in enumerate(poses_cv):
            img = _render_view(c2w, dirs, s)
            if mask is not None:
                img[~mask] = 0.0  # outside the image circle: no light, as on a real fisheye sensor
            path = f"{folder}/frame_{i:05d}.png"
            _write_png(root / path, _to_u8(img))
            frame = {"file_path": path, "transform_matrix": np.round(opencv_to_nerfstudio_c2w(c2w), 12).tolist()}
            if mask is not None:
                frame["mask_path"] = masks[name]
            frames[name].append(frame)

    xyz, rgb = _seed_points(poses_cv, 4000, rng)
    write_ply_points(root / "points3d.ply", xyz, rgb)

    def names(name: str) -> List[str]:
        return [f["file_path"] for f in frames[name]]

    zero_dist = {"k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0}
    kb = kb220_intrinsics(size)
    metas = {
        # Only used by nerfstudio's pixel sampler when no mask is given; the mask is authoritative.
        "transforms.json": _variant_meta("OPENCV_FISHEYE", {**fisheye_intrinsics(size), **zero_dist},
                                         frames["fisheye"], names("fisheye"), n_views,
                                         fisheye_crop_radius=size / 2.0),
        "transforms_pinhole.json": _variant_meta("OPENCV", {**pinhole_intrinsics(size), **zero_dist, "p1": 0.0,
                                                            "p2": 0.0}, frames["pinhole"], names("pinhole"), n_views),
        "transforms_fisheye220.json": _variant_meta("OPENCV_FISHEYE", kb, frames["fisheye220"], names("fisheye220"),
                                                    n_views, fisheye_crop_radius=size / 2.0),
        "transforms_equirect.json": _variant_meta("EQUIRECTANGULAR", equirect_intrinsics(size), frames["equirect"],
                                                  names("equirect"), n_views),
    }
    # A mixed rig in one file: per-frame camera_model and intrinsics (geer's nerfstudio dataparser), the
    # 220-degree fisheye and the pinhole at every pose.
    rig_frames = [{**f, "camera_model": "OPENCV_FISHEYE", **kb} for f in frames["fisheye220"]]
    rig_frames += [{**f, "camera_model": "OPENCV", **pinhole_intrinsics(size), "mask_path": masks["pinhole"]}
                   for f in frames["pinhole"]]
    rig_splits = [_splits(n_views, names(n)) for n in ("fisheye220", "pinhole")]
    metas["transforms_rig.json"] = {
        "orientation_override": "none",
        "ply_file_path": "points3d.ply",
        **{key: rig_splits[0][key] + rig_splits[1][key] for key in rig_splits[0]},
        "frames": rig_frames,
    }
    for name, meta in metas.items():
        (root / name).write_text(json.dumps(meta, indent=2) + "\n")
    marker = {"generator": "geer_ns.data.synthetic_room", "version": SCENE_VERSION,
              "n_views": n_views, "image_size": size, "seed": seed}
    (root / MARKER_NAME).write_text(json.dumps(marker, indent=2) + "\n")


def _read_marker(path: Path):
    try:
        return json.loads((path / MARKER_NAME).read_text())
    except (OSError, ValueError):
        return None


def generate_room(out_dir: Path, n_views: int = 24, image_size: int = 96, seed: int = 0,
                  overwrite: bool = False) -> Path:
    """Write the synthetic-room dataset to ``out_dir`` and return its path.

    Deterministic for given arguments. The dataset is built in a sibling temp directory and
    renamed into place, so an interrupted run never leaves a half-written dataset. An existing
    ``out_dir`` is replaced only if it is empty, was made by this generator (marker file), or
    ``overwrite=True``; otherwise FileExistsError is raised and nothing is touched.
    """
    out_dir = Path(out_dir).expanduser().absolute()
    if n_views < 1 or image_size < 2:
        raise ValueError("need n_views >= 1 and image_size >= 2")
    if out_dir.exists() or out_dir.is_symlink():
        if not out_dir.is_dir() or out_dir.is_symlink():
            raise FileExistsError(f"{out_dir} exists and is not a plain directory")
        non_empty = any(out_dir.iterdir())
        if non_empty and _read_marker(out_dir) is None and not overwrite:
            raise FileExistsError(
                f"{out_dir} is a non-empty directory not made by generate_room; pass overwrite=True to replace it")
        # Guard against catastrophic mistakes even with overwrite=True.
        if out_dir in (Path(out_dir.anchor), Path.home().absolute()):
            raise FileExistsError(f"refusing to replace {out_dir}")
    out_dir.parent.mkdir(parents=True, exist_ok=True)

    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        _write_dataset(tmp, n_views, image_size, seed)
        os.chmod(tmp, 0o755)  # mkdtemp makes 0700; a dataset should have normal permissions
        if out_dir.exists():
            # Swap via rename so out_dir is never half-written; drop the old copy last.
            old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-", dir=out_dir.parent))
            os.rmdir(old)
            os.rename(out_dir, old)
            os.rename(tmp, out_dir)
            shutil.rmtree(old)
        else:
            try:
                os.rename(tmp, out_dir)
            except OSError:
                # A concurrent generator won the race; keep its (identical, deterministic) result.
                if _read_marker(out_dir) is None:
                    raise
                shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def default_scene_dir() -> Path:
    """Cached default dataset (``$GEER_NS_CACHE`` or ``~/.cache/geer_ns``)/synthetic_room_v<SCENE_VERSION>,
    generated on first use (or if a previous cached copy is from another version)."""
    root = Path(os.environ.get("GEER_NS_CACHE", "~/.cache/geer_ns")).expanduser()
    path = root / f"synthetic_room_v{SCENE_VERSION}"
    marker = _read_marker(path)
    expected = {"version": SCENE_VERSION, "n_views": 24, "image_size": 96, "seed": 0}
    if marker is None or any(marker.get(k) != v for k, v in expected.items()):
        generate_room(path)
    return path


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description="Generate the geer-ns synthetic room dataset.")
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--n-views", type=int, default=24)
    ap.add_argument("--size", type=int, default=96, help="image width = height in pixels")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--overwrite", action="store_true", help="replace a non-empty foreign directory")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    path = generate_room(args.out_dir, args.n_views, args.size, args.seed, args.overwrite)
    print(f"wrote {path} in {time.perf_counter() - t0:.2f}s")


if __name__ == "__main__":
    main()
