"""Association cost on the CPU: tile tests and time of the tile-pyramid search (csrc/geer_associate.h)
against the search it replaced (every active tile tested, twice, on every grid that was not a full BEAP
grid), on the grids training and evaluation use. The previous search is main's csrc at commit 5190816,
built as a second extension and run in the same process on the same inputs.

Cases (also used by tests/test_association_cost.py):
  dev-room-beap      the dev fisheye room's BEAP training view (views.beap_view of its 384 px
                     equidistant fisheye; every BEAP cell lies inside its 179-degree crop circle, so no tile
                     is masked), its 20k seed points as Gaussians (kNN scales, opacity 0.1), view 0
  dev-room-beap-masked  the same grid masked to a 150-degree circle (cells beyond 75 degrees off-axis
                     invalid, corner tiles inactive): a masked training view
  donut-fisheye512   the trained donut (../shared/data/donut_3dgs.ply) in a 512x512 equidistant fisheye (180 degrees across
                     the inscribed circle, ~255 in the corners: every tile active)
  synth200k-fisheye512  200k synthetic Gaussians around the camera (bench_gpu's generator), same grid

    .venv/bin/python benchmarks/cpu_association.py --out benchmarks/cpu_association.md
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from benchmarks.timing import median_seconds  # noqa: E402
DATA = ROOT.parent / "shared" / "data"
BEFORE_COMMIT = "51908164d68e"  # main when this benchmark was written


def _pbf_inputs(means, quats, scales, opac, viewmat, grid, name, with_scene=False):
    """(name, grid, bounds [N,4], alive, depth) from the twin's preprocess (the specification), and with_scene:
    (means, quats, scales, opacities, viewmat) as well."""
    from geer_ns.render import preprocess

    with torch.no_grad():
        pre = preprocess(means, quats, scales, opac, means.new_zeros(means.shape[0], 3), viewmat)
    p = pre.pbf
    out = name, grid, torch.stack([p.theta_lo, p.theta_hi, p.phi_lo, p.phi_hi], -1).contiguous(), p.alive, pre.depth
    return out + ((means, quats, scales, opac, viewmat),) if with_scene else out


def fisheye_grid(size: int = 512):
    from geer_ns.cameras import EquidistantCamera
    from geer_ns.render import RayGrid

    f = (size / 2) / (math.pi / 2)  # 180 degrees across the inscribed circle, more in the corners
    dirs, valid = EquidistantCamera(size, size, f, f, size / 2, size / 2).pixel_rays(torch.float32)
    return RayGrid.from_rays(dirs, valid, tile_size=16)


def masked(case, crop_deg: float):
    """The same Gaussians and view, rays beyond crop_deg / 2 off the optical axis invalid."""
    from geer_ns.render import RayGrid

    name, grid, bounds, alive, depth = case
    valid = (grid.dirs[:, 2] >= math.cos(math.radians(crop_deg / 2))).reshape(grid.height, grid.width)
    grid = RayGrid.from_rays(grid.dirs.reshape(grid.height, grid.width, 3), valid, grid.tile_size)
    return f"{name}-masked", grid, bounds, alive, depth


def dev_room_case(room: Path = DATA / "fisheye_room_dev", with_scene: bool = False):
    from bench_gpu import _knn_rms

    from geer_ns.cameras import EquidistantCamera
    from geer_ns.data.views import beap_view
    from geer_ns.data.ply import read_ply_points
    from geer_ns.render.transforms import world_to_camera_opencv

    meta = json.loads((room / "transforms_fisheye.json").read_text())
    camera = EquidistantCamera(meta["w"], meta["h"], meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"])
    grid = beap_view(camera).rays
    xyz, _ = read_ply_points(room / meta["ply_file_path"])
    means = torch.from_numpy(xyz)
    scales = torch.from_numpy(_knn_rms(xyz.astype(np.float64), 3)).float().clamp_min(1e-7)[:, None].repeat(1, 3)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(means.shape[0], 1)
    opac = torch.full((means.shape[0],), 0.1)  # nerfstudio's initial opacity
    c2w = torch.tensor(meta["frames"][0]["transform_matrix"], dtype=torch.float32)[:3]
    return _pbf_inputs(means, quats, scales, opac, world_to_camera_opencv(c2w), grid, "dev-room-beap", with_scene)


def donut_case(grid=None, with_scene: bool = False):
    from bench_cpu_renderer import load_3dgs_ply, look_at_viewmat

    means, quats, scales, opac, _ = load_3dgs_ply(DATA / "donut_3dgs.ply")
    return _pbf_inputs(means, quats, scales, opac, look_at_viewmat(means, 2.2), grid or fisheye_grid(),
                       "donut-fisheye512", with_scene)


def synthetic_case(n: int = 200_000, grid=None):
    from bench_gpu import load_scene

    s = load_scene({"kind": "synthetic", "name": "synthetic", "n": n, "seed": 0}, None)
    return _pbf_inputs(s.means, s.quats, s.scales, s.opacities, s.viewmat, grid or fisheye_grid(),
                       f"synth{n // 1000}k-fisheye512")


# ------------------------------------------------------------------------------------------ before
def load_before_ops():
    """main's CPU build at BEFORE_COMMIT (its association tests every active tile on these grids)."""
    from torch.utils import cpp_extension

    src = Path(tempfile.mkdtemp(prefix="geer_before_"))
    for name in ("cpu_ops.cpp", "geer_math.h"):
        blob = subprocess.run(["git", "show", f"{BEFORE_COMMIT}:csrc/{name}"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout
        (src / name).write_text(blob)
    build = ROOT / ".cache" / "geer_ext" / "geer_cpu_ops_before"
    build.mkdir(parents=True, exist_ok=True)
    return cpp_extension.load(name="geer_cpu_ops_before", sources=[str(src / "cpu_ops.cpp")], extra_cflags=["-O2"],
                              extra_include_paths=[str(src)], build_directory=str(build))


def load_before_separable_axes():
    """main's cuda_backend.separable_axes: whether its pipeline took the binary-search path."""
    blob = subprocess.run(["git", "show", f"{BEFORE_COMMIT}:geer_ns/render/cuda_backend.py"], cwd=ROOT, check=True,
                          capture_output=True, text=True).stdout
    namespace: dict = {"__name__": "cuda_backend_before", "__package__": "geer_ns.render",
                       "__file__": str(ROOT / "geer_ns" / "render" / "cuda_backend.py")}
    exec(compile(blob, "cuda_backend_before.py", "exec"), namespace)  # noqa: S102 - our own file at a commit
    return namespace["separable_axes"]


def associate_before(ops, separable_axes, bounds, alive, depth, grid):
    """main's pipeline: binary search on separable grids (tile tests not exposed: None), else every tile."""
    order = torch.sort(depth, stable=True).indices
    rank = torch.empty_like(order, dtype=torch.int32)
    rank[order] = torch.arange(order.numel(), dtype=torch.int32)
    tm, pm = (t.to(bounds.dtype) for t in grid.tile_mirror_bounds())
    tiles = torch.cat([tm, pm], -1).contiguous()
    axes = separable_axes(tm, pm, grid.tile_active, grid.tiles_y, grid.tiles_x)
    empty = bounds.new_zeros(0, 2)
    col, row = axes if axes is not None else (empty, empty)
    ids, ranges = ops.associate(bounds, alive, rank, tiles, grid.tile_active, col, row, grid.tiles_x,
                                grid.tiles_y, axes is not None)
    # Count and emit each tested every active tile for every alive Gaussian.
    return ids, ranges, None if axes is not None else 2 * int(alive.sum()) * int(grid.tile_active.sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "cpu_association.md")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    from geer_ns.render.cuda_backend import associate_pairs, load_cpu_ops

    ops, before, separable_axes = load_cpu_ops(), load_before_ops(), load_before_separable_axes()
    grid512 = fisheye_grid()
    room = dev_room_case()
    cases = [room, masked(room, 150.0), donut_case(grid512), synthetic_case(200_000, grid512)]
    rows = []
    for name, grid, bounds, alive, depth in cases:
        ids, ranges, counts, tests = associate_pairs(ops, bounds, alive, depth, grid)
        ids_b, ranges_b, tests_b = associate_before(before, separable_axes, bounds, alive, depth, grid)
        if tests_b is not None:  # the binary-search path could add slack-level pairs; every-tile was exact
            assert torch.equal(ids, ids_b) and torch.equal(ranges, ranges_b), f"{name}: lists differ from before"
        t_new = median_seconds(lambda: associate_pairs(ops, bounds, alive, depth, grid), args.repeats)
        t_old = median_seconds(lambda: associate_before(before, separable_axes, bounds, alive, depth, grid),
                             args.repeats)
        n, pairs, tests = bounds.shape[0], int(counts.sum()), int(tests.sum())
        rows.append(f"| {name} | {n} | {grid.height}x{grid.width}, {int(grid.tile_active.sum())}/{grid.num_tiles} "
                    f"active tiles | {pairs} | {'binary search' if tests_b is None else f'{tests_b:.3g}'} | {tests} ({tests / (4 * pairs + 64 * n):.2f}) | "
                    f"{1e3 * t_old:.1f} | {1e3 * t_new:.1f} | {t_old / t_new:.1f}x |")
        print(rows[-1], flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    args.out.write_text(f"""# Association cost on the CPU: tile-pyramid search vs every-tile search

- device: CPU, {platform.machine()}, {torch.get_num_threads()} threads (2 cores shared with other jobs: absolute
  times are noisy, the before/after ratio is measured in one process on the same inputs); torch {torch.__version__}
- commit: {commit.strip()} (before: {BEFORE_COMMIT}, main's csrc built as a second extension)
- command: `.venv/bin/python benchmarks/cpu_association.py`
- association only (count, scan, emit, sort, ranges) from precomputed PBFs; time: median of {args.repeats} runs
  after a warm-up. Lists identical (asserted where main tested every tile; where main took its binary-search
  path for a full BEAP grid it could add pairs within a 1e-6 slack). Tile tests: before = 2 passes x alive
  Gaussians x active tiles; after = the count pass's pyramid tests + the emit pass's box tests, and in brackets the
  fraction of the bound tests/test_association_cost.py asserts (4 x pairs + 64 x N). Main's CPU build was
  single-threaded, this one runs on ATen's threads: the time ratio mixes both; the tile-test ratio does not.

| case | Gaussians | grid | pairs | tile tests before | tile tests after (of bound) | ms before | ms after | speed-up |
| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: |
""" + "\n".join(rows) + "\n")
    print(args.out.read_text())


if __name__ == "__main__":
    main()
