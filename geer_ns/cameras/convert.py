"""Camera models from nerfstudio ``Cameras`` and from ``pycolmap.Camera``."""

from __future__ import annotations

import math
from collections.abc import Callable

from geer_ns.cameras.base import CameraModel
from geer_ns.cameras.equirectangular import EquirectangularCamera
from geer_ns.cameras.fisheye import (
    EquidistantCamera,
    Fisheye624Camera,
    OpenCVFisheyeCamera,
    RadialFisheyeCamera,
    ThinPrismFisheyeCamera,
)
from geer_ns.cameras.omnidirectional import FOVCamera
from geer_ns.cameras.pinhole import PinholeCamera


def from_nerfstudio(cameras, index: int) -> CameraModel:
    """Camera ``index`` of a ``nerfstudio.cameras.cameras.Cameras`` (flattened batch).

    nerfstudio's ``distortion_params`` are (k1, k2, k3, k4, p1, p2):
    * PERSPECTIVE: radial 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8 and OpenCV tangential. The r^8 term has no
      OpenCV counterpart, so k4 != 0 raises ValueError.
    * FISHEYE: the same polynomial applied in theta space, i.e. Kannala-Brandt (k1..k4); with p1/p2 != 0
      it is COLMAP's THIN_PRISM_FISHEYE with zero prism terms.
    * FISHEYE624: 12 parameters (k0..k5, p0, p1, s0..s3).
    * EQUIRECTANGULAR: must have nerfstudio's standard intrinsics (fx = W/2, fy = H, c = image center).
    """
    from nerfstudio.cameras.cameras import CameraType

    cams = cameras.flatten() if len(cameras.shape) != 1 else cameras
    cam = cams[int(index)]

    def scalar(t, name: str) -> float:
        value = float(t.reshape(-1)[0])
        if not math.isfinite(value):
            raise ValueError(f"nerfstudio camera {index}: {name} must be finite, got {value!r}")
        return value

    fx, fy, cx, cy = (scalar(getattr(cam, n), n) for n in ("fx", "fy", "cx", "cy"))
    width, height = int(cam.width.reshape(-1)[0]), int(cam.height.reshape(-1)[0])
    ctype = CameraType(int(cam.camera_type.reshape(-1)[0]))
    dist = [0.0] * 6
    if cam.distortion_params is not None:
        dist = [float(v) for v in cam.distortion_params.reshape(-1)]
        for i, v in enumerate(dist):
            if not math.isfinite(v):
                raise ValueError(f"nerfstudio camera {index}: distortion_params[{i}] must be finite, got {v!r}")

    if ctype == CameraType.PERSPECTIVE:
        k1, k2, k3, k4, p1, p2 = (dist + [0.0] * 6)[:6]
        if k4 != 0:
            raise ValueError(
                f"nerfstudio camera {index}: PERSPECTIVE distortion k4 (r^8 term) = {k4} has no OpenCV equivalent"
            )
        return PinholeCamera(width, height, fx, fy, cx, cy, k1=k1, k2=k2, p1=p1, p2=p2, k3=k3)
    if ctype == CameraType.FISHEYE:
        k1, k2, k3, k4, p1, p2 = (dist + [0.0] * 6)[:6]
        if p1 != 0 or p2 != 0:
            return ThinPrismFisheyeCamera(width, height, fx, fy, cx, cy, k1=k1, k2=k2, p1=p1, p2=p2, k3=k3, k4=k4)
        return OpenCVFisheyeCamera(width, height, fx, fy, cx, cy, k1=k1, k2=k2, k3=k3, k4=k4)
    if ctype == CameraType.FISHEYE624:
        if len(dist) != 12:
            raise ValueError(f"nerfstudio camera {index}: FISHEYE624 needs 12 distortion_params, got {len(dist)}")
        names = ("k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3")
        return Fisheye624Camera(width, height, fx, fy, cx, cy, **dict(zip(names, dist)))
    if ctype == CameraType.EQUIRECTANGULAR:
        expected = {"fx": width / 2, "fy": height, "cx": width / 2, "cy": height / 2}
        for name, want in expected.items():
            got = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}[name]
            if abs(got - want) > 1e-3 * max(1.0, abs(want)):
                raise ValueError(
                    f"nerfstudio camera {index}: EQUIRECTANGULAR {name} = {got} differs from the standard {want}"
                )
        return EquirectangularCamera(width, height)
    raise ValueError(f"nerfstudio camera {index}: camera type {ctype.name} is not supported")


# COLMAP model name -> (builder from the parameter dict, parameter names in COLMAP order).
_COLMAP_MODELS: dict[str, tuple[tuple[str, ...], Callable[[int, int, dict], CameraModel]]] = {
    "SIMPLE_PINHOLE": (("f", "cx", "cy"), lambda w, h, p: PinholeCamera(w, h, p["f"], p["f"], p["cx"], p["cy"])),
    "PINHOLE": (("fx", "fy", "cx", "cy"), lambda w, h, p: PinholeCamera(w, h, **p)),
    "SIMPLE_RADIAL": (
        ("f", "cx", "cy", "k"),
        lambda w, h, p: PinholeCamera(w, h, p["f"], p["f"], p["cx"], p["cy"], k1=p["k"]),
    ),
    "RADIAL": (
        ("f", "cx", "cy", "k1", "k2"),
        lambda w, h, p: PinholeCamera(w, h, p["f"], p["f"], p["cx"], p["cy"], k1=p["k1"], k2=p["k2"]),
    ),
    "OPENCV": (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"), lambda w, h, p: PinholeCamera(w, h, **p)),
    "FULL_OPENCV": (
        ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
        lambda w, h, p: PinholeCamera(w, h, **p),
    ),
    "OPENCV_FISHEYE": (
        ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
        lambda w, h, p: OpenCVFisheyeCamera(w, h, **p),
    ),
    "SIMPLE_FISHEYE": (("f", "cx", "cy"), lambda w, h, p: EquidistantCamera(w, h, p["f"], p["f"], p["cx"], p["cy"])),
    "FISHEYE": (("fx", "fy", "cx", "cy"), lambda w, h, p: EquidistantCamera(w, h, **p)),
    "SIMPLE_RADIAL_FISHEYE": (
        ("f", "cx", "cy", "k"),
        lambda w, h, p: RadialFisheyeCamera(w, h, p["f"], p["cx"], p["cy"], k1=p["k"]),
    ),
    "RADIAL_FISHEYE": (("f", "cx", "cy", "k1", "k2"), lambda w, h, p: RadialFisheyeCamera(w, h, **p)),
    "FOV": (("fx", "fy", "cx", "cy", "omega"), lambda w, h, p: FOVCamera(w, h, **p)),
    "THIN_PRISM_FISHEYE": (
        ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1"),
        lambda w, h, p: ThinPrismFisheyeCamera(w, h, **p),
    ),
    "RAD_TAN_THIN_PRISM_FISHEYE": (
        ("fx", "fy", "cx", "cy", "k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3"),
        lambda w, h, p: Fisheye624Camera(w, h, **p),
    ),
    "EQUIRECTANGULAR": (("w", "h"), lambda w, h, p: _colmap_equirect(w, h, p)),
}


def _colmap_equirect(width: int, height: int, p: dict) -> CameraModel:
    if p["w"] != width or p["h"] != height:
        raise ValueError(f"COLMAP EQUIRECTANGULAR params (w, h) = ({p['w']}, {p['h']}) differ from the image size")
    return EquirectangularCamera(width, height)


def from_pycolmap(camera) -> CameraModel:
    """Convert a ``pycolmap.Camera``; supported models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL,
    OPENCV, FULL_OPENCV, OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, FOV, THIN_PRISM_FISHEYE,
    plus RAD_TAN_THIN_PRISM_FISHEYE (= FISHEYE624), SIMPLE_FISHEYE / FISHEYE (equidistant) and EQUIRECTANGULAR.
    """
    name = camera.model.name if hasattr(camera.model, "name") else str(camera.model_name)
    if name not in _COLMAP_MODELS:
        raise ValueError(f"COLMAP camera model {name} is not supported (supported: {', '.join(_COLMAP_MODELS)})")
    names, build = _COLMAP_MODELS[name]
    params = [float(v) for v in camera.params]
    if len(params) != len(names):
        raise ValueError(f"COLMAP {name} expects {len(names)} params ({', '.join(names)}), got {len(params)}")
    for n, v in zip(names, params):
        if not math.isfinite(v):
            raise ValueError(f"COLMAP {name} parameter {n} must be finite, got {v!r}")
    return build(int(camera.width), int(camera.height), dict(zip(names, params)))
