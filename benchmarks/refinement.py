"""Pose and lens refinement from perturbed cameras, on the dev fisheye room.

The dev room at --size^2; every training camera turned by 1 degree about a random axis and moved by 1 % of the
scene's extent, and the lens (every image's, test images' too) with its focal lengths 2 % long and k1 moved by
0.02 (benchmarks/camera_perturbation.py, seed 0; --perturbation changes the four). Runs of --steps steps from the
same seed: the true cameras, the perturbed ones without refinement, with pose refinement (SO3xR3), with pose and
lens refinement (`lens-refinement full`), each refining run also with the Levenberg-Marquardt pose solve
(`pose-solve-every`). Scored on the test split as ns-eval does (in the refined frame), with the test views at
their given poses, and with each test view's pose solved against the trained scene first (BARF's protocol); the
refined training cameras and lens are compared with the truth.

    python -m benchmarks.refinement [--size 128] [--steps 2000] [--only NAME ...]    # writes benchmarks/refinement.md
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
from pathlib import Path

import numpy as np
import torch

from benchmarks.camera_perturbation import perturb_cameras, pose_errors
from benchmarks.common import BENCHMARKS, dev_room, header, run_config, short_schedule, train_and_score


def adam_entry(lr: float, steps: int, warmup: int) -> dict:
    """An optimizer entry: Adam at `lr` after a linear warm-up from 0 over `warmup` steps, decaying to 1e-5."""
    from nerfstudio.engine.optimizers import AdamOptimizerConfig
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    return {"optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-5, max_steps=steps, warmup_steps=warmup,
                                                         lr_pre_warmup=0.0)}


def similarity_aligned(c2w: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """c2w [N,3,4] moved by the similarity that best maps its camera centres onto the truth's (Umeyama): the gauge
    that images cannot fix, removed as BARF-style pose benchmarks do before the errors are read."""
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


def camera_errors(pipeline, truth: dict, refined: bool) -> dict:
    """Rotation (degrees) and position (% of the extent) errors of the training cameras, as exported (in the
    given frame) and after similarity_aligned: mean and max."""
    from geer_ns.refinement.refined_cameras import refined_poses

    outputs = pipeline.datamanager.train_dataparser_outputs
    c2w = pipeline.datamanager.train_dataset.cameras.camera_to_worlds.detach().clone()
    if refined:
        c2w = refined_poses(pipeline).to(c2w.dtype)
    transform = torch.cat([outputs.dataparser_transform, torch.tensor([[0.0, 0.0, 0.0, 1.0]])]).double()
    scale = float(outputs.dataparser_scale)
    by_name = {"/".join(Path(k).parts[-2:]): np.asarray(v) for k, v in truth["frames"].items()}
    true = []
    for name in outputs.image_filenames:
        t = transform @ torch.from_numpy(by_name["/".join(Path(name).parts[-2:])])
        t[:3, 3] *= scale
        true.append(t[:3].numpy())
    c2w, true = c2w.double().numpy(), np.stack(true)
    errors = {}
    for prefix, estimate in (("", c2w), ("aligned_", similarity_aligned(c2w, true))):
        rot, pos = pose_errors(estimate, true)
        pos = 100.0 * pos / scale / truth["extent"]
        errors.update({f"{prefix}rot": (rot.mean(), rot.max()), f"{prefix}pos": (pos.mean(), pos.max())})
    return errors


def lens_errors(pipeline, truth: dict) -> dict:
    """The first training camera's refined lens against the truth: focal error (%, mean of fx and fy), k1 error,
    and how far (pixels, mean / max over the inscribed image circle) it moves each ray the true lens sees (its own
    error, free of the trade-offs between its coefficients)."""
    from geer_ns.refinement.refined_cameras import refined_cameras

    cam, true = refined_cameras(pipeline)[0][0], truth["intrinsics"]
    names = {"fl_x": "fx", "fl_y": "fy"}
    exact = dataclasses.replace(cam, **{names.get(k, k): v for k, v in true.items() if hasattr(cam, names.get(k, k))})
    dirs, valid = exact.pixel_rays(torch.float64)
    inside = ((exact.pixel_centers(torch.float64) - torch.tensor([exact.cx, exact.cy], dtype=torch.float64)).norm(dim=-1)
              <= 0.5 * min(exact.width, exact.height))
    moved = (cam.project(dirs.reshape(-1, 3))[0] - exact.project(dirs.reshape(-1, 3))[0]).norm(dim=-1)
    moved = moved[(valid & inside).reshape(-1)]
    return {"focal": 50.0 * (abs(cam.fx / exact.fx - 1) + abs(cam.fy / exact.fy - 1)), "k1": abs(cam.k1 - exact.k1),
            "map": (float(moved.mean()), float(moved.max()))}


def row(name: str, metrics: dict, as_given: float, solved: float, cams: dict | None, lens: dict | None) -> str:
    pair = lambda p, digits=3: f"{p[0]:.{digits}f} / {p[1]:.{digits}f}"  # noqa: E731
    cells = [name, f"{metrics['psnr']:.2f}", f"{as_given:.2f}", f"{solved:.2f}"]
    if cams:
        cells += [pair(cams["rot"]), pair(cams["pos"]), f"{cams['aligned_rot'][0]:.3f}, {cams['aligned_pos'][0]:.3f}",
                  pair(lens["map"]), f"{lens['focal']:.3f}", f"{lens['k1']:.4f}"]
    else:
        cells += ["0"] * 6
    return "| " + " | ".join(cells) + " |"


def pose_solved(pipeline, camera, batch):
    """The test camera with its pose solved against the trained scene (geer_ns.refinement.pose_solve)."""
    from geer_ns.refinement.pose_solve import solve_view_pose

    return solve_view_pose(pipeline.model, camera, batch, 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--only", nargs="+", default=[], help="run only the runs whose name contains one of these")
    ap.add_argument("--perturbation", type=float, nargs=4, default=(1.0, 0.01, 0.02, 0.02),
                    metavar=("ROT_DEG", "POS_FRACTION", "FOCAL_FRACTION", "K1_OFFSET"))
    ap.add_argument("--pose-lr", type=float, default=5e-4, help="camera_opt's (SO3xR3) learning rate")
    ap.add_argument("--lens-lr", type=float, default=2e-3)
    ap.add_argument("--pose-solve-every", type=int, default=500)
    ap.add_argument("--pose-solve-iterations", type=int, default=2)
    ap.add_argument("--work", type=Path, default=Path("/tmp/geer_refinement"))
    ap.add_argument("--out", type=Path, default=BENCHMARKS / "refinement.md")
    args = ap.parse_args()
    clean = dev_room(args.work, args.size) / "transforms_fisheye.json"
    noisy = args.work / f"perturbed_{args.size}"
    if noisy.exists():
        shutil.rmtree(noisy)
    truth = perturb_cameras(clean.parent, noisy, clean.name, *args.perturbation)
    optimizers = {"camera_opt": adam_entry(args.pose_lr, args.steps, 200), "lens_opt": adam_entry(args.lens_lr, args.steps, 200)}
    poses = {"camera_optimizer.mode": "SO3xR3"}
    lens = {"lens_refinement": "full", "lens_refinement_start": 200}
    solve = {"pose_solve_every": args.pose_solve_every, "pose_solve_iterations": args.pose_solve_iterations}
    runs = {"true cameras": (clean, {}), "perturbed, no refinement": (noisy / clean.name, {}),
            "perturbed, SO3xR3 poses": (noisy / clean.name, poses),
            "perturbed, SO3xR3 poses + pose solve": (noisy / clean.name, {**poses, **solve}),
            "perturbed, SO3xR3 poses + lens full": (noisy / clean.name, {**poses, **lens}),
            "perturbed, SO3xR3 poses + lens full + pose solve": (noisy / clean.name, {**poses, **lens, **solve})}
    runs = {k: v for k, v in runs.items() if not args.only or any(part in k for part in args.only)}
    rows = []
    for name, (data, options) in runs.items():
        tag = name.replace(" ", "_").replace(",", "").replace("+", "")
        config = run_config(data, args.work / "runs", tag, args.steps, {**short_schedule(), **options})
        config.optimizers.update(optimizers)
        metrics, _, pipeline = train_and_score(config)
        views = [(pose_solved(pipeline, camera, batch), batch)
                 for camera, batch in pipeline.datamanager.fixed_indices_eval_dataloader]
        solved = pipeline.get_average_image_metrics(views, image_prefix="eval")["psnr"]
        as_given, frame = metrics["psnr"], pipeline.model.refined_frame
        if frame is not None:  # the test views at their given poses, not mapped into the refined frame
            pipeline.model.refined_frame = None
            as_given = pipeline.get_average_eval_image_metrics(step=args.steps)["psnr"]
            pipeline.model.refined_frame = frame
        refined = data != clean
        cams = camera_errors(pipeline, truth, "camera_optimizer.mode" in options) if refined else None
        rows.append(row(name, metrics, as_given, solved, cams, lens_errors(pipeline, truth) if refined else None))
        print(rows[-1], flush=True)
    rot, pos, focal, k1 = args.perturbation
    text = header(
        "Pose and lens refinement from perturbed cameras",
        f"data: the dev fisheye room at {args.size}^2 (180-degree equidistant fisheye, BEAP supervision), every "
        f"training camera turned by {rot:g} degree about a random axis and moved by {100 * pos:g} % of the scene's "
        f"extent, the lens (all images) with focal {100 * focal:+g} % and k1 {k1:+g} (seed 0; test poses true)",
        f"runs: {args.steps} steps, warm-up 300, densification every 100 steps to step 1000, full resolution, same "
        f"seed. SO3xR3: Adam lr {args.pose_lr:g} after a 200-step warm-up, decaying to 1e-5; lens: `lens-refinement "
        f"full`, from step 200, Adam lr {args.lens_lr:g}; pose solve: every {args.pose_solve_every} steps, "
        f"{args.pose_solve_iterations} iterations per blur level",
        "test PSNR: ns-eval's (refined frame); as given: the test views at their given poses; solved: each test "
        "view's pose solved against the scene first. Camera errors: mean / max over the training cameras as "
        "exported; aligned: after the similarity of the camera centres (mean). Lens map: how far the refined lens "
        "moves each ray the true lens sees (px); focal %; |k1 error|",
    ) + ("\n| run | test PSNR | as given | solved | rotation deg | position % | aligned: rotation deg, position % | "
         "lens map px | focal % | k1 |\n| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n"
         + "\n".join(rows) + "\n")
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
