"""BEAP grid construction and resampling (3DGEER Sec. 3.3, App. E).

References are closed-form: the paper's Eq. 11 and E.1-E.3, atan((W/2)/fx) for a pinhole's FoV, the
equidistant model r = f theta, and smooth functions of the ray direction.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from conftest import SHARED_DATA
from geer_ns.cameras import CameraModel, EquidistantCamera, PinholeCamera, from_pycolmap
from geer_ns.data.beap import (
    DEFAULT_MAX_HALF_ANGLE,
    BeapGrid,
    beap_grid_for_camera,
    beap_to_native,
    camera_angular_extent,
    camera_center_step,
    resample_to_beap,
)

T265 = SHARED_DATA / "t265_fisheye"
LIM = DEFAULT_MAX_HALF_ANGLE


pytestmark = pytest.mark.usefixtures("single_thread")


def equidistant_180(radius: int = 200) -> EquidistantCamera:
    """Equidistant fisheye whose image is exactly the bounding square of its 180-degree circle."""
    f = radius / (math.pi / 2)
    return EquidistantCamera(2 * radius, 2 * radius, f, f, radius, radius)


def smooth_field(dirs: torch.Tensor) -> torch.Tensor:
    """A smooth scalar function of the ray direction, in [0, 1]."""
    return (0.5 + 0.25 * dirs[..., 0] + 0.2 * dirs[..., 1] * dirs[..., 2]).unsqueeze(-1)


# --------------------------------------------------------------------------------------------------
# Grid geometry
# --------------------------------------------------------------------------------------------------


def test_grid_directions_follow_eq_e1_e3_and_eq_11() -> None:
    grid = BeapGrid.from_fov(48, 32, math.radians(150), math.radians(100))
    ang = grid.angles(torch.float64)
    th, ph = ang[..., 0].numpy(), ang[..., 1].numpy()
    den = np.sqrt(
        np.sin(th) ** 2 * np.cos(ph) ** 2 + np.cos(th) ** 2 * np.sin(ph) ** 2 + np.cos(th) ** 2 * np.cos(ph) ** 2
    )
    ref = np.stack([np.sin(th) * np.cos(ph), np.cos(th) * np.sin(ph), np.cos(th) * np.cos(ph)], -1) / den[..., None]
    assert np.abs(grid.directions(torch.float64).numpy() - ref).max() < 1e-12
    # Eq. 6 recovers the angles.
    d = grid.directions(torch.float64)
    assert torch.allclose(torch.atan2(d[..., 0], d[..., 2]), ang[..., 0], atol=1e-12)
    assert torch.allclose(torch.atan2(d[..., 1], d[..., 2]), ang[..., 1], atol=1e-12)
    # Eq. 11 (1-based cell index) maps every point of a cell to that cell (tested a quarter cell off the
    # centre, away from floor()'s round-off at integers).
    w, h = grid.width, grid.height
    fov_x, fov_y = grid.fov
    x = np.floor(w * (th + 0.25 * grid.step_theta) / fov_x + (w + 1) / 2)
    y = np.floor(h * (ph + 0.25 * grid.step_phi) / fov_y + (h + 1) / 2)
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    assert (x == jj + 1).all() and (y == ii + 1).all()
    # angles_to_cells puts cell centres at +0.5.
    cells = grid.angles_to_cells(ang[..., 0], ang[..., 1])
    assert torch.allclose(cells[..., 0], torch.from_numpy(jj + 0.5).double(), atol=1e-9)


def test_grid_rejects_unrepresentable_ranges() -> None:
    with pytest.raises(ValueError, match="theta_max"):
        BeapGrid(16, 16, -0.5, math.pi / 2, -0.5, 0.5)
    with pytest.raises(ValueError, match="width"):
        BeapGrid(0, 16, -0.5, 0.5, -0.5, 0.5)


def test_fov_of_180_degree_equidistant_is_clipped() -> None:
    cam = equidistant_180()
    t0, t1, p0, p1 = camera_angular_extent(cam)
    assert (t0, t1, p0, p1) == pytest.approx((-LIM, LIM, -LIM, LIM), abs=1e-12)
    grid = beap_grid_for_camera(cam)
    assert grid.width % 16 == 0 and grid.height % 16 == 0
    assert grid.theta_min >= -LIM - 1e-12 and grid.theta_max <= LIM + 1e-12
    assert grid.theta_min == pytest.approx(-LIM, abs=1e-9) and grid.phi_max == pytest.approx(LIM, abs=1e-9)
    # A configurable clip.
    grid80 = beap_grid_for_camera(cam, max_half_angle=math.radians(80))
    assert grid80.theta_max == pytest.approx(math.radians(80), abs=1e-9)


@pytest.mark.parametrize("cx,cy", [(320.0, 240.0), (300.0, 250.0)])
def test_fov_of_pinhole_matches_atan(cx: float, cy: float) -> None:
    fx, fy = 500.0, 480.0
    cam = PinholeCamera(640, 480, fx, fy, cx, cy)
    expected = (-math.atan(cx / fx), math.atan((640 - cx) / fx), -math.atan(cy / fy), math.atan((480 - cy) / fy))
    assert camera_angular_extent(cam) == pytest.approx(expected, abs=1e-12)

    step = camera_center_step(cam)
    assert step == pytest.approx(2 * math.atan(0.5 / fx), rel=1e-9)  # finer of the two axes

    tight = beap_grid_for_camera(cam, tile_size=1)
    for got, want, sign in zip(
        (tight.theta_min, tight.theta_max, tight.phi_min, tight.phi_max), expected, (-1, 1, -1, 1)
    ):
        assert 0 <= sign * (got - want) <= step + 1e-12  # covers the FoV, within one cell

    tiled = beap_grid_for_camera(cam, tile_size=16)
    assert tiled.width % 16 == 0 and tiled.height % 16 == 0
    assert tiled.step_theta == pytest.approx(step) and tiled.step_phi == pytest.approx(step)
    assert tiled.theta_min <= expected[0] and tiled.theta_max >= expected[1]
    assert tiled.width - (expected[1] - expected[0]) / step < 16
    # Symmetric extension around the camera's extent.
    assert (expected[0] - tiled.theta_min) == pytest.approx(tiled.theta_max - expected[1], abs=1e-12)


# --------------------------------------------------------------------------------------------------
# Resampling geometry (smooth fields: exact up to bilinear interpolation error)
# --------------------------------------------------------------------------------------------------


def test_resample_and_back_are_geometrically_consistent() -> None:
    cam = PinholeCamera(320, 240, 200, 205, 161, 118, k1=-0.1, k2=0.01)
    grid = beap_grid_for_camera(cam)
    native_dirs, native_ok = cam.pixel_rays(torch.float64)
    native = smooth_field(native_dirs).float()
    beap, valid = resample_to_beap(native, cam, grid)
    assert valid.float().mean() > 0.8
    ref = smooth_field(grid.directions(torch.float64)).float()
    assert (beap - ref)[valid].abs().max() < 2e-3

    back, bvalid = beap_to_native(ref, grid, cam)
    assert bool(bvalid[native_ok].all())  # the grid covers every pixel of a pinhole
    assert (back - native)[bvalid].abs().max() < 2e-3


def test_no_pixel_dropped_for_180_degree_equidistant() -> None:
    cam = equidistant_180(150)
    grid = beap_grid_for_camera(cam)
    dirs, cam_ok = cam.pixel_rays(torch.float64)
    theta = torch.atan2(dirs[..., 0], dirs[..., 2])
    phi = torch.atan2(dirs[..., 1], dirs[..., 2])
    incidence = torch.atan2(dirs[..., :2].norm(dim=-1), dirs[..., 2])
    circle = cam_ok & (incidence < math.pi / 2)
    representable = circle & (theta.abs() <= LIM) & (phi.abs() <= LIM)
    assert representable.sum() > 0.95 * circle.sum()

    beap = smooth_field(grid.directions(torch.float64)).float()
    back, valid = beap_to_native(beap, grid, cam)
    assert bool(valid[representable].all()), "a native pixel within +-89.5 degrees has no BEAP sample"
    # Accuracy away from the BEAP corners, where (theta, phi) -> direction is singular (both -> 90 deg).
    inner = valid & (incidence < math.radians(80))
    assert (back - smooth_field(dirs).float())[inner].abs().max() < 2e-3

    # Through the image: native -> BEAP with the circle as mask -> native keeps the circle's interior.
    native = smooth_field(dirs).float()
    beap2, bvalid = resample_to_beap(native, cam, grid, mask=circle)
    back2, valid2 = beap_to_native(beap2, grid, cam, beap_valid=bvalid)
    interior = representable & (incidence < math.radians(85))
    assert bool(valid2[interior].all())
    assert (back2 - native)[valid2 & (incidence < math.radians(80))].abs().max() < 5e-3


# --------------------------------------------------------------------------------------------------
# Masks and antialiasing
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("supersample", [None, 1, 3])
def test_mask_respected(supersample) -> None:
    cam = EquidistantCamera(200, 160, 70, 70, 100.3, 79.6)
    rng = np.random.default_rng(0)
    image = (rng.uniform(0, 0.5, (160, 200, 3))).astype(np.float32)
    mask = np.ones((160, 200), np.uint8)
    mask[40:90, 120:170] = 0  # a hole
    mask[:, :12] = 0  # a border strip
    image[mask == 0] = 1.0  # poison: any bleed shows up as a value > 0.5
    grid = beap_grid_for_camera(cam, tile_size=8)
    beap, valid = resample_to_beap(image, cam, grid, mask=mask, supersample=supersample)
    assert valid.any()
    assert float(beap[valid].max()) <= 0.5 + 1e-6
    assert float(beap[~valid].abs().max()) == 0.0

    # Cells projecting deep inside the hole are invalid, cells far from it valid.
    px, ok = cam.project(grid.directions(torch.float64))
    deep = ok & (px[..., 0] > 125) & (px[..., 0] < 165) & (px[..., 1] > 45) & (px[..., 1] < 85)
    far = ok & (px[..., 0] > 20) & (px[..., 0] < 110) & (px[..., 1] > 5) & (px[..., 1] < 155)
    assert deep.any() and not bool(valid[deep].any())
    assert bool(valid[far].all())

    # A bool mask gives the same result; a wrong-shape mask is rejected.
    beap_b, valid_b = resample_to_beap(image, cam, grid, mask=torch.from_numpy(mask != 0), supersample=supersample)
    assert torch.equal(valid_b, valid) and torch.equal(beap_b, beap)
    with pytest.raises(ValueError, match="mask"):
        resample_to_beap(image, cam, grid, mask=mask[:-1])


def test_antialiasing_when_beap_is_coarser() -> None:
    cam = PinholeCamera(256, 256, 300, 300, 128, 128)
    yy, xx = np.mgrid[0:256, 0:256]
    checker = ((xx + yy) % 2).astype(np.uint8) * 255  # 1-pixel checkerboard, mean 0.5
    grid = beap_grid_for_camera(cam, step=4 * camera_center_step(cam), tile_size=1)
    beap_aa, valid_aa = resample_to_beap(checker, cam, grid)  # automatic k (4 here)
    beap_k1, valid_k1 = resample_to_beap(checker, cam, grid, supersample=1)
    assert valid_aa.float().mean() > 0.9
    assert float(beap_aa[valid_aa].std()) < 0.5 * float(beap_k1[valid_k1].std())
    assert float(beap_aa[valid_aa].mean()) == pytest.approx(0.5, abs=0.02)


# --------------------------------------------------------------------------------------------------
# Real T265 fisheye images
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def t265() -> tuple[CameraModel, list[np.ndarray]]:
    if not (T265 / "cameras.txt").is_file():
        pytest.skip(f"T265 data not found at {T265} (set GEER_TEST_DATA: docs/test_data.md)")
    import pycolmap

    cams = {}
    for line in (T265 / "cameras.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            tok = line.split()
            cams[int(tok[0])] = pycolmap.Camera(
                model=tok[1], width=int(tok[2]), height=int(tok[3]), params=[float(t) for t in tok[4:]]
            )
    images = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in sorted(T265.glob("cam001_*.jpg"))]
    if not images:
        pytest.skip(f"no cam001_* images in {T265}")
    return from_pycolmap(cams[1]), images


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10 * torch.log10(((a - b) ** 2).mean()))


def test_t265_round_trip_psnr(t265) -> None:
    cam, images = t265
    grid = beap_grid_for_camera(cam)  # step = angular resolution at the principal point
    dirs, cam_ok = cam.pixel_rays(torch.float64)
    incidence = torch.atan2(dirs[..., :2].norm(dim=-1), dirs[..., 2])
    circle = cam_ok & (incidence < math.radians(85))  # the lens' image circle (T265: ~163 deg FoV)
    for image in images:
        assert image.shape == (800, 848)
        beap, bvalid = resample_to_beap(image, cam, grid)
        back, valid = beap_to_native(beap, grid, cam, beap_valid=bvalid)
        assert valid[circle].float().mean() > 0.99
        sel = circle & valid
        value = psnr(back[..., 0][sel], torch.from_numpy(image).float()[sel] / 255)
        print(f"T265 native -> BEAP -> native PSNR: {value:.2f} dB")
        assert value >= 35.0
