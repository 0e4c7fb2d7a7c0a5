"""Densification, time to quality: the former densification defaults against the current ones, on the dev fisheye
room (180-degree fisheye views and the pinhole views of the same poses) at 128^2 and 256^2, and on the embedded
room; test PSNR / SSIM against training wall time and against the Gaussian count.

    former   --pipeline.model.densify-signal pixels --pipeline.model.use-absgrad False
             --pipeline.model.densify-grad-thresh 0.0002 --pipeline.model.prune-unseen False
    current  the defaults (angular statistics, absgrad with splatfacto's 0.0008, the unseen prune)

The former signal is no longer in geer_ns: the former runs train with geer_ns as it was at FORMER_COMMIT (the
last commit that had it), extracted with `git archive` into the work folder; the current runs with this
checkout's.

Dev room schedule (both): refinement every 100 steps from step 300, splits until step 1000, full resolution from
the start; one more pair trains the 128^2 fisheye views with geer's own schedule (splits until step 15000, as
splatfacto) to show where the count settles. Every run is a fresh process trained by nerfstudio's own loop;
evaluation (ns-eval's metrics on the held-out views, native pixels) every --eval-every steps, outside the timed
training. Each run's record is kept in the work folder, so a later call adds runs without repeating those done.

    python -m benchmarks.densification [--steps 3000] [--only NAME ...] [--again]    # writes benchmarks/densification.md
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.common import BENCHMARKS, ROOT, commit, dev_room, header, run_config

FORMER_COMMIT = "7f04c26~1"  # the last commit whose geer_ns had the former densification signal
FORMER = {"densify_signal": "pixels", "use_absgrad": False, "densify_grad_thresh": 0.0002, "prune_unseen": False}
# This report compares the angular signal with the former one, both in the reference camera's units (the units
# themselves: benchmarks/densify_default.py); the former tree has no densify_units option.
CURRENT = {"densify_units": "reference"}


def plan(work: Path, steps: int) -> dict:
    """name -> (data, steps, model options)."""
    from geer_ns.data.synthetic_room import default_scene_dir

    demo = {"num_downscales": 1, "resolution_schedule": 400, "warmup_length": 100, "refine_every": 50,
            "central_half_angles_deg": (60.0, 60.0)}
    room = default_scene_dir()
    runs = {"embedded room, former (demo: splits to 250)": (room, 800, {**FORMER, **demo, "stop_split_at": 251}),
            "embedded room, current (splits throughout)": (room, 800, {**demo, **CURRENT})}
    for width in (1000, 500):  # the reference camera's width (signal.REFERENCE_WIDTH_PIXELS, 300): its calibration
        runs[f"embedded room, current with W_ref {width}"] = (room, 800, {**demo, **CURRENT,
                                                                          "reference_width": width})
    dev = {"warmup_length": 300, "refine_every": 100, "stop_split_at": 1000, "num_downscales": 0}
    for size, n in ((128, steps), (256, max(steps // 3, 1000))):
        for camera in ("fisheye", "pinhole"):
            data = dev_room(work, size) / f"transforms_{camera}.json"
            runs[f"{camera} {size}, current"] = (data, n, {**dev, **CURRENT})
            runs[f"{camera} {size}, former"] = (data, n, {**FORMER, **dev})
    fisheye = dev_room(work, 128) / "transforms_fisheye.json"  # a user's first run: geer's own schedule
    runs["fisheye 128, current, default schedule"] = (fisheye, 5000, dict(CURRENT))
    runs["fisheye 128, former, default schedule"] = (fisheye, 5000, dict(FORMER))
    return runs


def record_file(work: Path, name: str) -> Path:
    return work / "records" / (name.replace(" ", "_") + ".json")


def one_run(name: str, data: Path, steps: int, options: dict, eval_every: int, work: Path) -> None:
    """Train in this process with nerfstudio's loop, evaluating every `eval_every` steps (not timed); the record
    is rewritten at each evaluation (a run stopped early keeps what it reached)."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
    from nerfstudio.scripts.train import _set_random_seed
    from nerfstudio.utils import writer

    if "reference_width" in options:  # not an option: the constant the thresholds' units are calibrated by
        from geer_ns.densify import signal

        signal.REFERENCE_WIDTH_PIXELS = float(options.pop("reference_width"))
    config = run_config(data, work / "runs", name.replace(" ", "_"), steps, options)
    writer.EVENT_WRITERS.clear()
    _set_random_seed(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    pipeline, model = trainer.pipeline, trainer.pipeline.model
    record = {"name": name, "commit": os.environ.get("GEER_RUN_COMMIT", commit()), "steps": steps,
              "machine_boot": Path("/proc/sys/kernel/random/boot_id").read_text()[:8], "points": []}
    report = pipeline.datamanager.supervision_report("train")
    record["supervised_pixels"] = sum(e.supervised_pixels for e in report.cameras.values())
    clock = {"train": 0.0, "start": 0.0}

    def before(step):
        clock["start"] = time.perf_counter()

    def after(step):
        clock["train"] += time.perf_counter() - clock["start"]
        if (step + 1) % eval_every == 0 or step + 1 == steps:
            metrics = pipeline.get_average_eval_image_metrics(step=step)
            pipeline.train()
            record["points"].append({"step": step + 1, "seconds": clock["train"], "gaussians": model.num_points,
                                     "psnr": metrics["psnr"], "ssim": metrics["ssim"]})
            print(f"[{name}] step {step + 1}: {model.num_points} Gaussians, {clock['train']:.0f} s, "
                  f"PSNR {metrics['psnr']:.2f}", flush=True)
            record_file(work, name).write_text(json.dumps(record))

    trainer.callbacks.insert(0, TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], before))
    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], after))
    trainer.train()


def former_source(work: Path) -> Path:
    """The tree of FORMER_COMMIT, extracted once into `work` (the former runs import its geer_ns)."""
    out = work / "former"
    if not (out / "geer_ns").is_dir():
        out.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "archive", "--format=tar", FORMER_COMMIT], cwd=ROOT, capture_output=True)
        if archive.returncode:
            raise SystemExit(f"densification: the former runs need commit {FORMER_COMMIT} of this repository's "
                             f"history: {archive.stderr.decode().strip()}")
        subprocess.run(["tar", "-x", "-C", str(out)], input=archive.stdout, check=True)
    return out


def comparisons(by_name: dict) -> list:
    """Current over former at the last step both reached, per scene; counts per supervised pixel across the
    fisheye and pinhole views of one room; the reference width's effect."""
    lines = ["| scene | step | Gaussians, current / former | training time, current / former | PSNR, current - former |",
             "| --- | ---: | ---: | ---: | ---: |"]
    pairs = [(n, n.replace(", current", ", former")) for n in by_name if ", current" in n and "W_ref" not in n]
    pairs = [(new, old.replace("(splits throughout)", "(demo: splits to 250)")) for new, old in pairs]
    for new, old in pairs:
        if old not in by_name:
            continue
        steps = {p["step"]: p for p in by_name[new]["points"]}
        common = [p for p in by_name[old]["points"] if p["step"] in steps]
        if not common:
            continue
        o, stopped = common[-1], len(by_name[old]["points"]) and by_name[old]["points"][-1]["step"] < by_name[old]["steps"]
        c = steps[o["step"]]
        ratio = (f"{c['seconds'] / o['seconds']:.2f}" if by_name[new]["machine_boot"] == by_name[old]["machine_boot"]
                 else "not comparable (runs on different boots of the machine)")
        scene = new.replace(", current", "").replace(" (splits throughout)", "")
        lines.append(f"| {scene}{' (former stopped at step %d)' % o['step'] if stopped else ''} | {o['step']} | "
                     f"{c['gaussians']:,} / {o['gaussians']:,} = {c['gaussians'] / o['gaussians']:.2f} | "
                     f"{c['seconds']:.0f} s / {o['seconds']:.0f} s = {ratio} | {c['psnr'] - o['psnr']:+.2f} dB |")
    for size in (128, 256):
        f, p = by_name.get(f"fisheye {size}, current"), by_name.get(f"pinhole {size}, current")
        if f and p:
            per = [r["points"][-1]["gaussians"] / r["supervised_pixels"] for r in (f, p)]
            lines.append(f"\nDev room {size}^2, current, at the last step: {1000 * per[0]:.1f} Gaussians per 1k "
                         f"supervised pixels with the fisheye views, {1000 * per[1]:.1f} with the pinhole views "
                         f"(ratio {max(per) / min(per):.2f}).")
    widths = [(n, r) for n, r in by_name.items() if n.startswith("embedded room, current")]
    lines.append("\nThe reference width W_ref (geer_ns/densify/signal.py), embedded room at step 800: " + "; ".join(
        f"{n.split('with ')[-1] if 'W_ref' in n else 'W_ref 300 (the default)'}: {r['points'][-1]['gaussians']:,} "
        f"Gaussians, {r['points'][-1]['psnr']:.2f} dB" for n, r in widths) + ".")
    return lines


def write(out: Path, records: list) -> None:
    lines = [header(
        "Densification: time to quality, the former defaults against the current ones",
        "renderer: the CPU build; runs: " + ", ".join(sorted({r["commit"] for r in records})),
        f"former (trained with geer_ns at {FORMER_COMMIT}): `densify-signal pixels`, summed gradients, "
        "`densify-grad-thresh 0.0002`, no unseen prune; current: the defaults (statistics in the views' pixels, "
        "AbsGS gradients, 0.0008, unseen prune, 1-pixel floor). Dev room: refinement every 100 steps from step 300, "
        "splits until step 1000, full resolution; eval: the 6 held-out views in native pixels. Embedded room: the "
        "demo's CPU schedule (96^2, half resolution for 400 steps, refinement every 50 steps from 100). Training "
        "seconds exclude evaluation; runs are separate processes, one after the other."),
        "## Current against former", "", *comparisons({r["name"]: r for r in records}), "", "## Time and quality", "",
        "| run | step | Gaussians | Gaussians / 1k supervised px | training s | PSNR | SSIM |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in records:
        for p in r["points"]:
            lines.append(f"| {r['name']} | {p['step']} | {p['gaussians']:,} | "
                         f"{1000 * p['gaussians'] / r['supervised_pixels']:.1f} | {p['seconds']:.0f} | "
                         f"{p['psnr']:.2f} | {p['ssim']:.3f} |")
    out.write_text("\n".join(lines) + "\n")
    print(out.read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--eval-every", type=int, default=500)
    ap.add_argument("--only", nargs="*", help="names (or prefixes) of the runs to make; default all")
    ap.add_argument("--again", action="store_true", help="repeat the chosen runs even if their records are kept")
    ap.add_argument("--minutes", type=float, default=0, help="stop a run after this long (0: no limit)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/geer_densification"))
    ap.add_argument("--out", type=Path, default=BENCHMARKS / "densification.md")
    ap.add_argument("--run", help=argparse.SUPPRESS)
    args = ap.parse_args()
    (args.work / "records").mkdir(parents=True, exist_ok=True)
    runs = plan(args.work, args.steps)
    if args.run:
        data, steps, options = runs[args.run]
        one_run(args.run, data, steps, options, min(args.eval_every, max(steps // 4, 1)), args.work)
        return
    for name in [n for n in runs if not args.only or any(n.startswith(o) for o in args.only)]:
        if record_file(args.work, name).is_file() and not args.again:
            continue
        former = "former" in name
        source = former_source(args.work) if former else ROOT
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(source), str(ROOT)]),
                   GEER_RUN_COMMIT=FORMER_COMMIT if former else commit())
        command = [sys.executable, "-m", "benchmarks.densification", "--run", name, "--steps", str(args.steps),
                   "--eval-every", str(args.eval_every), "--work", str(args.work)]
        try:  # from the work folder: the run imports geer_ns from `source` (PYTHONPATH), not from the checkout
            subprocess.run(command, check=True, cwd=args.work, env=env, timeout=args.minutes * 60 or None)
        except subprocess.TimeoutExpired:
            print(f"[{name}] stopped after {args.minutes} minutes", flush=True)
    records = [json.loads(record_file(args.work, n).read_text()) for n in runs if record_file(args.work, n).is_file()]
    write(args.out, records)


if __name__ == "__main__":
    main()
