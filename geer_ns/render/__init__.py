"""3DGEER renderer: one module per pipeline stage (see rasterize.py for the overview)."""

from .associate import TileLists, associate
from .backend import resolve_backend
from .composite import composite
from .moving import MovingRays
from .pbf import PBF, compute_pbf, mirror_tangent, pbf_lambda_sq
from .outputs import RenderOutput
from .rasterize import preprocess, render, render_batch, render_brute_force
from .raygrid import RayGrid, beap_directions
from .sh import sh_to_color
from .transforms import quat_to_rotmat, to_view_space, whitening
from .transmittance import canonical_ray_response, half_line_sq, pair_alpha

__all__ = [
    "MovingRays",
    "PBF",
    "RayGrid",
    "RenderOutput",
    "TileLists",
    "associate",
    "beap_directions",
    "canonical_ray_response",
    "composite",
    "compute_pbf",
    "half_line_sq",
    "mirror_tangent",
    "pair_alpha",
    "pbf_lambda_sq",
    "preprocess",
    "quat_to_rotmat",
    "render",
    "render_batch",
    "render_brute_force",
    "resolve_backend",
    "sh_to_color",
    "to_view_space",
    "whitening",
]
