"""A tiny forward + backward through every CUDA kernel, for compute-sanitizer (gpu_session.sh call 1).

Three cases cover both render builds (256- and 1024-thread blocks), warp padding, inactive tiles (the 180
degree fisheye circle), SH colours and plain RGB, in float32 and float64. Run under memcheck, racecheck and
synccheck with PYTORCH_NO_CUDA_MEMORY_CACHING=1, so that every tensor is its own allocation and an
out-of-bounds access cannot land unseen inside a neighbouring live tensor of the caching allocator.

    compute-sanitizer --tool memcheck python3 benchmarks/gpu_sanitize.py
    python benchmarks/gpu_sanitize.py --device cpu --backend torch     # the same script on the CPU (tests)
Exits 1 when an output or gradient is not finite.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from geer_ns.cameras import OpenCVFisheyeCamera  # noqa: E402
from geer_ns.render import RayGrid, render  # noqa: E402


def cases() -> list[tuple[str, RayGrid, torch.dtype, bool]]:
    """(name, grid, dtype, SH colours)."""
    f = 20 / (math.pi / 2)
    fd, fv = OpenCVFisheyeCamera.equidistant(40, 40, f, f, 20.0, 20.0).pixel_rays()
    fv = fv & (fd[..., 2] >= 0)  # the 180 degree circle: inactive corner tiles
    return [
        ("beap 40x24 tile 16 float32 rgb", RayGrid.beap(40, 24, math.radians(90), math.radians(60), tile_size=16),
         torch.float32, False),
        ("fisheye 40 tile 8 float32 sh1", RayGrid.from_rays(fd, fv, tile_size=8), torch.float32, True),
        ("fisheye 40 tile 20 float64 sh1 (1024-thread build)", RayGrid.from_rays(fd, fv, tile_size=20),
         torch.float64, True),
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--n", type=int, default=200)
    args = ap.parse_args(argv)
    gen = torch.Generator().manual_seed(0)
    n = args.n
    means = torch.randn(n, 3, generator=gen, dtype=torch.float64) * 0.8 + torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    quats = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    scales = torch.exp(math.log(0.05) + math.log(6.0) * torch.rand(n, 3, generator=gen, dtype=torch.float64))
    opacities = 0.05 + 0.9 * torch.rand(n, generator=gen, dtype=torch.float64)
    rgb = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    sh = torch.randn(n, 4, 3, generator=gen, dtype=torch.float64) * 0.3  # SH degree 1
    ok = True
    for name, grid, dtype, use_sh in cases():
        colors = sh if use_sh else rgb
        leaves = [t.to(args.device, dtype).requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
        viewmat = torch.eye(4, dtype=dtype, device=args.device)
        bg = torch.full((3,), 0.1, dtype=dtype, device=args.device)
        out = render(*leaves, viewmat, grid.to(args.device), background=bg, backend=args.backend)
        w = torch.rand(out.rgb.shape, generator=gen, dtype=torch.float64).to(args.device, dtype)
        loss = (out.rgb * w).sum() + 0.1 * out.depth.sum() + out.accumulation.sum()
        loss.backward()
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        finite = bool(torch.isfinite(out.rgb).all()) and all(bool(torch.isfinite(t.grad).all()) for t in leaves)
        ok &= finite
        print(f"{name}: pairs {int(out.tile_counts.sum())}, loss {float(loss.detach()):.6f}, finite {finite}", flush=True)
    print("sanitize scene done" if ok else "sanitize scene: NON-FINITE output or gradient", flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
