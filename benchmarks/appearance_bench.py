"""Exposure / white balance / vignetting compensation on the dev fisheye room (geer_ns/refinement/appearance.py).

The dev room at --size^2 gets per-frame exposure (+-0.7 stops) and white balance (sigma 0.15) and a
cos(theta/2)^4 vignetting, in linear light (benchmarks/appearance_variant.py; the test frames keep the
neutral exposure, the vignetting is the camera's). Two runs of --steps steps from the same seed: without
compensation and with --pipeline.model.appearance exposure; both scored on the test split as ns-eval does
(plain PSNR / SSIM and the colour-corrected psnr_cc / ssim_cc). Writes benchmarks/appearance.md.

    python benchmarks/appearance_bench.py [--size 80] [--steps 1000] [--work /tmp/geer_appearance]
"""

from __future__ import annotations

from refinement_runs import ROOT, bench_args, dump, fresh, git_commit, load_average, small_dev_room, train_and_score


def main() -> None:
    args = bench_args(__doc__, 1000, "/tmp/geer_appearance")
    from benchmarks.appearance_variant import make_variant

    clean = small_dev_room(args.work, args.size)
    variant = fresh(args.work / f"exposure_{args.size}")
    make_variant(clean.parent, variant, transforms=clean.name)
    schedule = {"warmup_length": 300, "refine_every": 100, "stop_split_at": 1000, "num_downscales": 0,
                "use_scale_regularization": False}
    runs = {"no compensation": {}, "appearance exposure": {"appearance": "exposure"}}
    rows, record = [], {"commit": git_commit(), "size": args.size, "steps": args.steps, "runs": {}}
    for name, overrides in runs.items():
        metrics, seconds, _ = train_and_score(name.replace(" ", "_"), variant / clean.name, args.steps,
                                              {**schedule, **overrides}, args.work)
        record["runs"][name] = {"seconds": seconds, **{k: metrics[k] for k in ("psnr", "ssim", "psnr_cc", "ssim_cc")}}
        rows.append(f"| {name} | {metrics['psnr']:.2f} | {metrics['ssim']:.3f} | {metrics['psnr_cc']:.2f} | "
                    f"{metrics['ssim_cc']:.3f} | {seconds:.0f} |")
        print(rows[-1], flush=True)
    dump(ROOT / "benchmarks" / "appearance_runs.json", record)
    report = f"""# Exposure, white balance and vignetting compensation

- data: the dev fisheye room at {args.size}x{args.size} (`benchmarks/refinement_runs.small_dev_room`), through
  `benchmarks/appearance_variant.py` (per-frame exposure +-0.7 stops, white balance sigma 0.15, vignetting
  cos(theta/2)^4, in linear light; test frames at neutral exposure, with the camera's vignetting)
- runs: {args.steps} steps each, warm-up 300, refinement every 100 until step 1000, full resolution, same seed;
  scored on the test split (6 views) as ns-eval does (valid pixels; psnr_cc / ssim_cc after a per-image affine
  colour fit to the ground truth: geer_ns/metrics/color_corrected.py)
- device: CPU, 2 cores shared with other jobs (load average {load_average()} when written; one run each)
- commit: {record['commit']} (+ the working tree that adds this file)
- command: `python benchmarks/appearance_bench.py --size {args.size} --steps {args.steps}`

| run | PSNR | SSIM | psnr_cc | ssim_cc | training s |
| --- | ---: | ---: | ---: | ---: | ---: |
""" + "\n".join(rows) + "\n"
    (ROOT / "benchmarks" / "appearance.md").write_text(report)
    print(report)


if __name__ == "__main__":
    main()
