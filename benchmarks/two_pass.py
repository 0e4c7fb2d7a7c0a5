"""Pose refinement in two passes: a scene trained from the first pass's refined poses, at a gentler learning rate.

The dev room at --size^2 with every training camera turned by 1 degree and moved by 1 % of the extent (seed 0,
test poses true, lens true). Pass 1 refines the poses (SO3xR3) at --first-lr, which moves them far enough while
the scene forms; its refined poses (the run's cameras_refined.json) replace the training poses of a copy of the
data, and pass 2 trains a new scene from them at --second-lr, whose early wander is smaller
(benchmarks/pose_drift.md). Both passes scored as lens_bench.py scores. Writes benchmarks/two_pass{suffix}.md.

    python benchmarks/two_pass.py [--size 128] [--steps 2000] [--second-lr 1e-4] [--second-warmup 1000]
"""

from __future__ import annotations

import json
from pathlib import Path

from pose_bench import camera_errors, error_columns
from refinement_runs import (ROOT, adam_entry, bench_args, fresh, git_commit, load_average, perturbed_dev_room,
                             short_schedule, solved_test_metrics, train_and_score)


def with_refined_poses(data: Path, run: Path, out: Path) -> Path:
    """A copy of the dataset folder holding `data` (a transforms file) at `out` (replaced if present), its frames'
    poses replaced by those of the cameras_refined.json the training run under `run` exported (matched by image
    file name); returns its transforms."""
    import shutil

    refined = next(run.rglob("cameras_refined.json"), None)
    if refined is None:
        raise FileNotFoundError(f"{run}: the run exported no cameras_refined.json")
    shutil.copytree(data.parent, fresh(out))
    meta = json.loads(data.read_text())
    poses = {Path(f["file_path"]).name: f["transform_matrix"] for f in json.loads(refined.read_text())["frames"]}
    replaced = 0
    for frame in meta["frames"]:
        if Path(frame["file_path"]).name in poses:
            frame["transform_matrix"], replaced = poses[Path(frame["file_path"]).name], replaced + 1
    if replaced == 0:
        raise ValueError(f"{refined}: no frame matches an image of {data}")
    (out / data.name).write_text(json.dumps(meta, indent=2) + "\n")
    return out / data.name


def main() -> None:
    import argparse

    extra = argparse.ArgumentParser(add_help=False)
    extra.add_argument("--first-lr", type=float, default=5e-4)
    extra.add_argument("--second-lr", type=float, default=1e-4)
    extra.add_argument("--second-warmup", type=int, default=1000)
    extra.add_argument("--suffix", default="")
    args = bench_args(__doc__, 2000, "/tmp/geer_two_pass", extra)
    _, perturbed, truth = perturbed_dev_room(args.work, args.size, f"two_pass_{args.size}")
    overrides = {**short_schedule(), "camera_optimizer.mode": "SO3xR3"}

    rows, data = [], perturbed
    passes = (("pass 1", args.first_lr, 200), ("pass 2", args.second_lr, args.second_warmup))
    for index, (name, lr, warmup) in enumerate(passes):
        tag = name.replace(" ", "_")
        fresh(args.work / "runs" / tag)
        metrics, seconds, pipeline = train_and_score(tag, data, args.steps, overrides, args.work,
                                                     {"camera_opt": adam_entry(lr, args.steps, warmup)})
        solved = solved_test_metrics(pipeline)
        cam = camera_errors(pipeline, truth, refined=True)
        rows.append(f"| {name}: lr {lr:g}, warm-up {warmup} | {metrics['psnr']:.2f} | {solved['psnr']:.2f} | "
                    f"{error_columns(cam)} | {seconds:.0f} |")
        print(rows[-1], flush=True)
        if index == 0:
            data = with_refined_poses(perturbed, args.work / "runs" / tag, args.work / f"two_pass_{args.size}_refined")
    report = f"""# Pose refinement in two passes

{__doc__.split(chr(10) + chr(10))[1]}

- {args.size}x{args.size}, {args.steps} steps a pass, densification to step 1000; camera_opt decays to 1e-5
- test PSNR: ns-eval's (test views at their true poses, in the refined frame); test poses solved: each test
  view's pose solved against the scene first; camera errors against the truth as lens_bench.py reads them
- CPU, 2 cores, load average {load_average()} when written; commit {git_commit()} (+ working tree)
- command: `{args.command}`

| pass | test PSNR | test poses solved | rotation deg (mean / max) | position % (mean / max) | aligned: rotation deg, position % | training s |
| --- | ---: | ---: | ---: | ---: | ---: | ---: |
""" + "\n".join(rows) + "\n"
    (ROOT / "benchmarks" / f"two_pass{args.suffix}.md").write_text(report)
    print(report)


if __name__ == "__main__":
    main()
