"""Pose refinement by rebuilding: rounds of a scene trained from scratch on the current poses, then one
Levenberg-Marquardt solve of every training camera against it.

The dev room at --size^2 with every training camera turned by 1 degree and moved by 1 % of the extent (seed 0,
test poses true, lens true). Each round trains a new scene for --steps steps with the poses held (camera_opt at
lr 1e-8: no Adam wander), solves every camera at its last step (geer_ns/refinement/pose_solve.py, 2 iterations per blur
level), and hands the solved poses (the run's cameras_refined.json) to the next round: alternation in which no
scene keeps the memory of poses already corrected. Writes benchmarks/rebuild_rounds{suffix}.md.

    python benchmarks/rebuild_rounds.py [--size 128] [--steps 501] [--rounds 5]
"""

from __future__ import annotations

from pose_bench import camera_errors, error_columns
from refinement_runs import (ROOT, adam_entry, bench_args, fresh, git_commit, load_average, perturbed_dev_room,
                             short_schedule, train_and_score)
from two_pass import with_refined_poses


def main() -> None:
    import argparse

    extra = argparse.ArgumentParser(add_help=False)
    extra.add_argument("--rounds", type=int, default=5)
    extra.add_argument("--suffix", default="")
    args = bench_args(__doc__, 501, "/tmp/geer_rebuild", extra)
    _, perturbed, truth = perturbed_dev_room(args.work, args.size, f"rebuild_{args.size}")
    densify_until = min(1000, args.steps - 100)
    overrides = {**short_schedule(densify_until), "camera_optimizer.mode": "SO3xR3",
                 "pose_solve_every": args.steps - 1, "pose_solve_iterations": 2}
    rows, data = [], perturbed
    for index in range(args.rounds):
        tag = f"round_{index + 1}"
        fresh(args.work / "runs" / tag)
        metrics, seconds, pipeline = train_and_score(tag, data, args.steps, overrides, args.work,
                                                     {"camera_opt": adam_entry(1e-8, args.steps, 200)})
        rows.append(f"| {index + 1} | {metrics['psnr']:.2f} | {error_columns(camera_errors(pipeline, truth, True))} "
                    f"| {seconds:.0f} |")
        print(rows[-1], flush=True)
        data = with_refined_poses(perturbed, args.work / "runs" / tag, args.work / f"{tag}_poses")
    report = f"""# Pose refinement by rebuilding the scene

{__doc__.split(chr(10) + chr(10))[1]}

- {args.size}x{args.size}, {args.steps} steps a round, densification to step {densify_until}; the errors are
  those of each round's solved poses as exported (cameras_refined.json), read as lens_bench.py reads them
- test PSNR: ns-eval's, of the round's scene (trained on the poses before its solve), in the refined frame
- CPU, 2 cores, load average {load_average()} when written; commit {git_commit()} (+ working tree)
- command: `{args.command}`

| round | test PSNR | rotation deg (mean / max) | position % (mean / max) | aligned: rotation deg, position % | training s |
| ---: | ---: | ---: | ---: | ---: | ---: |
""" + "\n".join(rows) + "\n"
    (ROOT / "benchmarks" / f"rebuild_rounds{args.suffix}.md").write_text(report)
    print(report)


if __name__ == "__main__":
    main()
