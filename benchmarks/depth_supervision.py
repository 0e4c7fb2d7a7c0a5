"""Depth supervision on the synthetic room: the same geer training with and without its ground-truth distances.

The room (geer_ns.data.synthetic_room, 180-degree fisheye) gets radial distance maps from its analytic ray caster
(geer_ns.data.synthetic_depth); both runs train on transforms_fisheye_depth.json from the same seed for the same
steps, one with --pipeline.model.depth-loss-weight 0. Figures on the held-out test views (ns-eval's metrics):
distance RMSE against the ray caster (dataparser units) and PSNR. One process, both runs in it.

    python -m benchmarks.depth_supervision [--steps 600] [--size 64] [--views 16]    # writes benchmarks/depth_supervision.md
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from benchmarks.common import BENCHMARKS, header, run_config, train_and_score


def run(room: Path, out: Path, name: str, steps: int, weight: float) -> dict:
    config = run_config(room / "transforms_fisheye_depth.json", out, name, steps, {
        "depth_loss_weight": weight, "warmup_length": steps // 4, "refine_every": max(steps // 8, 1),
        "stop_split_at": steps, "renderer_backend": "cpu", "num_downscales": 1, "resolution_schedule": 1_000_000})
    config.machine.seed = 42
    metrics, seconds, pipeline = train_and_score(config)
    return {"name": name, "weight": weight, "seconds": seconds, "gaussians": pipeline.model.num_points,
            **{k: metrics[k] for k in ("psnr", "distance_rmse", "depth_rmse") if k in metrics}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--weight", type=float, default=0.2)
    args = ap.parse_args()
    from geer_ns.data.synthetic_depth import write_depth_variant
    from geer_ns.data.synthetic_room import generate_room

    tmp = Path(tempfile.mkdtemp(prefix="geer_depth_bench_"))
    room = generate_room(tmp / "room", n_views=args.views, image_size=args.size)
    write_depth_variant(room, "fisheye")
    rows = [run(room, tmp / "runs", "rgb_only", args.steps, 0.0),
            run(room, tmp / "runs", "with_depth", args.steps, args.weight)]
    lines = [
        header("Depth supervision on the synthetic room",
               f"180-degree fisheye room, {args.views} views of {args.size}x{args.size} (every 8th held out for test), "
               f"{args.steps} steps each, same seed; distances are the room's analytic ray caster's (radial, "
               "dataparser units). Depth loss: huber on the relative error, scale 0.05. The first run's time "
               "includes the process's one-time start-up (extension load, caches)."),
        "| run | depth-loss-weight | test distance RMSE | test depth (z) RMSE | test PSNR (dB) | Gaussians | train s |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(f"| {r['name']} | {r['weight']} | {r.get('distance_rmse', float('nan')):.4f} | "
                     f"{r.get('depth_rmse', float('nan')):.4f} | {r['psnr']:.2f} | {r['gaussians']} | "
                     f"{r['seconds']:.0f} |")
    base, depth = rows
    lines += ["", f"Distance RMSE ratio (with / without): {depth['distance_rmse'] / base['distance_rmse']:.3f}; "
              f"PSNR difference: {depth['psnr'] - base['psnr']:+.2f} dB.", ""]
    (BENCHMARKS / "depth_supervision.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
