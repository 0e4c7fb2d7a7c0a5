"""What the cone test's pre-reject saves: the CPU build's association and forward render with the cone test as it
was (BEFORE_COMMIT: every box survivor through the eigen-decomposition and the Newton steps) and as it is (a bound
without division settles most far pairs first; docs/association.md), the box test alone for reference; pairs
listed and the largest image difference between the builds. Same inputs, one process, median of --repeats runs.

Cases: 512^2 equidistant fisheyes (180 degrees across the inscribed circle, its own pixels, 16-pixel tiles) on the
trained donut (../shared/data/donut_3dgs.ply), 200k synthetic Gaussians around the camera and the dev room's
seed points (kNN scales, opacity 0.1), and a 90-degree pinhole on the donut.

    .venv/bin/python benchmarks/cone_test_cost.py --out benchmarks/cone_test_cost.md
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from benchmarks.timing import median_seconds  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
BEFORE_COMMIT = "ead17dd"  # main with the cone test, before its pre-reject


def load_before_ops():
    """The CPU build of csrc/ at BEFORE_COMMIT, as a second extension."""
    from geer_ns.render.extensions import _CPU_SOURCES, build_and_load, cpu_cflags

    src = Path(tempfile.mkdtemp(prefix="geer_cone_before_"))
    subprocess.run(f"git archive {BEFORE_COMMIT} csrc | tar -x -C {src}", shell=True, cwd=ROOT, check=True)
    return build_and_load("geer_cpu_ops_cone_before", [src / "csrc" / s for s in _CPU_SOURCES], cuda=False,
                          cflags=cpu_cflags(), include_dir=src / "csrc")


def pinhole_grid(size: int = 512, fov_deg: float = 90.0):
    from geer_ns.cameras import PinholeCamera
    from geer_ns.render import RayGrid

    f = (size / 2) / math.tan(math.radians(fov_deg / 2))
    dirs, valid = PinholeCamera(size, size, f, f, size / 2, size / 2).pixel_rays(torch.float32)
    return RayGrid.from_rays(dirs, valid, tile_size=16)


def cases():
    """(name, grid, means, quats, scales, opacities, colours, viewmat) per case."""
    from bench_cpu_renderer import load_3dgs_ply, look_at_viewmat
    from bench_gpu import load_scene
    from cpu_association import dev_room_case, fisheye_grid

    fish = fisheye_grid()
    means, quats, scales, opac, sh_dc = load_3dgs_ply(DATA / "donut_3dgs.ply")
    colors = (0.28209479177387814 * sh_dc[:, 0] + 0.5).clamp_min(0.0)  # SH band 0 as RGB
    donut_view = look_at_viewmat(means, 2.2)
    yield "donut, fisheye 180", fish, means, quats, scales, opac, colors, donut_view
    yield "donut, pinhole 90", pinhole_grid(), means, quats, scales, opac, colors, donut_view
    s = load_scene({"kind": "synthetic", "name": "synthetic", "n": 200_000, "seed": 0}, None)
    yield ("synthetic 200k, fisheye 180", fish, s.means, s.quats, s.scales, s.opacities,
           torch.rand(s.means.shape[0], 3, generator=torch.Generator().manual_seed(0)), s.viewmat)
    *_, scene = dev_room_case(with_scene=True)
    m, q, sc, o, v = scene
    yield ("dev room seed points, fisheye 180", fish, m, q, sc, o,
           torch.rand(m.shape[0], 3, generator=torch.Generator().manual_seed(0)), v)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "cone_test_cost.md")
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    from geer_ns.render import preprocess
    from geer_ns.render.cuda_backend import associate_pairs, load_cpu_ops, render_cuda

    after, before = load_cpu_ops(), load_before_ops()
    rows = []
    for name, grid, means, quats, scales, opac, colors, viewmat in cases():
        with torch.no_grad():
            pre = preprocess(means, quats, scales, opac, colors, viewmat)
            p = pre.pbf
            bounds = torch.stack([p.theta_lo, p.theta_hi, p.phi_lo, p.phi_hi], -1).contiguous()

            def assoc(ops, cone):
                return lambda: associate_pairs(ops, bounds, p.alive, pre.depth, grid, cone)

            def forward(ops):
                return lambda: render_cuda(means, quats, scales, opac, colors, viewmat, grid, ops=ops)

            pairs = {k: int(assoc(ops, cone)()[2].sum()) for k, ops, cone in
                     (("box", after, None), ("before", before, p.cone), ("after", after, p.cone))}
            ms = {k: 1e3 * median_seconds(assoc(ops, cone), args.repeats) for k, ops, cone in
                  (("box", after, None), ("before", before, p.cone), ("after", after, p.cone))}
            fwd = {k: 1e3 * median_seconds(forward(ops), args.repeats) for k, ops in (("before", before), ("after", after))}
            diff = float((forward(before)().rgb - forward(after)().rgb).abs().max())
        tiles = int(grid.tile_active.sum())
        rows.append(f"| {name} | {means.shape[0]:,} | {pairs['box'] / tiles:.1f} | {pairs['before'] / tiles:.1f} | "
                    f"{pairs['after'] / tiles:.1f} | {ms['box']:.1f} | {ms['before']:.1f} | {ms['after']:.1f} | "
                    f"{ms['before'] / ms['after']:.2f}x | {fwd['before']:.0f} / {fwd['after']:.0f} | {diff:.1e} |")
        print(rows[-1], flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    text = f"""# The cone test's pre-reject: association and forward time on the CPU build

- device: CPU, {platform.machine()}, {os.cpu_count()} cores shared with other jobs (load average
  {os.getloadavg()[0]:.1f} when written), torch {torch.__version__}; only the ratios within this run mean anything
- commit: {commit} (before: {BEFORE_COMMIT}'s csrc built as a second extension, same process, same inputs)
- command: `.venv/bin/python benchmarks/cone_test_cost.py --repeats {args.repeats}`
- pairs per active tile: box = the (theta, phi) box test alone; before / after = box + cone test without / with
  the pre-reject. Times: median of {args.repeats} runs after a warm-up, ms: the association (count and emit
  passes, sort) and the whole forward (preprocess, association, render). Image diff: the largest |rgb before -
  rgb after| (float32).

| case | Gaussians | pairs / tile, box | before | after | association ms, box | before | after | association speed-up | forward ms, before / after | image diff |
| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |
{chr(10).join(rows)}
"""
    args.out.write_text(text)
    print(json.dumps({"out": str(args.out)}))


if __name__ == "__main__":
    main()
