"""How far joint training moves cameras that start at the truth: the error floor of pose refinement.

geer trained on the dev fisheye room at --size^2 from its true cameras with nerfstudio's SO3xR3 camera optimizer
on; every --every steps the training cameras' pose adjustments (the truth is zero) are read as rotation (degrees)
and position (% of the scene's extent) errors, raw and after the similarity that best maps the centres onto the
truth (pose_bench.similarity_aligned): what joint training leaves when there is nothing to correct. Writes
benchmarks/pose_drift{suffix}.md (+ .json), one section per run (the file is appended to).

    python benchmarks/pose_drift.py [--size 128] [--steps 2000] [--pose-lr 5e-4] [--pose-warmup 200]
        [--set model_option=value ...] [--suffix ""]
"""

from __future__ import annotations

import json

from pose_bench import error_columns
from refinement_runs import (OPTIMIZER_NAMES, ROOT, adam_entry, bench_args, git_commit, load_average, model_options,
                             record_every, short_schedule, small_dev_room, train_and_score)


def drift(pipeline, extent: float) -> dict:
    """pose_bench.error_summary of the training cameras' adjusted poses against their given (true) ones."""
    from geer_ns.refinement.refined_frame import adjusted_poses
    from pose_bench import error_summary

    given = pipeline.datamanager.train_dataset.cameras.camera_to_worlds.detach().double()
    moved = adjusted_poses(pipeline.model.camera_optimizer, given).numpy()
    scale = float(pipeline.datamanager.train_dataparser_outputs.dataparser_scale)
    return error_summary(moved, given.numpy(), scale, extent)


def main() -> None:
    import argparse

    extra = argparse.ArgumentParser(add_help=False)
    extra.add_argument("--pose-lr", type=float, default=5e-4)
    extra.add_argument("--pose-optimizer", choices=tuple(OPTIMIZER_NAMES), default="adam",
                       help="camera_opt's optimizer: torch's Adam, or benchmarks/lazy_adam.py")
    extra.add_argument("--pose-warmup", type=int, default=200, help="camera_opt's linear warm-up from 0 (steps)")
    extra.add_argument("--every", type=int, default=100)
    extra.add_argument("--set", nargs="*", default=[], metavar="OPTION=VALUE",
                       help="model options (dotted, e.g. camera_optimizer.rot_l2_penalty=0); values as JSON")
    extra.add_argument("--label", default="", help="the run's name in the report")
    extra.add_argument("--suffix", default="")
    args = bench_args(__doc__, 2000, "/tmp/geer_drift", extra)
    from benchmarks.camera_perturbation import scene_extent

    clean = small_dev_room(args.work, args.size)
    extent = scene_extent(clean.parent, json.loads(clean.read_text()))
    overrides = {**short_schedule(), "camera_optimizer.mode": "SO3xR3"}
    overrides.update(model_options(args.set))
    optimizers = {"camera_opt": adam_entry(args.pose_lr, args.steps, args.pose_warmup, args.pose_optimizer)}
    trace: list = []
    record_every(args.every, args.steps - 1, lambda pipeline: drift(pipeline, extent), trace)
    label = args.label or args.command
    metrics, seconds, pipeline = train_and_score("drift", clean, args.steps, overrides, args.work, optimizers)
    record = {"commit": git_commit(), "command": args.command, "label": label, "size": args.size, "steps": args.steps,
              "overrides": {k: str(v) for k, v in overrides.items()}, "pose_lr": args.pose_lr,
              "pose_warmup": args.pose_warmup, "pose_optimizer": args.pose_optimizer, "psnr": metrics["psnr"],
              "seconds": seconds, "trace": trace}
    stem = ROOT / "benchmarks" / f"pose_drift{args.suffix}"
    runs = json.loads(stem.with_suffix(".json").read_text()) if stem.with_suffix(".json").exists() else []
    stem.with_suffix(".json").write_text(json.dumps([*runs, record], indent=2) + "\n")
    rows = "\n".join(f"| {t['step']} | {error_columns(t)} |" for t in trace)
    section = f"""
## {label}

- {args.size}x{args.size}, {args.steps} steps, camera_opt {OPTIMIZER_NAMES[args.pose_optimizer]} lr {args.pose_lr:g}
  after a {args.pose_warmup}-step linear warm-up, decaying to 1e-5; model options {overrides}
- ns-eval test PSNR {metrics['psnr']:.2f} (test views as given, in the refined frame); {seconds:.0f} s of training
  (CPU, 2 cores, load average {load_average()} when written)
- commit {record['commit']} (+ working tree); command: `{args.command}`

| step | rotation deg (mean / max) | position % (mean / max) | aligned: rotation deg, position % (mean) |
| ---: | ---: | ---: | ---: |
{rows}
"""
    path = stem.with_suffix(".md")
    head = "" if path.exists() else \
        "# Pose drift: joint training from the true cameras\n\n" + __doc__.split("\n\n")[1] + "\n"
    path.write_text((path.read_text() if path.exists() else head) + section)
    print(section)


if __name__ == "__main__":
    main()
