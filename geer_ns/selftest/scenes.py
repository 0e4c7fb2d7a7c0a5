"""The self-test's scenes and cameras: seeded, made here from numbers alone (no data files), in float64.

Each scene is (means, quats, scales, opacities, colors) in the camera frame of an identity view (the camera at
the origin looking along +z, OpenCV axes), meant to reach the renderer's rare paths: the stress Gaussians
(disks, needles, the camera inside one, straddling z = 0, behind the camera, a scale below MIN_SCALE, non-unit
quaternions, opacities exactly 0 and 1), and `gap_scene`, the randomized case that found a float32
gradient gap in the shared headers (docs/cuda.md).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from geer_ns.render import RayGrid

F64 = torch.float64
Scene = tuple[Tensor, Tensor, Tensor, Tensor, Tensor]


def random_gaussians(n: int, seed: int, *, around: bool, scale_range=(0.02, 0.4), opacity_range=(0.05, 0.95)) -> Scene:
    """n random anisotropic Gaussians with RGB colors: in front of the camera (z ~ 4) or on all sides of it."""
    gen = torch.Generator().manual_seed(seed)
    if around:
        d = torch.randn(n, 3, generator=gen, dtype=F64)
        means = d / d.norm(dim=-1, keepdim=True) * (0.3 + 4.0 * torch.rand(n, 1, generator=gen, dtype=F64))
    else:
        means = torch.tensor([0.0, 0.0, 4.0], dtype=F64) + 1.5 * torch.randn(n, 3, generator=gen, dtype=F64)
    lo, hi = (math.log(s) for s in scale_range)
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=gen, dtype=F64))
    quats = torch.randn(n, 4, generator=gen, dtype=F64)
    opacities = opacity_range[0] + (opacity_range[1] - opacity_range[0]) * torch.rand(n, generator=gen, dtype=F64)
    return means, quats, scales, opacities, torch.rand(n, 3, generator=gen, dtype=F64)


def _rows(rows, seed: int) -> Scene:
    """((mean, scales, opacity), ...) -> a scene with random quaternions of norm ~3 and random colors."""
    gen = torch.Generator().manual_seed(seed)
    n = len(rows)
    means, scales, opac = (torch.tensor([r[k] for r in rows], dtype=F64) for k in range(3))
    return means, torch.randn(n, 4, generator=gen, dtype=F64) * 3.0, scales, opac, torch.rand(n, 3, generator=gen,
                                                                                                dtype=F64)


def stress_scene(seed: int = 3) -> Scene:
    """The degenerate Gaussians every renderer test meets (see the module docstring)."""
    return _rows([
        ((0.1, 0.0, 2.0), (1e-8, 0.3, 0.2), 0.8),      # disk
        ((0.1, 0.0, 2.0), (0.4, 1e-8, 1e-8), 0.8),     # needle
        ((0.05, -0.02, 0.1), (0.6, 0.5, 0.7), 0.8),    # the camera inside
        ((0.3, 0.1, 0.0), (0.3, 0.2, 0.4), 0.8),       # straddling z = 0
        ((0.0, 0.2, -2.0), (0.3, 0.3, 0.3), 0.8),      # behind the camera
        ((0.4, -0.3, 3.0), (1e-13, 0.2, 0.3), 0.9),    # a scale below MIN_SCALE
        ((-0.5, 0.5, 1.5), (0.2, 0.1, 0.05), 1.0),     # opacity exactly 1
        ((0.0, 0.0, 2.0), (0.3, 0.3, 0.3), 0.0),       # opacity exactly 0
        ((2.0, 0.1, 0.3), (0.5, 0.05, 0.05), 0.7),     # grazing the camera from the side
    ], seed)


def gap_scene(seed: int) -> Scene:
    """The float32 gap's case, randomized (docs/cuda.md, "the float32 gap"): from `seed`, maybe a Gaussian
    behind the camera, maybe the camera inside a huge (10-1000 m) opaque Gaussian, up to three Gaussians with
    scales of 1e-8 on random axes and opacities of exactly 1, 1/255 or 0.5, maybe one quaternion of norm
    ~1e-20, then 4-20 random Gaussians, some with opacities of exactly 1 and 1/255."""
    gen = torch.Generator().manual_seed(seed)
    u = lambda: float(torch.rand(1, generator=gen))  # noqa: E731
    rows = []
    if u() < 0.7:
        rows.append(((u() - 0.5, u() - 0.5, -1 - 2 * u()), (0.3, 0.2, 0.4), 0.8))
    if u() < 0.7:
        rows.append(((0.1 * (u() - 0.5), 0.1 * (u() - 0.5), 0.3 * u()), tuple(10 ** (1 + 2 * u()) for _ in range(3)), 1.0))
    for _ in range(int(u() * 4)):
        scales = [0.05 + 0.4 * u() for _ in range(3)]
        scales = [1e-8 if u() < 0.4 else v for v in scales]
        rows.append(((u() - 0.5, u() - 0.5, 1 + 3 * u()), tuple(scales), (1.0, 1 / 255, 0.5)[int(u() * 3)]))
    if not rows:
        rows.append(((0.0, 0.0, 2.0), (0.3, 0.3, 0.3), 1.0))
    means, quats, scales, opac, colors = _rows(rows, seed)
    if u() < 0.5:
        quats[int(u() * len(rows))] *= 1e-20
    rnd = random_gaussians(int(4 + u() * 16), seed + 99, around=u() < 0.3, scale_range=(0.05, 0.6))
    rnd[3][:3] = 1.0
    rnd[3][3:6] = 1 / 255
    return tuple(torch.cat([a, b]) for a, b in zip((means, quats, scales, opac, colors), rnd))  # type: ignore


def fisheye_rays(size: int, fov_deg: float, dtype=F64) -> tuple[Tensor, Tensor]:
    """Rays of an ideal equidistant fisheye (r = f angle) whose image circle spans fov_deg, and their mask."""
    f = (size / 2) / math.radians(fov_deg / 2)
    c = (torch.arange(size, dtype=dtype) + 0.5) - size / 2
    v, u = torch.meshgrid(c, c, indexing="ij")
    ang, psi = torch.sqrt(u * u + v * v) / f, torch.atan2(v, u)
    dirs = torch.stack([torch.sin(ang) * torch.cos(psi), torch.sin(ang) * torch.sin(psi), torch.cos(ang)], -1)
    return dirs, ang <= math.radians(fov_deg / 2)


def panorama_rays(width: int, height: int, dtype=F64) -> Tensor:
    """Rays of a full 360 x 180 degree equirectangular image (longitude 0 looks along +z, y down)."""
    lon = ((torch.arange(width, dtype=dtype) + 0.5) / width - 0.5) * 2 * math.pi
    lat = ((torch.arange(height, dtype=dtype) + 0.5) / height - 0.5) * math.pi
    la, lo = torch.meshgrid(lat, lon, indexing="ij")
    return torch.stack([torch.cos(la) * torch.sin(lo), torch.sin(la), torch.cos(la) * torch.cos(lo)], -1)


def camera(name: str, size: int, dtype=F64) -> RayGrid:
    """A self-test camera of about size x size rays: "beap" (120 x 90 degrees, 8-pixel tiles), "beap1" (the
    same with 1-pixel tiles), "fisheye200" (200 degrees, on its own pixel rays) or "panorama" (360 degrees)."""
    if name in ("beap", "beap1"):
        return RayGrid.beap(size, size * 3 // 4, math.radians(120), math.radians(90),
                            tile_size=8 if name == "beap" else 1, dtype=dtype)
    if name == "fisheye200":
        dirs, valid = fisheye_rays(size, 200.0, dtype)
        return RayGrid.from_rays(dirs, valid, tile_size=8)
    if name == "panorama":
        return RayGrid.from_rays(panorama_rays(size, size // 2, dtype), None, tile_size=8)
    raise ValueError(f"unknown self-test camera {name!r}")
