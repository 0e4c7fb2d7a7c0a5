"""Rolling shutter: what modelling it costs a step, and what it buys on a fast-moving capture.

    python -m benchmarks.rolling_shutter step [--gaussians N --size S --runs K]
    python -m benchmarks.rolling_shutter train-step WORK_DIR [--size S --steps N]
    python -m benchmarks.rolling_shutter train WORK_DIR [--steps N --size S --seed K]
    python -m benchmarks.rolling_shutter refine WORK_DIR [--steps N]

`step`: one process, the CPU build, the same Gaussians and pixel grid of a 180-degree fisheye: a render's forward +
backward with one pose (global shutter) against every ray at its own pose (rolling shutter, the synthetic
capture's motion: 8 degrees and 5 cm over the readout; the rays' origins and directions, their tile bounds
and the widened association included), alternated, after a warm-up, median of K. `train-step`: whole nerfstudio training steps of
the synthetic capture below with the shutter model against the same frames as global shutter (the seed points'
Gaussians in both), alternated in one process, median. `train`: the synthetic rolling-shutter room
(geer_ns.data.synthetic_rolling) trained three ways with `ns-train geer` at the same steps and schedule, each
scored by `ns-eval` on the same held-out global-shutter views (the static scene): the rolling-shutter frames with
the shutter model, the same frames as global-shutter images, and the global-shutter frames of the same path.
`refine`: the same capture with every readout motion halved, trained with the shutter model without and with
readout refinement. Each prints a markdown table (benchmarks/rolling_shutter.md).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from pathlib import Path

import torch

from benchmarks.common import header

RUNS = {  # label -> transforms file of the capture
    "rolling-shutter frames, shutter model": "transforms.json",
    "rolling-shutter frames as global shutter": "transforms_as_global.json",
    "global-shutter frames of the same path": "transforms_global.json",
}


def step_cost(gaussians: int, size: int, runs: int) -> list[str]:
    from geer_ns.cameras import EquidistantCamera
    from geer_ns.cameras.shutter import ray_times, rolling_rays
    from geer_ns.data.synthetic_rolling import readout_poses
    from geer_ns.render import RayGrid, render
    from geer_ns.render.moving import MovingRays
    import numpy as np

    torch.manual_seed(0)
    camera = EquidistantCamera(size, size, size / math.pi, size / math.pi, size / 2, size / 2)
    dirs, valid = camera.pixel_rays(torch.float32)
    grid = RayGrid.from_rays(dirs, valid, tile_size=16)
    direction = torch.nn.functional.normalize(torch.randn(gaussians, 3), dim=-1)
    means = direction * (1.0 + 3.0 * torch.rand(gaussians, 1))
    quats = torch.nn.functional.normalize(torch.randn(gaussians, 4), dim=-1)
    scales = 0.01 + 0.05 * torch.rand(gaussians, 3)
    opacities = 0.1 + 0.8 * torch.rand(gaussians)
    colors = torch.rand(gaussians, 16, 3) * 0.3
    start, end = (torch.tensor(p) for p in readout_poses(np.eye(4), 8.0, 0.05, np.random.default_rng(0)))
    times = ray_times(camera, grid.dirs.double(), "top-to-bottom")
    params = [t.requires_grad_(True) for t in (means, quats, scales, opacities, colors)]

    def once(rolling: bool) -> float:
        t0 = time.perf_counter()
        viewmat, motion = torch.eye(4, dtype=torch.float64), None
        if rolling:
            viewmat, origins, rays, offset = rolling_rays(grid.dirs.double(), times, start, end)
            motion = MovingRays(origins.float(), rays.float(), offset)
        out = render(*params, viewmat, grid, backend="cpu", motion=motion)
        out.rgb.sum().backward()
        return time.perf_counter() - t0

    for rolling in (False, True, False, True):  # warm-up: the build, the grid's caches
        once(rolling)
    times_s = {False: [], True: []}
    for _ in range(runs):
        for rolling in (False, True):
            times_s[rolling].append(once(rolling))
    glob, roll = (statistics.median(times_s[k]) for k in (False, True))
    return ["| render | median of {} (s) |".format(runs), "| --- | --- |",
            f"| global shutter | {glob:.4f} |", f"| rolling shutter | {roll:.4f} |",
            f"| ratio | {roll / glob:.3f}x |"]


def train(work: Path, steps: int, size: int, seed: int) -> list[str]:
    from benchmarks.common import run_config, train_and_score
    from geer_ns.data.synthetic_rolling import write_rolling_room

    data = work / f"room_{size}_seed{seed}"
    if not data.exists():
        write_rolling_room(data, size=size, seed=seed)
    rows = ["| training images | PSNR | SSIM | Gaussians | training (s) |", "| --- | --- | --- | --- | --- |"]
    for label, file in RUNS.items():
        record = work / f"{Path(file).stem}_{size}_{steps}_seed{seed}.json"
        if not record.exists():  # one record per run, kept: a rerun reports without retraining
            metrics, seconds, pipeline = train_and_score(run_config(data / file, work, record.stem, steps, seed=seed))
            record.write_text(json.dumps({**metrics, "seconds": seconds, "gaussians": pipeline.model.num_points}))
        r = json.loads(record.read_text())
        rows.append(f"| {label} | {r['psnr']:.3f} | {r['ssim']:.4f} | {r['gaussians']:,} | {r['seconds']:.0f} |")
    return rows


def train_step(work: Path, size: int, steps: int) -> list[str]:
    """nerfstudio training steps (GeerTrainer.train_iteration) on the rolling-shutter frames with the shutter model
    against the same frames as global shutter: the same seed points and images, schedules as written (no
    densification in the first 500 steps, so both keep the seed's Gaussians), alternated in one process."""
    import geer_ns.config  # noqa: F401 - nerfstudio's configs before its writer (the host's import order)
    from benchmarks.common import run_config
    from geer_ns.data.synthetic_rolling import write_rolling_room
    from nerfstudio.utils import writer

    data = work / f"room_{size}_seed0"
    if not data.exists():
        write_rolling_room(data, size=size, seed=0)
    trainers = {}
    for label, file in list(RUNS.items())[:2]:
        config = run_config(data / file, work, f"step_{Path(file).stem}", 10**6)
        config.schedules = "fixed"
        writer.EVENT_WRITERS.clear()
        trainers[label] = config.setup(local_rank=0, world_size=1)
        trainers[label].setup()
    times = {label: [] for label in trainers}
    for step in range(steps):
        for label, trainer in trainers.items():
            t0 = time.perf_counter()
            trainer.train_iteration(step)
            if step >= 5:  # warm-up: the build, the views' caches
                times[label].append(time.perf_counter() - t0)
    rows = [f"| training step ({size}², {steps - 5} steps after 5 of warm-up) | median (s) | Gaussians |",
            "| --- | --- | --- |"]
    for label, trainer in trainers.items():
        rows.append(f"| {label} | {statistics.median(times[label]):.4f} | {trainer.pipeline.model.num_points:,} |")
    ratio = statistics.median(times[list(RUNS)[0]]) / statistics.median(times[list(RUNS)[1]])
    return rows + [f"| ratio | {ratio:.3f}x | |"]


def refine(work: Path, steps: int) -> list[str]:
    """The capture (size 96, seed 0) with each frame's readout motion halved (the end pose at the start's half-way
    point): the shutter model on the wrong motion, without and with --pipeline.model.readout-refinement."""
    import numpy as np
    from scipy.spatial.transform import Rotation, Slerp

    from benchmarks.common import run_config, train_and_score
    from geer_ns.data.synthetic_rolling import write_rolling_room

    data = work / "room_96_seed0"
    if not data.exists():
        write_rolling_room(data, size=96, seed=0)
    meta = json.loads((data / "transforms.json").read_text())
    for frame in meta["frames"]:
        if "transform_matrix_end" in frame:
            a, b = np.array(frame["transform_matrix"]), np.array(frame["transform_matrix_end"])
            half = b.copy()
            half[:3, :3] = Slerp([0, 1], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))([0.5]).as_matrix()[0]
            half[:3, 3] = 0.5 * (a[:3, 3] + b[:3, 3])
            frame["transform_matrix_end"] = half.tolist()
    (data / "transforms_half_motion.json").write_text(json.dumps(meta, indent=2))
    rows = ["| readout motion | PSNR | SSIM | mean readout turn learnt (deg) |", "| --- | --- | --- | --- |"]
    for name, options in (("half_motion", {}), ("half_motion_refined", {"readout_refinement": True})):
        record = work / f"{name}.json"
        if not record.exists():
            metrics, seconds, pipeline = train_and_score(
                run_config(data / "transforms_half_motion.json", work, name, steps, options, seed=0))
            readout = pipeline.model.readout
            turn = None if readout is None else float(readout.adjustments.detach()[:, :3].norm(dim=-1).mean())
            record.write_text(json.dumps({**metrics, "seconds": seconds,
                                          "mean_turn_deg": None if turn is None else math.degrees(turn)}))
        r = json.loads(record.read_text())
        turn = "-" if r.get("mean_turn_deg") is None else f"{r['mean_turn_deg']:.2f}"
        rows.append(f"| halved{', refined' if 'refined' in name else ''} | {r['psnr']:.3f} | {r['ssim']:.4f} | {turn} |")
    return rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="what", required=True)
    s = sub.add_parser("step")
    s.add_argument("--gaussians", type=int, default=50000)
    s.add_argument("--size", type=int, default=128)
    s.add_argument("--runs", type=int, default=9)
    ts = sub.add_parser("train-step")
    ts.add_argument("work", type=Path)
    ts.add_argument("--size", type=int, default=96)
    ts.add_argument("--steps", type=int, default=45)
    rf = sub.add_parser("refine")
    rf.add_argument("work", type=Path)
    rf.add_argument("--steps", type=int, default=2000)
    t = sub.add_parser("train")
    t.add_argument("work", type=Path)
    t.add_argument("--steps", type=int, default=1000)
    t.add_argument("--size", type=int, default=96)
    t.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if a.what == "step":
        rows = step_cost(a.gaussians, a.size, a.runs)
    elif a.what == "train-step":
        rows = train_step(a.work, a.size, a.steps)
    elif a.what == "refine":
        rows = refine(a.work, a.steps)
    else:
        rows = train(a.work, a.steps, a.size, a.seed)
    print(header(f"Rolling shutter: {a.what}"))
    print("\n".join(rows))


if __name__ == "__main__":
    main()
