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

    .venv/bin/python benchmarks/error_vs_time.py --run /tmp/i29/train/room128/geer/t
writes benchmarks/error_vs_time.md and benchmarks/error_vs_time.png.
"""

from __future__ import annotations

import argparse
import math
import platform
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
SIZE, TILE = 256, 16


def cameras():
    """name -> (RayGrid, gsplat camera model, focal in pixels, field of view in degrees)."""
    from geer_ns.render import RayGrid

    c = (torch.arange(SIZE, dtype=torch.float64) + 0.5) - SIZE / 2
    v, u = torch.meshgrid(c, c, indexing="ij")
    out = {}
    for fov in (60.0, 120.0, 180.0):
        f = (SIZE / 2) / math.radians(fov / 2)
        ang, psi = torch.sqrt(u * u + v * v) / f, torch.atan2(v, u)
        dirs = torch.stack([ang.sin() * psi.cos(), ang.sin() * psi.sin(), ang.cos()], -1)
        grid = RayGrid.from_rays(dirs.float(), ang <= math.radians(fov / 2), TILE)
        out[f"fisheye {fov:.0f}"] = (grid, "fisheye", f, fov)
    for fov in (60.0, 120.0):
        f = (SIZE / 2) / math.tan(math.radians(fov / 2))
        dirs = torch.nn.functional.normalize(torch.stack([u / f, v / f, torch.ones_like(u)], -1), dim=-1)
        out[f"pinhole {fov:.0f}"] = (RayGrid.from_rays(dirs.float(), None, TILE), "pinhole", f, fov)
    return out


def geer_image(ops, scene, viewmat, grid, dtype, paper_lambda: bool):
    """(rgb [R,3] float64, seconds) of the CPU build's forward (preprocess, association, render)."""
    from geer_ns.render.associate import pbf_cull_pieces
    from geer_ns.render.cones import gaussian_cone_form
    from geer_ns.render.cuda_backend import associate_pairs
    from geer_ns.render.pbf import pbf_lambda_sq

    means, quats, scales, opac, colors = (t.to(dtype) for t in scene)
    vm = viewmat.to(dtype)
    start = time.perf_counter()
    with torch.no_grad():
        rot = vm[:3, :3].contiguous()
        means_c = (means @ rot.T + vm[:3, 3]).contiguous()
        w, o_u, _, bounds, alive, inside = ops.preprocess_forward(
            means_c, quats, scales, opac, means.new_zeros(means.shape[0], 0, 3), means_c, rot, -1, paper_lambda)
        lam2 = pbf_lambda_sq(opac, "paper" if paper_lambda else "opacity")[0]
        form = gaussian_cone_form(w, o_u, lam2, inside)
        ids, ranges, _, _ = associate_pairs(ops, bounds, alive, means_c.norm(dim=-1), grid, form)
        rgb, *_ = ops.render_forward(w, o_u, colors.contiguous(), opac, pbf_cull_pieces(bounds), grid.dirs.to(dtype),
                                     grid.ray_cull_bounds(dtype), grid.warp_cull_bounds(dtype), grid.valid, ids, ranges,
                                     grid.height, grid.width, grid.tile_size, False)
    return rgb.double(), time.perf_counter() - start


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
    from association_tightness import load_scene, test_viewmat

    from geer_ns.render.cuda_backend import load_cpu_ops

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a geer run's output folder (checkpoint inside)")
    args = parser.parse_args()
    ops = load_cpu_ops()
    *scene, step = load_scene(args.run)
    viewmat = test_viewmat(args.run)
    rows = []
    for name, (grid, kind, focal, fov) in cameras().items():
        ref, _ = geer_image(ops, scene, viewmat, grid, torch.float64, False)
        valid = grid.valid
        row = {"name": name, "fov": fov, "kind": kind}
        for label, paper in (("geer", False), ("geer paper lambda", True)):
            geer_image(ops, scene, viewmat, grid, torch.float32, paper)  # warm-up
            times = []
            for _ in range(3):
                img, t = geer_image(ops, scene, viewmat, grid, torch.float32, paper)
                times.append(t)
            row[label] = (float((img - ref)[valid].abs().max()), _psnr(img, ref, valid), sorted(times)[1])
        for label, eps2d in (("EWA", 0.3), ("EWA eps2d 0", 0.0)):
            img = ewa_image(scene, viewmat, kind, focal, eps2d)
            row[label] = (float((img - ref)[valid].abs().max()), _psnr(img, ref, valid), None)
        rows.append(row)
        print(row, flush=True)
    write(args, rows, scene, step)


def write(args, rows, scene, step) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout
    out = ROOT / "benchmarks" / "error_vs_time.md"
    lines = [
        "# Run time against error: geer's CPU build and EWA splatting against the float64 exact image",
        "",
        f"- device: CPU, {platform.machine()}, 2 cores shared with other sessions (times: median of 3 after a "
        f"warm-up, noisy); torch {torch.__version__}",
        f"- commit: {commit.strip()} (+ the working tree at the time of the run)",
        f"- command: `.venv/bin/python benchmarks/error_vs_time.py --run {args.run}`",
        f"- scene: the dev room trained by `ns-train geer` on its 128^2 fisheye views to step {step} "
        f"({scene[0].shape[0]:,} Gaussians, colours: SH band 0); first held-out pose; {SIZE} x {SIZE} rays, "
        "equidistant fisheyes (field of view across the inscribed circle) and pinholes.",
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
    lines += ["", "![PSNR against the exact image](error_vs_time.png)", ""]
    out.write_text("\n".join(lines))
    fig, ax = plt.subplots(figsize=(6, 4))
    for kind, marker in (("fisheye", "o"), ("pinhole", "s")):
        sel = [r for r in rows if r["kind"] == kind]
        fovs = [r["fov"] for r in sel]
        for label, color in (("geer", "C0"), ("geer paper lambda", "C1"), ("EWA", "C3"), ("EWA eps2d 0", "C2")):
            ax.plot(fovs, [min(r[label][1], 100.0) for r in sel], marker=marker, color=color,
                    linestyle="-" if kind == "fisheye" else "--", label=f"{label} ({kind})")
    ax.set_xlabel("field of view (degrees)")
    ax.set_ylabel("PSNR against the float64 exact image (dB, capped at 100)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(ROOT / "benchmarks" / "error_vs_time.png", dpi=100)
    print(out.read_text())


if __name__ == "__main__":
    main()
