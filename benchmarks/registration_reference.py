"""How good a reference the registration recipe's low-capacity scene is: rounds of (train it, solve every pose).

The recipe (`camera-refinement register`, geer_ns/refinement/registration.py) solves each training pose by
Levenberg-Marquardt against a scene whose means are held at the seed points, SH degree 0, no densification. A solve
is only as good as the scene it solves against: against a scene trained on the true cameras to convergence it
reaches 0.01 degree (benchmarks/refinement.md). This measures the reference the recipe actually has.

Each round trains the scene --steps-per-round steps with the poses (and, by default, the means) held, then solves
every training pose (pose_solve.solve_poses, the recipe's solve; where the lens is perturbed, the lens first:
lens_solve.solve_lens, unless --no-lens-solve) and reads the camera errors against the truth
(truth-fitted similarity, geer_ns/refinement/camera_errors.py). Training runs nerfstudio's train_iteration
directly, without the training callbacks (so no densification, no opacity reset, no scheduled solve). Cameras:
the dev room at --size^2 as given (`--cameras true`: does the solve keep good poses?) or perturbed as in
benchmarks/refinement.py (`perturbed`, lens included and refined by Adam; `perturbed-poses`: the poses only).
One line per round is appended to --out; --round-steps gives rounds of different lengths (short ones while the
poses are rough, then long ones).

    python -m benchmarks.registration_reference --cameras true --steps-per-round 1500 --rounds 1
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from benchmarks.camera_perturbation import perturb_cameras
from benchmarks.common import BENCHMARKS, dev_room, header, run_config
from benchmarks.refinement import errors, in_run_frame, lens_errors

PERTURBATIONS = {"true": None, "perturbed": (1.0, 0.01, 0.02, 0.02), "perturbed-poses": (1.0, 0.01, 0.0, 0.0)}


def data_and_truth(work: Path, size: int, cameras: str, seed: int) -> tuple[Path, dict]:
    clean = dev_room(work, size) / "transforms_fisheye.json"
    pert = PERTURBATIONS[cameras] or (1.0, 0.01, 0.02, 0.02)  # the truth of the true run: any perturbation's record
    noisy = work / f"perturbed_{size}_seed{seed}" if pert[2] else work / f"perturbed_poses_{size}_seed{seed}"
    truth = (json.loads((noisy / "cameras_truth.json").read_text()) if noisy.exists() else
             perturb_cameras(clean.parent, noisy, clean.name, *pert, seed=seed))
    return (clean if PERTURBATIONS[cameras] is None else noisy / clean.name), truth


def reset_scene(trainer, model, seed_scene: dict) -> None:
    """The Gaussians back to `seed_scene` (no densification runs here: the shapes are the seed's), their Adam
    state cleared; poses, lens and their optimizers untouched."""
    with torch.no_grad():
        for name, p in model.gauss_params.items():
            p.copy_(seed_scene[name])
            trainer.optimizers.optimizers[name].state.clear()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cameras", choices=list(PERTURBATIONS), default="true")
    ap.add_argument("--steps-per-round", type=int, default=1500)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--round-steps", type=str, default=None,
                    help="each round's length, comma-separated (e.g. 500,500,1500); replaces the two above")
    ap.add_argument("--train-means", action="store_true", help="train the means too (the recipe holds them)")
    ap.add_argument("--reset-scene", action="store_true",
                    help="start each round after the first from the seed scene (fresh Adam state): the reference "
                         "then holds only what the current poses put in it, not what earlier poses did")
    ap.add_argument("--no-lens-solve", action="store_true",
                    help="leave the lens to Adam (the recipe solves it before the poses)")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--work", type=Path, default=Path("/tmp/geer_refinement"))
    ap.add_argument("--out", type=Path, default=BENCHMARKS / "registration_reference.md")
    args = ap.parse_args()
    rounds = ([int(n) for n in args.round_steps.split(",")] if args.round_steps
              else [args.steps_per_round] * args.rounds)

    import geer_ns.config  # noqa: F401 - before nerfstudio's writer (docs/training.md)
    from geer_ns.refinement.lens_solve import solve_lens
    from geer_ns.refinement.pose_solve import solve_poses
    from geer_ns.refinement.refined_cameras import refined_poses

    data, truth = data_and_truth(args.work, args.size, args.cameras, args.seed)
    lens = PERTURBATIONS[args.cameras] is not None and PERTURBATIONS[args.cameras][2] != 0
    options = {"camera_optimizer.mode": "SO3xR3", "lens_refinement": "full" if lens else "off",
               "warmup_length": 10**6, "sh_degree": 0, "num_downscales": 0}
    config = run_config(data, args.work / "runs", f"reference_{args.cameras}", sum(rounds),
                        options, seed=args.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    pipeline, model = trainer.pipeline, trainer.pipeline.model
    extent = truth["extent"] * float(pipeline.datamanager.train_dataparser_outputs.dataparser_scale)
    true_c2w = in_run_frame(pipeline, truth["frames"])
    held = {"camera_opt"} | (set() if args.train_means else {"means"})
    title = "The registration scene as a reference: rounds of training it and solving every pose"
    table = ("\n| cameras | means | steps trained | solve s | moved deg | rotation mean / median / max deg | position "
             "median % | RPE rotation | focal % | lens px |\n" + "| --- " * 10 + "|\n")
    if not args.out.exists():
        args.out.write_text(header(title) + table)
    else:  # a later run: its own device, commit and command above its rows
        with args.out.open("a") as f:
            f.write("\n" + header(title).replace("# ", "## Run: ", 1) + table)
    seed_scene = {name: p.detach().clone() for name, p in model.gauss_params.items()}
    step = 0
    for k, length in enumerate(rounds):
        if k and args.reset_scene:
            reset_scene(trainer, model, seed_scene)
        for _ in range(length):
            for name in held:  # this iteration only: the scheduler sets the rate again after the step
                for group in trainer.optimizers.optimizers[name].param_groups:
                    group["lr"] = 0.0
            model.update_to_step(step)  # what nerfstudio's callback does: the lens and SH schedules read it
            trainer.train_iteration(step)
            step += 1
        start = time.perf_counter()
        if lens and not args.no_lens_solve:
            solve_lens(model, pipeline.datamanager, range(len(model.camera_optimizer.pose_adjustment)), 2)
        moved = solve_poses(model, pipeline.datamanager, range(len(model.camera_optimizer.pose_adjustment)), 2)
        seconds = time.perf_counter() - start
        e = errors(refined_poses(pipeline).double().numpy(), true_c2w, extent)
        lens_cells = "- | -"
        if lens:
            le = lens_errors(pipeline, truth)
            lens_cells = f"{le['focal_pct']:.3f} | {le['lens_px']:.3f}"
        how = ("" if not lens else (", lens by Adam" if args.no_lens_solve else ", lens solved")) + (
            ", scene reset each round" if args.reset_scene else "")
        line = (f"| {args.cameras}{how} (seed {args.seed}) | {'trained' if args.train_means else 'held'} | {step} | "
                f"{seconds:.0f} | {moved['rotation_deg']:.3f} | {e['rot'][0]:.3f} / {e['rot'][1]:.3f} / "
                f"{e['rot'][2]:.3f} | {e['pos'][1]:.3f} | {e['rpe_rot'][1]:.3f} | {lens_cells} |")
        print(line, flush=True)
        with args.out.open("a") as f:
            f.write(line + "\n")


if __name__ == "__main__":
    main()
