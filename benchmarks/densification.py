"""Densification, time to quality: the former densification defaults against the current ones, on the dev fisheye
room (180-degree fisheye views and the pinhole views of the same poses) at 128^2 and 256^2, and on the embedded
room; test PSNR / SSIM against training wall time and against the Gaussian count, and what each refinement did,
rule by rule.

    former   --pipeline.model.densify-signal pixels --pipeline.model.use-absgrad False
             --pipeline.model.densify-grad-thresh 0.0002 --pipeline.model.prune-unseen False
    current  the defaults (angular statistics, absgrad with splatfacto's 0.0008, the unseen prune)

The former signal is no longer in geer_ns: the former runs train with geer_ns as it was at the git tag
`densify-pixel-signal` (the last commit that had it), extracted with `git archive` into the work dir; the current
runs with this checkout's.

Dev room schedule (both): refinement every 100 steps from step 300, splits until step 1000, full resolution from
the start (num-downscales 0), otherwise geer's defaults; one more run trains the 128^2 fisheye views with geer's
own schedule (splits until step 15000, as splatfacto) to show where the count settles. The 128^2 / 256^2
datasets are the dev room's images and masks resized with OpenCV's INTER_AREA, intrinsics scaled. Every run
is a fresh process, trained by nerfstudio's own loop; evaluation (ns-eval's metrics on the 6 held-out views,
native pixels) every --eval-every steps, outside the timed training. Each finished (or stopped) run's record,
with the commit it ran at, is kept in benchmarks/densification_runs.json; the report, benchmarks/densification.md,
is written from all the records there, so a later session adds runs without repeating the ones that took hours.

    .venv/bin/python benchmarks/densification.py [--steps 3000] [--only NAME ...] [--again]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FORMER_TAG = "densify-pixel-signal"  # git tag: the last commit whose geer_ns had the former densification signal
SOURCE_ENV = "GEER_DENSIFICATION_SOURCE"  # a run's geer_ns tree (the tag's, for the former runs)
sys.path.insert(0, os.environ.get(SOURCE_ENV, str(ROOT)))
DEV_ROOM = ROOT.parent / "shared" / "data" / "fisheye_room_dev"
FORMER = {"densify_signal": "pixels", "use_absgrad": False, "densify_grad_thresh": 0.0002, "prune_unseen": False}


def resized_room(work: Path, size: int) -> Path:
    """The dev room at size^2: images, masks and intrinsics (fisheye and pinhole) scaled from 384^2."""
    import cv2

    out = work / f"dev_room_{size}"
    if (out / "transforms_pinhole.json").is_file():
        return out
    scale = size / 384.0
    for name in ("transforms_fisheye.json", "transforms_pinhole.json"):
        meta = json.loads((DEV_ROOM / name).read_text())
        for key in ("fl_x", "fl_y", "cx", "cy", "fisheye_crop_radius"):
            if key in meta:
                meta[key] = meta[key] * scale
        meta["w"] = meta["h"] = size
        for frame in meta["frames"]:
            for key in ("file_path", "mask_path"):
                if key in frame and not (out / frame[key]).exists():
                    (out / frame[key]).parent.mkdir(parents=True, exist_ok=True)
                    image = cv2.imread(str(DEV_ROOM / frame[key]), cv2.IMREAD_UNCHANGED)
                    small = cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)
                    if key == "mask_path":
                        small = ((small >= 128) * 255).astype("uint8")  # a mask stays binary
                    cv2.imwrite(str(out / frame[key]), small, [cv2.IMWRITE_JPEG_QUALITY, 95])
        (out / name).write_text(json.dumps(meta))
    shutil.copy(DEV_ROOM / "points3d.ply", out / "points3d.ply")
    return out


def plan(work: Path, steps: int, former_steps: int = 0) -> dict:
    """name -> (data, steps, model overrides, schedule overrides)."""
    from geer_ns.data.synthetic_room import default_scene_dir

    runs = {}
    demo = {"num_downscales": 1, "resolution_schedule": 400, "warmup_length": 100, "refine_every": 50,
            "central_half_angles_deg": (60.0, 60.0)}
    room = default_scene_dir()
    runs["embedded room, former (demo: splits to 250)"] = (room, 800, {**FORMER, **demo, "stop_split_at": 251})
    runs["embedded room, current (splits throughout)"] = (room, 800, dict(demo))
    for width in (1000, 500):  # the reference camera's width (signal.REFERENCE_WIDTH_PIXELS, 300): its calibration
        runs[f"embedded room, current with W_ref {width}"] = (room, 800, {**demo, "reference_width": width})
    dev = {"warmup_length": 300, "refine_every": 100, "stop_split_at": 1000, "num_downscales": 0}
    for size, n in ((128, steps), (256, max(steps // 3, 1000))):
        room = resized_room(work, size)
        for camera in ("fisheye", "pinhole"):
            data = room / f"transforms_{camera}.json"
            runs[f"{camera} {size}, current"] = (data, n, dict(dev))
            # the former defaults reach ~285k Gaussians by step 1000 (seconds a step on 2 cores): run to the
            # end of the splits, where the counts and the time per step have stopped changing
            runs[f"{camera} {size}, former"] = (data, former_steps or n, {**FORMER, **dev})
    # what a user's first run gets: geer's own schedule (splatfacto's: splits until step 15000, an opacity reset
    # every 3000 steps, a coarse-to-fine resolution), to see whether the count settles or keeps growing
    fisheye = resized_room(work, 128) / "transforms_fisheye.json"
    runs["fisheye 128, current, default schedule"] = (fisheye, 5000, {})
    runs["fisheye 128, former, default schedule"] = (fisheye, 5000, dict(FORMER))
    return runs


# ------------------------------------------------------------------------------------------ one run
def run_files(work: Path, name: str) -> tuple:
    """A run's record in the work dir: (finished, what a stopped run had reached)."""
    stem = work / name.replace(" ", "_")
    return stem.with_name(stem.name + ".json"), stem.with_name(stem.name + ".partial.json")


def one_run(name: str, data: Path, steps: int, overrides: dict, eval_every: int, out: Path) -> None:
    """Train in this process with nerfstudio's loop; evaluate every `eval_every` steps (not timed)."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
    from nerfstudio.scripts.train import _set_random_seed
    from nerfstudio.utils import writer

    from geer_ns.config import geer_trainer_config
    from geer_ns.model import GeerModelConfig

    config = geer_trainer_config("geer", GeerModelConfig())
    config.data = config.pipeline.datamanager.data = data
    config.pipeline.datamanager.cache_images = "cpu"
    config.output_dir, config.experiment_name, config.timestamp = out / "runs", name.replace(" ", "_"), "run"
    done_file, partial_file = run_files(out, name)
    config.vis = "tensorboard"
    config.max_num_iterations = steps
    config.steps_per_eval_image = config.steps_per_eval_batch = config.steps_per_eval_all_images = 0
    config.steps_per_save = 10**9
    for key, value in overrides.items():
        if key == "reference_width":  # not an option: the constant the thresholds' units are calibrated by
            from geer_ns.densify import signal

            signal.REFERENCE_WIDTH_PIXELS = float(value)
        else:
            setattr(config.pipeline.model, key, value)
    writer.EVENT_WRITERS.clear()
    _set_random_seed(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    pipeline, model = trainer.pipeline, trainer.pipeline.model
    commit = f"{git_commit(FORMER_TAG)} ({FORMER_TAG})" if is_former(overrides) else git_commit()
    record = {"name": name, "commit": commit, "machine_session": machine_session(), "steps": steps,
              "overrides": {k: list(v) if isinstance(v, tuple) else v for k, v in overrides.items()}, "points": []}
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
            partial = {**record, "refinements": getattr(model.strategy, "log", []), "stopped_at": step + 1}
            partial_file.write_text(json.dumps(partial))  # if it is stopped

    trainer.callbacks.insert(0, TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], before))
    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], after))
    report = pipeline.datamanager.supervision_report("train")
    record["supervised_pixels"] = sum(e.supervised_pixels for e in report.cameras.values())  # native pixels
    trainer.train()
    record["refinements"] = getattr(model.strategy, "log", [])
    done_file.write_text(json.dumps(record))


# ----------------------------------------------------------------------------------------- the report
def git_commit(rev: str = "HEAD") -> str:
    done = subprocess.run(["git", "rev-parse", "--short", f"{rev}^{{commit}}"], capture_output=True, text=True,
                          cwd=ROOT)
    return done.stdout.strip()


def is_former(overrides: dict) -> bool:
    return overrides.get("densify_signal") == "pixels"


def former_source(work: Path) -> Path:
    """The tree of git tag FORMER_TAG, extracted once into `work` (the former runs import its geer_ns)."""
    out = work / FORMER_TAG
    if not (out / "geer_ns").is_dir():
        out.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "archive", "--format=tar", FORMER_TAG], cwd=ROOT, capture_output=True)
        if archive.returncode:
            raise SystemExit(f"densification.py: the former runs need git tag {FORMER_TAG} (the last commit with the "
                             f"former signal): {archive.stderr.decode().strip()}")
        subprocess.run(["tar", "-x", "-C", str(out)], input=archive.stdout, check=True)
    return out


def machine_session() -> str:
    """This boot of this machine: wall times are comparable only between runs of one session."""
    return Path("/proc/sys/kernel/random/boot_id").read_text().strip()[:8]


def load_records(path: Path) -> dict:
    """name -> record, from the kept records (a stopped run's record has `stopped_at`)."""
    return {r["name"]: r for r in json.loads(path.read_text())} if path.is_file() else {}


def keep_records(path: Path, records: dict, runs: dict) -> None:
    order = {n: i for i, n in enumerate(runs)}
    ordered = sorted(records.values(), key=lambda r: order.get(r["name"], len(order)))
    path.write_text(json.dumps(ordered, indent=1) + "\n")


def shown_name(record: dict) -> str:
    if "stopped_at" in record:
        return f"{record['name']} (stopped at step {record['stopped_at']} of {record['steps']})"
    return record["name"]


def table(records: list) -> str:
    lines = ["| run | session | step | Gaussians | Gaussians / 1k supervised px | training s | PSNR | SSIM |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in records:
        for p in r["points"]:
            per = f"{1000 * p['gaussians'] / r['supervised_pixels']:.1f}" if r.get("supervised_pixels") else "n/a"
            lines.append(f"| {shown_name(r)} | {r.get('machine_session', '?')} | {p['step']} | {p['gaussians']:,} | "
                         f"{per} | {p['seconds']:.0f} | {p['psnr']:.2f} | {p['ssim']:.3f} |")
    return "\n".join(lines)


def rules(records: list) -> str:
    lines = ["| run | step | before | duplicated (gradient) | split (gradient) | split (screen size only) | held back "
             "(finer than a pixel) | pruned (opacity, 3D size, screen size, unseen) | after | growth |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: |"]
    for r in records:
        for e in r.get("refinements", []):
            pruned = ", ".join(str(e.get(f"pruned ({k})", 0)) for k in ("opacity", "3D size", "screen size", "unseen"))
            lines.append(f"| {shown_name(r)} | {e['step']} | {e['before']:,} | {e['duplicated (gradient)']:,} | "
                         f"{e['split (gradient)']:,} | {e['split (screen size only)']:,} | "
                         f"{e.get('held back (finer than a pixel)', 0):,} | {pruned} | {e['after']:,} | "
                         f"x{e['after'] / max(e['before'], 1):.2f} |")
    return "\n".join(lines)


def comparisons(records: list) -> str:
    """Current over former at the last step both reached, per scene; counts per supervised pixel across the
    fisheye and pinhole views of one room."""
    by_name = {r["name"]: r for r in records}
    lines = ["| scene | step | Gaussians, current / former | training time, current / former | PSNR, current - former |",
             "| --- | ---: | ---: | ---: | ---: |"]
    pairs = [(n, n.replace(", current", ", former")) for n in by_name if ", current" in n and "W_ref" not in n]
    pairs += [("embedded room, current (splits throughout)", "embedded room, former (demo: splits to 250)")]
    for new, old in pairs:
        if new not in by_name or old not in by_name:  # a stopped run counts to the last step it reached
            continue
        steps = {p["step"]: p for p in by_name[new]["points"]}
        common = [p for p in by_name[old]["points"] if p["step"] in steps]
        if not common:
            continue
        o = common[-1]
        c = steps[o["step"]]
        stopped = f" (former stopped at {by_name[old]['stopped_at']})" if "stopped_at" in by_name[old] else ""
        apart = by_name[new].get("machine_session") != by_name[old].get("machine_session")
        time_ratio = "not comparable (different sessions)" if apart else f"{c['seconds'] / o['seconds']:.2f}"
        scene = new.replace(", current", "").replace(" (splits throughout)", "")
        lines.append(f"| {scene}{stopped} | {o['step']} | {c['gaussians']:,} / {o['gaussians']:,} = "
                     f"{c['gaussians'] / o['gaussians']:.2f} | {c['seconds']:.0f} s / {o['seconds']:.0f} s = "
                     f"{time_ratio} | {c['psnr'] - o['psnr']:+.2f} dB |")
    for size in (128, 256):
        f, p = by_name.get(f"fisheye {size}, current"), by_name.get(f"pinhole {size}, current")
        if f and p:
            per = [r["points"][-1]["gaussians"] / r["supervised_pixels"] for r in (f, p)]
            lines.append(f"\nDev room {size}^2, current, at the last step: {1000 * per[0]:.1f} Gaussians per 1k "
                         f"supervised pixels with the fisheye views, {1000 * per[1]:.1f} with the pinhole views "
                         f"(ratio {max(per) / min(per):.2f}).")
    widths = [(n, by_name[n]) for n in by_name if n.startswith("embedded room, current")]
    if len(widths) > 1:
        lines.append("\nThe reference width W_ref (geer_ns/densify/signal.py), embedded room at step 800: " + "; ".join(
            f"{n.split('with ')[-1] if 'W_ref' in n else 'W_ref 300 (the default)'}: {r['points'][-1]['gaussians']:,} Gaussians, "
            f"{r['points'][-1]['psnr']:.2f} dB" for n, r in widths) + ".")
    return "\n".join(lines)


def write(out_md: Path, records: list, runs: dict, args) -> None:
    import torch

    commits = sorted({r.get("commit", "?") for r in records})
    missing = [n for n in runs if n not in {r["name"] for r in records}]
    stopped = [shown_name(r) for r in records if "stopped_at" in r]
    text = f"""# Densification: time to quality, the former defaults against the current ones

- device: CPU, {platform.machine()}, {os.cpu_count()} cores (load average {os.getloadavg()[0]:.2f} when written), torch
  {torch.__version__}; renderer: the CPU build
- report written at commit {git_commit()} from the kept records (`benchmarks/densification_runs.json`); the runs
  were made at {", ".join(commits)} (one training code: between them only benchmarks and documentation
  changed)
- commands: `.venv/bin/python benchmarks/densification.py [--only NAME ...] [--again]` makes the runs not yet
  kept (or repeats the named ones) and rewrites this report; each record keeps its steps and overrides. This
  report: `.venv/bin/python benchmarks/densification.py {shlex.join(sys.argv[1:])}`
- former (trained with geer_ns at git tag `{FORMER_TAG}`): `densify-signal pixels`, summed gradients, `densify-grad-thresh 0.0002`, no unseen prune (the 1-pixel
  growth floor stays on; the rules table shows what it held back); current: the defaults (statistics in the
  views' pixels, AbsGS gradients, 0.0008, unseen prune, 1-pixel floor). Dev room: refinement every 100 steps
  from step 300, splits until step 1000, full resolution; eval: the 6 held-out views in native pixels (fisheye
  runs: fisheye views; pinhole runs: pinhole views). Embedded room: the demo's CPU schedule (96^2, half
  resolution for 400 steps, refinement every 50 steps from 100). Training seconds exclude evaluation. Runs are
  separate processes, one after the other, on one otherwise idle machine; wall times compare only within one
  session (the table's session column: the machine's boot), so a time ratio across sessions is not given.
- not run: {", ".join(missing) or "none"}; stopped before their last step: {"; ".join(stopped) or "none"}

## Current against former

{comparisons(records)}

## Time and quality

{table(records)}

## What each refinement did, rule by rule

{rules(records)}
"""
    out_md.write_text(text)
    print(text)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--eval-every", type=int, default=500)
    ap.add_argument("--former-steps", type=int, default=0, help="steps of the former defaults' dev-room runs "
                    "(default: --steps)")
    ap.add_argument("--only", nargs="*", help="names (or prefixes) of the runs to make; default all")
    ap.add_argument("--work", type=Path, default=Path("/tmp/geer_densification"))
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "densification.md")
    ap.add_argument("--records", type=Path, default=ROOT / "benchmarks" / "densification_runs.json")
    ap.add_argument("--minutes", type=float, default=0, help="stop a run after this long (it keeps the points "
                    "it reached); default: no limit")
    ap.add_argument("--again", action="store_true", help="repeat the chosen runs even if their records are kept")
    ap.add_argument("--run", help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    runs = plan(args.work, args.steps, args.former_steps)
    if args.run:
        data, steps, overrides = runs[args.run]
        eval_every = args.eval_every if steps >= args.eval_every else max(steps // 4, 1)
        one_run(args.run, data, steps, overrides, eval_every, args.work)
        return
    from geer_ns.render.cuda_backend import load_cpu_ops

    load_cpu_ops()
    kept = load_records(args.records)
    chosen = [n for n in runs if not args.only or any(n.startswith(o) for o in args.only)]
    for name in chosen:
        outputs = run_files(args.work, name)
        finished = outputs[0].is_file() or (name in kept and "stopped_at" not in kept[name])
        if args.again or not finished:
            for stale in outputs:  # a repeated run's record replaces the former one, even if it is stopped
                stale.unlink(missing_ok=True)
            command = [sys.executable, __file__, "--run", name, "--steps", str(args.steps), "--former-steps",
                       str(args.former_steps), "--eval-every", str(args.eval_every), "--work", str(args.work)]
            source = ROOT
            if is_former(runs[name][2]):
                source = former_source(args.work)
                print(f"[{name}] trains with geer_ns at git tag {FORMER_TAG} ({source}): the former signal is no "
                      "longer in this checkout", flush=True)
            try:
                subprocess.run(command, check=True, env=dict(os.environ, PYTHONPATH=str(source),
                                                              **{SOURCE_ENV: str(source)}),
                               timeout=args.minutes * 60 if args.minutes else None)
            except subprocess.TimeoutExpired:  # the run keeps the points it reached (its .partial.json)
                print(f"[{name}] stopped after {args.minutes} minutes", flush=True)
    records = load_records(args.records)
    for n in runs:  # this work dir's finished runs, or what a stopped run had reached
        done, partial = run_files(args.work, n)
        found = done if done.is_file() else partial if partial.is_file() else None
        if found is not None:
            record = json.loads(found.read_text())
            for key, here in (("commit", git_commit), ("machine_session", machine_session)):
                record.setdefault(key, records.get(n, {}).get(key) or here())  # a record from before they were kept
            if found is done:
                record.pop("stopped_at", None)
            records[n] = record
    keep_records(args.records, records, runs)
    write(args.out, list(load_records(args.records).values()), runs, args)


if __name__ == "__main__":
    main()
