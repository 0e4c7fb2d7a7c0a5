"""The training cameras as refined (lens refinement, pose refinement) written beside a run's checkpoints.

    <run>/cameras_refined.json   nerfstudio transforms.json style: per frame its refined camera-to-world (in the
                                 data's own frame, nerfstudio's dataparser transform undone), a rolling-shutter
                                 frame's readout and refined end-of-readout pose (`rolling_shutter`,
                                 `transform_matrix_end`), and its camera's refined intrinsics; top level the first
                                 camera's intrinsics, so that `geer-process-data --calibration cameras_refined.json`
                                 reads it
    <run>/colmap/cameras.txt     COLMAP text model of the same: cameras.txt (one camera per refined camera that
         images.txt              COLMAP has a model for), images.txt (world-to-camera of every training image;
                                 a rolling-shutter image's start pose: COLMAP has no readout),
         points3D.txt            an empty points3D.txt; pycolmap.Reconstruction reads the folder

docs/refinement.md says when they are written.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch

from geer_ns.cameras import (
    CameraModel,
    EquirectangularCamera,
    FOVCamera,
    Fisheye624Camera,
    OpenCVFisheyeCamera,
    PinholeCamera,
    RadialFisheyeCamera,
    ThinPrismFisheyeCamera,
)
from geer_ns.cameras.convert import _COLMAP_MODELS
from geer_ns.cameras.shutter import READOUTS
from geer_ns.data.rolling_shutter import GLOBAL, MOTION_KEY, READOUT_KEY, end_pose
from geer_ns.refinement.refined_frame import adjusted_poses

FILE_NAME = "cameras_refined.json"
COLMAP_DIR = "colmap"


def colmap_camera(camera: CameraModel) -> Optional[Tuple[str, List[float]]]:
    """(COLMAP model name, params in COLMAP's order) of a camera; None where COLMAP has no such model (Mei)."""
    if isinstance(camera, PinholeCamera):
        full = any(getattr(camera, k) != 0 for k in ("k3", "k4", "k5", "k6"))
        name = "FULL_OPENCV" if full else "OPENCV"
    elif isinstance(camera, EquirectangularCamera):
        return None
    else:
        names = {OpenCVFisheyeCamera: "OPENCV_FISHEYE", RadialFisheyeCamera: "RADIAL_FISHEYE",
                 ThinPrismFisheyeCamera: "THIN_PRISM_FISHEYE", Fisheye624Camera: "RAD_TAN_THIN_PRISM_FISHEYE",
                 FOVCamera: "FOV"}
        name = names.get(type(camera))
        if name is None:
            return None
    return name, [float(getattr(camera, n)) for n in _COLMAP_MODELS[name][0]]


def nerfstudio_intrinsics(camera: CameraModel) -> Dict[str, object]:
    """transforms.json per-frame camera fields of a camera (camera_model, fl_x, ..., distortion); a model
    nerfstudio cannot describe gets colmap_model / colmap_params instead."""
    out: Dict[str, object] = {"w": camera.width, "h": camera.height}
    if isinstance(camera, EquirectangularCamera):
        return {**out, "camera_model": "EQUIRECTANGULAR", "fl_x": camera.width / 2, "fl_y": float(camera.height),
                "cx": camera.width / 2, "cy": camera.height / 2}
    base = {"fl_x": camera.fx, "fl_y": camera.fy, "cx": camera.cx, "cy": camera.cy}
    if isinstance(camera, PinholeCamera) and camera.k4 == camera.k5 == camera.k6 == 0:
        dist = {k: getattr(camera, k) for k in ("k1", "k2", "k3", "p1", "p2")}
        return {**out, "camera_model": "OPENCV", **base, **dist}
    if isinstance(camera, (OpenCVFisheyeCamera, RadialFisheyeCamera)):
        dist = {k: float(getattr(camera, k, 0.0)) for k in ("k1", "k2", "k3", "k4")}
        return {**out, "camera_model": "OPENCV_FISHEYE", **base, **dist}
    if isinstance(camera, Fisheye624Camera):
        names = ("k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3")
        return {**out, "camera_model": "FISHEYE624", **base,
                "distortion_params": [getattr(camera, n) for n in names]}
    colmap = colmap_camera(camera)
    extra = {"colmap_model": colmap[0], "colmap_params": colmap[1]} if colmap else {"geer_model": repr(camera)}
    return {**out, **base, **extra}


def _in_given_frame(model, c2w: torch.Tensor) -> torch.Tensor:
    """Run-frame camera-to-worlds [N, 3, 4] with the similarity the scene drifted by taken out
    (geer_ns/refinement/refined_frame.py), so that they sit beside the poses the run was given (its test views')."""
    frame = model.refined_frame
    return c2w if frame is None else frame.similarity(model.camera_optimizer).inverse().apply(c2w)


def _run_frame_poses(pipeline) -> torch.Tensor:
    """[N, 3, 4] float64 the training images' camera-to-worlds with the camera optimizer's corrections, in the
    run's frame."""
    given = pipeline.datamanager.train_dataset.cameras.camera_to_worlds
    return adjusted_poses(pipeline.model.camera_optimizer, given)


def refined_poses(pipeline) -> torch.Tensor:
    """[N, 3, 4] float64 the training images' refined camera-to-worlds in the run's given frame: the camera
    optimizer's corrections applied, the scene's drift taken out (_in_given_frame). A rolling-shutter image's is
    its start-of-readout pose (refined_readouts: its end)."""
    return _in_given_frame(pipeline.model, _run_frame_poses(pipeline))


def refined_readouts(pipeline, starts: torch.Tensor) -> Tuple[List[Optional[str]], torch.Tensor]:
    """(each training image's readout, None for a global shutter; [N, 3, 4] float64 its refined camera-to-world at
    the end of the readout in the frame of refined_poses, the start's for a global shutter), from the run-frame
    refined starts [N, 3, 4] (_run_frame_poses). The end follows the refined start by the data's motion during the
    readout, with the readout refinement's adjustment where the run has one (geer_ns/refinement/readout.py)."""
    model = pipeline.model
    cameras = pipeline.datamanager.train_dataset.cameras
    ends = starts.clone()
    names: List[Optional[str]] = [None] * len(starts)
    metadata = cameras.metadata or {}
    refinement = getattr(model, "readout", None)
    if READOUT_KEY in metadata:
        for i, index in enumerate(metadata[READOUT_KEY].reshape(-1).tolist()):
            if index == GLOBAL:
                continue
            motion = metadata[MOTION_KEY][i].detach().cpu().double()
            if refinement is not None:
                with torch.no_grad():
                    motion = refinement.adjusted(motion, i).detach().cpu()
            names[i], ends[i] = READOUTS[index], end_pose(starts[i], motion)
    return names, _in_given_frame(model, ends)


def to_data_frame(c2w: torch.Tensor, transform: torch.Tensor, scale: float,
                  applied: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Run-frame camera-to-worlds [N, 3, 4] -> [N, 4, 4] in the data's frame: nerfstudio maps the file's x to
    s (T x) (dataparser_transform T, which holds applied_transform A when the file has one: the file's poses
    are A-frame poses already, so A is applied back)."""
    t = transform.double()
    rot = t[:3, :3].T @ c2w[:, :3, :3]
    pos = t[:3, :3].T @ (c2w[:, :3, 3:] / scale - t[:3, 3:])
    out = torch.eye(4, dtype=torch.float64).repeat(c2w.shape[0], 1, 1)
    out[:, :3] = torch.cat([rot, pos], -1)
    if applied is not None:
        a = torch.eye(4, dtype=torch.float64)
        a[:3] = applied.double()
        out = a @ out
    return out


def _applied_transform(datamanager) -> Optional[torch.Tensor]:
    meta_of = getattr(datamanager, "_transforms_meta", None)
    meta = meta_of()[1] if meta_of is not None else None
    applied = None if meta is None else meta.get("applied_transform")
    return None if applied is None else torch.tensor(applied, dtype=torch.float64)


def refined_cameras(pipeline) -> Tuple[List[CameraModel], List[int]]:
    """(the distinct training cameras with refined intrinsics, each training image's index into them)."""
    from geer_ns.refinement.lens import training_camera_groups

    lens = pipeline.model.lens
    if lens is not None:
        return lens.refined_cameras(), list(lens.image_camera)
    return training_camera_groups(pipeline.datamanager.train_dataset.cameras)


def write_refined_cameras(pipeline, out_dir: Path) -> Optional[Path]:
    """Write cameras_refined.json and colmap/ into `out_dir` when the run refines its lens, poses or readouts
    (else nothing; returns None). Returns the JSON's path."""
    model = pipeline.model
    if model.lens is None and model.camera_optimizer.config.mode == "off" and getattr(model, "readout", None) is None:
        return None
    out_dir = Path(out_dir)
    outputs = pipeline.datamanager.train_dataparser_outputs
    cams, image_camera = refined_cameras(pipeline)
    to_data = lambda poses: to_data_frame(poses, outputs.dataparser_transform,  # noqa: E731
                                          float(outputs.dataparser_scale), _applied_transform(pipeline.datamanager))
    starts = _run_frame_poses(pipeline)
    c2w = to_data(_in_given_frame(model, starts))
    readouts, ends = refined_readouts(pipeline, starts)
    c2w_end = to_data(ends)
    data = Path(pipeline.datamanager.config.dataparser.data)
    out_dir.mkdir(parents=True, exist_ok=True)
    frames = []
    for i, name in enumerate(outputs.image_filenames):  # paths relative to the file (it parses where it lies)
        rel = os.path.relpath(Path(name).resolve(), out_dir.resolve())
        frame = {"file_path": rel, "transform_matrix": c2w[i].tolist()}
        if readouts[i] is not None:
            frame.update(rolling_shutter={"readout": readouts[i]}, transform_matrix_end=c2w_end[i].tolist())
        frames.append({**frame, **nerfstudio_intrinsics(cams[image_camera[i]])})
    meta = {**nerfstudio_intrinsics(cams[0]), "frames": frames,
            "refinement": {"lens": model.config.lens_refinement, "poses": model.camera_optimizer.config.mode,
                           "step": int(model.step), "data": str(data)}}
    path = out_dir / FILE_NAME
    partial = out_dir / f".{FILE_NAME}.partial"
    partial.write_text(json.dumps(meta, indent=2) + "\n")
    os.replace(partial, path)
    write_colmap_text(out_dir / COLMAP_DIR, cams, image_camera, c2w, [f["file_path"] for f in frames])
    return path


def write_colmap_text(folder: Path, cams: List[CameraModel], image_camera: List[int], c2w: torch.Tensor,
                      names: List[str]) -> None:
    """cameras.txt / images.txt / points3D.txt of the cameras COLMAP has a model for (images of the others are
    left out); c2w [N, 4, 4] nerfstudio (OpenGL axes) camera-to-worlds."""
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    ids: Dict[int, int] = {}
    for i, cam in enumerate(cams):
        found = colmap_camera(cam)
        if found is None:
            lines.append(f"# camera {i + 1}: {type(cam).__name__} has no COLMAP model")
            continue
        ids[i] = i + 1
        lines.append(f"{i + 1} {found[0]} {cam.width} {cam.height} " + " ".join(repr(v) for v in found[1]))
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    rows = ["# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, name in enumerate(names):
        if image_camera[i] not in ids:
            continue
        pose = c2w[i].numpy().copy()
        pose[:3, 1:3] *= -1  # OpenGL -> OpenCV camera axes
        rot = pose[:3, :3].T
        trans = -rot @ pose[:3, 3]
        q = _quaternion(rot)
        rows.append(f"{i + 1} " + " ".join(repr(float(v)) for v in (*q, *trans)) + f" {ids[image_camera[i]]} {name}")
        rows.append("")
    (folder / "images.txt").write_text("\n".join(rows) + "\n")
    (folder / "points3D.txt").write_text("# 3D point list (none: cameras only)\n")


def _quaternion(rot: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix, w >= 0 (pycolmap's conversion; it returns x, y, z, w)."""
    import pycolmap

    x, y, z, w = pycolmap.Rotation3d(np.asarray(rot, dtype=np.float64)).quat
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q
