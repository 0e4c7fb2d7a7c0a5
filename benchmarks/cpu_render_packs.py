"""Render forward and backward on the CPU build: packs of rays (csrc/geer_packs.h, AVX2) with the backward
visiting only the lanes the forward recorded as blending each entry, against the same stage at START_COMMIT
(one ray at a time, the per-warp and per-ray cull in both passes, -O2), built as a second extension and run
in the same process on the same inputs. The current build's one-ray-per-thread path (render_forward_gpu_path /
render_backward_gpu_path: the kernels' orchestration, warp cull only in the backward) is the third column.

Cases as benchmarks/cpu_render_cull.py: the dev fisheye room's BEAP training view with its 20k seed points as
Gaussians, and the trained donut in a 512x512 equidistant fisheye.

    .venv/bin/python benchmarks/cpu_render_packs.py --out benchmarks/cpu_render_packs.md
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from benchmarks.timing import median_seconds  # noqa: E402
from cpu_association import dev_room_case, donut_case  # noqa: E402
from cpu_render_cull import load_before_ops, stage_inputs  # noqa: E402

START_COMMIT = "c693625"  # main before the packs and the forward's record


def render_pair(forward, backward, c, cull, grads, recorded: bool):
    """(forward outputs, a backward call giving the gradient rows) of one stage-3 implementation on the case's
    inputs; recorded: this build's signature (the forward's record argument and output, the backward's
    blended_lanes and absgrad rows)."""
    fwd = forward(c["whiten"], c["o_u"], c["rgb"], c["opac"], cull[0], c["dirs"], cull[1], cull[2], c["valid"],
                  c["ids"], c["ranges"], *c["layout"], *((True,) if recorded else ()))
    record = (fwd[5],) if recorded else ()
    no_absgrad = (c["whiten"].new_zeros(0),) if recorded else ()  # this build's backward: absgrad's rows, empty
    args = (c["whiten"], c["o_u"], c["rgb"], c["opac"], cull[0], c["dirs"], cull[1], cull[2], c["valid"], c["ids"],
            c["ranges"], *c["layout"], fwd[3], fwd[4], *record, *grads, *no_absgrad)
    # This build's backward returns (gradient rows, absgrad); the start's the rows alone.
    return fwd[:5], (lambda: backward(*args)[0]) if recorded else (lambda: backward(*args))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "cpu_render_packs.md")
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    from geer_ns.render.cuda_backend import load_cpu_ops

    ops, start = load_cpu_ops(), load_before_ops(START_COMMIT)
    impls = {
        "start": (start.render_forward, start.render_backward, False),
        "one ray": (ops.render_forward_gpu_path, ops.render_backward_gpu_path, True),
        "packs": (ops.render_forward, ops.render_backward, True),
    }
    rows = []
    for case in (dev_room_case(with_scene=True), donut_case(with_scene=True)):
        name, grid, pairs, c, cull, grads = stage_inputs(case)
        runs = {k: render_pair(*impl[:2], c, cull, grads, impl[2]) for k, impl in impls.items()}
        ref_fwd, ref_bwd = runs["start"][0], runs["start"][1]()
        same = all(all(torch.equal(a, b) for a, b in zip(fwd, ref_fwd)) and torch.equal(bwd(), ref_bwd)
                   for fwd, bwd in runs.values())
        t_fwd = {k: median_seconds(lambda impl=impl: render_pair(*impl[:2], c, cull, grads, impl[2]), args.repeats)
                 for k, impl in impls.items()}
        t_bwd = {k: median_seconds(bwd, args.repeats) for k, (_, bwd) in runs.items()}
        cells = [f"{1e3 * t[k]:.1f}" for t in (t_fwd, t_bwd) for k in impls]
        rows.append(f"| {name} | {c['whiten'].shape[0]} | {grid.height}x{grid.width} | {pairs} | "
                    + " | ".join(cells[:3]) + f" | {t_fwd['start'] / t_fwd['packs']:.2f}x | "
                    + " | ".join(cells[3:]) + f" | {t_bwd['start'] / t_bwd['packs']:.2f}x | {'yes' if same else 'NO'} |")
        print(rows[-1], flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    lanes = ops.render_lanes(False)
    args.out.write_text(f"""# Render stage on the CPU build: packs of rays and the forward's record vs one ray at a time

- device: CPU, {platform.machine()}, {torch.get_num_threads()} threads, torch CPU capability
  {torch.backends.cpu.get_cpu_capability()} (packs of {lanes} float32 rays); torch {torch.__version__}
- commit: {commit.strip()} (start: {START_COMMIT}, main's csrc and flags then, built as a second extension, same
  process)
- command: `.venv/bin/python benchmarks/cpu_render_packs.py`
- float32, tile size 16; stage 3 only (render_forward; render_backward with a fixed random loss gradient) on
  the same frames and tile lists; time: median of {args.repeats} runs after a warm-up. Columns: "start" the CPU
  build at {START_COMMIT}; "one ray" this build's one-ray-per-thread path (the kernels' orchestration);
  "packs" this build's CPU path. "Same bits": forward outputs and backward gradient rows of all three
  bitwise equal.

| case | Gaussians | grid | tile-list pairs | forward ms start | one ray | packs | speed-up | backward ms start | one ray | packs | speed-up | same bits |
| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |
""" + "\n".join(rows) + "\n")
    print(args.out.read_text())


if __name__ == "__main__":
    main()
