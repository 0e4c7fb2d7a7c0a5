"""The dataset: ``transforms.json`` (nerfstudio format), ``sparse/0``, ``points3d.ply`` and the report.

Poses follow nerfstudio's COLMAP conversion (``nerfstudio.process_data.colmap_utils.colmap_to_json`` with
``keep_original_world_coordinate=True``): camera axes OpenCV -> OpenGL, the world is COLMAP's (the one of
``sparse/0`` and ``points3d.ply``), so no ``applied_transform`` is written. Why not nerfstudio's (x, z, -y) world
with ``applied_transform``: nerfstudio loads the PLY in the transforms.json world, but consumers that map it with
``dataparser_transform`` (which includes ``applied_transform``; geer's datamanager seeds this way) would move the
points a second time; one world for poses, points and the COLMAP model leaves nothing to get wrong, and
nerfstudio's orientation step finds "up" from the cameras either way. Intrinsics come from nerfstudio's
``parse_colmap_camera_params`` (OPENCV_FISHEYE with k1..k4). ``colmap_to_json`` itself is not called: it
assumes camera id 1 for a shared camera and one mask for every camera, and reads the model with its own reader.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Dict, List, Optional, Sequence

import numpy as np
import pycolmap
from nerfstudio.process_data.colmap_utils import parse_colmap_camera_params
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table

from geer_ns.data.ply import write_ply_points

def camera_dict(camera: "pycolmap.Camera") -> Dict[str, object]:
    """nerfstudio intrinsics of a COLMAP camera (camera_model, fl_x, ..., k1..k4 / p1, p2)."""
    cam = SimpleNamespace(model=camera.model.name, width=int(camera.width), height=int(camera.height),
                          params=[float(p) for p in camera.params])
    return parse_colmap_camera_params(cam)


def nerfstudio_c2w(image: "pycolmap.Image") -> np.ndarray:
    """4x4 camera-to-world in nerfstudio's convention (OpenGL camera axes), COLMAP's world."""
    w2c = np.eye(4)
    w2c[:3] = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
    c2w = np.linalg.inv(w2c)
    c2w[0:3, 1:3] *= -1
    return c2w


def write_ply(path: Path, recon: "pycolmap.Reconstruction") -> int:
    """The sparse points (in the transforms.json world) as a binary PLY: x y z float, red green blue uchar."""
    pts = [p for _, p in sorted(recon.points3D.items())]
    write_ply_points(path, np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3),
                     np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3))
    return len(pts)


def write_transforms(out_dir: Path, recon: "pycolmap.Reconstruction", masks: Dict[int, Optional[Path]],
                     ply_name: str = "points3d.ply") -> int:
    """transforms.json for the registered images; ``masks`` maps COLMAP camera id -> mask (relative path)."""
    images = sorted((im for im in recon.images.values() if im.has_pose), key=lambda im: im.name)
    camera_ids = sorted({int(im.camera_id) for im in images})
    shared = len(camera_ids) == 1
    out: Dict[str, object] = camera_dict(recon.cameras[camera_ids[0]]) if shared else {}
    frames = []
    for im in images:
        frame: Dict[str, object] = {
            "file_path": f"images/{im.name}",
            "transform_matrix": nerfstudio_c2w(im).tolist(),
            "colmap_im_id": int(im.image_id),
        }
        mask = masks.get(int(im.camera_id))
        if mask is not None:
            frame["mask_path"] = mask.as_posix()
        if not shared:
            frame.update(camera_dict(recon.cameras[int(im.camera_id)]))
        frames.append(frame)
    out["frames"] = frames
    write_ply(out_dir / ply_name, recon)
    out["ply_file_path"] = ply_name
    (out_dir / "transforms.json").write_text(json.dumps(out, indent=2), encoding="utf8")
    return len(frames)


def summary(recon: "pycolmap.Reconstruction", names: Sequence[str], num_models: int,
            timings: Dict[str, float], extra: Dict[str, object]) -> Dict[str, object]:
    """The numbers of the report (also written as process_data_report.json)."""
    registered = sorted(im.name for im in recon.images.values() if im.has_pose)
    cams = {}
    for cid in sorted({int(im.camera_id) for im in recon.images.values() if im.has_pose}):
        c = recon.cameras[cid]
        cams[str(cid)] = {"model": c.model.name, "width": int(c.width), "height": int(c.height),
                          "params_info": c.params_info, "params": [float(p) for p in c.params]}
    return {
        "num_input_images": len(names),
        "num_registered_images": len(registered),
        "unregistered_images": sorted(set(names) - set(registered)),
        "num_models": num_models,
        "num_points3d": int(recon.num_points3D()),
        "mean_track_length": float(recon.compute_mean_track_length()) if recon.num_points3D() else 0.0,
        "mean_reprojection_error_px": float(recon.compute_mean_reprojection_error()),
        "cameras": cams,
        "timings_s": {k: round(v, 2) for k, v in timings.items()},
        **extra,
    }


def print_report(report: Dict[str, object]) -> None:
    table = Table(title="geer-process-data", show_header=False)
    table.add_row("registered images", f"{report['num_registered_images']} / {report['num_input_images']}")
    if report["unregistered_images"]:
        names: List[str] = report["unregistered_images"]  # type: ignore[assignment]
        table.add_row("not registered", ", ".join(names[:8]) + (" ..." if len(names) > 8 else ""))
    table.add_row("3D points", f"{report['num_points3d']} (mean track length {report['mean_track_length']:.2f})")
    table.add_row("mean reprojection error", f"{report['mean_reprojection_error_px']:.3f} px")
    for cid, cam in report["cameras"].items():  # type: ignore[union-attr]
        params = ", ".join(f"{n.strip()}={v:.6g}" for n, v in zip(cam["params_info"].split(","), cam["params"]))
        table.add_row(f"camera {cid}", f"{cam['model']} {cam['width']}x{cam['height']}: {params}")
    table.add_row("time", ", ".join(f"{k} {v:.1f} s" for k, v in report["timings_s"].items()))  # type: ignore
    CONSOLE.print(table)
