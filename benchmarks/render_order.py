"""Compositing order: each ray's own (geer_order.h) against the per-view order, in run time, accuracy and popping.

    python -m benchmarks.render_order train WORK_DIR [--size S --steps N --seeds 0 1 2 --orders view ray:32]
    python -m benchmarks.render_order speed WORK_DIR [--size S --runs K]
    python -m benchmarks.render_order popping WORK_DIR [--size S --frames F --pixels P]

`train`: the dev room's fisheye views trained with `ns-train geer` at the same steps, schedule and seed for each
order, scored by `ns-eval` on the held-out views (the run's own order); the trained Gaussians are kept for the
other two. `speed`: one process, the CPU build, a render's forward + backward of the same Gaussians and rays in
each order, alternated after a warm-up, median of K: the trained dev room (180-degree fisheye) and the trained
donut (a 3DGS scene of large Gaussians, from inside its ring's reach), and the error of each order against the
exact one. `popping`: smooth camera paths (an orbit and a walk) through the trained scenes, 180 and 220-degree
fisheyes and a pinhole: for each frame the difference to the float64 exact per-ray render; the largest change of
any pixel between consecutive frames; and the largest jump at a vanishing step: the 3 intervals whose change
departs most from their neighbours' (a continuous image changes smoothly along the path) are bisected 14 times,
each time into the half that changes more, so that a continuous change shrinks to ~2^-14 of the interval's and
a discontinuity keeps its size. Each prints a markdown table (benchmarks/render_order.md).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from pathlib import Path

import torch

from benchmarks.common import dev_room, header, run_config, short_schedule, test_data, train_and_score

SIZE = 128


def scene_file(work: Path, order: str, seed: int, size: int, steps: int) -> Path:
    return work / f"room_{size}_{steps}_{order.replace(':', '')}_seed{seed}"


def train(work: Path, size: int, steps: int, seeds: list[int], orders: list[str]) -> list[str]:
    """The dev room's fisheye views trained in each order; per seed and order a record (metrics) and the Gaussians."""
    data = dev_room(work, size) / "transforms_fisheye.json"
    rows = ["| order | seed | PSNR | SSIM | Gaussians | training (s) |", "| --- | --- | --- | --- | --- | --- |"]
    results: dict = {order: [] for order in orders}
    for seed in seeds:
        for order in orders:
            base = scene_file(work, order, seed, size, steps)
            record = base.with_suffix(".json")
            if not record.exists():  # one record per run, kept: a rerun reports without retraining
                config = run_config(data, work / "runs", base.name, steps,
                                    {**short_schedule(), "composite_order": order}, seed=seed)
                metrics, seconds, pipeline = train_and_score(config)
                model = pipeline.model
                params = model.render_gaussians()
                colors, degree = model.colors(params)
                scales, opacities = model.activated(params)
                cameras = pipeline.datamanager.train_dataparser_outputs.cameras
                torch.save({"means": params["means"], "quats": params["quats"], "scales": scales,
                            "opacities": opacities, "colors": colors, "sh_degree": degree,
                            "camera_to_worlds": cameras.camera_to_worlds.detach().cpu()}, base.with_suffix(".pt"))
                record.write_text(json.dumps({**metrics, "seconds": seconds, "gaussians": model.num_points}))
            r = json.loads(record.read_text())
            results[order].append(r)
            rows.append(f"| {order} | {seed} | {r['psnr']:.3f} | {r['ssim']:.4f} | {r['gaussians']:,} | "
                        f"{r['seconds']:.0f} |")
    rows += ["", "| order | PSNR mean ± 95 % | SSIM mean ± 95 % | runs |", "| --- | --- | --- | --- |"]
    for order, runs in results.items():
        rows.append(f"| {order} | {_interval([r['psnr'] for r in runs], 3)} | "
                    f"{_interval([r['ssim'] for r in runs], 4)} | {len(runs)} |")
    if len(orders) == 2 and all(len(v) == len(seeds) for v in results.values()):
        diff = [b["psnr"] - a["psnr"] for a, b in zip(*results.values())]
        rows.append(f"| {orders[1]} - {orders[0]} (paired) | {_interval(diff, 3)} | | {len(diff)} |")
    return rows


def _interval(values: list[float], digits: int) -> str:
    """mean ± half the 95 % Student-t interval (n - 1 degrees of freedom)."""
    t95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571}
    mean = statistics.fmean(values)
    if len(values) < 2:
        return f"{mean:.{digits}f}"
    half = t95.get(len(values) - 1, 2.0) * statistics.stdev(values) / math.sqrt(len(values))
    return f"{mean:.{digits}f} ± {half:.{digits}f}"


# ------------------------------------------------------------------------------------------ scenes
def trained_room(work: Path, size: int, steps: int, dtype=torch.float32):
    """((means, quats, scales, opacities, SH colours), SH degree(s), the training cameras' camera-to-world poses
    [C,4,4] float64, OpenCV axes, in capture order) of the dev room trained in the per-view order, seed 0."""
    saved = torch.load(scene_file(work, "view", 0, size, steps).with_suffix(".pt"))
    scene = tuple(saved[k].detach().to(dtype).contiguous() for k in ("means", "quats", "scales", "opacities", "colors"))
    c2w = torch.eye(4, dtype=torch.float64).repeat(saved["camera_to_worlds"].shape[0], 1, 1)
    c2w[:, :3, :4] = saved["camera_to_worlds"].double()
    c2w[:, :3, 1:3] *= -1  # nerfstudio's OpenGL camera axes -> OpenCV
    degree = saved["sh_degree"]  # one for all, or each Gaussian's own ([N]: sh-per-gaussian)
    return scene, degree if isinstance(degree, torch.Tensor) else int(degree), c2w


def donut(dtype=torch.float32):
    """The trained donut (3DGS PLY, SH degree 0) and a camera-to-world pose inside its ring's reach."""
    import numpy as np
    from plyfile import PlyData

    v = PlyData.read(str(test_data("donut_3dgs.ply")))["vertex"]
    col = lambda *names: torch.tensor(np.stack([np.asarray(v[n]) for n in names], -1))  # noqa: E731
    means = col("x", "y", "z")
    colors = 0.5 + 0.28209479177387814 * col("f_dc_0", "f_dc_1", "f_dc_2")  # SH degree 0 as RGB
    scene = (means, col("rot_0", "rot_1", "rot_2", "rot_3"), col("scale_0", "scale_1", "scale_2").exp(),
             torch.sigmoid(col("opacity")[:, 0]), colors.clamp_min(0))
    centre = means.median(0).values.double()
    radius = float((means - centre.float()).norm(dim=-1).quantile(0.95))
    return tuple(t.to(dtype).contiguous() for t in scene), centre, radius


# ------------------------------------------------------------------------------------------ speed
ORDERS = ("view", "ray", "ray:64", "ray:16")


def fisheye_grid(size: int, fov_deg: float, dtype=torch.float32):
    from geer_ns.cameras import EquidistantCamera
    from geer_ns.render import RayGrid

    f = (size / 2) / math.radians(fov_deg / 2)
    dirs, valid = EquidistantCamera(size, size, f, f, size / 2, size / 2).pixel_rays(dtype)
    return RayGrid.from_rays(dirs, valid, tile_size=16)


def pinhole_grid(size: int, dtype=torch.float32):
    from geer_ns.cameras import PinholeCamera
    from geer_ns.render import RayGrid

    dirs, valid = PinholeCamera(size, size, size / 2, size / 2, size / 2, size / 2).pixel_rays(dtype)  # 90 degrees
    return RayGrid.from_rays(dirs, valid, tile_size=16)


def look_from(c2w: torch.Tensor) -> torch.Tensor:
    """world-to-camera of a camera-to-world pose."""
    return torch.linalg.inv(c2w)


def speed(work: Path, size: int, steps: int, runs: int) -> list[str]:
    from geer_ns.render import render

    room, degree, c2w = trained_room(work, size, steps)
    ring, centre, radius = donut()
    donut_pose = torch.eye(4, dtype=torch.float64)
    donut_pose[:3, 3] = centre - torch.tensor([0.0, 0.0, 1.2 * radius], dtype=torch.float64)
    cases = {f"dev room, fisheye 180°, {size}²": (room, degree, look_from(c2w[3]), fisheye_grid(size, 180.0)),
             f"donut, fisheye 180°, {size}²": (ring, None, look_from(donut_pose), fisheye_grid(size, 180.0))}
    rows = [f"| scene | order | forward + backward (s, median of {runs}) | x view | forward (s) | x view | "
            "max abs rgb - exact |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for label, (scene, deg, viewmat, grid) in cases.items():
        def step(order: str) -> tuple[float, float, torch.Tensor]:
            leaves = [t.clone().requires_grad_(True) for t in scene]
            t0 = time.perf_counter()
            out = render(*leaves, viewmat, grid, sh_degree=deg, backend="cpu", order=order)
            (out.rgb.square().sum() + out.depth.sum()).backward()
            both = time.perf_counter() - t0
            with torch.no_grad():
                t0 = time.perf_counter()
                render(*scene, viewmat, grid, sh_degree=deg, backend="cpu", order=order)
                fwd = time.perf_counter() - t0
            return both, fwd, out.rgb.detach()

        for order in ORDERS:  # warm-up
            step(order)
        times: dict = {o: ([], []) for o in ORDERS}
        images = {}
        for _ in range(runs):
            for order in ORDERS:
                both, fwd, images[order] = step(order)
                times[order][0].append(both)
                times[order][1].append(fwd)
        base = [statistics.median(t) for t in times["view"]]
        for order in ORDERS:
            both, fwd = (statistics.median(t) for t in times[order])
            err = float((images[order] - images["ray"]).abs().max())
            rows.append(f"| {label} | {order} | {both:.4f} | {both / base[0]:.2f}x | {fwd:.4f} | {fwd / base[1]:.2f}x | "
                        f"{err:.2e} |")
    return rows

# ------------------------------------------------------------------------------------------ popping
POP_ORDERS = ("view", "ray:64", "ray")


def _axis_rotation(axis: torch.Tensor, angle: float) -> torch.Tensor:
    """[3,3] float64 rotation by `angle` (radians) about the unit `axis` (Rodrigues)."""
    k = torch.tensor([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def _slerp_pose(a: torch.Tensor, b: torch.Tensor, s: float) -> torch.Tensor:
    """camera-to-world between a (s = 0) and b (s = 1): rotation along the geodesic, centre linear."""
    from geer_ns.cameras.shutter import so3_exp, so3_log

    rel = a[:3, :3].T @ b[:3, :3]
    out = a.clone()
    out[:3, :3] = a[:3, :3] @ so3_exp(s * so3_log(rel[None]))[0]
    out[:3, 3] = (1 - s) * a[:3, 3] + s * b[:3, 3]
    return out


def paths(c2w_first: torch.Tensor, walk_to: list, centre: torch.Tensor, up: torch.Tensor, orbit_deg: float):
    """{name: pose(s) for s in [0, 1]}: "walk" through the poses walk_to (piecewise geodesic), "orbit" the first
    pose turned about the vertical axis through centre by orbit_deg."""
    stops = [c2w_first] + walk_to

    def walk(s: float) -> torch.Tensor:
        x = min(s, 1.0 - 1e-12) * (len(stops) - 1)
        i = int(x)
        return _slerp_pose(stops[i], stops[i + 1], x - i)

    def orbit(s: float) -> torch.Tensor:
        r = _axis_rotation(up, math.radians(orbit_deg) * s)
        out = c2w_first.clone()
        out[:3, :3] = r @ c2w_first[:3, :3]
        out[:3, 3] = centre + r @ (c2w_first[:3, 3] - centre)
        return out

    return {"walk": walk, "orbit": orbit}


def largest_vanishing_jump(render_at, s0: float, s1: float, levels: int) -> float:
    """The largest change of any pixel between two path parameters, followed by bisection into the half that
    changes most, `levels` times: a continuous image's change shrinks by ~2 a level, a discontinuity's stays."""
    i0, i1 = render_at(s0), render_at(s1)
    for _ in range(levels):
        mid = 0.5 * (s0 + s1)
        im = render_at(mid)
        a, b = float((im - i0).abs().max()), float((i1 - im).abs().max())
        if a >= b:
            s1, i1 = mid, im
        else:
            s0, i0 = mid, im
    return float((i1 - i0).abs().max())


def popping(work: Path, size: int, steps: int, frames: int, pixels: int, levels: int = 14,
            bisected: int = 3) -> list[str]:
    """The table of the module docstring: the room trained at `size`, images of `pixels`^2."""
    from geer_ns.render import render

    room, degree, c2w = trained_room(work, size, steps)
    ring, centre, radius = donut()
    room_centre = c2w[:, :3, 3].mean(0)
    room_up = -c2w[:, :3, 1].mean(0)
    room_up = room_up / room_up.norm()  # the cameras' mean up (OpenCV: -y)
    donut_start = torch.eye(4, dtype=torch.float64)
    donut_start[:3, 3] = centre - torch.tensor([0.0, 0.0, 1.2 * radius], dtype=torch.float64)
    donut_end = donut_start.clone()
    donut_end[:3, 3] = centre - torch.tensor([0.0, 0.0, 0.6 * radius], dtype=torch.float64)
    scenes = {
        "dev room": (room, degree, paths(c2w[0], [c2w[i] for i in (1, 2, 3)], room_centre, room_up, 60.0)),
        "donut": (ring, None, paths(donut_start, [donut_end], centre, torch.tensor([0.0, -1.0, 0.0],
                                                                                   dtype=torch.float64), 90.0)),
    }
    grids = {"fisheye 180°": lambda dt: fisheye_grid(pixels, 180.0, dt),
             "fisheye 220°": lambda dt: fisheye_grid(pixels, 220.0, dt), "pinhole 90°": lambda dt: pinhole_grid(pixels, dt)}
    rows = [f"| scene | path | camera | order | mean abs error vs float64 exact | largest abs error | largest change "
            f"between frames ({frames}) | largest jump at a vanishing step (2^-{levels} of a frame) | render (s) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for scene_name, (scene, deg, scene_paths) in scenes.items():
        scene64 = tuple(t.double() for t in scene)
        for path_name, pose in scene_paths.items():
            for cam_name, make_grid in grids.items():
                grid, grid64 = make_grid(torch.float32), make_grid(torch.float64)

                def image(order: str, s: float, exact64: bool = False) -> torch.Tensor:
                    viewmat = look_from(pose(s))
                    with torch.no_grad():
                        if exact64:
                            return render(*scene64, viewmat, grid64, sh_degree=deg, backend="cpu", order="ray").rgb
                        return render(*scene, viewmat, grid, sh_degree=deg, backend="cpu", order=order).rgb.double()

                params = [k / (frames - 1) for k in range(frames)]
                reference = [image("ray", s, exact64=True) for s in params]
                for order in POP_ORDERS:
                    t0 = time.perf_counter()
                    imgs = [image(order, s) for s in params]
                    seconds = (time.perf_counter() - t0) / frames
                    errs = [(a - b).abs() for a, b in zip(imgs, reference)]
                    changes = [float((b - a).abs().max()) for a, b in zip(imgs, imgs[1:])]
                    # where a pixel's change departs most from its neighbouring intervals' (a continuous image
                    # changes smoothly along the path, a discontinuity at once): the intervals bisected
                    bend = [0.0] + [float(((c - b) - 0.5 * ((b - a) + (d - c))).abs().max())
                                    for a, b, c, d in zip(imgs, imgs[1:], imgs[2:], imgs[3:])] + [0.0]
                    bend = bend + [0.0] * (len(changes) - len(bend))
                    worst = sorted(range(len(changes)), key=lambda i: -bend[i])[:bisected]
                    jump = max(largest_vanishing_jump(lambda s: image(order, s), params[i], params[i + 1], levels)
                               for i in worst)
                    rows.append(f"| {scene_name} | {path_name} | {cam_name} | {order} | "
                                f"{statistics.fmean(float(e.mean()) for e in errs):.2e} | "
                                f"{max(float(e.max()) for e in errs):.2e} | {max(changes):.3f} | {jump:.2e} | "
                                f"{seconds:.3f} |")
                    print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=("train", "speed", "popping"))
    parser.add_argument("work", type=Path, nargs="?", default=Path("/tmp/geer_render_order"))
    parser.add_argument("--size", type=int, default=SIZE)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--orders", nargs="+", default=["view", "ray:32"])
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--pixels", type=int, default=96, help="popping: the images' size")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    if args.what == "train":
        rows = train(args.work, args.size, args.steps, args.seeds, args.orders)
    elif args.what == "speed":
        rows = speed(args.work, args.size, args.steps, args.runs)
    else:
        rows = popping(args.work, args.size, args.steps, args.frames, args.pixels)
    print(header(f"Compositing order: {args.what}"))
    print("\n".join(rows))


if __name__ == "__main__":
    main()
