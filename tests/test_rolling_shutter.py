"""Rolling shutter: every ray at its own pose, rendered exactly by both compiled paths and the twin.

The reference is independent of the renderer: each pixel's pose from scipy's Slerp of the start and end rotations
and a linear camera centre, the Gaussian's density along the world-space ray minimised over t >= 0 with its
world covariance inverted directly (no canonical frame, no cross product), every Gaussian against every ray,
composited in the view's order (distance from the mid-readout camera centre) with the renderer's thresholds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from geer_ns.cameras import EquidistantCamera, PinholeCamera
from geer_ns.cameras.shutter import interpolate_poses, ray_times, rolling_rays, sensor_times, so3_exp, so3_log
from geer_ns.render import RayGrid, render
from geer_ns.render.moving import MovingRays, motion_scales
from geer_ns.render.transforms import quat_to_rotmat

SIZE = (20, 24)  # height, width: two tiles of 16 across, two down (one overhanging)


def _cameras(size=SIZE):
    h, w = size
    fish180 = EquidistantCamera(w, h, (w / 2) / (math.pi / 2), (w / 2) / (math.pi / 2), w / 2, h / 2)
    fish200 = EquidistantCamera(w, h, (w / 2) / math.radians(100), (w / 2) / math.radians(100), w / 2, h / 2)
    pinhole = PinholeCamera(w, h, 14.0, 14.0, w / 2, h / 2)
    return {"fisheye180": fish180, "fisheye200": fish200, "pinhole": pinhole}


def _look_at(centre, yaw_deg, pitch_deg):
    """camera-to-world [4,4] float64 (OpenCV axes) at `centre`, turned by yaw about world y, pitch about x."""
    r = Rotation.from_euler("yx", [yaw_deg, pitch_deg], degrees=True).as_matrix()
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = r, centre
    return torch.tensor(c2w)


def _scene(seed: int, n: int = 48):
    """Gaussians around the camera path, most in front, some beside and behind (the 200-degree view sees them)."""
    g = torch.Generator().manual_seed(seed)
    direction = torch.randn(n, 3, generator=g, dtype=torch.float64)
    direction[: 3 * n // 4, 2] = direction[: 3 * n // 4, 2].abs() + 0.6
    means = direction / direction.norm(dim=-1, keepdim=True) * (1.5 + 2.0 * torch.rand(n, 1, generator=g,
                                                                                       dtype=torch.float64))
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    scales = 0.05 + 0.35 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    scales[:4, 0] = 0.01  # a few flat ones
    opacities = 0.2 + 0.75 * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return means, quats, scales, opacities, colors


def _poses():
    """A fast turn and a step during the readout: 9 degrees of yaw, 3 of pitch, 0.25 units sideways and forward."""
    return _look_at([0.0, 0.0, 0.0], -4.5, -1.5), _look_at([0.2, 0.05, 0.15], 4.5, 1.5)


def _grid(camera, tile_size=16):
    dirs, valid = camera.pixel_rays(torch.float64)
    return RayGrid.from_rays(dirs, valid, tile_size=tile_size)


def _times(camera, grid, readout="top-to-bottom"):
    return ray_times(camera, grid.dirs, readout)


def oracle(means, quats, scales, opacities, colors, grid, times, c2w0, c2w1):
    """[R, 3] float64 rgb of every valid ray, per the module docstring (numpy, scipy)."""
    key = Rotation.from_matrix(np.stack([c2w0[:3, :3].numpy(), c2w1[:3, :3].numpy()]))
    slerp = Slerp([0.0, 1.0], key)
    c0, c1 = c2w0[:3, 3].numpy(), c2w1[:3, 3].numpy()
    t = times.numpy()
    rot = slerp(t).as_matrix()
    origin = (1 - t)[:, None] * c0 + t[:, None] * c1
    world_dirs = np.einsum("rij,rj->ri", rot, grid.dirs.numpy())
    c_mid = 0.5 * (c0 + c1)
    r = quat_to_rotmat(quats).numpy()
    cov = np.einsum("nij,nj,nkj->nik", r, scales.numpy() ** 2, r)
    prec = np.linalg.inv(cov)
    mu, sig, col = means.numpy(), opacities.numpy(), colors.numpy()
    order = np.argsort(np.linalg.norm(mu - c_mid, axis=1), kind="stable")
    out = np.zeros((grid.num_rays, 3))
    for ray in np.flatnonzero(grid.valid.numpy()):
        o, d = origin[ray], world_dirs[ray]
        trans, rgb = 1.0, np.zeros(3)
        for i in order:
            e = o - mu[i]
            a, b, c = d @ prec[i] @ d, d @ prec[i] @ e, e @ prec[i] @ e
            ts = max(-b / a, 0.0)
            q = a * ts * ts + 2 * b * ts + c
            raw = sig[i] * math.exp(-0.5 * q)
            if raw < 1.0 / 255.0:
                continue
            alpha = min(raw, 0.99)
            after = trans * (1 - alpha)
            if after < 1e-4:
                break
            rgb += trans * alpha * col[i]
            trans = after
        out[ray] = rgb
    return torch.tensor(out)


def _render(scene, grid, times, c2w0, c2w1, backend, dtype=torch.float64, widen=True):
    viewmat, origins, dirs, offset = rolling_rays(grid.dirs, times, c2w0, c2w1)
    motion = MovingRays(origins.to(dtype), dirs.to(dtype), offset if widen else 0.0)
    means, quats, scales, opacities, colors = (t.to(dtype) for t in scene)
    out = render(means, quats, scales, opacities, colors, viewmat, grid.to("cpu"), backend=backend, motion=motion)
    return out.rgb.reshape(-1, 3).double(), out


@pytest.mark.parametrize("camera_name", ["fisheye180", "fisheye200", "pinhole"])
@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_rolling_shutter_renders_match_the_per_ray_oracle(camera_name, backend):
    camera = _cameras()[camera_name]
    grid = _grid(camera)
    scene = _scene(seed=3)
    c2w0, c2w1 = _poses()
    times = _times(camera, grid)
    ref = oracle(*scene, grid, times, c2w0, c2w1)
    assert ref.abs().max() > 0.2  # the view sees the scene
    rgb, _ = _render(scene, grid, times, c2w0, c2w1, backend)
    assert (rgb - ref).abs().max() <= 1e-9
    rgb32, _ = _render(scene, grid, times, c2w0, c2w1, backend, dtype=torch.float32)
    assert (rgb32 - ref).abs().max() <= 2e-4


def test_association_with_motion_is_complete_and_needs_its_widening(monkeypatch):
    """Every pair the oracle blends is in its tile's list; without widening the bounds by the motion (offset 0,
    which MovingRays.check refuses: switched off here), pairs are missed and the image is wrong (the check can
    fail)."""
    camera = _cameras((40, 40))["fisheye180"]
    grid = _grid(camera, tile_size=4)
    means, quats, scales, opacities, colors = _scene(seed=5, n=120)
    scene = (means, quats, scales * 0.15, opacities, colors)  # small Gaussians: the motion moves them by their size
    c2w0, c2w1 = _poses()
    times = _times(camera, grid)
    ref = oracle(*scene, grid, times, c2w0, c2w1)
    for backend in ("torch", "cpu"):
        rgb, _ = _render(scene, grid, times, c2w0, c2w1, backend)
        assert (rgb - ref).abs().max() <= 1e-9, backend
        with monkeypatch.context() as m:
            m.setattr(MovingRays, "check", lambda *args: None)
            narrow, _ = _render(scene, grid, times, c2w0, c2w1, backend, widen=False)
        assert (narrow - ref).abs().max() > 1e-3, backend


def test_motion_scales_contain_the_moved_ellipsoid():
    """Sampled points of a lambda-ellipsoid moved by up to `offset` stay inside the widened ellipsoid (float64,
    random Gaussians, thin ones included, and offsets)."""
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        scales = torch.rand(3, generator=g, dtype=torch.float64) ** 3 + 1e-3
        quat = torch.randn(4, generator=g, dtype=torch.float64)
        rot = quat_to_rotmat((quat / quat.norm())[None])[0]
        lam2 = torch.tensor([9.0], dtype=torch.float64)
        offset = float(torch.rand(1, generator=g)) * 0.5
        wide = motion_scales(scales[None], lam2, offset)[0]
        unit = torch.randn(4000, 3, generator=g, dtype=torch.float64)
        unit = unit / unit.norm(dim=-1, keepdim=True)
        points = (unit * scales * 3.0) @ rot.T
        shift = torch.randn(4000, 3, generator=g, dtype=torch.float64)
        shift = shift / shift.norm(dim=-1, keepdim=True) * offset * torch.rand(4000, 1, generator=g,
                                                                               dtype=torch.float64) ** 0.1
        local = (points + shift) @ rot / (wide * 3.0)
        assert (local * local).sum(-1).max() <= 1.0 + 1e-12
        assert (wide >= scales).all()
    still = motion_scales(scales[None], lam2, 0.0)[0]
    assert torch.allclose(still, scales, rtol=1e-15, atol=0)


def test_pose_interpolation_matches_scipy_slerp():
    c2w0, c2w1 = _look_at([0, 0, 0], -30, 10), _look_at([1, 2, 3], 50, -20)
    times = torch.linspace(0, 1, 11, dtype=torch.float64)
    rot, centre = interpolate_poses(c2w0, c2w1, times)
    key = Rotation.from_matrix(np.stack([c2w0[:3, :3].numpy(), c2w1[:3, :3].numpy()]))
    assert np.abs(rot.numpy() - Slerp([0.0, 1.0], key)(times.numpy()).as_matrix()).max() < 1e-12
    assert torch.allclose(centre[5], torch.tensor([0.5, 1.0, 1.5], dtype=torch.float64))
    omega = torch.tensor([[0.3, -0.2, 0.1], [1e-9, 0, 0], [0, 0, 3.1]], dtype=torch.float64)
    assert torch.allclose(so3_log(so3_exp(omega)), omega, atol=1e-12)


def test_sensor_times_follow_the_readout():
    pixels = torch.tensor([[0.5, 0.5], [23.5, 19.5], [12.0, 10.0]], dtype=torch.float64)
    assert sensor_times(pixels, 24, 20, "top-to-bottom").tolist() == pytest.approx([0.0, 1.0, 9.5 / 19])
    assert sensor_times(pixels, 24, 20, "bottom-to-top").tolist() == pytest.approx([1.0, 0.0, 1 - 9.5 / 19])
    assert sensor_times(pixels, 24, 20, "left-to-right").tolist() == pytest.approx([0.0, 1.0, 11.5 / 23])
    assert sensor_times(pixels, 24, 20, "right-to-left").tolist() == pytest.approx([1.0, 0.0, 1 - 11.5 / 23])
    with pytest.raises(ValueError, match="readout: expected one of"):
        sensor_times(pixels, 24, 20, "sideways")


def _tangent_pose(c2w, xi):
    """c2w moved by xi [6]: rotation exp(xi[:3]) applied on the world side, centre + xi[3:]."""
    out = c2w.clone()
    out[:3, :3] = so3_exp(xi[:3]) @ c2w[:3, :3]
    out[:3, 3] = c2w[:3, 3] + xi[3:]
    return out


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_gradients_reach_both_poses_and_match_central_differences(backend):
    camera = _cameras()["fisheye180"]
    grid = _grid(camera)
    scene = _scene(seed=7, n=24)
    c2w0, c2w1 = _poses()
    times = _times(camera, grid)
    weights = torch.rand(grid.num_rays, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    def loss(xi0, xi1):
        rgb, _ = _render(scene, grid, times, _tangent_pose(c2w0, xi0), _tangent_pose(c2w1, xi1), backend)
        return (rgb * weights).sum()

    xi0 = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    xi1 = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    loss(xi0, xi1).backward()
    eps = 1e-6
    for which, grad in ((0, xi0.grad), (1, xi1.grad)):
        assert grad.abs().max() > 1e-3
        numeric = torch.zeros(6, dtype=torch.float64)
        for k in range(6):
            step = torch.zeros(6, dtype=torch.float64)
            step[k] = eps
            zero = torch.zeros(6, dtype=torch.float64)
            plus = loss(step, zero) if which == 0 else loss(zero, step)
            minus = loss(-step, zero) if which == 0 else loss(zero, -step)
            numeric[k] = (plus - minus) / (2 * eps)
        assert torch.allclose(grad, numeric, rtol=1e-4, atol=1e-6), (which, grad, numeric)


def test_compiled_gradients_equal_the_twin():
    """Gaussian and ray gradients of the CPU build against the PyTorch renderer, float64, rolling shutter."""
    camera = _cameras()["fisheye200"]
    grid = _grid(camera)
    c2w0, c2w1 = _poses()
    times = _times(camera, grid)
    weights = torch.rand(grid.num_rays, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    grads = {}
    for backend in ("cpu", "torch"):
        scene = [t.clone().requires_grad_(True) for t in _scene(seed=11)]
        viewmat, origins, dirs, offset = rolling_rays(grid.dirs, times, c2w0, c2w1)
        origins, dirs = origins.clone().requires_grad_(True), dirs.clone().requires_grad_(True)
        out = render(*scene, viewmat, grid, backend=backend, motion=MovingRays(origins, dirs, offset))
        (out.rgb.reshape(-1, 3) * weights).sum().backward()
        grads[backend] = [t.grad for t in scene] + [origins.grad, dirs.grad]
    for ours, ref in zip(grads["cpu"], grads["torch"]):
        assert ref.abs().max() > 0
        assert (ours - ref).abs().max() <= 1e-9 * max(1.0, float(ref.abs().max()))


def test_bad_motion_is_a_clear_error():
    camera = _cameras()["pinhole"]
    grid = _grid(camera)
    means, quats, scales, opacities, colors = _scene(seed=1, n=4)
    bad = MovingRays(torch.zeros(5, 3, dtype=torch.float64), grid.dirs, 0.0)
    with pytest.raises(ValueError, match=r"motion.origins: expected \[480, 3\]"):
        render(means, quats, scales, opacities, colors, torch.eye(4, dtype=torch.float64), grid, motion=bad)
    nan = MovingRays(torch.zeros(480, 3, dtype=torch.float64), grid.dirs, float("nan"))
    with pytest.raises(ValueError, match="motion.offset: expected a finite value"):
        render(means, quats, scales, opacities, colors, torch.eye(4, dtype=torch.float64), grid, motion=nan)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_rolling_shutter_one_ray_per_thread_path_gives_the_cpu_paths_bits(monkeypatch, dtype):
    """The kernels' path (one ray per thread, warp cull, every lane of the blended prefix; render_*_gpu_path) and
    the CPU's one-ray path give the packs path's bits with per-ray origins too: images and every gradient, the
    rays' origins and directions included."""
    from geer_ns.render.extensions import load_cpu_ops

    ops = load_cpu_ops()
    camera = _cameras((40, 40))["fisheye200"]
    grid = _grid(camera)
    c2w0, c2w1 = _poses()
    times = _times(camera, grid)

    def run():
        scene = [t.to(dtype).requires_grad_(True) for t in _scene(seed=13, n=80)]
        viewmat, origins, dirs, offset = rolling_rays(grid.dirs, times, c2w0, c2w1)
        origins = origins.to(dtype).requires_grad_(True)
        dirs = dirs.to(dtype).requires_grad_(True)
        out = render(*scene, viewmat, grid.to("cpu"), backend="cpu", motion=MovingRays(origins, dirs, offset))
        weights = torch.rand(out.rgb.shape, generator=torch.Generator().manual_seed(3), dtype=dtype)
        ((out.rgb * weights).sum() + out.depth.sum()).backward()
        return [out.rgb.detach(), out.depth.detach(), out.max_weight] + [t.grad for t in scene + [origins, dirs]]

    packs = run()
    monkeypatch.setattr(ops, "render_forward", ops.render_forward_gpu_path)
    monkeypatch.setattr(ops, "render_backward", ops.render_backward_gpu_path)
    gpu_path = run()
    monkeypatch.setattr(ops, "render_backward", ops.render_backward_one_ray)
    one_ray = run()
    assert float(packs[-2].abs().max()) > 0 and float(packs[-1].abs().max()) > 0
    for a, b, c in zip(packs, gpu_path, one_ray):
        assert torch.equal(a, b) and torch.equal(a, c)


def test_ray_times_come_from_the_sensor_for_any_grid():
    """A ray's time is its sensor pixel's: native pixel rays read their own rows, and a BEAP cell's direction reads
    the row it projects to."""
    from geer_ns.data.views import beap_view

    camera = _cameras((40, 40))["fisheye180"]
    grid = _grid(camera)
    pixels = camera.pixel_centers(torch.float64).reshape(-1, 2)
    valid = grid.valid
    native = ray_times(camera, grid.dirs, "top-to-bottom")
    assert torch.allclose(native[valid], sensor_times(pixels, 40, 40, "top-to-bottom")[valid], atol=1e-9)
    beap = beap_view(camera).rays
    times = ray_times(camera, beap.dirs.double(), "left-to-right")
    projected, ok = camera.project(beap.dirs.double())
    assert torch.allclose(times[ok], ((projected[ok, 0] - 0.5) / 39).clamp(0, 1), atol=1e-9)
