"""Training on several CPU processes (gloo): time per step, images per second, the collectives' share of the
step, bytes exchanged and peak memory per process, for 1 and 2 processes, image-parallel and Gaussian-parallel.

Every run is a fresh process (its peak memory is its own) training the embedded synthetic room at its full
96 x 96 BEAP resolution with a fixed number of Gaussians (the seed cloud jittered to --gaussians and
--sharded-gaussians points; no densification, so every step costs the same): nerfstudio's launcher (what
`ns-train --machine.num-devices N` runs) for 2 processes, the training loop itself for 1. Timed: each step's
wall time after --warmup steps (median), the time inside the collectives (gradient and statistics all-reduce;
the all-to-all exchanges), the payload bytes, the peak RSS (VmHWM, reset after the set-up). One run, one
machine; writes benchmarks/distributed.md.

    python -m benchmarks.distributed [--steps 24] [--gaussians 100000] [--sharded-gaussians 1000000]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.common import BENCHMARKS, ROOT, header, run_config


def _status_kib(key: str) -> int:
    """A line of /proc/self/status in KiB (VmRSS, VmHWM)."""
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(key))


def peak_reset() -> int:
    """Current RSS in KiB, the peak (VmHWM) reset to it: what follows is measured alone."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    return _status_kib("VmRSS")


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
    """`steps` steps (counted in images: whatever the batch) at full resolution without densification."""
    cfg = run_config(data, out, name, steps * images_per_step * processes,
                     {"num_downscales": 0, "warmup_length": 10**9, "stop_split_at": 0, "distributed": distributed})
    cfg.pipeline.datamanager.images_per_step = images_per_step
    cfg.machine.device_type = "cpu"
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
                               "setup_kib": setup_kib, "peak_kib": _status_kib("VmHWM")}))


def run_worker(args) -> None:
    """worker_main on args.processes processes."""
    import pickle

    main = worker_main
    cfg = pickle.loads(Path(args.worker).read_bytes())
    if args.processes == 1:
        main(0, 1, cfg)
        return
    from nerfstudio.scripts.train import launch

    from geer_ns.training.trainer import install_run_fixes

    install_run_fixes()  # what ns-train's main installs before it launches (geer's CPU worker among them)
    launch(main, num_devices_per_machine=args.processes, device_type="cpu", config=cfg)


# ------------------------------------------------------------------------------------------ driver
def measure(cfg, processes: int, work: Path) -> dict:
    """This module's worker in a fresh process tree; each rank's timings.<rank>.json."""
    import pickle

    path = work / f"{cfg.experiment_name}.pkl"
    path.write_bytes(pickle.dumps(cfg))
    subprocess.run([sys.executable, "-m", "benchmarks.distributed", "--worker", str(path), "--processes",
                    str(processes)], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    base = Path(cfg.output_dir) / cfg.experiment_name
    return {r: json.loads((base / f"timings.{r}.json").read_text()) for r in range(processes)}


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
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=24)
    ap.add_argument("--warmup", type=int, default=4)
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--sharded-gaussians", type=int, default=1_000_000)
    ap.add_argument("--out", type=Path, default=BENCHMARKS / "distributed.md")
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


def _per_gaussian(results) -> str:
    """The figures docs/distributed.md's scaling model starts from."""
    image = next(r for r in results if r["run"].startswith("2 processes, image"))
    shard = next(r for r in results if r["run"].startswith("2 processes, Gaussian"))
    one = next(r for r in results if r["run"] == "1 process" and r["gaussians"] == shard["gaussians"])
    rows = shard["bytes"] / (16 * 4 * 2)  # rows exchanged per process and step (16 numbers, both ways)
    return (f"the image-parallel all-reduce carries {image['bytes'] / image['gaussians']:.0f} bytes; a Gaussian's "
            f"training state is {shard['state_mib'] * 2**20 / shard['here']:.0f} bytes; a Gaussian-parallel process "
            f"exchanged {rows:,.0f} rows ({100 * rows / shard['gaussians']:.0f} % of the scene, what its camera sees); "
            f"the two Gaussian-parallel processes trained {shard['images_per_s'] / one['images_per_s']:.2f}x the "
            "images per second of one process with both cores")


def write(args, results) -> None:
    head = ("| run | processes x threads | images / step | Gaussians | per process | s / step | images / s | "
            "collectives s / step (share) | MiB exchanged / step / process | Gaussian state MiB / process | "
            "RSS after set-up MiB | peak RSS in training MiB |\n"
            "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    text = header(
        "Distributed training on the CPU (gloo): time, traffic and memory per process",
        "renderer: the CPU build; each of 2 processes gets 1 of the 2 cores",
        "scene: the embedded synthetic room (21 training views, 96 x 96 BEAP), its seed cloud jittered to a fixed "
        "Gaussian count (no densification); SH degree 3 parameters; figures: median step wall time over steps "
        f"{args.warmup}..{args.steps - 1} (the slowest process's), the median time per step inside the collectives, "
        "the payload per step and process (image-parallel: the gradient and statistics all-reduce; "
        "Gaussian-parallel: the rows exchanged, forward and backward), the Gaussian training state a process holds "
        "(parameters, gradients and Adam's two moments: 4 x 4 bytes x 59 numbers per Gaussian), its RSS after "
        "set-up and its peak RSS in training (RSS counts the process's whole heap: the image cache, the libraries, "
        "what the allocator keeps).") + f"""
{head}
{chr(10).join(row(r) for r in results)}

Per Gaussian and step: {_per_gaussian(results)} (the scaling model built on them: docs/distributed.md).
"""
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
