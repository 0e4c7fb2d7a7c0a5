"""geer's own model options (the `ns-train geer` flags geer adds to splatfacto's), and the lists --help shows.

GeerModelConfig (geer_ns/model.py) lists GeerOwnOptions after SplatfactoModelConfig among its bases: dataclasses
collect fields along the reversed MRO, so these come first in `ns-train geer --help`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Literal, Optional, Tuple

from geer_ns.densify.signal import DensifyUnits
from geer_ns.refinement.lens import LensMode
from geer_ns.refinement.registration import CameraRefinement
from geer_ns.errors import OptionError
from geer_ns.render.backend import Backend
from geer_ns.render.order import CompositeOrder
from geer_ns.render.pbf import LambdaMode
from geer_ns.selftest.sentinel import DEFAULT_EVERY


@dataclass
class GeerOwnOptions:
    """geer's own model options (first in --help: see the module docstring)."""

    strategy: Literal["default", "mcmc"] = "default"
    """Densification: gsplat's DefaultStrategy (3DGS heuristics) or MCMCStrategy."""
    max_gaussians: int = 0
    """Most Gaussians densification may create (0: no limit); the strongest candidates grow first. With
    strategy=mcmc, the cap of MCMCStrategy when set."""
    densify_units: DensifyUnits = "image"
    """What densification's gradient and screen-size statistics count: halves of each camera's own image, as
    gsplat counts ("image": splatfacto's thresholds mean what they mean there, at every resolution), or pixels of
    a 60-degree reference camera 300 pixels across ("reference": fewer Gaussians below 300 pixels, more above).
    The default measured best over two scenes and two cameras (benchmarks/densify_default.md)."""
    densify_min_pixels: float = 1.0
    """A Gaussian splits or duplicates only where some training view resolves it: its radius (the 1/255
    contour) at least this many of that view's pixels. Finer Gaussians add nothing the images can show."""
    prune_unseen: bool = True
    """Prune Gaussians whose blend weight stayed below 1/255 on every training ray for a whole pass over the
    training images (too faint, or hidden behind opaque surfaces in every view)."""
    sh_per_gaussian: bool = True
    """Each Gaussian keeps only the SH bands its training images show: chosen once, at the run's last step, by
    measuring the training views' PSNR (sh-budget-db), the kept bands refit to the colours its views saw; the
    kernels evaluate (and a resumed run trains) each Gaussian only up to its degree, and checkpoints and exports
    store only what it keeps (geer_ns/sh_degrees). False: every Gaussian keeps every band (splatfacto).
    Not with --pipeline.model.distributed gaussians."""
    sh_budget_db: float = 0.05
    """sh-per-gaussian: the most PSNR the training views may lose, measured when the bands are chosen (0.05 dB:
    below the spread of runs that differ only in their seed, ~0.1 dB on the dev room)."""
    optimizer_rows: Literal["visible", "all"] = "all"
    """"all": every Gaussian, every step (torch's Adam). "visible": Adam steps only the Gaussians the step's views
    can see (geer_ns/optim/selective_adam.py: torch's Adam on those rows, its bias correction; the others and their
    moments wait), as gsplat's opt-in selective Adam: faster where a view sees a small part of a large scene, but
    a Gaussian seen in few steps also misses its momentum's later steps, which cost 0.1-0.3 dB on the dev room in
    a short run (benchmarks/skip_unneeded.md)."""
    view_cull: bool = True
    """Render and probe only the Gaussians a view can see (their bounding balls against the view's tiles: the same
    images, gradients and densification statistics; geer_ns/render/cull.py). False: every Gaussian in every view."""
    distributed: Literal["images", "gaussians"] = "images"
    """With several processes (--machine.num-devices): "images", every process holds the whole model and trains
    on its own images; "gaussians", each holds a shard of the Gaussians (scenes larger than one device), and
    every camera is rendered from the shards' Gaussians it sees (geer_ns/distributed/sharded_render.py)."""
    renderer_backend: Backend = "auto"
    """geer_ns.render backend: auto (CPU tensors: the kernels' math compiled for the CPU, JIT-built once, else
    the PyTorch renderer, said once; CUDA tensors: the kernels once they passed their self-test on this GPU,
    docs/cuda.md),
    torch, cuda (the kernels without a self-test) or cpu (the compiled CPU build; benchmarks/cpu_training.md)."""
    kernel_check_every: int = DEFAULT_EVERY
    """Every this many steps one training view is also rendered by the PyTorch renderer and compared with the
    compiled renderer; a disagreement switches the run to the PyTorch renderer (0: never; docs/cuda.md)."""
    lambda_mode: LambdaMode = "opacity"
    """PBF extent rule of the renderer (geer_ns.render.pbf)."""
    composite_order: str = "view"
    """How each ray composites its pairs (geer_ns/render/order.py): "view", the tile lists' one order per view (by
    the distance to each Gaussian's mean); "ray", each ray its own exact order (by where it meets each Gaussian's
    peak); "ray:K", the same holding at most K pending pairs a ray (exact while it holds at most K). The CUDA
    kernels hold 64 ("ray" and "ray:64"). "view" is the default: "ray" trains to the same PSNR at 1.45x the
    render cost and does not reduce popping (benchmarks/render_order.md, docs/compositing_order.md)."""
    max_pairs: int = 1 << 22
    """Renderer memory cap: (ray, Gaussian) pairs evaluated at once."""
    central_half_angles_deg: Optional[Tuple[float, float]] = None
    """Half-extents (theta, phi) of the 'central' eval region in degrees; None = the paper's App. G rule
    (theta in +-w/(2 fx), phi in +-h/(2 fy))."""
    appearance: Literal["off", "exposure"] = "off"
    """"exposure": a per-image exposure and white balance and the camera's vignetting (radial falloff in the
    ray's angle from the optical axis), applied in linear light to each rendered training image; evaluation
    renders neutral exposure with the learnt vignetting (geer_ns/refinement/appearance.py). use-bilateral-grid is the other
    option."""
    appearance_reg: float = 0.1
    """appearance=exposure: weight pulling the images' mean log gain to zero."""
    lens_refinement: LensMode = "off"
    """Refine each training camera's intrinsics (per distinct camera, not per image): "focal" (focal lengths),
    "focal+principal" (and the principal point) or "full" (and every distortion coefficient), through the rays
    they define (geer_ns/refinement/lens.py; optimizer lens_opt). The refined cameras go to
    <run>/cameras_refined.json and colmap/cameras.txt with every checkpoint."""
    lens_refinement_start: int = 500
    """lens-refinement: the step from which renders use (and train) the refined intrinsics."""
    lens_refinement_aspect: bool = False
    """lens-refinement: refine the aspect ratio fy / fx too (off: fx and fy scale together). Cameras that stay
    upright cannot tell a wrong ratio from a vertical stretch of the scene (docs/refinement.md)."""
    readout_refinement: bool = False
    """Rolling-shutter images (docs/rolling_shutter.md): also refine each training image's camera motion during its
    readout (a rotation and a move of the end pose relative to the start; optimizer readout_opt), through every
    ray's origin and direction. The start pose is refined by camera-optimizer.mode as for any image."""
    camera_refinement: CameraRefinement = "manual"
    """"register": the registration recipe for rough cameras (geer_ns/refinement/registration.py): SO3xR3 pose
    adjustments, the first 20 % of the run a low-capacity scene (the seed Gaussians held in place, SH degree 0, no
    densification) against which every training pose is solved twice (with lens-refinement, the lens solved
    first), then the poses held while the scene forms, solved once more against it and held to the end. Measured
    on the dev room it leaves the cameras bent by ~0.5 degree against the truth and moves good poses as far: for
    rough cameras only (docs/refinement.md). "manual": camera-optimizer.mode, pose-solve-every and
    pose-refinement-start as set."""
    pose_refinement_start: int = 0
    """With camera-optimizer.mode SO3xR3 or SE3: the step from which training renders use (and train) the pose
    adjustments (and pose-solve-every solves them). Poses refined while the scene forms wander, and the scene
    sets in around them: a later start keeps good (SfM) poses good; rough ones need 0 (docs/refinement.md)."""
    pose_solve_every: int = 0
    """With camera-optimizer.mode SO3xR3 or SE3: every this many steps, hold the scene and solve each training
    camera's pose adjustments by Levenberg-Marquardt on its image's residuals (0: off; geer_ns/refinement/pose_solve.py).
    Adam's one-image steps leave poses short of where the scene puts them (docs/refinement.md)."""
    pose_solve_iterations: int = 2
    """pose-solve-every: Levenberg-Marquardt iterations per camera at each of the solve's four blur levels (an
    iteration renders the image about 13 times)."""
    refined_frame: bool = True
    """With camera-optimizer.mode SO3xR3 or SE3: render cameras from outside training (ns-eval's test views, the
    viewer's, ns-render's) in the frame the scene and its refined cameras drifted to together, moved by the
    similarity that best maps the given training poses onto the refined ones; the refined poses are exported
    mapped back into the given frame (geer_ns/refinement/refined_frame.py). False: render them as given."""
    mcmc_cap_max: int = 1_000_000
    """strategy=mcmc: most Gaussians (gsplat MCMCStrategy cap_max)."""
    mcmc_noise_lr: float = 5e5
    """strategy=mcmc: learning rate of the sampling noise on the means (gsplat MCMCStrategy noise_lr)."""
    mcmc_min_opacity: float = 0.005
    """strategy=mcmc: Gaussians below this opacity are relocated (gsplat MCMCStrategy min_opacity)."""
    mcmc_opacity_reg: float = 0.01
    """strategy=mcmc: weight of the mean-opacity loss."""
    mcmc_scale_reg: float = 0.01
    """strategy=mcmc: weight of the mean-scale loss."""


# splatfacto options geer accepts (so that splatfacto command lines still parse) but does not use.
IGNORED_OPTIONS = ("rasterize_mode", "output_depth_during_training", "color_corrected_metrics", "n_split_samples")
# geer's own options, listed first in `ns-train geer --help` (the method description).
OWN_OPTIONS_HELP = (
    "geer's own options: --pipeline.model.renderer-backend {auto,torch,cuda,cpu}, --pipeline.model.lambda-mode "
    "{opacity,paper}, --pipeline.model.strategy {default,mcmc}, "
    "--pipeline.model.max-gaussians, --pipeline.model.densify-units {reference,image}, "
    "--pipeline.model.densify-min-pixels, --pipeline.model.prune-unseen, "
    "--pipeline.model.distributed {images,gaussians}, --pipeline.model.sh-per-gaussian, "
    "--pipeline.model.sh-budget-db, --pipeline.model.optimizer-rows {visible,all}, --pipeline.model.view-cull, "
    "--pipeline.model.max-pairs, --pipeline.model.kernel-check-every, "
    "--pipeline.model.central-half-angles-deg, --pipeline.model.lens-refinement {off,focal,focal+principal,full}, "
    "--pipeline.model.camera-refinement {manual,register}, --pipeline.model.pose-solve-every, "
    "--pipeline.model.pose-solve-iterations, --pipeline.model.refined-frame, "
    "--pipeline.datamanager.supervision, "
    "--pipeline.datamanager.mask-edge-fill, --pipeline.datamanager.images-per-step, --machine.timeout-s, "
    "--schedules {follow-run,fixed} (splatfacto's schedules stretched to --max-num-iterations by default); resume "
    "with --load-dir <run>/nerfstudio_models. Splatfacto options "
    "marked IGNORED are accepted and not used."
)


def ignored_options_set(config, defaults) -> List[str]:
    """`name=value` of each IGNORED_OPTIONS entry `config` sets away from `defaults` (a default config), for
    the one start-up line that says geer does not use them."""
    return [f"{name}={getattr(config, name)!r}" for name in IGNORED_OPTIONS
            if getattr(config, name) != getattr(defaults, name)]


def densification_line(options: GeerOwnOptions) -> str:
    """The start-up words on densification: the strategy and, for DefaultStrategy, its statistics' units."""
    if options.strategy == "mcmc":
        return "densification by gsplat's MCMCStrategy"
    units = ("gsplat's units of each camera's image (densify-units image)" if options.densify_units == "image"
             else "pixels of the 300-pixel reference camera (densify-units reference)")
    return f"densification by DefaultStrategy, statistics in {units}"


def skipping_line(options: GeerOwnOptions, sh_chosen: bool, sharded: bool) -> str:
    """The start-up line on what training skips: per-Gaussian SH degrees (`sh_chosen`: at the run's last step;
    never with Gaussians `sharded` over processes), the optimizer's rows and the view cull."""
    if sh_chosen:
        sh = ("each Gaussian's SH degree chosen at the run's last step, its kept bands refit (sh-per-gaussian, "
              f"budget {options.sh_budget_db} dB)")
    elif options.sh_per_gaussian and sharded:
        sh = "every SH band kept (sh-per-gaussian is not chosen with Gaussians sharded over processes)"
    else:
        sh = "every SH band kept"
    rows = ("Adam steps the Gaussians each step's views see (optimizer-rows visible)"
            if options.optimizer_rows == "visible" else "Adam steps every Gaussian (optimizer-rows all)")
    cull = "views render the Gaussians they can see" if options.view_cull else "views render every Gaussian"
    return f"{sh}; {rows}; {cull}"


def check_composite_order(options: GeerOwnOptions) -> None:
    """OptionError naming --pipeline.model.composite-order unless it is 'view', 'ray' or 'ray:K' (render/order.py)."""
    try:
        CompositeOrder.parse(options.composite_order)
    except ValueError as err:
        raise OptionError(f"--pipeline.model.composite-order: {err}") from None
