"""GeerDataManager on the embedded synthetic room: no undistortion, BEAP training views (on request), native ones
(the default), masks, seed points."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest
import torch

from nerfstudio.cameras.cameras import CameraType
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

from geer_ns.data.beap import DEFAULT_MAX_HALF_ANGLE, directions_to_angles
from geer_ns.data.datamanager import GeerDataManagerConfig, native_valid_mask
from geer_ns.data.synthetic_room import default_scene_dir
from geer_ns.data.views import beap_view, camera_model
from geer_ns.data.ply import read_ply_points

from conftest import shared_data


@pytest.fixture(scope="module")
def manager():
    """Built like ns-train builds it, with cache_images="cpu" (pin_memory crashes without a GPU) and
    load_3D_points=True (nerfstudio would import open3d)."""
    config = GeerDataManagerConfig(
        data=default_scene_dir(),
        dataparser=NerfstudioDataParserConfig(load_3D_points=True),
        cache_images="cpu",
        supervision="beap",
    )
    return config.setup(device="cpu", test_mode="val")


def test_cpu_image_cache_does_not_pin_without_a_gpu(manager):
    views = manager.cached_train
    assert len(views) == len(manager.train_dataset) == 21
    assert all(v["image"].dtype == torch.uint8 and v["mask"].dtype == torch.bool for v in views)


def test_fisheye_cameras_are_kept_not_undistorted(manager):
    cams = manager.train_cameras
    assert (cams.camera_type == CameraType.FISHEYE.value).all()
    assert torch.allclose(cams.fx, torch.full_like(cams.fx, 96 / math.pi))
    assert (cams.width == 96).all() and (cams.height == 96).all()
    eval_view = manager.cached_eval[0]
    assert eval_view["image"].shape == (96, 96, 3)  # native pixels for eval


def test_training_views_are_beap_images_of_the_shared_grid(manager):
    view = beap_view(camera_model(manager.train_cameras, 0))
    cached = manager.cached_train[0]
    assert tuple(cached["image"].shape[:2]) == view.size == tuple(cached["mask"].shape[:2])
    camera, batch = manager.next_train(0)
    assert camera.metadata["geer_view"] == "beap"


def _assert_no_pixel_dropped(manager, crop_radius: float, min_pixels: int) -> None:
    """Every native pixel centre inside the circle (and inside BEAP's +-89.5 deg) lands in a valid BEAP cell."""
    dataset = manager.train_dataset
    cam = camera_model(dataset.cameras, 0)
    grid = beap_view(cam).grid
    native_mask = dataset.get_data(0, image_type="uint8")["mask"]
    inside = native_valid_mask(cam, native_mask, crop_radius)
    dirs, _ = cam.pixel_rays(torch.float64)
    theta, phi = directions_to_angles(dirs)
    lim = DEFAULT_MAX_HALF_ANGLE
    sel = inside & (theta.abs() <= lim) & (phi.abs() <= lim)
    assert int(sel.sum()) > min_pixels
    cells = grid.angles_to_cells(theta[sel], phi[sel])
    col = cells[:, 0].floor().long().clamp(0, grid.width - 1)
    row = cells[:, 1].floor().long().clamp(0, grid.height - 1)
    for view in manager.cached_train:
        valid = view["mask"][..., 0]
        assert bool(valid[row, col].all()), f"{int((~valid[row, col]).sum())} in-circle pixels dropped"


def test_no_pixel_inside_the_fisheye_circle_is_dropped(manager):
    _assert_no_pixel_dropped(manager, 48.0, 7000)


def test_dev_fisheye_room_trains_on_full_fov_beap_views():
    """The Blender-rendered 180-degree room of the test data (docs/test_data.md): full-FoV BEAP views, no in-circle pixel lost."""
    json_path = shared_data("fisheye_room_dev", "transforms_fisheye.json")
    meta = json.loads(json_path.read_text())
    manager = GeerDataManagerConfig(
        data=json_path, dataparser=NerfstudioDataParserConfig(load_3D_points=True), cache_images="cpu",
        supervision="beap").setup(device="cpu", test_mode="val")
    grid = beap_view(camera_model(manager.train_dataset.cameras, 0)).grid
    assert math.degrees(grid.theta_max - grid.theta_min) >= 179.0
    assert math.degrees(grid.phi_max - grid.phi_min) >= 179.0
    _assert_no_pixel_dropped(manager, meta["fisheye_crop_radius"], 100_000)


def test_seed_points_read_without_open3d(manager):
    meta = manager.train_dataparser_outputs.metadata
    xyz, rgb = read_ply_points(default_scene_dir() / "points3d.ply")
    outputs = manager.train_dataparser_outputs
    expected = (np.c_[xyz, np.ones(len(xyz))] @ outputs.dataparser_transform.numpy().T) * outputs.dataparser_scale
    assert np.allclose(meta["points3D_xyz"].numpy(), expected, atol=1e-5)
    assert torch.equal(meta["points3D_rgb"], torch.from_numpy(rgb))
    assert sys.modules.get("open3d") is None


def test_seed_points_ignore_applied_transform(tmp_path):
    """`applied_transform` (original data -> the frame of transforms.json) says where the poses came from; the
    PLY is in the poses' frame, so adding the key to an otherwise identical dataset moves neither the cameras
    nor the seeds (nerfstudio's own PLY loader leaves it out too). Applying it to the seeds a second time
    moved every ns-process-data dataset's seed cloud off its cameras."""
    from conftest import copy_room

    def seeds_and_cameras(root):
        config = GeerDataManagerConfig(data=root, cache_images="cpu")
        outputs = config.setup(device="cpu", test_mode="val").train_dataparser_outputs
        return outputs.metadata["points3D_xyz"], outputs.cameras.camera_to_worlds[:, :, 3]

    plain = copy_room(tmp_path / "plain", n_frames=4)
    turned = copy_room(tmp_path / "turned", n_frames=4)
    meta = json.loads((turned / "transforms.json").read_text())
    meta["applied_transform"] = [[0, 1, 0, 0.5], [1, 0, 0, -0.25], [0, 0, -1, 2.0]]
    (turned / "transforms.json").write_text(json.dumps(meta))
    seeds, centres = seeds_and_cameras(plain)
    seeds_t, centres_t = seeds_and_cameras(turned)
    assert torch.allclose(centres, centres_t, atol=1e-6)
    assert torch.allclose(seeds, seeds_t, atol=1e-5)


@pytest.mark.parametrize("supervision", ["native", "auto"])  # auto: native rays (geer_ns/data/view_choice.py)
def test_native_supervision_keeps_pixels(manager, supervision):
    config = GeerDataManagerConfig(data=default_scene_dir(), cache_images="cpu", supervision=supervision)
    native = config.setup(device="cpu", test_mode="val")
    camera, batch = native.next_train(0)
    assert camera.metadata["geer_view"] == "native"
    assert batch["image"].shape == (96, 96, 3) and batch["mask"].shape == (96, 96, 1)
    assert batch["mask"].sum() < 96 * 96  # outside the image circle is not supervised


def test_missing_transforms_json_names_the_path(tmp_path):
    with pytest.raises(FileNotFoundError, match=str(tmp_path).replace("\\", "\\\\") + ".*transforms.json"):
        GeerDataManagerConfig(data=tmp_path).setup(device="cpu")
