"""Lens refinement: each training camera's intrinsics (focal lengths, principal point, distortion) learnt with
the scene, through the rays they define.

A camera (a distinct set of intrinsics among the training images, shared by every image taken with it) gets
one zero-initialised delta per refined parameter:

    focal:      fx = fx0 exp(d), fy = fy0 exp(d)   (relative: one learning rate for any image size; one delta for
                both, so the aspect ratio stays as calibrated, unless `aspect`: then one delta each)
    principal:  cx = cx0 + d sqrt(fx0 fy0)   (in units of the focal length, ~radians at the centre)
    others:     k  = k0 + d              (distortion coefficients, FOV's omega, Mei's xi, skew in focal units)

Rays of refined cameras. A pixel position x (a native pixel centre, or the source position of a BEAP cell,
below) sees the ray d(p) with project(d(p); p) = x. Each render refreshes the ray of every such x from its
last value by Newton steps on the unit sphere, d <- normalize(d - J^+ (project(d; p) - x)), J = d project / d d
(2x3, by float64 central differences; its pseudo-inverse maps into the tangent plane): three detached chord steps,
then one more with J at the result and the intrinsics as tensors that require grad, so that
d(d)/d(p) = -J^+ d project / d p, the implicit-function gradient (its value moves by the converged residual
only). The renderer returns dL/d(ray direction) (both compiled backends), which autograd carries to the deltas.
A refresh whose residual stays above a thousandth of a pixel (a large jump of the intrinsics) is redone by the
camera model's own unprojection.

BEAP supervision. A BEAP target image was resampled once from the source image: cell c holds the source image at
x_c = project(d_c; p0), the original lens. The target is kept as cached; cell c is rendered along the ray the
refined lens gives x_c, d_c(p), so that a cell still compares the source pixels at x_c with the ray through
x_c (no resampling, whatever the step; the grid's cells become slightly non-uniform in angle, which the
renderer does not mind). Native views render each pixel centre's refined ray.

docs/refinement.md says how to use it (`--pipeline.model.lens-refinement`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Dict, List, Literal, Optional, Sequence, Tuple

import torch
from torch import Tensor, nn

from geer_ns.cameras import CameraModel
from geer_ns.errors import OptionError
from geer_ns.render import RayGrid

LensMode = Literal["off", "focal", "focal+principal", "full"]
MODES: Tuple[str, ...] = ("off", "focal", "focal+principal", "full")
FOCAL_FIELDS = ("fx", "fy", "f")
PRINCIPAL_FIELDS = ("cx", "cy")
PIXEL_FIELDS = ("fx", "fy", "f", "cx", "cy", "skew")  # fields in pixels (scale with the image)
_NEWTON_STEPS = 3  # detached (chord) Newton steps before the attaching one
_RESIDUAL_PX = 1e-3  # a refresh above this (pixels, float64) is redone by the model's unprojection
_TILE = 16


def refined_fields(camera: CameraModel, mode: str) -> Tuple[str, ...]:
    """The names of `camera`'s float fields `mode` refines (none for a camera without intrinsics)."""
    if mode not in MODES:
        raise ValueError(f"lens_refinement must be one of {', '.join(MODES)}, got {mode!r}")
    names = [f.name for f in dataclasses.fields(camera) if f.name not in ("width", "height")]
    keep = []
    for name in names:
        if name in FOCAL_FIELDS:
            keep.append(mode != "off")
        elif name in PRINCIPAL_FIELDS:
            keep.append(mode in ("focal+principal", "full"))
        else:  # FOV's omega = 0 is the pinhole limit, where the model divides by omega
            keep.append(mode == "full" and not (name == "omega" and getattr(camera, name) == 0))
    return tuple(n for n, k in zip(names, keep) if k)


def refined_parameters(camera: CameraModel, mode: str, aspect: bool = False) -> Tuple[Tuple[str, ...], ...]:
    """The fields `mode` refines, grouped by the delta they share: fx and fy one group unless `aspect` (the
    ratio fy / fx refined too), every other field its own.

    Why the ratio is kept by default: cameras that stay upright while they move (a handheld walk, a car, a robot)
    cannot tell a wrong fy / fx from a vertical stretch of the scene, which the Gaussians learn; refined alone, fy
    drifts with the scene (docs/refinement.md)."""
    fields = refined_fields(camera, mode)
    if aspect or not ("fx" in fields and "fy" in fields):
        return tuple((name,) for name in fields)
    rest = tuple((name,) for name in fields if name not in ("fx", "fy"))
    return (("fx", "fy"),) + rest


def tensor_camera(camera: CameraModel, values: Dict[str, Tensor]) -> CameraModel:
    """A copy of `camera` whose fields named in `values` are those tensors (projection only: its `project` is
    then differentiable in them). Validation is skipped; the maximum angle is the original camera's."""
    copy = object.__new__(type(camera))
    for f in dataclasses.fields(camera):
        object.__setattr__(copy, f.name, values.get(f.name, getattr(camera, f.name)))
    copy.__dict__["max_angle"] = camera.max_angle
    return copy


def rescaled(values: Dict[str, object], factor: int) -> Dict[str, object]:
    """Intrinsics of the image downscaled by `factor` (nerfstudio's rescale_output_resolution: pixel fields / f)."""
    return {k: (v / factor if k in PIXEL_FIELDS else v) for k, v in values.items()}


def _jacobian(camera: CameraModel, dirs: Tensor) -> Tensor:
    """[R, 2, 3] d project / d direction by float64 central differences (step 1e-6 on unit directions: error
    ~1e-10 relative, far below what a Newton step or the gradient needs; forward-mode AD through the lens
    models' Python scalars cost 5x more)."""
    h = 1e-6
    cols = []
    for axis in range(3):
        step = torch.zeros_like(dirs)
        step[:, axis] = h
        cols.append((camera.project(dirs + step)[0] - camera.project(dirs - step)[0]) / (2 * h))
    return torch.stack(cols, -1)


def _newton_step(dirs: Tensor, jac: Tensor, residual: Tensor) -> Tensor:
    """normalize(dirs - J^+ residual), J^+ = J^T (J J^T)^-1 (zero step where J J^T is singular)."""
    jjt = jac @ jac.transpose(-1, -2)
    det = jjt[:, 0, 0] * jjt[:, 1, 1] - jjt[:, 0, 1] * jjt[:, 1, 0]
    ok = det.abs() > 1e-30
    det = torch.where(ok, det, torch.ones_like(det))
    inv = torch.stack([torch.stack([jjt[:, 1, 1], -jjt[:, 0, 1]], -1),
                       torch.stack([-jjt[:, 1, 0], jjt[:, 0, 0]], -1)], -2) / det[:, None, None]
    step = (jac.transpose(-1, -2) @ (inv @ residual[..., None]))[..., 0]
    moved = dirs - torch.where(ok[:, None], step, torch.zeros_like(step))
    return moved / moved.norm(dim=-1, keepdim=True)


def refresh_rays(fixed: CameraModel, attached: CameraModel, pixels: Tensor, dirs: Tensor,
                 valid: Tensor) -> Tuple[Tensor, float]:
    """Rays [R, 3] (float64) through `pixels` [R, 2] of the camera whose intrinsics `attached` holds (tensors
    that may require grad; `fixed` the same values detached), Newton-refreshed from `dirs`; invalid rays keep
    theirs. Returns (rays, the largest pixel residual over the valid rays before the attaching step)."""
    d = dirs.detach()
    with torch.no_grad():
        jac = _jacobian(fixed, d)  # chord steps: the Jacobian barely moves over a step's change of the lens
        for _ in range(_NEWTON_STEPS):
            d = torch.where(valid[:, None], _newton_step(d, jac, fixed.project(d)[0] - pixels), d)
        residual = (fixed.project(d)[0] - pixels).norm(dim=-1)
        worst = float(torch.where(valid, residual, torch.zeros_like(residual)).max()) if len(d) else 0.0
        jac = _jacobian(fixed, d)
    out = _newton_step(d, jac, attached.project(d)[0] - pixels)  # value: d; gradient: the implicit one
    return torch.where(valid[:, None], out, d), worst


def camera_groups(models: Sequence[CameraModel]) -> Tuple[List[CameraModel], List[int]]:
    """(the distinct camera models in the order of their first image, each image's index into them)."""
    distinct: Dict[CameraModel, int] = {}
    image_camera = [distinct.setdefault(m, len(distinct)) for m in models]
    return list(distinct), image_camera


def training_camera_groups(cameras) -> Tuple[List[CameraModel], List[int]]:
    """camera_groups of nerfstudio Cameras (the training images'), as geer's camera models."""
    from geer_ns.data.views import camera_model

    return camera_groups([camera_model(cameras, i) for i in range(len(cameras))])


def attach(model, cameras) -> None:
    """Give a geer model its per-camera state once the training cameras (nerfstudio Cameras) are known (the
    pipeline calls this before the optimizers are made): the lens refinement when the model's lens_refinement
    is on, and one vignetting per camera when its appearance model is on."""
    if model.config.lens_refinement == "off" and model.appearance is None:
        return
    distinct, image_camera = training_camera_groups(cameras)
    if model.appearance is not None:
        model.appearance.set_cameras(distinct, image_camera)
    if model.config.lens_refinement != "off":
        lens = LensRefinement(distinct, image_camera, model.config.lens_refinement, model.config.lens_refinement_start,
                              aspect=model.config.lens_refinement_aspect)
        model.lens = lens.to(model.device)


@dataclass
class _RayState:
    """The positions a view's rays pass through and their last refreshed directions (float64, detached)."""

    pixels: Tensor  # [R, 2] in the refined camera's pixels (after the downscale)
    valid: Tensor  # [R] bool
    dirs: Tensor  # [R, 3]
    factor: int  # the downscale of the camera the pixels belong to (1 for BEAP: full-resolution source)
    last: Optional[tuple] = None  # (the deltas, a view rebuilt from their rays) of the last render without grad


class LensRefinement(nn.Module):
    """The refined intrinsics of the training cameras: `cameras` their distinct models, in the order of their
    first image; `image_camera[i]` the camera of training image i; `aspect`: refine fy / fx too
    (refined_parameters). `deltas[c, j]` moves the fields `delta_fields[c][j]` of camera c."""

    def __init__(self, cameras: Sequence[CameraModel], image_camera: Sequence[int], mode: str, start: int = 0,
                 aspect: bool = False):
        super().__init__()
        self.mode, self.start = mode, int(start)
        self.cameras: List[CameraModel] = list(cameras)
        self.image_camera = [int(i) for i in image_camera]
        self.index: Dict[CameraModel, int] = {cam: i for i, cam in enumerate(self.cameras)}
        self.aspect = aspect
        self.delta_fields = [refined_parameters(cam, mode, aspect) for cam in self.cameras]
        self.deltas = nn.Parameter(torch.zeros(len(self.cameras), self._width(aspect), dtype=torch.float64))
        self._states: Dict[tuple, _RayState] = {}

    def _width(self, aspect: bool) -> int:
        """Deltas per camera with that aspect setting (the most any camera needs, at least one)."""
        return max([len(refined_parameters(cam, self.mode, aspect)) for cam in self.cameras] + [1])

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        """A checkpoint refined with the other aspect setting fails with the option to pass, not a size error."""
        saved = state_dict.get(prefix + "deltas")
        other = not self.aspect
        if saved is not None and saved.shape != self.deltas.shape and \
                tuple(saved.shape) == (len(self.cameras), self._width(other)):
            raise OptionError(f"{prefix}deltas: the checkpoint's lens was refined with lens-refinement-aspect "
                              f"{other}; resume with --pipeline.model.lens-refinement-aspect {other}")
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @classmethod
    def from_cameras(cls, models: Sequence[CameraModel], mode: str, start: int = 0,
                     aspect: bool = False) -> "LensRefinement":
        """One refined camera per distinct model among the training images' `models`."""
        distinct, image_camera = camera_groups(models)
        return cls(distinct, image_camera, mode, start, aspect)

    # ------------------------------------------------------------------------------------ values
    def values(self, camera: int) -> Dict[str, Tensor]:
        """The refined values (float64 tensors, differentiable in the deltas) of camera `camera`'s fields."""
        base = self.cameras[camera]
        delta = self.deltas[camera]
        scale = math.sqrt(base.fx * base.fy) if hasattr(base, "fx") else 1.0
        out = {}
        for j, group in enumerate(self.delta_fields[camera]):
            for name in group:
                v0 = float(getattr(base, name))
                if name in FOCAL_FIELDS:
                    out[name] = v0 * torch.exp(delta[j])
                elif name in PRINCIPAL_FIELDS or name == "skew":
                    out[name] = v0 + scale * delta[j]
                else:
                    out[name] = v0 + delta[j]
        return out

    def refined_camera(self, camera: int) -> CameraModel:
        """Camera `camera` with its refined intrinsics (a plain camera model, floats)."""
        with torch.no_grad():
            values = {k: float(v) for k, v in self.values(camera).items()}
        return dataclasses.replace(self.cameras[camera], **values)

    def refined_cameras(self) -> List[CameraModel]:
        return [self.refined_camera(i) for i in range(len(self.cameras))]

    def active(self, step: int) -> bool:
        """Whether renders at `step` use (and train) the refined intrinsics."""
        return step >= self.start and any(self.delta_fields)

    # ------------------------------------------------------------------------------------- views
    def refine_view(self, view, camera: CameraModel, step: int):
        """`view` (a BeapView or NativeView of the original `camera`, at any downscale) with its rays through
        the refined intrinsics of `camera`'s group: differentiable in the deltas when grad is enabled. A camera
        that is not a training camera (a viewer camera), or a step before `start`, gets `view` back."""
        from geer_ns.data.views import BeapView, NativeView

        group = self.index.get(camera)
        if group is None or not self.delta_fields[group] or not self.active(step):
            return view
        state = self._state(view, camera, group)
        # a render without gradients under unchanged intrinsics (the pose solve's many renders, an eval) reuses
        # the rays of the last one
        deltas = None if torch.is_grad_enabled() else self.deltas[group].detach().clone()
        if deltas is not None and state.last is not None and state.last[0].device == deltas.device and \
                torch.equal(state.last[0], deltas):
            return state.last[1](view)
        full = self.values(group)
        values = rescaled(full, state.factor)
        base = self._scaled_base(group, state.factor)
        fixed = tensor_camera(base, {k: v.detach() for k, v in values.items()})
        attached = tensor_camera(base, values)
        dirs, worst = refresh_rays(fixed, attached, state.pixels, state.dirs, state.valid)
        if worst > _RESIDUAL_PX:  # a jump too far for the refresh: the model's own unprojection, then again
            with torch.no_grad():
                plain = dataclasses.replace(base, **{k: float(v) for k, v in values.items()})
                state.dirs = torch.where(state.valid[:, None], plain.unproject(state.pixels)[0], state.dirs)
            dirs, worst = refresh_rays(fixed, attached, state.pixels, state.dirs, state.valid)
        state.dirs = dirs.detach()
        dirs32 = dirs.to(view.rays.dirs.dtype)
        height, width = view.rays.height, view.rays.width
        rays = RayGrid.from_rays(dirs32.detach().reshape(height, width, 3), view.rays.valid.reshape(height, width),
                                 _TILE)
        rays.dirs = dirs32 if torch.is_grad_enabled() else dirs32.detach()
        if isinstance(view, BeapView):
            def rebuild(v):
                return BeapView(v.camera, v.grid, rays, v.downscale)
        else:
            with torch.no_grad():
                refined = dataclasses.replace(view.camera, **rescaled({k: float(v) for k, v in full.items()},
                                                                      state.factor))

            def rebuild(v):
                return NativeView(refined, rays, v.step)
        if deltas is not None:
            state.last = (deltas, rebuild)
        return rebuild(view)

    def _scaled_base(self, group: int, factor: int) -> CameraModel:
        base = self.cameras[group]
        if factor == 1:
            return base
        fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(base)}
        fields = rescaled(fields, factor)
        fields["width"], fields["height"] = int(base.width / factor), int(base.height / factor)
        return dataclasses.replace(base, **fields)

    def _state(self, view, camera: CameraModel, group: int) -> _RayState:
        """The cached positions of a view's rays (made on the view's first refined render)."""
        from geer_ns.data.views import BeapView

        beap = isinstance(view, BeapView)
        factor = 1 if beap else max(1, round(camera.width / view.camera.width))
        key = (group, "beap" if beap else "native", view.size, factor)
        if key not in self._states:
            valid = view.rays.valid.cpu()
            if beap:  # the source positions of the cells, through the original lens (what the target holds)
                dirs = view.grid.directions(torch.float64).reshape(-1, 3)
                pixels = camera.project(dirs)[0]
            else:
                scaled = self._scaled_base(group, factor)
                pixels = scaled.pixel_centers(torch.float64).reshape(-1, 2)
                dirs = view.rays.dirs.detach().cpu().double()
                dirs = dirs / dirs.norm(dim=-1, keepdim=True)
            self._states[key] = _RayState(pixels, valid, dirs, factor)
        state = self._states[key]
        device = self.deltas.device
        if state.pixels.device != device:
            state.pixels, state.valid, state.dirs = (t.to(device) for t in (state.pixels, state.valid, state.dirs))
        return state
