"""nerfstudio-format data (transforms.json) with fisheye, Fisheye624 and equirectangular cameras through
nerfstudio's OWN dataparser: geer's exact camera model of each camera (geer_ns.cameras.from_nerfstudio) gives
nerfstudio's own rays (generate_rays). ply_file_path is left out: open3d needs libusb on these machines."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from test_colmap_parser import _angle_deg, _rotation

from geer_ns import cameras as gc
from geer_ns.data.colmap_parser import camera_model_for_image


def _pose(seed: int) -> list:
    m = np.eye(4)
    m[:3, :3] = _rotation(np.random.default_rng(seed))
    m[:3, 3] = np.random.default_rng(seed + 100).uniform(-1, 1, 3)
    return m.tolist()


def _write_ns(root: Path, meta: dict, size: tuple, n: int = 3, masks: bool = False) -> Path:
    frames = []
    for k in range(n):
        (root / "images").mkdir(parents=True, exist_ok=True)
        Image.new("RGB", size).save(root / "images" / f"f{k}.png")
        fr = {"file_path": f"images/f{k}.png", "transform_matrix": _pose(k)}
        if masks:
            (root / "masks").mkdir(exist_ok=True)
            Image.new("L", size, 255).save(root / "masks" / f"f{k}.png")
            fr["mask_path"] = f"masks/f{k}.png"
        frames.append(fr)
    path = root / "transforms.json"
    path.write_text(json.dumps({**meta, "frames": frames}))
    return path


def _ns_load(path: Path):
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    cfg = NerfstudioDataParserConfig(data=path, downscale_factor=1, load_3D_points=False, eval_mode="all")
    return cfg.setup().get_dataparser_outputs(split="train")


def _check_ns_rays_match(out, model_cls):
    """nerfstudio's generate_rays == geer's exact model rays (OpenGL <-> OpenCV) for each camera."""
    for i in range(len(out.cameras)):
        m = gc.from_nerfstudio(out.cameras, i)
        assert type(m) is model_cls
        assert camera_model_for_image(out, i) == m  # fallback for non-geer outputs
        px = m.pixel_centers(torch.float64)[::3, ::3].reshape(-1, 2)
        dirs, valid = m.unproject(px)
        rays = out.cameras.generate_rays(camera_indices=i, coords=px[:, [1, 0]].float())
        c2w = out.cameras.camera_to_worlds[i].double()
        ref = (dirs * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)) @ c2w[:, :3].T
        ang = _angle_deg(rays.directions.double(), ref)[valid].max().item()
        assert ang < 0.05, f"{model_cls.__name__}: nerfstudio ray differs from the geer model by {ang} deg"


def test_nerfstudio_format_opencv_fisheye_with_masks(tmp_path):
    k = [0.03, -0.01, 0.004, -0.0015]
    meta = {"camera_model": "OPENCV_FISHEYE", "fl_x": 20.0, "fl_y": 20.4, "cx": 31.7, "cy": 24.2, "w": 64, "h": 48,
            "k1": k[0], "k2": k[1], "k3": k[2], "k4": k[3], "fisheye_crop_radius": 30.0}
    out = _ns_load(_write_ns(tmp_path, meta, (64, 48), masks=True))
    assert [p.name for p in out.mask_filenames] == ["f0.png", "f1.png", "f2.png"]
    assert out.cameras.metadata["fisheye_crop_radius"] == 30.0
    m = gc.from_nerfstudio(out.cameras, 0)
    assert (m.k1, m.k2, m.k3, m.k4) == pytest.approx(k, rel=1e-6)
    _check_ns_rays_match(out, gc.OpenCVFisheyeCamera)


def test_nerfstudio_format_fisheye624(tmp_path):
    d = [0.02, -0.01, 0.003, 0.0, 0.0, 0.0, 0.001, -0.0015, 0.001, 0.0, -0.0008, 0.0]
    meta = {"camera_model": "FISHEYE624", "fl_x": 20.0, "fl_y": 20.5, "cx": 25.2, "cy": 19.7, "w": 50, "h": 40,
            "distortion_params": d, "fisheye_crop_radius": 24.0}
    out = _ns_load(_write_ns(tmp_path, meta, (50, 40)))
    assert out.cameras.distortion_params.shape == (3, 12)
    assert out.cameras.metadata["fisheye_crop_radius"] == 24.0
    m = gc.from_nerfstudio(out.cameras, 1)
    assert [m.k0, m.k1, m.k2, m.k3, m.k4, m.k5, m.p0, m.p1, m.s0, m.s1, m.s2, m.s3] == pytest.approx(d, rel=1e-6)
    _check_ns_rays_match(out, gc.Fisheye624Camera)


def test_nerfstudio_format_equirectangular(tmp_path):
    meta = {"camera_model": "EQUIRECTANGULAR", "fl_x": 32.0, "fl_y": 32.0, "cx": 32.0, "cy": 16.0, "w": 64, "h": 32}
    out = _ns_load(_write_ns(tmp_path, meta, (64, 32), masks=True))
    assert len(out.mask_filenames) == 3
    assert gc.from_nerfstudio(out.cameras, 2) == gc.EquirectangularCamera(64, 32)
    _check_ns_rays_match(out, gc.EquirectangularCamera)
