"""Association completeness: every (ray, Gaussian) pair with alpha >= 1/255 is in that ray's tile list.

Reference pairs come from float64 Mahalanobis geometry computed directly from Sigma^-1 (no whitening,
no PBF): min over the ray's half-line t >= 0 of (p - mu)^T Sigma^-1 (p - mu) (the half-line rule: the line's
minimum where its argmin t* > 0, the camera centre's value otherwise). Ray sets: pinhole-like BEAP, a 180 degree fisheye and a full 360
degree equirectangular camera; scenes with Gaussians in front, behind and around the camera.
"""

from __future__ import annotations

import math

import pytest
import torch

from conftest import equidistant_fisheye_rays, equirect_rays, random_scene
from geer_ns.render import RayGrid, associate, preprocess, quat_to_rotmat


def _reference_geometry(means_c, rot_v, scales, opac, dirs):
    """([R, N] alpha of the half-line rule, [R, N] t*, [N] camera inside the alpha = 1/255 ellipsoid)."""
    sigma_inv = rot_v @ torch.diag_embed(scales**-2.0) @ rot_v.transpose(-1, -2)
    a = -means_c  # camera centre minus mean
    aa = torch.einsum("ni,nij,nj->n", a, sigma_inv, a)
    ad = torch.einsum("ni,nij,rj->rn", a, sigma_inv, dirs)
    dd = torch.einsum("ri,nij,rj->rn", dirs, sigma_inv, dirs)
    d2 = (aa[None] - ad * ad / dd).clamp_min(0.0)
    t_star = -ad / dd
    q = torch.where(t_star > 0, d2, aa[None].expand_as(d2))
    alpha = (opac[None] * torch.exp(-0.5 * q)).clamp_max(0.99)
    inside = opac * torch.exp(-0.5 * aa) >= 1 / 255
    return alpha, t_star, inside


def _reference_pairs(means_c, rot_v, scales, opac, dirs):
    """[R, N] bool: alpha >= 1/255 under the half-line rule."""
    alpha, t_star, inside = _reference_geometry(means_c, rot_v, scales, opac, dirs)
    # What makes the PBF (bounds of the half-lines that meet the ellipsoid) complete: with the camera
    # outside the alpha = 1/255 ellipsoid, no ray whose line peaks behind the camera (t* <= 0) is visible.
    assert not bool(((alpha >= 1 / 255) & (t_star <= 0) & ~inside[None]).any())
    return alpha >= 1 / 255


def _check_complete(grid, scene, lambda_mode="opacity"):
    means, quats, scales, opac, colors = scene
    viewmat = torch.eye(4, dtype=means.dtype)
    pre = preprocess(means, quats, scales, opac, colors, viewmat, lambda_mode=lambda_mode)
    tiles = associate(pre.pbf, grid, pre.depth)
    rot_v = quat_to_rotmat(quats)
    ref = _reference_pairs(means, rot_v, scales, opac, grid.dirs)
    ref &= grid.valid[:, None]
    # Tile of every ray.
    ray_tile = torch.full((grid.num_rays,), -1, dtype=torch.long)
    for t in range(grid.num_tiles):
        r = grid.tile_rays[t]
        ray_tile[r[r >= 0]] = t
    member = torch.zeros(grid.num_tiles, means.shape[0], dtype=torch.bool)
    rows = torch.arange(grid.num_tiles)[:, None].expand_as(tiles.gaussians)
    ok = tiles.gaussians >= 0
    member[rows[ok], tiles.gaussians[ok]] = True
    rays, gs = torch.nonzero(ref, as_tuple=True)
    missed = ~member[ray_tile[rays], gs]
    return int(ref.sum()), int(missed.sum()), tiles


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_complete_beap(seed):
    scene = random_scene(400, seed, scale_range=(0.005, 0.5))
    grid = RayGrid.beap(96, 64, math.radians(150), math.radians(120), tile_size=16, dtype=torch.float64)
    n_pairs, missed, _ = _check_complete(grid, scene)
    assert n_pairs > 1000 and missed == 0


@pytest.mark.parametrize("seed", [0, 1])
def test_complete_fisheye_180(seed):
    scene = random_scene(500, seed, around=True, scale_range=(0.005, 0.6))
    dirs, valid = equidistant_fisheye_rays(96, 180.0)
    grid = RayGrid.from_rays(dirs, valid, tile_size=16)
    n_pairs, missed, tiles = _check_complete(grid, scene)
    assert n_pairs > 1000 and missed == 0
    assert not tiles.counts[~grid.tile_active].any()  # corner tiles outside the circle cost nothing


@pytest.mark.parametrize("seed", [0, 1])
def test_complete_equirect_360(seed):
    scene = random_scene(500, seed, around=True, scale_range=(0.005, 0.6))
    grid = RayGrid.from_rays(equirect_rays(128, 64), None, tile_size=16)
    n_pairs, missed, _ = _check_complete(grid, scene)
    assert n_pairs > 1000 and missed == 0


def test_paper_lambda_misses_opaque_tails():
    """With the paper's fixed lambda = 3, opaque Gaussians lose visible pairs; the opacity rule does not."""
    scene = random_scene(300, 5, scale_range=(0.01, 0.3), opacity_range=(0.9, 0.99))
    grid = RayGrid.beap(128, 128, math.radians(100), math.radians(100), tile_size=8, dtype=torch.float64)
    _, missed_paper, _ = _check_complete(grid, scene, "paper")
    _, missed_ours, _ = _check_complete(grid, scene, "opacity")
    assert missed_paper > 0 and missed_ours == 0


def test_tighter_than_paper_for_faint_gaussians():
    scene = random_scene(300, 6, scale_range=(0.01, 0.3), opacity_range=(0.01, 0.1))
    grid = RayGrid.beap(96, 96, math.radians(100), math.radians(100), tile_size=8, dtype=torch.float64)
    _, _, tiles_paper = _check_complete(grid, scene, "paper")
    _, missed, tiles_ours = _check_complete(grid, scene, "opacity")
    assert missed == 0 and tiles_ours.counts.sum() < 0.8 * tiles_paper.counts.sum()


def test_tile_lists_sorted_front_to_back():
    scene = random_scene(300, 3)
    means = scene[0]
    grid = RayGrid.beap(64, 64, math.radians(90), math.radians(90), tile_size=16, dtype=torch.float64)
    pre = preprocess(*scene, torch.eye(4, dtype=torch.float64))
    tiles = associate(pre.pbf, grid, pre.depth)
    for row in tiles.gaussians:
        ids = row[row >= 0]
        d = means[ids].norm(dim=-1)
        assert (d[1:] >= d[:-1]).all()


def test_complete_with_the_camera_inside_gaussians():
    """The camera inside or just outside many Gaussians' alpha = 1/255 ellipsoids, on a 360 degree camera:
    inside, the PBF is the full range and every direction sees the Gaussian (at least the camera centre's
    response); outside, rays with t* <= 0 stay below 1/255 (asserted in _reference_pairs), so the bounds of
    the half-lines through the ellipsoid are complete."""
    means, quats, scales, opac, colors = random_scene(300, 8, around=True, scale_range=(0.05, 0.8))
    means = means * 0.3  # crowd the camera
    grid = RayGrid.from_rays(equirect_rays(96, 48), None, tile_size=16)
    n_pairs, missed, _ = _check_complete(grid, (means, quats, scales, opac, colors))
    pre = preprocess(means, quats, scales, opac, colors, torch.eye(4, dtype=torch.float64))
    alpha, t_star, inside = _reference_geometry(means, quat_to_rotmat(quats), scales, opac, grid.dirs)
    assert missed == 0 and n_pairs > 1000
    assert int(inside.sum()) >= 5 and bool(((t_star <= 0) & ~inside[None] & (alpha > 0)).any())
    assert bool((alpha[:, inside] >= 1 / 255).all())  # inside: visible in every direction
    full = (pre.pbf.theta_lo == -math.pi) & (pre.pbf.theta_hi == math.pi)
    full &= (pre.pbf.phi_lo == -math.pi) & (pre.pbf.phi_hi == math.pi)
    assert bool(full[inside].all()) and torch.equal(pre.pbf.camera_inside[inside], inside[inside])


# ----------------------------------------------------------------------------------------------------------------
# The kernels' per-ray and per-warp cull (csrc/geer_ray.h ray_meets_pbf on RayGrid.ray_cull_bounds and
# warp_cull_bounds): a (ray, Gaussian) pair it skips must have alpha < 1/255 by the float64 reference.


def _check_cull_complete(grid, scene, dtype):
    from geer_ns.render.associate import _interval_pieces, _overlaps

    means, quats, scales, opac, colors = (t.to(dtype) for t in scene)
    viewmat = torch.eye(4, dtype=dtype)
    pre = preprocess(means, quats, scales, opac, colors, viewmat)
    theta_p = _interval_pieces(pre.pbf.theta_lo, pre.pbf.theta_hi, 1.0)
    phi_p = _interval_pieces(pre.pbf.phi_lo, pre.pbf.phi_hi, 1.0)
    s64 = [t.double() for t in scene]
    ref = _reference_pairs(s64[0], quat_to_rotmat(s64[1]), s64[2], s64[3], grid.dirs.double())
    ref &= grid.valid[:, None] & pre.pbf.alive[None]

    def meets(b):  # [K, 4] bounds -> [K, N] the PBF test of ray_meets_pbf
        return (_overlaps(b[:, 0, None], b[:, 1, None], tuple(p[None] for p in theta_p))
                & _overlaps(b[:, 2, None], b[:, 3, None], tuple(p[None] for p in phi_p)))

    ray_ok = meets(grid.ray_cull_bounds(dtype))
    # Each ray's warp: thread tid of tile t (grid.tile_rays[t, tid]) is in warp t * warps + tid // 32.
    warps = -(-grid.tile_rays.shape[1] // 32)
    warp_of = torch.full((grid.num_rays,), -1, dtype=torch.long)
    tid = torch.arange(grid.tile_rays.shape[1])
    for t in range(grid.num_tiles):
        r = grid.tile_rays[t]
        warp_of[r[r >= 0]] = t * warps + tid[r >= 0] // 32
    warp_ok = meets(grid.warp_cull_bounds(dtype))[warp_of]
    culled_visible = ref & ~(ray_ok & warp_ok)
    return int(ref.sum()), int(culled_visible.sum()), float(ray_ok[grid.valid].float().mean())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", ["beap", "fisheye_200", "equirect_360", "camera_inside"])
def test_ray_and_warp_cull_skip_only_invisible_pairs(case, dtype):
    if case == "beap":
        scene = random_scene(400, 0, scale_range=(0.005, 0.5))
        grid = RayGrid.beap(96, 64, math.radians(150), math.radians(120), tile_size=16, dtype=dtype)
    elif case == "fisheye_200":
        scene = random_scene(500, 1, around=True, scale_range=(0.005, 0.6))
        dirs, valid = equidistant_fisheye_rays(96, 200.0, dtype=dtype)
        grid = RayGrid.from_rays(dirs, valid, tile_size=16)
    elif case == "equirect_360":
        scene = random_scene(500, 2, around=True, scale_range=(0.005, 0.6))
        grid = RayGrid.from_rays(equirect_rays(128, 64, dtype=dtype), None, tile_size=16)
    else:
        means, quats, scales, opac, colors = random_scene(300, 8, around=True, scale_range=(0.05, 0.8))
        scene = (means * 0.3, quats, scales, opac, colors)
        grid = RayGrid.from_rays(equirect_rays(96, 48, dtype=dtype), None, tile_size=16)
    n_visible, culled_visible, meet_fraction = _check_cull_complete(grid, scene, dtype)
    assert n_visible > 1000 and culled_visible == 0
    # And the cull does skip: most (ray, Gaussian) pairs miss the PBF (fewer when the camera sits inside many
    # Gaussians, whose PBFs are the whole sphere).
    assert meet_fraction < (0.8 if case == "camera_inside" else 0.5)


# ----------------------------------------------------------------------------------------------------------------
# The cone test (geer_ns/render/cones.py, csrc/geer_associate.h cone_meets_tile): as complete at the fisheye rim as
# at the centre, and as tight.


def _rim_scene(n, seed):
    """Small anisotropic Gaussians whose means lie 60-115 degrees off the optical axis, 0.5-4 units away."""
    from conftest import random_quats

    gen = torch.Generator().manual_seed(seed)
    off = math.radians(60) + math.radians(55) * torch.rand(n, generator=gen, dtype=torch.float64)
    psi = 2 * math.pi * torch.rand(n, generator=gen, dtype=torch.float64)
    d = torch.stack([off.sin() * psi.cos(), off.sin() * psi.sin(), off.cos()], -1)
    means = d * (0.5 + 3.5 * torch.rand(n, 1, generator=gen, dtype=torch.float64))
    scales = torch.exp(math.log(0.004) + math.log(40.0) * torch.rand(n, 3, generator=gen, dtype=torch.float64))
    opac = 0.05 + 0.9 * torch.rand(n, generator=gen, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    return means, random_quats(n, gen, torch.float64), scales, opac, colors


def _tile_visible(grid, scene):
    """[T, N] bool: some valid ray of the tile has alpha >= 1/255 (float64 reference)."""
    means, quats, scales, opac, _ = scene
    ref = _reference_pairs(means, quat_to_rotmat(quats), scales, opac, grid.dirs.double()) & grid.valid[:, None]
    idx = grid.tile_rays.clamp_min(0)
    return (ref[idx] & (grid.tile_rays >= 0)[..., None]).any(1)


def _listed(tiles, grid, n):
    member = torch.zeros(grid.num_tiles, n, dtype=torch.bool)
    rows = torch.arange(grid.num_tiles)[:, None].expand_as(tiles.gaussians)
    ok = tiles.gaussians >= 0
    member[rows[ok], tiles.gaussians[ok]] = True
    return member


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("fov", [180.0, 200.0])
def test_cone_test_complete_and_tight_at_the_rim(fov, dtype):
    """Every (tile, Gaussian) pair with a visible ray stays listed, on rim tiles as on central ones; and at the rim the
    lists are about as close to that exact set as at the centre, where the box test alone lists several times more."""
    dirs, valid = equidistant_fisheye_rays(96, fov, dtype=dtype)
    grid = RayGrid.from_rays(dirs, valid, tile_size=8)
    around = random_scene(300, 4, around=True, scale_range=(0.004, 0.15))
    scene = [torch.cat(parts) for parts in zip(_rim_scene(500, 3), around)]
    visible = _tile_visible(grid, scene)
    pre = preprocess(*(t.to(dtype) for t in scene), torch.eye(4, dtype=dtype))
    listed = _listed(associate(pre.pbf, grid, pre.depth), grid, visible.shape[1])
    pre.pbf.cone = None
    boxed = _listed(associate(pre.pbf, grid, pre.depth), grid, visible.shape[1])
    assert int(visible.sum()) > 1000 and not bool((visible & ~listed).any())
    centre_ray = torch.nn.functional.normalize(grid.dirs.double()[grid.tile_rays.clamp_min(0)].sum(1), dim=-1)
    off_axis = torch.rad2deg(torch.acos(centre_ray[:, 2].clamp(-1, 1)))
    rim, centre = grid.tile_active & (off_axis > 70), grid.tile_active & (off_axis < 45)

    def excess(member, tiles):  # listed pairs per exact pair on those tiles
        return float(member[tiles].sum()) / float(visible[tiles].sum())

    assert excess(listed, rim) < 1.5 * excess(listed, centre) and excess(listed, rim) < 2.0
    assert excess(boxed, rim) > 1.5 * excess(listed, rim)
