"""Pose refinement against a frozen scene: can the pose gradient alone bring perturbed cameras back to the truth?

Train geer on the dev room's true cameras (--size^2, --steps, nerfstudio's loop, the pose optimizer present at
learning rate 0 so its adjustments exist and stay zero), freeze every Gaussian, set every training camera's
SO3xR3 adjustment to a turn of --rotation degrees about a random axis and a move of --position of the scene's
extent, then refine the adjustments alone with Adam for --refine-steps steps on the training loss, one image a
step as training draws them. The truth is the zero adjustment, so the errors are the adjustments' own sizes.
Separates what the gradient can do from what the joint problem (a scene that learns each view's pose error)
allows. Writes benchmarks/pose_frozen_scene.md (+ .json).

    python benchmarks/pose_frozen_scene.py [--size 128] [--steps 2000] [--refine-steps 2000] [--lr 5e-4]
    python benchmarks/pose_frozen_scene.py --solver lm [--iterations 2] [--blur-levels 4,2,1,0 2,1,0]
        # the Levenberg-Marquardt solve instead, one pass per blur schedule, each from the same perturbation
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import torch

from refinement_runs import ROOT, dump, git_commit, load_average, small_dev_room, train_and_score


def adjustment_errors(adjustment: torch.Tensor, extent: float) -> dict:
    """Mean / max rotation (degrees) and position (% of extent) of SO3xR3 adjustments [N, 6] (translation first)."""
    rot = torch.rad2deg(adjustment[:, 3:].detach().double().norm(dim=-1))
    pos = 100.0 * adjustment[:, :3].detach().double().norm(dim=-1) / extent
    return {"rotation_deg_mean": float(rot.mean()), "rotation_deg_median": float(rot.median()),
            "rotation_deg_max": float(rot.max()),
            "position_pct_mean": float(pos.mean()), "position_pct_max": float(pos.max())}


def perturb(model, rotation_deg: float, position_fraction: float, extent: float, seed: int = 0) -> torch.Tensor:
    """Freeze the model and set every training camera's adjustment to the perturbation; the adjustments."""
    model.train()
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    adjustment = model.camera_optimizer.pose_adjustment
    rng = np.random.default_rng(seed)
    axes, moves = rng.normal(size=(len(adjustment), 3)), rng.normal(size=(len(adjustment), 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    moves /= np.linalg.norm(moves, axis=1, keepdims=True)
    with torch.no_grad():
        adjustment[:, 3:] = torch.from_numpy(axes * math.radians(rotation_deg)).to(adjustment)
        adjustment[:, :3] = torch.from_numpy(moves * position_fraction * extent).to(adjustment)
    return adjustment


def refine_poses(pipeline, rotation_deg: float, position_fraction: float, extent: float, steps: int, lr: float,
                 lr_final: float, seed: int = 0, log_every: int = 100) -> list:
    """Perturb the pose adjustments, refine them alone by Adam against the frozen scene; the error history."""
    model, data = pipeline.model, pipeline.datamanager
    adjustment = perturb(model, rotation_deg, position_fraction, extent, seed)
    adjustment.requires_grad_(True)
    optimizer = torch.optim.Adam([adjustment], lr=lr, eps=1e-15)
    decay = (lr_final / lr) ** (1.0 / max(steps, 1))
    history = [{"step": 0, **adjustment_errors(adjustment, extent)}]
    losses = []
    for step in range(1, steps + 1):
        camera, batch = data.next_train(step)
        outputs = model.get_outputs(camera)
        loss = model.get_image_loss_dict(outputs, batch)["main_loss"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        for group in optimizer.param_groups:
            group["lr"] *= decay
        model.views.clear()
        losses.append(float(loss.detach()))
        if step % log_every == 0 or step == steps:
            history.append({"step": step, "loss": float(np.mean(losses[-log_every:])),
                            **adjustment_errors(adjustment, extent)})
            print(json.dumps(history[-1]), flush=True)
    return history


def main() -> None:
    import argparse
    import shlex
    import sys
    from pathlib import Path

    from nerfstudio.engine.optimizers import AdamOptimizerConfig

    from benchmarks.camera_perturbation import scene_extent

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--steps", type=int, default=2000, help="training steps on the true cameras")
    parser.add_argument("--refine-steps", type=int, default=2000)
    parser.add_argument("--lr", type=float, default=5e-4)
    parser.add_argument("--lr-final", type=float, default=1e-5)
    parser.add_argument("--rotation", type=float, default=1.0, help="degrees")
    parser.add_argument("--position", type=float, default=0.01, help="fraction of the scene's extent")
    parser.add_argument("--solver", choices=("adam", "lm"), default="adam",
                        help="adam: the camera optimizer's steps; lm: one pass of geer_ns/refinement/pose_solve.py")
    parser.add_argument("--iterations", type=int, default=2, help="--solver lm: iterations per blur level")
    parser.add_argument("--blur-levels", nargs="+", default=["4,2,1,0"],
                        help="--solver lm: blur schedules (pixels, coarse to fine, comma-separated), one pass each")
    parser.add_argument("--work", type=Path, default=Path("/tmp/geer_frozen"))
    parser.add_argument("--suffix", default="")
    args = parser.parse_args()
    command = shlex.join(["python", "benchmarks/pose_frozen_scene.py", *sys.argv[1:]])

    transforms = small_dev_room(args.work, args.size)
    schedule = {"warmup_length": 300, "refine_every": 100, "stop_split_at": 1000, "num_downscales": 0,
                "camera_optimizer.mode": "SO3xR3"}
    frozen = {"camera_opt": {"optimizer": AdamOptimizerConfig(lr=0.0, eps=1e-15), "scheduler": None}}
    metrics, seconds, pipeline = train_and_score("true_cameras", transforms, args.steps, schedule, args.work, frozen)
    outputs = pipeline.datamanager.train_dataparser_outputs
    extent = scene_extent(transforms.parent, json.loads(transforms.read_text())) * float(outputs.dataparser_scale)
    if args.solver == "lm":
        from geer_ns.refinement.pose_solve import solve_poses

        history = []
        for schedule_text in args.blur_levels:
            levels = tuple(float(b) for b in schedule_text.split(","))
            adjustment = perturb(pipeline.model, args.rotation, args.position, extent)
            if not history:
                history.append({"step": 0, **adjustment_errors(adjustment, extent)})
            start = time.perf_counter()
            summary = solve_poses(pipeline.model, pipeline.datamanager, range(len(adjustment)), args.iterations,
                                  levels)
            rotation = torch.rad2deg(adjustment[:, 3:].detach().double().norm(dim=-1))
            history.append({"step": f"solved, blur {schedule_text} px", "loss": summary["residual_change"],
                            "seconds": time.perf_counter() - start,
                            "rotation_deg_per_camera": [round(float(r), 4) for r in rotation],
                            **adjustment_errors(adjustment, extent)})
            print(json.dumps(history[-1]), flush=True)
    else:
        history = refine_poses(pipeline, args.rotation, args.position, extent, args.refine_steps, args.lr,
                               args.lr_final)
    record = {"commit": git_commit(), "command": command, "scene_psnr": metrics["psnr"], "history": history}
    dump(ROOT / "benchmarks" / f"pose_frozen_scene{args.suffix}.json", record)
    rows = "\n".join(f"| {h['step']} | {h.get('loss', float('nan')):.4f} | {h['rotation_deg_mean']:.4f} / "
                     f"{h['rotation_deg_median']:.4f} / {h['rotation_deg_max']:.4f} | "
                     f"{h['position_pct_mean']:.4f} / {h['position_pct_max']:.4f} | "
                     f"{h.get('seconds', float('nan')):.0f} |" for h in history)
    method = (f"one pass of the Levenberg-Marquardt pose solve per blur schedule, {args.iterations} iterations per "
              "blur level, each from the same perturbation)" if args.solver == "lm" else
              f"Adam lr {args.lr:g} decaying to {args.lr_final:g} over {args.refine_steps} steps, one training image a "
              "step")
    (ROOT / "benchmarks" / f"pose_frozen_scene{args.suffix}.md").write_text(f"""# Pose refinement against a frozen scene

- scene: geer trained {args.steps} steps on the dev room's true cameras at {args.size}^2 (test PSNR
  {metrics['psnr']:.2f}), then frozen
- perturbation: every training camera's SO3xR3 adjustment set to {args.rotation:g} degree about a random axis and
  {100 * args.position:g} % of the extent (seed 0); refined alone: {method}
- device: CPU, 2 cores (load average {load_average()}); commit {record['commit']}
- command: `{command}`

| step | loss: Adam's mean of the last 100 / the solve's relative change of the squared residuals | rotation deg (mean / median / max) | position % (mean / max) | seconds |
| ---: | ---: | ---: | ---: | ---: |
{rows}
""")


if __name__ == "__main__":
    main()
