"""Render forward and backward on the CPU build with the per-warp and per-ray cull (csrc/geer_math.h
ray_meets_pbf at AFTER_COMMIT) against the same stage without it: main's csrc at BEFORE_COMMIT (the transposing
warp reduction already in, no cull, every lane of the warp emulation through the butterfly). Each is built as an
extension of its own and run in the same process on the same inputs (preprocess and association from the
current build).

Cases: the dev fisheye room's BEAP training view with its 20k seed points as Gaussians (kNN scales, opacity 0.1:
faint and large, a training start) and the trained donut in a 512x512 equidistant fisheye (cpu_association.py).

    .venv/bin/python benchmarks/cpu_render_cull.py --out benchmarks/cpu_render_cull.md
"""

from __future__ import annotations

import argparse
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
from cpu_association import dev_room_case, donut_case  # noqa: E402

BEFORE_COMMIT = "1c7ac91"  # main before the cull
AFTER_COMMIT = "5dc2d15"  # main with the cull (before the packs of benchmarks/cpu_render_packs.py)


def load_before_ops(commit: str = BEFORE_COMMIT, headers=("geer_math.h", "geer_associate.h", "geer_blocks.h"),
                    cflags=("-O2", "-ffp-contract=off")):
    """main's CPU build at `commit`, built as a second extension (its own name and build folder)."""
    from torch.utils import cpp_extension

    name = f"geer_cpu_ops_{commit}"
    src = Path(tempfile.mkdtemp(prefix=f"{name}_"))
    for file in ("cpu_ops.cpp", *headers):
        blob = subprocess.run(["git", "show", f"{commit}:csrc/{file}"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout
        (src / file).write_text(blob)
    build = ROOT / ".cache" / "geer_ext" / name
    build.mkdir(parents=True, exist_ok=True)
    return cpp_extension.load(name=name, sources=[str(src / "cpu_ops.cpp")], extra_cflags=list(cflags),
                              extra_include_paths=[str(src)], build_directory=str(build))


def stage_inputs(case):
    """Stage-3 inputs of one view from the current build: per-Gaussian frames, lists, a loss gradient."""
    from geer_ns.render import preprocess
    from geer_ns.render.associate import pbf_cull_pieces
    from geer_ns.render.cuda_backend import associate_pairs, load_cpu_ops

    name, grid, bounds, alive, depth, scene = case
    means, quats, scales, opac, viewmat = scene
    ops = load_cpu_ops()
    with torch.no_grad():
        pre = preprocess(means, quats, scales, opac, means.new_full((means.shape[0], 3), 0.5), viewmat)
    ids, ranges, counts, _ = associate_pairs(ops, bounds, alive, depth, grid)
    f = torch.float32
    common = dict(whiten=pre.whiten.to(f).contiguous(), o_u=pre.o_u.to(f).contiguous(),
                  rgb=pre.colors.to(f).contiguous(), opac=opac.to(f).contiguous(), dirs=grid.dirs.to(f).contiguous(),
                  valid=grid.valid.contiguous(), ids=ids, ranges=ranges, layout=(grid.height, grid.width, grid.tile_size))
    cull = (pbf_cull_pieces(bounds.to(f)), grid.ray_cull_bounds(f), grid.warp_cull_bounds(f))
    r = grid.num_rays
    g = torch.Generator().manual_seed(0)
    grads = (torch.rand(r, 3, generator=g), torch.rand(r, generator=g), torch.rand(r, generator=g))
    return name, grid, int(counts.sum()), common, cull, grads


def meet_fraction(grid, ids, ranges, pieces, rays, chunk: int = 4096) -> float:
    """Of the (valid ray, tile-list entry) pairs the render stage visits, the fraction whose ray meets the
    Gaussian's PBF (geer_ray.h ray_meets_pbf, with the twin's overlap test): the rest the cull skips."""
    from geer_ns.render.associate import _overlaps

    tile_of = torch.repeat_interleave(torch.arange(grid.num_tiles), (ranges[:, 1] - ranges[:, 0]).long())
    meet = total = 0
    for j0 in range(0, ids.numel(), chunk):
        g, t = ids[j0:j0 + chunk].long(), tile_of[j0:j0 + chunk]
        r = grid.tile_rays[t]  # [P, tile rays]
        ok = (r >= 0) & grid.valid[r.clamp_min(0)]
        b = rays[r.clamp_min(0)]  # [P, tile rays, 4]
        p = pieces[g][:, None, :]
        hit = _overlaps(b[..., 0], b[..., 1], p[..., 0:4].unbind(-1))
        hit &= _overlaps(b[..., 2], b[..., 3], p[..., 4:8].unbind(-1))
        meet += int((hit & ok).sum())
        total += int(ok.sum())
    return meet / max(total, 1)


def run_after(ops, c, cull, grads):
    fwd = ops.render_forward(c["whiten"], c["o_u"], c["rgb"], c["opac"], cull[0], c["dirs"], cull[1], cull[2],
                             c["valid"], c["ids"], c["ranges"], *c["layout"])
    bwd = lambda: ops.render_backward(c["whiten"], c["o_u"], c["rgb"], c["opac"], cull[0], c["dirs"], cull[1],  # noqa: E731
                                      cull[2], c["valid"], c["ids"], c["ranges"], *c["layout"], fwd[3], fwd[4], *grads)
    return fwd, bwd


def run_before(ops, c, grads):
    fwd = ops.render_forward(c["whiten"], c["o_u"], c["rgb"], c["opac"], c["dirs"], c["valid"], c["ids"],
                             c["ranges"], *c["layout"])
    bwd = lambda: ops.render_backward(c["whiten"], c["o_u"], c["rgb"], c["opac"], c["dirs"], c["valid"],  # noqa: E731
                                      c["ids"], c["ranges"], *c["layout"], fwd[3], fwd[4], *grads)
    return fwd, bwd


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "cpu_render_cull.md")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    # Both sides are main's csrc at their commits (the render stage's signature has moved on since).
    ops, before = load_before_ops(AFTER_COMMIT), load_before_ops()
    rows = []
    for case in (dev_room_case(with_scene=True), donut_case(with_scene=True)):
        name, grid, pairs, c, cull, grads = stage_inputs(case)
        fwd_a, bwd_a = run_after(ops, c, cull, grads)
        fwd_b, bwd_b = run_before(before, c, grads)
        same_fwd = all(torch.equal(a, b) for a, b in zip(fwd_a, fwd_b))
        same_bwd = torch.equal(bwd_a(), bwd_b())
        meets = meet_fraction(grid, c["ids"], c["ranges"], cull[0], cull[1])
        t = [median_seconds(fn, args.repeats) for fn in (
            lambda: run_before(before, c, grads), lambda: run_after(ops, c, cull, grads), bwd_b, bwd_a)]
        rows.append(f"| {name} | {c['whiten'].shape[0]} | {grid.height}x{grid.width} | {pairs} | {100 * meets:.1f} % | "
                    f"{1e3 * t[0]:.1f} | {1e3 * t[1]:.1f} | {t[0] / t[1]:.2f}x | {1e3 * t[2]:.1f} | {1e3 * t[3]:.1f} | "
                    f"{t[2] / t[3]:.2f}x | {'yes' if same_fwd and same_bwd else 'NO'} |")
        print(rows[-1], flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    args.out.write_text(f"""# Render stage on the CPU build: with the per-warp and per-ray cull vs without

- device: CPU, {platform.machine()}, {torch.get_num_threads()} threads; torch {torch.__version__}
- commit: {commit.strip()} (before: {BEFORE_COMMIT}, after: {AFTER_COMMIT}, main's csrc at each built as an
  extension of its own, same process)
- command: `.venv/bin/python benchmarks/cpu_render_cull.py`
- float32, tile size 16; stage 3 only (render_forward; render_backward with a fixed random loss gradient) on
  the same frames and tile lists; time: median of {args.repeats} runs after a warm-up. "Same bits": forward
  outputs and backward gradient rows bitwise equal between the two builds. "Rays meeting the PBF": of the
  (valid ray, tile-list entry) pairs of the view, those the per-ray cull does not skip.

| case | Gaussians | grid | tile-list pairs | rays meeting the PBF | forward ms before | after | speed-up | backward ms before | after | speed-up | same bits |
| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |
""" + "\n".join(rows) + "\n")
    print(args.out.read_text())


if __name__ == "__main__":
    main()
