"""A training or test camera's rays at their own readout times (rolling shutter), for the model's renders.

A camera whose data carries a rolling shutter (geer_ns/data/rolling_shutter.py) is rendered as captured: each
ray's time from its position on the sensor, its pose between the start pose (with any pose adjustment) and the
end pose, the whole in the frame of the mid-readout pose (geer_ns/cameras/shutter.py, render/moving.py). Every
other camera, the viewer's included, is rendered with one pose: the static scene.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch
from torch import Tensor

from nerfstudio.cameras.cameras import Cameras

from geer_ns.cameras.shutter import READOUTS, ray_times, rolling_rays
from geer_ns.data.rolling_shutter import GLOBAL, MOTION_KEY, READOUT_KEY, end_pose
from geer_ns.data.views import host_camera_model
from geer_ns.errors import OptionError
from geer_ns.refinement.readout import ReadoutRefinement
from geer_ns.render import RayGrid
from geer_ns.render.moving import MovingRays
from geer_ns.render.transforms import world_to_camera_opencv

_FLIP = (1.0, -1.0, -1.0)  # nerfstudio's OpenGL camera axes -> OpenCV's


def readout_of(camera: Cameras) -> Optional[Tuple[str, Tensor]]:
    """(readout, motion [12]) of a one-camera Cameras with a rolling shutter, else None."""
    md = camera.metadata or {}
    if READOUT_KEY not in md:
        return None
    index = int(md[READOUT_KEY].reshape(-1)[0])
    return None if index == GLOBAL else (READOUTS[index], md[MOTION_KEY].reshape(-1)[:12])


def refuse_rolling_shutter(cameras, what: str) -> None:
    """OptionError naming `what` when one of `cameras` (one-camera Cameras) has a rolling shutter: a render path
    without per-ray poses, which would otherwise render it with one pose, silently."""
    if any(readout_of(camera) is not None for camera in cameras):
        raise OptionError(f"geer: {what} does not render rolling-shutter images yet (each ray at its own pose); "
                          "train them with --pipeline.model.distributed images (the default)")


def model_view(model, camera: Cameras, grid: RayGrid, device) -> Tuple[Tensor, Optional[MovingRays]]:
    """shutter_view for a GeerModel's render of `camera`: its render pose, while training the readout
    refinement, otherwise the refined frame's scale (which scales the readout's travel as it scales the scene)."""
    frame = None if model.training else model.refined_frame
    scale = 1.0 if frame is None else float(frame.similarity(model.camera_optimizer).scale)
    return shutter_view(camera, model.render_pose(camera), grid, device, model.readout if model.training else None,
                        scale)


def shutter_view(camera: Cameras, pose: Tensor, grid: RayGrid, device, refinement: Optional[ReadoutRefinement] = None,
                 scale: float = 1.0) -> Tuple[Tensor, Optional[MovingRays]]:
    """(world-to-camera viewmat [4, 4] float64, MovingRays or None) to render `camera` at nerfstudio pose `pose`
    [3, 4] (its start pose, adjusted) on `grid`: the pose's own viewmat and None for a global shutter.
    `refinement`: the training images' readout adjustments (used for a camera with a training image index);
    `scale`: of the frame `pose` is in relative to the data's (the readout's travel is the data's)."""
    readout = readout_of(camera)
    if readout is None:
        return world_to_camera_opencv(pose.to(device, torch.float64)), None
    name, motion = readout
    image = (camera.metadata or {}).get("cam_idx")
    if refinement is not None and image is not None:
        motion = refinement.adjusted(motion, int(image))
    if scale != 1.0:
        motion = torch.cat([motion.reshape(3, 4)[:, :3], motion.reshape(3, 4)[:, 3:] * scale], 1).reshape(12)
    start = pose.to(device, torch.float64)
    end = end_pose(start, motion.to(device))
    flip = start.new_tensor(_FLIP)

    def opencv(c2w: Tensor) -> Tensor:
        return torch.cat([c2w[:, :3] * flip, c2w[:, 3:]], dim=1)

    key = ("readout_times", name)
    if key not in grid._cache:  # a view's grid comes round every epoch: its rays' times are fixed
        grid._cache[key] = ray_times(host_camera_model(camera), grid.dirs.cpu(), name).to(device, torch.float64)
    viewmat, origins, dirs, offset = rolling_rays(grid.dirs.to(device, torch.float64), grid._cache[key],
                                                  opencv(start), opencv(end))
    # The moved directions' tile bounds are made per render (MovingRays.tile_grid): kept per image they would hold
    # a grid's worth of bounds for every training image.
    return viewmat, MovingRays(origins, dirs, offset)
