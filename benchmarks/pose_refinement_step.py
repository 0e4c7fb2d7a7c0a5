"""Training step time with and without camera pose refinement, on the compiled kernels (CPU build or CUDA).

Problem: benchmarks/cpu_training_step.py's (one BEAP view of the dev fisheye room, its 20k seed points as
Gaussians, masked L1 against frame 0, backward, Adam). With refinement the pose is nerfstudio's SO3xR3
CameraOptimizer applied to the frame's camera-to-world (as geer's model does), its 6 parameters in the same
Adam step. Steps of the two cases alternate (one of each per round, after a warm-up round) so that both see
the same machine load; figure: median step time of each and their ratio (on a GPU: wall clock around a
synchronised step). Writes benchmarks/pose_refinement.md (or --out).

    .venv/bin/python benchmarks/pose_refinement_step.py [--size 128] [--rounds 15] [--room DIR]
    python benchmarks/pose_refinement_step.py --device cuda --size 384 --rounds 50 --out $OUT/pose_step_gpu.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


class Trainer:
    """One training setup: the Gaussians, an optional pose optimizer, one Adam over both."""

    def __init__(self, params0: dict, c2w, rays, target, valid, refine_pose: bool, device: str):
        from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig

        self.device = torch.device(device)
        self.backend = "cuda" if self.device.type == "cuda" else "cpu"
        self.params = {k: v.to(device).clone().requires_grad_(True) for k, v in params0.items()}
        self.c2w, self.target, self.valid = c2w.to(device), target.to(device), valid.to(device)
        self.rays = rays.to(device)
        lrs = {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh": 2.5e-3}
        groups = [{"params": [self.params[k]], "lr": lr} for k, lr in lrs.items()]
        self.pose = CameraOptimizerConfig(mode="SO3xR3" if refine_pose else "off").setup(num_cameras=1, device=device)
        if refine_pose:
            groups.append({"params": list(self.pose.parameters()), "lr": 1e-4})
        self.opt = torch.optim.Adam(groups, eps=1e-15)

    def step(self) -> float:
        from nerfstudio.utils import poses as pose_utils

        from geer_ns.render.transforms import world_to_camera_opencv
        from geer_ns.render import render

        if self.device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        c2w = pose_utils.multiply(self.c2w[None], self.pose(torch.tensor([0], device=self.device)))[0]
        viewmat = world_to_camera_opencv(c2w.to(torch.float64))
        p = self.params
        out = render(p["means"], p["quats"], torch.exp(p["scales"]), torch.sigmoid(p["opacities"]), p["sh"], viewmat,
                     self.rays, background=torch.zeros(3, device=self.device), backend=self.backend)
        loss = (out.rgb - self.target).abs()[self.valid].mean()
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        if self.device.type == "cuda":
            torch.cuda.synchronize()
        return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--room", type=Path, default=None, help="the dev fisheye room (default: cpu_training_step's)")
    parser.add_argument("--device", default="cpu", help="cpu (the CPU build) or cuda (the CUDA kernels)")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "pose_refinement.md")
    args = parser.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: no CUDA device here (torch.cuda.is_available() is False); --device cpu times "
                     "the CPU build")
    import cpu_training_step

    if args.room is not None:
        cpu_training_step.ROOM = args.room
    room = cpu_training_step.ROOM

    from geer_ns.render import cuda_backend

    if args.device == "cuda":
        cuda_backend.load_extension()  # built outside the timing
    else:
        cuda_backend.load_cpu_ops()
    params, _viewmat, rays, target, valid = cpu_training_step.dev_room_problem(args.size)
    frame = json.loads((room / "transforms_fisheye.json").read_text())["frames"][0]
    c2w = torch.tensor(frame["transform_matrix"], dtype=torch.float32)[:3]
    trainers = {case: Trainer(params, c2w, rays, target, valid, case == "pose", args.device) for case in ("fixed", "pose")}
    times = {case: [] for case in trainers}
    for r in range(args.rounds + 1):
        for case, trainer in trainers.items():
            seconds = trainer.step()
            if r:
                times[case].append(seconds)
    med = {case: statistics.median(t) for case, t in times.items()}
    commit = os.environ.get("GEER_COMMIT") or subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    with open("/proc/loadavg") as f:
        load = f.read().split()[0]
    n = params["means"].shape[0]
    if args.device == "cuda":
        where, device = "CUDA kernels", f"{torch.cuda.get_device_name()}, wall clock around synchronised steps"
    else:
        where, device = "CPU build", (f"CPU, {platform.machine()}, {torch.get_num_threads()} torch threads, shared "
                                      f"with other jobs (load average {load} when written: absolute times are "
                                      "inflated and noisy; the ratio compares the two cases within one run, their "
                                      "steps alternating)")
    report = f"""# Pose refinement: training step time on the {where}

- device: {device}
- torch {torch.__version__}; commit {commit.strip()}
- command: `python benchmarks/pose_refinement_step.py --device {args.device} --size {args.size} --rounds {args.rounds} --room {room}`
- problem: one {args.size}x{args.size} BEAP view of the dev fisheye room, {n} Gaussians (SH degree 0),
  render + masked L1 + backward + Adam; "pose": nerfstudio's SO3xR3 camera optimizer on the view's pose, its
  gradient from the compiled backend (before: the PyTorch renderer, 1.89 s against 0.061 s a step)
- median of {args.rounds} steps each after a warm-up round

| case | ms per training step | ratio to fixed pose |
| --- | ---: | ---: |
| fixed pose | {1e3 * med['fixed']:.2f} | 1.00x |
| pose refinement (SO3xR3) | {1e3 * med['pose']:.2f} | {med['pose'] / med['fixed']:.2f}x |
"""
    args.out.write_text(report)
    print(report)


if __name__ == "__main__":
    main()
