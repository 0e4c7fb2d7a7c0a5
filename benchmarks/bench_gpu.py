"""GPU benchmark (issue 3, items 4-6): 3DGEER (CUDA kernels and PyTorch twin) against gsplat 1.4.0.

The benchmark is defined in configs/bench_gpu.yaml (scenes, cameras, contenders, repeats, warm-up). One
process; every contender of a (scene, camera) gets the same float32 inputs, pose, pixels, background and
loss. Per row (scene, camera, contender):

- forward ms: inference forward (torch.no_grad), median of `repeats` after `warmup` runs;
- train fwd / bwd / fwd+bwd ms: one training iteration timed in three parts (forward with grad, backward
  of sum(rgb * w), their sum), medians over the same iterations; a synchronize precedes each run, so every
  sample is one isolated run (CUDA events on a GPU, time.perf_counter on the CPU);
- Gaussians per tile (mean, std over the active tiles) and (tile, Gaussian) pairs: geer's PBF lists
  (`tile_counts`), gsplat's tile intersections (`meta["isect_offsets"]` / `meta["isect_ids"]`); active
  tiles = tiles with at least one valid ray (the fisheye's corners are inactive: skipped by geer);
- peak memory: torch.cuda.max_memory_allocated during the forward / training runs, above what was
  allocated before them (the inputs);
- error: max abs and PSNR of the contender's image against rasterize.render_brute_force in float64 on the
  same rays (a seeded subsample of the valid rays for large images, see the yaml);
- stage timings (GPU): per-kernel device time per training iteration from torch.profiler.

    python benchmarks/bench_gpu.py [--config configs/bench_gpu.yaml] [--out benchmarks/gpu_results.md]
    python benchmarks/bench_gpu.py --dry-run --out /tmp/gpu_dry.md     # CPU, tiny sizes

Data files are read from .device/data/ (`bash benchmarks/gpu_session.sh prep` copies them from ../shared/data;
--data-root points elsewhere). Rows run in the order of the config's `first` pairs, then the rest; the GPU
session passes --time-budget-s (and --no-gsplat while gsplat's build is not ready).

Writes the markdown table to --out and everything (device, commit, command line, config, rows) to the
same path with suffix .json; both are rewritten after every row, so a run cut short keeps its results.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import shlex
import statistics
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_cpu_renderer import load_3dgs_ply, look_at_viewmat
from bench_gpu_report import write_outputs

from geer_ns.cameras import OpenCVFisheyeCamera, PinholeCamera
from geer_ns.render import RayGrid, render, render_brute_force

NEEDS_CUDA = "needs CUDA (skipped in the dry run / without a GPU)"


# ----------------------------------------------------------------------------------------------- scenes
@dataclass
class Scene:
    name: str
    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor  # [N, 3] RGB, or [N, K, 3] SH coefficients
    sh_degree: int | None
    viewmat: torch.Tensor  # [4, 4] world -> camera (OpenCV)
    note: str = ""

    @property
    def n(self) -> int:
        return self.means.shape[0]

    def tensors(self) -> list[torch.Tensor]:
        return [self.means, self.quats, self.scales, self.opacities, self.colors]


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(int(seed))


def _subsample(tensors: list[torch.Tensor], n_max: int | None, seed: int) -> list[torch.Tensor]:
    n = tensors[0].shape[0]
    if n_max is None or n <= n_max:
        return tensors
    idx = torch.randperm(n, generator=_gen(seed))[:n_max].sort().values
    return [t[idx] for t in tensors]


def _random_quats(n: int, gen: torch.Generator) -> torch.Tensor:
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    return (q / q.norm(dim=-1, keepdim=True)).float()


def _knn_rms(points: np.ndarray, k: int) -> np.ndarray:
    """RMS distance of each point to its k nearest neighbours (gsplat's simple_trainer initialisation)."""
    try:
        from scipy.spatial import cKDTree

        dist, _ = cKDTree(points).query(points, k=k + 1)
        d = dist[:, 1:]
    except ImportError:  # chunked brute force
        p = torch.from_numpy(points).double()
        d = torch.cat([torch.cdist(c, p).topk(k + 1, largest=False).values[:, 1:] for c in p.split(4096)]).numpy()
    return np.sqrt((d**2).mean(-1))


def data_file(root: Path, rel: str, what: str) -> Path:
    """A data file of the config, relative to root (the repository, or where gpu_prep.py put .device/)."""
    path = root / rel
    if not path.is_file():
        raise FileNotFoundError(f"configs/bench_gpu.yaml: {what} reads {path}, which does not exist (run "
                                "`bash benchmarks/gpu_session.sh prep` to copy ../shared/data into .device/)")
    return path


def load_scene(spec: dict, n_max: int | None, root: Path = ROOT) -> Scene:
    kind, name = spec["kind"], spec["name"]
    seed = int(spec.get("seed", 0))
    if kind == "ply":
        means, quats, scales, opac, sh = load_3dgs_ply(data_file(root, spec["path"], f"scene {name}"))
        n_full = means.shape[0]
        viewmat = look_at_viewmat(means, float(spec.get("look_at", 2.2)))
        means, quats, scales, opac, sh = _subsample([means, quats, scales, opac, sh], n_max, seed)
        return Scene(name, means, quats, scales, opac, sh, 0, viewmat,
                     f"trained 3DGS, {n_full} Gaussians in the file, SH degree 0")
    if kind == "garden_npz":
        data = np.load(data_file(root, spec["path"], f"scene {name}"))
        means = torch.from_numpy(data["means3d"]).float()
        colors = torch.from_numpy(data["colors"]).float() / 255.0
        n_full = means.shape[0]
        means, colors = _subsample([means, colors], n_max, seed)
        gen = _gen(seed)
        n = means.shape[0]
        dist = _knn_rms(means.double().numpy(), int(spec.get("knn", 3))) * float(spec.get("scale_factor", 1.0))
        scales = torch.from_numpy(dist).float().clamp_min(1e-7)[:, None].repeat(1, 3)
        quats = _random_quats(n, gen)
        lo, hi = spec.get("opacity", [0.5, 1.0])
        opac = lo + (hi - lo) * torch.rand(n, generator=gen)
        viewmat = torch.from_numpy(data["viewmats"][int(spec.get("view_index", 0))]).float()
        return Scene(name, means, quats, scales, opac, colors, None, viewmat,
                     f"{n_full} points in the file; kNN scales, seeded quats/opacities, RGB colours")
    if kind == "synthetic":
        n = int(spec["n"]) if n_max is None else min(int(spec["n"]), n_max)
        gen = _gen(seed)
        d = torch.randn(n, 3, generator=gen, dtype=torch.float64)
        d = d / d.norm(dim=-1, keepdim=True)
        r_lo, r_hi = (math.log(v) for v in spec.get("radius", [2.0, 30.0]))
        r = torch.exp(r_lo + (r_hi - r_lo) * torch.rand(n, 1, generator=gen, dtype=torch.float64))
        s_lo, s_hi = (math.log(v) for v in spec.get("rel_scale", [0.002, 0.01]))
        scales = r * torch.exp(s_lo + (s_hi - s_lo) * torch.rand(n, 3, generator=gen, dtype=torch.float64))
        quats = _random_quats(n, gen)
        lo, hi = spec.get("opacity", [0.5, 1.0])
        opac = lo + (hi - lo) * torch.rand(n, generator=gen, dtype=torch.float64)
        colors = torch.rand(n, 3, generator=gen, dtype=torch.float64)
        return Scene(name, (d * r).float(), quats, scales.float(), opac.float(), colors.float(), None,
                     torch.eye(4), f"synthetic, {int(spec['n'])} Gaussians around the camera (seed {seed})")
    raise ValueError(f"scene {name}: unknown kind {kind!r}")


# ---------------------------------------------------------------------------------------------- cameras
@dataclass
class Camera:
    name: str
    model: str  # "pinhole" | "fisheye" (gsplat camera_model)
    width: int
    height: int
    K: torch.Tensor  # [3, 3] float32
    dirs: torch.Tensor  # [H, W, 3] float64 unit rays of the pixel centres (u, v) = (j + 0.5, i + 0.5)
    valid: torch.Tensor  # [H, W] bool


def build_camera(spec: dict, max_side: int | None, root: Path = ROOT) -> Camera:
    model = spec["model"]
    if "intrinsics_from" in spec:
        data = np.load(data_file(root, spec["intrinsics_from"], f"camera {spec['name']}"))
        K = data["Ks"][int(spec.get("index", 0))].astype(np.float64)
        w, h = int(data["width"]), int(data["height"])
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    else:
        w, h = int(spec["width"]), int(spec["height"])
        cx, cy = w / 2, h / 2
        if model == "pinhole":
            fx = fy = (w / 2) / math.tan(math.radians(float(spec["fov_x_deg"])) / 2)
        else:  # equidistant: the fov_deg circle touches the shorter image side
            fx = fy = (min(w, h) / 2) / math.radians(float(spec["fov_deg"]) / 2)
    if max_side is not None and max(w, h) > max_side:  # dry run: same FoV, fewer pixels
        s = max_side / max(w, h)
        w2, h2 = max(1, round(w * s)), max(1, round(h * s))
        sx, sy = w2 / w, h2 / h
        fx, cx, fy, cy, w, h = fx * sx, cx * sx, fy * sy, cy * sy, w2, h2
    if model == "pinhole":
        dirs, valid = PinholeCamera(w, h, fx, fy, cx, cy).pixel_rays(torch.float64)
    elif model == "fisheye":
        dirs, valid = OpenCVFisheyeCamera.equidistant(w, h, fx, fy, cx, cy).pixel_rays(torch.float64)
        half = math.radians(float(spec.get("fov_deg", 180.0))) / 2
        angle = torch.acos((dirs[..., 2] / dirs.norm(dim=-1)).clamp(-1.0, 1.0))
        valid = valid & (angle <= half + 1e-12)
    else:
        raise ValueError(f"camera {spec['name']}: unknown model {model!r}")
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float32)
    return Camera(spec["name"], model, w, h, K, dirs, valid.to(torch.bool))


# ----------------------------------------------------------------------------------------------- timing
class Timer:
    """Per-run timing: CUDA events on a GPU (a synchronize precedes every run), perf_counter on the CPU."""

    def __init__(self, cuda: bool):
        self.cuda = cuda

    def sync(self) -> None:
        if self.cuda:
            torch.cuda.synchronize()

    def marks(self, n: int) -> list:
        return [torch.cuda.Event(enable_timing=True) for _ in range(n)] if self.cuda else [None] * n

    def record(self, marks: list, i: int) -> None:
        if self.cuda:
            marks[i].record()
        else:
            marks[i] = time.perf_counter()

    def ms(self, marks: list, i: int, j: int) -> float:
        if self.cuda:
            marks[j].synchronize()
            return float(marks[i].elapsed_time(marks[j]))
        return (marks[j] - marks[i]) * 1e3


class PeakMemory:
    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"
        self.mib: float | None = None

    def __enter__(self):
        if self.cuda:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            self.base = torch.cuda.memory_allocated()
        return self

    def __exit__(self, *exc):
        if self.cuda and exc[0] is None:
            torch.cuda.synchronize()
            self.mib = (torch.cuda.max_memory_allocated() - self.base) / 2**20


def time_forward(fn, timer: Timer, warmup: int, repeats: int) -> float:
    with torch.no_grad():
        for _ in range(warmup):
            fn()
        samples = []
        for _ in range(repeats):
            timer.sync()
            m = timer.marks(2)
            timer.record(m, 0)
            fn()
            timer.record(m, 1)
            samples.append(timer.ms(m, 0, 1))
    return statistics.median(samples)


def time_train(loss_fn, params: list[torch.Tensor], timer: Timer, warmup: int, repeats: int) -> tuple[float, float, float]:
    fwd, bwd, tot = [], [], []
    for i in range(warmup + repeats):
        for p in params:
            p.grad = None
        timer.sync()
        m = timer.marks(3)
        timer.record(m, 0)
        loss = loss_fn()
        timer.record(m, 1)
        loss.backward()
        timer.record(m, 2)
        if i >= warmup:
            fwd.append(timer.ms(m, 0, 1))
            bwd.append(timer.ms(m, 1, 2))
            tot.append(timer.ms(m, 0, 2))
        else:
            timer.sync()
    return statistics.median(fwd), statistics.median(bwd), statistics.median(tot)


def profile_stages(loss_fn, params: list[torch.Tensor], iters: int) -> dict[str, float]:
    """Per-kernel device time (ms per training iteration), largest first."""
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(iters):
            for p in params:
                p.grad = None
            loss_fn().backward()
        torch.cuda.synchronize()
    stages: dict[str, float] = {}
    for e in prof.key_averages():
        us = getattr(e, "self_device_time_total", None)
        if us is None:
            us = getattr(e, "self_cuda_time_total", 0.0)
        if us and us > 0:
            stages[e.key] = stages.get(e.key, 0.0) + us / 1e3 / iters
    return dict(sorted(stages.items(), key=lambda kv: -kv[1]))


# -------------------------------------------------------------------------------------------- contenders
class GeerContender:
    def __init__(self, spec: dict, scene: Scene, cam: Camera, grid: RayGrid, bg: torch.Tensor, backend: str):
        self.spec, self.scene, self.grid, self.bg, self.backend = spec, scene, grid, bg, backend
        self.viewmat = scene.viewmat.to(bg.device)

    def __call__(self, params):
        means, quats, scales, opac, colors = params
        out = render(means, quats, scales, opac, colors, self.viewmat, self.grid, sh_degree=self.scene.sh_degree,
                     background=self.bg, lambda_mode=self.spec.get("lambda_mode", "opacity"), backend=self.backend)
        return out.rgb, out

    def tile_counts(self, out) -> torch.Tensor:
        return out.tile_counts

    def visible(self, out) -> int:
        return int(out.visible.sum())


class GsplatContender:
    def __init__(self, spec: dict, scene: Scene, cam: Camera, grid: RayGrid, bg: torch.Tensor, tile_size: int):
        from gsplat import rasterization

        self.rasterization, self.scene, self.cam, self.bg, self.tile_size = rasterization, scene, cam, bg, tile_size
        self.viewmat = scene.viewmat.to(bg.device)[None]
        self.K = cam.K.to(bg.device)[None]

    def __call__(self, params):
        means, quats, scales, opac, colors = params
        rgb, _alpha, meta = self.rasterization(
            means, quats, scales, opac, colors, self.viewmat, self.K, self.cam.width, self.cam.height,
            sh_degree=self.scene.sh_degree, tile_size=self.tile_size, backgrounds=self.bg[None],
            camera_model=self.cam.model,
        )
        return rgb[0], meta

    def tile_counts(self, meta) -> torch.Tensor:
        offsets = meta["isect_offsets"].reshape(-1).long()
        total = torch.tensor([meta["isect_ids"].numel()], device=offsets.device)
        return torch.diff(offsets, append=total)

    def visible(self, meta) -> int:
        """Gaussians that intersect at least one tile (geer: listed in at least one active tile)."""
        hit = meta["tiles_per_gauss"].reshape(-1) > 0  # packed: [nnz]; unpacked: [C, N]
        ids = meta.get("gaussian_ids")
        return int(torch.unique(ids[hit]).numel()) if ids is not None else int(hit.sum())


# ------------------------------------------------------------------------------------------------- main
def run_order(cfg: dict, scenes: list[dict], cameras: list[str]) -> list[tuple[dict, int]]:
    """(scene spec, camera index) pairs to run: the config's `first` pairs (the headline rows, so that a time
    budget never skips them), then every other pair, scenes outer, in config order."""
    by_name = {s["name"]: s for s in cfg["scenes"]}
    all_cams = [c["name"] for c in cfg["cameras"]]
    picked = {s["name"] for s in scenes}
    first = []
    for scene_name, cam_name in cfg.get("first", []):
        if scene_name not in by_name or cam_name not in all_cams:
            raise ValueError(f"configs/bench_gpu.yaml: first: [{scene_name}, {cam_name}] names no scene / camera")
        if scene_name in picked and cam_name in cameras:
            first.append((scene_name, cameras.index(cam_name)))
    rest = [(s["name"], i) for s in scenes for i in range(len(cameras)) if (s["name"], i) not in first]
    return [(by_name[name], i) for name, i in first + rest]


@dataclass
class Reference:
    index: torch.Tensor  # [M] flat pixel ids (valid rays)
    rgb: torch.Tensor  # [M, 3] float64
    seconds: float
    n_valid: int


def make_reference(scene: Scene, cam: Camera, bg: torch.Tensor, err_cfg: dict, max_rays: int, device) -> Reference:
    valid = cam.valid.reshape(-1)
    index = torch.nonzero(valid).squeeze(1)
    n_valid = index.numel()
    if n_valid > max_rays:
        pick = torch.randperm(n_valid, generator=_gen(err_cfg.get("seed", 0)))[:max_rays].sort().values
        index = index[pick]
    dirs = cam.dirs.reshape(-1, 3)[index]
    sub = RayGrid.from_rays(dirs[None], torch.ones(1, index.numel(), dtype=torch.bool), tile_size=16).to(device)
    t0 = time.perf_counter()
    with torch.no_grad():
        ref = render_brute_force(*[t.to(device, torch.float64) for t in scene.tensors()],
                                 scene.viewmat.to(device, torch.float64), sub, sh_degree=scene.sh_degree,
                                 background=bg.to(torch.float64), rays_per_group=int(err_cfg.get("rays_per_group", 64)),
                                 max_pairs=int(err_cfg.get("max_pairs", 1 << 22)))
    if device.type == "cuda":
        torch.cuda.synchronize()
    return Reference(index.to(device), ref.rgb.reshape(-1, 3), time.perf_counter() - t0, n_valid)


def _finite(x):
    return None if x is None or not math.isfinite(x) else float(x)


def run_row(cspec, scene, cam, grid, ref, bg, weight, timer, cfg, dry) -> dict:
    """One (scene, camera, contender) row; raises on failure (the caller records it)."""
    device = bg.device
    row: dict = {}
    renderer = cspec["renderer"]
    if renderer == "geer":
        backend = cspec.get("backend", "auto")
        if device.type != "cuda" and backend == "cuda":
            backend = "torch"
            row["note"] = "dry run: PyTorch twin on the CPU"
        row["backend"] = backend
        contender = GeerContender(cspec, scene, cam, grid, bg, backend)
    elif renderer == "gsplat":
        row["backend"] = "gsplat"
        contender = GsplatContender(cspec, scene, cam, grid, bg, int(cfg.get("tile_size", 16)))
    else:
        raise ValueError(f"contender {cspec['name']}: unknown renderer {renderer!r}")

    tcfg = cfg["timing"]
    warmup = int(cspec.get("warmup", tcfg["warmup"])) if not dry else int(tcfg["warmup"])
    repeats = int(cspec.get("repeats", tcfg["repeats"])) if not dry else int(tcfg["repeats"])
    row["repeats"] = repeats
    params = [t.to(device, torch.float32).clone().requires_grad_(True) for t in scene.tensors()]
    passes = cspec.get("passes", ["forward", "train"])

    def loss_fn():
        return (contender(params)[0] * weight).sum()

    if "forward" in passes:
        with PeakMemory(device) as mem:
            row["forward_ms"] = time_forward(lambda: contender(params), timer, warmup, repeats)
        row["peak_forward_mib"] = mem.mib
    if "train" in passes:
        with PeakMemory(device) as mem:
            f, b, t = time_train(loss_fn, params, timer, warmup, repeats)
        row.update(train_forward_ms=f, backward_ms=b, fwd_bwd_ms=t, peak_train_mib=mem.mib)
        if device.type == "cuda" and int(tcfg.get("profile_iters", 0)) > 0:
            try:
                row["stages_ms"] = profile_stages(loss_fn, params, int(tcfg["profile_iters"]))
            except Exception as exc:  # noqa: BLE001 - stage timings are optional
                row["stages_error"] = f"{type(exc).__name__}: {exc}"

    with torch.no_grad():
        img, aux = contender(params)
        counts = contender.tile_counts(aux).double()
        active = grid.tile_active
        if counts.numel() == active.numel():
            sel = counts[active]
        else:  # should not happen (same tile grid); report over all tiles and say so
            sel = counts
            row["note"] = (row.get("note", "") + "; tile stats over all tiles").lstrip("; ")
        row.update(
            gpt_mean=float(sel.mean()), gpt_std=float(sel.std()) if sel.numel() > 1 else 0.0,
            pairs=int(counts.sum()), active_tiles=int(active.sum()), tiles=int(active.numel()),
            visible=contender.visible(aux),
        )
        got = img.reshape(-1, 3)[ref.index].double()
        diff = got - ref.rgb
        mse = float((diff**2).mean())
        row.update(err_max=float(diff.abs().max()), err_psnr=(math.inf if mse == 0 else -10 * math.log10(mse)),
                   err_rays=int(ref.index.numel()), finite=bool(torch.isfinite(img).all()))
    return row


def git_commit() -> str:
    """HEAD (and whether tracked files differ from it); $GEER_COMMIT where the checkout has no .git."""
    if os.environ.get("GEER_COMMIT"):
        return os.environ["GEER_COMMIT"]
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=ROOT, check=False).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True, check=False,
                               text=True, cwd=ROOT).stdout.strip()
        return (rev or "unknown") + (" (uncommitted changes)" if dirty else "")
    except OSError:
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "bench_gpu.yaml")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "gpu_results.md")
    ap.add_argument("--dry-run", action="store_true", help="CPU, tiny sizes, gsplat skipped (for tests)")
    ap.add_argument("--time-budget-s", type=float, default=None, help="stop starting rows after this (0: none)")
    ap.add_argument("--scenes", default=None, help="comma-separated scene names (default: all in the config)")
    ap.add_argument("--cameras", default=None, help="comma-separated camera names (default: all)")
    ap.add_argument("--contenders", default=None, help="comma-separated contender names (default: all)")
    ap.add_argument("--no-gsplat", action="store_true", help="write gsplat rows as skipped (its build is not ready)")
    ap.add_argument("--data-root", type=Path, default=ROOT, help="where the config's data paths start (default: repo)")
    args = ap.parse_args(argv)
    t_start = time.perf_counter()

    cfg = yaml.safe_load(args.config.read_text())
    dry = args.dry_run
    cuda = torch.cuda.is_available() and not dry
    device = torch.device("cuda" if cuda else "cpu")
    n_max = max_side = None
    err_cfg = dict(cfg.get("error", {}))
    max_rays = int(err_cfg.get("max_rays", 4096))
    if dry:
        d = cfg.get("dry_run", {})
        n_max, max_side = int(d.get("max_gaussians", 800)), int(d.get("max_side", 32))
        cfg["timing"] = {**cfg["timing"], **{k: d[k] for k in ("warmup", "repeats", "profile_iters") if k in d}}
        max_rays = int(d.get("error_max_rays", 1024))
        cfg["tile_size"] = int(d.get("tile_size", cfg.get("tile_size", 16)))
        torch.set_num_threads(1)  # element-wise ops on a small shared CPU: fastest single-threaded
    budget = args.time_budget_s if args.time_budget_s is not None else float(cfg.get("time_budget_s", 0) or 0)
    pick = lambda items, sel: [x for x in items if sel is None or x["name"] in sel.split(",")]

    try:
        import gsplat

        gsplat_version = gsplat.__version__
    except Exception as exc:  # noqa: BLE001
        gsplat_version = f"unavailable ({type(exc).__name__}: {exc})"
    device_name = torch.cuda.get_device_name(device) if cuda else f"CPU ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)"
    meta = {
        "device": device_name, "torch": torch.__version__, "cuda": torch.version.cuda, "gsplat": gsplat_version,
        "commit": git_commit(), "command": shlex.join([Path(sys.executable).name, *sys.argv]) if argv is None
        else shlex.join(["python", "benchmarks/bench_gpu.py", *argv]),
        "config_path": str(args.config), "config": cfg, "dry_run": dry,
        "timer": "cuda_events" if cuda else "perf_counter", "timing": cfg["timing"], "error_max_rays": max_rays,
        "scenes": [], "cameras": [],
    }
    print(f"device: {device_name}; torch {torch.__version__}; gsplat {gsplat_version}; dry_run={dry}", flush=True)

    bg = torch.tensor(cfg.get("background", [0.0, 0.0, 0.0]), dtype=torch.float32, device=device)
    timer = Timer(cuda)
    tile = int(cfg.get("tile_size", 16))
    cameras = []
    for cspec in pick(cfg["cameras"], args.cameras):
        cam = build_camera(cspec, max_side, args.data_root)
        cameras.append(cam)
        meta["cameras"].append({"name": cam.name, "model": cam.model, "width": cam.width, "height": cam.height,
                                "K": cam.K.tolist(), "valid_rays": int(cam.valid.sum()), "ref_s": {}})
    rows: list[dict] = []
    contenders = pick(cfg["contenders"], args.contenders)
    order = run_order(cfg, pick(cfg["scenes"], args.scenes), [c.name for c in cameras])
    loaded: dict[str, Scene] = {}
    for idx, (sspec, ci) in enumerate(order):
        if sspec["name"] not in loaded:
            loaded[sspec["name"]] = load_scene(sspec, n_max, args.data_root)
            scene = loaded[sspec["name"]]
            meta["scenes"].append({"name": scene.name, "n": scene.n, "note": scene.note})
            print(f"scene {scene.name}: {scene.n} Gaussians", flush=True)
        scene, cam, cmeta = loaded[sspec["name"]], cameras[ci], meta["cameras"][ci]
        # One (scene, camera): its grid, loss weights and reference are shared by the contenders.
        grid = RayGrid.from_rays(cam.dirs.float(), cam.valid, tile_size=tile).to(device)
        weight = torch.rand(cam.height, cam.width, 3, generator=_gen(cfg.get("loss_seed", 0))).to(device)
        ref = None
        for cspec in contenders:
            row = {"scene": scene.name, "camera": cam.name, "contender": cspec["name"],
                   "n_gaussians": scene.n, "width": cam.width, "height": cam.height}
            elapsed = time.perf_counter() - t_start
            reason = None
            if budget and elapsed > budget:
                reason = f"skipped: time budget ({budget:.0f} s) spent"
            elif cspec["renderer"] == "gsplat" and not cuda:
                reason = NEEDS_CUDA
            elif cspec["renderer"] == "gsplat" and args.no_gsplat:
                reason = "skipped: gsplat's CUDA build was not ready (--no-gsplat)"
            elif not dry and scene.n > int(cspec.get("max_gaussians", 1 << 62)):
                reason = f"skipped: config limits this contender to {cspec['max_gaussians']} Gaussians"
            elif not dry and cam.width * cam.height > int(cspec.get("max_pixels", 1 << 62)):
                reason = f"skipped: config limits this contender to {cspec['max_pixels']} pixels"
            if reason is None and ref is None:
                try:
                    ref = make_reference(scene, cam, bg, err_cfg, max_rays, device)
                    cmeta["ref_s"][scene.name] = round(ref.seconds, 2)
                except Exception as exc:  # noqa: BLE001
                    reason = f"reference failed: {type(exc).__name__}: {exc}"
            if reason is None:
                try:
                    row.update(run_row(cspec, scene, cam, grid, ref, bg, weight, timer, cfg, dry))
                except Exception as exc:  # noqa: BLE001 - record and go on (unverified kernels, OOM)
                    traceback.print_exc()
                    row["note"] = f"error: {type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}"
                    if cuda:
                        torch.cuda.empty_cache()
            else:
                row["note"] = reason
            rows.append(row)
            print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items() if k != "stages_ms"},
                  flush=True)
            write_outputs(args.out, meta, rows)
        del grid, weight, ref
        if all(s["name"] != scene.name for s, _ in order[idx + 1 :]):
            del loaded[scene.name]
        if cuda:
            torch.cuda.empty_cache()
    meta["total_s"] = round(time.perf_counter() - t_start, 1)
    write_outputs(args.out, meta, rows)
    print(f"wrote {args.out} and {args.out.with_suffix('.json')} in {meta['total_s']} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
