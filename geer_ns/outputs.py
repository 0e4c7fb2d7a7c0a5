"""The nerfstudio outputs of a geer render: one name per meaning, and which of them the viewer lists.

    rgb               color, background composited
    accumulation      sum of the blend weights (opacity of the ray)
    distance          expected distance along the ray, sum_i w_i t_i / sum_i w_i (radial: fisheye, 360)
    depth             camera-space z of the expected hit point, as splatfacto's `depth` (pinhole convention)
    median_distance   distance at which the ray's transmittance falls below 0.5
    normal            blended Gaussian normals, world axes, shown as (n + 1) / 2 (nerfstudio's normal images)
    normal_camera     the same in camera axes (OpenCV: x right, y down, z forward)

Rays where a value is undefined (nothing hit; z of a ray at or beyond 90 degrees from the optical axis) hold the
view's largest defined value, as splatfacto fills its depth, so that colormaps stay readable and nothing is NaN;
`depth_defined` marks where `depth` is defined. Internal outputs (validity masks, the background) stay out of
the viewer's list. Meanings, conventions and units: docs/outputs.md.
"""

from __future__ import annotations

from typing import Dict, Optional

import torch
from torch import Tensor

from geer_ns.render.normals import NormalImages
from geer_ns.render.outputs import RenderOutput, z_depth

# Outputs the losses and metrics read that mean nothing to a viewer user.
INTERNAL_OUTPUTS = ("valid_rays", "central_region", "background", "depth_defined")


def filled(values: Tensor, defined: Tensor) -> Tensor:
    """values where `defined`, the largest defined value (no gradient) elsewhere; 0 when nothing is defined.
    No host synchronization (it runs every training step)."""
    top = torch.where(defined, values.detach(), torch.full_like(values, -torch.inf)).amax()
    return torch.where(defined, values, torch.where(torch.isfinite(top), top, torch.zeros_like(top)))


def shaded(normal: Tensor, hit: Tensor) -> Tensor:
    """A unit-normal image [H, W, 3] as nerfstudio shows normals ((n + 1) / 2 in [0, 1]); 0 where not hit."""
    return torch.where(hit, (normal + 1.0) * 0.5, torch.zeros_like(normal))


def geometry_outputs(out: RenderOutput, dirs: Tensor, normals: Optional[NormalImages] = None,
                     median: bool = False) -> Dict[str, Tensor]:
    """distance, depth, depth_defined (and median_distance, normal, normal_camera when asked for) of one render;
    dirs [H*W, 3] the view's unit ray directions in the camera frame. distance and depth keep their gradient
    (depth supervision); the others are forward only."""
    hit = out.accumulation > 0
    depth, defined = z_depth(out.distance, dirs, hit)
    found = {"distance": filled(out.distance, hit), "depth": filled(depth, defined), "depth_defined": defined}
    if median and out.median_distance is not None:
        crossed = (out.median_distance > 0) | (out.accumulation > 0.5)  # 0 is a real value inside a Gaussian
        found["median_distance"] = filled(out.median_distance.detach(), crossed)
    if normals is not None:
        found["normal"] = shaded(normals.world, hit)
        found["normal_camera"] = shaded(normals.camera, hit)
    return found


def viewer_outputs(outputs: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """The outputs the viewer's dropdown lists: every output but the internal ones."""
    return {name: value for name, value in outputs.items() if name not in INTERNAL_OUTPUTS}


def distance_images(outputs: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """ns-eval's saved images of the geometry outputs, colormapped as nerfstudio's depth images."""
    from nerfstudio.utils import colormaps

    images = {}
    for name in ("distance", "depth", "median_distance"):
        if name in outputs:
            images[name] = colormaps.apply_depth_colormap(outputs[name], accumulation=outputs["accumulation"])
    if "normal" in outputs:
        images["normal"] = outputs["normal"]
    return images


def distance_statistics(outputs: Dict[str, Tensor], valid: Tensor) -> Dict[str, float]:
    """ns-eval's per-image `mean_distance` and `mean_depth` over valid rays that hit something (each omitted
    where no such ray exists): the two conventions, named apart."""
    hit = valid & (outputs["accumulation"][..., 0] > 0)
    stats = {}
    for name, mask in (("mean_distance", hit), ("mean_depth", hit & outputs["depth_defined"][..., 0])):
        source = outputs["distance" if name == "mean_distance" else "depth"][..., 0]
        if bool(mask.any()):
            stats[name] = float(source[mask].mean())
    return stats
