"""Lens and pose refinement on the dev fisheye room with perturbed training poses and a perturbed lens.

The dev room at --size^2; every training camera turned by 1 degree about a random axis and moved by 1 % of the
scene's extent, and the lens (every image's, test images' too) with its focal lengths 2 % long and k1 moved by
0.02 (benchmarks/camera_perturbation.py, seed 0). Runs of --steps steps from the same seed: the true cameras,
the perturbed ones without refinement, with pose refinement only (SO3xR3), and with pose and lens refinement
(`lens_refinement full`), each also with the Levenberg-Marquardt pose solve (`pose_solve_every`). Scored on
the test split as ns-eval does (test images: true poses, the run's lens);
the refined training cameras are compared with the truth. Writes benchmarks/lens_refinement.md (+ .json).

    python benchmarks/lens_bench.py [--size 64] [--steps 1000] [--work /tmp/geer_lens]
"""

from __future__ import annotations

from pose_bench import camera_errors, error_columns
from refinement_runs import (OPTIMIZER_NAMES, ROOT, adam_entry, bench_args, dump, git_commit, load_average,
                             model_options, perturbed_dev_room, record_every, short_schedule, solved_test_metrics,
                             train_and_score)


def lens_errors(pipeline, truth: dict) -> dict:
    """Relative focal error (%, mean of fx and fy) and the k1 error of the (first) training camera."""
    from geer_ns.refinement.refined_cameras import refined_cameras

    cam = refined_cameras(pipeline)[0][0]
    scale = float(pipeline.datamanager.train_dataparser_outputs.cameras.width[0, 0]) / truth["intrinsics"]["w"] \
        if "w" in truth["intrinsics"] else 1.0
    true = truth["intrinsics"]
    focal = 50.0 * (abs(cam.fx / (true["fl_x"] * scale) - 1) + abs(cam.fy / (true["fl_y"] * scale) - 1))
    map_mean, map_max = lens_map_error(cam, true, scale)
    return {"focal_pct": float(focal), "k1_abs": float(abs(cam.k1 - true.get("k1", 0.0))),
            "cx_px": float(cam.cx - true["cx"] * scale), "cy_px": float(cam.cy - true["cy"] * scale),
            "map_px_mean": map_mean, "map_px_max": map_max, "fx": cam.fx, "fy": cam.fy, "k1": cam.k1}


def lens_map_error(cam, true: dict, scale: float) -> tuple:
    """(mean, max) pixel distance between where the refined lens `cam` and the true lens put each ray the true
    lens sees in the inscribed image circle: the lens's own error, free of the trade-offs between its
    coefficients (a focal error that the distortion polynomial makes up for moves no pixel)."""
    import dataclasses

    import torch

    names = {"fl_x": "fx", "fl_y": "fy"}
    values = {names.get(k, k): (v * scale if k in ("fl_x", "fl_y", "cx", "cy") else v) for k, v in true.items()}
    truth = dataclasses.replace(cam, **{k: v for k, v in values.items() if hasattr(cam, k)})
    dirs, valid = truth.pixel_rays(torch.float64)
    pixels = truth.pixel_centers(torch.float64)
    inside = ((pixels - torch.tensor([truth.cx, truth.cy], dtype=torch.float64)).norm(dim=-1)
              <= 0.5 * min(truth.width, truth.height))  # the image circle (the inscribed one)
    dirs, valid = dirs.reshape(-1, 3), (valid & inside).reshape(-1)
    moved = (cam.project(dirs)[0] - truth.project(dirs)[0]).norm(dim=-1)[valid]
    return float(moved.mean()), float(moved.max())


def trace_table(name: str, trace: list) -> str:
    """A run's camera errors along training (lens_bench --trace), as a markdown section."""
    lines = "\n".join(f"| {t['step']} | {error_columns(t)} |" for t in trace)
    return f"""
### {name}: camera errors along training

| step | rotation deg (mean / max) | position % (mean / max) | aligned: rotation deg, position % (mean) |
| ---: | ---: | ---: | ---: |
{lines}
"""


def _report(args, record: dict, rows: list, traces: list) -> str:
    rot, pos, focal, k1 = args.perturbation[0], 100 * args.perturbation[1], 100 * args.perturbation[2], \
        args.perturbation[3]
    return f"""# Lens and pose refinement with perturbed training cameras

- data: the dev fisheye room at {args.size}x{args.size} (`benchmarks/refinement_runs.small_dev_room`, 180-degree
  equidistant fisheye; BEAP supervision, the crop circle keeps its rays within 84 degrees, so every BEAP target
  is resampled once through the perturbed lens and its cells rendered along the refined lens's rays), every
  training camera turned by {rot:g} degree(s) about a random axis and moved by {pos:g} % of the scene's extent,
  the lens (all images) with focal lengths {focal:+g} % and k1 {k1:+g} (`benchmarks/camera_perturbation.py`,
  seed 0; test poses true)
- runs: {args.steps} steps each, warm-up 300, refinement every 100 until step {args.densify_until}, full resolution
  unless options say otherwise, same seed; model options {record['options']}.
  SO3xR3: nerfstudio's camera optimizer from step {args.pose_start} (pose-refinement-start),
  {OPTIMIZER_NAMES[args.pose_optimizer]} lr
  {args.pose_lr:g} after a linear warm-up from 0 that ends at step {args.pose_start + args.pose_warmup}, decaying
  to 1e-5. Lens:
  `--pipeline.model.lens-refinement full --pipeline.model.lens-refinement-start 200`, Adam (lens_opt) lr
  {args.lens_lr:g} after a 200-step warm-up, decaying to 1e-5; gradients from the CPU build of the kernels. Pose
  solve: `--pipeline.model.pose-solve-every {args.pose_solve_every} --pipeline.model.pose-solve-iterations
  {args.pose_solve_iterations}` (geer_ns/refinement/pose_solve.py)
- lens map: how far (pixels) the refined lens moves each ray the true lens sees, mean / max over the image
  circle (independent of how focal and distortion coefficients trade off)
- camera errors: training cameras against the truth mapped into the dataparser's frame (no re-alignment; mean /
  max over the training cameras), position in % of the scene's extent; aligned: the same after the similarity
  that best maps the cameras' centres onto the truth's (pose_bench.similarity_aligned: the gauge images cannot
  fix, removed as BARF-style benchmarks do); focal in % (mean of fx and fy), k1 absolute, principal point in pixels
- scored on the test split (6 views, true poses, the run's lens: refined where refined) as ns-eval does: with
  pose refinement in the refined frame (the test poses moved by the similarity that maps the given training
  poses onto the refined ones, geer_ns/refinement/refined_frame.py; the training cameras' errors are those of the poses as
  exported, mapped back); "as given": the test views at their given poses; "test poses solved": each test view's
  pose solved against the trained scene first (the test-time pose alignment of pose-refinement benchmarks:
  `refinement_runs.solved_test_metrics`)
- device: CPU, 2 cores shared with other jobs (training seconds vary with the other jobs: not a speed measure; load average {load_average()} when written; one run each)
- commit: {record['commit']} (+ the working tree that adds this file)
- command: `{args.command}`

| run | test PSNR | test PSNR, as given | test PSNR, test poses solved | test SSIM | rotation deg (mean / max) | position % (mean / max) | aligned: rotation deg, position % (mean) | lens map px (mean / max) | focal % | k1 | cx, cy px | training s |
| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |
""" + "\n".join(rows) + "\n" + "".join(traces)


def main() -> None:
    import argparse

    extra = argparse.ArgumentParser(add_help=False)
    extra.add_argument("--lens-lr", type=float, default=2e-3)
    extra.add_argument("--pose-lr", type=float, default=5e-4, help="camera_opt's (SO3xR3) learning rate")
    extra.add_argument("--pose-optimizer", choices=tuple(OPTIMIZER_NAMES), default="adam",
                       help="camera_opt's optimizer: torch's Adam, or benchmarks/lazy_adam.py")
    extra.add_argument("--pose-warmup", type=int, default=200,
                       help="camera_opt's warm-up: its learning rate rises from 0 over this many steps")
    extra.add_argument("--pose-start", type=int, default=0,
                       help="--pipeline.model.pose-refinement-start of the pose runs; camera_opt's warm-up then "
                            "ends --pose-warmup steps after it")
    extra.add_argument("--densify-until", type=int, default=1000, help="the last step that densifies (0: none)")
    extra.add_argument("--only", nargs="+", default=[], help="run only the runs whose name contains one of these")
    extra.add_argument("--skip", nargs="+", default=[], help="leave out the runs whose name contains one of these")
    extra.add_argument("--suffix", default="", help="appended to the report's file names")
    extra.add_argument("--trace", type=int, default=0, metavar="EVERY",
                       help="record the refined runs' camera errors every EVERY steps (0: only at the end)")
    extra.add_argument("--set", nargs="*", default=[], metavar="OPTION=VALUE",
                       help="model options for every run (dotted; values as JSON), e.g. num_downscales=2")
    extra.add_argument("--pose-penalty", type=float, nargs=2, default=(1e-2, 1e-3), metavar=("TRANS", "ROT"),
                       help="nerfstudio's camera optimizer L2 penalties on the pose adjustments (its defaults)")
    extra.add_argument("--pose-solve-every", type=int, default=500,
                       help="the '+ pose solve' runs: --pipeline.model.pose-solve-every")
    extra.add_argument("--pose-solve-iterations", type=int, default=3)
    extra.add_argument("--aspect", action="store_true", help="refine fy / fx too (lens-refinement-aspect)")
    extra.add_argument("--perturbation", type=float, nargs=4, default=(1.0, 0.01, 0.02, 0.02),
                       metavar=("ROT_DEG", "POS_FRACTION", "FOCAL_FRACTION", "K1_OFFSET"),
                       help="the training cameras' rotation (degrees) and move (fraction of the extent), the lens's "
                            "focal change (fraction) and k1 offset")
    args = bench_args(__doc__, 1000, "/tmp/geer_lens", extra)
    rotation_deg, position_fraction, focal_fraction, k1_offset = args.perturbation
    clean, perturbed, truth = perturbed_dev_room(
        args.work, args.size, f"lens_{args.size}", rotation_deg=rotation_deg, position_fraction=position_fraction,
        focal_fraction=focal_fraction, k1_offset=k1_offset)
    schedule = short_schedule(args.densify_until)
    schedule.update(model_options(args.set))

    optimizers = {"camera_opt": adam_entry(args.pose_lr, args.steps, args.pose_start + args.pose_warmup,
                                           args.pose_optimizer),
                  "lens_opt": adam_entry(args.lens_lr, args.steps, 200)}
    poses = {"camera_optimizer.mode": "SO3xR3", "pose_refinement_start": args.pose_start,
             "camera_optimizer.trans_l2_penalty": args.pose_penalty[0],
             "camera_optimizer.rot_l2_penalty": args.pose_penalty[1]}
    lens_only = {"lens_refinement": "full", "lens_refinement_start": 200, "lens_refinement_aspect": args.aspect}
    lens = {**poses, **lens_only}
    solve = {"pose_solve_every": args.pose_solve_every, "pose_solve_iterations": args.pose_solve_iterations}
    runs = {"perturbed, no refinement": (perturbed, {}),
            "perturbed, SO3xR3 poses + lens full": (perturbed, lens),
            "true cameras": (clean, {}),
            "perturbed, SO3xR3 poses only": (perturbed, poses),
            "perturbed, lens full (poses fixed)": (perturbed, lens_only),
            "perturbed, SO3xR3 poses only + pose solve": (perturbed, {**poses, **solve}),
            "perturbed, SO3xR3 poses + lens full + pose solve": (perturbed, {**lens, **solve})}
    if args.only:
        runs = {k: v for k, v in runs.items() if any(part in k for part in args.only)}
    runs = {k: v for k, v in runs.items() if not any(part in k for part in args.skip)}
    record = {"commit": git_commit(), "size": args.size, "steps": args.steps, "lens_lr": args.lens_lr,
              "pose_lr": args.pose_lr, "pose_warmup": args.pose_warmup, "pose_optimizer": args.pose_optimizer,
              "pose_start": args.pose_start,
              "perturbation": list(args.perturbation), "densify_until": args.densify_until, "options": schedule,
              "runs": {}}
    rows, trace, traces = [], [], []
    if args.trace:
        record_every(args.trace, args.steps - 1, lambda pipeline: camera_errors(pipeline, truth, refined=True)
                     if pipeline.model.refining_poses else None, trace)
    for name, (data, overrides) in runs.items():
        trace.clear()
        tag = name.replace(" ", "_").replace(",", "").replace("+", "")
        metrics, seconds, pipeline = train_and_score(tag, data, args.steps, {**schedule, **overrides}, args.work,
                                                     optimizers)
        solved = solved_test_metrics(pipeline)
        as_given = metrics["psnr"]
        frame = pipeline.model.refined_frame
        if frame is not None:
            pipeline.model.refined_frame = None
            as_given = pipeline.get_average_eval_image_metrics(step=args.steps)["psnr"]
            pipeline.model.refined_frame = frame
        entry = {"seconds": seconds, "psnr": metrics["psnr"], "ssim": metrics["ssim"], "psnr_as_given": as_given,
                 "psnr_test_poses_solved": solved["psnr"]}
        if data != clean:
            entry["cameras"] = camera_errors(pipeline, truth, refined="camera_optimizer.mode" in overrides)
            entry["lens"] = lens_errors(pipeline, truth)
        if trace:
            entry["trace"] = list(trace)
            traces.append(trace_table(name, trace))
        record["runs"][name] = entry
        cam, lens_e = entry.get("cameras"), entry.get("lens")
        if cam:
            errors = (f"{error_columns(cam)} | {lens_e['map_px_mean']:.3f} / {lens_e['map_px_max']:.3f} | "
                      f"{lens_e['focal_pct']:.3f} | {lens_e['k1_abs']:.4f} | {lens_e['cx_px']:+.2f}, {lens_e['cy_px']:+.2f}")
        else:
            errors = "0 | 0 | 0 | 0 | 0 | 0 | 0"
        rows.append(f"| {name} | {metrics['psnr']:.2f} | {as_given:.2f} | {solved['psnr']:.2f} | {metrics['ssim']:.3f} | {errors} | "
                    f"{seconds:.0f} |")
        print(rows[-1], flush=True)
        dump(ROOT / "benchmarks" / f"lens_refinement_runs{args.suffix}.json", record)
        (ROOT / "benchmarks" / f"lens_refinement{args.suffix}.md").write_text(_report(args, record, rows, traces))
    print(_report(args, record, rows, traces))


if __name__ == "__main__":
    main()
