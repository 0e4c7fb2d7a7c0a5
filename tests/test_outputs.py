"""distance, depth, median_distance and normal against a float64 per-ray reference written from the definitions
(numpy, one ray at a time, no code of the renderer), on every backend; depth's pinhole convention; the model's
output names."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import equidistant_fisheye_rays, equirect_rays, random_scene
from geer_ns.outputs import INTERNAL_OUTPUTS, geometry_outputs, viewer_outputs
from geer_ns.render import RayGrid, render
from geer_ns.render.normals import render_normals

T_MIN, ALPHA_MAX = 1e-4, 0.99


def _rotation(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def reference(means, quats, scales, opacities, dirs, valid):
    """Per ray, camera at the origin (identity pose): each Gaussian's peak response on the half-line t >= 0,
    q = min_t>=0 (t d - mu)^T Sigma^-1 (t d - mu), alpha = min(0.99, o exp(-q/2)) kept when >= 1/255, blended
    front to back by the mean's distance, stopping before T < 1e-4. Returns per ray (distance, median distance,
    unit normal sum) with the normal the smallest-scale axis turned toward the camera."""
    means, quats, scales = (np.asarray(x, dtype=np.float64) for x in (means, quats, scales))
    rots = [_rotation(q) for q in quats]
    precisions = [r @ np.diag(1.0 / s ** 2) @ r.T for r, s in zip(rots, scales)]
    normals = []
    for r, s, m in zip(rots, scales, means):
        n = r[:, int(np.argmin(s))]
        normals.append(-n if n @ (-m) < 0 else n)
    order = np.argsort(np.linalg.norm(means, axis=1), kind="stable")
    out_dist, out_median, out_normal = [], [], []
    for d, ok in zip(np.asarray(dirs, dtype=np.float64), np.asarray(valid)):
        trans, acc, dist, median, normal = 1.0, 0.0, 0.0, 0.0, np.zeros(3)
        for i in order if ok else ():
            p, m = precisions[i], means[i]
            t = max((d @ p @ m) / (d @ p @ d), 0.0)
            e = t * d - m
            alpha = min(ALPHA_MAX, float(opacities[i]) * math.exp(-0.5 * e @ p @ e))
            if alpha < 1 / 255:
                continue
            after = trans * (1 - alpha)
            if after < T_MIN:
                break
            w = trans * alpha
            acc, dist, normal = acc + w, dist + w * t, normal + w * normals[i]
            if trans >= 0.5 > after:
                median = t
            trans = after
        out_dist.append(dist / acc if acc > 0 else 0.0)
        out_median.append(median)
        length = np.linalg.norm(normal)
        out_normal.append(normal / length if length > 0 else normal)
    return np.array(out_dist), np.array(out_median), np.array(out_normal)


def _grids():
    fish_dirs, fish_valid = equidistant_fisheye_rays(14, 200.0)
    return {
        "beap": RayGrid.beap(14, 10, math.radians(100), math.radians(80), tile_size=6, dtype=torch.float64),
        "fisheye200": RayGrid.from_rays(fish_dirs, fish_valid, tile_size=6),
        "equirect360": RayGrid.from_rays(equirect_rays(16, 8), None, tile_size=6),
    }


def _scene(name):
    if name == "inside":  # the camera inside a large Gaussian, others around it
        means, quats, scales, opac, colors = random_scene(12, 5, around=True, scale_range=(0.1, 0.5))
        means[0], scales[0], opac[0] = torch.tensor([0.05, -0.02, 0.1]), torch.tensor([0.6, 0.4, 0.3]), 0.3
        return means, quats, scales, opac, colors
    return random_scene(40, 3, around=name != "beap", spread=1.0, scale_range=(0.1, 0.6))


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("grid_name,scene_name", [("beap", "beap"), ("fisheye200", "around"),
                                                   ("equirect360", "around"), ("fisheye200", "inside")])
def test_geometry_outputs_match_float64_reference(backend, grid_name, scene_name, request):
    if backend == "cpu":
        request.getfixturevalue("cpu_ops")
    grid = _grids()[grid_name]
    means, quats, scales, opac, colors = _scene(scene_name)
    viewmat = torch.eye(4, dtype=torch.float64)
    out = render(means, quats, scales, opac, colors, viewmat, grid, backend=backend)
    normals = render_normals(means, quats, scales, opac, viewmat, grid, backend=backend)
    dist, median, normal = reference(means.numpy(), quats.numpy(), scales.numpy(), opac.numpy(), grid.dirs.numpy(),
                                     grid.valid.numpy())
    hit = out.accumulation.reshape(-1) > 0
    assert int(hit.sum()) > grid.num_rays // 4  # the scene is visible
    tol = 1e-9
    assert np.abs(out.distance.reshape(-1).numpy() - dist).max() < tol
    assert np.abs(out.median_distance.reshape(-1).numpy() - median).max() < tol
    assert (median > 0).any()
    assert np.abs(normals.world.reshape(-1, 3).numpy() - normal).max() < 1e-7
    # camera frame: identity pose here; the rotation itself is checked in test_normal_camera_frame
    assert torch.allclose(normals.camera, normals.world)
    # z-depth: distance times the ray's z, defined in front of the image plane only, never NaN
    found = geometry_outputs(out, grid.dirs, normals, median=True)
    dz = grid.dirs[:, 2].numpy()
    defined = found["depth_defined"].reshape(-1).numpy()
    assert (defined == (hit.numpy() & (dz > 0))).all()
    assert np.abs(found["depth"].reshape(-1).numpy()[defined] - (dist * dz)[defined]).max() < tol
    for value in found.values():
        assert torch.isfinite(value.double()).all()
    if grid_name != "beap":
        assert (hit.numpy() & (dz <= 0)).any()  # rays at/behind 90 degrees were hit: the mask matters


def test_normal_camera_frame():
    """normal_camera is the world normal in camera axes: rendering the moved scene from a moved camera gives
    the same camera-frame normals, and world normals rotate with the scene."""
    grid = _grids()["beap"]
    means, quats, scales, opac, _ = _scene("beap")
    ident = render_normals(means, quats, scales, opac, torch.eye(4, dtype=torch.float64), grid, backend="torch")
    angle = 0.7
    rot = torch.tensor([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]],
                       dtype=torch.float64)
    q_rot = torch.tensor([math.cos(angle / 2), 0, math.sin(angle / 2), 0], dtype=torch.float64)
    w, x, y, z = quats.unbind(-1)  # q_rot * q (rotate each Gaussian by rot)
    a, b, c, d = q_rot
    moved_quats = torch.stack([a * w - b * x - c * y - d * z, a * x + b * w + c * z - d * y,
                               a * y - b * z + c * w + d * x, a * z + b * y - c * x + d * w], -1)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = rot.T  # world to camera: the camera turned with the scene
    moved = render_normals(means @ rot.T, moved_quats, scales, opac, viewmat, grid, backend="torch")
    assert torch.allclose(moved.camera, ident.camera, atol=1e-9)
    assert torch.allclose(moved.world, ident.world @ rot.T, atol=1e-9)


def test_pinhole_depth_is_splatfacto_z():
    """On a pinhole view of a wall of thin disks at z = 3 facing the camera, `depth` is the wall's z at every
    pixel (splatfacto's convention: camera-space z), while `distance` grows toward the corners as 3 / cos."""
    g = torch.linspace(-2.5, 2.5, 21, dtype=torch.float64)
    yy, xx = torch.meshgrid(g, g, indexing="ij")
    n = xx.numel()
    means = torch.stack([xx.reshape(-1), yy.reshape(-1), torch.full((n,), 3.0, dtype=torch.float64)], -1)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(n, 4).contiguous()
    scales = torch.tensor([[0.2, 0.2, 1e-4]], dtype=torch.float64).expand(n, 3).contiguous()
    opac = torch.full((n,), 0.9, dtype=torch.float64)
    size, f = 16, 10.0
    c = torch.arange(size, dtype=torch.float64) + 0.5 - size / 2
    v, u = torch.meshgrid(c, c, indexing="ij")
    grid = RayGrid.from_rays(torch.stack([u / f, v / f, torch.ones_like(u)], -1), None, tile_size=8)
    out = render(means, quats, scales, opac, torch.rand(n, 3, dtype=torch.float64), torch.eye(4, dtype=torch.float64),
                 grid, backend="torch")
    found = geometry_outputs(out, grid.dirs)
    assert found["depth_defined"].all()
    assert (found["depth"] - 3.0).abs().max() < 1e-6
    corner = found["distance"][0, 0, 0]
    assert abs(float(corner) - 3.0 / float(grid.dirs[0, 2])) < 1e-6 and float(corner) > 3.3


def test_viewer_list_hides_internal_outputs():
    outputs = {name: torch.zeros(2, 2, 1) for name in ("rgb", "distance", "depth", "normal", *INTERNAL_OUTPUTS)}
    assert set(viewer_outputs(outputs)) == {"rgb", "distance", "depth", "normal"}


def test_model_outputs_in_the_viewer_and_in_ns_eval():
    """The viewer's list (its render thread) names distance, depth, median_distance and both normals and no
    internal output; ns-eval's metrics name mean_distance and mean_depth apart, and its images include them."""
    import threading

    from test_nerfstudio_model import _viewer_cameras, make_model

    model = make_model(n=60)
    model.eval()
    camera = _viewer_cameras()["fisheye"]
    found = {}
    thread = threading.Thread(target=lambda: found.update(model.get_outputs_for_camera(camera)))
    thread.start()
    thread.join()
    assert {"rgb", "accumulation", "distance", "depth", "median_distance", "normal", "normal_camera"} <= set(found)
    assert not set(found) & set(INTERNAL_OUTPUTS)
    assert float(found["normal"].max()) > 0.5  # normals rendered where the Gaussians are seen
    outputs = model.get_outputs_for_camera(camera)  # main thread (ns-eval): internal outputs kept
    batch = {"image": torch.rand(int(camera.height), int(camera.width), 3)}
    metrics, images = model.get_image_metrics_and_images(outputs, batch)
    assert {"mean_distance", "mean_depth"} <= set(metrics) and metrics["mean_depth"] != metrics["mean_distance"]
    assert {"distance", "depth", "normal"} <= set(images)
