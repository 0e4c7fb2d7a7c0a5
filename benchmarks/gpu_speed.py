"""geer's CUDA kernels (and the PyTorch renderer) against gsplat's rasterization, on one GPU.

The benchmark is defined in configs/bench_gpu.yaml (scenes, cameras, contenders, repeats, warm-up). One process;
every contender of a (scene, camera) gets the same float32 inputs, pose, pixels, background and loss. Per row:

- forward ms: no-grad forward, median of `repeats` after `warmup` runs (CUDA events; a synchronize first);
- train fwd / bwd / fwd+bwd ms: one training iteration (loss sum(rgb * w)) timed in parts, medians;
- Gaussians per active tile (mean, std) and (tile, Gaussian) pairs: geer's PBF lists, gsplat's tile intersections;
- peak MiB: torch.cuda.max_memory_allocated during the forward / training runs, above the inputs;
- error: max abs and PSNR against the float64 brute-force render on the same rays (a seeded subsample).

    python -m benchmarks.gpu_speed [--out benchmarks/gpu_speed.md]     # part of bash benchmarks/gpu.sh
    python -m benchmarks.gpu_speed --dry-run --out /tmp/gpu_dry.md     # CPU, tiny sizes, gsplat rows skipped

The scenes' files are read from the test data (docs/test_data.md).
"""

from __future__ import annotations

import argparse
import math
import statistics
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml

from benchmarks.common import BENCHMARKS, ROOT, header, test_data
from geer_ns.cameras import OpenCVFisheyeCamera, PinholeCamera
from geer_ns.render import RayGrid, render, render_brute_force


@dataclass
class Scene:
    name: str
    tensors: list  # means, quats, scales, opacities, colors ([N,3] RGB or [N,K,3] SH)
    sh_degree: int | None
    viewmat: torch.Tensor  # [4, 4] world -> camera (OpenCV)
    note: str


def _subsample(tensors: list, n_max: int | None, seed: int) -> list:
    n = tensors[0].shape[0]
    if n_max is None or n <= n_max:
        return tensors
    idx = torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:n_max].sort().values
    return [t[idx] for t in tensors]


def _unit_quats(n: int, gen: torch.Generator) -> torch.Tensor:
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    return (q / q.norm(dim=-1, keepdim=True)).float()


def load_scene(spec: dict, n_max: int | None) -> Scene:
    kind, seed = spec["kind"], int(spec.get("seed", 0))
    gen = torch.Generator().manual_seed(seed)
    if kind == "ply":  # a trained 3DGS PLY (SH degree 0), seen from -z at look_at x its 95 % radius
        from plyfile import PlyData

        v = PlyData.read(str(test_data(spec["path"])))["vertex"]
        col = lambda *names: torch.tensor(np.stack([np.asarray(v[n]) for n in names], -1), dtype=torch.float32)  # noqa: E731
        means = col("x", "y", "z")
        tensors = [means, col("rot_0", "rot_1", "rot_2", "rot_3"), col("scale_0", "scale_1", "scale_2").exp(),
                   torch.sigmoid(col("opacity")[:, 0]), col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :]]
        centre = means.median(0).values
        viewmat = torch.eye(4)
        radius = float((means - centre).norm(dim=-1).quantile(0.95))
        viewmat[:3, 3] = -(centre - torch.tensor([0.0, 0.0, float(spec.get("look_at", 2.2)) * radius]))
        return Scene(spec["name"], _subsample(tensors, n_max, seed), 0, viewmat,
                     f"trained 3DGS, {means.shape[0]} Gaussians in the file, SH degree 0")
    if kind == "garden_npz":  # SfM points: kNN scales (gsplat's simple_trainer), seeded rotations and opacities
        from scipy.spatial import cKDTree

        data = np.load(test_data(spec["path"]))
        means, colors = _subsample([torch.from_numpy(data["means3d"]).float(),
                                    torch.from_numpy(data["colors"]).float() / 255.0], n_max, seed)
        dist, _ = cKDTree(means.double().numpy()).query(means.double().numpy(), k=int(spec.get("knn", 3)) + 1)
        scales = torch.from_numpy(np.sqrt((dist[:, 1:] ** 2).mean(-1))).float().clamp_min(1e-7)[:, None].repeat(1, 3)
        lo, hi = spec.get("opacity", [0.5, 1.0])
        opacities = lo + (hi - lo) * torch.rand(means.shape[0], generator=gen)
        viewmat = torch.from_numpy(data["viewmats"][int(spec.get("view_index", 0))]).float()
        return Scene(spec["name"], [means, _unit_quats(means.shape[0], gen), scales, opacities, colors], None, viewmat,
                     f"{data['means3d'].shape[0]} points in the file; kNN scales, seeded rotations and opacities")
    if kind == "synthetic":  # around the camera, log-uniform distances, sizes proportional to the distance
        n = int(spec["n"]) if n_max is None else min(int(spec["n"]), n_max)
        d = torch.randn(n, 3, generator=gen, dtype=torch.float64)
        log_uniform = lambda lo_hi, shape: torch.exp(math.log(lo_hi[0]) + math.log(lo_hi[1] / lo_hi[0])  # noqa: E731
                                                     * torch.rand(shape, generator=gen, dtype=torch.float64))
        r = log_uniform(spec.get("radius", [2.0, 30.0]), (n, 1))
        scales = r * log_uniform(spec.get("rel_scale", [0.002, 0.01]), (n, 3))
        lo, hi = spec.get("opacity", [0.5, 1.0])
        opacities = lo + (hi - lo) * torch.rand(n, generator=gen, dtype=torch.float64)
        tensors = [(d / d.norm(dim=-1, keepdim=True) * r).float(), _unit_quats(n, gen), scales.float(),
                   opacities.float(), torch.rand(n, 3, generator=gen, dtype=torch.float64).float()]
        return Scene(spec["name"], tensors, None, torch.eye(4), f"synthetic, {spec['n']} Gaussians around the camera")
    raise ValueError(f"configs/bench_gpu.yaml: scene {spec['name']}: unknown kind {kind!r}")


@dataclass
class Camera:
    name: str
    model: str  # gsplat's camera_model: pinhole | fisheye
    width: int
    height: int
    K: torch.Tensor  # [3, 3] float32
    dirs: torch.Tensor  # [H, W, 3] float64 unit rays of the pixel centres
    valid: torch.Tensor  # [H, W] bool


def build_camera(spec: dict, max_side: int | None) -> Camera:
    model = spec["model"]
    if "intrinsics_from" in spec:
        data = np.load(test_data(spec["intrinsics_from"]))
        k = data["Ks"][int(spec.get("index", 0))].astype(np.float64)
        w, h, fx, fy, cx, cy = int(data["width"]), int(data["height"]), k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    else:
        w, h = int(spec["width"]), int(spec["height"])
        cx, cy = w / 2, h / 2
        if model == "pinhole":
            fx = fy = (w / 2) / math.tan(math.radians(float(spec["fov_x_deg"])) / 2)
        else:  # equidistant: the fov_deg circle touches the shorter image side
            fx = fy = (min(w, h) / 2) / math.radians(float(spec["fov_deg"]) / 2)
    if max_side is not None and max(w, h) > max_side:  # dry run: the same field of view on fewer pixels
        s = max_side / max(w, h)
        w2, h2 = max(1, round(w * s)), max(1, round(h * s))
        fx, cx, fy, cy, w, h = fx * w2 / w, cx * w2 / w, fy * h2 / h, cy * h2 / h, w2, h2
    if model == "pinhole":
        dirs, valid = PinholeCamera(w, h, fx, fy, cx, cy).pixel_rays(torch.float64)
    else:
        dirs, valid = OpenCVFisheyeCamera.equidistant(w, h, fx, fy, cx, cy).pixel_rays(torch.float64)
        angle = torch.acos((dirs[..., 2] / dirs.norm(dim=-1)).clamp(-1.0, 1.0))
        valid = valid & (angle <= math.radians(float(spec.get("fov_deg", 180.0))) / 2 + 1e-12)
    k = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float32)
    return Camera(spec["name"], model, w, h, k, dirs, valid.to(torch.bool))


def timed(fn, warmup: int, repeats: int, cuda: bool, parts: int = 1) -> list[float]:
    """Median ms of each of `parts` consecutive parts of fn, and of their sum when parts > 1 (fn(mark) calls mark()
    between its parts)."""
    import time

    samples = []
    for i in range(warmup + repeats):
        if cuda:
            torch.cuda.synchronize()
        marks = []

        def mark():
            if cuda:
                marks.append(torch.cuda.Event(enable_timing=True))
                marks[-1].record()
            else:
                marks.append(time.perf_counter())

        mark()
        fn(mark)
        mark()
        if cuda:
            torch.cuda.synchronize()
        if i >= warmup:
            ms = [a.elapsed_time(b) if cuda else 1e3 * (b - a) for a, b in zip(marks, marks[1:])]
            samples.append(ms + [sum(ms)] if parts > 1 else ms)
    return [statistics.median(column) for column in zip(*samples)]


def peak_mib(fn, cuda: bool):
    """(fn's result, the allocator's peak above what was allocated before it, MiB; None off a GPU)."""
    if not cuda:
        return fn(), None
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated()
    out = fn()
    torch.cuda.synchronize()
    return out, (torch.cuda.max_memory_allocated() - base) / 2**20


def contender_fn(spec: dict, scene: Scene, cam: Camera, grid: RayGrid, bg: torch.Tensor, tile: int, cuda: bool):
    """(params -> (rgb [H,W,3], per-tile pair counts [tiles])) of one contender."""
    viewmat = scene.viewmat.to(bg.device)
    if spec["renderer"] == "geer":
        backend = spec.get("backend", "auto") if cuda else "torch"

        def geer(params):
            out = render(*params, viewmat, grid, sh_degree=scene.sh_degree, background=bg,
                         lambda_mode=spec.get("lambda_mode", "opacity"), backend=backend)
            return out.rgb, out.tile_counts
        return geer
    from gsplat import rasterization

    def gsplat(params):
        rgb, _, meta = rasterization(*params, viewmat[None], cam.K.to(bg.device)[None], cam.width, cam.height,
                                     sh_degree=scene.sh_degree, tile_size=tile, backgrounds=bg[None],
                                     camera_model=cam.model)
        offsets = meta["isect_offsets"].reshape(-1).long()
        total = torch.tensor([meta["isect_ids"].numel()], device=offsets.device)
        return rgb[0], torch.diff(offsets, append=total)
    return gsplat


def run_row(spec, scene, cam, grid, ref, bg, weight, timing, tile, cuda) -> dict:
    fn = contender_fn(spec, scene, cam, grid, bg, tile, cuda)
    warmup, repeats = int(spec.get("warmup", timing["warmup"])), int(spec.get("repeats", timing["repeats"]))
    params = [t.to(bg.device, torch.float32).clone().requires_grad_(True) for t in scene.tensors]
    row = {"note": "" if cuda else "dry run: the PyTorch renderer on the CPU"}
    if "forward" in spec.get("passes", ["forward", "train"]):
        with torch.no_grad():
            (row["forward"],), row["peak_fwd"] = peak_mib(lambda: timed(lambda mark: fn(params), warmup, repeats, cuda), cuda)
    if "train" in spec.get("passes", ["forward", "train"]):
        def step(mark):
            for p in params:
                p.grad = None
            loss = (fn(params)[0] * weight).sum()
            mark()
            loss.backward()
        (row["train_fwd"], row["bwd"], row["fwd_bwd"]), row["peak_train"] = peak_mib(
            lambda: timed(step, warmup, repeats, cuda, parts=2), cuda)
    with torch.no_grad():
        rgb, counts = fn(params)
        counts = counts.double()[grid.tile_active]
        diff = rgb.reshape(-1, 3)[ref[0]].double() - ref[1]
        mse = float(diff.square().mean())
        row.update(gpt=(float(counts.mean()), float(counts.std())), pairs=int(counts.sum()), err=float(diff.abs().max()),
                   psnr=math.inf if mse == 0 else -10 * math.log10(mse))
    return row


def reference(scene: Scene, cam: Camera, bg: torch.Tensor, cfg: dict, max_rays: int) -> tuple:
    """(flat pixel ids [M], float64 rgb [M,3]) of the brute-force render on a seeded subsample of the valid rays."""
    index = torch.nonzero(cam.valid.reshape(-1)).squeeze(1)
    if index.numel() > max_rays:
        pick = torch.randperm(index.numel(), generator=torch.Generator().manual_seed(int(cfg.get("seed", 0))))
        index = index[pick[:max_rays].sort().values]
    dirs = cam.dirs.reshape(-1, 3)[index][None].to(bg.device)
    sub = RayGrid.from_rays(dirs, torch.ones(1, index.numel(), dtype=torch.bool, device=bg.device), tile_size=16)
    with torch.no_grad():
        out = render_brute_force(*[t.to(bg.device, torch.float64) for t in scene.tensors],
                                 scene.viewmat.to(bg.device, torch.float64), sub, sh_degree=scene.sh_degree,
                                 background=bg.double(), rays_per_group=int(cfg.get("rays_per_group", 64)),
                                 max_pairs=int(cfg.get("max_pairs", 1 << 22)))
    return index.to(bg.device), out.rgb.reshape(-1, 3)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "bench_gpu.yaml")
    ap.add_argument("--out", type=Path, default=BENCHMARKS / "gpu_speed.md")
    ap.add_argument("--dry-run", action="store_true", help="CPU, tiny sizes, gsplat rows skipped (a check of this script)")
    args = ap.parse_args(argv)
    cfg = yaml.safe_load(args.config.read_text())
    cuda = torch.cuda.is_available() and not args.dry_run
    if not cuda and not args.dry_run:
        raise SystemExit("gpu_speed: no CUDA GPU here (--dry-run checks the script on the CPU)")
    dry = cfg["dry_run"] if args.dry_run else {}
    timing = {**cfg["timing"], **{k: dry[k] for k in ("warmup", "repeats") if k in dry}}
    tile, max_rays = int(dry.get("tile_size", cfg["tile_size"])), int(dry.get("error_max_rays", cfg["error"]["max_rays"]))
    device = torch.device("cuda" if cuda else "cpu")
    bg = torch.tensor(cfg["background"], dtype=torch.float32, device=device)
    cameras = [build_camera(c, dry.get("max_side")) for c in cfg["cameras"]]
    lines = ["| scene | camera | contender | forward ms | train fwd ms | bwd ms | fwd+bwd ms | Gaussians / tile | "
             "pairs | peak MiB fwd / train | max abs err | PSNR vs exact | note |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    notes = []
    for sspec in cfg["scenes"]:
        scene = load_scene(sspec, dry.get("max_gaussians"))
        notes.append(f"scene {scene.name}: {scene.tensors[0].shape[0]} Gaussians; {scene.note}")
        for cam in cameras:
            grid = RayGrid.from_rays(cam.dirs.float(), cam.valid, tile_size=tile).to(device)
            weight = torch.rand(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(cfg["loss_seed"]))
            ref = reference(scene, cam, bg, cfg["error"], max_rays)
            for spec in cfg["contenders"]:
                row = {}
                if spec["renderer"] == "gsplat" and not cuda:
                    row["note"] = "gsplat needs CUDA"
                elif cam.width * cam.height > int(spec.get("max_pixels", 1 << 62)) or \
                        scene.tensors[0].shape[0] > int(spec.get("max_gaussians", 1 << 62)):
                    row["note"] = "larger than this contender's limits in the config"
                else:
                    try:
                        row = run_row(spec, scene, cam, grid, ref, bg, weight.to(device), timing, tile, cuda)
                    except Exception as exc:  # noqa: BLE001 - recorded in its row (out of memory, a failed launch)
                        traceback.print_exc()
                        row["note"] = f"error: {type(exc).__name__}: {str(exc).splitlines()[0][:160] if str(exc) else ''}"
                f = lambda key, spec=".2f": format(row[key], spec) if row.get(key) is not None else ""  # noqa: E731
                peaks = f"{f('peak_fwd', '.0f')} / {f('peak_train', '.0f')}" if cuda and "pairs" in row else ""
                gpt = f"{row['gpt'][0]:.1f} ± {row['gpt'][1]:.1f}" if "gpt" in row else ""
                lines.append(f"| {scene.name} | {cam.name} | {spec['name']} | {f('forward')} | {f('train_fwd')} | "
                             f"{f('bwd')} | {f('fwd_bwd')} | {gpt} | {row.get('pairs', '')} | {peaks} | "
                             f"{f('err', '.2e')} | {f('psnr', '.1f')} | {row['note']} |")
                print(lines[-1], flush=True)
            if cuda:
                torch.cuda.empty_cache()
    text = header("geer against gsplat on one GPU" + (" (DRY RUN: CPU, tiny sizes)" if args.dry_run else ""),
                  f"config: {args.config.relative_to(ROOT) if args.config.is_relative_to(ROOT) else args.config}; "
                  f"warm-up {timing['warmup']}, median of {timing['repeats']} runs (per-contender overrides in the "
                  "config); one process, the same inputs for every contender", *notes)
    args.out.write_text(text + "\n" + "\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
