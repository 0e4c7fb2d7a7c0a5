"""geer's pycolmap-based COLMAP dataparser, and nerfstudio-format fisheye / 624 / equirectangular data.

Synthetic COLMAP models are built with pycolmap and written (text and binary) into tmp_path with dummy images
of the right sizes. Poses are checked by projecting 3-D points with pycolmap (image.project_point) and with
the parser's nerfstudio cameras (OpenGL c2w) + the exact geer model; rays go the other way.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from conftest import SHARED_DATA
from geer_ns import cameras as gc
from geer_ns.data.dataset_checks import DatasetError
from geer_ns.data.frustum_seed import seed_count
from geer_ns.data.colmap_parser import (
    GeerColmapDataParserConfig,
    camera_model_for_image,
    camera_model_from_cameras,
    geer_colmap_dataparser,
)
from nerfstudio.cameras.cameras import CameraType


# (camera_id, model, width, height, params)
CAMERAS = [
    (1, "OPENCV_FISHEYE", 64, 48, [21.0, 21.5, 32.3, 23.8, 0.021, -0.013, 0.0035, 0.0042]),  # k4 != 0
    (2, "FULL_OPENCV", 40, 30, [36.0, 35.0, 20.2, 14.7, -0.05, 0.01, 0.001, -0.002, 0.002, 0.03, -0.01, 0.004]),
    (3, "THIN_PRISM_FISHEYE", 48, 40, [18.0, 18.4, 24.1, 19.9, 0.012, -0.004, 0.0012, -0.0008, 0.001, 0.0005,
                                       0.0015, -0.001]),
    (4, "FOV", 36, 36, [30.0, 30.5, 18.2, 17.6, 0.9]),
]
# Largest off-axis angle (deg) used for test points per model (where pycolmap's projection is well-defined).
MAX_DEG = {"OPENCV_FISHEYE": 75, "FULL_OPENCV": 25, "THIN_PRISM_FISHEYE": 70, "FOV": 35, "OPENCV": 30,
           "RAD_TAN_THIN_PRISM_FISHEYE": 70}
# (image name, camera id); deliberately not in name order of ids
IMAGES = [("sub/e.png", 2), ("a.png", 1), ("b.png", 3), ("c.png", 4), ("d.png", 1), ("f.png", 3)]


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def build_recon(cameras=CAMERAS, images=IMAGES, n_points: int = 25, seed: int = 0) -> pycolmap.Reconstruction:
    rng = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction()
    for cid, model, w, h, params in cameras:
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(camera_id=cid, model=model, width=w, height=h, params=[float(p) for p in params])
        )
    for iid, (name, cid) in enumerate(images, start=1):
        rot = _rotation(rng)
        centre = rng.uniform(-2, 2, size=3)
        cam_from_world = pycolmap.Rigid3d(np.hstack([rot, (-rot @ centre)[:, None]]))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=cid, image_id=iid), cam_from_world)
    for _ in range(n_points):
        rec.add_point3D(rng.normal(size=3), pycolmap.Track(), rng.integers(0, 256, size=3).astype(np.uint8))
    return rec


def write_dataset(root: Path, rec: pycolmap.Reconstruction, fmt: str = "bin", model_dir: str = "sparse/0",
                  masks: bool = False) -> Path:
    out = root / model_dir
    out.mkdir(parents=True, exist_ok=True)
    (rec.write_binary if fmt == "bin" else rec.write_text)(str(out))
    for im in rec.images.values():
        cam = rec.cameras[im.camera_id]
        path = root / "images" / im.name
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.new("RGB", (cam.width, cam.height), (90, 120, 150)).save(path)
        if masks:
            mpath = (root / "masks" / im.name).with_suffix(".png")
            mpath.parent.mkdir(parents=True, exist_ok=True)
            Image.new("L", (cam.width, cam.height), 255).save(mpath)
    return root


def load(root: Path, split: str = "train", **kw):
    kw.setdefault("eval_mode", "all")
    return GeerColmapDataParserConfig(data=root, **kw).setup().get_dataparser_outputs(split=split)


def _to_output_world(outputs, xyz: np.ndarray) -> torch.Tensor:
    t = outputs.dataparser_transform.double()
    x = torch.as_tensor(xyz, dtype=torch.float64)
    return (x @ t[:, :3].T + t[:, 3]) * outputs.dataparser_scale


def _test_points(rng, image: pycolmap.Image, max_deg: float, n: int = 12) -> np.ndarray:
    """World points in front of ``image`` at up to max_deg off its optical axis."""
    ang = np.radians(rng.uniform(0, max_deg, n))
    az = rng.uniform(-math.pi, math.pi, n)
    depth = rng.uniform(0.5, 3.0, n)
    pc = np.stack([np.sin(ang) * np.cos(az), np.sin(ang) * np.sin(az), np.cos(ang)], -1) * depth[:, None]
    m = np.asarray(image.cam_from_world().matrix())
    return (pc - m[:, 3]) @ m[:, :3]  # R^T (p - t)


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle between direction vectors (any length), degrees; accurate for tiny angles."""
    return torch.rad2deg(torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1)))


def _check_projection_and_rays(rec, outputs, names, use_nerfstudio_rays: bool):
    """pycolmap projection == nerfstudio pose + exact model projection; rays through the pycolmap pixel."""
    rng = np.random.default_rng(1)
    by_name = {im.name: im for im in rec.images.values()}
    cams = outputs.cameras
    for i, name in enumerate(names):
        im = by_name[name]
        cam = rec.cameras[im.camera_id]
        xw = _test_points(rng, im, MAX_DEG[cam.model.name])
        px_ref = np.stack([np.asarray(im.project_point(x)) for x in xw])
        model = camera_model_for_image(outputs, i)
        c2w = cams.camera_to_worlds[i].double()
        xo = _to_output_world(outputs, xw)
        p_gl = (xo - c2w[:, 3]) @ c2w[:, :3]  # R^T (x - t)
        p_cv = p_gl * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
        px, valid = model.project(p_cv)
        assert bool(valid.all()), name
        err = (px - torch.from_numpy(px_ref)).abs().max().item()
        assert err < 1e-3, f"{name} ({cam.model.name}): reprojection differs from pycolmap by {err} px"
        # Ray from the pycolmap pixel through the point.
        dirs, ok = model.unproject(torch.from_numpy(px_ref))
        assert bool(ok.all())
        world_dirs = (dirs * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)) @ c2w[:, :3].T
        ang = _angle_deg(world_dirs, xo - c2w[:, 3]).max().item()
        assert ang < 1e-4, f"{name} ({cam.model.name}): exact-model ray misses the point by {ang} deg"
        if use_nerfstudio_rays and outputs.metadata["geer_colmap_cameras"][i].nerfstudio_exact:
            coords = torch.from_numpy(px_ref[:, ::-1].copy()).float()  # nerfstudio coords are (row, col)
            rays = cams.generate_rays(camera_indices=i, coords=coords)
            o = rays.origins.double()
            d = rays.directions.double()
            ang = _angle_deg(d, xo - o).max().item()
            assert ang < 0.02, f"{name} ({cam.model.name}): nerfstudio's own rays miss by {ang} deg"


# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["txt", "bin"])
def test_loads_exact_cameras_poses_and_points(tmp_path, fmt):
    rec = build_recon()
    write_dataset(tmp_path, rec, fmt)
    out = load(tmp_path)
    names = sorted(n for n, _ in IMAGES)
    assert [p.relative_to(tmp_path / "images").as_posix() for p in out.image_filenames] == names
    by_name = {im.name: im for im in rec.images.values()}
    specs = out.metadata["geer_colmap_cameras"]
    for i, name in enumerate(names):
        cam = rec.cameras[by_name[name].camera_id]
        spec = specs[i]
        assert (spec.model, spec.width, spec.height, spec.camera_id) == (
            cam.model.name, cam.width, cam.height, cam.camera_id)
        np.testing.assert_array_equal(np.array(spec.params), cam.params)  # bit-exact, text and binary
        model = camera_model_for_image(out, i)
        ref = gc.from_pycolmap(cam)
        assert model == ref
        assert camera_model_from_cameras(out.cameras, i) == ref
        assert int(out.cameras.width[i]) == cam.width and int(out.cameras.height[i]) == cam.height
        if spec.nerfstudio_exact:  # fitted cameras may scale the focal length; cx, cy are always COLMAP's
            assert float(out.cameras.fx[i]) == pytest.approx(cam.params[0], rel=1e-6)
        assert float(out.cameras.cy[i]) == pytest.approx(cam.params[3], rel=1e-6)
        ctype = CameraType(int(out.cameras.camera_type[i]))
        dist = out.cameras.distortion_params[i].tolist()
        if cam.model.name == "OPENCV_FISHEYE":  # k4 != 0 maps exactly to nerfstudio FISHEYE
            assert ctype == CameraType.FISHEYE and spec.nerfstudio_exact
            np.testing.assert_allclose(dist, list(cam.params[4:8]) + [0, 0], rtol=1e-6)
            assert gc.from_nerfstudio(out.cameras, i) == gc.OpenCVFisheyeCamera(
                cam.width, cam.height, *[float(np.float32(v)) for v in cam.params])
        elif cam.model.name == "THIN_PRISM_FISHEYE":
            assert ctype == CameraType.FISHEYE and not spec.nerfstudio_exact
        elif cam.model.name == "FULL_OPENCV":
            assert ctype == CameraType.PERSPECTIVE and not spec.nerfstudio_exact
        elif cam.model.name == "FOV":
            assert not spec.nerfstudio_exact
    _check_projection_and_rays(rec, out, names, use_nerfstudio_rays=True)

    # Camera centres and orientations directly.
    for i, name in enumerate(names):
        im = by_name[name]
        c2w = out.cameras.camera_to_worlds[i].double()
        centre = _to_output_world(out, np.asarray(im.projection_center())[None])[0]
        torch.testing.assert_close(c2w[:, 3], centre, atol=1e-6, rtol=0)
        r_cw = np.asarray(im.cam_from_world().matrix())[:, :3]  # world -> camera (OpenCV)
        t = out.dataparser_transform.double()[:, :3]
        want = (t @ torch.from_numpy(r_cw.T)) * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
        torch.testing.assert_close(c2w[:, :3], want, atol=1e-6, rtol=0)

    # Proper rigid motions (no reflection slipped into the convention changes).
    dets = torch.linalg.det(out.cameras.camera_to_worlds[:, :, :3].double())
    torch.testing.assert_close(dets, torch.ones_like(dets), atol=1e-5, rtol=0)
    assert torch.linalg.det(out.dataparser_transform[:, :3].double()).item() == pytest.approx(1.0, abs=1e-5)

    # Seed points: every points3D entry, transformed and scaled like the poses, with its colour.
    pts = [rec.points3D[k] for k in sorted(rec.points3D)]
    xyz = out.metadata["points3D_xyz"]
    assert xyz.shape == (len(pts), 3) and xyz.dtype == torch.float32
    torch.testing.assert_close(xyz.double(), _to_output_world(out, np.stack([p.xyz for p in pts])), atol=1e-5, rtol=0)
    rgb = out.metadata["points3D_rgb"]
    assert rgb.dtype == torch.uint8
    np.testing.assert_array_equal(rgb.numpy(), np.stack([p.color for p in pts]))
    # Auto scale: camera origins within [-1, 1], one of them on the boundary.
    assert out.cameras.camera_to_worlds[:, :, 3].abs().max().item() == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("orientation", ["none", "pca"])
def test_other_orientations_still_project(tmp_path, orientation):
    rec = build_recon(seed=3)
    write_dataset(tmp_path, rec, "bin")
    out = load(tmp_path, orientation_method=orientation, center_method="focus", scale_factor=2.5)
    _check_projection_and_rays(rec, out, sorted(n for n, _ in IMAGES), use_nerfstudio_rays=False)


def _check_fitted_close(out, max_deg: float):
    for i, spec in enumerate(out.metadata["geer_colmap_cameras"]):
        if spec.nerfstudio_exact:
            continue
        exact = camera_model_for_image(out, i)
        assert camera_model_from_cameras(out.cameras, i) == exact
        px = exact.pixel_centers(torch.float64).reshape(-1, 2)
        dirs, valid = exact.unproject(px)
        rays = out.cameras.generate_rays(camera_indices=i, coords=px[:, [1, 0]].float())
        c2w = out.cameras.camera_to_worlds[i].double()
        ref = (dirs * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)) @ c2w[:, :3].T
        ang = _angle_deg(rays.directions.double(), ref)[valid].max().item()
        assert ang < max_deg, f"{spec.model}: fitted nerfstudio camera is {ang} deg off"


def test_fov_and_thin_prism_approximations_are_sensible(tmp_path):
    """The fitted nerfstudio cameras (viewer only) stay close to the exact model over the whole image."""
    write_dataset(tmp_path, build_recon(), "bin")
    out = load(tmp_path)
    assert sum(not s.nerfstudio_exact for s in out.metadata["geer_colmap_cameras"]) == 4
    _check_fitted_close(out, max_deg=0.5)


RAD_TAN = (1, "RAD_TAN_THIN_PRISM_FISHEYE", 50, 40,
           [20.0, 20.5, 25.2, 19.7, 0.02, -0.01, 0.003, 0.0, 0.0, 0.0, 0.001, -0.0015, 0.001, 0.0, -0.0008, 0.0])


def test_rad_tan_thin_prism_fisheye_maps_to_fisheye624(tmp_path):
    images = [("a.png", 1), ("b.png", 1), ("c.png", 1)]
    rec = build_recon([RAD_TAN], images, seed=5)
    write_dataset(tmp_path, rec, "txt")
    out = load(tmp_path)
    assert out.cameras.distortion_params.shape == (3, 12)
    assert [CameraType(int(t)) for t in out.cameras.camera_type[:, 0]] == [CameraType.FISHEYE624] * 3
    assert all(s.nerfstudio_exact for s in out.metadata["geer_colmap_cameras"])
    np.testing.assert_allclose(out.cameras.distortion_params[0].numpy(), RAD_TAN[4][4:], rtol=1e-6)
    _check_projection_and_rays(rec, out, ["a.png", "b.png", "c.png"], use_nerfstudio_rays=True)


def test_rad_tan_mixed_with_other_cameras_is_fitted(tmp_path):
    """nerfstudio's 624 ray generation breaks for mixed camera types: the parser then shows a fitted FISHEYE."""
    cams = [RAD_TAN, (2, "OPENCV", 40, 30, [30.0, 31.0, 20.0, 15.0, -0.05, 0.01, 0.001, -0.001])]
    images = [("a.png", 1), ("b.png", 2), ("c.png", 1)]
    rec = build_recon(cams, images, seed=5)
    write_dataset(tmp_path, rec, "txt")
    out = load(tmp_path)
    assert out.cameras.distortion_params.shape == (3, 6)
    types = [CameraType(int(t)) for t in out.cameras.camera_type[:, 0]]
    assert types == [CameraType.FISHEYE, CameraType.PERSPECTIVE, CameraType.FISHEYE]
    assert [s.nerfstudio_exact for s in out.metadata["geer_colmap_cameras"]] == [False, True, False]
    _check_projection_and_rays(rec, out, ["a.png", "b.png", "c.png"], use_nerfstudio_rays=True)
    _check_fitted_close(out, max_deg=0.5)


# ---------------------------------------------------------------------------------------------------
def test_nerfstudio_colmap_parser_rejects_fisheye_k4_but_geer_loads_it(tmp_path):
    from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig

    cams = [CAMERAS[0]]
    rec = build_recon(cams, [("a.png", 1), ("b.png", 1), ("c.png", 1)])
    write_dataset(tmp_path, rec, "txt", model_dir="colmap/sparse/0")  # nerfstudio's default location
    host = ColmapDataParserConfig(data=tmp_path, downscale_factor=1, eval_mode="all").setup()
    try:
        host.get_dataparser_outputs(split="train")
    except ValueError as e:
        assert "K4" in str(e)
    else:
        pytest.fail("nerfstudio's colmap dataparser now accepts OPENCV_FISHEYE with k4 != 0: the host changed "
                    "(its fisheye k4 bug fixed?); revisit why geer ships its own parser")
    out = load(tmp_path)  # finds colmap/sparse/0 by itself
    assert [s.params[7] for s in out.metadata["geer_colmap_cameras"]] == [0.0042] * 3
    np.testing.assert_allclose(out.cameras.distortion_params[:, 3].numpy(), 0.0042, rtol=1e-6)


def test_split_interval_and_list_files(tmp_path):
    write_dataset(tmp_path, build_recon(), "bin")
    names = sorted(n for n, _ in IMAGES)  # a b c d sub/e f

    def split_names(split, **kw):
        out = load(tmp_path, split=split, **kw)
        assert len(out.metadata["geer_colmap_cameras"]) == len(out.image_filenames) == len(out.cameras)
        return [p.relative_to(tmp_path / "images").as_posix() for p in out.image_filenames]

    assert split_names("train", eval_mode="interval") == names[1:]  # default every 8th: only the first is eval
    assert split_names("val", eval_mode="interval") == names[:1]
    assert split_names("train", eval_mode="interval", eval_interval=2) == [names[1], names[3], names[5]]
    assert split_names("test", eval_mode="interval", eval_interval=2) == [names[0], names[2], names[4]]
    # Poses are normalised over all images: the same image has the same pose in both splits.
    tr = load(tmp_path, split="train", eval_mode="interval", eval_interval=2)
    al = load(tmp_path, split="train", eval_mode="all")
    torch.testing.assert_close(tr.cameras.camera_to_worlds, al.cameras.camera_to_worlds[1::2])

    (tmp_path / "test_list.txt").write_text("b.png\nsub/e.png\n")
    assert split_names("train") == ["a.png", "c.png", "d.png", "f.png"]
    assert split_names("val") == ["b.png", "sub/e.png"]
    (tmp_path / "train_list.txt").write_text("a.png\nf.png\n")
    assert split_names("train") == ["a.png", "f.png"]
    (tmp_path / "test_list.txt").write_text("b.png\nnope.png\n")
    with pytest.raises(ValueError, match=r"test_list\.txt.*nope\.png"):
        load(tmp_path, split="test")


def test_downscaled_images_and_masks(tmp_path):
    rec = build_recon()
    write_dataset(tmp_path, rec, "bin", masks=True)
    for folder, mode in (("images", "RGB"), ("masks", "L")):
        for f in (tmp_path / folder).rglob("*.png"):
            with Image.open(f) as im:
                w, h = im.size
            out = tmp_path / f"{folder}_2" / f.relative_to(tmp_path / folder)
            out.parent.mkdir(parents=True, exist_ok=True)
            Image.new(mode, (w // 2, h // 2)).save(out)
    full = load(tmp_path)
    half = load(tmp_path, downscale_factor=2)
    assert all("images_2" in p.parts for p in half.image_filenames)
    assert all("masks_2" in p.parts for p in half.mask_filenames)
    for i, (sf, sh) in enumerate(zip(full.metadata["geer_colmap_cameras"], half.metadata["geer_colmap_cameras"])):
        assert (sh.width, sh.height) == (sf.width // 2, sf.height // 2)
        pc = pycolmap.Camera(model=sf.model, width=2, height=2, params=sf.params)
        pixel_idx = set(pc.focal_length_idxs()) | set(pc.principal_point_idxs())
        for j, (a, b) in enumerate(zip(sf.params, sh.params)):
            want = a / 2 if j in pixel_idx else a  # focal lengths and principal point halve
            assert b == pytest.approx(want, rel=1e-12), (sf.model, j)
        m = camera_model_for_image(half, i)
        assert camera_model_from_cameras(half.cameras, i) == m
        assert (m.width, m.height) == (sh.width, sh.height)
        # Following nerfstudio's own rescale of the full-resolution cameras gives the same model.
        c = full.cameras[i : i + 1]
        c.rescale_output_resolution(0.5)
        mf = camera_model_from_cameras(c, 0)
        for k in ("fx", "fy", "cx", "cy", "width", "height"):
            assert getattr(mf, k) == pytest.approx(getattr(m, k), rel=1e-6), k
    # Wrong size in the downscaled folder is caught too.
    Image.new("RGB", (5, 5)).save(tmp_path / "images_2" / "a.png")
    with pytest.raises(ValueError, match=r"images_2/a\.png.*5x5.*32x24"):
        load(tmp_path, downscale_factor=2)
    with pytest.raises(FileNotFoundError, match=r"images_4"):
        load(tmp_path, downscale_factor=4)


def test_camera_model_from_cameras_falls_back_when_host_undistorted(tmp_path):
    write_dataset(tmp_path, build_recon(), "bin")
    out = load(tmp_path)
    i = 0  # a.png: OPENCV_FISHEYE
    c = out.cameras[i : i + 1]
    assert isinstance(camera_model_from_cameras(c, 0), gc.OpenCVFisheyeCamera)
    # What nerfstudio's FullImageDatamanager does to a distorted fisheye: undistort to a pinhole camera.
    c.distortion_params = torch.zeros_like(c.distortion_params)
    c.camera_type = torch.full_like(c.camera_type, CameraType.PERSPECTIVE.value)
    assert isinstance(camera_model_from_cameras(c, 0), gc.PinholeCamera)


# ---------------------------------------------------------------------------------------------------
# Bad input
def test_missing_model_dir(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(FileNotFoundError, match=r"no COLMAP model directory.*sparse/0"):
        load(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"my/model.*colmap_path"):
        load(tmp_path, colmap_path=Path("my/model"))
    with pytest.raises(FileNotFoundError, match=r"dataset directory .*nothere"):
        load(tmp_path / "nothere")


def test_missing_image_file(tmp_path):
    write_dataset(tmp_path, build_recon(), "txt")
    (tmp_path / "images" / "sub" / "e.png").unlink()
    (tmp_path / "images" / "b.png").unlink()
    with pytest.raises(DatasetError, match=r"images\.txt: 2 image\(s\) named there were not found \('b\.png', "
                                           r"'sub/e\.png'\); searched .*/images, "):
        load(tmp_path)


def test_unsupported_camera_model(tmp_path):
    cams = [CAMERAS[0], (7, "EUCM", 40, 30, [20.0, 20.0, 20.0, 15.0, 0.5, 1.0])]
    write_dataset(tmp_path, build_recon(cams, [("a.png", 1), ("b.png", 7)]), "bin")
    with pytest.raises(ValueError, match=r"cameras\.bin: camera 7: unsupported or invalid camera \(EUCM\)"):
        load(tmp_path)


def test_unknown_model_name_in_text_model(tmp_path):
    write_dataset(tmp_path, build_recon(), "txt")
    f = tmp_path / "sparse/0/cameras.txt"
    f.write_text(f.read_text().replace("FOV", "FOOBAR_LENS"))
    with pytest.raises(ValueError, match=r"cameras\.txt:7: camera 4: unknown COLMAP camera model FOOBAR_LENS; expected one of .*OPENCV_FISHEYE"):
        load(tmp_path)


def test_non_finite_intrinsics_binary_and_text(tmp_path):
    rec = build_recon()
    cam = rec.cameras[3]
    p = cam.params.copy()
    p[1] = np.inf
    cam.params = p
    write_dataset(tmp_path / "b", rec, "bin")
    with pytest.raises(ValueError, match=r"cameras\.bin: camera 3: THIN_PRISM_FISHEYE parameter fy = inf is not fin"):
        load(tmp_path / "b")
    write_dataset(tmp_path / "t", build_recon(), "txt")
    f = tmp_path / "t/sparse/0/cameras.txt"
    lines = [ln.split() for ln in f.read_text().splitlines()]
    text = []
    for ln in lines:
        if ln and ln[0] == "2":
            ln[5] = "nan"  # FULL_OPENCV fx fy cx ...: fy
        text.append(" ".join(ln))
    f.write_text("\n".join(text) + "\n")
    with pytest.raises(ValueError, match=r"cameras\.txt:5: camera 2: FULL_OPENCV parameter fy = nan is not finite"):
        load(tmp_path / "t")


def test_image_size_mismatch(tmp_path):
    write_dataset(tmp_path, build_recon(), "bin")
    Image.new("RGB", (63, 48)).save(tmp_path / "images" / "d.png")
    with pytest.raises(ValueError, match=r"image 'd\.png' \(COLMAP camera 1\): image file \S*images/d\.png is 63x48 px, expected 64x48 "):
        load(tmp_path)
    load(tmp_path, check_image_sizes=False)  # can be switched off


def test_masks_missing_or_wrong_size(tmp_path):
    write_dataset(tmp_path, build_recon(), "bin", masks=True)
    out = load(tmp_path)
    assert [p.relative_to(tmp_path / "masks").as_posix() for p in out.mask_filenames] == sorted(
        n for n, _ in IMAGES)
    assert load(tmp_path, masks_path=None).mask_filenames is None
    Image.new("L", (10, 10)).save(tmp_path / "masks" / "b.png")
    with pytest.raises(ValueError, match=r"masks/b\.png is 10x10 px, expected 48x40 \(the image's size\)"):
        load(tmp_path)
    Image.new("L", (48, 40)).save(tmp_path / "masks" / "b.png")
    (tmp_path / "masks" / "c.png").unlink()
    with pytest.raises(DatasetError, match=r"masks/c\.png does not exist"):
        load(tmp_path)


def _assert_seeds_inside_frusta(out) -> None:
    """Every seed point projects into the valid image of at least one camera (exact models), in front of it."""
    xyz = out.metadata["points3D_xyz"].double()
    assert len(xyz) == seed_count(len(out.image_filenames))
    seen = torch.zeros(len(xyz), dtype=torch.bool)
    for i in range(len(out.image_filenames)):
        c2w = out.cameras.camera_to_worlds[i].double()
        rot = c2w[:, :3] * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)  # OpenGL -> OpenCV axes
        local = (xyz - c2w[:, 3]) @ rot
        m = camera_model_for_image(out, i)
        px, valid = m.project(local)
        inside = valid & (px[:, 0] >= 0) & (px[:, 0] <= m.width) & (px[:, 1] >= 0) & (px[:, 1] <= m.height)
        seen |= inside & (local.norm(dim=-1) > 0)
    assert bool(seen.all()), int((~seen).sum())


# ---------------------------------------------------------------------------------------------------
def test_real_t265_calibration(tmp_path):
    src = SHARED_DATA / "t265_fisheye"
    if not (src / "cameras.txt").exists():
        pytest.skip(f"test data not found at {src} (set GEER_TEST_DATA: docs/test_data.md)")
    # The kapture export writes comma-separated images.txt and names the files cam00<id>_frame_<n>.jpg:
    # rewrite into a standard COLMAP text model and the images/<name> layout the parser expects.
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    shutil.copy(src / "cameras.txt", model / "cameras.txt")
    entries = []
    for line in (src / "images.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            tok = [t.strip() for t in line.split(",")]
            entries.append(tok)
            cid, name = int(tok[8]), tok[9]
            frame = int(Path(name).stem.split("_")[-1])
            dst = tmp_path / "images" / name
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(src / f"cam{cid:03d}_frame_{frame}.jpg", dst)
    (model / "images.txt").write_text("".join(" ".join(t) + "\n\n" for t in entries))  # no points3D.txt
    out = load(tmp_path)

    calib = {}
    for line in (src / "cameras.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            tok = line.split()
            calib[int(tok[0])] = (tok[1], int(tok[2]), int(tok[3]), tuple(float(v) for v in tok[4:]))
    by_name = {t[9]: t for t in entries}
    names = sorted(by_name)
    assert [p.relative_to(tmp_path / "images").as_posix() for p in out.image_filenames] == names
    _assert_seeds_inside_frusta(out)  # no points3D.txt: seeds drawn in the camera frusta
    for i, name in enumerate(names):
        cid = int(by_name[name][8])
        model_name, w, h, params = calib[cid]
        spec = out.metadata["geer_colmap_cameras"][i]
        assert (spec.model, spec.width, spec.height, spec.params, spec.camera_id) == (model_name, w, h, params, cid)
        m = camera_model_for_image(out, i)
        assert m == gc.OpenCVFisheyeCamera(w, h, *params)
        assert params[7] != 0  # k4: the case nerfstudio's colmap parser rejects
        assert CameraType(int(out.cameras.camera_type[i])) == CameraType.FISHEYE
        np.testing.assert_allclose(out.cameras.distortion_params[i].numpy(), list(params[4:]) + [0, 0], rtol=1e-6)
        # ~163 degree field of view: the image circle (radius ~400 px, it touches the top and bottom) is ~80
        # degrees off-axis.
        edge = m.unproject(torch.tensor([[m.cx - 400.0, m.cy]], dtype=torch.float64))[0][0]
        assert 75 < math.degrees(math.acos(float(edge[2]))) < 90
    # Stereo pairs: same rotation, translation differing by 0.064 along x -> centres 0.064 apart.
    c = out.cameras.camera_to_worlds[:, :, 3].double() / out.dataparser_scale
    left = [i for i, n in enumerate(names) if n.startswith("leftraw")]
    right = [i for i, n in enumerate(names) if n.startswith("rightraw")]
    for li, ri in zip(left, right):
        assert (c[li] - c[ri]).norm().item() == pytest.approx(0.064, abs=1e-6)


# ---------------------------------------------------------------------------------------------------
def test_registered_with_nerfstudio():
    from nerfstudio.plugins.registry_dataparser import DataParserSpecification, discover_dataparsers

    assert isinstance(geer_colmap_dataparser, DataParserSpecification)
    found, _ = discover_dataparsers()
    assert "geer-colmap" in found, "run `pip install -e .` so the entry point is registered"
    assert isinstance(found["geer-colmap"], GeerColmapDataParserConfig)


def test_matches_nerfstudio_colmap_parser_where_it_works(tmp_path):
    """Same poses, seed points, transform and scale as nerfstudio's own parser on a model it supports."""
    from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig

    cams = [(1, "OPENCV", 40, 30, [30.0, 31.0, 20.0, 15.0, -0.05, 0.01, 0.001, -0.001]),
            (2, "OPENCV", 40, 30, [33.0, 32.0, 19.0, 16.0, 0.02, 0.0, 0.0, 0.002])]
    images = [(f"im{k}.png", 1 + k % 2) for k in range(5)]  # ids in name order (nerfstudio sorts by id)
    write_dataset(tmp_path, build_recon(cams, images, seed=11), "bin", model_dir="colmap/sparse/0")
    ref = ColmapDataParserConfig(data=tmp_path, downscale_factor=1, eval_mode="all").setup().get_dataparser_outputs()
    out = load(tmp_path)
    assert out.image_filenames == ref.image_filenames
    torch.testing.assert_close(out.cameras.camera_to_worlds, ref.cameras.camera_to_worlds, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.dataparser_transform, ref.dataparser_transform, atol=1e-5, rtol=0)
    assert out.dataparser_scale == pytest.approx(ref.dataparser_scale, rel=1e-5)
    torch.testing.assert_close(out.metadata["points3D_xyz"], ref.metadata["points3D_xyz"], atol=1e-5, rtol=0)
    torch.testing.assert_close(out.metadata["points3D_rgb"], ref.metadata["points3D_rgb"])
    for k in ("fx", "fy", "cx", "cy", "width", "height", "distortion_params", "camera_type"):
        torch.testing.assert_close(getattr(out.cameras, k).to(getattr(ref.cameras, k).dtype), getattr(ref.cameras, k))


def test_geer_renders_with_the_exact_colmap_model(tmp_path):
    """The model and datamanager pick their camera through views.camera_model: the exact COLMAP camera
    (FOV, thin-prism, FULL_OPENCV), not the closest nerfstudio type the parser had to give nerfstudio."""
    from geer_ns.data.views import camera_model

    out = load(write_dataset(tmp_path, build_recon()))
    expected = {"FOV": gc.FOVCamera, "THIN_PRISM_FISHEYE": gc.ThinPrismFisheyeCamera,
                "OPENCV_FISHEYE": gc.OpenCVFisheyeCamera, "FULL_OPENCV": gc.PinholeCamera}
    seen = set()
    for i, name in enumerate(out.image_filenames):
        model_name = next(m for cid, m, *_ in CAMERAS if cid == dict(IMAGES)[_rel(name, tmp_path)])
        cam = camera_model(out.cameras[i : i + 1], 0)
        assert isinstance(cam, expected[model_name]), (name, model_name, type(cam).__name__)
        seen.add(model_name)
    assert {"FOV", "THIN_PRISM_FISHEYE"} <= seen


def _rel(path, root: Path) -> str:
    return Path(path).relative_to(root / "images").as_posix()


def test_geer_datamanager_caches_beap_views_of_colmap_cameras(tmp_path):
    """geer-colmap feeds GeerDataManager end to end: every training view becomes a BEAP image + mask on the
    grid of its exact COLMAP camera (FOV, thin-prism and k4 fisheye included)."""
    from geer_ns.data.datamanager import GeerDataManagerConfig
    from geer_ns.data.views import beap_view, camera_model

    root = write_dataset(tmp_path, build_recon())
    manager = GeerDataManagerConfig(
        data=root, dataparser=GeerColmapDataParserConfig(eval_mode="interval", eval_interval=3), cache_images="cpu",
        supervision="beap",  # auto would train the thin-prism camera (rays past 90 deg) on native rays
    ).setup(device="cpu", test_mode="val")
    cameras = manager.train_dataset.cameras
    assert len(manager.cached_train) == len(cameras) >= 3
    for i, view in enumerate(manager.cached_train):
        grid = beap_view(camera_model(cameras[i : i + 1], 0)).grid
        assert view["image"].shape == (grid.height, grid.width, 3)
        assert 0.3 < float(view["mask"].float().mean()) <= 1.0


def test_rolling_shutter_readouts_from_neighbouring_poses(tmp_path):
    """--pipeline.datamanager.dataparser.rolling-shutter: a camera turning and moving at constant rates between
    COLMAP poses (taken as mid-readout) gets each image's start pose and motion exactly; wrong options are errors."""
    from scipy.spatial.transform import Rotation

    from geer_ns.data.rolling_shutter import MOTION_KEY, READOUT_KEY, end_pose

    fps, readout_time, omega, velocity = 30.0, 0.02, np.array([0.3, -0.9, 1.4]), np.array([0.4, 0.1, -0.3])
    names = [f"frame_{k:05d}.png" for k in range(5)]
    rec = build_recon(cameras=CAMERAS[:1], images=[(n, 1) for n in names])
    r0 = _rotation(np.random.default_rng(3))
    for k, image in enumerate(sorted(rec.images.values(), key=lambda im: im.name)):
        t = k / fps
        c2w_rot = r0 @ Rotation.from_rotvec(omega * t).as_matrix()  # OpenCV camera axes, world from camera
        centre = np.array([0.2, -0.5, 1.0]) + velocity * t
        rec.images[image.image_id].frame.rig_from_world = pycolmap.Rigid3d(
            np.hstack([c2w_rot.T, (-c2w_rot.T @ centre)[:, None]]))
    root = write_dataset(tmp_path, rec)
    still = load(root, orientation_method="none", center_method="none", auto_scale_poses=False)
    out = load(root, orientation_method="none", center_method="none", auto_scale_poses=False,
               rolling_shutter="top-to-bottom", readout_time=readout_time, frame_rate=fps)
    assert (out.cameras.metadata[READOUT_KEY] == 0).all()
    flip = torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
    for i in range(5):
        mid = still.cameras.camera_to_worlds[i].double()
        start = out.cameras.camera_to_worlds[i].double()
        end = end_pose(start, out.cameras.metadata[MOTION_KEY][i])
        for pose, dt in ((start, -readout_time / 2), (end, readout_time / 2)):
            turn = (mid[:, :3] * flip).T @ (pose[:, :3] * flip)  # in the camera's (OpenCV) axes
            assert np.allclose(Rotation.from_matrix(turn.numpy()).as_rotvec(), omega * dt, atol=2e-6)
            assert torch.allclose(pose[:, 3], mid[:, 3] + still.dataparser_transform[:3, :3].double()
                                  @ torch.tensor(velocity * dt), atol=2e-6)
    with pytest.raises(DatasetError, match="needs geer-colmap --readout-time"):
        load(root, rolling_shutter="top-to-bottom", frame_rate=fps)
    with pytest.raises(DatasetError, match="must be shorter than a frame interval"):
        load(root, rolling_shutter="top-to-bottom", readout_time=0.05, frame_rate=fps)
