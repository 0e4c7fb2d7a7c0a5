"""Peak memory per process of Gaussian-parallel training on 2 CPU processes (gloo) against one process training
the same scene: in training, during a checkpoint save and during an evaluation.

Every run is a fresh process tree: nerfstudio's launcher for 2 processes (what `ns-train --machine.num-devices 2
--pipeline.model.distributed gaussians` runs), the training loop itself for 1. The scene is the embedded
synthetic room with its seed cloud jittered to --gaussians points (benchmarks/distributed_bench.py's scene), SH
degree 3, no densification; --steps steps, the all-images evaluation (3 images) at the last step, then
nerfstudio's final save. Each phase's peak RSS (VmHWM, reset to the current RSS when the phase starts: the
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


def worker_main(local_rank: int, world_size: int, cfg, global_rank: int = 0) -> None:
    """One run; each phase's peak RSS into memory.<rank>.json in the run's folder."""
    from nerfstudio.scripts.train import _set_random_seed

    from peak_rss import peak_kib, peak_reset

    _set_random_seed(cfg.machine.seed + global_rank)
    record: dict = {}
    peak_reset()
    trainer = cfg.setup(local_rank=local_rank, world_size=world_size)
    trainer.setup()
    record["setup"] = peak_kib()
    record["after_setup"] = peak_reset()
    last = trainer.config.max_num_iterations - 1  # the scaled schedule's last step
    trainer.config.steps_per_eval_all_images = last
    evaluate, save = trainer.eval_iteration, trainer.save_checkpoint

    def eval_iteration(step: int) -> None:
        if step != last:
            evaluate(step)
            return
        record["train"] = peak_kib()
        record["before_eval"] = peak_reset()
        t0 = time.perf_counter()
        evaluate(step)
        record["eval"], record["eval_s"] = peak_kib(), time.perf_counter() - t0

    def save_checkpoint(step: int) -> None:
        record["before_save"] = peak_reset()
        t0 = time.perf_counter()
        save(step)
        record["save"], record["save_s"] = peak_kib(), time.perf_counter() - t0

    trainer.eval_iteration, trainer.save_checkpoint = eval_iteration, save_checkpoint
    trainer.train()
    model = trainer.pipeline.model
    record.update(gaussians=model.scene_gaussians or model.num_points, here=model.num_points,
                  state_bytes=4 * sum(p.numel() * p.element_size() for p in model.gauss_params.values()))
    out = Path(cfg.output_dir) / cfg.experiment_name / f"memory.{global_rank}.json"
    out.write_text(json.dumps(record))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--gaussians", type=int, default=4_000_000)
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "distributed_memory.md")
    ap.add_argument("--work", type=Path, default=Path("/tmp/geer_distributed_memory"))
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--processes", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args()
    from distributed_bench import config, measure, run_worker, scene

    if args.worker:
        run_worker(args, worker_main)
        return

    from geer_ns.render.cuda_backend import load_cpu_ops

    load_cpu_ops()
    args.work.mkdir(parents=True, exist_ok=True)
    data = scene(args.work, args.gaussians)
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
    one = results["1 process"][0]
    rows = []
    for name, ranks in results.items():
        for rank, r in ranks.items():
            cells = " | ".join(f"{r[p] / 1024:,.0f} ({r[p] / one[p]:.2f}x)" for p in PHASES)
            rows.append(f"| {name} | {rank} | {r['gaussians']:,} | {r['here']:,} | {r['state_bytes'] / 2**20:,.0f} | "
                        f"{cells} | {r['save_s']:.1f} | {r['eval_s']:.1f} |")
    text = f"""# Peak memory per process: Gaussian-parallel on 2 gloo processes against one process

- device: CPU, {platform.machine()}, {os.cpu_count()} cores shared with other jobs (load average
  {os.getloadavg()[0]:.1f} when written; times are indicative only), torch {torch.__version__}
- commit: {commit}
- command: `nice .venv/bin/python benchmarks/distributed_memory.py --gaussians {args.gaussians} --steps {args.steps}`
- scene: the embedded synthetic room (21 training views, 96 x 96 BEAP; 3 evaluation images), its seed cloud
  jittered to {args.gaussians:,} Gaussians, SH degree 3, no densification; {args.steps} training steps, the
  all-images evaluation at the last step, then the final checkpoint
- figures: peak RSS (VmHWM) in MiB of each phase, reset to the current RSS at the phase's start (so each
  includes what the process holds: libraries, images, its Gaussians' training state), and its ratio to the one
  process's in the same phase. set-up: building the model (Gaussian-parallel: every process builds the seed
  model whole, then keeps its shard); train: the steps; eval: the all-images evaluation; save: the checkpoint.

| run | rank | Gaussians | held | training state MiB | set-up MiB | train MiB | eval MiB | save MiB | save s | eval s |
| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |
{chr(10).join(rows)}
"""
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
