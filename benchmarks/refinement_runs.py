"""Short training runs for the refinement benchmarks (benchmarks/appearance_bench.py, pose_bench.py): train
geer in this process with nerfstudio's loop, then score the eval split as ns-eval does."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
DEV_ROOM = Path("/work/shared/data/fisheye_room_dev")


def bench_args(doc: str, steps: int, work: str, extra=None):
    """The benchmarks' command line: --size (the dev room's), --steps, --work (a scratch folder), and a script's
    own options from `extra` (an argparse parser made with add_help=False); `command` is the line as run, for the
    reports."""
    import argparse
    import shlex

    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0], parents=[] if extra is None else [extra])
    parser.add_argument("--size", type=int, default=80)
    parser.add_argument("--steps", type=int, default=steps)
    parser.add_argument("--work", type=Path, default=Path(work))
    args = parser.parse_args()
    args.command = shlex.join(["python", f"benchmarks/{Path(sys.argv[0]).name}", *sys.argv[1:]])
    return args


def model_options(items) -> dict:
    """`option=value` strings (a --set list) as model options; values read as JSON where they parse, else kept as
    text."""
    options = {}
    for item in items:
        key, text = item.split("=", 1)
        try:
            options[key] = json.loads(text)
        except json.JSONDecodeError:
            options[key] = text
    return options


def short_schedule(densify_until: int = 1000) -> dict:
    """The refinement benchmarks' model options for runs of a few thousand steps: densification every 100 steps
    from step 300 to `densify_until`, full resolution throughout."""
    return {"warmup_length": 300, "refine_every": 100, "stop_split_at": densify_until, "num_downscales": 0}


OPTIMIZER_NAMES = {"adam": "Adam", "lazy": "LazyAdam (benchmarks/lazy_adam.py)"}  # adam_entry's optimizers


def adam_entry(lr: float, steps: int, warmup: int, optimizer: str = "adam") -> dict:
    """An optimizer entry (nerfstudio's config): `optimizer` (an OPTIMIZER_NAMES key) at `lr` after a linear
    warm-up from 0 over `warmup` steps, decaying exponentially to 1e-5 at `steps`."""
    from nerfstudio.engine.optimizers import AdamOptimizerConfig
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    from lazy_adam import LazyAdamOptimizerConfig

    config = {"adam": AdamOptimizerConfig, "lazy": LazyAdamOptimizerConfig}[optimizer]
    return {"optimizer": config(lr=lr, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-5, max_steps=steps, warmup_steps=warmup,
                                                         lr_pre_warmup=0.0)}


def fresh(path: Path) -> Path:
    """path, removed first if it exists (a variant is written anew)."""
    import shutil

    if path.exists():
        shutil.rmtree(path)
    return path


def small_dev_room(work: Path, size: int, room: Path = DEV_ROOM) -> Path:
    """The dev room at size^2 (benchmarks/densification.resized_room), its fisheye transforms file."""
    import densification

    densification.DEV_ROOM = room
    return densification.resized_room(work, size) / "transforms_fisheye.json"


def perturbed_dev_room(work: Path, size: int, name: str, **perturbation) -> tuple[Path, Path, dict]:
    """(the dev room's transforms at size^2, the same room with its training cameras perturbed, written under
    work/name, and the truth perturb_cameras returns). perturbation: perturb_cameras' keywords; 1 degree and 1 % of
    the extent unless given (the perturbation benchmarks' default)."""
    from benchmarks.camera_perturbation import perturb_cameras

    clean = small_dev_room(work, size)
    noisy = fresh(work / name)
    truth = perturb_cameras(clean.parent, noisy, transforms=clean.name,
                            **{"rotation_deg": 1.0, "position_fraction": 0.01, **perturbation})
    return clean, noisy / clean.name, truth


def train_and_score(name: str, data: Path, steps: int, overrides: dict, out: Path, optimizers: dict | None = None):
    """(ns-eval's averaged metrics of the eval split, seconds of training, the trained pipeline). overrides: model
    options (dotted: camera_optimizer.mode); optimizers: parameter group -> optimizer entry replacing geer's."""
    from nerfstudio.utils import writer

    from geer_ns.compare.run import train_timed
    from geer_ns.config import geer_trainer_config
    from geer_ns.model import GeerModelConfig

    config = geer_trainer_config("geer", GeerModelConfig())
    config.data = config.pipeline.datamanager.data = data
    config.pipeline.datamanager.cache_images = "cpu"
    config.output_dir, config.experiment_name, config.timestamp = out / "runs", name, "run"
    config.vis = "tensorboard"
    config.max_num_iterations = steps
    config.steps_per_eval_image = config.steps_per_eval_batch = config.steps_per_eval_all_images = 0
    config.steps_per_save = 10**9
    for key, value in overrides.items():
        target = config.pipeline.model
        *path, leaf = key.split(".")
        for part in path:
            target = getattr(target, part)
        setattr(target, leaf, value)
    config.optimizers.update(optimizers or {})
    trainer, seconds = train_timed(config)
    metrics = trainer.pipeline.get_average_eval_image_metrics(step=steps)
    writer.EVENT_WRITERS.clear()
    return metrics, seconds, trainer.pipeline


def record_every(every: int, last: int, measure, into: list) -> None:
    """Patch GeerModel's training callbacks with one that appends {"step": step, **measure(pipeline)} to `into`
    every `every` steps and at the `last` step, where measure(pipeline) returns a dict (None: nothing recorded)."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    from geer_ns.model import GeerModel

    original = GeerModel.get_training_callbacks

    def with_record(self, attributes):
        def record(step):
            if step % every == 0 or step == last:
                measured = measure(attributes.pipeline)
                if measured is not None:
                    into.append({"step": step, **measured})

        return [*original(self, attributes),
                TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], record)]

    GeerModel.get_training_callbacks = with_record


def solved_test_metrics(pipeline, iterations: int = 2) -> dict:
    """ns-eval's averaged metrics of the eval split after each test view's pose is solved against the trained
    scene (geer_ns.refinement.pose_solve.solve_view_pose): the test-time pose alignment of pose-refinement benchmarks
    (BARF's protocol), which takes out the small rigid motion between a refined scene and the given test poses."""
    from geer_ns.refinement.pose_solve import solve_view_pose

    views = [(solve_view_pose(pipeline.model, camera, batch, iterations), batch)
             for camera, batch in pipeline.datamanager.fixed_indices_eval_dataloader]
    return pipeline.get_average_image_metrics(views, image_prefix="eval")


def git_commit() -> str:
    done = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT)
    return done.stdout.strip()


def load_average() -> str:
    return Path("/proc/loadavg").read_text().split()[0]


def dump(path: Path, record: dict) -> None:
    path.write_text(json.dumps(record, indent=2) + "\n")
