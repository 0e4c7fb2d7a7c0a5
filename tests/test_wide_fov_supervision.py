"""Every pixel a camera saw is supervised and scored: 220-degree fisheyes and panoramas on native rays, the
180-degree room on BEAP with its thin lost rim said and counted, black borders found without a mask.

References: the generator's own masks (closed-form KB / equidistant circles, tests/test_synthetic_room.py checks
them against OpenCV), the dev room's rendered circle mask, and BEAP's angle limit.
"""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from geer_ns.data.beap import DEFAULT_MAX_HALF_ANGLE, directions_to_angles
from geer_ns.data.datamanager import GeerDataManagerConfig
from geer_ns.data.synthetic_room import default_scene_dir
from geer_ns.data.views import camera_model, native_view

from conftest import shared_data

pytestmark = pytest.mark.filterwarnings("ignore:Using a non-tuple sequence:UserWarning")


def _manager(data, **kw):
    return GeerDataManagerConfig(data=data, cache_images="cpu", **kw).setup(device="cpu", test_mode="val")


def _png_mask(path) -> torch.Tensor:
    return torch.from_numpy(cv2.imread(str(path), cv2.IMREAD_UNCHANGED) > 0)


@pytest.fixture(scope="module")
def kb220():
    return _manager(default_scene_dir() / "transforms_fisheye220.json")


def test_220_degree_kb_fisheye_supervises_every_in_circle_pixel(kb220):
    circle = _png_mask(default_scene_dir() / "masks" / "fisheye220_mask.png")
    n_circle = int(circle.sum())
    assert n_circle > 0.75 * circle.numel()
    for split, views in (("train", kb220.cached_train), ("eval", kb220.cached_eval)):
        for i, view in enumerate(views):
            mask = view["mask"][..., 0]
            assert mask.shape == circle.shape, (split, i)  # native pixels, not a BEAP image
            assert torch.equal(mask, circle), f"{split} view {i}: {int((circle & ~mask).sum())} in-circle pixels lost"
    report = kb220.supervision_report("train")
    (entry,) = report.cameras.values()
    assert entry.view == "native" and entry.images == len(kb220.train_dataset)
    assert entry.supervised_pixels == entry.valid_pixels == n_circle * entry.images
    assert entry.max_angle_deg > 105.0  # the periphery really is past 90 degrees
    camera, batch = kb220.next_train(0)
    assert camera.metadata["geer_view"] == "native" and int(batch["mask"].sum()) == n_circle
    # The viewer and eval render the camera's own rays: every in-circle pixel has one.
    viewer_rays = native_view(camera_model(kb220.eval_dataset.cameras, 0)).rays.valid.reshape(circle.shape)
    assert bool(viewer_rays[circle].all())


def test_forcing_beap_on_a_220_degree_camera_says_what_is_lost(kb220):
    forced = _manager(default_scene_dir() / "transforms_fisheye220.json", supervision="beap")
    (entry,) = forced.supervision_report("train").cameras.values()
    assert entry.view == "beap" and 0 < entry.supervised_pixels < entry.valid_pixels
    line = forced.supervision_report("train").lines()[0]
    assert f"{entry.valid_pixels - entry.supervised_pixels} pixels" in line and "NOT supervised" in line
    camera, _ = forced.next_train(0)
    assert camera.metadata["geer_view"] == "beap"


def test_equirectangular_panorama_trains_on_all_pixels():
    manager = _manager(default_scene_dir() / "transforms_equirect.json")
    (entry,) = manager.supervision_report("train").cameras.values()
    assert entry.view == "native" and entry.supervised_pixels == entry.valid_pixels == 2 * 96 * 96 * entry.images


def test_180_degree_room_in_beap_counts_its_rim():
    """BEAP on request: the pixels it cannot hold are exactly those beyond BEAP's +-89.5 deg."""
    manager = _manager(default_scene_dir(), supervision="beap")
    camera, _ = manager.next_train(0)
    assert camera.metadata["geer_view"] == "beap"
    (entry,) = manager.supervision_report("train").cameras.values()
    assert entry.view == "beap"
    circle = _png_mask(default_scene_dir() / "masks" / "fisheye_mask.png")
    cam = camera_model(manager.train_dataset.cameras, 0)
    theta, phi = directions_to_angles(cam.pixel_rays(torch.float64)[0])
    beyond = circle & ((theta.abs() > DEFAULT_MAX_HALF_ANGLE) | (phi.abs() > DEFAULT_MAX_HALF_ANGLE))
    assert entry.valid_pixels == int(circle.sum()) * entry.images
    assert entry.valid_pixels - entry.supervised_pixels == int(beyond.sum()) * entry.images
    assert "NOT supervised" in manager.supervision_report("train").lines()[0]


def test_fisheye_without_mask_gets_its_image_circle_detected(tmp_path):
    """The dev room without mask_path and fisheye_crop_radius: only pixels inside the lens circle count."""
    src = shared_data("fisheye_room_dev", "transforms_fisheye.json")
    meta = json.loads(src.read_text())
    frames = [f for f in meta["frames"] if f["file_path"].endswith(("00000.jpg", "00001.jpg", "00002.jpg",
                                                                    "00008.jpg"))]
    for frame in frames:
        frame.pop("mask_path")
        frame["file_path"] = str(src.parent / frame["file_path"])
    names = [f["file_path"] for f in frames]
    meta = {k: v for k, v in meta.items() if k not in ("fisheye_crop_radius", "ply_file_path")}
    meta.update(frames=frames, train_filenames=names[1:3], val_filenames=names[::3], test_filenames=names[::3])
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps(meta))
    manager = _manager(path, supervision="native", load_seed_points=False)
    # The lit circle: rays within 90 degrees of the equidistant lens (r = f theta, f = 384 / pi: radius 192 px).
    # (The dataset's own mask is the more conservative fisheye_crop_radius, 191 px.)
    uv = np.arange(384) + 0.5
    truth = torch.from_numpy(np.hypot(uv[None, :] - meta["cx"], uv[:, None] - meta["cy"]) <= meta["fl_x"] * math.pi / 2)
    for view in manager.cached_train + manager.cached_eval:
        mask = view["mask"][..., 0]
        assert int((mask & ~truth).sum()) == 0  # nothing outside the lens circle is supervised or scored
        # ... and the ring lost inside it is the 2-pixel margin (circumference ~1200 px): < 4 px of radius.
        lost = int((truth & ~mask).sum())
        assert lost < 4 * 2 * math.pi * 192, lost
    (entry,) = manager.supervision_report("train").cameras.values()
    assert entry.supervised_pixels == entry.valid_pixels < 0.8 * 384 * 384 * entry.images
