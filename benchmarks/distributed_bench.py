"""Training on several CPU processes (gloo): time per step, images per second, the collectives' share of the
step, bytes exchanged and peak memory per process, for 1 and 2 processes, image-parallel and Gaussian-parallel.

Every run is a fresh process (its peak memory is its own) training the embedded synthetic room at its full
96 x 96 BEAP resolution with a fixed number of Gaussians (the seed cloud jittered to --gaussians and
--sharded-gaussians points; no densification, so every step costs the same): nerfstudio's launcher (what
`ns-train --machine.num-devices N` runs) for 2 processes, the training loop itself for 1. Timed: each step's
wall time after --warmup steps (median), the time inside the collectives (gradient and statistics all-reduce;
the all-to-all exchanges), the payload bytes. One run, one machine; writes benchmarks/distributed.md.

    .venv/bin/python benchmarks/distributed_bench.py [--steps 24] [--gaussians 100000] [--sharded-gaussians 1000000]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


# ----------------------------------------------------------------------------------------- the scene
def scene(root: Path, n: int) -> Path:
    """The embedded room with its seed cloud jittered to n points (a fixed count of Gaussians)."""
    import numpy as np
    from plyfile import PlyData, PlyElement

    from geer_ns.data.synthetic_room import default_scene_dir
    from geer_ns.data.ply import read_ply_points

    out = root / f"room_{n}"
    if (out / "transforms.json").is_file():
        return out
    src = default_scene_dir()
    shutil.copytree(src, out)
    meta = json.loads((src / "transforms.json").read_text())
    xyz, rgb = read_ply_points(src / meta["ply_file_path"])
    rng = np.random.default_rng(0)
    pick = rng.integers(0, xyz.shape[0], n)
    points = xyz[pick] + rng.normal(scale=0.01, size=(n, 3)).astype(np.float32)
    vertex = np.empty(n, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = points.T
    vertex["red"], vertex["green"], vertex["blue"] = rgb[pick].T
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(out / meta["ply_file_path"]))
    return out


def config(data: Path, out: Path, name: str, steps: int, distributed: str, images_per_step: int, processes: int):
    from geer_ns.config import geer_trainer_config
    from geer_ns.model import GeerModelConfig

    cfg = geer_trainer_config("geer", GeerModelConfig())
    cfg.data = cfg.pipeline.datamanager.data = data
    cfg.pipeline.datamanager.cache_images = "cpu"
    cfg.pipeline.datamanager.images_per_step = images_per_step
    cfg.output_dir, cfg.experiment_name, cfg.timestamp = out, name, "run"
    cfg.vis = "tensorboard"
    cfg.max_num_iterations = steps * images_per_step * processes  # in images: `steps` steps whatever the batch
    cfg.steps_per_eval_image = cfg.steps_per_eval_batch = cfg.steps_per_eval_all_images = 0
    cfg.steps_per_save = 10**9
    cfg.machine.device_type = "cpu"
    model = cfg.pipeline.model
    model.num_downscales, model.warmup_length, model.stop_split_at = 0, 10**9, 0  # full resolution, no refinement
    model.distributed = distributed
    return cfg


# ------------------------------------------------------------------------------------- in a worker
def _instrument(record: dict) -> None:
    """Wall time inside the collectives and the payload they carry, this process's."""
    import torch.distributed as dist

    from geer_ns.distributed import gaussian_parallel as sharded, reductions

    record.update(collective_s=0.0, allreduce_bytes=0, exchanged_rows=0, payload_numbers=0)

    def timed(fn, counts_bytes=None):
        def wrapper(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                record["collective_s"] += time.perf_counter() - t0
                if counts_bytes is not None:
                    counts_bytes(args, kwargs)
        return wrapper

    def all_reduce_bytes(args, kwargs):
        record["allreduce_bytes"] += sum(t.numel() * t.element_size() for t in args[0])

    reductions.all_reduce_ = timed(reductions.all_reduce_, all_reduce_bytes)
    dist.all_to_all_single = timed(dist.all_to_all_single)  # the payload (both ways), counts, weights
    render = sharded.render_sharded

    def counted(*args, **kwargs):
        out, views = render(*args, **kwargs)
        record["exchanged_rows"] += views.sent
        record["payload_numbers"] = 16 if kwargs.get("absgrad_sinks") is not None else 14
        return out, views

    sharded.render_sharded = counted


def worker_main(local_rank: int, world_size: int, cfg, global_rank: int = 0) -> None:
    """One training run; writes timings.<rank>.json into the run's output folder."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
    from nerfstudio.scripts.train import _set_random_seed

    from peak_rss import peak_kib, peak_reset

    record: dict = {}
    _instrument(record)
    _set_random_seed(cfg.machine.seed + global_rank)
    trainer = cfg.setup(local_rank=local_rank, world_size=world_size)
    trainer.setup()
    setup_kib = peak_reset()  # the peak from here on: training, not the set-up (which builds the seed model whole)
    starts, steps, collective = {}, [], []
    state = {"c0": 0.0}

    def before(step):
        starts[step] = time.perf_counter()
        state["c0"] = record["collective_s"]

    def after(step):
        steps.append(time.perf_counter() - starts[step])
        collective.append(record["collective_s"] - state["c0"])

    trainer.callbacks.insert(0, TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], before))
    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], after))
    trainer.train()
    import torch

    model = trainer.pipeline.model
    params = sum(p.numel() * p.element_size() for p in model.gauss_params.values())
    out = Path(cfg.output_dir) / cfg.experiment_name / f"timings.{global_rank}.json"
    out.write_text(json.dumps({"steps": steps, "collective": collective, "record": record, "threads":
                               torch.get_num_threads(), "gaussians_here": model.num_points,
                               "gaussians": model.scene_gaussians or model.num_points,
                               "state_bytes": 4 * params,  # parameters, gradients, Adam's two moments
                               "setup_kib": setup_kib, "peak_kib": peak_kib()}))


def run_worker(args, main=None) -> None:
    """The worker's run of `main` (default worker_main) on args.processes processes."""
    import pickle

    main = main or worker_main
    cfg = pickle.loads(Path(args.worker).read_bytes())
    if args.processes == 1:
        main(0, 1, cfg)
        return
    from nerfstudio.scripts.train import launch

    from geer_ns.training.trainer import install_run_fixes

    install_run_fixes()  # what ns-train's main installs before it launches (geer's CPU worker among them)
    launch(main, num_devices_per_machine=args.processes, device_type="cpu", config=cfg)


# ------------------------------------------------------------------------------------------ driver
def measure(cfg, processes: int, work: Path, script: str = __file__, record: str = "timings") -> dict:
    """`script --worker` in a fresh process tree; each rank's <record>.<rank>.json."""
    import pickle

    path = work / f"{cfg.experiment_name}.pkl"
    path.write_bytes(pickle.dumps(cfg))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    subprocess.run([sys.executable, script, "--worker", str(path), "--processes", str(processes)], check=True,
                   env=env, stdout=subprocess.DEVNULL)
    base = Path(cfg.output_dir) / cfg.experiment_name
    return {r: json.loads((base / f"{record}.{r}.json").read_text()) for r in range(processes)}


def summarise(name: str, runs: dict, warmup: int, images_per_step: int) -> dict:
    ranks = list(runs.values())
    step = statistics.median(max(r["steps"][i] for r in ranks) for i in range(warmup, len(ranks[0]["steps"])))
    coll = statistics.median(statistics.median(r["collective"][warmup:]) for r in ranks)
    rec = ranks[0]["record"]
    n_steps = len(ranks[0]["steps"])
    images = images_per_step * len(ranks)
    exchanged = rec["exchanged_rows"] * rec["payload_numbers"] * 4 * 2 / max(n_steps, 1)  # both ways
    reduced = rec["allreduce_bytes"] / max(n_steps, 1) if len(ranks) > 1 else 0
    return {"run": name, "processes": len(ranks), "threads": ranks[0]["threads"], "images": images,
            "gaussians": ranks[0]["gaussians"], "here": ranks[0]["gaussians_here"], "step_s": step,
            "images_per_s": images / step, "collective_s": coll, "share": coll / step,
            "bytes": reduced or exchanged, "peak_mib": max(r["peak_kib"] for r in ranks) / 1024,
            "setup_mib": max(r["setup_kib"] for r in ranks) / 1024,
            "state_mib": max(r["state_bytes"] for r in ranks) / 2**20}


def row(s: dict) -> str:
    return (f"| {s['run']} | {s['processes']} x {s['threads']} | {s['images']} | {s['gaussians']:,} | "
            f"{s['here']:,} | {s['step_s']:.3f} | {s['images_per_s']:.1f} | {s['collective_s']:.3f} "
            f"({100 * s['share']:.0f} %) | {s['bytes'] / 2**20:.1f} | {s['state_mib']:.0f} | {s['setup_mib']:.0f} | "
            f"{s['peak_mib']:.0f} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=24)
    ap.add_argument("--warmup", type=int, default=4)
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--sharded-gaussians", type=int, default=1_000_000)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "distributed.md")
    ap.add_argument("--work", type=Path, default=Path("/tmp/geer_distributed_bench"))
    ap.add_argument("--report-only", action="store_true", help="rewrite the report from the last run's timings")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--processes", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        run_worker(args)
        return
    args.work.mkdir(parents=True, exist_ok=True)
    if not args.report_only:
        from geer_ns.render.cuda_backend import load_cpu_ops

        load_cpu_ops()  # built outside the timings
    small = args.work / f"room_{args.gaussians}" if args.report_only else scene(args.work, args.gaussians)
    large = args.work / f"room_{args.sharded_gaussians}" if args.report_only else scene(args.work, args.sharded_gaussians)
    plan = [  # (name, data, processes, engine, images per process)
        ("1 process", small, 1, "images", 1),
        ("1 process, 2 images per step", small, 1, "images", 2),
        ("2 processes, image-parallel", small, 2, "images", 1),
        ("1 process", large, 1, "images", 1),
        ("2 processes, Gaussian-parallel", large, 2, "gaussians", 1),
    ]
    results = []
    for i, (name, data, processes, engine, per) in enumerate(plan):
        tag = f"{processes}_{i}"
        base = args.work / "runs" / tag
        if args.report_only:
            runs = {r: json.loads((base / f"timings.{r}.json").read_text()) for r in range(processes)}
        else:
            cfg = config(data, args.work / "runs", tag, args.steps, engine, per, processes)
            shutil.rmtree(base, ignore_errors=True)
            print(f"[bench] {name}, {data.name} ...", flush=True)
            runs = measure(cfg, processes, args.work)
        results.append(summarise(name, runs, args.warmup, per))
        print(row(results[-1]), flush=True)
    write(args, results)


# Published bandwidths (bus bandwidth, what a ring all-reduce or an all-to-all moves per process per second):
# nccl-tests all_reduce_perf busbw at large messages, 8 x H100 SXM5 NVLink 4: 460-480 GB/s; 2 nodes x 8 H200
# over 4 x ConnectX-7 RoCE: ~35 GB/s; 100 Gb Ethernet: 12.5 GB/s line rate. A training step of splatfacto on an
# H100: ~14 ms (540x960, 7k steps; ../shared/device/README.md).
LINKS = (("NVLink 4 (8 x H100, one node)", 450e9, 8), ("RoCE, 2 nodes x 8 GPUs", 35e9, 16), ("100 Gb Ethernet, 2 machines", 11e9, 2))
STEP_S = 0.014


def model(results) -> str:
    """How the costs scale, from the measured per-Gaussian quantities and the published bandwidths above."""
    image = next(r for r in results if r["run"].startswith("2 processes, image"))
    shard = next(r for r in results if r["run"].startswith("2 processes, Gaussian"))
    one = next(r for r in results if r["run"] == "1 process" and r["gaussians"] == shard["gaussians"])
    per_gaussian = image["bytes"] / image["gaussians"]  # all-reduced bytes per Gaussian and step
    state = shard["state_mib"] * 2**20 / shard["here"]  # training state per Gaussian held
    rows = shard["bytes"] / (16 * 4 * 2)  # rows exchanged per process and step (16 numbers, both ways)
    visible = rows / shard["gaussians"]  # ... as a fraction of the scene (each process's camera, its own rows too)
    lines = [
        "## The model: how memory, traffic and time scale",
        "",
        f"Measured here: the image-parallel all-reduce carries {per_gaussian:.0f} bytes per Gaussian and step (59 "
        f"gradient numbers + 4 statistics, float32); a Gaussian's training state is {state:.0f} bytes; a "
        f"Gaussian-parallel process exchanged {rows:,.0f} rows per step ({100 * visible:.0f} % of the scene: what its "
        f"camera sees, 16 numbers each way).",
        "",
        "**Image-parallel** (every process holds the scene): memory per process = N x the state + one image's render "
        "working set; traffic per step and process = 2 (W-1)/W x bytes x N (ring all-reduce); it pays while that "
        "takes less than a step. With a 14 ms step (splatfacto's on an H100), the all-reduce costs as much as the "
        "step at N* Gaussians:",
        "",
        "| link | processes | bus bandwidth | N* (all-reduce = 14 ms step) |",
        "| --- | ---: | ---: | ---: |",
    ]
    for name, bandwidth, w in LINKS:
        n_star = STEP_S * bandwidth / (2 * (w - 1) / w * per_gaussian)
        lines.append(f"| {name} | {w} | {bandwidth / 1e9:.0f} GB/s | {n_star / 1e6:.1f} M |")
    big, gpus, seen = 100e6, 64, 0.02
    lines += [
        "",
        "**Gaussian-parallel** (each process holds N/W): memory per process = N/W x the state + the render working "
        "set of what one camera sees (f N Gaussians, f the visible fraction: "
        f"{100 * visible:.0f} % in this room, whose 180-degree views see most of it; a few % in a city block or a "
        "campus) + its images; traffic per step and process ~ f N x 128 bytes (16 numbers, both ways), "
        "independent of W; per-Gaussian work per step ~ N/W x the cameras of the step (visibility) + f N (render).",
        "",
        f"A 100M-Gaussian scene on 64 GPUs with f = {100 * seen:.0f} %: state {big / gpus * state / 2**30:.2f} GiB per "
        f"GPU (all of it: {big * state / 2**30:.0f} GiB, no single GPU holds it), {seen * big / 1e6:.0f} M Gaussians "
        f"rendered per camera, {seen * big * 128 / 2**30:.2f} GiB exchanged per GPU and step: "
        f"{seen * big * 128 / 450e9 * 1e3:.0f} ms on NVLink 4, {seen * big * 128 / 50e9 * 1e3:.0f} ms on 400 Gb/s "
        f"InfiniBand, {seen * big * 128 / 11e9 * 1e3:.0f} ms on 100 Gb Ethernet. Published beside it: Grendel "
        "(Zhao et al., \"On Scaling Up 3D Gaussian Splatting Training\", ICLR 2025) trains 40.4M Gaussians on 16 GPUs "
        "(4K Rubble, test PSNR 27.28 against 26.28 with 11.2M on one GPU) with the same pattern (Gaussians sent "
        "by a sparse all-to-all to the pixels' GPU); gsplat merged its multi-GPU strategy (distributed=True) for "
        "pinhole EWA splatting only. On these 2 CPU cores the exchange is "
        f"{100 * shard['share']:.0f} % of a step, and the two processes together trained "
        f"{shard['images_per_s'] / one['images_per_s']:.2f}x the images per second of one process with both cores.",
    ]
    return "\n".join(lines)


def write(args, results) -> None:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip()
    import torch

    head = ("| run | processes x threads | images / step | Gaussians | per process | s / step | images / s | "
            "collectives s / step (share) | MiB exchanged / step / process | Gaussian state MiB / process | "
            "RSS after set-up MiB | peak RSS in training MiB |\n"
            "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    text = f"""# Distributed training on the CPU (gloo): time, traffic and memory per process

- device: CPU, {platform.machine()}, {os.cpu_count()} cores (load average {os.getloadavg()[0]:.2f} when written), torch
  {torch.__version__}; renderer: the CPU build; each of 2 processes gets 1 of the 2 cores
- commit: {commit}
- command: `.venv/bin/python benchmarks/distributed_bench.py --steps {args.steps} --gaussians {args.gaussians}
  --sharded-gaussians {args.sharded_gaussians}`
- scene: the embedded synthetic room (21 training views, 96 x 96 BEAP), its seed cloud jittered to a fixed
  Gaussian count (no densification); SH degree 3 parameters; figures: median step wall time over steps
  {args.warmup}..{args.steps - 1} (the slowest process's), the median time per step inside the collectives, the
  payload per step and process (image-parallel: the gradient and statistics all-reduce; Gaussian-parallel: the
  rows exchanged, forward and backward), the Gaussian training state a process holds (parameters, gradients and
  Adam's two moments: 4 x 4 bytes x 59 numbers per Gaussian), its RSS after set-up and its peak RSS in training
  (RSS counts the process's whole heap: the image cache, the libraries, what the allocator keeps).

{head}
{chr(10).join(row(r) for r in results)}

{model(results)}
"""
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
