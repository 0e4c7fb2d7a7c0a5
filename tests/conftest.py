"""Shared fixtures: seeded random scenes, reference ray sets and the location of the external test data."""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest
import torch

# The external test data (docs/test_data.md): $GEER_TEST_DATA, else ../shared/data beside the checkout.
SHARED_DATA = Path(os.environ.get("GEER_TEST_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def start_in_thread(fn, daemon: bool = False):
    """fn() started in a non-main thread: (the thread, a dict that gets "result" or "error" when it ends)."""
    import threading

    box = {}

    def run():
        try:
            box["result"] = fn()
        except BaseException as error:  # noqa: BLE001 - handed to the test
            box["error"] = error

    thread = threading.Thread(target=run, daemon=daemon)
    thread.start()
    return thread, box


def shared_data(*parts: str) -> Path:
    """Path under the external test data; skips the test, saying why, when that data is not there."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"test data not found at {path} (set GEER_TEST_DATA: docs/test_data.md)")
    return path


@pytest.fixture(scope="module")
def single_thread():
    """Element-wise torch ops on a shared 2-core machine are far faster single-threaded (no spin-waiting
    on oversubscribed cores); restored afterwards so other test modules are unaffected."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def cpu_ops():
    """The CPU build (csrc/cpu_ops.cpp, JIT-built once per configuration); skips without a C++ compiler."""
    import shutil

    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler: cannot build csrc/cpu_ops.cpp")
    from geer_ns.render.cuda_backend import load_cpu_ops

    return load_cpu_ops()


def random_quats(n: int, gen: torch.Generator, dtype=torch.float64) -> torch.Tensor:
    return torch.randn(n, 4, generator=gen, dtype=dtype)


def random_scene(
    n: int,
    seed: int,
    *,
    dtype=torch.float64,
    center=(0.0, 0.0, 4.0),
    spread=1.5,
    scale_range=(0.02, 0.4),
    opacity_range=(0.05, 0.95),
    around: bool = False,
):
    """Random anisotropic Gaussians. around=True scatters them on all sides of the camera (wide FoV)."""
    gen = torch.Generator().manual_seed(seed)
    if around:
        d = torch.randn(n, 3, generator=gen, dtype=dtype)
        d = d / d.norm(dim=-1, keepdim=True)
        means = d * (0.3 + 4.0 * torch.rand(n, 1, generator=gen, dtype=dtype))
    else:
        means = torch.tensor(center, dtype=dtype) + spread * torch.randn(n, 3, generator=gen, dtype=dtype)
    lo, hi = (math.log(s) for s in scale_range)
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=gen, dtype=dtype))
    quats = random_quats(n, gen, dtype)
    opacities = opacity_range[0] + (opacity_range[1] - opacity_range[0]) * torch.rand(n, generator=gen, dtype=dtype)
    colors = torch.rand(n, 3, generator=gen, dtype=dtype)
    return means, quats, scales, opacities, colors


def stress_gaussians(dtype=torch.float64):
    """(means, quats, scales, opacities) of degenerate Gaussians, seen from the origin looking along +z: disk,
    needle, camera inside, straddling z = 0, behind, a scale below MIN_SCALE, non-unit quaternions, opacity
    exactly 1 and 0, one grazing the camera from the side."""
    rows = [  # mean, scales, opacity
        ((0.1, 0.0, 2.0), (1e-8, 0.3, 0.2), 0.8),
        ((0.1, 0.0, 2.0), (0.4, 1e-8, 1e-8), 0.8),
        ((0.05, -0.02, 0.1), (0.6, 0.5, 0.7), 0.8),
        ((0.3, 0.1, 0.0), (0.3, 0.2, 0.4), 0.8),
        ((0.0, 0.2, -2.0), (0.3, 0.3, 0.3), 0.8),
        ((0.4, -0.3, 3.0), (1e-13, 0.2, 0.3), 0.9),
        ((-0.5, 0.5, 1.5), (0.2, 0.1, 0.05), 1.0),
        ((0.0, 0.0, 2.0), (0.3, 0.3, 0.3), 0.0),
        ((2.0, 0.1, 0.3), (0.5, 0.05, 0.05), 0.7),
    ]
    means = torch.tensor([r[0] for r in rows], dtype=dtype)
    scales = torch.tensor([r[1] for r in rows], dtype=dtype)
    opac = torch.tensor([r[2] for r in rows], dtype=dtype)
    gen = torch.Generator().manual_seed(3)
    quats = torch.randn(len(rows), 4, generator=gen, dtype=dtype) * 3.0  # deliberately not unit
    return means, quats, scales, opac


def random_viewmat(seed: int, dtype=torch.float64, translation_scale: float = 0.5) -> torch.Tensor:
    """A random rigid world-to-camera transform."""
    gen = torch.Generator().manual_seed(seed)
    q = torch.randn(4, generator=gen, dtype=dtype)
    from geer_ns.render import quat_to_rotmat

    vm = torch.eye(4, dtype=dtype)
    vm[:3, :3] = quat_to_rotmat(q)
    vm[:3, 3] = translation_scale * torch.randn(3, generator=gen, dtype=dtype)
    return vm


def equidistant_fisheye_rays(size: int, fov_deg: float = 180.0, dtype=torch.float64):
    """Rays of an ideal equidistant fisheye (r = f * angle) whose image circle spans fov_deg."""
    f = (size / 2) / math.radians(fov_deg / 2)
    c = (torch.arange(size, dtype=dtype) + 0.5) - size / 2
    v, u = torch.meshgrid(c, c, indexing="ij")
    r = torch.sqrt(u * u + v * v)
    ang = r / f
    psi = torch.atan2(v, u)
    dirs = torch.stack([torch.sin(ang) * torch.cos(psi), torch.sin(ang) * torch.sin(psi), torch.cos(ang)], -1)
    return dirs, ang <= math.radians(fov_deg / 2)


def small_grid(name: str, dtype=torch.float64):
    """12 x 12 rays in 6-pixel tiles (36 rays: a full warp and a padded one per tile): "beap" (100 x 80
    degrees) or "fisheye" (190 degrees equidistant: rays beyond 90 degrees off axis, corners invalid)."""
    from geer_ns.render import RayGrid

    if name == "beap":
        return RayGrid.beap(12, 12, math.radians(100), math.radians(80), tile_size=6, dtype=dtype)
    dirs, valid = equidistant_fisheye_rays(12, 190.0, dtype=dtype)
    return RayGrid.from_rays(dirs, valid, tile_size=6)


def small_scene(grid_name: str, seed: int = 0, n: int = 40):
    """([means, quats, scales, opacities, colours] in world space, a rigid float64 viewmat) of n Gaussians
    in small_grid(grid_name)'s view (all around the camera for the fisheye), RGB colours."""
    means_c, quats, scales, opac, colors = random_scene(n, seed, around=grid_name == "fisheye", spread=0.7,
                                                        scale_range=(0.05, 0.5))
    viewmat = random_viewmat(seed + 10)
    rot, t = viewmat[:3, :3], viewmat[:3, 3]
    return [(means_c - t) @ rot, quats, scales, opac, colors], viewmat  # camera-frame means: means_c


def equirect_rays(width: int, height: int, dtype=torch.float64):
    """Rays of a full 360 x 180 degree equirectangular image (longitude 0 looks along +z, y down)."""
    lon = ((torch.arange(width, dtype=dtype) + 0.5) / width - 0.5) * 2 * math.pi
    lat = ((torch.arange(height, dtype=dtype) + 0.5) / height - 0.5) * math.pi
    la, lo = torch.meshgrid(lat, lon, indexing="ij")
    return torch.stack([torch.cos(la) * torch.sin(lo), torch.sin(la), torch.cos(la) * torch.cos(lo)], -1)


# Which of the reference grids look in every direction (test scenes then surround the camera).
WIDE_GRIDS = ("fisheye180", "equirect360")


def reference_grids(dtype=torch.float64) -> dict:
    """The three ray grids the renderer tests share: a 120x90 degree BEAP grid, a 180 degree equidistant
    fisheye (corner tiles inactive) and a full 360 degree equirectangular camera."""
    from geer_ns.render import RayGrid

    fish_dirs, fish_valid = equidistant_fisheye_rays(64, 180.0, dtype=dtype)
    return {
        "beap": RayGrid.beap(80, 48, math.radians(120), math.radians(90), tile_size=16, dtype=dtype),
        "fisheye180": RayGrid.from_rays(fish_dirs, fish_valid, tile_size=16),
        "equirect360": RayGrid.from_rays(equirect_rays(96, 48, dtype=dtype), None, tile_size=16),
    }


def tiny_trainer_config(data: Path, out: Path, name: str, steps: int):
    """geer's TrainerConfig for a few CPU steps: no viewer, no evaluation, half resolution, cached on the CPU."""
    from geer_ns.config import geer_trainer_config
    from geer_ns.model import GeerModelConfig

    config = geer_trainer_config("geer", GeerModelConfig())
    config.data = config.pipeline.datamanager.data = data  # as ns-train's main() does
    config.pipeline.datamanager.cache_images = "cpu"
    config.output_dir, config.experiment_name, config.timestamp = out, name, "run"
    config.vis = "tensorboard"
    config.max_num_iterations = steps
    config.steps_per_eval_image = config.steps_per_eval_batch = config.steps_per_eval_all_images = 0
    config.pipeline.model.num_downscales, config.pipeline.model.resolution_schedule = 1, 1_000_000
    return config


def train_in_process(config) -> Path:
    """nerfstudio's training loop (what ns-train runs after parsing); returns the last checkpoint."""
    from nerfstudio.scripts.train import train_loop
    from nerfstudio.utils import writer

    writer.EVENT_WRITERS.clear()  # nerfstudio's writers are module globals: one run's writers per run
    train_loop(0, 1, config)
    writer.EVENT_WRITERS.clear()
    return sorted((config.get_base_dir() / "nerfstudio_models").glob("step-*.ckpt"))[-1]


def copy_room(root: Path, n_frames: int, n_eval: int = 0) -> Path:
    """The first n_frames frames of the embedded room (images, shared mask, seed points) as a dataset in root;
    the last n_eval of them form the val/test split (without one, no split lists)."""
    import json
    import shutil

    from geer_ns.data.synthetic_room import default_scene_dir

    src = default_scene_dir()
    meta = json.loads((src / "transforms.json").read_text())
    meta["frames"] = meta["frames"][:n_frames]
    names = [f["file_path"] for f in meta["frames"]]
    for key in ("train_filenames", "val_filenames", "test_filenames"):
        meta.pop(key)
    if n_eval:
        meta["train_filenames"] = names[: n_frames - n_eval]
        meta["val_filenames"] = meta["test_filenames"] = names[n_frames - n_eval:]
    for frame in meta["frames"]:
        for key in ("file_path", "mask_path"):
            (root / frame[key]).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(src / frame[key], root / frame[key])
    shutil.copy(src / meta["ply_file_path"], root / meta["ply_file_path"])
    (root / "transforms.json").write_text(json.dumps(meta))
    return root
