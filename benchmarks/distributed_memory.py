"""Peak memory per process of Gaussian-parallel training on 2 CPU processes (gloo) against one process training
the same scene: in training, during a checkpoint save and during an evaluation.

Every run is a fresh process tree: nerfstudio's launcher for 2 processes (what `ns-train --machine.num-devices 2
--pipeline.model.distributed gaussians` runs), the training loop itself for 1. The scene is the embedded
synthetic room with its seed cloud jittered to --gaussians points (benchmarks/distributed_bench.py's scene), SH
degree 3, no densification; --steps steps, the all-images evaluation (3 images) at the last step, then
nerfstudio's final save (--steps 0: no step; the gradients and Adam's moments a step leaves are made by an
optimiser step on zero gradients, then the evaluation and the save: a scene whose training step would not fit
the machine can still be measured where the claim is, saving and evaluating). Each phase's peak RSS (VmHWM, reset to the current RSS when the phase starts: the
figure includes everything the process already holds) is recorded per process. One run; writes
benchmarks/distributed_memory.md. Memory: the one-process run holds the whole training state (~944 bytes a
Gaussian); run it alone on a shared machine (`nice`).

    .venv/bin/python benchmarks/distributed_memory.py [--gaussians 4000000] [--steps 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

PHASES = ("setup", "train", "eval", "save")
MMAP_THRESHOLD = 1 << 20  # glibc: blocks from 1 MiB up are mapped and unmapped (RSS is what is held, both runs)


class AnonPeak:
    """The largest anonymous RSS (RssAnon: the process's own memory, without the shared libraries' file pages)
    seen by a thread polling /proc/self/status every 5 ms since the last reset."""

    def __init__(self) -> None:
        import threading

        from peak_rss import status_kib

        self.peak, self._status = 0, status_kib
        threading.Thread(target=self._poll, daemon=True).start()

    def _poll(self) -> None:
        while True:
            self.peak = max(self.peak, self._status("RssAnon") or 0)
            time.sleep(0.005)

    def reset(self) -> int:
        self.peak = self._status("RssAnon") or 0
        return self.peak


def grow_to(trainer, n: int) -> None:
    """The model's Gaussians replaced by the scene of n (this process's rows of it: r::R when sharded): the
    room's seed points jittered (as distributed_bench.scene), their colours, scales of 1 cm, random rotations,
    opacity 0.1, SH degree 3 (higher bands 0). Made directly: no PLY of n points, no nearest-neighbour scales."""
    import json

    import numpy as np
    import torch

    from geer_ns.data.synthetic_room import default_scene_dir
    from geer_ns.data.ply import read_ply_points

    model, world = trainer.pipeline.model, trainer.world
    src = default_scene_dir()
    xyz, rgb = read_ply_points(src / json.loads((src / "transforms.json").read_text())["ply_file_path"])
    rng = np.random.default_rng(0)
    pick = rng.integers(0, xyz.shape[0], n)
    rows = slice(world.rank, None, world.size) if model.config.distributed == "gaussians" else slice(None)
    means = (xyz[pick] + rng.normal(scale=0.01, size=(n, 3)))[rows].astype(np.float32)
    colours = rgb[pick][rows].astype(np.float32) / 255.0
    quats = torch.randn(n, 4, generator=torch.Generator().manual_seed(0))[rows]
    k = means.shape[0]
    new = {"means": torch.from_numpy(means), "scales": torch.full((k, 3), float(np.log(0.01))),
           "quats": quats / quats.norm(dim=-1, keepdim=True), "opacities": torch.full((k, 1), float(np.log(0.1 / 0.9))),
           "features_dc": (torch.from_numpy(colours) - 0.5) / 0.28209479177387814,
           "features_rest": torch.zeros(k, 15, 3)}
    with torch.no_grad():
        for name, p in model.gauss_params.items():
            p.data = new[name].to(p)
    model.strategy_state["id"] = torch.arange(n)[rows].clone()
    if model.config.distributed == "gaussians":
        trainer.engine.state.scene_gaussians = n


def worker_main(local_rank: int, world_size: int, cfg, global_rank: int = 0) -> None:
    """One run; each phase's peak RSS into memory.<rank>.json in the run's folder."""
    from nerfstudio.scripts.train import _set_random_seed

    import torch

    from peak_rss import peak_kib, peak_reset

    _set_random_seed(cfg.machine.seed + global_rank)
    record: dict = {}
    anon = AnonPeak()
    record["libraries"], record["libraries_anon"] = peak_reset(), anon.reset()
    trainer = cfg.setup(local_rank=local_rank, world_size=world_size)
    trainer.setup()
    record["setup"], record["setup_anon"] = peak_kib(), anon.peak
    record["after_setup"] = peak_reset()
    anon.reset()
    last = trainer.config.max_num_iterations - 1  # the scaled schedule's last step
    trainer.config.steps_per_eval_all_images = last
    evaluate, save = trainer.eval_iteration, trainer.save_checkpoint

    def eval_iteration(step: int) -> None:
        if step != last:
            evaluate(step)
            return
        record["train"], record["train_anon"] = peak_kib(), anon.peak
        record["before_eval"] = peak_reset()
        anon.reset()
        t0 = time.perf_counter()
        evaluate(step)
        record["eval"], record["eval_s"], record["eval_anon"] = peak_kib(), time.perf_counter() - t0, anon.peak

    def save_checkpoint(step: int) -> None:
        record["before_save"] = peak_reset()
        anon.reset()
        t0 = time.perf_counter()
        save(step)
        record["save"], record["save_s"], record["save_anon"] = peak_kib(), time.perf_counter() - t0, anon.peak

    trainer.eval_iteration, trainer.save_checkpoint = eval_iteration, save_checkpoint
    if last >= 0:
        trainer.train()
    else:  # no step: the scene's Gaussians made directly, the state a step leaves made without rendering
        model = trainer.pipeline.model
        grow_to(trainer, int(os.environ["GEER_BENCH_GAUSSIANS"]))
        for p in model.gauss_params.values():
            p.grad = torch.zeros_like(p)
        for name in model.gauss_params:
            trainer.optimizers.optimizers[name].step()
        record["after_setup"] = peak_reset()  # set-up: the small seed model, then the scene made here
        record["setup"] = record["train"] = record["after_setup"]
        record["setup_anon"] = record["train_anon"] = anon.reset()
        trainer.config.steps_per_eval_all_images = 0
        trainer.config.steps_per_eval_image = last = 1  # one evaluation image
        eval_iteration(1)
        save_checkpoint(1)
    model = trainer.pipeline.model
    record.update(gaussians=model.scene_gaussians or model.num_points, here=model.num_points,
                  state_bytes=4 * sum(p.numel() * p.element_size() for p in model.gauss_params.values()))
    out = Path(cfg.output_dir) / cfg.experiment_name / f"memory.{global_rank}.json"
    out.write_text(json.dumps(record))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--gaussians", type=int, default=4_000_000)
    ap.add_argument("--steps", type=int, default=3, help="0: no training step (its state made without rendering)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "distributed_memory.md")
    ap.add_argument("--work", type=Path, default=Path("/tmp/geer_distributed_memory"))
    ap.add_argument("--report-only", action="store_true", help="rewrite the report from the last run's memory.json")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--processes", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args()
    from distributed_bench import config, measure, run_worker, scene

    if args.worker:
        run_worker(args, worker_main)
        return
    if args.report_only:
        write(args, json.loads((args.work / "memory.json").read_text()))
        return

    from geer_ns.render.cuda_backend import load_cpu_ops

    load_cpu_ops()
    os.environ["MALLOC_MMAP_THRESHOLD_"] = str(MMAP_THRESHOLD)  # the workers' (the same for both runs)
    args.work.mkdir(parents=True, exist_ok=True)
    data = scene(args.work, args.gaussians if args.steps else 20_000)  # --steps 0: the scene is made in the worker
    os.environ["GEER_BENCH_GAUSSIANS"] = str(args.gaussians)
    results = {}
    for name, processes, engine in (("1 process", 1, "images"), ("2 processes, Gaussian-parallel", 2, "gaussians")):
        tag = f"memory_{processes}"
        shutil.rmtree(args.work / "runs" / tag, ignore_errors=True)
        cfg = config(data, args.work / "runs", tag, args.steps, engine, 1, processes)
        print(f"[bench] {name} ...", flush=True)
        results[name] = measure(cfg, processes, args.work, __file__, "memory")
        print(json.dumps(results[name]), flush=True)
    (args.work / "memory.json").write_text(json.dumps(results))
    write(args, results)


def write(args, results) -> None:
    import torch

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    results = {name: {str(rank): r for rank, r in ranks.items()} for name, ranks in results.items()}
    one, zero = results["1 process"]["0"], results["2 processes, Gaussian-parallel"]["0"]
    summary = []
    for phase in ("save", "eval"):
        above = (zero[phase] - zero["libraries"]) / (one[phase] - one["libraries"])
        summary.append(f"- {phase}: rank 0 {zero[phase] / 1024:,.0f} MiB against {one[phase] / 1024:,.0f} MiB, "
                       f"{zero[phase] / one[phase]:.2f}x in RSS, {zero[phase + '_anon'] / one[phase + '_anon']:.2f}x "
                       f"in anonymous RSS, {above:.2f}x above the libraries (peak - the RSS before the model)")
    rows = []
    for name, ranks in results.items():
        for rank, r in ranks.items():
            cells = " | ".join(f"{r[p] / 1024:,.0f} ({r[p] / one[p]:.2f}x) | {r[p + '_anon'] / 1024:,.0f} "
                               f"({r[p + '_anon'] / one[p + '_anon']:.2f}x)" for p in PHASES)
            rows.append(f"| {name} | {rank} | {r['gaussians']:,} | {r['here']:,} | {r['state_bytes'] / 2**20:,.0f} | "
                        f"{r['libraries'] / 1024:,.0f} | {cells} | {r['save_s']:.1f} | {r['eval_s']:.1f} |")
    text = f"""# Peak memory per process: Gaussian-parallel on 2 gloo processes against one process

- device: CPU, {platform.machine()}, {os.cpu_count()} cores shared with other jobs (load average
  {os.getloadavg()[0]:.1f} when written; times are indicative only), torch {torch.__version__}
- commit: {commit}
- command: `nice .venv/bin/python benchmarks/distributed_memory.py --gaussians {args.gaussians} --steps {args.steps}`
- scene: the embedded synthetic room (21 training views, 96 x 96 BEAP; 3 evaluation images), its seed cloud
  jittered to {args.gaussians:,} Gaussians, SH degree 3, no densification; {args.steps} training step(s), the
  all-images evaluation at the last step, then the final checkpoint; MALLOC_MMAP_THRESHOLD_={MMAP_THRESHOLD} in
  both runs (freed tensors go back to the system: RSS is what a process holds, not what glibc kept)
- {"--steps 0: no training step; the Gaussians are made in each process after the set-up of a 20,000-point seed model (grow_to), with the gradients and Adam moments a step leaves; set-up and train are then the RSS once that state is made, and the evaluation renders one image" if not args.steps else "training steps as above"}
- figures, MiB, each phase's peak and its ratio to the one process's in the same phase: RSS is VmHWM, reset
  to the current RSS when the phase starts (so it includes what the process holds: libraries, images, its
  Gaussians' training state); anon is RssAnon (the process's own memory, without the shared libraries' file
  pages), the largest of polls every 5 ms. libraries: RSS before the model is built (imports, the CPU kernels).
  set-up builds the model (Gaussian-parallel: every process builds the seed model whole, then keeps its
  shard); train: the steps; eval: the all-images evaluation; save: the checkpoint.

| run | rank | Gaussians | held | training state MiB | libraries MiB | set-up RSS | anon | train RSS | anon | eval RSS | anon | save RSS | anon | save s | eval s |
| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |
{chr(10).join(rows)}

Rank 0 against the one process:

{chr(10).join(summary)}

The model of these figures (rank 0 of R processes, N Gaussians, p = 236 parameter bytes a Gaussian at SH
degree 3, its training state 4 p): docs/distributed.md, "Memory".
"""
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
