"""Pose refinement on the dev fisheye room with perturbed training poses (benchmarks/camera_perturbation.py).

The dev room at --size^2; every training camera turned by 1 degree about a random axis and moved by 1 % of the
scene's extent (test cameras true). Three runs of --steps steps from the same seed: the true poses, the
perturbed poses without refinement, and the perturbed poses with nerfstudio's SO3xR3 camera optimizer (its
gradient from the CPU build of the kernels; Adam lr 5e-4 after a 200-step warm-up, decaying to 1e-5). Scored on
the test split as ns-eval does; the refined training cameras are compared with the truth (mapped into the
dataparser's frame), as the perturbed ones are. Writes benchmarks/pose_refinement_runs.md.

    python benchmarks/pose_bench.py [--size 80] [--steps 1200] [--work /tmp/geer_poses]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from refinement_runs import ROOT, bench_args, dump, git_commit, load_average, perturbed_dev_room, train_and_score


def camera_errors(pipeline, truth: dict, refined: bool) -> dict:
    """Mean / max rotation (degrees) and position (% of the extent) error of the training cameras."""
    outputs = pipeline.datamanager.train_dataparser_outputs
    cameras = pipeline.datamanager.train_dataset.cameras
    c2w = cameras.camera_to_worlds.detach().clone()
    if refined:  # as the run exports them: in the given frame (geer_ns/refinement/refined_frame.py)
        from geer_ns.refinement.refined_cameras import refined_poses

        c2w = refined_poses(pipeline).to(c2w.dtype)
    transform = torch.cat([outputs.dataparser_transform, torch.tensor([[0.0, 0.0, 0.0, 1.0]])]).double()
    scale = float(outputs.dataparser_scale)
    by_name = {"/".join(Path(k).parts[-2:]): np.asarray(v) for k, v in truth["frames"].items()}
    true = []
    for name in outputs.image_filenames:
        t = transform @ torch.from_numpy(by_name["/".join(Path(name).parts[-2:])])
        t[:3, 3] *= scale
        true.append(t[:3].numpy())
    return error_summary(c2w.double().numpy(), np.stack(true), scale, truth["extent"])


def error_summary(c2w: np.ndarray, true: np.ndarray, scale: float, extent: float) -> dict:
    """Mean / max rotation (degrees) and position (% of `extent`, a length in the data's units; `scale` the
    dataparser's) errors of camera-to-worlds [N, 3, 4] against `true`, as they are and (keys aligned_...) after
    similarity_aligned."""
    from benchmarks.camera_perturbation import pose_errors

    errors = {}
    for prefix, estimate in (("", c2w), ("aligned_", similarity_aligned(c2w, true))):
        rot, pos = pose_errors(estimate, true)
        pos = 100.0 * pos / scale / extent
        errors.update({f"{prefix}rotation_deg_mean": float(rot.mean()), f"{prefix}rotation_deg_max": float(rot.max()),
                       f"{prefix}position_pct_mean": float(pos.mean()), f"{prefix}position_pct_max": float(pos.max())})
    return errors


def error_columns(errors: dict) -> str:
    """error_summary's rotation, position and aligned errors as three markdown table cells: "rot mean / max |
    pos mean / max | aligned rot, aligned pos" (the reports' shared columns)."""
    return (f"{errors['rotation_deg_mean']:.3f} / {errors['rotation_deg_max']:.3f} | "
            f"{errors['position_pct_mean']:.3f} / {errors['position_pct_max']:.3f} | "
            f"{errors['aligned_rotation_deg_mean']:.3f}, {errors['aligned_position_pct_mean']:.3f}")


def similarity_aligned(c2w: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """c2w [N,3,4] moved by the similarity that best maps its camera centres onto the truth's (Umeyama, least
    squares): the gauge (frame and scale) that training on images alone cannot fix, removed as BARF-style pose
    benchmarks do before the errors are read."""
    x, y = c2w[:, :3, 3], truth[:, :3, 3]
    mx, my = x.mean(0), y.mean(0)
    u, d, vt = np.linalg.svd((y - my).T @ (x - mx) / len(x))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ sign @ vt
    scale = np.trace(np.diag(d) @ sign) / ((x - mx) ** 2).sum(1).mean()
    out = c2w.copy()
    out[:, :3, :3] = rot @ c2w[:, :3, :3]
    out[:, :3, 3] = scale * (x - mx) @ rot.T + my
    return out


def _report(args, record: dict, truth: dict, rows: list) -> str:
    """The markdown report of the runs so far."""
    return f"""# Pose refinement with perturbed training cameras

- data: the dev fisheye room at {args.size}x{args.size} (`benchmarks/refinement_runs.small_dev_room`), every
  training camera turned by 1 degree about a random axis and moved by 1 % of the scene's extent
  (`benchmarks/camera_perturbation.py`, seed 0; test cameras true)
- runs: {args.steps} steps each, warm-up 300, refinement every 100 until step 1000, full resolution, same seed;
  SO3xR3: nerfstudio's camera optimizer, Adam lr 5e-4 after a 200-step warm-up, decaying to 1e-5; pose
  gradients from the CPU build of the kernels
- camera errors: training cameras against the truth mapped into the dataparser's frame (no re-alignment),
  mean / max over the {len(truth['frames']) - 6} training cameras; position in % of the scene's extent
- scored on the test split (6 views) as ns-eval does
- device: CPU, 2 cores shared with other jobs (load average {load_average()} when written; one run each)
- commit: {record['commit']} (+ the working tree that adds this file)
- command: `python benchmarks/pose_bench.py --size {args.size} --steps {args.steps}`

| run | test PSNR | test SSIM | rotation error deg (mean / max) | position error % (mean / max) | training s |
| --- | ---: | ---: | ---: | ---: | ---: |
""" + "\n".join(rows) + "\n"


def main() -> None:
    args = bench_args(__doc__, 1200, "/tmp/geer_poses")
    from nerfstudio.engine.optimizers import AdamOptimizerConfig
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    clean, perturbed, truth = perturbed_dev_room(args.work, args.size, f"poses_{args.size}")
    schedule = {"warmup_length": 300, "refine_every": 100, "stop_split_at": 1000, "num_downscales": 0}
    camera_opt = {"camera_opt": {
        "optimizer": AdamOptimizerConfig(lr=5e-4, eps=1e-15),
        "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-5, max_steps=args.steps, warmup_steps=200,
                                                     lr_pre_warmup=0.0)}}
    runs = {"perturbed, no refinement": (perturbed, {}),
            "perturbed, SO3xR3": (perturbed, {"camera_optimizer.mode": "SO3xR3"}), "true poses": (clean, {})}
    record = {"commit": git_commit(), "size": args.size, "steps": args.steps, "runs": {}}
    rows = []
    for name, (data, overrides) in runs.items():
        metrics, seconds, pipeline = train_and_score(name.replace(" ", "_").replace(",", ""), data, args.steps,
                                                     {**schedule, **overrides}, args.work, camera_opt)
        entry = {"seconds": seconds, "psnr": metrics["psnr"], "ssim": metrics["ssim"]}
        if data != clean:
            entry["cameras"] = camera_errors(pipeline, truth, refined="camera_optimizer.mode" in overrides)
        record["runs"][name] = entry
        cam = entry.get("cameras")
        errors = (f"{cam['rotation_deg_mean']:.3f} / {cam['rotation_deg_max']:.3f} | "
                  f"{cam['position_pct_mean']:.3f} / {cam['position_pct_max']:.3f}") if cam else "0 | 0"
        rows.append(f"| {name} | {metrics['psnr']:.2f} | {metrics['ssim']:.3f} | {errors} | {seconds:.0f} |")
        print(rows[-1], flush=True)
        dump(ROOT / "benchmarks" / "pose_refinement_runs.json", record)
        report = _report(args, record, truth, rows)
        (ROOT / "benchmarks" / "pose_refinement_runs.md").write_text(report)  # after every run
    print(report)


if __name__ == "__main__":
    main()
