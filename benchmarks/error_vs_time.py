"""Run time against error: what exactness buys at each field of view. For the trained dev room's Gaussians (colours:
SH band 0) seen from its first held-out pose, equidistant fisheyes of 60, 120 and 180 degrees and pinholes of 60 and
120 degrees at 256^2: each renderer's image against the float64 exact reference (geer's CPU build in float64, the
opacity lambda rule: every pair with alpha >= 1/255), beside geer's forward time on the CPU build.

    geer (opacity lambda)  the CPU build in float32, the default rule (complete association)
    geer (paper lambda)    the CPU build in float32 with lambda = 3 (paper Sec. 3.2: misses opaque Gaussians' tails)
    EWA                    gsplat 1.4's own projection (gsplat.cuda._torch_impl._fully_fused_projection, pinhole or
                           equidistant-fisheye Jacobian, eps2d 0.3, 3-sigma radius), composited per pixel in depth
                           order by the loop below (3DGS's rule: alpha = min(0.99, o exp(-power)), skip alpha < 1/255,
                           stop before T < 1e-4); gsplat's rasterizer needs CUDA, its PyTorch reference too. With
                           gsplat's default 2-D dilation (eps2d 0.3, as splatfacto renders) and without it (eps2d 0:
                           the projection's own error).

    python -m benchmarks.error_vs_time --run RUN     # RUN: a geer run on the dev room (docs/benchmarks.md)
writes benchmarks/error_vs_time.md.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch

from benchmarks.association_tightness import equidistant_rays, load_scene, test_viewmat
from benchmarks.common import BENCHMARKS, header

SIZE, TILE = 256, 16


def cameras():
    """name -> (RayGrid, gsplat camera model, focal in pixels, field of view in degrees)."""
    from geer_ns.render import RayGrid

    out = {}
    for fov in (60.0, 120.0, 180.0):
        dirs, valid, f = equidistant_rays(fov, SIZE)
        out[f"fisheye {fov:.0f}"] = (RayGrid.from_rays(dirs, valid, TILE), "fisheye", f, fov)
    c = (torch.arange(SIZE, dtype=torch.float64) + 0.5) - SIZE / 2
    v, u = torch.meshgrid(c, c, indexing="ij")
    for fov in (60.0, 120.0):
        f = (SIZE / 2) / math.tan(math.radians(fov / 2))
        dirs = torch.nn.functional.normalize(torch.stack([u / f, v / f, torch.ones_like(u)], -1), dim=-1)
        out[f"pinhole {fov:.0f}"] = (RayGrid.from_rays(dirs.float(), None, TILE), "pinhole", f, fov)
    return out


def geer_image(scene, viewmat, grid, dtype, lambda_mode: str):
    """(rgb [R,3] float64, seconds) of geer's forward on the CPU build (no background)."""
    from geer_ns.render import render

    tensors = [t.to(dtype) for t in scene]
    start = time.perf_counter()
    with torch.no_grad():
        out = render(*tensors, viewmat.to(dtype), grid, background=tensors[0].new_zeros(3), lambda_mode=lambda_mode,
                     backend="cpu")
    return out.rgb.reshape(-1, 3).double(), time.perf_counter() - start


def ewa_image(scene, viewmat, kind: str, focal: float, eps2d: float = 0.3) -> torch.Tensor:
    """[R,3] float64: gsplat's EWA projection (eps2d: its 2-D dilation) composited per pixel, tile by tile."""
    from geer_ns.gsplat_private import fully_fused_projection

    from geer_ns.render import quat_to_rotmat

    means, quats, scales, opac, colors = scene
    m = quat_to_rotmat(quats) * scales[:, None, :]
    k = torch.tensor([[focal, 0, SIZE / 2], [0, focal, SIZE / 2], [0, 0, 1]], dtype=torch.float32)
    radii, means2d, depths, conics, _ = fully_fused_projection(means, m @ m.transpose(-1, -2), viewmat[None], k[None],
                                                               SIZE, SIZE, eps2d=eps2d, camera_model=kind)
    radii, means2d, depths, conics = radii[0].double(), means2d[0].double(), depths[0].double(), conics[0].double()
    keep = (radii > 0) & (opac >= 1 / 255)
    order = torch.nonzero(keep).squeeze(1)
    order = order[torch.argsort(depths[order], stable=True)]
    out = torch.zeros(SIZE, SIZE, 3, dtype=torch.float64)
    tiles = SIZE // TILE
    for ty in range(tiles):
        for tx in range(tiles):
            x0, y0 = tx * TILE, ty * TILE
            mu, r = means2d[order], radii[order][:, None]
            hit = ((mu[:, 0] + r[:, 0] > x0) & (mu[:, 0] - r[:, 0] < x0 + TILE) & (mu[:, 1] + r[:, 0] > y0)
                   & (mu[:, 1] - r[:, 0] < y0 + TILE))
            g = order[hit]
            if g.numel() == 0:
                continue
            py, px = torch.meshgrid(torch.arange(y0, y0 + TILE, dtype=torch.float64) + 0.5,
                                    torch.arange(x0, x0 + TILE, dtype=torch.float64) + 0.5, indexing="ij")
            dx = means2d[g][:, 0, None, None] - px  # [G, T, T]
            dy = means2d[g][:, 1, None, None] - py
            a, b, c = (conics[g][:, i, None, None] for i in range(3))
            power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
            alpha = (opac.double()[g][:, None, None] * torch.exp(power)).clamp_max(0.99)
            alpha = torch.where((power <= 0) & (alpha >= 1 / 255), alpha, torch.zeros_like(alpha))
            # Front to back: T after each Gaussian is non-increasing, so "stop before T < 1e-4" keeps exactly the
            # Gaussians whose T after is still >= 1e-4 (every later one is below too).
            after = torch.cumprod(1 - alpha, 0)
            before = torch.cat([torch.ones_like(after[:1]), after[:-1]])
            weight = torch.where((alpha > 0) & (after >= 1e-4), alpha * before, torch.zeros_like(alpha))
            out[y0:y0 + TILE, x0:x0 + TILE] = torch.einsum("gyx,gc->yxc", weight, colors.double()[g])
    return out.reshape(-1, 3)


def _psnr(img: torch.Tensor, ref: torch.Tensor, valid: torch.Tensor) -> float:
    mse = float((img - ref)[valid].square().mean())
    return 10 * math.log10(1.0 / mse) if mse > 0 else math.inf


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a geer run's output folder (checkpoint inside)")
    args = parser.parse_args()
    *scene, step = load_scene(args.run)
    viewmat = test_viewmat(args.run)
    rows = []
    for name, (grid, kind, focal, fov) in cameras().items():
        ref, _ = geer_image(scene, viewmat, grid, torch.float64, "opacity")
        valid = grid.valid.reshape(-1)
        row = {"name": name, "fov": fov, "kind": kind}
        for label, rule in (("geer", "opacity"), ("geer paper lambda", "paper")):
            geer_image(scene, viewmat, grid, torch.float32, rule)  # warm-up
            times = []
            for _ in range(3):
                img, t = geer_image(scene, viewmat, grid, torch.float32, rule)
                times.append(t)
            row[label] = (float((img - ref)[valid].abs().max()), _psnr(img, ref, valid), sorted(times)[1])
        for label, eps2d in (("EWA", 0.3), ("EWA eps2d 0", 0.0)):
            img = ewa_image(scene, viewmat, kind, focal, eps2d)
            row[label] = (float((img - ref)[valid].abs().max()), _psnr(img, ref, valid), None)
        rows.append(row)
        print(row, flush=True)
    write(args, rows, scene, step)


def write(args, rows, scene, step) -> None:
    out = BENCHMARKS / "error_vs_time.md"
    lines = [
        header("Run time against error: geer's CPU build and EWA splatting against the float64 exact image",
               "times: median of 3 after a warm-up",
               f"scene: the dev room trained by `ns-train geer` on its 128^2 fisheye views to step {step} "
               f"({scene[0].shape[0]:,} Gaussians, colours: SH band 0); first held-out pose; {SIZE} x {SIZE} rays, "
               "equidistant fisheyes (field of view across the inscribed circle) and pinholes."),
        "- reference: geer's CPU build in float64 with the opacity lambda rule (every pair with alpha >= 1/255); "
        "errors over the camera's valid pixels, colours in [0, 1], no background. EWA: gsplat 1.4's projection "
        "composited per pixel (see the script); its time is not given (a Python loop, not gsplat's rasterizer).",
        "",
        "| camera | geer max abs err | geer PSNR vs exact | geer ms | geer paper-lambda max abs err | PSNR | ms | "
        "EWA max abs err | EWA PSNR vs exact | EWA eps2d 0: max abs err | PSNR |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        g, p, e, e0 = r["geer"], r["geer paper lambda"], r["EWA"], r["EWA eps2d 0"]
        lines.append(f"| {r['name']} | {g[0]:.1e} | {g[1]:.1f} | {1e3 * g[2]:.0f} | {p[0]:.1e} | {p[1]:.1f} | "
                     f"{1e3 * p[2]:.0f} | {e[0]:.2f} | {e[1]:.1f} | {e0[0]:.2f} | {e0[1]:.1f} |")
    out.write_text(lines[0] + "\n".join(lines[1:]) + "\n")
    print(out.read_text())


if __name__ == "__main__":
    main()
