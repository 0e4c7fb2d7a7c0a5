"""Cameras brought to the truth: pose and lens refinement from perturbed cameras on the dev fisheye room.

The dev room at --size^2; for each seed, every training camera turned by 1 degree about a random axis and moved by
1 % of the scene's extent, the lens (every image's) with its focal lengths 2 % long and k1 moved by 0.02
(benchmarks/camera_perturbation.py with the seed; --perturbation changes the four). Runs of --steps steps with the
seed, every schedule following the run (geer_ns/training/horizon.py): geer on the true cameras; geer on the
perturbed ones without refinement, with Adam (SO3xR3 poses + `lens-refinement full`), with the registration recipe
(`camera-refinement register` + `lens-refinement full`); the recipe on the true cameras (good poses stay good);
splatfacto-fisheye with nerfstudio's camera optimizer (SO3xR3; splatfacto refines no lens) on the same perturbation;
and, as the optimiser's own baseline, each perturbed training pose solved by Levenberg-Marquardt against the
scene trained on the true cameras, frozen. Camera errors after the similarity fitted to the truth
(geer_ns/refinement/camera_errors.py). Every run's record is kept in --work and reused.

    python -m benchmarks.refinement [--size 128] [--steps 2000] [--seeds 1 2 3] [--only NAME ...]
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from benchmarks.camera_perturbation import perturb_cameras
from benchmarks.common import BENCHMARKS, dev_room, header, run_config, train_and_score
from geer_ns.compare.report import interval
from geer_ns.refinement.camera_errors import camera_errors

LENS = {"lens_refinement": "full"}
RUNS = {"true cameras": ("clean", {}), "perturbed, no refinement": ("noisy", {}),
        "perturbed, Adam (SO3xR3 + lens full)": ("noisy", {"camera_optimizer.mode": "SO3xR3", **LENS}),
        "perturbed, register + lens full": ("noisy", {"camera_refinement": "register", **LENS}),
        "true cameras, register": ("clean", {"camera_refinement": "register"}),
        "splatfacto-fisheye, camera optimizer SO3xR3": ("noisy", None)}
FROZEN = "frozen true scene, LM solve per camera"


def in_run_frame(pipeline, frames: dict) -> np.ndarray:
    """[N, 3, 4] the camera-to-worlds `frames` (file_path -> data-frame matrix) of the run's training images, in
    the run's frame (nerfstudio's dataparser transform and scale)."""
    outputs = pipeline.datamanager.train_dataparser_outputs
    transform = torch.cat([outputs.dataparser_transform, torch.tensor([[0.0, 0.0, 0.0, 1.0]])]).double()
    by_name = {"/".join(Path(k).parts[-2:]): np.asarray(v) for k, v in frames.items()}
    out = []
    for name in outputs.image_filenames:
        c2w = transform @ torch.from_numpy(by_name["/".join(Path(name).parts[-2:])])
        c2w[:3, 3] *= float(outputs.dataparser_scale)
        out.append(c2w[:3].numpy())
    return np.stack(out)


def lens_errors(pipeline, truth: dict) -> dict:
    """The refined lens of the first training camera against the true one: focal error (%, mean of fx and fy) and
    how far it moves each ray the true lens sees (px, mean / max over the inscribed image circle)."""
    from geer_ns.refinement.refined_cameras import refined_cameras

    cam, true = refined_cameras(pipeline)[0][0], truth["intrinsics"]
    names = {"fl_x": "fx", "fl_y": "fy"}
    exact = dataclasses.replace(cam, **{names.get(k, k): v for k, v in true.items() if hasattr(cam, names.get(k, k))})
    dirs, valid = exact.pixel_rays(torch.float64)
    inside = ((exact.pixel_centers(torch.float64) - torch.tensor([exact.cx, exact.cy], dtype=torch.float64)).norm(dim=-1)
              <= 0.5 * min(exact.width, exact.height))
    moved = (cam.project(dirs.reshape(-1, 3))[0] - exact.project(dirs.reshape(-1, 3))[0]).norm(dim=-1)
    moved = moved[(valid & inside).reshape(-1)]
    return {"focal_pct": 50.0 * (abs(cam.fx / exact.fx - 1) + abs(cam.fy / exact.fy - 1)),
            "lens_px": float(moved.mean()), "lens_px_max": float(moved.max())}


def errors(estimate: np.ndarray, truth_c2w: np.ndarray, extent: float) -> dict:
    e = camera_errors(estimate, truth_c2w, extent)
    return {"rot": e.rotation_deg, "pos": e.position_pct, "rpe_rot": e.relative_rotation_deg,
            "rpe_pos": e.relative_position_pct}


def frozen_solves(pipeline, noisy: dict, truth: dict, extent: float, iterations: int) -> dict:
    """Each training camera at its perturbed pose solved against `pipeline`'s scene (trained on the true cameras)."""
    from geer_ns.refinement.pose_solve import solve_view_pose

    given = torch.from_numpy(in_run_frame(pipeline, noisy)).float()
    solved = []
    for index in range(given.shape[0]):
        camera, batch = pipeline.datamanager.train_view(index)
        camera = copy.copy(camera)
        camera.camera_to_worlds = given[index : index + 1].to(camera.camera_to_worlds)
        solved.append(solve_view_pose(pipeline.model, camera, batch, iterations).camera_to_worlds[0].double().numpy())
    return errors(np.stack(solved), in_run_frame(pipeline, truth["frames"]), extent)


def train_splatfacto(data: Path, out: Path, steps: int, seed: int):
    from geer_ns.compare.run import train_timed
    from geer_ns.compare.splatfacto import splatfacto_trainer_config
    from geer_ns.training.horizon import stretch_schedules

    config = splatfacto_trainer_config("fisheye")
    config.data = config.pipeline.datamanager.data = config.pipeline.datamanager.dataparser.data = data
    config.output_dir, config.experiment_name, config.timestamp = out, "splatfacto", f"seed{seed}"
    config.vis, config.max_num_iterations, config.steps_per_save = "tensorboard", steps, 10**9
    config.steps_per_eval_image = config.steps_per_eval_batch = config.steps_per_eval_all_images = 0
    config.machine.seed = seed
    config.pipeline.model.camera_optimizer.mode = "SO3xR3"
    stretch_schedules(config, steps)
    trainer, seconds = train_timed(config)
    return trainer.pipeline, seconds


def one_run(name: str, seed: int, args, clean: Path, noisy: Path, truth: dict) -> dict:
    from geer_ns.refinement.refined_cameras import refined_poses
    from geer_ns.refinement.refined_frame import adjusted_poses

    where, options = RUNS[name]
    data = clean if where == "clean" else noisy
    if options is None:
        pipeline, seconds = train_splatfacto(data, args.work / "runs", args.steps, seed)
        record = {"psnr": None, "psnr_given": None, "seconds": seconds}
        model = pipeline.model
        estimate = adjusted_poses(model.camera_optimizer, pipeline.datamanager.train_dataset.cameras.camera_to_worlds)
    else:
        tag = f"{name}_{seed}".replace(" ", "_").replace(",", "").replace("+", "").replace("(", "").replace(")", "")
        metrics, seconds, pipeline = train_and_score(run_config(data, args.work / "runs", tag, args.steps, options,
                                                                seed=seed))
        record = {"psnr": metrics["psnr"], "psnr_given": metrics["psnr"], "seconds": seconds}
        if pipeline.model.refined_frame is not None:  # the test views at their given poses, not mapped
            frame, pipeline.model.refined_frame = pipeline.model.refined_frame, None
            record["psnr_given"] = pipeline.get_average_eval_image_metrics(step=args.steps)["psnr"]
            pipeline.model.refined_frame = frame
        estimate = refined_poses(pipeline)
    scale = float(pipeline.datamanager.train_dataparser_outputs.dataparser_scale)
    extent = truth["extent"] * scale
    record.update(errors(estimate.double().numpy(), in_run_frame(pipeline, truth["frames"]), extent))
    if options is not None and options.get("lens_refinement"):
        record.update(lens_errors(pipeline, truth))
    if name == "true cameras":
        noisy_frames = {f["file_path"]: f["transform_matrix"] for f in json.loads(noisy.read_text())["frames"]}
        return {name: record, FROZEN: frozen_solves(pipeline, noisy_frames, truth, extent, 2)}
    return {name: record}


def cell(records: list, key: str, index: int | None = None, digits: int = 3) -> str:
    values = [r[key] if index is None else r[key][index] for r in records if r.get(key) is not None]
    if not values:
        return "-"
    mean, half = interval(values)
    return f"{mean:.{digits}f}" + (f" +- {half:.{digits}f}" if half == half else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--only", nargs="+", default=[], choices=list(RUNS), metavar="RUN", help="run only these runs")
    ap.add_argument("--perturbation", type=float, nargs=4, default=(1.0, 0.01, 0.02, 0.02),
                    metavar=("ROT_DEG", "POS_FRACTION", "FOCAL_FRACTION", "K1_OFFSET"))
    ap.add_argument("--work", type=Path, default=Path("/tmp/geer_refinement"))
    ap.add_argument("--out", type=Path, default=BENCHMARKS / "refinement.md")
    args = ap.parse_args()
    clean = dev_room(args.work, args.size) / "transforms_fisheye.json"
    records_path = args.work / f"records_{args.size}_{args.steps}.jsonl"
    done = [json.loads(line) for line in records_path.read_text().splitlines()] if records_path.exists() else []
    for seed in args.seeds:
        noisy_dir = args.work / f"perturbed_{args.size}_seed{seed}"
        truth = (json.loads((noisy_dir / "cameras_truth.json").read_text()) if noisy_dir.exists() else
                 perturb_cameras(clean.parent, noisy_dir, clean.name, *args.perturbation, seed=seed))
        for name in RUNS:
            have = {r["run"] for r in done if r["seed"] == seed}
            if name in have or (args.only and name not in args.only):
                continue
            for run, record in one_run(name, seed, args, clean, noisy_dir / clean.name, truth).items():
                done.append({"run": run, "seed": seed, **record})
                with records_path.open("a") as f:
                    f.write(json.dumps(done[-1]) + "\n")
                print(done[-1], flush=True)
    rows = []
    for name in (*RUNS, FROZEN):
        rs = [r for r in done if r["run"] == name and r["seed"] in args.seeds]
        if rs:
            rows.append(f"| {name} | {len(rs)} | {cell(rs, 'psnr', digits=2)} | {cell(rs, 'psnr_given', digits=2)} | "
                        + " | ".join(cell(rs, k, i) for k, i in (("rot", 0), ("rot", 1), ("rot", 2), ("pos", 0),
                                                                  ("pos", 1), ("rpe_rot", 1), ("rpe_pos", 1)))
                        + f" | {cell(rs, 'lens_px')} | {cell(rs, 'focal_pct')} | {cell(rs, 'seconds', digits=0)} |")
    rot, pos, focal, k1 = args.perturbation
    text = header(
        "Cameras brought to the truth: pose and lens refinement from perturbed cameras",
        f"data: the dev fisheye room at {args.size}^2 (180-degree equidistant fisheye, native rays); per seed, every "
        f"training camera turned by {rot:g} degree about a random axis and moved by {100 * pos:g} % of the scene's "
        f"extent, the lens (all images) with focal {100 * focal:+g} % and k1 {k1:+g}; test poses true",
        f"runs: {args.steps} steps, schedules following the run (geer_ns/training/horizon.py), seeds "
        f"{' '.join(map(str, args.seeds))} (the perturbation's and the run's)",
        "a cell: the mean over the seeds +- the half-width of its 95 % Student-t interval. test PSNR: ns-eval's "
        "(geer: in the refined frame); at given poses: the test views as given; camera errors after the similarity "
        "fitted to the truth (rotation degrees, position % of the extent); RPE: each camera against its nearest "
        "neighbour (gauge-free), median; lens map: how far the refined lens moves each ray the true lens sees (px, "
        "mean); splatfacto's PSNR is not comparable here (other pixels: geer-compare scores both alike)",
    ) + ("\n| run | seeds | test PSNR | at given poses | rotation mean | rotation median | rotation max | position mean"
         " | position median | RPE rotation | RPE position | lens map px | focal % | train s |\n"
         + "| --- " * 14 + "|\n" + "\n".join(rows) + "\n")
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
