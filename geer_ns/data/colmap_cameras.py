"""The COLMAP camera of every image, as geer keeps it and as nerfstudio sees it.

The exact COLMAP model of every image is kept (``metadata["geer_colmap_cameras"]``, one
:class:`ColmapCameraSpec` per image of the split, at the loaded resolution, plus tensors in
``Cameras.metadata``); geer renders with it through :func:`camera_model_for_image` /
:func:`camera_model_from_cameras`. The nerfstudio ``Cameras`` get the closest type nerfstudio knows, so that
nerfstudio's viewer and ray generator still show something sensible:

=========================================  ===========================================  =====
COLMAP model                               nerfstudio camera_type, distortion_params   exact
=========================================  ===========================================  =====
SIMPLE_PINHOLE PINHOLE SIMPLE_RADIAL       PERSPECTIVE (k1 k2 0 0 p1 p2)                yes
RADIAL OPENCV
FULL_OPENCV                                PERSPECTIVE (k1 k2 k3 0 p1 p2)               if k4 = k5 = k6 = 0
OPENCV_FISHEYE                             FISHEYE (k1 k2 k3 k4 0 0)                    yes (k4 != 0 too)
SIMPLE_RADIAL_FISHEYE RADIAL_FISHEYE       FISHEYE (k1 k2 0 0 0 0), fx = fy = f         yes
SIMPLE_FISHEYE FISHEYE                     FISHEYE (0 ...)                              yes
THIN_PRISM_FISHEYE                         FISHEYE (k1 k2 k3 k4 p1 p2)                  if sx1 = sy1 = 0
RAD_TAN_THIN_PRISM_FISHEYE                 FISHEYE624 (12 params) when every image      yes
                                           uses that one camera, else fitted FISHEYE    (else no)
FOV                                        PERSPECTIVE, or FISHEYE when the image       omega = 0 only
                                           reaches 80 degrees off-axis
EQUIRECTANGULAR                            EQUIRECTANGULAR (fx = W/2, fy = H)           yes
=========================================  ===========================================  =====

Where nerfstudio cannot represent the model, the nerfstudio camera is a least-squares fit of the exact model
over the image (in nerfstudio's own ideal-point space; a common focal scale and 0 to 4 radial terms plus
tangential, keeping the candidate whose nerfstudio undistortion reproduces the exact rays best); cx, cy stay
the COLMAP ones. FISHEYE624 is used only when all images share one RAD_TAN_THIN_PRISM_FISHEYE camera:
nerfstudio 1.1.5's ray generation uses the first camera's 624 parameters for every 624 camera and fails with
an IndexError when 624 cameras are mixed with other types (then ``distortion_params`` has 12 columns).
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import NamedTuple, Sequence, Tuple

import numpy as np
import torch

from nerfstudio.cameras import camera_utils
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs

from geer_ns.cameras import CameraModel, from_nerfstudio, from_pycolmap
from geer_ns.data.colmap_files import param_names as _param_names

__all__ = [
    "ColmapCameraSpec",
    "NerfstudioIntrinsics",
    "camera_model_for_image",
    "camera_model_from_cameras",
    "nerfstudio_intrinsics",
]

GEER_CAMERAS_KEY = "geer_colmap_cameras"
# Cameras.metadata keys (tensors, so that they follow nerfstudio's indexing / slicing of Cameras).
MODEL_ID_KEY = "geer_colmap_model_id"  # int64 [N, 1]: pycolmap.CameraModelId value
PARAMS_KEY = "geer_colmap_params"  # float64 [N, MAX_PARAMS]: COLMAP params, zero padded
NS_TYPE_KEY = "geer_ns_camera_type"  # int64 [N, 1]: the nerfstudio CameraType value the parser chose
DISTORTED_KEY = "geer_ns_distorted"  # bool [N, 1]: the parser gave the nerfstudio camera non-zero distortion
NS_INTRINSICS_KEY = "geer_ns_intrinsics"  # float64 [N, 4]: fx, fy, cx, cy the parser gave the nerfstudio camera
MAX_PARAMS = 16

_FISHEYE_FAMILY = {
    "OPENCV_FISHEYE",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "SIMPLE_FISHEYE",
    "FISHEYE",
    "THIN_PRISM_FISHEYE",
}
_PERSPECTIVE_LIMIT_DEG = 80.0  # approximated models reaching this far off-axis are shown as FISHEYE


class ColmapCameraSpec(NamedTuple):
    """The exact COLMAP camera of one image (at the loaded resolution)."""

    model: str
    width: int
    height: int
    params: Tuple[float, ...]
    camera_id: int
    nerfstudio_exact: bool  # whether the nerfstudio Cameras entry represents it exactly


class NerfstudioIntrinsics(NamedTuple):
    camera_type: CameraType
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: Tuple[float, ...]  # 6 values (k1 k2 k3 k4 p1 p2), or 12 for FISHEYE624
    exact: bool


# ==================================================================================================
# COLMAP model -> nerfstudio camera
# ==================================================================================================


def _pycolmap_camera(model: str, width: int, height: int, params: Sequence[float], camera_id: int = 1):
    import pycolmap

    return pycolmap.Camera(
        camera_id=int(camera_id), model=model, width=int(width), height=int(height), params=[float(p) for p in params]
    )


def _fit_distortion(exact: CameraModel, fx: float, fy: float, cx: float, cy: float, fisheye: bool):
    """Least-squares nerfstudio camera (fx', fy', k1..k4, p1, p2) for ``exact``, in nerfstudio's ideal space.

    nerfstudio maps the ideal point q (x/z for PERSPECTIVE, theta * azimuth for FISHEYE) to
    d = q (1 + k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4) + tangential(p1, p2), pixel = (fx' d_x + cx, fy' d_y + cy).
    With fx' = c0 fx this is linear in (c0, c0 k, c0 p). Candidates with 0..4 radial terms are fitted; the one
    whose nerfstudio undistortion (``radial_and_tangential_undistort``, what nerfstudio's ray generator runs)
    best reproduces the exact ideal points wins: high-order fits can make that Newton iteration diverge.
    Returns (fx', fy', coefficients, largest off-axis angle in degrees over the image, error in pixels).
    """
    # Sample directions (projection is closed form; unprojection would need Newton) and keep those that land
    # inside the image.
    n_theta, n_az = 48, 64
    theta_max = min(float(exact.max_angle), math.pi) * (1 - 1e-6)
    th = (torch.arange(1, n_theta + 1, dtype=torch.float64) / n_theta) * theta_max
    az = torch.arange(n_az, dtype=torch.float64) * (2 * math.pi / n_az)
    tt, aa = torch.meshgrid(th, az, indexing="ij")
    dirs = torch.stack([torch.sin(tt) * torch.cos(aa), torch.sin(tt) * torch.sin(aa), torch.cos(tt)], -1).reshape(-1, 3)
    px, valid = exact.project(dirs)
    valid &= (px[:, 0] >= 0) & (px[:, 0] <= exact.width) & (px[:, 1] >= 0) & (px[:, 1] <= exact.height)
    theta = tt.reshape(-1)
    max_deg = float(torch.rad2deg(theta[valid].max())) if bool(valid.any()) else 0.0
    if fisheye:
        keep = valid
        rho = torch.linalg.norm(dirs[:, :2], dim=-1).clamp_min(1e-12)
        q = dirs[:, :2] * (theta / rho).unsqueeze(-1)
    else:
        keep = valid & (theta < math.radians(_PERSPECTIVE_LIMIT_DEG))
        q = dirs[:, :2] / dirs[:, 2:3].clamp_min(1e-12)
    if int(keep.sum()) < 8:
        return fx, fy, (0.0,) * 6, max_deg, math.inf
    q, p = q[keep].numpy(), px[keep].numpy()
    d = np.stack([(p[:, 0] - cx) / fx, (p[:, 1] - cy) / fy], -1)
    x, y = q[:, 0], q[:, 1]
    r2 = x * x + y * y
    # Columns: c0, c0 k1..k4, c0 p1, c0 p2 (x rows then y rows).
    cols_x = [x, x * r2, x * r2**2, x * r2**3, x * r2**4, 2 * x * y, r2 + 2 * x * x]
    cols_y = [y, y * r2, y * r2**2, y * r2**3, y * r2**4, r2 + 2 * y * y, 2 * x * y]
    b = np.concatenate([d[:, 0], d[:, 1]])
    best = (fx, fy, (0.0,) * 6, math.inf)
    for n_radial in range(5):
        use = [0, *range(1, 1 + n_radial), 5, 6]
        a = np.stack([np.concatenate([cols_x[j], cols_y[j]]) for j in use], -1)
        scale = np.linalg.norm(a, axis=0)
        scale[scale == 0] = 1.0
        sol, *_ = np.linalg.lstsq(a / scale, b, rcond=None)
        sol = sol / scale
        full = np.zeros(7)
        full[use] = sol
        c0 = full[0]
        if not (np.all(np.isfinite(full)) and c0 > 0):
            continue
        coef = tuple(float(c) for c in full[1:] / c0)
        fx_ns, fy_ns = fx * c0, fy * c0
        dn = torch.from_numpy(np.stack([(p[:, 0] - cx) / fx_ns, (p[:, 1] - cy) / fy_ns], -1)).float()
        coef_t = torch.tensor(coef, dtype=torch.float32).expand(len(dn), 6)
        und = camera_utils.radial_and_tangential_undistort(dn, coef_t)
        err = float(np.abs(und.double().numpy() - q).max()) * max(fx_ns, fy_ns)
        if np.isfinite(err) and err < best[3] - 1e-6:
            best = (float(fx_ns), float(fy_ns), coef, err)
    return best[0], best[1], best[2], max_deg, best[3]


def nerfstudio_intrinsics(
    model: str, width: int, height: int, params: Sequence[float], allow_fisheye624: bool = True
) -> NerfstudioIntrinsics:
    """The closest nerfstudio camera for a COLMAP camera (see the module docstring's table).

    ``allow_fisheye624=False`` gives a fitted FISHEYE camera for RAD_TAN_THIN_PRISM_FISHEYE.
    Raises ValueError for models geer does not support (via :func:`geer_ns.cameras.from_pycolmap`).
    Cached: nerfstudio parses the same dataset once per split.
    """
    return _nerfstudio_intrinsics(
        str(model), int(width), int(height), tuple(float(v) for v in params), bool(allow_fisheye624)
    )


@functools.lru_cache(maxsize=256)
def _nerfstudio_intrinsics(
    model: str, width: int, height: int, params: Tuple[float, ...], allow_fisheye624: bool
) -> NerfstudioIntrinsics:
    exact_model = from_pycolmap(_pycolmap_camera(model, width, height, params))
    p = dict(zip(_param_names(model), (float(v) for v in params)))
    persp, fish = CameraType.PERSPECTIVE, CameraType.FISHEYE

    def dist(k1=0.0, k2=0.0, k3=0.0, k4=0.0, p1=0.0, p2=0.0):
        return (k1, k2, k3, k4, p1, p2)

    if model == "EQUIRECTANGULAR":
        return NerfstudioIntrinsics(
            CameraType.EQUIRECTANGULAR, width / 2, float(height), width / 2, height / 2, dist(), True
        )
    if "f" in p:
        fx = fy = p["f"]
    else:
        fx, fy = p["fx"], p["fy"]
    cx, cy = p["cx"], p["cy"]
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        return NerfstudioIntrinsics(persp, fx, fy, cx, cy, dist(), True)
    if model == "SIMPLE_RADIAL":
        return NerfstudioIntrinsics(persp, fx, fy, cx, cy, dist(k1=p["k"]), True)
    if model == "RADIAL":
        return NerfstudioIntrinsics(persp, fx, fy, cx, cy, dist(k1=p["k1"], k2=p["k2"]), True)
    if model == "OPENCV":
        return NerfstudioIntrinsics(persp, fx, fy, cx, cy, dist(p["k1"], p["k2"], 0, 0, p["p1"], p["p2"]), True)
    if model == "FULL_OPENCV" and p["k4"] == 0 and p["k5"] == 0 and p["k6"] == 0:
        return NerfstudioIntrinsics(
            persp, fx, fy, cx, cy, dist(p["k1"], p["k2"], p["k3"], 0, p["p1"], p["p2"]), True
        )
    if model == "OPENCV_FISHEYE":
        return NerfstudioIntrinsics(fish, fx, fy, cx, cy, dist(p["k1"], p["k2"], p["k3"], p["k4"]), True)
    if model == "SIMPLE_RADIAL_FISHEYE":
        return NerfstudioIntrinsics(fish, fx, fy, cx, cy, dist(k1=p["k"]), True)
    if model == "RADIAL_FISHEYE":
        return NerfstudioIntrinsics(fish, fx, fy, cx, cy, dist(k1=p["k1"], k2=p["k2"]), True)
    if model in ("SIMPLE_FISHEYE", "FISHEYE"):
        return NerfstudioIntrinsics(fish, fx, fy, cx, cy, dist(), True)
    if model == "THIN_PRISM_FISHEYE" and p["sx1"] == 0 and p["sy1"] == 0:
        return NerfstudioIntrinsics(
            fish, fx, fy, cx, cy, dist(p["k1"], p["k2"], p["k3"], p["k4"], p["p1"], p["p2"]), True
        )
    if model == "RAD_TAN_THIN_PRISM_FISHEYE" and allow_fisheye624:
        names = ("k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3")
        return NerfstudioIntrinsics(CameraType.FISHEYE624, fx, fy, cx, cy, tuple(p[n] for n in names), True)
    if model == "FOV" and p["omega"] == 0:
        return NerfstudioIntrinsics(persp, fx, fy, cx, cy, dist(), True)
    # Not representable: fit. Fisheye family -> FISHEYE; others PERSPECTIVE unless the image is too wide.
    if model in _FISHEYE_FAMILY or model == "RAD_TAN_THIN_PRISM_FISHEYE":
        fx_ns, fy_ns, coef, _, _ = _fit_distortion(exact_model, fx, fy, cx, cy, fisheye=True)
        return NerfstudioIntrinsics(fish, fx_ns, fy_ns, cx, cy, coef, False)
    fx_ns, fy_ns, coef, max_deg, _ = _fit_distortion(exact_model, fx, fy, cx, cy, fisheye=False)
    if max_deg >= _PERSPECTIVE_LIMIT_DEG:
        fx_ns, fy_ns, coef, _, _ = _fit_distortion(exact_model, fx, fy, cx, cy, fisheye=True)
        return NerfstudioIntrinsics(fish, fx_ns, fy_ns, cx, cy, coef, False)
    return NerfstudioIntrinsics(persp, fx_ns, fy_ns, cx, cy, coef, False)


# ==================================================================================================
# Exact models for the renderer
# ==================================================================================================


def camera_model_for_image(dataparser_outputs: DataparserOutputs, index: int) -> CameraModel:
    """Exact geer camera model of image ``index`` of ``dataparser_outputs``.

    Uses the COLMAP camera stored by :class:`GeerColmapDataParser`; for outputs of other dataparsers (no
    ``geer_colmap_cameras`` metadata) it falls back to :func:`geer_ns.cameras.from_nerfstudio`.
    """
    specs = (dataparser_outputs.metadata or {}).get(GEER_CAMERAS_KEY)
    if specs is None:
        return from_nerfstudio(dataparser_outputs.cameras, index)
    spec = specs[int(index)]
    return from_pycolmap(_pycolmap_camera(spec.model, spec.width, spec.height, spec.params, spec.camera_id))


def camera_model_from_cameras(cameras: Cameras, index: int) -> CameraModel:
    """Exact geer camera model of camera ``index`` of a (flattened) nerfstudio ``Cameras``.

    Reads the COLMAP model this parser put into ``Cameras.metadata`` and follows later changes of resolution
    (``rescale_output_resolution``): focal lengths, principal point and size are taken from ``cameras``.
    Falls back to :func:`geer_ns.cameras.from_nerfstudio` when the metadata is absent, or when something
    replaced the camera (camera type changed, or distortion zeroed, e.g. by nerfstudio's image undistortion in
    ``FullImageDatamanager``): then the nerfstudio camera is what the images now show.
    """
    import pycolmap

    cams = cameras.flatten() if len(cameras.shape) != 1 else cameras
    cam = cams[int(index)]
    meta = cam.metadata or {}
    if MODEL_ID_KEY not in meta or PARAMS_KEY not in meta:
        return from_nerfstudio(cams, index)
    ns_type = int(cam.camera_type.reshape(-1)[0])
    if NS_TYPE_KEY in meta and int(meta[NS_TYPE_KEY].reshape(-1)[0]) != ns_type:
        return from_nerfstudio(cams, index)
    model_id = pycolmap.CameraModelId(int(meta[MODEL_ID_KEY].reshape(-1)[0]))
    model = model_id.name
    n = len(_param_names(model))
    params = [float(v) for v in meta[PARAMS_KEY].reshape(-1)[:n]]
    if DISTORTED_KEY in meta and bool(meta[DISTORTED_KEY].reshape(-1)[0]):
        if cam.distortion_params is None or not bool(cam.distortion_params.any()):
            # The parser set distortion but it is gone: something (e.g. nerfstudio's FullImageDatamanager)
            # undistorted the images and replaced the camera, so the nerfstudio camera is what they show.
            return from_nerfstudio(cams, index)
    width, height = int(cam.width.reshape(-1)[0]), int(cam.height.reshape(-1)[0])
    if model == "EQUIRECTANGULAR":
        return from_pycolmap(_pycolmap_camera(model, width, height, [width, height]))
    pc = _pycolmap_camera(model, width, height, params)
    now = [float(getattr(cam, k).reshape(-1)[0]) for k in ("fx", "fy", "cx", "cy")]
    ref = [float(v) for v in meta[NS_INTRINSICS_KEY].reshape(-1)] if NS_INTRINSICS_KEY in meta else now
    if all(abs(a - b) <= 1e-6 * max(1.0, abs(b)) for a, b in zip(now, ref)):
        return from_pycolmap(pc)  # unchanged (up to float32 rounding): keep the float64 COLMAP values
    # Rescaled (or otherwise changed) since parsing: scale COLMAP's focal lengths like nerfstudio's, and take
    # the principal point from cameras (the parser copies COLMAP's cx, cy unchanged).
    sx, sy = now[0] / ref[0], now[1] / ref[1]
    f_idx, c_idx = list(pc.focal_length_idxs()), list(pc.principal_point_idxs())
    if len(f_idx) == 1:
        if abs(sx - sy) > 1e-4 * max(sx, sy):
            raise ValueError(f"camera {index}: COLMAP {model} has one focal length but was rescaled by {sx} x {sy}")
        params[f_idx[0]] *= 0.5 * (sx + sy)
    else:
        params[f_idx[0]] *= sx
        params[f_idx[1]] *= sy
    params[c_idx[0]], params[c_idx[1]] = now[2], now[3]
    return from_pycolmap(_pycolmap_camera(model, width, height, params))


# ==================================================================================================
# Per-camera checks and rescaling (used by the dataparser)
# ==================================================================================================


def _check_camera(camera, cameras_file: Path) -> Tuple[ColmapCameraSpec, NerfstudioIntrinsics]:
    model = camera.model.name
    cid = int(camera.camera_id)
    width, height = int(camera.width), int(camera.height)
    if width <= 0 or height <= 0:
        raise ValueError(f"{cameras_file}: camera {cid}: size {width}x{height} is not positive")
    params = [float(v) for v in camera.params]
    try:
        names = _param_names(model)
    except Exception:
        names = [f"params[{i}]" for i in range(len(params))]
    for name, value in zip(names, params):
        if not math.isfinite(value):
            raise ValueError(f"{cameras_file}: camera {cid}: {model} parameter {name} = {value} is not finite")
    try:
        ns = nerfstudio_intrinsics(model, width, height, params)
    except ValueError as e:
        raise ValueError(f"{cameras_file}: camera {cid}: unsupported or invalid camera ({model}): {e}") from e
    spec = ColmapCameraSpec(model, width, height, tuple(params), cid, ns.exact)
    return spec, ns


def _rescaled(spec: ColmapCameraSpec, factor: float, width: int, height: int) -> ColmapCameraSpec:
    """Scale focal lengths and principal point by factor (as nerfstudio's rescale_output_resolution)."""
    if spec.model == "EQUIRECTANGULAR":
        return spec._replace(width=width, height=height, params=(float(width), float(height)))
    pc = _pycolmap_camera(spec.model, spec.width, spec.height, spec.params)
    params = list(spec.params)
    for i in list(pc.focal_length_idxs()) + list(pc.principal_point_idxs()):
        params[i] *= factor
    return spec._replace(width=width, height=height, params=tuple(params))


def _model_id(model: str) -> int:
    import pycolmap

    return int(pycolmap.CameraModelId.__members__[model].value)
