"""Camera models vs independent references: OpenCV (cv2, cv2.fisheye, cv2.omnidir), pycolmap and nerfstudio.

Cross-library and round-trip tolerances are 1e-3 px in float64 (directions: 1e-3 px / focal, i.e. the
same error expressed as an angle).
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import torch

from conftest import SHARED_DATA
from geer_ns.cameras import (
    CameraModel,
    EquidistantCamera,
    EquirectangularCamera,
    Fisheye624Camera,
    FOVCamera,
    MeiCamera,
    OpenCVFisheyeCamera,
    PinholeCamera,
    RadialFisheyeCamera,
    ThinPrismFisheyeCamera,
    from_nerfstudio,
    from_pycolmap,
)

PX_TOL = 1e-3
T265 = SHARED_DATA / "t265_fisheye"
W, H = 640, 480


pytestmark = pytest.mark.usefixtures("single_thread")


# --------------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------------


def random_directions(rng: np.random.Generator, n: int, max_theta: float) -> np.ndarray:
    """Unit directions uniformly spread in azimuth with angle from +z uniform in [0, max_theta]."""
    theta = rng.uniform(0, max_theta, n)
    azim = rng.uniform(-math.pi, math.pi, n)
    return np.stack([np.sin(theta) * np.cos(azim), np.sin(theta) * np.sin(azim), np.cos(theta)], -1)


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1))


def random_colmap_params(name: str, rng: np.random.Generator, height: int = H) -> list[float]:
    f = rng.uniform(250, 450)
    fx, fy = f, f * rng.uniform(0.97, 1.03)
    cx, cy = W / 2 + rng.uniform(-15, 15), H / 2 + rng.uniform(-15, 15)

    def small(s: float) -> float:
        return float(rng.uniform(-s, s))

    table = {
        "SIMPLE_PINHOLE": lambda: [f, cx, cy],
        "PINHOLE": lambda: [fx, fy, cx, cy],
        "SIMPLE_RADIAL": lambda: [f, cx, cy, small(0.1)],
        "RADIAL": lambda: [f, cx, cy, small(0.1), small(0.02)],
        "OPENCV": lambda: [fx, fy, cx, cy, small(0.1), small(0.02), small(2e-3), small(2e-3)],
        "FULL_OPENCV": lambda: (
            [fx, fy, cx, cy, small(0.1), small(0.02), small(2e-3), small(2e-3)]
            + [small(5e-3), small(0.05), small(0.01), small(1e-3)]
        ),
        "OPENCV_FISHEYE": lambda: [fx, fy, cx, cy, small(0.05), small(0.01), small(2e-3), small(5e-4)],
        "SIMPLE_RADIAL_FISHEYE": lambda: [f, cx, cy, small(0.05)],
        "RADIAL_FISHEYE": lambda: [f, cx, cy, small(0.05), small(0.01)],
        "FOV": lambda: [fx, fy, cx, cy, float(rng.uniform(0.3, 1.2))],
        "THIN_PRISM_FISHEYE": lambda: (
            [fx, fy, cx, cy, small(0.05), small(0.01), small(1e-3), small(1e-3)]
            + [small(2e-3), small(5e-4), small(1e-3), small(1e-3)]
        ),
        "RAD_TAN_THIN_PRISM_FISHEYE": lambda: (
            [fx, fy, cx, cy]
            + [small(0.05), small(0.01), small(2e-3), small(5e-4), small(1e-4), small(1e-5)]
            + [small(1e-3), small(1e-3), small(1e-3), small(1e-4), small(1e-3), small(1e-4)]
        ),
        "SIMPLE_FISHEYE": lambda: [f, cx, cy],
        "FISHEYE": lambda: [fx, fy, cx, cy],
        "EQUIRECTANGULAR": lambda: [float(W), float(height)],
    }
    return table[name]()


COLMAP_MODELS = [
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
    "FULL_OPENCV",
    "OPENCV_FISHEYE",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "FOV",
    "THIN_PRISM_FISHEYE",
    "RAD_TAN_THIN_PRISM_FISHEYE",
    "SIMPLE_FISHEYE",
    "FISHEYE",
    "EQUIRECTANGULAR",
]


def all_models() -> dict[str, CameraModel]:
    """One instance of every model class (moderate, realistic distortion)."""
    return {
        "pinhole": PinholeCamera(W, H, 420, 425, 322, 238, k1=-0.12, k2=0.02, p1=1e-3, p2=-8e-4, k3=-1e-3),
        "pinhole_rational": PinholeCamera(W, H, 420, 425, 322, 238, k1=0.1, k2=-0.01, k3=1e-3, k4=0.2, k5=0.01),
        "kb": OpenCVFisheyeCamera(W, H, 250, 252, 321, 241, k1=0.02, k2=-0.01, k3=2e-3, k4=-3e-4),
        "equidistant": EquidistantCamera(W, H, 200, 200, 320, 240),
        "radial_fisheye": RadialFisheyeCamera(W, H, 240, 320, 240, k1=0.03, k2=-0.004),
        "fov": FOVCamera(W, H, 300, 305, 320, 240, omega=0.9),
        "thin_prism": ThinPrismFisheyeCamera(
            W, H, 250, 252, 321, 241, 0.02, -0.01, 1e-3, -1e-3, 2e-3, -3e-4, 1e-3, 5e-4
        ),
        "fisheye624": Fisheye624Camera(
            W, H, 250, 252, 321, 241, k0=0.02, k1=-0.01, k2=2e-3, k3=-3e-4, p0=1e-3, p1=-5e-4, s0=1e-3, s2=-1e-3
        ),
        "mei": MeiCamera(W, H, 300, 305, 320, 240, xi=0.9, k1=-0.05, k2=0.01, p1=1e-3, p2=-1e-3, skew=0.3),
        "mei_xi_gt_1": MeiCamera(W, H, 300, 305, 320, 240, xi=1.3, k1=-0.02),
        "equirect": EquirectangularCamera(W, W // 2),
    }


def read_colmap_cameras_txt(path: Path) -> dict[int, pycolmap.Camera]:
    cams = {}
    for line in path.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        tok = line.split()
        cams[int(tok[0])] = pycolmap.Camera(
            model=tok[1], width=int(tok[2]), height=int(tok[3]), params=[float(t) for t in tok[4:]]
        )
    return cams


# --------------------------------------------------------------------------------------------------
# OpenCV references
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("rational", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pinhole_matches_cv2(rational: bool, seed: int) -> None:
    rng = np.random.default_rng(seed)
    fx, fy, cx, cy = rng.uniform(300, 600), rng.uniform(300, 600), rng.uniform(300, 340), rng.uniform(220, 260)
    k1, k2, p1, p2, k3 = (
        rng.uniform(-0.2, 0.2),
        rng.uniform(-0.05, 0.05),
        *rng.uniform(-2e-3, 2e-3, 2),
        rng.uniform(-5e-3, 5e-3),
    )
    k4, k5, k6 = (rng.uniform(-0.1, 0.1), rng.uniform(-0.01, 0.01), rng.uniform(-1e-3, 1e-3)) if rational else (0, 0, 0)
    cam = PinholeCamera(W, H, fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    D = np.array([k1, k2, p1, p2, k3] + ([k4, k5, k6] if rational else []))

    pts = random_directions(rng, 2000, math.radians(45)) * rng.uniform(0.5, 20, (2000, 1))
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, D)
    px, valid = cam.project(torch.from_numpy(pts))
    assert bool(valid.all())
    assert np.abs(px.numpy() - ref[:, 0]).max() < PX_TOL

    # Unprojection vs cv2.undistortPoints (normalised coordinates, compared in pixels via the focal).
    uv = np.stack([rng.uniform(0, W, 2000), rng.uniform(0, H, 2000)], -1)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    # OpenCV 4.x takes iteration criteria through undistortPointsIter (5.x also via undistortPoints).
    und = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), K, D, None, None, crit)[:, 0]
    dirs, ok = cam.unproject(torch.from_numpy(uv))
    assert bool(ok.all())
    q = (dirs[:, :2] / dirs[:, 2:]).numpy()
    assert (np.abs(q - und) * np.array([fx, fy])).max() < PX_TOL


@pytest.mark.parametrize("seed", [0, 1])
def test_kannala_brandt_matches_cv2_fisheye(seed: int) -> None:
    rng = np.random.default_rng(seed)
    fx, fy = rng.uniform(200, 320, 2)
    cx, cy = W / 2 + rng.uniform(-10, 10), H / 2 + rng.uniform(-10, 10)
    D = np.array(
        [rng.uniform(-0.05, 0.05), rng.uniform(-0.01, 0.01), rng.uniform(-2e-3, 2e-3), rng.uniform(-5e-4, 5e-4)]
    )
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    cam = OpenCVFisheyeCamera(W, H, fx, fy, cx, cy, *D)

    pts = random_directions(rng, 2000, math.radians(85)) * rng.uniform(0.5, 20, (2000, 1))
    ref, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    px, valid = cam.project(torch.from_numpy(pts))
    assert bool(valid.all())
    assert np.abs(px.numpy() - ref[:, 0]).max() < PX_TOL

    uv = ref[:, 0]
    dirs, ok = cam.unproject(torch.from_numpy(uv))
    assert bool(ok.all())
    truth = pts / np.linalg.norm(pts, axis=-1, keepdims=True)
    assert angle_between(dirs.numpy(), truth).max() < PX_TOL / max(fx, fy)
    # cv2.fisheye.undistortPoints clamps theta_d to pi/2, so compare only below that.
    theta = np.arccos(truth[:, 2])
    theta_d = theta * (1 + sum(k * theta ** (2 * i + 2) for i, k in enumerate(D)))
    sel = theta_d < math.pi / 2 - 1e-3
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    und = cv2.fisheye.undistortPoints(uv[sel].reshape(-1, 1, 2), K, D, criteria=crit)[:, 0]
    ref_dirs = np.concatenate([und, np.ones((len(und), 1))], -1)
    ref_dirs /= np.linalg.norm(ref_dirs, axis=-1, keepdims=True)
    assert angle_between(dirs.numpy()[sel], ref_dirs).max() < PX_TOL / max(fx, fy)


@pytest.mark.parametrize("xi", [0.0, 0.7, 1.0, 1.6])
def test_mei_matches_cv2_omnidir(xi: float) -> None:
    rng = np.random.default_rng(int(xi * 10))
    fx, fy, cx, cy, skew = 300.0, 310.0, 322.0, 236.0, 0.4
    D = np.array([[-0.05, 0.01, 1e-3, -1e-3]])
    K = np.array([[fx, skew, cx], [0, fy, cy], [0, 0, 1.0]])
    cam = MeiCamera(W, H, fx, fy, cx, cy, xi=xi, k1=-0.05, k2=0.01, p1=1e-3, p2=-1e-3, skew=skew)

    pts = random_directions(rng, 2000, min(math.radians(85), 0.9 * cam.max_angle)) * rng.uniform(0.5, 20, (2000, 1))
    ref, _ = cv2.omnidir.projectPoints(pts.reshape(-1, 1, 3), np.zeros((1, 3)), np.zeros((1, 3)), K, xi, D)
    px, valid = cam.project(torch.from_numpy(pts))
    assert bool(valid.all())
    assert np.abs(px.numpy() - ref[:, 0]).max() < PX_TOL

    dirs, ok = cam.unproject(torch.from_numpy(ref[:, 0]))
    assert bool(ok.all())
    truth = pts / np.linalg.norm(pts, axis=-1, keepdims=True)
    assert angle_between(dirs.numpy(), truth).max() < PX_TOL / fx
    # cv2.omnidir.undistortPoints inverts the distortion with a fixed 20-step fixed-point iteration that
    # does not converge at large radii of strong (pinhole-like, small xi) distortion: compare <= 60 deg.
    sel = truth[:, 2] > math.cos(math.radians(60))
    und = cv2.omnidir.undistortPoints(ref[sel], K, D, np.array([[xi]]), np.eye(3))[:, 0]  # x/z of the ray
    ref_dirs = np.concatenate([und, np.ones((len(und), 1))], -1)
    ref_dirs /= np.linalg.norm(ref_dirs, axis=-1, keepdims=True)
    assert angle_between(dirs.numpy()[sel], ref_dirs).max() < PX_TOL / fx


# --------------------------------------------------------------------------------------------------
# pycolmap references
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", COLMAP_MODELS)
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_pycolmap(name: str, seed: int) -> None:
    rng = np.random.default_rng(seed)
    height = W // 2 if name == "EQUIRECTANGULAR" else H
    ref_cam = pycolmap.Camera(model=name, width=W, height=height, params=random_colmap_params(name, rng, height))
    cam = from_pycolmap(ref_cam)
    assert (cam.width, cam.height) == (W, height)
    spherical = name == "EQUIRECTANGULAR"

    # COLMAP's lens models only project z > 0 (and FOV/pinhole-like distortion is only sane well before
    # 90 degrees); stay inside the model's monotonic range too.
    max_theta = math.pi if spherical else min(0.95 * cam.max_angle, math.radians(80 if "FISHEYE" in name else 55))
    pts = random_directions(rng, 3000, max_theta) * rng.uniform(0.5, 20, (3000, 1))
    px, valid = cam.project(torch.from_numpy(pts))
    ref = ref_cam.img_from_cam(pts)
    assert bool(valid.all())
    assert np.abs(px.numpy() - ref).max() < PX_TOL

    # Unprojection: pixels from the projected points and random pixels of the image.
    uv = np.concatenate([ref, np.stack([rng.uniform(0, W, 2000), rng.uniform(0, height, 2000)], -1)])
    ref_dirs = ref_cam.cam_ray_from_img(uv)
    dirs, ok = cam.unproject(torch.from_numpy(uv))
    both = ok.numpy() & np.isfinite(ref_dirs).all(-1)
    assert both[: len(ref)].all(), "every in-domain projected pixel must unproject"
    f = 1.0 if spherical else max(cam.fx, cam.fy)
    tol = PX_TOL * 2 * math.pi / W if spherical else PX_TOL / f
    assert angle_between(dirs.numpy()[both], ref_dirs[both]).max() < tol


@pytest.mark.parametrize("name", ["EUCM", "SIMPLE_DIVISION", "DIVISION"])
def test_pycolmap_unsupported_model_raises(name: str) -> None:
    ref_cam = pycolmap.Camera.create_from_model_name(1, name, 300.0, W, H)
    with pytest.raises(ValueError, match=name):
        from_pycolmap(ref_cam)


def test_pycolmap_non_finite_param_raises() -> None:
    ref_cam = pycolmap.Camera(model="OPENCV", width=W, height=H, params=[300, 300, 320, 240, 0.1, float("nan"), 0, 0])
    with pytest.raises(ValueError, match="k2"):
        from_pycolmap(ref_cam)


# --------------------------------------------------------------------------------------------------
# Real calibration: Intel RealSense T265 (COLMAP OPENCV_FISHEYE)
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def t265_cameras() -> dict[int, pycolmap.Camera]:
    path = T265 / "cameras.txt"
    if not path.is_file():
        pytest.skip(f"T265 calibration not found at {path} (set GEER_TEST_DATA: docs/test_data.md)")
    return read_colmap_cameras_txt(path)


def test_t265_calibration(t265_cameras: dict[int, pycolmap.Camera]) -> None:
    for ref_cam in t265_cameras.values():
        assert ref_cam.model.name == "OPENCV_FISHEYE"
        cam = from_pycolmap(ref_cam)
        assert isinstance(cam, OpenCVFisheyeCamera)
        uv = cam.pixel_centers(torch.float64)[::7, ::7].reshape(-1, 2)
        dirs, ok = cam.unproject(uv)
        assert bool(ok.all()), "the T265 polynomial is monotonic over the whole image"
        back, ok2 = cam.project(dirs)
        assert bool(ok2.all())
        assert (back - uv).abs().max() < PX_TOL

        # Against pycolmap and cv2.fisheye where they are defined (in front of the camera).
        front = (dirs[:, 2] > math.cos(math.radians(85))).numpy()
        ref_dirs = ref_cam.cam_ray_from_img(uv.numpy()[front])
        assert angle_between(dirs.numpy()[front], ref_dirs).max() < PX_TOL / ref_cam.focal_length_x
        K = ref_cam.calibration_matrix()
        D = np.asarray(ref_cam.params[4:])
        proj, _ = cv2.fisheye.projectPoints(dirs.numpy()[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
        assert np.abs(proj[:, 0] - uv.numpy()[front]).max() < PX_TOL


# --------------------------------------------------------------------------------------------------
# Round trips and general properties (all model classes)
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("key", list(all_models()))
def test_round_trip(key: str) -> None:
    cam = all_models()[key]
    uv = cam.pixel_centers(torch.float64)[::5, ::5].reshape(-1, 2)
    dirs, ok = cam.unproject(uv)
    assert ok.float().mean() > 0.5
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(len(dirs), dtype=torch.float64))
    back, ok2 = cam.project(dirs[ok])
    assert bool(ok2.all())
    assert (back - uv[ok]).abs().max() < PX_TOL

    rng = np.random.default_rng(3)
    pts = torch.from_numpy(random_directions(rng, 2000, 0.98 * min(cam.max_angle, math.pi)))
    px, valid = cam.project(pts)
    assert bool(valid.all())
    d2, ok3 = cam.unproject(px)
    assert bool(ok3.all())
    assert angle_between(d2.numpy(), pts.numpy()).max() < 1e-9


@pytest.mark.parametrize("key", list(all_models()))
def test_nan_free_at_and_beyond_90_degrees(key: str) -> None:
    cam = all_models()[key]
    pts = torch.tensor(
        [
            [0, 0, 0],
            [0, 0, -1],
            [1, 0, 0],
            [0, -1, 0],
            [1, 1, -1e-12],
            [1, 0, -1],
            [1e-30, 0, 1],
            [1e30, 0, 1],
            [0, 0, 1],
            [-0.3, 0.2, -5],
        ],
        dtype=torch.float64,
    )
    for dtype in (torch.float64, torch.float32):
        px, valid = cam.project(pts.to(dtype))
        assert px.dtype == dtype
        assert bool(torch.isfinite(px).all())
        assert not bool(valid[0])  # the origin has no direction
        if cam.max_angle <= math.pi / 2:
            assert not bool(valid[1:6].any())  # at/behind 90 degrees
        assert bool(valid[8])
    pixels = torch.tensor(
        [[float("nan"), 1.0], [float("inf"), 0.0], [1e9, -1e9], [-1e12, 3.0], [W / 2, H / 2], [1e-300, 0]],
        dtype=torch.float64,
    )
    for dtype in (torch.float64, torch.float32):
        dirs, ok = cam.unproject(pixels.to(dtype))
        assert dirs.dtype == dtype
        assert bool(torch.isfinite(dirs).all())
        assert torch.allclose(dirs.norm(dim=-1), torch.ones(len(dirs), dtype=dtype), atol=1e-5)
        assert not bool(ok[0]) and not bool(ok[1])
        assert bool((dirs[~ok] == torch.tensor([0, 0, 1], dtype=dtype)).all())


def test_pixel_rays_use_pixel_centres() -> None:
    cam = all_models()["kb"]
    dirs, valid = cam.pixel_rays(torch.float64)
    assert dirs.shape == (H, W, 3) and valid.shape == (H, W)
    i, j = 17, 401
    ref, _ = cam.unproject(torch.tensor([[j + 0.5, i + 0.5]], dtype=torch.float64))
    assert torch.allclose(dirs[i, j], ref[0], atol=1e-15)
    # The principal point pixel looks down +z up to the half-pixel offset.
    p = EquidistantCamera(64, 48, 50, 50, 32, 24)
    d, _ = p.pixel_rays(torch.float64)
    assert torch.allclose(
        d[24, 32],
        torch.tensor(
            [math.sin(0.5 / 50 * math.sqrt(2)) / math.sqrt(2)] * 2 + [math.cos(0.5 / 50 * math.sqrt(2))],
            dtype=torch.float64,
        ),
    )
    assert cam.pixel_rays()[0].dtype == torch.float32


def test_float32_follows_input() -> None:
    cam = all_models()["thin_prism"]
    uv = cam.pixel_centers(torch.float32)[::9, ::9].reshape(-1, 2)
    dirs, ok = cam.unproject(uv)
    assert dirs.dtype == torch.float32 and bool(ok.all())
    back, _ = cam.project(dirs)
    assert back.dtype == torch.float32
    assert (back - uv).abs().max() < 0.02


def test_gradients() -> None:
    cam = all_models()["pinhole"]
    pts = torch.tensor([[0.1, -0.2, 1.0], [0.4, 0.3, 2.0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p: cam.project(p)[0], (pts,))
    for key in ("pinhole", "kb", "fisheye624", "mei"):
        cam = all_models()[key]
        uv = torch.tensor([[100.5, 80.25], [400.0, 300.0]], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda x, cam=cam: cam.unproject(x)[0], (uv,), atol=1e-6)


# --------------------------------------------------------------------------------------------------
# max_angle
# --------------------------------------------------------------------------------------------------


def first_turning_point(theta: np.ndarray, radius: np.ndarray) -> float:
    """Independent dense numpy scan: last theta before the radius stops increasing."""
    bad = np.nonzero(np.diff(radius) <= 0)[0]
    return float(theta[bad[0]]) if len(bad) else float(theta[-1])


@pytest.mark.parametrize(
    "coeffs", [(-0.1, 0.0, 0.0, 0.0), (0.05, -0.08, 0.01, 0.0), (0.0, 0.0, -0.01, 0.0), (0.02, -0.01, 0.002, -0.0005)]
)
def test_kb_max_angle_is_turning_point(coeffs: tuple[float, ...]) -> None:
    f = 250.0
    cam = OpenCVFisheyeCamera(W, H, f, f, 320, 240, *coeffs)
    theta = np.linspace(0, math.pi, 2_000_001)
    theta_d = theta * (1 + sum(k * theta ** (2 * i + 2) for i, k in enumerate(coeffs)))
    expected = first_turning_point(theta, theta_d)
    assert abs(cam.max_angle - expected) < 1e-5
    if coeffs == (-0.1, 0.0, 0.0, 0.0):
        assert abs(cam.max_angle - math.sqrt(1 / 0.3)) < 1e-9  # d/dtheta theta (1 + k1 theta^2) = 0

    # Pixels beyond the image radius of the turning point are invalid, just inside are valid.
    rd_max = float(np.interp(cam.max_angle, theta, theta_d))
    radii = f * rd_max * np.array([0.99, 0.999, 1.001, 1.05, 2.0])
    uv = torch.from_numpy(np.stack([320 + radii, np.full_like(radii, 240)], -1))
    _, ok = cam.unproject(uv)
    assert ok.tolist() == [True, True, False, False, False]
    # Points beyond max_angle do not project validly.
    th = np.array([0.99, 1.01]) * cam.max_angle
    pts = torch.from_numpy(np.stack([np.sin(th), np.zeros(2), np.cos(th)], -1))
    assert cam.project(pts)[1].tolist() == [True, cam.max_angle >= math.pi]


def test_pinhole_barrel_max_angle() -> None:
    k1 = -0.3
    cam = PinholeCamera(W, H, 300, 300, 320, 240, k1=k1)
    assert abs(cam.max_angle - math.atan(math.sqrt(-1 / (3 * k1)))) < 1e-9
    r = np.linspace(0, 50, 5_000_001)
    assert abs(cam.max_angle - math.atan(first_turning_point(r, r * (1 + k1 * r**2)))) < 1e-5
    r_star = math.sqrt(-1 / (3 * k1))
    rd_max = r_star * (1 + k1 * r_star**2)  # largest distorted radius the lens produces
    u = 320.0 + 300 * rd_max * np.array([0.99, 0.9999, 1.0001, 1.1])
    _, ok = cam.unproject(torch.from_numpy(np.stack([u, np.full_like(u, 240.0)], -1)))
    assert ok.tolist() == [True, True, False, False]
    assert PinholeCamera(W, H, 300, 300, 320, 240).max_angle == pytest.approx(math.pi / 2)


def test_other_max_angles() -> None:
    assert MeiCamera(W, H, 300, 300, 320, 240, xi=1.6).max_angle == pytest.approx(math.acos(-1 / 1.6), abs=1e-9)
    assert MeiCamera(W, H, 300, 300, 320, 240, xi=0.5).max_angle == pytest.approx(math.acos(-0.5), abs=1e-9)
    assert MeiCamera(W, H, 300, 300, 320, 240, xi=0.0).max_angle == pytest.approx(math.pi / 2, abs=1e-9)
    assert FOVCamera(W, H, 300, 300, 320, 240, omega=0.8).max_angle == pytest.approx(math.pi)
    assert FOVCamera(W, H, 300, 300, 320, 240, omega=0.0).max_angle == pytest.approx(math.pi / 2)
    assert EquidistantCamera(W, H, 200, 200, 320, 240).max_angle == pytest.approx(math.pi)
    assert EquirectangularCamera(W, H).max_angle == math.pi


# --------------------------------------------------------------------------------------------------
# nerfstudio
# --------------------------------------------------------------------------------------------------


def _ns_cameras(camera_type, w: int, h: int, fx: float, fy: float, cx: float, cy: float, dist=None):
    from nerfstudio.cameras.cameras import Cameras

    return Cameras(
        camera_to_worlds=torch.eye(4)[None, :3, :],
        fx=float(fx),
        fy=float(fy),
        cx=float(cx),
        cy=float(cy),
        width=w,
        height=h,
        distortion_params=None if dist is None else torch.tensor([dist], dtype=torch.float32),
        camera_type=camera_type,
    )


@pytest.mark.parametrize(
    "kind,dist",
    [
        ("PERSPECTIVE", [-0.1, 0.02, -1e-3, 0.0, 1e-3, -5e-4]),
        ("FISHEYE", [0.02, -0.01, 2e-3, -3e-4, 0.0, 0.0]),
        ("FISHEYE", [0.02, -0.01, 2e-3, -3e-4, 1e-3, -1e-3]),
        ("EQUIRECTANGULAR", None),
    ],
)
def test_matches_nerfstudio_generate_rays(kind: str, dist) -> None:
    from nerfstudio.cameras.cameras import CameraType

    w, h = (96, 48) if kind == "EQUIRECTANGULAR" else (80, 60)
    if kind == "EQUIRECTANGULAR":
        ns = _ns_cameras(CameraType.EQUIRECTANGULAR, w, h, w / 2, float(h), w / 2, h / 2)
    else:
        # Principal point off the pixel centres: nerfstudio's FISHEYE divides 0/0 exactly on it.
        ns = _ns_cameras(getattr(CameraType, kind), w, h, 45.0, 46.0, 40.3, 29.6, dist)
    cam = from_nerfstudio(ns, 0)
    expected_type = {
        "PERSPECTIVE": PinholeCamera,
        "FISHEYE": ThinPrismFisheyeCamera if dist and dist[4] else OpenCVFisheyeCamera,
        "EQUIRECTANGULAR": EquirectangularCamera,
    }[kind]
    assert type(cam) is expected_type
    with torch.no_grad():
        ref = ns.generate_rays(camera_indices=0).directions.double()  # OpenGL camera frame (c2w = I)
    ref_cv = ref * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
    dirs, valid = cam.pixel_rays(torch.float64)
    assert bool(valid.all())
    assert (dirs - ref_cv).abs().max() < 1e-4


def test_from_nerfstudio_param_order_and_fisheye624() -> None:
    from nerfstudio.cameras import camera_utils
    from nerfstudio.cameras.cameras import CameraType

    ns = _ns_cameras(CameraType.PERSPECTIVE, 64, 48, 50, 51, 32, 24, [0.1, 0.2, 0.3, 0.0, 0.4, 0.5])
    cam = from_nerfstudio(ns, 0)
    assert (cam.k1, cam.k2, cam.k3, cam.p1, cam.p2) == pytest.approx((0.1, 0.2, 0.3, 0.4, 0.5))
    with pytest.raises(ValueError, match="k4"):
        from_nerfstudio(_ns_cameras(CameraType.PERSPECTIVE, 64, 48, 50, 51, 32, 24, [0, 0, 0, 0.1, 0, 0]), 0)

    params12 = [0.02, -0.01, 2e-3, -3e-4, 1e-5, -1e-6, 1e-3, -5e-4, 1e-3, -1e-4, -1e-3, 1e-4]
    ns = _ns_cameras(CameraType.FISHEYE624, W, H, 250.0, 252.0, 321.0, 241.0, params12)
    cam = from_nerfstudio(ns, 0)
    assert isinstance(cam, Fisheye624Camera)
    rng = np.random.default_rng(5)
    pts = torch.from_numpy(random_directions(rng, 1000, math.radians(80)))
    full = torch.tensor([[250.0, 252.0, 321.0, 241.0] + params12], dtype=torch.float64)
    ref = camera_utils.fisheye624_project(pts[None], full)[0]
    px, ok = cam.project(pts)
    assert bool(ok.all())
    assert (px - ref).abs().max() < PX_TOL
    ref_rays = camera_utils.fisheye624_unproject_helper(ref[None], full, max_iters=30)[0]
    ref_rays = ref_rays / ref_rays.norm(dim=-1, keepdim=True)
    dirs, ok = cam.unproject(ref)
    assert bool(ok.all())
    assert angle_between(dirs.numpy(), ref_rays.numpy()).max() < PX_TOL / 250


# --------------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "build,field",
    [
        (lambda: PinholeCamera(W, H, float("nan"), 300, 320, 240), "fx"),
        (lambda: PinholeCamera(W, H, 300, -1, 320, 240), "fy"),
        (lambda: PinholeCamera(W, H, 300, 300, float("inf"), 240), "cx"),
        (lambda: PinholeCamera(W, H, 300, 300, 320, 240, k3=float("nan")), "k3"),
        (lambda: PinholeCamera(0, H, 300, 300, 320, 240), "width"),
        (lambda: OpenCVFisheyeCamera(W, -5, 300, 300, 320, 240), "height"),
        (lambda: RadialFisheyeCamera(W, H, 0.0, 320, 240), "f"),
        (lambda: FOVCamera(W, H, 300, 300, 320, 240, omega=4.0), "omega"),
        (lambda: MeiCamera(W, H, 300, 300, 320, 240, xi=-1.0), "xi"),
        (lambda: EquirectangularCamera(W, 0), "height"),
    ],
)
def test_bad_parameters_raise(build, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        build()
