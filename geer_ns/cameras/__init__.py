"""Central camera models (pinhole, fisheye, omnidirectional, equirectangular) in batched torch.

Conventions
-----------
* Camera frame: OpenCV, x right, y down, z forward (nerfstudio uses OpenGL, x right, y up, z backward;
  :func:`from_nerfstudio` only converts intrinsics, rays from nerfstudio must be flipped as (x, -y, -z)).
* Pixel coordinates: continuous, (u, v) = (column, row), the top-left image corner is (0, 0) and the
  bottom-right corner is (width, height); pixel (i, j) (row i, column j) has its center at
  (j + 0.5, i + 0.5). This is COLMAP's convention and nerfstudio's (``get_image_coords`` adds 0.5).
* ``max_angle`` is the largest angle from the optical axis for which the model is a bijection between
  directions and image points. It is derived from the model alone (where the radial mapping
  theta -> distorted radius stops increasing, where a Mei/pinhole projection hits its pole, pi for the
  full sphere); it is NOT limited to what the image shows (that is the caller's job, e.g. BEAP).
  Tangential / thin-prism terms are not radially symmetric and are left out of ``max_angle``; their
  failures are caught by the convergence test of :meth:`CameraModel.unproject`.
* dtype follows the input (float32 or float64; other inputs are converted to float32). Projection is
  closed form and differentiable; unprojection solves with a fixed number of (safeguarded) Newton
  iterations under ``no_grad`` and re-attaches gradients with one final Newton step (implicit
  differentiation), so it is differentiable w.r.t. the pixels too.
* Nothing returns NaN/Inf: invalid points get finite placeholder pixels, invalid pixels get +z.

Modules: ``base`` (the :class:`CameraModel` interface), ``lens`` (the machinery shared by all lens models),
``pinhole``, ``fisheye`` (theta-space models), ``omnidirectional`` (FOV, Mei), ``equirectangular`` and
``convert`` (from nerfstudio and pycolmap cameras).
"""

from geer_ns.cameras.base import CameraModel
from geer_ns.cameras.convert import from_nerfstudio, from_pycolmap
from geer_ns.cameras.equirectangular import EquirectangularCamera
from geer_ns.cameras.fisheye import (
    EquidistantCamera,
    Fisheye624Camera,
    OpenCVFisheyeCamera,
    RadialFisheyeCamera,
    ThinPrismFisheyeCamera,
)
from geer_ns.cameras.omnidirectional import FOVCamera, MeiCamera
from geer_ns.cameras.pinhole import PinholeCamera

__all__ = [
    "CameraModel",
    "EquidistantCamera",
    "EquirectangularCamera",
    "FOVCamera",
    "Fisheye624Camera",
    "MeiCamera",
    "OpenCVFisheyeCamera",
    "PinholeCamera",
    "RadialFisheyeCamera",
    "ThinPrismFisheyeCamera",
    "from_nerfstudio",
    "from_pycolmap",
]
