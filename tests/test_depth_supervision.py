"""Depth supervision: depth files become the room's true ray distances (the analytic ray caster is the
reference), LiDAR points land on the pixels a pinhole formula puts them, and the loss's gradient through the
compiled CPU backend equals the PyTorch renderer's."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from conftest import random_scene
from geer_ns.cameras import PinholeCamera
from geer_ns.data.depth import TARGET_KEY, points_distance
from geer_ns.data.synthetic_cameras import fisheye_pixel_dirs, pinhole_pixel_dirs
from geer_ns.data.synthetic_depth import frame_distances, write_depth_variant
from geer_ns.data.synthetic_room import generate_room
from geer_ns.data.views import native_view
from geer_ns.depth_supervision import DepthSupervisionOptions, depth_loss, depth_metrics, robust
from geer_ns.render import RayGrid, render

SIZE = 24


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    root = generate_room(tmp_path_factory.mktemp("depth") / "room", n_views=3, image_size=SIZE)
    for variant in ("fisheye", "pinhole"):
        write_depth_variant(root, variant)
    return root


@pytest.mark.parametrize("variant", ["fisheye", "pinhole"])
def test_depth_files_give_true_distances(room, variant):
    """The datamanager's target (native pixels) is the ray caster's distance times the dataparser's scale:
    radial .npy maps for the fisheye, 16-bit z maps (mm) converted along each pixel ray for the pinhole."""
    from geer_ns.config import geer_trainer_config
    from geer_ns.model import GeerModelConfig

    name = {"fisheye": "transforms_fisheye_depth.json", "pinhole": "transforms_pinhole_depth.json"}[variant]
    config = geer_trainer_config("geer", GeerModelConfig())
    config.pipeline.datamanager.data = room / name
    config.pipeline.datamanager.supervision = "native"
    config.pipeline.datamanager.cache_images = "cpu"
    manager = config.pipeline.datamanager.setup(device="cpu")
    dirs, inside = fisheye_pixel_dirs(SIZE) if variant == "fisheye" else (pinhole_pixel_dirs(SIZE), None)
    scale = float(manager.train_dataparser_outputs.dataparser_scale)
    meta = json.loads((room / name).read_text())
    poses = {f["file_path"]: np.array(f["transform_matrix"]) for f in meta["frames"]}
    for index, path in enumerate(manager.train_dataset.image_filenames):
        target = manager.cached_train[index][TARGET_KEY][..., 0].double().numpy()
        truth = frame_distances(poses[str(path.relative_to(room))], dirs) * scale
        measured = target > 0
        if inside is not None:
            assert (measured == inside).all()
        assert measured.mean() > 0.5
        # z stored in whole millimetres: 0.5 mm of z is 0.5 mm / cos(angle off-axis) of distance
        tol = 1e-6 if variant == "fisheye" else 0.5e-3 * scale / dirs[..., 2] * 1.01 + 1e-6
        assert (np.abs(target - truth) <= tol)[measured].all()


def test_lidar_points_land_on_their_pixels():
    """Each point supervises the pixel a pinhole projection puts it on with its distance; of two points on one
    ray (the first two) the nearest wins."""
    camera = PinholeCamera(width=8, height=6, fx=5.0, fy=5.0, cx=4.0, cy=3.0)
    c2w = torch.eye(4, dtype=torch.float64)[:3]  # nerfstudio axes: the camera looks along -z
    cam_points = torch.tensor([[0.5, -0.3, 2.0], [1.0, -0.6, 4.0], [-1.0, 0.8, 3.0]], dtype=torch.float64)
    world = cam_points * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)  # OpenCV -> OpenGL axes
    target = points_distance(world, c2w, native_view(camera))
    expected = torch.zeros(6, 8, dtype=torch.float64)
    for x, y, z in cam_points[[0, 2]]:
        u, v = 5.0 * x / z + 4.0, 5.0 * y / z + 3.0
        expected[int(v), int(u)] = math.sqrt(x * x + y * y + z * z)
    assert torch.allclose(target, expected)


def test_robust_losses():
    r = torch.tensor([0.0, 0.02, 0.2, -0.2])
    assert torch.allclose(robust(r, "l1", 0.05), torch.tensor([0.0, 0.02, 0.2, 0.2]))
    assert torch.allclose(robust(r, "huber", 0.05), torch.tensor([0.0, 0.004, 0.175, 0.175]))
    assert torch.allclose(robust(r, "cauchy", 0.05), 0.025 * torch.log1p(torch.tensor([0.0, 0.16, 16.0, 16.0])))


def test_depth_loss_gradient_through_cpu_backend(cpu_ops):
    """The depth loss's gradient w.r.t. every Gaussian parameter is the same through the compiled CPU backend
    as through the PyTorch renderer (autograd of the specification)."""
    grid = RayGrid.beap(12, 10, math.radians(80), math.radians(60), tile_size=6, dtype=torch.float64)
    scene = random_scene(30, 7, spread=1.0, scale_range=(0.1, 0.6))
    target = torch.full((10, 12, 1), 4.0, dtype=torch.float64)
    target[0, :] = 0.0  # unmeasured row
    options = DepthSupervisionOptions(depth_loss_weight=1.0, depth_loss="huber", depth_loss_scale=0.05)
    grads = {}
    for backend in ("torch", "cpu"):
        leaves = [t.clone().requires_grad_(True) for t in scene]
        out = render(*leaves, torch.eye(4, dtype=torch.float64), grid, backend=backend)
        valid = grid.valid.reshape(10, 12, 1)
        loss = depth_loss(out.distance, out.accumulation, target, valid, options)
        loss.backward()
        grads[backend] = [leaf.grad for leaf in leaves[:4]]
        assert float(loss.detach()) > 0
    for ours, ref in zip(grads["cpu"], grads["torch"]):
        assert torch.isfinite(ours).all()
        assert torch.allclose(ours, ref, rtol=1e-7, atol=1e-10)
    assert float(grads["torch"][0].abs().max()) > 0


def test_depth_metrics_name_distance_and_depth():
    distance = torch.tensor([[[2.0], [3.0]]])
    outputs = {"distance": distance, "depth": distance * 0.5, "depth_defined": torch.tensor([[[True], [False]]])}
    batch = {TARGET_KEY: torch.tensor([[[2.5], [3.0]]])}
    found = depth_metrics(outputs, batch, torch.ones(1, 2, dtype=torch.bool))
    assert found["distance_rmse"] == pytest.approx(math.sqrt(0.25 / 2))
    assert found["depth_rmse"] == pytest.approx(0.25)  # z of 2.5 along a ray of unit z 0.5, against 1.0
