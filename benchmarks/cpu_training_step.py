"""Training step time on the CPU, PyTorch twin vs the CPU build, on the dev fisheye room: one BEAP view at
--size^2 (the camera's whole BEAP range), the room's 20k seed points as Gaussians (kNN scales, opacity 0.1,
SH degree 0 from the point colours), masked L1 loss against frame 0 resampled to BEAP, backward, Adam step.
Both backends train the same parameters from the same start in one process; figure: median step time.

    .venv/bin/python benchmarks/cpu_training_step.py [--size 256] [--steps 8]   # prints one markdown row each
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
ROOM = ROOT.parent / "shared" / "data" / "fisheye_room_dev"
SH_C0 = 0.28209479177387814


def dev_room_problem(size: int):
    from bench_gpu import _knn_rms

    from geer_ns.cameras import EquidistantCamera
    from geer_ns.data.beap import BeapGrid, resample_to_beap
    from geer_ns.data.views import full_beap_grid
    from geer_ns.data.ply import read_ply_points
    from geer_ns.render.transforms import world_to_camera_opencv
    from geer_ns.render import RayGrid

    meta = json.loads((ROOM / "transforms_fisheye.json").read_text())
    camera = EquidistantCamera(meta["w"], meta["h"], meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"])
    full = full_beap_grid(camera)
    grid = BeapGrid(size, size, full.theta_min, full.theta_max, full.phi_min, full.phi_max)
    frame = meta["frames"][0]
    image = cv2.cvtColor(cv2.imread(str(ROOM / frame["file_path"])), cv2.COLOR_BGR2RGB)
    mask = cv2.imread(str(ROOM / frame["mask_path"]), cv2.IMREAD_GRAYSCALE) > 0
    target, valid = resample_to_beap(image, camera, grid, mask)
    rays = RayGrid.from_rays(grid.directions(torch.float32), None, tile_size=16)
    xyz, rgb = read_ply_points(ROOM / meta["ply_file_path"])
    n = xyz.shape[0]
    params = {
        "means": torch.from_numpy(xyz),
        "scales": torch.from_numpy(np.log(_knn_rms(xyz.astype(np.float64), 3))).float()[:, None].repeat(1, 3),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        "opacities": torch.logit(torch.full((n,), 0.1)),
        "sh": ((torch.from_numpy(rgb).float() / 255.0 - 0.5) / SH_C0)[:, None, :],
    }
    c2w = torch.tensor(frame["transform_matrix"], dtype=torch.float32)[:3]
    return params, world_to_camera_opencv(c2w), rays, target, valid


def time_steps(backend: str, params0: dict, viewmat, rays, target, valid, steps: int) -> tuple[float, float]:
    """(median seconds per step, final loss) of `steps` Adam steps after one warm-up step."""
    from geer_ns.render import render

    params = {k: v.clone().requires_grad_(True) for k, v in params0.items()}
    lrs = {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh": 2.5e-3}
    opt = torch.optim.Adam([{"params": [params[k]], "lr": lr} for k, lr in lrs.items()], eps=1e-15)
    bg = torch.zeros(3)
    times, loss = [], None
    for step in range(steps + 1):
        t0 = time.perf_counter()
        out = render(params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
                     params["sh"], viewmat, rays, background=bg, backend=backend)
        loss = (out.rgb - target).abs()[valid].mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step:
            times.append(time.perf_counter() - t0)
    return statistics.median(times), float(loss)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--steps", type=int, default=8)
    args = parser.parse_args()
    from geer_ns.render.cuda_backend import load_cpu_ops

    load_cpu_ops()  # built outside the timing
    problem = dev_room_problem(args.size)
    n = problem[0]["means"].shape[0]
    results = {b: time_steps(b, *problem, args.steps) for b in ("torch", "cpu")}
    for b, (sec, loss) in results.items():
        print(f"| dev fisheye room, {args.size}x{args.size} BEAP, {n} Gaussians | {b} | {sec:.3f} | "
              f"{results['torch'][0] / sec:.1f}x | {loss:.4f} |")


if __name__ == "__main__":
    main()
