"""The registration recipe (geer_ns/refinement/registration.py): its plan follows the run, its set-up is idempotent
and manual leaves everything alone, and in a real run it solves at its steps and then holds the poses.
(How close it brings perturbed cameras to the truth is measured by benchmarks/refinement.py.)"""

import torch

from geer_ns.refinement import registration


def _config(steps: int, refinement: str):
    from geer_ns.config import geer_trainer_config
    from geer_ns.model import GeerModelConfig
    from geer_ns.training.horizon import follow_run

    config = geer_trainer_config("geer", GeerModelConfig(camera_refinement=refinement))
    config.max_num_iterations = steps
    follow_run(config)
    return config


def test_the_plan_follows_the_run():
    steps = registration.plan(2000, 1000)
    assert (steps.register_until, steps.solves, steps.hold_from) == (400, (200, 400, 1000), 400)
    short = registration.plan(10, 3)  # densification ending inside registration: the final solve after it
    assert short.solves[-1] == 3 and short.register_until == 2 and all(s >= 1 for s in short.solves)


def test_register_sets_the_run_up_once_and_manual_changes_nothing():
    config = _config(2000, "register")
    said = registration.apply(config)
    model = config.pipeline.model
    assert model.camera_optimizer.mode == "SO3xR3"
    assert model.warmup_length == 400 and model.sh_degree_interval == 400 and model.pose_refinement_start == 0
    assert "steps 0-400" in said and "at step 1000" in said
    before = (model.warmup_length, model.sh_degree_interval, model.camera_optimizer.mode)
    registration.apply(config)
    assert (model.warmup_length, model.sh_degree_interval, model.camera_optimizer.mode) == before
    assert "lens" not in said
    model.lens_refinement = "focal"
    assert registration.apply(config).endswith("; at each solve the lens first, then the poses")
    manual = _config(2000, "manual")
    snapshot = repr(manual.pipeline.model)
    assert registration.apply(manual) == "" and repr(manual.pipeline.model) == snapshot


def test_a_run_solves_at_its_steps_and_then_holds_the_poses(tmp_path, capsys):
    """12 steps on four frames of the embedded room, focal refinement on: the means held during registration (steps
    0-1), solves (the lens, then the poses) at steps 1, 2 and 6 (densification ends at 6), and no pose adjustment
    changes after the last solve."""
    from conftest import copy_room, tiny_trainer_config
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
    from nerfstudio.utils import writer

    from geer_ns.compare.run import train_timed

    config = tiny_trainer_config(copy_room(tmp_path / "room", 4), tmp_path / "out", "register", 12)
    model = config.pipeline.model
    model.camera_refinement, model.stop_split_at, model.sh_per_gaussian = "register", 6, False
    model.pose_solve_iterations = 1
    model.lens_refinement, model.lens_refinement_start = "focal", 0
    seen, means = {}, {}

    def record(step: int, trainer=None) -> None:
        model = trainer.pipeline.model
        seen[step] = model.camera_optimizer.pose_adjustment.detach().clone()
        means[step] = model.means.detach().clone()

    from nerfstudio.engine import trainer as host_trainer

    setup = host_trainer.Trainer.setup

    def setup_and_watch(self, *args, **kwargs):
        setup(self, *args, **kwargs)
        self.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], record,
                                               kwargs={"trainer": self}))

    host_trainer.Trainer.setup = setup_and_watch
    try:
        trainer, _ = train_timed(config)
    finally:
        host_trainer.Trainer.setup = setup
        writer.EVENT_WRITERS.clear()
    out = capsys.readouterr().out
    for step in (1, 2, 6):
        assert f"registration solve at step {step}:" in out
        lens = out.index(f"registration lens solve at step {step}: 1 lens(es)")
        assert lens < out.index(f"registration solve at step {step}:")
    assert "registration: steps 0-2" in out
    for step in range(7, 12):
        assert torch.equal(seen[step], seen[6]), step
    assert torch.equal(means[0], means[1])  # registration: the Gaussians stay where the seed put them
    assert not torch.equal(means[2], means[3])
    assert trainer.pipeline.model.config.camera_optimizer.mode == "SO3xR3"
