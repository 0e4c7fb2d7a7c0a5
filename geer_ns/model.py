"""The `geer` model: splatfacto's Gaussians, schedule and densification, rendered exactly with 3DGEER.

It keeps splatfacto's `gauss_params` (means, scales, quats, features_dc, features_rest, opacities). Training
batches are rendered in the view the datamanager cached them in (BEAP or the camera's own rays), evaluation and
viewer cameras on their own pixel rays; losses and metrics count valid pixels only; densification is gsplat's
strategy fed geer's statistics (geer_ns/densify). Nothing assumes CUDA. A training engine (one or many processes)
attaches its state and uses the model's public side only (geer_ns/distributed/engine.py).

Why a subclass of SplatfactoModel rather than a model composing what it reuses: nerfstudio decides by
`isinstance(model, SplatfactoModel)` whether the viewer shows a Gaussian scene (its render state machine, export
panel, crop box) and whether `ns-export gaussian-splat` accepts a run (scripts/exporter.py asserts it). geer
overrides what it renders and scores, and reuses splatfacto's parameter layout, initialization helpers, camera
optimizer, bilateral grid and SH schedule.
"""

from __future__ import annotations

import math
from copy import deepcopy
from dataclasses import dataclass, field
from typing import Dict, List, Literal, Optional, Tuple, Type, Union

import torch
from gsplat.strategy import MCMCStrategy
from pytorch_msssim import SSIM
from torch import Tensor
from torch.fx.experimental.symbolic_shapes import guard_or_false
import tyro

from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.model_components.lib_bilagrid import BilateralGrid
from nerfstudio.models.base_model import ModelConfig
from nerfstudio.models.splatfacto import (
    RGB2SH,
    SplatfactoModel,
    SplatfactoModelConfig,
    num_sh_bases,
    random_quat_tensor,
)
from nerfstudio.utils.colors import get_color
from nerfstudio.utils.rich_utils import CONSOLE

from geer_ns import compat, depth_supervision, resume
from geer_ns import outputs as geer_outputs
from geer_ns.refinement.appearance import Appearance
from geer_ns.metrics.color_corrected import color_corrected_metrics
from geer_ns.data.datamanager import VIEW_KEY
from geer_ns.data.views import BeapView, NativeView, beap_view, camera_model, host_camera_model, native_view
from geer_ns.refinement.lens import LensRefinement
from geer_ns.refinement.readout import ReadoutRefinement
from geer_ns.densify.signal import StepStatistics, ViewProbe, ViewRecord, angular_signal, statistic_widths
from geer_ns.densify.strategy import GeerDefaultStrategy, build_strategy
from geer_ns.errors import OptionError
from geer_ns.distributed.engine import EngineState
from geer_ns.metrics.regions import central_region, downscale_mask, masked_psnr, region_psnr
from geer_ns.options import GeerOwnOptions, check_composite_order, densification_line, ignored_options_set, skipping_line
from geer_ns.metrics.perceptual import build_lpips_if_cached
from geer_ns.refinement.registration import pose_callbacks
from geer_ns.refinement.refined_frame import RefinedFrame, scene_pose
from geer_ns.render import render
from geer_ns.render.backend import announce_backend
from geer_ns.render.cull import view_rows
from geer_ns.render.normals import render_normals
from geer_ns.render.pbf import pbf_lambda_sq
from geer_ns.render.transforms import view_transform, world_to_camera_opencv
from geer_ns.render_guard import RenderGuard, camera_problem, in_viewer_thread, is_viewer_interrupt
from geer_ns.selftest.sentinel import KernelSentinel, ViewInputs
from geer_ns.sh_degrees import packing as sh_packing
from geer_ns.sh_degrees.choice import BandChoice
from geer_ns.shutter_views import model_view

View = Union[BeapView, NativeView]


def _model_config_default(name: str):
    """nerfstudio's default of a ModelConfig field, for re-declaring it hidden (defaults stay nerfstudio's)."""
    return field(default_factory=lambda: deepcopy(getattr(ModelConfig(), name)))


@dataclass
class GeerModelConfig(SplatfactoModelConfig, depth_supervision.DepthSupervisionOptions, GeerOwnOptions):
    _target: Type = field(default_factory=lambda: GeerModel)
    # Ray-marching options of nerfstudio's ModelConfig that no Gaussian model reads: hidden from --help.
    enable_collider: tyro.conf.Suppress[bool] = _model_config_default("enable_collider")
    collider_params: tyro.conf.Suppress[Optional[Dict[str, float]]] = _model_config_default("collider_params")
    loss_coefficients: tyro.conf.Suppress[Dict[str, float]] = _model_config_default("loss_coefficients")
    eval_num_rays_per_chunk: tyro.conf.Suppress[int] = _model_config_default("eval_num_rays_per_chunk")
    prompt: tyro.conf.Suppress[Optional[str]] = _model_config_default("prompt")
    densify_grad_thresh: float = 0.0008
    """Gradient threshold of DefaultStrategy's growth, in gsplat's units (what they mean: docs/densification.md);
    splatfacto's value for AbsGS gradients (gsplat's 0.0002 is for summed gradients, use-absgrad False)."""
    use_absgrad: bool = True
    """Densify on AbsGS's per-pixel absolute gradients (the renderer's backward sums |dL_p/d position| over each
    Gaussian's pixels: no canceling) instead of the summed gradient, as splatfacto does."""
    # splatfacto options geer does not use: accepted (splatfacto command lines still parse), marked, and said
    # once at start-up when set (IGNORED_OPTIONS).
    rasterize_mode: Literal["classic", "antialiased"] = "classic"
    """IGNORED by geer (a gsplat rasterizer option): every Gaussian is evaluated exactly along each ray."""
    output_depth_during_training: bool = False
    """IGNORED by geer: depth is always rendered."""
    color_corrected_metrics: bool = False
    """IGNORED by geer: metrics are computed over the valid pixels, without color correction."""
    n_split_samples: int = 2
    """IGNORED by geer: gsplat's DefaultStrategy splits a Gaussian into two."""


def exact_activation(fn, x: Tensor) -> Tensor:
    """fn(x) evaluated in float64 and rounded to x's dtype. torch's float32 exp and sigmoid round an element by
    where it falls in the tensor (vectorized body, scalar tail); a shard or a subset of the Gaussians then gets
    other bits than the whole model. In float64 those differences are below what rounding to float32 keeps."""
    return fn(x.double()).to(x.dtype) if x.dtype == torch.float32 else fn(x)


# ------------------------------------------------------------------------------------- the model


class GeerModel(SplatfactoModel):
    config: GeerModelConfig

    # ------------------------------------------------------------------------------------- set-up
    def populate_modules(self):
        compat.install()  # before ns-eval / ns-viewer / ns-render load this model's checkpoint (geer_ns/compat.py)
        means = self._initial_means()
        distances, _ = self.k_nearest_sklearn(means.data, 3)
        avg_dist = torch.from_numpy(distances).mean(dim=-1, keepdim=True).clamp_min(1e-7)
        n = means.shape[0]
        features_dc, features_rest = self._initial_features(n)
        self.gauss_params = torch.nn.ParameterDict(
            {
                "means": means,
                "scales": torch.nn.Parameter(torch.log(avg_dist.repeat(1, 3))),
                "quats": torch.nn.Parameter(random_quat_tensor(n)),
                "features_dc": torch.nn.Parameter(features_dc),
                "features_rest": torch.nn.Parameter(features_rest),
                "opacities": torch.nn.Parameter(torch.logit(0.1 * torch.ones(n, 1))),
            }
        )
        self.camera_optimizer = self.config.camera_optimizer.setup(num_cameras=self.num_train_data, device="cpu")
        if self.config.pose_solve_every < 0 or self.config.pose_solve_iterations < 1:
            raise OptionError("--pipeline.model.pose-solve-every must be >= 0 and "
                              "--pipeline.model.pose-solve-iterations >= 1 (got "
                              f"{self.config.pose_solve_every}, {self.config.pose_solve_iterations})")
        if self.config.pose_solve_every > 0 and self.config.camera_optimizer.mode == "off":
            raise OptionError("--pipeline.model.pose-solve-every: needs --pipeline.model.camera-optimizer.mode SO3xR3 "
                              "or SE3 (the pose adjustments it solves)")
        if self.config.pose_refinement_start < 0 or (self.config.pose_refinement_start > 0
                                                     and self.config.camera_optimizer.mode == "off"):
            raise OptionError("--pipeline.model.pose-refinement-start: a step >= 0, with "
                              "--pipeline.model.camera-optimizer.mode SO3xR3 or SE3 (got "
                              f"{self.config.pose_refinement_start}, mode {self.config.camera_optimizer.mode})")
        check_composite_order(self.config)
        self.ssim = SSIM(data_range=1.0, size_average=True, channel=3)
        self._perceptual: Dict[str, object] = {}  # LPIPS, built on first use (not a submodule: no state)
        self.step = 0
        self.crop_box = None
        if self.config.background_color == "random":
            self.background_color = torch.tensor([0.1490, 0.1647, 0.2157])  # viser's default background
        else:
            self.background_color = get_color(self.config.background_color)
        if self.config.use_bilateral_grid:
            shape = self.config.grid_shape
            self.bil_grids = BilateralGrid(num=self.num_train_data, grid_X=shape[0], grid_Y=shape[1], grid_W=shape[2])
        self.appearance = Appearance(self.num_train_data) if self.config.appearance == "exposure" else None
        self.engine_state = EngineState()  # until an engine attaches its own (geer_ns/distributed/engine.py)
        changed = ignored_options_set(self.config, GeerModelConfig())
        if changed:
            CONSOLE.print(f"[yellow]geer: ignoring splatfacto option(s) {', '.join(changed)} (not used by the 3DGEER renderer)")
        self.lens: Optional[LensRefinement] = None  # set with the training cameras (lens_refinement.attach)
        self.readout = ReadoutRefinement(self.num_train_data) if self.config.readout_refinement else None
        self.refined_frame: Optional[RefinedFrame] = None  # set with the training cameras (the pipeline)
        self.strategy, self.strategy_state = build_strategy(self.config, self.num_train_data, self.images_per_step)
        self.views: List[ViewRecord] = []  # this step's rendered training views, for the densification statistics
        self._statistics: Optional[StepStatistics] = None  # the step's statistics, when the engine reduced them
        self._step_background: Optional[Tensor] = None  # one random background per step, for all its views
        self.render_guard = RenderGuard()
        self._said_skipping = False
        self.sentinel = KernelSentinel(self.config.kernel_check_every, say=lambda line: CONSOLE.print(line, markup=False))

    def _initial_means(self) -> torch.nn.Parameter:
        if self.seed_points is not None and not self.config.random_init:
            return torch.nn.Parameter(self.seed_points[0].float().clone())
        return torch.nn.Parameter((torch.rand((self.config.num_random, 3)) - 0.5) * self.config.random_scale)

    def _initial_features(self, n: int) -> Tuple[Tensor, Tensor]:
        dim_sh = num_sh_bases(self.config.sh_degree)
        seeded = self.seed_points is not None and not self.config.random_init and self.seed_points[1].shape[0] > 0
        if not seeded:
            return torch.rand(n, 3), torch.zeros(n, dim_sh - 1, 3)
        rgb = self.seed_points[1].float() / 255.0
        dc = RGB2SH(rgb) if self.config.sh_degree > 0 else torch.logit(rgb, eps=1e-10)
        return dc, torch.zeros(n, dim_sh - 1, 3)

    # ------------------------------------------------------------------------------------- engine
    def attach(self, state: EngineState) -> None:
        """Be trained by the engine whose state this is (geer_ns/distributed/engine.py): before any checkpoint
        is loaded, so that its steps convert to this engine's batch; the strategy is rebuilt for that batch."""
        rebuild = state.images_per_step != self.images_per_step
        self.engine_state = state
        if rebuild:
            self.strategy, self.strategy_state = build_strategy(self.config, self.num_train_data, self.images_per_step)

    @property
    def images_per_step(self) -> int:
        """Images one training step sees over every process (the engine's effective batch; 1 without one)."""
        return self.engine_state.images_per_step

    @property
    def scene_gaussians(self) -> Optional[int]:
        """Gaussians over every shard where this model holds one shard (Gaussian-parallel), else None."""
        return self.engine_state.scene_gaussians

    # ------------------------------------------------------------------------------------- resume
    # A nerfstudio 1.1.5 bug (docs/training.md): splatfacto's load_state_dict replaces the Parameters the trainer's
    # optimizers hold, so `--load-dir` trained nothing. Resize in place and keep the strategy state,
    # step and RNG states with the checkpoint (geer_ns/resume.py).
    def load_state_dict(self, state_dict, strict: bool = True, **kwargs):  # type: ignore[override]
        state_dict = sh_packing.unpacked_model_state(dict(state_dict), self.gauss_params["features_rest"].shape[1])
        if "means" in state_dict:  # splatfacto's backwards compatibility with pre-gauss_params checkpoints
            for name in ("means", "scales", "quats", "features_dc", "features_rest", "opacities"):
                state_dict[resume.GAUSS_PREFIX + name] = state_dict.pop(name)
        resume.resize_in_place(self.gauss_params, state_dict)
        return torch.nn.Module.load_state_dict(self, state_dict, strict=strict, **kwargs)

    def update_to_step(self, step: int) -> None:
        self.step = step  # splatfacto pins 30000 on load; the SH degree schedule needs the real step

    def get_extra_state(self) -> Dict[str, object]:
        return {"step": self.step, "strategy_state": resume.strategy_state(self.strategy_state),
                "images_per_step": self.images_per_step}  # RNG states: the trainer's part

    def set_extra_state(self, state: Dict[str, object]) -> None:
        # A checkpoint's steps are in its own effective batch; this model's are in images_per_step.
        self.step = resume.convert_step(int(state["step"]), int(state.get("images_per_step", 1)), self.images_per_step)
        resume.restore_strategy_state(self.strategy_state, state["strategy_state"], self.device)

    # ---------------------------------------------------------------------------------- rendering
    def view_for(self, camera: Cameras) -> View:
        """The ray grid a camera is rendered on: its cached BEAP view for BEAP-supervised training batches,
        else its own pixel rays (downscaled by splatfacto's resolution schedule while training); through the
        refined lens when lens refinement is on (geer_ns/refinement/lens.py)."""
        kind = (camera.metadata or {}).get(VIEW_KEY, "native") if self.training else "native"
        factor = self._get_downscale_factor()
        model = host_camera_model(camera)
        if kind == "beap":
            view = beap_view(model, factor)
        elif factor > 1:
            camera_small = deepcopy(camera)
            camera_small.rescale_output_resolution(1.0 / factor)
            view = native_view(camera_model(camera_small, 0))
        else:
            view = native_view(model)
        return view if self.lens is None else self.lens.refine_view(view, model, self.step)

    def render_gaussians(self) -> Optional[Dict[str, Tensor]]:
        """Parameters to render (the engine's display copy when set, outside training; cropped to the viewer's
        box when one is set); None if nothing is left."""
        names = ("means", "scales", "quats", "features_dc", "features_rest", "opacities")
        display = self.engine_state.display_gaussians
        shown = display if display is not None and not self.training else None
        params = {name: (self.gauss_params if shown is None else shown)[name] for name in names}
        degrees = self.strategy_state.get(sh_packing.DEGREES)
        if shown is None and degrees is not None:  # each Gaussian's own SH degree (geer_ns/sh_degrees)
            params[sh_packing.DEGREES] = degrees
        if self.crop_box is not None and not self.training:
            keep = self.crop_box.within(self.means).squeeze()
            if keep.sum() == 0:
                return None
            params = {name: p[keep] for name, p in params.items()}
        return params

    def colors(self, params: Dict[str, Tensor]) -> Tuple[Tensor, Union[int, Tensor, None]]:
        """The renderer's colors of `params` (SH coefficients up to the schedule's degree, or sigmoid RGB) and the
        SH degree: one for all, each Gaussian's own where params has its degrees ([N], at most the schedule's),
        None for RGB."""
        if self.config.sh_degree > 0:
            active = min(self.step // self.config.sh_degree_interval, self.config.sh_degree)
            rest = params["features_rest"][:, : num_sh_bases(active) - 1]  # the kernels read no band above
            colors = torch.cat([params["features_dc"][:, None, :], rest], dim=1)
            own = params.get(sh_packing.DEGREES)
            return colors, active if own is None else own.clamp(max=active)
        return exact_activation(torch.sigmoid, params["features_dc"]), None

    def render_options(self) -> Dict[str, object]:
        """The renderer options every render of this model passes (its own, the sharded engines', the split
        evaluation's): the backend the kernel sentinel leaves in use, the PBF lambda rule, the pair budget, the
        compositing order."""
        return dict(backend=self.sentinel.backend(self.config.renderer_backend), lambda_mode=self.config.lambda_mode,
                    max_pairs=self.config.max_pairs, order=self.config.composite_order)

    @staticmethod
    def activated(params: Dict[str, Tensor]) -> Tuple[Tensor, Tensor]:
        """(scales, opacities) the renderer takes: exp of the log-scales, sigmoid of the opacity logits."""
        return (exact_activation(torch.exp, params["scales"]),
                exact_activation(torch.sigmoid, params["opacities"]).squeeze(-1))

    def get_outputs(self, camera: Cameras) -> Dict[str, Union[Tensor, List]]:
        if not isinstance(camera, Cameras):
            return {}
        view = self.view_for(camera)
        height, width = view.size
        params = self.render_gaussians()
        if params is None:
            return self.get_empty_outputs(width, height, self.background_color)
        background = self.render_background().to(params["means"])
        viewmat, motion = model_view(self, camera, view.rays, params["means"].device)
        rows = self.view_rows(params, viewmat, view.rays) if motion is None else None
        if rows is not None:  # the rows the view can see: the same render, for their work only
            params = {name: p[rows] for name, p in params.items()}
        means = params["means"]
        scales, opacities = self.activated(params)
        probe = None
        if self.training and torch.is_grad_enabled():  # not for viewer renders during training
            probe = self.probe(view, means, viewmat, scales, opacities, rows)
            means = probe.displace(means, viewmat)
        colors, sh_degree = self.colors(params)
        options = self.render_options()
        announce_backend(options["backend"], means.device, say=CONSOLE.log, order=options["order"])
        grid = view.rays.to(means.device)
        out = render(
            means, params["quats"], scales, opacities, colors, viewmat, grid, sh_degree=sh_degree,
            background=background, motion=motion, **options,
            **({} if probe is None or probe.absgrad is None else {"absgrad": (probe.signal.lateral, probe.absgrad)}),
        )
        if probe is not None:  # a disagreement makes the sentinel's backend "torch" for every later render
            self.sentinel.check(self.step, options["backend"], ViewInputs(
                means, params["quats"], scales, opacities, colors, viewmat, grid, sh_degree, background,
                self.config.lambda_mode, motion))
            self.views.append(probe.record(out.visible.detach(), out.max_weight))
        normals = None
        if not self.training:  # forward only: no loss reads normals
            normals = render_normals(means, params["quats"], scales, opacities, viewmat, view.rays.to(means.device),
                                     **options)
        return self.view_outputs(out, view, background, camera, normals)

    def view_rows(self, params: Dict[str, Tensor], viewmat: Tensor, grid) -> Optional[Tensor]:
        """The rows of `params` a view (its ray grid) can see (geer_ns/render/cull.py), or None: every row (the cull
        off, or every row seen)."""
        if not self.config.view_cull:
            return None
        rows = view_rows(params["means"], torch.exp(params["scales"].detach().amax(-1)),
                         torch.sigmoid(params["opacities"].detach()).reshape(-1), viewmat, grid, self.config.lambda_mode)
        return None if guard_or_false(rows.shape[0] == params["means"].shape[0]) else rows  # symbolic: the rows

    def step_rows(self) -> Tensor:
        """[N] bool: the Gaussians this process's views of the step so far could see (their densification
        records' visible rows): the rows a selective optimizer steps."""
        seen = torch.zeros(self.num_points, dtype=torch.bool, device=self.device)
        for record in self.views:
            rows = record.rows.to(self.device) if record.rows is not None else torch.arange(self.num_points,
                                                                                            device=self.device)
            seen[rows[record.visible.to(self.device)]] = True
        return seen

    def render_pose(self, camera: Cameras) -> Tensor:
        """[3, 4] the camera-to-world a render of `camera` (one camera) uses: while training, the training image's
        with its pose adjustment; otherwise the camera as given in the data's frame, mapped into the scene's when
        poses are refined (geer_ns/refinement/refined_frame.py)."""
        if self.training:
            if not self.refining_poses:
                return camera.camera_to_worlds[0]
            return self.camera_optimizer.apply_to_camera(camera)[0]
        return scene_pose(self.refined_frame, self.camera_optimizer, camera.camera_to_worlds[0])

    @property
    def refining_poses(self) -> bool:
        """Whether this training step renders with (and trains) the pose adjustments."""
        return self.camera_optimizer.config.mode != "off" and self.step >= self.config.pose_refinement_start

    @staticmethod
    def viewmat(camera_to_world: Tensor, device) -> Tensor:
        """The world-to-camera matrix (OpenCV axes) of a nerfstudio pose, in float64 (see view_transform)."""
        return world_to_camera_opencv(camera_to_world.to(device, torch.float64))

    def view_outputs(self, out, view: View, background: Tensor, camera: Cameras, normals=None) -> Dict[str, Tensor]:
        """nerfstudio's outputs of a render of `camera` (and its bilateral grid while training)."""
        height, width = view.size
        outputs = self._outputs(out, view, background, normals)
        cam_idx = (camera.metadata or {}).get("cam_idx")
        if self.config.use_bilateral_grid and self.training and cam_idx is not None:
            outputs["rgb"] = self._apply_bilateral_grid(outputs["rgb"][None], cam_idx, height, width)[0]
        if self.appearance is not None:
            image = cam_idx if self.training else None
            outputs["rgb"] = self.appearance(outputs["rgb"], view.rays.dirs, image,
                                             self.appearance.camera_of(image, host_camera_model(camera)))
        return outputs

    def probe(self, view: View, means: Tensor, viewmat: Tensor, scales: Tensor, opacities: Tensor,
              rows: Optional[Tensor] = None) -> ViewProbe:
        """The densification leaves of a training view of these Gaussians (geer_ns/densify/signal.py): the
        model's `rows` (the ones the view sees: a sharded render's probe is as large as that), or all of them
        (None). means, scales, opacities: those Gaussians' ([K,3], [K,3] activated, [K])."""
        means_c = view_transform(means.detach(), viewmat)
        lam2, _ = pbf_lambda_sq(opacities.detach(), self.config.lambda_mode)
        full = 1 if isinstance(view, BeapView) else self._get_downscale_factor()  # a BEAP view's camera is full size
        widths = statistic_widths(view.camera.width * full, view.camera.height * full, self.config.densify_units)
        signal = angular_signal(view.project, view.rays.num_valid, view.center_solid_angle, means_c,
                                scales, lam2, view.source_project, widths)
        return ViewProbe.zeros(signal, means, self.config.use_absgrad, rows)

    def render_background(self) -> Tensor:
        """splatfacto's background color, with one random color per training step (drawn at its first view):
        every view of a step, on every process, composites over the same color, and the random stream stays
        the same however a step's views are split over processes."""
        if self.config.background_color == "random" and self.training:
            if self._step_background is None:
                self._step_background = torch.rand(3, device=self.device)
            return self._step_background
        return super()._get_background_color()

    def _get_background_color(self) -> Tensor:  # splatfacto's name, for its own callers
        return self.render_background()

    def _outputs(self, out, view: View, background: Tensor, normals=None) -> Dict[str, Tensor]:
        height, width = view.size
        acc = out.accumulation
        outputs = {
            "rgb": out.rgb.clamp(0.0, 1.0),
            **geer_outputs.geometry_outputs(out, view.rays.dirs.to(acc.device), normals, median=not self.training),
            "accumulation": acc,
            "background": background if self.training else background.expand(height, width, 3),
            "valid_rays": view.rays.to(out.rgb.device).valid.reshape(height, width, 1),  # cached per device
        }
        if not self.training and isinstance(view, NativeView):
            dirs = view.rays.dirs.reshape(height, width, 3)
            half = self.config.central_half_angles_deg
            central = central_region(view.camera, dirs, None if half is None else tuple(math.radians(a) for a in half))
            if central is not None:
                outputs["central_region"] = central[..., None].to(out.rgb.device)
        return outputs

    @torch.no_grad()
    def get_outputs_for_camera(self, camera: Cameras, obb_box=None) -> Dict[str, Tensor]:
        """Render any nerfstudio camera (PERSPECTIVE, FISHEYE, FISHEYE624, EQUIRECTANGULAR) from its own rays.

        In the viewer's render thread a camera that cannot be rendered (zero or 180-degree field of view, NaN
        pose, empty image) gives the last good frame and one log line, so that the thread survives
        (geer_ns/render_guard.py); elsewhere (ns-eval, ns-render) it is an error naming the problem."""
        assert camera is not None, "must provide camera to gaussian model"
        self.set_crop(obb_box)
        problem = camera_problem(camera)
        if problem is None:
            try:
                outputs = self.get_outputs(camera.to(self.device))
                if in_viewer_thread():
                    outputs = geer_outputs.viewer_outputs(outputs)
                return self.render_guard.remember(outputs)
            except Exception as error:  # noqa: BLE001 - the viewer thread must survive any of them
                if is_viewer_interrupt(error) or not in_viewer_thread():
                    raise
                problem = f"{type(error).__name__}: {error}"
        if not in_viewer_thread():
            raise ValueError(f"geer: cannot render this camera: {problem}")
        size = [max(1, int(getattr(camera, k).reshape(-1)[0])) for k in ("width", "height")]
        return self.render_guard.fallback(problem, self.get_empty_outputs(*size, self.background_color.to(self.device)))

    # ------------------------------------------------------------------------------- densification
    def step_cb(self, optimizers, step):
        super().step_cb(optimizers, step)
        self._step_background = None
        if not self._said_skipping:
            self._said_skipping = True
            sharded = self.scene_gaussians is not None
            CONSOLE.log(f"geer: {densification_line(self.config)}; "
                        f"{skipping_line(self.config, self.chooses_sh_degrees(), sharded)}")
        if step == self.config.pose_refinement_start > 0:
            CONSOLE.log(f"geer: step {step}: pose refinement starts ({self.camera_optimizer.config.mode}, "
                        "pose-refinement-start)")

    @property
    def needs_step_statistics(self) -> bool:
        """Whether step_post_backward will read this step's statistics (DefaultStrategy, before its last split)."""
        return isinstance(self.strategy, GeerDefaultStrategy) and self.step < self.strategy.refine_stop_iter

    def step_statistics(self) -> StepStatistics:
        """This process's densification statistics of the step so far (its views, after their backward)."""
        return StepStatistics.of_views(self.views, self.num_points, self.device)

    def use_step_statistics(self, statistics: StepStatistics) -> None:
        """The step's statistics over every process (the engine's reduction), for step_post_backward."""
        self._statistics = statistics

    def step_post_backward(self, step):
        assert step == self.step
        statistics = self._statistics
        if statistics is None and self.needs_step_statistics:  # no engine reduced them: this process's views
            statistics = self.step_statistics()
        self.views, self._statistics = [], None
        if isinstance(self.strategy, MCMCStrategy):
            lr = self.optimizers["means"].param_groups[0]["lr"]
            self.strategy.step_post_backward(self.gauss_params, self.optimizers, self.strategy_state, step, {}, lr=lr)
            return
        self.strategy.step_post_backward(self.gauss_params, self.optimizers, self.strategy_state, step,
                                         {"statistics": statistics}, packed=False)

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        callbacks = [
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], self.step_cb,
                             args=[training_callback_attributes.optimizers]),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.step_post_backward),
        ]
        if self.chooses_sh_degrees() and training_callback_attributes.trainer is not None:
            callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], BandChoice(
                training_callback_attributes.pipeline, training_callback_attributes.optimizers,
                training_callback_attributes.trainer, self.config.sh_budget_db, say=CONSOLE.log)))
        return callbacks + pose_callbacks(training_callback_attributes, say=CONSOLE.log)

    def chooses_sh_degrees(self) -> bool:
        """Whether each Gaussian's SH degree is chosen, at the run's last step (geer_ns/sh_degrees/choice.py): not
        with sh-per-gaussian off, without SH, or with the Gaussians sharded over processes."""
        return self.config.sh_per_gaussian and self.config.sh_degree > 0 and self.scene_gaussians is None

    # ------------------------------------------------------------------------------------- losses
    def supervised_mask(self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]) -> Tensor:
        """[H,W,1] bool: supervised pixels (the datamanager's validity mask and the rendered rays)."""
        valid = outputs["valid_rays"].to(self.device)
        if "mask" in batch:
            mask = downscale_mask(batch["mask"].to(self.device), self._get_downscale_factor())
            valid = valid & mask
        return valid

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Tensor]:
        gt = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])
        valid = self.supervised_mask(outputs, batch)[..., 0]
        squared = torch.where(valid[..., None], (outputs["rgb"].detach() - gt) ** 2, 0.0)  # no boolean index: no sync
        mse = (squared.sum() / (valid.sum() * gt.shape[-1]).clamp_min(1)).clamp_min(1e-10)
        metrics = {"psnr": -10.0 * torch.log10(mse), "gaussian_count": self.scene_gaussians or self.num_points}
        self.camera_optimizer.get_metrics_dict(metrics)
        return metrics

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        return {**self.get_image_loss_dict(outputs, batch), **self.get_step_loss_dict()}

    def get_image_loss_dict(self, outputs, batch) -> Dict[str, Tensor]:
        """The losses of one rendered image (a step averages them over its images)."""
        gt = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])
        valid = self.supervised_mask(outputs, batch)
        pred = torch.where(valid, outputs["rgb"], gt)  # invalid pixels equal: no loss, no SSIM edge
        l1 = (pred - gt).abs().sum() / (valid.sum() * gt.shape[-1]).clamp_min(1)
        ssim = self.ssim(gt.permute(2, 0, 1)[None], pred.permute(2, 0, 1)[None])
        losses = {"main_loss": (1 - self.config.ssim_lambda) * l1 + self.config.ssim_lambda * (1 - ssim)}
        target = depth_supervision.target_of(batch, self._get_downscale_factor(), self.device)
        if target is not None and self.config.depth_loss_weight > 0:
            losses["depth_loss"] = depth_supervision.depth_loss(outputs["distance"], outputs["accumulation"], target,
                                                                valid, self.config)
        return losses

    def get_step_loss_dict(self) -> Dict[str, Tensor]:
        """The losses of the parameters alone (regularizers), once per step whatever its images."""
        losses = {"scale_reg": self._scale_regularization()}
        if isinstance(self.strategy, MCMCStrategy):
            losses["opacity_reg"] = self.config.mcmc_opacity_reg * torch.sigmoid(self.opacities).mean()
            losses["mcmc_scale_reg"] = self.config.mcmc_scale_reg * torch.exp(self.scales).mean()
        if self.training:
            if self.refining_poses:
                self.camera_optimizer.get_loss_dict(losses)
            if self.appearance is not None:
                losses["appearance_reg"] = self.config.appearance_reg * self.appearance.regularization()
        return losses

    def get_param_groups(self) -> Dict[str, List[torch.nn.Parameter]]:
        groups = super().get_param_groups()
        if self.appearance is not None:
            groups["appearance"] = list(self.appearance.parameters())
        if self.lens is not None:
            groups["lens_opt"] = [self.lens.deltas]
        if self.readout is not None:
            groups["readout_opt"] = [self.readout.adjustments]
        return groups

    def _scale_regularization(self) -> Tensor:
        if not (self.config.use_scale_regularization and self.step % 10 == 0):
            return torch.tensor(0.0, device=self.device)
        scale = torch.exp(self.scales)
        ratio = scale.amax(dim=-1) / scale.amin(dim=-1)
        return 0.1 * self._scene_mean(torch.clamp_min(ratio, self.config.max_gauss_ratio) - self.config.max_gauss_ratio)

    def _scene_mean(self, values: Tensor) -> Tensor:
        """The mean over the scene's Gaussians: all of them, also where this model holds one shard."""
        return values.mean() if self.scene_gaussians is None else values.sum() / self.scene_gaussians

    # ------------------------------------------------------------------------------------ metrics
    def _lpips(self):
        if "lpips" not in self._perceptual:
            metric = build_lpips_if_cached()
            self._perceptual["lpips"] = metric.to(self.device) if metric is not None else None
        return self._perceptual["lpips"]

    def get_image_metrics_and_images(self, outputs, batch) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        """Native-image metrics over valid pixels: PSNR, SSIM, LPIPS (when its weights are cached), the
        central / peripheral PSNR of the paper's App. G and the color-corrected psnr_cc / ssim_cc."""
        gt = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])
        valid = self.supervised_mask(outputs, batch)
        pred = torch.where(valid, outputs["rgb"], gt)
        psnr = masked_psnr(pred, gt, valid[..., 0])
        metrics: Dict[str, float] = {"psnr": float("nan") if psnr is None else psnr}
        gt_b, pred_b = gt.permute(2, 0, 1)[None], pred.permute(2, 0, 1)[None]
        metrics["ssim"] = float(self.ssim(gt_b, pred_b))
        lpips = self._lpips()
        if lpips is not None:
            metrics["lpips"] = float(lpips(gt_b.clamp(0, 1), pred_b.clamp(0, 1)))
        metrics.update(region_psnr(pred, gt, valid[..., 0], outputs.get("central_region")))
        metrics.update(color_corrected_metrics(pred, gt, valid[..., 0], self.ssim))
        metrics["valid_fraction"] = float(valid.float().mean())
        metrics.update(geer_outputs.distance_statistics(outputs, valid[..., 0]))
        metrics.update(depth_supervision.depth_metrics(outputs, batch, valid[..., 0]))
        images = {"img": torch.cat([gt, outputs["rgb"] * valid], dim=1), **geer_outputs.distance_images(outputs)}
        return metrics, images
