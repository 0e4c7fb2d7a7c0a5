"""A capture rendered from real Gaussians: the trained 3DGS donut (test data, 45,624 Gaussians) inside a
textured box of flat Gaussians, seen from 48 poses around it by a 90-degree pinhole and a 200-degree equidistant
fisheye, ground truth rendered in float64 (nerfstudio format, PNG, like the dev room).

The box gives every ray a surface (no background for a method to guess) and the 200-degree views something to
see behind the camera; the fisheye's image circle is its mask (as the dev room's). The images are exact renders of a Gaussian scene, so they favour no rasterizer's
approximation except by being exact: the float64 render is checked against the brute-force reference
(every ray against every Gaussian) on two views, and the report says by how much they differ.

    python -m benchmarks.gaussian_scene --size 128 --work DIR   # prints DIR/donut_room_128
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import test_data

VIEWS = 48
FISHEYE_FOV_DEG = 200.0
TEST_EVERY = 8  # every 8th view is a test view, as in the dev room


def donut_scene() -> tuple[tuple[torch.Tensor, ...], torch.Tensor, float]:
    """The donut's Gaussians in float64 (means, quats wxyz, scales, opacities, RGB colours: SH degree 0), its
    centre and the radius holding 95 % of its means."""
    from plyfile import PlyData

    v = PlyData.read(str(test_data("donut_3dgs.ply")))["vertex"]
    col = lambda *names: torch.tensor(np.stack([np.asarray(v[n], np.float64) for n in names], -1))  # noqa: E731
    means = col("x", "y", "z")
    colors = (0.5 + 0.28209479177387814 * col("f_dc_0", "f_dc_1", "f_dc_2")).clamp(0.0, 1.0)  # SH degree 0 as RGB
    quats = col("rot_0", "rot_1", "rot_2", "rot_3")
    scene = (means, quats / quats.norm(dim=-1, keepdim=True), col("scale_0", "scale_1", "scale_2").exp(),
             torch.sigmoid(col("opacity")[:, 0]), colors)
    centre = means.median(0).values
    radius = float((means - centre).norm(dim=-1).quantile(0.95))
    return scene, centre, radius


def box_walls(centre: torch.Tensor, half: float, cells: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """The six inner faces of a cube (side 2 `half` around `centre`), each a `cells` x `cells` grid of flat,
    nearly opaque Gaussians coloured by a smooth pattern with a checker on it (seeded): texture at every scale
    a 128^2 view resolves."""
    g = torch.Generator().manual_seed(seed)
    step = 2 * half / cells
    u = (torch.arange(cells, dtype=torch.float64) + 0.5) * step - half
    a, b = torch.meshgrid(u, u, indexing="ij")
    a, b = a.reshape(-1), b.reshape(-1)
    means, quats, colors = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = torch.zeros(a.numel(), 3, dtype=torch.float64)
            p[:, axis] = sign * half
            p[:, (axis + 1) % 3], p[:, (axis + 2) % 3] = a, b
            means.append(p + centre)
            # a rotation taking the Gaussian's z axis (its thin one) to the face normal
            q = {0: (math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0), 1: (math.sqrt(0.5), -math.sqrt(0.5), 0.0, 0.0),
                 2: (1.0, 0.0, 0.0, 0.0)}[axis]
            quats.append(torch.tensor(q, dtype=torch.float64).expand(a.numel(), 4))
            phase = torch.rand(3, 3, generator=g, dtype=torch.float64) * 2 * math.pi
            freq = 1.0 + 3.0 * torch.rand(3, 2, generator=g, dtype=torch.float64)
            smooth = 0.5 + 0.25 * torch.sin(freq[:, :1].T * a[:, None] / half * math.pi + phase[0]) \
                + 0.15 * torch.cos(freq[:, 1:].T * b[:, None] / half * math.pi + phase[1])
            checker = ((torch.floor(a / (4 * step)) + torch.floor(b / (4 * step))) % 2)[:, None]
            colors.append((smooth * (0.75 + 0.25 * checker)).clamp(0.02, 0.98))
    n = 6 * a.numel()
    # sigma 0.8 step at opacity 0.995: no light through the walls between centres (under 0.5 %)
    scales = torch.tensor([0.8 * step, 0.8 * step, 0.02 * step], dtype=torch.float64).expand(n, 3)
    return (torch.cat(means), torch.cat(quats), scales.contiguous(), torch.full((n,), 0.995, dtype=torch.float64),
            torch.cat(colors))


def orbit_poses(centre: torch.Tensor, radius: float) -> torch.Tensor:
    """VIEWS camera-to-world poses (OpenCV axes) on a wavy orbit at 2 `radius` around `centre`, each looking at
    a point near the centre."""
    poses = []
    for i in range(VIEWS):
        phi = 2 * math.pi * i / VIEWS
        eye = centre + radius * torch.tensor([2.0 * math.cos(phi), 2.0 * math.sin(phi), 0.6 * math.sin(3 * phi)],
                                             dtype=torch.float64)
        target = centre + 0.2 * radius * torch.tensor([math.sin(2 * phi), math.cos(5 * phi), 0.0],
                                                      dtype=torch.float64)
        forward = (target - eye) / (target - eye).norm()
        right = torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        right = right / right.norm()
        down = torch.linalg.cross(forward, right)
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
        poses.append(c2w)
    return torch.stack(poses)


def cameras(size: int) -> dict:
    """The two cameras at size^2: (transforms.json intrinsics, the geer camera model)."""
    from geer_ns.cameras import OpenCVFisheyeCamera, PinholeCamera

    c = size / 2
    f_fish = (c - 1.0) / math.radians(FISHEYE_FOV_DEG / 2)  # the crop circle (radius c - 1) at 100 degrees
    return {
        "pinhole": ({"camera_model": "OPENCV", "fl_x": c, "fl_y": c, "cx": c, "cy": c, "w": size, "h": size,
                     "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0},
                    PinholeCamera(size, size, c, c, c, c)),
        "fisheye": ({"camera_model": "OPENCV_FISHEYE", "fl_x": f_fish, "fl_y": f_fish, "cx": c, "cy": c, "w": size,
                     "h": size, "k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0, "fisheye_crop_radius": c - 1.0},
                    OpenCVFisheyeCamera(size, size, f_fish, f_fish, c, c)),
    }


def scene_and_poses() -> tuple[tuple[torch.Tensor, ...], torch.Tensor]:
    """The whole scene (donut and box, float64) and the VIEWS poses."""
    donut, centre, radius = donut_scene()
    walls = box_walls(centre, 4.0 * radius, 48)
    scene = tuple(torch.cat([d, w]) for d, w in zip(donut, walls))
    return scene, orbit_poses(centre, radius)


def write_seed_points(path: Path, scene: tuple[torch.Tensor, ...], count: int = 20000, seed: int = 0) -> None:
    """`count` of the scene's means, jittered by 1 % of the box, with their colours: the SfM-like seed both
    methods start from."""
    from geer_ns.data.ply import write_ply_points

    g = torch.Generator().manual_seed(seed)
    means, colors = scene[0], scene[4]
    pick = torch.randperm(means.shape[0], generator=g)[:count]
    extent = float((means.max(0).values - means.min(0).values).max())
    xyz = means[pick] + 0.01 * extent * torch.randn(count, 3, generator=g, dtype=torch.float64)
    write_ply_points(path, xyz.numpy(), (colors[pick] * 255).round().clamp(0, 255).numpy().astype(np.uint8))


def donut_room(work: Path, size: int, check_views: int = 2) -> Path:
    """Write the capture at size^2 under work/donut_room_SIZE (kept if there): transforms_pinhole.json and
    transforms_fisheye.json over the same poses, PNG images, the fisheye's circle mask, points3d.ply, and
    reference_check.json (the float64
    render against the brute-force reference on `check_views` views of each camera)."""
    import cv2

    from geer_ns.render import RayGrid, render
    from geer_ns.render.rasterize import render_brute_force

    out = work / f"donut_room_{size}"
    if (out / "transforms_fisheye.json").is_file():
        return out
    out.mkdir(parents=True, exist_ok=True)
    scene, poses = scene_and_poses()
    write_seed_points(out / "points3d.ply", scene)
    names = [f"frame_{i:05d}.png" for i in range(VIEWS)]
    test = [n for i, n in enumerate(names) if i % TEST_EVERY == 0]
    check = {}
    for kind, (intrinsics, camera) in cameras(size).items():
        dirs, valid = camera.pixel_rays(torch.float64)
        grid = RayGrid.from_rays(dirs, valid, tile_size=16)
        (out / f"images_{kind}").mkdir(exist_ok=True)
        inside, mask = torch.ones(size, size, dtype=torch.bool), {}
        if "fisheye_crop_radius" in intrinsics:  # the image circle as a mask (the dev room's way): every method
            # trains and is scored inside it, and the corners are black as a real fisheye's
            centre = torch.arange(size, dtype=torch.float64) + 0.5 - intrinsics["cx"]
            inside = centre[:, None] ** 2 + centre[None, :] ** 2 <= intrinsics["fisheye_crop_radius"] ** 2
            (out / "masks").mkdir(exist_ok=True)
            cv2.imwrite(str(out / "masks" / "fisheye_mask.png"), inside.to(torch.uint8).numpy() * 255)
            mask = {"mask_path": "masks/fisheye_mask.png"}
        frames, worst = [], 0.0
        for i, c2w in enumerate(poses):
            viewmat = torch.linalg.inv(c2w)
            with torch.no_grad():
                rgb = render(*scene, viewmat, grid, sh_degree=None, backend="torch").rgb
                if i < check_views:
                    brute = render_brute_force(*scene, viewmat, grid, sh_degree=None).rgb
                    worst = max(worst, float((rgb - brute).abs().max()))
            image = (rgb.clamp(0, 1) * inside[..., None] * 255).round().to(torch.uint8).numpy()
            cv2.imwrite(str(out / f"images_{kind}" / names[i]), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            gl = c2w @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))  # OpenCV -> OpenGL axes
            frames.append({"file_path": f"images_{kind}/{names[i]}", "transform_matrix": gl.tolist(), **mask})
            print(f"[donut_room] {kind} view {i + 1}/{VIEWS}", file=sys.stderr, flush=True)
        meta = dict(intrinsics, ply_file_path="points3d.ply", frames=frames,
                    train_filenames=[f"images_{kind}/{n}" for n in names if n not in test],
                    val_filenames=[f"images_{kind}/{n}" for n in test],
                    test_filenames=[f"images_{kind}/{n}" for n in test])
        (out / f"transforms_{kind}.json").write_text(json.dumps(meta))
        check[kind] = {"views_checked": check_views, "max_abs_rgb_vs_brute_force": worst}
    (out / "reference_check.json").write_text(json.dumps(check))
    return out


def main() -> None:
    """`python -m benchmarks.gaussian_scene --size SIZE [--work DIR]`: write the donut room, print its folder."""
    import argparse

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--work", type=Path, default=Path("/tmp/geer_bench"))
    args = ap.parse_args()
    print(donut_room(args.work, args.size))


if __name__ == "__main__":
    main()
