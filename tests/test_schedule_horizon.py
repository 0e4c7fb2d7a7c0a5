"""Schedules follow the run (geer_ns/training/horizon.py): splatfacto's 30000-step shape stretched to
--max-num-iterations, checked against nerfstudio's own splatfacto config; options given a value stay; said and
saved once; a real run's learning rate reaches its final value at the run's last step."""

import copy

import pytest
import yaml

from geer_ns.training.horizon import follow_run, stretch_schedules


def _geer(steps: int):
    from geer_ns.config import geer_trainer_config
    from geer_ns.model import GeerModelConfig

    config = geer_trainer_config("geer", GeerModelConfig())
    config.max_num_iterations = steps
    return config


def _splatfacto():
    from nerfstudio.configs.method_configs import method_configs

    return copy.deepcopy(method_configs["splatfacto"])


def test_a_short_run_gets_splatfactos_shape_at_its_length():
    """Every schedule at the same fraction of the run as splatfacto's at 30000 steps (nerfstudio's own config is
    the reference)."""
    reference = _splatfacto()
    ref_model, steps = reference.pipeline.model, 3000
    f = steps / reference.max_num_iterations
    config = _geer(steps)
    follow_run(config)
    model = config.pipeline.model
    for name in ("warmup_length", "stop_split_at", "stop_screen_size_at", "sh_degree_interval", "resolution_schedule"):
        assert getattr(model, name) == round(getattr(ref_model, name) * f), name
    assert model.refine_every == 10  # 100 x 0.1, and never under 10
    assert model.reset_alpha_every * model.refine_every == round(
        ref_model.reset_alpha_every * ref_model.refine_every * f)  # an opacity reset every 10 % of the run
    short = _geer(500)
    follow_run(short)  # 10 % would be 5 refinements: at least 10 apart, so that refinement is not always paused
    assert short.pipeline.model.reset_alpha_every == 10
    for group in ("means", "camera_opt", "bilateral_grid"):
        mine, theirs = config.optimizers[group]["scheduler"], reference.optimizers[group]["scheduler"]
        assert mine.max_steps == steps and mine.lr_final == theirs.lr_final
        assert mine.warmup_steps == round(theirs.warmup_steps * f)
    # geer's own step options follow too
    assert model.lens_refinement_start == round(500 * f) and model.pose_solve_every == 0


def test_options_given_a_value_are_the_users_step_counts():
    config = _geer(2000)
    model = config.pipeline.model
    model.stop_split_at, model.refine_every = 700, 50
    config.optimizers["means"]["scheduler"].max_steps = 5000
    said = follow_run(config)
    assert (model.stop_split_at, model.refine_every) == (700, 50)
    assert config.optimizers["means"]["scheduler"].max_steps == 5000
    assert model.reset_alpha_every == 30  # it counts the user's refinements
    assert "options given a value kept" in said and "until 700" in said


def test_stretched_once_kept_in_the_saved_config_and_fixed_keeps_everything():
    config = _geer(2000)
    follow_run(config)
    once = copy.deepcopy(config.pipeline.model)
    assert config.schedules_written_for == 2000
    reloaded = yaml.load(yaml.dump(config), Loader=yaml.Loader)  # what ns-train saves and ns-eval reads back
    assert "following the run" in follow_run(reloaded)
    assert reloaded.pipeline.model == once and config.pipeline.model == once
    fixed = _geer(2000)
    fixed.schedules = "fixed"
    follow_run(fixed)
    assert fixed.pipeline.model == _geer(30000).pipeline.model
    assert fixed.optimizers["means"]["scheduler"].max_steps == 30000


def test_splatfacto_configs_follow_the_same_rule_and_bad_lengths_are_named():
    config = _splatfacto()
    stretch_schedules(config, 1500)
    assert config.pipeline.model.sh_degree_interval == 50
    assert config.optimizers["means"]["scheduler"].max_steps == 1500
    with pytest.raises(ValueError, match="run lengths must be positive"):
        stretch_schedules(_splatfacto(), 0)
    from geer_ns.errors import OptionError

    with pytest.raises(OptionError, match="--max-num-iterations 0: a run whose schedules follow it"):
        follow_run(_geer(0))  # ns-train reports it in one line (errors.py), not as a stack trace


def test_a_run_ends_its_learning_rate_schedule_at_its_last_step_and_a_resumed_run_follows_its_total(tmp_path):
    """A 12-step run on the embedded room: the means' learning rate is at its final value when the run ends, the
    start-up says what the schedules are; resumed for 6 more steps, its schedules follow 18 steps."""
    from conftest import copy_room, tiny_trainer_config
    from nerfstudio.utils import writer

    from geer_ns import resume
    from geer_ns.compare.run import train_timed

    config = tiny_trainer_config(copy_room(tmp_path / "room", 4), tmp_path / "out", "horizon", 12)
    config.pipeline.model.sh_per_gaussian = False
    trainer, _ = train_timed(config)
    trainer.save_checkpoint(11)
    writer.EVENT_WRITERS.clear()
    # splatfacto's means: 1.6e-4 decaying to 1.6e-6 (as written, still 1.6e-4 x 0.01^(12/30000) = 1.597e-4 here)
    assert trainer.optimizers.optimizers["means"].param_groups[0]["lr"] == pytest.approx(1.6e-6, rel=1e-6)
    assert "schedules for 12 steps (stretched" in trainer.schedule_said
    more = tiny_trainer_config(config.data, tmp_path / "out", "horizon_more", 6)
    more.load_dir = config.get_base_dir() / "nerfstudio_models"
    assert resume.images_seen(more) == 12
    assert "schedules for 18 steps (stretched x0.0006" in follow_run(more, resume.images_seen(more))
    assert more.optimizers["means"]["scheduler"].max_steps == 18
