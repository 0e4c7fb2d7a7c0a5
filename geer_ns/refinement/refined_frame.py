"""The frame a pose-refining run's scene lies in, against the frame its cameras were given in.

Images fix a scene and its cameras only up to a similarity (the gauge): while poses are refined, the scene and the
training cameras drift together by a small rotation, translation and scale that no image sees. Every pose from
outside the run (the test views ns-eval scores, the viewer's and ns-render's cameras) is given in the data's
frame, so a render outside training maps its camera into the scene's frame by the similarity that best maps the
given training poses onto their refined ones; the refined training poses are exported mapped back
(geer_ns/refinement/refined_cameras.py), so that every pose a run reads or writes lives in the given frame.
docs/refinement.md says what this changes in the scores.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import torch
from torch import Tensor

# The centres carry a scale only when they spread (root mean square about their mean) this many times further
# than refinement moved them (about the same mean): not one camera, a rotation-only capture, or a rig a few
# centimetres across whose centres moved as far as that.
_SCALE_SPREAD = 10.0


class Similarity(NamedTuple):
    """x -> scale * rotation @ x + translation (float64, CPU); camera rotations turn by `rotation`."""

    rotation: Tensor  # [3, 3]
    translation: Tensor  # [3]
    scale: float

    def apply(self, c2w: Tensor) -> Tensor:
        """Camera-to-worlds [..., 3, 4] (nerfstudio's, any dtype and device) moved by the similarity."""
        rot = self.rotation.to(c2w.device, torch.float64)
        pose = c2w.to(torch.float64)
        out = torch.cat([rot @ pose[..., :3, :3],
                         self.scale * (rot @ pose[..., :3, 3:]) + self.translation.to(rot)[:, None]], dim=-1)
        return out.to(c2w.dtype)

    def describe(self) -> str:
        """'turned 0.07 degree, moved 0.0035 units, scaled by 0.983' (the scene against the given frame)."""
        cos = min(1.0, max(-1.0, (float(torch.trace(self.rotation)) - 1.0) / 2.0))
        return (f"turned {math.degrees(math.acos(cos)):.3g} degree, moved {float(self.translation.norm()):.3g} "
                f"units, scaled by {self.scale:.4g}")

    def inverse(self) -> "Similarity":
        rot = self.rotation.T
        return Similarity(rot, -(rot @ self.translation) / self.scale, 1.0 / self.scale)


def adjusted_poses(camera_optimizer, c2w: Tensor) -> Tensor:
    """[N, 3, 4] float64 CPU: the training images' camera-to-worlds `c2w` [N, 3, 4] with nerfstudio's camera
    optimizer's corrections (its apply_to_camera: rotation applied in world axes, translation added)."""
    c2w = c2w.detach().to("cpu", torch.float64)
    if camera_optimizer.config.mode == "off":
        return c2w
    with torch.no_grad():
        adj = camera_optimizer(torch.arange(c2w.shape[0])).detach().to("cpu", torch.float64)
    return torch.cat([adj[:, :3, :3] @ c2w[:, :3, :3], c2w[:, :3, 3:] + adj[:, :3, 3:]], dim=-1)


def fit_similarity(given: Tensor, refined: Tensor, guard_scale: bool = True) -> Similarity:
    """The similarity S with refined_i ~ S(given_i) for camera-to-worlds [N, 3, 4], least squares: its rotation
    the chordal mean of the cameras' own turns R'_i R_i^T (their orientations pin it far better than the centres
    of a capture a few camera-lengths across), then the scale and translation that best map the centres given
    that rotation. With guard_scale, the scale is 1 where the centres do not spread well beyond their moves (one
    camera, a rotation-only capture, a small rig)."""
    given, refined = given.to(torch.float64), refined.to(torch.float64)
    turns = (refined[:, :3, :3] @ given[:, :3, :3].transpose(-1, -2)).sum(0)
    u, _, vt = torch.linalg.svd(turns)
    fix = torch.diag(torch.tensor([1.0, 1.0, float(torch.sign(torch.linalg.det(u @ vt)))], dtype=torch.float64))
    rotation = u @ fix @ vt
    centres, moved = given[:, :3, 3], refined[:, :3, 3]
    a = (centres - centres.mean(0)) @ rotation.T
    b = moved - moved.mean(0)
    spread = float(a.square().sum(-1).mean())
    moves = float((b - a).square().sum(-1).mean())
    carries_scale = spread > 0 and (not guard_scale or spread > _SCALE_SPREAD ** 2 * moves)
    scale = float((a * b).sum(-1).mean()) / spread if carries_scale else 1.0
    translation = moved.mean(0) - scale * (rotation @ centres.mean(0))
    return Similarity(rotation, translation, scale)


class RefinedFrame:
    """The given training poses of a run that refines them; `similarity(camera_optimizer)` is the map from the
    given frame into the scene's, at the optimizer's current corrections."""

    def __init__(self, given_c2w: Tensor) -> None:
        """given_c2w: [N, 3, 4] the training images' camera-to-worlds as the dataparser gave them."""
        self.given = given_c2w.detach().to("cpu", torch.float64)
        self._cached: Optional[tuple] = None  # (the corrections' identity and version, their similarity)

    def similarity(self, camera_optimizer) -> Similarity:
        """The similarity at the optimizer's current corrections, refitted only when they changed since the last
        call (the viewer renders many frames between two optimizer steps)."""
        adjustment = getattr(camera_optimizer, "pose_adjustment", None)  # absent in mode off
        key = None if adjustment is None else (id(adjustment), adjustment._version)
        if key is None or self._cached is None or self._cached[0] != key:
            self._cached = (key, fit_similarity(self.given, adjusted_poses(camera_optimizer, self.given)))
        return self._cached[1]


def scene_pose(frame: Optional[RefinedFrame], camera_optimizer, c2w: Tensor) -> Tensor:
    """A camera-to-world [..., 3, 4] given in the data's frame, in the scene's (itself without a frame)."""
    return c2w if frame is None else frame.similarity(camera_optimizer).apply(c2w)
