"""The registration recipe (`--pipeline.model.camera-refinement register`): bring rough cameras to where the images
put them before the scene forms around their errors.

A scene that densifies while its cameras are wrong absorbs their errors: each image gets detail placed where its own
wrong pose sees it, and a later pose refinement then finds the wrong poses optimal (docs/refinement.md). Adam's
one-image steps are also a poor pose optimiser against a fixed scene (0.26 degree left where a Levenberg-Marquardt
solve reaches 0.03). So the recipe splits the run:

1. Registration, the first REGISTER_FRACTION of the run: a low-capacity, low-pass scene (the seed Gaussians held
   where the seed points put them, no densification, SH degree 0; splatfacto's resolution schedule keeps the
   first part coarse), and every training camera's pose solved against it SOLVES times (pose_solve.solve_poses:
   Levenberg-Marquardt, coarse to fine over blurred residuals). The cameras are registered to the seed points'
   geometry and to what the other images agree on, before the scene can bend to fit any one image's error (with
   the means free, cameras and scene bend together: docs/refinement.md). Where the points came from the same
   SfM as the poses, this is registration to that solution; the later solve against the formed scene refines
   from there.
2. Formation, to the end of densification: the poses held, the scene densifies and gains its SH bands.
3. A final solve against the formed scene, then training on with the poses held.

Lens refinement (--pipeline.model.lens-refinement) joins as set: its rays are what every solve renders through, and
each solve solves the lens first (lens_solve.py: a pose solve under a wrong lens moves the poses away from the
truth), then the poses.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, List, Literal, Tuple

CameraRefinement = Literal["manual", "register"]
REGISTER_FRACTION = 0.2
SOLVES = 2


@dataclass(frozen=True)
class RegistrationPlan:
    """The steps of the recipe for one run."""

    register_until: int  # end of the registration stage: densification and SH bands start here
    solves: Tuple[int, ...]  # steps (before their iteration) at which every training pose is solved

    @property
    def hold_from(self) -> int:
        """From this step on Adam does not move the poses: the end of the registration stage."""
        return self.register_until

    def describe(self) -> str:
        return (f"registration: steps 0-{self.register_until} with the seed Gaussians held in place, SH degree 0 and "
                f"no densification, every training pose solved by Levenberg-Marquardt at steps "
                f"{', '.join(map(str, self.solves[:-1]))} and, against the formed scene, at step {self.solves[-1]}; "
                f"the poses held from step {self.hold_from}")


def plan(steps: int, stop_split_at: int) -> RegistrationPlan:
    """The recipe's steps for a run of `steps` whose densification ends at `stop_split_at`."""
    until = max(1, round(REGISTER_FRACTION * steps))
    solves = tuple(max(1, round(until * (k + 1) / SOLVES)) for k in range(SOLVES))
    final = min(max(stop_split_at, until + 1), max(steps - 1, until + 1))
    return RegistrationPlan(until, solves + (final,))


def apply(config) -> str:
    """Set a geer TrainerConfig up for the recipe, in place and idempotently (ns-train's set-up and the trainer both
    call it): SO3xR3 pose adjustments where the camera optimizer is off, no densification and no SH band before
    the registration stage ends. Returns the start-up line ("" when camera-refinement is manual)."""
    from geer_ns.training.horizon import run_length

    model = config.pipeline.model
    if model.camera_refinement != "register":
        return ""
    if model.camera_optimizer.mode == "off":
        model.camera_optimizer.mode = "SO3xR3"
    steps = plan(run_length(config), model.stop_split_at)
    model.warmup_length = max(model.warmup_length, steps.register_until)
    model.sh_degree_interval = max(model.sh_degree_interval, steps.register_until)
    model.pose_refinement_start = 0
    lens = "" if model.lens_refinement == "off" else "; at each solve the lens first, then the poses"
    return steps.describe() + lens


def pose_callbacks(attributes, say: Callable[[str], None]) -> List:
    """The training callbacks that solve poses: the registration recipe's (camera-refinement register) and the
    periodic pose solve's (pose-solve-every), each where its option asks for it. attributes: nerfstudio's
    TrainingCallbackAttributes (the trainer gives the run's length)."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    from geer_ns.refinement.pose_solve import PoseSolver
    from geer_ns.training.horizon import run_length

    pipeline, optimizers = attributes.pipeline, attributes.optimizers
    options = pipeline.model.config
    solvers = []
    if options.camera_refinement == "register":
        steps = plan(run_length(attributes.trainer.config), options.stop_split_at)
        solvers.append(Registration(pipeline, optimizers, steps, options.pose_solve_iterations, say))
    if options.pose_solve_every > 0:
        solvers.append(PoseSolver(pipeline, optimizers, options.pose_solve_every, options.pose_solve_iterations, say))
    return [TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], solver) for solver in solvers]


class Registration:
    """The training callback (before each iteration): the means held during registration, the solves at their
    steps, the poses held after registration."""

    def __init__(self, pipeline, optimizers, steps: RegistrationPlan, iterations: int,
                 say: Callable[[str], None]) -> None:
        self.pipeline, self.optimizers, self.plan, self.iterations, self.say = (pipeline, optimizers, steps,
                                                                              iterations, say)

    def __call__(self, step: int) -> None:
        from geer_ns.refinement.pose_solve import solve_every_camera

        if step in self.plan.solves:
            solve_lenses(self.pipeline, self.optimizers, self.iterations, step, self.say)
            solve_every_camera(self.pipeline, self.optimizers, self.iterations, f"registration solve at step {step}",
                               self.say)
        held = "camera_opt" if step >= self.plan.hold_from else "means"
        for group in getattr(self.optimizers.optimizers.get(held), "param_groups", []):
            group["lr"] = 0.0  # this iteration's step only: the scheduler sets it again after


def solve_lenses(pipeline, optimizers, iterations: int, step: int, say: Callable[[str], None]) -> None:
    """Where the lens is refined (and active): solve it against the scene before the poses are (lens_solve.py: a
    pose solve under a lens Adam has not brought home moves the poses away from the truth), then restart Adam's
    momentum of it; says what moved."""
    import time

    from geer_ns.refinement.lens_solve import solve_lens
    from geer_ns.refinement.pose_solve import restart_momentum

    model = pipeline.model
    if model.lens is None or not model.lens.active(model.step):
        return
    start = time.perf_counter()
    summary = solve_lens(model, pipeline.datamanager, range(len(model.lens.image_camera)), iterations)
    restart_momentum(optimizers, "lens_opt")
    say(f"geer: registration lens solve at step {step}: {summary['lenses']} lens(es), focal moved "
        f"{100 * summary['focal_change']:.2f} % at most, residuals {100 * summary['residual_change']:+.1f} %, "
        f"{time.perf_counter() - start:.0f} s")
