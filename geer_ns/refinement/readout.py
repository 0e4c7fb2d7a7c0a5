"""Refining a rolling-shutter image's camera motion during its readout (--pipeline.model.readout-refinement).

Each training image gets 6 adjustments of its readout motion (geer_ns/data/rolling_shutter.py: the end pose
relative to the start, in the start camera's frame): a rotation vector composed on the motion's rotation and a
move added to its translation. The renders' rays (geer_ns/shutter_views.py) carry their gradient: every ray's
origin and direction depends on the end pose in proportion to its readout time. Zero adjustments leave the
motion as the data gave it; images without a rolling shutter never use theirs.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from geer_ns.cameras.shutter import so3_exp


class ReadoutRefinement(nn.Module):
    """adjustments [num_images, 6] (rotation vector, move), float64, zero at the start."""

    def __init__(self, num_images: int):
        super().__init__()
        self.adjustments = nn.Parameter(torch.zeros(num_images, 6, dtype=torch.float64))

    def adjusted(self, motion: Tensor, image: int) -> Tensor:
        """The motion [12] (R row-major, t) of training image `image` with its adjustment applied."""
        m = motion.to(self.adjustments).reshape(3, 4)
        delta = self.adjustments[image]
        return torch.cat([m[:, :3] @ so3_exp(delta[:3]), m[:, 3:] + delta[3:, None]], dim=1).reshape(12)
