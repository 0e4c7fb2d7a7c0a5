"""The half-line rule near and inside Gaussians: every pair responds with the peak of sigma G on the ray as
travelled (t >= 0), so images are continuous as the camera moves through a Gaussian, and every clamp has
one gradient that both backends (the PyTorch twin, autograd; geer_ray.h compiled for the CPU, analytic)
agree on.

References: the half-line minimum of the Mahalanobis distance found numerically in float64 from Sigma^-1
(dense samples along t >= 0, then a bounded refinement; no whitening, no closed form); central finite
differences of the float64 renders.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch
from scipy import optimize

from conftest import equirect_rays, random_quats
from geer_ns.render import RayGrid, canonical_ray_response, pbf_lambda_sq, preprocess, quat_to_rotmat, render

F64 = torch.float64
FIELDS = ("means", "quats", "scales", "opacities", "colors")


@pytest.fixture(scope="module")
def backends():
    """The twin always; the CPU build of csrc when it builds here."""
    pytest.importorskip("ninja")
    from geer_ns.render import cuda_backend

    cuda_backend.load_cpu_ops()
    return ("torch", "cpu")


def _half_line_reference(mean, rot, scales, opacity, d):
    """(alpha, argmin t) of sigma exp(-min_{t >= 0} q(t) / 2), q(t) = (t d - mu)^T Sigma^-1 (t d - mu), float64."""
    sigma_inv = rot @ np.diag(scales**-2.0) @ rot.T
    q = lambda t: (t * d - mean) @ sigma_inv @ (t * d - mean)  # noqa: E731
    reach = np.linalg.norm(mean) + 12 * scales.max()
    ts = np.linspace(0.0, reach, 4001)
    x = ts[:, None] * d[None] - mean[None]
    k = int(np.argmin(np.einsum("ti,ij,tj->t", x, sigma_inv, x)))
    best = (q(ts[k]), ts[k])
    # Refine between the neighbouring samples; the end point t = 0 stays a candidate (the bounded search
    # never evaluates its bounds).
    lo, hi = ts[max(k - 1, 0)], ts[min(k + 1, len(ts) - 1)]
    res = optimize.minimize_scalar(q, bounds=(lo, hi), method="bounded", options={"xatol": 1e-14})
    best = min(best, (res.fun, res.x))
    alpha = min(0.99, opacity * math.exp(-0.5 * best[0]))
    return alpha, best[1]


def _near_camera_case(seed):
    """One Gaussian whose canonical distance to the camera is 0..4 (camera inside, on or near its surface),
    and rays in every direction."""
    rng = np.random.default_rng(seed)
    scales = np.exp(rng.uniform(math.log(0.05), math.log(0.6), size=3))
    quat = random_quats(1, torch.Generator().manual_seed(seed))[0]
    rot = quat_to_rotmat(quat).numpy()
    u = rng.normal(size=3)
    mean = -(rot * scales) @ (u / np.linalg.norm(u) * rng.uniform(0.0, 4.0))  # camera at R S u from the mean
    dirs = rng.normal(size=(256, 3))
    dirs[:96] = mean[None] + ((rot * scales) @ rng.normal(size=(3, 96))).T  # aimed through the Gaussian
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return mean, quat.numpy(), rot, scales, dirs


@functools.lru_cache(maxsize=None)
def _reference(seed):
    """(alpha [R], argmin t [R]) of case `seed` for opacity 0.9."""
    mean, _quat, rot, scales, dirs = _near_camera_case(seed)
    ref = [_half_line_reference(mean, rot, scales, 0.9, d) for d in dirs]
    return torch.tensor([a for a, _ in ref], dtype=F64), torch.tensor([t for _, t in ref], dtype=F64)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_half_line_matches_sampled_reference(backends, seed, dtype):
    mean, quat, rot, scales, dirs = _near_camera_case(seed)
    opacity = 0.9
    alpha_ref, t_ref = _reference(seed)
    on_threshold = (alpha_ref - 1 / 255).abs() < 1e-6
    expected = torch.where(alpha_ref >= 1 / 255, alpha_ref, torch.zeros_like(alpha_ref))
    t = lambda a: torch.as_tensor(np.asarray(a)).to(dtype)  # noqa: E731
    grid = RayGrid.from_rays(t(dirs).reshape(16, 16, 3), None, tile_size=8)
    for backend in backends:
        out = render(t(mean)[None], t(quat)[None], t(scales)[None], t([opacity]), t([[0.5, 0.5, 0.5]]),
                     torch.eye(4, dtype=dtype), grid, backend=backend)
        acc, depth = out.accumulation.reshape(-1).double(), out.depth.reshape(-1).double()
        tol = 1e-9 if dtype == F64 else 1e-5
        err = (acc - expected).abs()[~on_threshold]
        assert float(err.max()) <= tol, (backend, float(err.max()))
        seen = (expected > 0) & ~on_threshold
        depth_err = (depth - t_ref).abs()[seen] / t_ref[seen].clamp_min(1.0)
        assert float(depth_err.max()) <= (1e-6 if dtype == F64 else 1e-4), backend


def test_reference_cases_cover_inside_and_behind(backends):
    """The cases above really contain the camera inside Gaussians and rays whose peak is behind it."""
    n_behind = n_front = 0
    for seed in range(6):
        alpha, t = _reference(seed)
        n_behind += int(((t == 0.0) & (alpha >= 1 / 255)).sum())
        n_front += int(((t > 0.0) & (alpha >= 1 / 255)).sum())
    assert n_behind > 100 and n_front > 100


# ------------------------------------------------------------------------------------------ continuity
def _sweep_scene(crossing: str):
    """A large Gaussian A near the camera, two others; the camera path crosses, at k = 0 in steps of 1e-6
    along `step_dir`, A's alpha = 1/255 surface ("alpha"), the slightly larger surface where its PBF switches
    to the full range ("pbf"), or its mean ("mean")."""
    means = torch.tensor([[0.1, -0.05, 0.4], [0.3, 0.2, 2.0], [-0.6, 0.1, -1.5]], dtype=F64)
    quats = torch.tensor([[0.9, 0.2, -0.3, 0.1], [1.0, 0.0, 0.0, 0.0], [0.7, 0.1, 0.5, -0.2]], dtype=F64)
    scales = torch.tensor([[0.35, 0.2, 0.25], [0.3, 0.3, 0.2], [0.4, 0.3, 0.3]], dtype=F64)
    opac = torch.tensor([0.9, 0.7, 0.8], dtype=F64)
    colors = torch.tensor([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 0.9]], dtype=F64)
    rot = quat_to_rotmat(quats[0])
    step_dir = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 1.0], dtype=F64), dim=0)
    if crossing == "mean":
        cross = means[0].clone()
    else:
        # The surface point along step_dir from the mean: mu + s u with (s u)^T Sigma^-1 (s u) = level.
        q_max = 2 * math.log(255 * float(opac[0]))
        if crossing == "pbf":
            q_max = float(pbf_lambda_sq(opac[:1])[0][0])
        u = -step_dir
        m = float(u @ rot @ torch.diag(scales[0] ** -2.0) @ rot.T @ u)
        cross = means[0] + math.sqrt(q_max / m) * u
    return (means, quats, scales, opac, colors), cross, step_dir


def _camera_at(pos):
    vm = torch.eye(4, dtype=F64)
    vm[:3, 3] = -pos
    return vm


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("crossing", ["alpha", "pbf", "mean"])
def test_continuity_camera_through_a_gaussian(backends, crossing, dtype):
    """Moving the camera in 1e-6 steps through a Gaussian's surface (and through its mean) changes no pixel by
    more than the 1/255 skip threshold plus O(step), with either backend."""
    scene, cross, step_dir = _sweep_scene(crossing)
    render_scene = [t.to(dtype) for t in scene]
    grid = RayGrid.from_rays(equirect_rays(32, 16, dtype=dtype), None, tile_size=8)  # every direction
    step = 1e-6
    for backend in backends:
        frames, levels = [], []
        for k in range(-20, 21):
            vm = _camera_at(cross + k * step * step_dir)
            out = render(*render_scene, vm.to(dtype), grid, backend=backend, background=torch.zeros(3, dtype=dtype))
            frames.append(torch.cat([out.rgb, out.accumulation], -1))
            levels.append((float(preprocess(*scene, vm).o_u[0].square().sum()), bool(out.pbf.camera_inside[0])))
        jumps = torch.stack([(b - a).abs().max() for a, b in zip(frames, frames[1:])])
        assert float(jumps.max()) <= 1 / 255 + 1e3 * step, (backend, float(jumps.max()))
        q_max = 2 * math.log(255 * float(scene[3][0]))
        if crossing == "alpha":  # the camera really crossed the surface
            assert (levels[0][0] <= q_max) != (levels[-1][0] <= q_max)
        if crossing == "pbf":
            assert levels[0][1] != levels[-1][1]
    # What the old camera-inside rule switched on at the crossing: rays whose whole-line response is large
    # but whose peak lies behind the camera (the half-line rule gives them ~1/255 here).
    pre = preprocess(*scene, _camera_at(cross))
    d2, t_star = canonical_ray_response(pre.o_u[:1], pre.whiten[:1], grid.dirs.double())
    whole_line = 0.9 * torch.exp(-0.5 * d2[:, 0])
    if crossing != "mean":  # (at the mean t* = 0 on every ray: nothing lies behind)
        assert float(whole_line[t_star[:, 0] < 0].max()) > 0.3


# ------------------------------------------------------------------------------------------ gradients
def _loss_fn(grid, vm, backend, seed=0):
    gen = torch.Generator().manual_seed(seed)
    wr = torch.randn(grid.height, grid.width, 3, generator=gen, dtype=F64)
    wd = torch.randn(grid.height, grid.width, 1, generator=gen, dtype=F64)
    wa = torch.randn(grid.height, grid.width, 1, generator=gen, dtype=F64)

    def loss(*scene):
        out = render(*scene, vm, grid, backend=backend, background=torch.full((3,), 0.3, dtype=F64))
        return (wr * out.rgb).sum() + 0.1 * (wd * out.depth).sum() + (wa * out.accumulation).sum()

    return loss


@pytest.mark.parametrize("side", [-1.0, 1.0])
def test_gradients_match_finite_differences_on_both_sides_of_the_surface(backends, side):
    """1e-3 inside (side -1) and outside (+1) a Gaussian's alpha = 1/255 surface: analytic gradients of
    both backends against central differences of the float64 twin."""
    scene, cross, step_dir = _sweep_scene("alpha")
    vm = _camera_at(cross - side * 1e-3 * step_dir)  # step_dir points into the Gaussian
    grid = RayGrid.from_rays(equirect_rays(24, 12), None, tile_size=6)
    level = float(preprocess(*scene, vm).o_u[0].square().sum())
    assert (level <= 2 * math.log(255 * float(scene[3][0]))) == (side < 0)
    fd_loss = _loss_fn(grid, vm, "torch")
    eps = 1e-6
    fd = []
    with torch.no_grad():
        for i, x in enumerate(scene):
            g = torch.zeros_like(x)
            for j in range(x.numel()):
                plus, minus = [t.clone() for t in scene], [t.clone() for t in scene]
                plus[i].view(-1)[j] += eps
                minus[i].view(-1)[j] -= eps
                g.view(-1)[j] = (fd_loss(*plus) - fd_loss(*minus)) / (2 * eps)
            fd.append(g)
    for backend in backends:
        leaves = [t.clone().requires_grad_(True) for t in scene]
        _loss_fn(grid, vm, backend)(*leaves).backward()
        for name, leaf, ref in zip(FIELDS, leaves, fd):
            err = float((leaf.grad - ref).norm() / ref.norm())
            assert err <= 1e-5, (backend, name, err)


def _clamp_scene():
    """Gaussians placed exactly on every clamp, rays through them:
    0: mean exactly at the camera (o_u = 0, t* = 0 on every ray);
    1: alpha exactly 0.99 on the +z ray (sigma = 0.99, ray through the centre: D^2 = 0 exactly);
    2: t* = 0 exactly on the +x ray (axis-aligned, mean on the z axis: o_u . d_u = 0);
    3: alpha exactly 1/255 on the -y ray (sigma = 1/255: q = q_max = 0 exactly);
    4-5: two alpha-0.99 Gaussians on the -x ray, then 6: the ray stops near T = 1e-4."""
    means = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0], [0.0, 0.0, 0.5], [0.0, -3.0, 0.0],
                          [-1.0, 0.0, 0.0], [-2.0, 0.0, 0.0], [-3.0, 0.0, 0.0]], dtype=F64)
    quats = torch.tensor([[0.8, 0.3, -0.2, 0.4]] + [[1.0, 0.0, 0.0, 0.0]] * 6, dtype=F64)
    scales = torch.tensor([[0.2, 0.3, 0.25], [0.3, 0.3, 0.3], [0.3, 0.2, 0.5], [0.2, 0.2, 0.2],
                           [0.1, 0.1, 0.1], [0.1, 0.1, 0.1], [0.1, 0.1, 0.1]], dtype=F64)
    opac = torch.tensor([0.6, 0.99, 0.8, 1 / 255, 0.995, 0.995, 0.9], dtype=F64)
    colors = torch.rand(7, 3, generator=torch.Generator().manual_seed(4), dtype=F64)
    axes = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=F64)
    other = torch.nn.functional.normalize(torch.randn(12, 3, generator=torch.Generator().manual_seed(5),
                                                      dtype=F64), dim=-1)
    grid = RayGrid.from_rays(torch.cat([axes, other]).reshape(4, 4, 3), None, tile_size=4)
    return (means, quats, scales, opac, colors), grid


def test_one_gradient_at_every_clamp(backends):
    scene, grid = _clamp_scene()
    vm = torch.eye(4, dtype=F64)
    pre = preprocess(*scene, vm)
    d2, t_star = canonical_ray_response(pre.o_u, pre.whiten, grid.dirs)
    assert float(pre.o_u[0].abs().max()) == 0.0 and bool((t_star[:, 0] == 0).all())
    assert float(d2[0, 1]) == 0.0 and float(t_star[1, 2]) == 0.0
    grads = {}
    for backend in backends:
        leaves = [t.clone().requires_grad_(True) for t in scene]
        out = render(*leaves, vm, grid, backend=backend)
        assert float(out.accumulation[0, 0, 0].detach()) > 0.99  # the capped pair is blended
        _loss_fn(grid, vm, backend, seed=3)(*leaves).backward()
        grads[backend] = [t.grad for t in leaves]
        # Mean at the camera: q = |o_u|^2 has gradient 2 o_u = 0 and depth max(t*, 0) takes 0 at t* = 0.
        assert float(leaves[0].grad[0].abs().max()) == 0.0
        assert float(leaves[3].grad[0].abs()) > 0  # ...while it is seen and its opacity matters
    if len(grads) == 2:
        for name, a, b in zip(FIELDS, grads["torch"], grads["cpu"]):
            assert float((a - b).norm()) <= 1e-10 * max(1.0, float(a.norm())), name
