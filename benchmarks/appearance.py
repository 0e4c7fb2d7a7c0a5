"""Exposure / white balance / vignetting compensation on the dev fisheye room (geer_ns/refinement/appearance.py).

The dev room at --size^2 gets per-frame exposure (+-0.7 stops) and white balance (sigma 0.15) and a
cos(theta/2)^4 vignetting, in linear light (benchmarks/appearance_variant.py; the test frames keep the
neutral exposure, the vignetting is the camera's). Two runs of --steps steps from the same seed: without
compensation and with --pipeline.model.appearance exposure; both scored on the test split as ns-eval does
(plain PSNR / SSIM and the colour-corrected psnr_cc / ssim_cc).

    python -m benchmarks.appearance [--size 80] [--steps 1000]     # writes benchmarks/appearance.md
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from benchmarks.appearance_variant import make_variant
from benchmarks.common import BENCHMARKS, dev_room, header, run_config, short_schedule, train_and_score


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=80)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--work", type=Path, default=Path("/tmp/geer_appearance"))
    args = ap.parse_args()
    clean = dev_room(args.work, args.size) / "transforms_fisheye.json"
    variant = args.work / f"exposure_{args.size}"
    shutil.rmtree(variant, ignore_errors=True)
    make_variant(clean.parent, variant, transforms=clean.name)
    rows = []
    for name, options in {"no compensation": {}, "appearance exposure": {"appearance": "exposure"}}.items():
        options = {**short_schedule(), "use_scale_regularization": False, **options}
        config = run_config(variant / clean.name, args.work / "runs", name.replace(" ", "_"), args.steps, options)
        metrics, seconds, _ = train_and_score(config)
        rows.append(f"| {name} | {metrics['psnr']:.2f} | {metrics['ssim']:.3f} | {metrics['psnr_cc']:.2f} | "
                    f"{metrics['ssim_cc']:.3f} | {seconds:.0f} |")
        print(rows[-1], flush=True)
    text = header(
        "Exposure, white balance and vignetting compensation",
        f"data: the dev fisheye room at {args.size}^2 through benchmarks/appearance_variant.py (per-frame exposure "
        "+-0.7 stops, white balance sigma 0.15, vignetting cos(theta/2)^4, in linear light; test frames at neutral "
        "exposure, with the camera's vignetting)",
        f"runs: {args.steps} steps each, warm-up 300, densification every 100 steps to step 1000, full resolution, "
        "same seed; scored on the test split (6 views) as ns-eval does (valid pixels; psnr_cc / ssim_cc after a "
        "per-image affine colour fit to the ground truth: geer_ns/metrics/color_corrected.py)",
    ) + ("\n| run | PSNR | SSIM | psnr_cc | ssim_cc | training s |\n| --- | ---: | ---: | ---: | ---: | ---: |\n"
         + "\n".join(rows) + "\n")
    (BENCHMARKS / "appearance.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
