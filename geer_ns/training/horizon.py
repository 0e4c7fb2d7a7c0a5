"""Schedules that follow the run: every step-valued schedule a run leaves at its default stretched from the run
length it was written for (splatfacto's 30000 steps) to --max-num-iterations: splatfacto's shape at any length.

A schedule written for 30000 steps and cut off at 2000 leaves the Gaussians at ~74 % of their learning rate
while a decaying camera optimizer is nearly frozen, never resets opacities and stays at low SH degrees: the
scene is still plastic when the run ends. Stretched by f = steps / 30000:

* learning-rate schedules written for the whole run (max_steps = 30000): max_steps and warmup_steps times f;
* densification: warm-up, the end of splitting and of the screen-size rule times f; refinements every
  refine_every x f steps, but not under MIN_REFINE_EVERY (a refinement's statistics should cover some images),
  and the opacity reset after the same fraction of the run as splatfacto's (every 10 %), but not within
  MIN_RESET_REFINEMENTS refinements of the last (runs under 1000 steps reset less often);
* the SH degree and resolution schedules, and geer's own step options (lens and pose refinement starts, the
  pose solve's period), times f.

Options given a value of their own (on the command line, by a script) are the user's step counts and stay as
given. A resumed run ends at its checkpoint's step + --max-num-iterations (nerfstudio's rule), and its schedules
follow that length. One rule for geer's runs (GeerTrainer, said at start-up), geer-compare's methods (splatfacto's included) and
the benchmarks; `--schedules fixed` keeps every option as written.
"""

from __future__ import annotations

from typing import Literal

from geer_ns.errors import OptionError

REFERENCE_STEPS = 30000
MIN_REFINE_EVERY = 10
# Refinements between opacity resets, at least: the strategies pause refinement for one pass over the images
# plus one interval after each reset, which must leave refinements in between.
MIN_RESET_REFINEMENTS = 10
Schedules = Literal["follow-run", "fixed"]

# Step-valued model options stretched in proportion (those a config has; geer's own ones last).
PROPORTIONAL_MODEL_FIELDS = ("warmup_length", "stop_split_at", "stop_screen_size_at", "sh_degree_interval",
                             "resolution_schedule", "lens_refinement_start", "pose_refinement_start", "pose_solve_every")


def _scaled(value: int, factor: float) -> int:
    """A step count times factor, rounded; 0 stays 0 ("never" / "from the start"), anything else at least 1."""
    return 0 if value == 0 else max(1, round(value * factor))


def stretch_schedules(config, steps: int, written_for: int = REFERENCE_STEPS) -> str:
    """Stretch `config`'s (a nerfstudio TrainerConfig) step-valued schedules that are at their defaults, in place,
    from `written_for` steps to `steps` (module docstring). Returns what the schedules are now, for a start-up
    line."""
    if steps <= 0 or written_for <= 0:
        raise ValueError(f"schedules: run lengths must be positive, got {steps} steps for a schedule of {written_for}")
    if steps == written_for:
        return schedule_line(config, "as written", steps)
    factor = steps / written_for
    model = config.pipeline.model
    default = type(model)()
    untouched = lambda name: getattr(model, name) == getattr(default, name)  # noqa: E731
    for name in PROPORTIONAL_MODEL_FIELDS:
        if hasattr(model, name) and untouched(name):
            setattr(model, name, _scaled(getattr(model, name), factor))
    if hasattr(model, "refine_every") and untouched("refine_every"):
        reset_period = model.reset_alpha_every * model.refine_every * factor  # steps between opacity resets
        model.refine_every = max(min(MIN_REFINE_EVERY, model.refine_every), _scaled(model.refine_every, factor))
        if untouched("reset_alpha_every"):  # it counts refinements: the user's, where refine_every is theirs
            model.reset_alpha_every = max(MIN_RESET_REFINEMENTS, round(reset_period / model.refine_every))
    for entry in config.optimizers.values():
        scheduler = entry.get("scheduler")
        if scheduler is not None and getattr(scheduler, "max_steps", None) == written_for:  # decays over the run
            scheduler.max_steps = steps
            if getattr(scheduler, "warmup_steps", 0):
                scheduler.warmup_steps = _scaled(scheduler.warmup_steps, factor)
    return schedule_line(config, f"stretched x{factor:.4g} from {written_for} steps, options given a value kept", steps)


def schedule_line(config, how: str, steps: int | None = None) -> str:
    """What `config`'s schedules are, for the start-up line: for a run of `steps` (default --max-num-iterations);
    `how` says where they come from."""
    model, steps = config.pipeline.model, config.max_num_iterations if steps is None else steps
    said = f"schedules for {steps} steps ({how})"
    if hasattr(model, "refine_every"):
        said += (f": densification from step {model.warmup_length} every {model.refine_every} steps until "
                 f"{model.stop_split_at}, opacity reset every {model.reset_alpha_every * model.refine_every} steps, "
                 f"SH degree up every {model.sh_degree_interval} steps")
    return said


def run_length(config) -> int:
    """The step a geer TrainerConfig's run ends at as its schedules see it: the length they were stretched to
    (a resumed run's checkpoint step included), else --max-num-iterations."""
    return config.schedules_written_for if config.schedules == "follow-run" else config.max_num_iterations


def follow_run(config, resumed_at: int = 0) -> str:
    """A geer TrainerConfig's schedules made to follow its run (config.schedules == "follow-run"), in place and
    once: the run ends at step resumed_at + --max-num-iterations (resumed_at: the steps its checkpoint had done,
    resume.images_seen), and config.schedules_written_for becomes that length, so a saved and reloaded config is
    not stretched again. Returns the start-up line (what the schedules are now)."""
    if config.schedules == "fixed":
        return schedule_line(config, "as written: --schedules fixed")
    length = resumed_at + config.max_num_iterations
    if length <= 0:
        raise OptionError(f"geer: --max-num-iterations {config.max_num_iterations}: a run whose schedules follow it "
                          "needs at least one step (pass a positive count, or --schedules fixed)")
    if config.schedules_written_for == length:
        return schedule_line(config, "following the run", length)
    said = stretch_schedules(config, length, config.schedules_written_for)
    config.schedules_written_for = length
    return said
