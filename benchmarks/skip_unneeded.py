"""What skipping what a scene does not need saves, and what it costs: per-Gaussian SH degrees, Adam on the rows a
step's views see, the view cull. Writes benchmarks/skip_unneeded.md (device, commit, command).

    python -m benchmarks.skip_unneeded [--steps 1000] [--seeds 42] [--only PREFIX ...] [--threads 1]

1. The dev room at 128^2, fisheye and pinhole, each run in its own process (nerfstudio's loop) on the defaults'
   schedule scaled down: refinement every 100 steps from step 200, splits until 600, the SH degree up every 150
   steps (3 from step 450; the degrees are chosen at the last step). VARIANTS against every band at the same Adam
   rows; held-out views at the last step; bytes per Gaussian of the final checkpoint and of geer-export's PLY and
   SPZ. On the first seed's every-band runs, degrees applied to their final Gaussians without training after
   (every Gaussian at one degree, its bands cut off and refit; the choice at several budgets). Runs and sweeps in
   --work are kept.
2. The colour stage: the CPU build's preprocess forward + backward (SH evaluated there), every band against each
   Gaussian's own degree, alternated, median.
3. A training step at 1M Gaussians, each view seeing a few percent (a corridor, pinhole views of its walls):
   STEP_SETTINGS in turn on one trainer in one process, after a warm-up round, median.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from benchmarks.common import commit as git_commit
from benchmarks.common import dev_room, run_config, short_schedule, train_and_score


def small_dev_room(work: Path, size: int) -> Path:
    """The dev room at size^2, its fisheye transforms file."""
    return dev_room(work, size) / "transforms_fisheye.json"


def trainer_config(name: str, data: Path, steps: int, overrides: dict, out: Path, **options):
    return run_config(data, out / "runs", name, steps, overrides, **options)


def load_average() -> str:
    return f"{os.getloadavg()[0]:.1f}"

ROOT = Path(__file__).resolve().parents[1]
REPORT = ROOT / "benchmarks" / "skip_unneeded.md"
SIZE = 128
SCHEDULE = {**short_schedule(600), "warmup_length": 200, "sh_degree_interval": 150}
ALL, SEEN = {"optimizer_rows": "all"}, {"optimizer_rows": "visible"}
VARIANTS = {  # name -> model options; "own degrees" at the default budget unless named
    "every band, Adam on every row": {"sh_per_gaussian": False, **ALL},
    "own degrees, Adam on every row": ALL, "own degrees 0.5 dB, Adam on every row": {"sh_budget_db": 0.5, **ALL},
    "own degrees 1 dB, Adam on every row": {"sh_budget_db": 1.0, **ALL},
    "every band, Adam on seen rows": {"sh_per_gaussian": False, **SEEN}, "own degrees, Adam on seen rows": SEEN,
    "own degrees 0.2 dB, Adam on seen rows": {"sh_budget_db": 0.2, **SEEN},
    "own degrees 2 dB, Adam on seen rows": {"sh_budget_db": 2.0, **SEEN}}
FILES = ("checkpoint", "ply", "spz")
STEP_SETTINGS = {  # the step benchmark's contenders: model options
    "today (view-cull False, optimizer-rows all)": {"view_cull": False, **ALL},
    "Adam on the seen rows only (view-cull False, optimizer-rows visible)": {"view_cull": False, **SEEN},
    "view cull: the defaults (view-cull True, optimizer-rows all)": {"view_cull": True, **ALL},
    "view cull and Adam on the seen rows (optimizer-rows visible)": {"view_cull": True, **SEEN}}


def _parts(name: str, work: Path):
    """(camera, variant, seed, transforms file, folder name) of the run `name`: "camera variant seed N"."""
    camera, rest = name.split(" ", 1)
    variant, seed = rest.rsplit(" seed ", 1)
    return camera, variant, int(seed), small_dev_room(work, SIZE).with_name(f"transforms_{camera}.json"), \
        name.replace(" ", "_")


def one_run(name: str, work: Path, steps: int) -> dict:
    """Train and score the run `name` ("camera variant seed N"), write its PLY and SPZ; returns its record."""
    import numpy as np

    from geer_ns.export.cli import splats_of
    from geer_ns.export.formats import write_ply, write_spz

    camera, variant, seed, data, tag = _parts(name, work)
    metrics, seconds, pipeline = train_and_score(trainer_config(tag, data, steps, {**SCHEDULE, **VARIANTS[variant]},
                                                                work, seed=seed))
    model = pipeline.model
    checkpoint = max((work / "runs" / tag).rglob("step-*.ckpt"))
    files = work / "files" / tag
    files.mkdir(parents=True, exist_ok=True)
    splats = splats_of(model)
    write_ply(splats, files / "splat.ply", {})
    write_spz(splats, files / "splat.spz", {})
    degrees = model.strategy_state.get("sh_degree")
    torch.save({"params": {k: p.detach() for k, p in model.gauss_params.items()}, "sh_degree": degrees},
               files / "gaussians.pt")
    return {"name": name, "camera": camera, "variant": variant, "seed": seed, "steps": steps,
            "gaussians": model.num_points, "seconds": seconds, "psnr": metrics["psnr"], "ssim": metrics["ssim"],
            "checkpoint": checkpoint.stat().st_size, "ply": (files / "splat.ply").stat().st_size,
            "spz": (files / "splat.spz").stat().st_size, "stored_degree": splats.sh_degree, "commit": git_commit(),
            "degree_counts": None if degrees is None else np.bincount(degrees.cpu().numpy(), minlength=4).tolist()}


def degree_sweep(name: str, work: Path, budgets=(0.02, 0.1, 0.2, 0.5)) -> list:
    """Degrees applied to the final Gaussians of the every-band run `name` (loaded, one step), no training after:
    every Gaussian at one degree, its bands cut off and refit (geer_ns/sh_degrees/refit.py), and the choice at each
    budget (refit). Rows: (rule, highest degree, Gaussians per degree, training views' loss in dB, test PSNR
    change in dB)."""
    from geer_ns.sh_degrees.choice import band_errors, choose, set_degrees
    from geer_ns.sh_degrees.packing import DEGREES

    _, variant, seed, data, tag = _parts(name, work)
    base, _, pipeline = train_and_score(trainer_config(
        f"{tag}_sweep", data, 1, {**SCHEDULE, **VARIANTS[variant]}, work, seed=seed,
        load_dir=work / "runs" / tag / "geer" / "run" / "nerfstudio_models"))
    model = pipeline.model
    rest, dc = model.gauss_params["features_rest"], model.gauss_params["features_dc"]
    dense_rest, dense_dc = rest.detach().clone(), dc.detach().clone()

    def applied(degrees, fits=None):
        rest.data.copy_(dense_rest)
        dc.data.copy_(dense_dc)
        model.strategy_state.pop(DEGREES, None)
        if degrees is not None:
            set_degrees(model, degrees, fits)

    def test_change(degrees, fits=None) -> float:
        applied(degrees, fits)
        psnr = pipeline.get_average_eval_image_metrics(step=model.step)["psnr"]
        pipeline.train()
        return psnr - base["psnr"]

    fits = band_errors(model, pipeline).fits
    rows = []
    for d in range(3):
        degrees = torch.full((model.num_points,), d, dtype=torch.uint8)
        counts = [model.num_points if k == d else 0 for k in range(4)]
        rows.append((f"every Gaussian at {d}, cut off", d, counts, None, test_change(degrees)))
        rows.append((f"every Gaussian at {d}, refit", d, counts, None, test_change(degrees, fits)))
    for budget in budgets:
        applied(None)
        choice = choose(model, pipeline, budget)
        rows.append((f"the choice, budget {budget} dB", choice.cap,
                     torch.bincount(choice.degrees.long(), minlength=4).tolist(), choice.loss_db,
                     test_change(choice.degrees, choice.fits)))
    return rows


def colour_stage(gaussians: Path, repeats: int = 40) -> dict:
    """Median seconds of the CPU build's preprocess forward + backward, every band and each Gaussian's own degree
    (alternated), on the saved Gaussians seen from 3 units behind the origin."""
    from geer_ns.render.cuda_backend import load_cpu_ops

    ops, saved = load_cpu_ops(), torch.load(gaussians)
    g, degrees = saved["params"], saved["sh_degree"]
    n = g["means"].shape[0]
    means_c = (g["means"] + torch.tensor([0.0, 0.0, 3.0])).contiguous()
    sh = torch.cat([g["features_dc"][:, None], g["features_rest"]], 1).contiguous()
    quats, scales = g["quats"].contiguous(), torch.exp(g["scales"]).contiguous()
    opac, dirs, rot = torch.sigmoid(g["opacities"]).reshape(-1).contiguous(), g["means"].contiguous(), torch.eye(3)
    grads = torch.zeros(n, 3, 3), torch.zeros(n, 3), torch.ones(n, 3)

    def once(own):
        start = time.perf_counter()
        ops.preprocess_forward(means_c, quats, scales, opac, sh, dirs, rot, 3, False, own)
        ops.preprocess_backward(means_c, quats, scales, sh, dirs, rot, 3, *grads, False, own)
        return time.perf_counter() - start

    once(None), once(degrees)
    times = {"every band": [], "own degree": []}
    for _ in range(repeats):
        times["every band"].append(once(None))
        times["own degree"].append(once(degrees))
    kept = ((degrees.long() + 1) ** 2).sum().item() / (16 * n)
    return {"gaussians": n, "coefficients": kept, **{k: statistics.median(v) for k, v in times.items()}}


def corridor(work: Path, n: int, cameras: int = 20, length: float = 8.0) -> Path:
    """A corridor x in [0, length] with walls at y, z = +-1, n seed points on them, `cameras` 90-degree pinhole
    views of a side wall each (alternating sides), noise images: every view sees a few percent of the points."""
    import cv2
    import numpy as np
    from plyfile import PlyData, PlyElement

    out = work / f"corridor_{n}"
    if (out / "transforms.json").is_file():
        return out
    (out / "images").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    wall, along, across = rng.integers(0, 4, n), rng.uniform(0, length, n), rng.uniform(-1, 1, n)
    vertex = np.empty(n, dtype=[(c, "f4") for c in "xyz"] + [(c, "u1") for c in ("red", "green", "blue")])
    vertex["x"] = along
    vertex["y"] = np.where(wall == 0, 1.0, np.where(wall == 1, -1.0, across))
    vertex["z"] = np.where(wall == 2, 1.0, np.where(wall == 3, -1.0, across))
    for c in ("red", "green", "blue"):
        vertex[c] = rng.integers(0, 256, n)
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(out / "points.ply"))
    frames = []
    for i in range(cameras):
        forward, up = np.array([0.0, 1.0 if i % 2 == 0 else -1.0, 0.0]), np.array([0.0, 0.0, 1.0])
        c2w = np.eye(4)  # nerfstudio's camera axes: x right, y up, looking along -z
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = np.cross(forward, up), up, -forward, [
            length * (i + 0.5) / cameras, 0.0, 0.0]
        cv2.imwrite(str(out / f"images/{i:03d}.png"), rng.integers(0, 256, (SIZE, SIZE, 3)).astype(np.uint8))
        frames.append({"file_path": f"images/{i:03d}.png", "transform_matrix": c2w.tolist()})
    (out / "transforms.json").write_text(json.dumps({
        "camera_model": "OPENCV", "fl_x": SIZE / 2, "fl_y": SIZE / 2, "cx": SIZE / 2, "cy": SIZE / 2, "w": SIZE,
        "h": SIZE, "frames": frames, "ply_file_path": "points.ply"}))
    return out


def step_times(work: Path, n: int, steps: int) -> dict:
    """Seconds of trainer.train_iteration (nerfstudio's callbacks around it) at each of STEP_SETTINGS, in turn on
    one trainer (the options are read at every step), after a warm-up round; the medians, and the fraction of the
    Gaussians a step's views saw."""
    from nerfstudio.engine.callbacks import TrainingCallbackLocation as At
    from nerfstudio.utils import writer

    config = trainer_config("step", corridor(work, n), 10**6, {
        "num_downscales": 0, "sh_degree_interval": 1, "warmup_length": 10**6}, work)  # SH degree 3 from step 3
    config.steps_per_eval_image = config.steps_per_eval_batch = config.steps_per_eval_all_images = 10**9
    writer.EVENT_WRITERS.clear()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    times, seen, i = {name: [] for name in STEP_SETTINGS}, [], 0
    for round_ in range(steps + 1):  # round 0: warm-up (and the SH degree rising to 3)
        for name, options in STEP_SETTINGS.items():
            for key, value in options.items():
                setattr(model.config, key, value)
            start = time.perf_counter()
            for callback in trainer.callbacks:
                callback.run_callback_at_location(i, location=At.BEFORE_TRAIN_ITERATION)
            trainer.train_iteration(i)
            seen.append(float(model.step_rows().float().mean()))
            for callback in trainer.callbacks:
                callback.run_callback_at_location(i, location=At.AFTER_TRAIN_ITERATION)
            if round_:
                times[name].append(time.perf_counter() - start)
            i += 1
    return {"gaussians": model.num_points, "steps": steps, "seen": statistics.mean(seen), "all": times,
            "median": {name: statistics.median(t) for name, t in times.items()}}


def report(records: list, sweeps: list, colour: dict | None, step: dict | None, command: str) -> str:
    lines = ["# Skipping what a scene does not need: per-Gaussian SH degrees, Adam on the seen rows, view cull", "",
             f"- device: CPU ({platform.processor() or platform.machine()}, {_cpu_model()}), 2 cores shared with "
             f"other jobs (load average {load_average()} when written), the CPU build", f"- commit: {git_commit()}",
             f"- command: `{command}`",
             f"- dev room at {SIZE}^2, {SCHEDULE}; held-out views (every 8th), native pixels, at the last step", "",
             "## Dev room: quality and bytes per Gaussian", "",
             "| camera | variant | seed | Gaussians | PSNR | SSIM | checkpoint, PLY, SPZ B/G | at degree 0/1/2/3 | "
             "vs every band (own degrees: same Adam rows): checkpoint, PLY, SPZ smaller | PSNR, SSIM - every band |",
             "|" + " --- |" * 10]
    by_name = {r["name"]: r for r in records}
    for r in sorted(records, key=lambda r: (r["camera"], list(VARIANTS).index(r["variant"]), r["seed"])):
        rows = "Adam on every row" if r["variant"].startswith("every band") else r["variant"].split(", ")[1]
        ref = by_name.get(f"{r['camera']} every band, {rows} seed {r['seed']}")
        counts = r["degree_counts"]
        lines.append(f"| {r['camera']} | {r['variant']} | {r['seed']} | {r['gaussians']:,} | {r['psnr']:.3f} | "
                     f"{r['ssim']:.4f} | " + ", ".join(f"{r[k] / r['gaussians']:.0f}" for k in FILES) + " | " +
                     ("-" if not counts else "/".join(f"{100 * c / sum(counts):.0f}" for c in counts) + " %") +
                     " | " + ("- | -" if ref is None or ref is r else ", ".join(f"{ref[k] / r[k]:.2f}x" for k in FILES)
                              + f" | {r['psnr'] - ref['psnr']:+.3f}, {r['ssim'] - ref['ssim']:+.4f}") + " |")
    if sweeps:
        lines += ["", "What each choice would cost: degrees applied to an every-band run's final Gaussians, no "
                  "training after (PLY and SPZ store the highest degree for all: a PLY vertex holds "
                  "17 + 3((d + 1)^2 - 1) floats)",
                  "", "| run | degrees | highest | Gaussians at 0/1/2/3 | SH coefficients kept | PLY ratio | "
                  "training views (dB) | test PSNR (dB) |", "|" + " --- |" * 8]
        for sweep in sweeps:
            for rule, top, counts, train, test in sweep["rows"]:
                kept = sum(c * (d + 1) ** 2 for d, c in enumerate(counts)) / (16 * sum(counts))
                lines.append(f"| {sweep['name']} | {rule} | {top} | " + "/".join(
                    f"{100 * c / sum(counts):.0f}" for c in counts) + f" % | {100 * kept:.0f} % | "
                    f"{62 / (17 + 3 * ((top + 1) ** 2 - 1)):.2f}x | {'-' if train is None else f'{train:+.3f}'} | "
                    f"{test:+.3f} |")
    if colour:
        lines += ["", "## The colour stage", "", f"The CPU build's preprocess forward + backward (SH evaluated and "
                  f"differentiated there) on the {colour['gaussians']:,} final Gaussians of `{colour['run']}`, the "
                  f"two alternated, median of 40 calls each, {colour['threads']} torch thread(s): every band "
                  f"{1e3 * colour['every band']:.2f} ms, each Gaussian's own degree "
                  f"{1e3 * colour['own degree']:.2f} ms "
                  f"({colour['own degree'] / colour['every band']:.2f}x); SH coefficients read: "
                  f"{100 * colour['coefficients']:.0f} % of every band's."]
    if step:
        today = step["median"][next(iter(STEP_SETTINGS))]
        lines += ["", f"## A training step at {step['gaussians']:,} Gaussians", "",
                  f"A corridor, 20 pinhole views (90 degrees, {SIZE}^2) of its walls; a step's view saw "
                  f"{100 * step['seen']:.1f} % of the Gaussians. One process, one trainer, the settings in turn, "
                  f"{step['steps']} steps each after a warm-up round, median (SH degree 3); {step['threads']} torch "
                  "thread(s).", "", "| step | s per step (median) | all steps (s) | x today |",
                  "| --- | ---: | --- | ---: |"]
        for name, median in step["median"].items():
            lines.append(f"| {name} | {median:.3f} | {', '.join(f'{t:.2f}' for t in step['all'][name])} | "
                         f"{median / today:.3f} |")
    return "\n".join(lines) + "\n"


def _cpu_model() -> str:
    info = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    return next((l.split(":", 1)[1].strip() for l in info.splitlines() if l.startswith("model name")), "unknown")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[42])
    parser.add_argument("--only", nargs="*", help="run name prefixes to make (default: all; none: --only alone)")
    parser.add_argument("--work", type=Path, default=Path("/tmp/geer_skip_unneeded"))
    parser.add_argument("--step-gaussians", type=int, default=1_000_000)
    parser.add_argument("--step-steps", type=int, default=4, help="timed steps of each setting (0: none)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of every part")
    parser.add_argument("--part", nargs=2, help=argparse.SUPPRESS)  # (run | sweep, name): in its own process
    args = parser.parse_args()
    torch.set_num_threads(args.threads)  # 1: a core each on a shared machine (no thread of a pair waits on the other)
    dirs = {"run": args.work / "records", "sweep": args.work / "sweeps"}
    for folder in dirs.values():
        folder.mkdir(parents=True, exist_ok=True)
    if args.part:
        part, name = args.part
        result = one_run(name, args.work, args.steps) if part == "run" else {"name": name,
                                                                              "rows": degree_sweep(name, args.work)}
        (dirs[part] / f"{name.replace(' ', '_')}.json").write_text(json.dumps(result))
        return
    names = [f"{c} {v} seed {s}" for s in args.seeds for c in ("fisheye", "pinhole") for v in VARIANTS]
    chosen = [n for n in names if args.only is None or any(n.startswith(o) for o in args.only)]
    sweeps = [n for n in chosen if "every band, Adam on every row" in n and n.endswith(f" seed {args.seeds[0]}")]
    for part, name in [("run", n) for n in chosen] + [("sweep", n) for n in sweeps]:
        if not (dirs[part] / f"{name.replace(' ', '_')}.json").is_file():
            print(f"[skip_unneeded] {part} {name}", flush=True)
            subprocess.run([sys.executable, "-m", "benchmarks.skip_unneeded", "--part", part, name, "--steps",
                            str(args.steps), "--work", str(args.work), "--threads", str(args.threads)],
                           check=True, cwd=ROOT)
    step_file = args.work / f"step_{args.step_gaussians}.json"
    if args.step_steps:
        step_file.write_text(json.dumps({**step_times(args.work, args.step_gaussians, args.step_steps),
                                         "threads": torch.get_num_threads()}))
    records, sweeps = ([json.loads(p.read_text()) for p in sorted(dirs[part].glob("*.json"))] for part in dirs)
    source = sorted((r["variant"] != "own degrees, Adam on every row", r["name"]) for r in records
                    if r["degree_counts"])[:1]
    colour = [{**colour_stage(args.work / "files" / name.replace(" ", "_") / "gaussians.pt"), "run": name,
               "threads": args.threads} for _, name in source]
    step = json.loads(step_file.read_text()) if step_file.is_file() else None
    command = shlex.join(["python", "-m", "benchmarks.skip_unneeded", *sys.argv[1:]])
    REPORT.write_text(report(records, sweeps, colour[0] if colour else None, step, command))
    print(REPORT.read_text())


if __name__ == "__main__":
    main()
