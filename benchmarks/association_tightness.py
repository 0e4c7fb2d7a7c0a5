"""Association tightness (paper Tab. K.6 on our data): (tile, Gaussian) pairs per tile for geer's PBF (the box test
alone, as before, and with the cone test), gsplat 1.4's EWA bounds and a 3DGUT-style unscented-transform bound, on a
trained dev room at 512^2: a 180-degree equidistant fisheye's own pixels, its BEAP grid, a 220-degree fisheye and a
90-degree pinhole view; and the CPU build's forward render time per geer variant (same inputs, one process), with
the images' largest difference between the variants.

    EWA  gsplat.cuda._torch_impl._fully_fused_projection (its PyTorch reference: pinhole or equidistant-fisheye
         Jacobian, eps2d 0.3, radius ceil(3 sqrt(largest eigenvalue))), tiles as gsplat's isect_tiles: the tiles
         overlapped by the square [mean - radius, mean + radius]. No BEAP projection in gsplat: n/a there; beyond
         90 degrees off axis (the 220-degree fisheye) gsplat culls the Gaussian (depth <= near plane).
    UT   3DGUT's unscented transform (alpha 1, beta 2, kappa 0: the 7 sigma points mean and mean +- sqrt(3) M e_i,
         mean weight 0 / 1/6, covariance weight 2 / 1/6) through the camera's own projection, + eps2d 0.3, the same
         3-sigma square and tiles; a Gaussian whose mean's projection is undefined (behind a pinhole) is culled.

    python -m benchmarks.association_tightness --run RUN     # RUN: a geer run on the dev room (docs/benchmarks.md)
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch

from benchmarks.common import BENCHMARKS, header, test_data

SIZE, TILE = 512, 16


# ------------------------------------------------------------------------------------------ scene and views
def load_scene(run: Path):
    """(means, quats, scales, opacities, colours [N,3] (view-independent: SH band 0), step) of the latest checkpoint
    of a geer run trained with SH."""
    ckpt = sorted((run / "nerfstudio_models").glob("step-*.ckpt"))[-1]
    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    p = {k.split(".")[-1]: v for k, v in state["pipeline"].items() if ".gauss_params." in k}
    colors = (0.28209479177387814 * p["features_dc"] + 0.5).clamp_min(0.0)  # SH band 0 (sh_degree > 0 runs)
    return (p["means"].float(), torch.nn.functional.normalize(p["quats"].float(), dim=-1), p["scales"].exp().float(),
            torch.sigmoid(p["opacities"]).squeeze(-1).float(), colors.float(), int(state["step"]))


def test_viewmat(run: Path) -> torch.Tensor:
    """World-to-camera (OpenCV) of the dev room's first held-out view, in the run's dataparser frame."""
    from geer_ns.render.transforms import world_to_camera_opencv

    meta = json.loads(test_data("fisheye_room_dev", "transforms_fisheye.json").read_text())
    name = meta["test_filenames"][0]
    frame = next(f for f in meta["frames"] if f["file_path"] == name)
    tf = json.loads((run / "dataparser_transforms.json").read_text())
    c2w = torch.tensor(frame["transform_matrix"], dtype=torch.float64)
    t = torch.eye(4, dtype=torch.float64)
    t[:3] = torch.tensor(tf["transform"], dtype=torch.float64)
    c2w = t @ c2w
    c2w[:3, 3] *= tf["scale"]
    return world_to_camera_opencv(c2w[:3].float())


def equidistant_rays(fov_deg: float, size: int = SIZE):
    """([S,S,3] unit rays, [S,S] valid, focal) of an equidistant fisheye whose inscribed circle spans fov_deg."""
    f = (size / 2) / math.radians(fov_deg / 2)
    c = (torch.arange(size, dtype=torch.float64) + 0.5) - size / 2
    v, u = torch.meshgrid(c, c, indexing="ij")
    ang = torch.sqrt(u * u + v * v) / f
    psi = torch.atan2(v, u)
    dirs = torch.stack([ang.sin() * psi.cos(), ang.sin() * psi.sin(), ang.cos()], -1)
    return dirs.float(), ang <= math.radians(fov_deg / 2), f


def views():
    """name -> (RayGrid, projection kind, focal, [3x3] K or None)."""
    from geer_ns.cameras import EquidistantCamera
    from geer_ns.data.views import beap_view
    from geer_ns.render import RayGrid

    out = {}
    for fov in (180.0, 220.0):
        dirs, valid, f = equidistant_rays(fov)
        out[f"fisheye {fov:.0f} (own pixels)"] = (RayGrid.from_rays(dirs, valid, TILE), "fisheye", f)
    f180 = (SIZE / 2) / (math.pi / 2)
    beap = beap_view(EquidistantCamera(SIZE, SIZE, f180, f180, SIZE / 2, SIZE / 2)).rays
    out["fisheye 180, BEAP grid"] = (beap, "beap", None)
    fp = (SIZE / 2) / math.tan(math.radians(45))
    c = (torch.arange(SIZE, dtype=torch.float64) + 0.5 - SIZE / 2) / fp
    v, u = torch.meshgrid(c, c, indexing="ij")
    dirs = torch.nn.functional.normalize(torch.stack([u, v, torch.ones_like(u)], -1), dim=-1).float()
    out["pinhole 90"] = (RayGrid.from_rays(dirs, None, TILE), "pinhole", fp)
    return out


# ------------------------------------------------------------------------------------------ splatting bounds
def _box_counts(means2d: torch.Tensor, radius: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[tiles_y * tiles_x] Gaussians per tile for 2-D squares (gsplat 1.4 isect_tiles: tile_min = floor((m - r) /
    tile), tile_max = ceil((m + r) / tile), clamped to the image's tiles; radius 0: culled)."""
    tx, ty = -(-width // TILE), -(-height // TILE)
    keep = radius > 0
    m, r = means2d[keep].double(), radius[keep].double()[:, None]
    lo = torch.floor((m - r) / TILE).long()
    hi = torch.ceil((m + r) / TILE).long()
    x0, x1 = lo[:, 0].clamp(0, tx), hi[:, 0].clamp(0, tx)
    y0, y1 = lo[:, 1].clamp(0, ty), hi[:, 1].clamp(0, ty)
    ok = (x1 > x0) & (y1 > y0)
    diff = torch.zeros(ty + 1, tx + 1, dtype=torch.long)
    for (ys, xs, sign) in ((y0, x0, 1), (y0, x1, -1), (y1, x0, -1), (y1, x1, 1)):
        diff.index_put_((ys[ok], xs[ok]), torch.full_like(ys[ok], sign), accumulate=True)
    return diff.cumsum(0).cumsum(1)[:ty, :tx].reshape(-1)


def _covariances(quats, scales):
    from geer_ns.render import quat_to_rotmat

    m = quat_to_rotmat(quats) * scales[:, None, :]
    return m, m @ m.transpose(-1, -2)


def ewa_counts(scene, viewmat, kind: str, focal: float):
    """gsplat 1.4's EWA: its PyTorch reference projection and 3-sigma squares."""
    from geer_ns.gsplat_private import fully_fused_projection

    means, quats, scales = scene[:3]
    _, covars = _covariances(quats, scales)
    k = torch.tensor([[focal, 0, SIZE / 2], [0, focal, SIZE / 2], [0, 0, 1]], dtype=torch.float32)
    radii, means2d, _, _, _ = fully_fused_projection(means, covars, viewmat[None], k[None], SIZE, SIZE,
                                                      camera_model=kind)
    alive = scene[3] >= 1 / 255
    return _box_counts(means2d[0][alive], radii[0][alive].float(), SIZE, SIZE)


def _project(points: torch.Tensor, kind: str, focal: float, grid):
    """[..., 2] pixel coordinates of camera-frame points [..., 3] and [...] whether defined."""
    x, y, z = points.unbind(-1)
    if kind == "pinhole":
        ok = z > 1e-2
        zs = torch.where(ok, z, torch.ones_like(z))
        return torch.stack([focal * x / zs + SIZE / 2, focal * y / zs + SIZE / 2], -1), ok
    if kind == "fisheye":
        rxy = torch.sqrt(x * x + y * y)
        ang = torch.atan2(rxy, z)
        s = focal * ang / rxy.clamp_min(1e-12)
        return torch.stack([s * x + SIZE / 2, s * y + SIZE / 2], -1), rxy > 0
    # BEAP: pixels uniform in theta = atan2(x, z), phi = atan2(y, z) over the grid's span (cell centres)
    theta, phi = torch.atan2(x, z), torch.atan2(y, z)
    d = grid.dirs.double().reshape(grid.height, grid.width, 3)
    t_row, p_col = torch.atan2(d[0, :, 0], d[0, :, 2]), torch.atan2(d[:, 0, 1], d[:, 0, 2])
    step_t, step_p = float(t_row[1] - t_row[0]), float(p_col[1] - p_col[0])
    u = (theta - float(t_row[0])) / step_t + 0.5
    v = (phi - float(p_col[0])) / step_p + 0.5
    return torch.stack([u, v], -1), (z > 0) & (theta.abs() < math.pi / 2) & (phi.abs() < math.pi / 2)


def ut_counts(scene, viewmat, kind: str, focal: float, grid):
    """3DGUT-style unscented transform of each Gaussian through the camera's projection, then 3-sigma squares."""
    means, quats, scales, opac = scene[:4]
    m, _ = _covariances(quats.double(), scales.double())
    rot, trans = viewmat[:3, :3].double(), viewmat[:3, 3].double()
    mu = means.double() @ rot.T + trans
    cols = (rot @ m) * math.sqrt(3.0)  # [N, 3, 3]: columns are the sigma offsets
    offsets = torch.cat([torch.zeros_like(mu)[:, None], cols.transpose(1, 2), -cols.transpose(1, 2)], 1)  # [N, 7, 3]
    pts, ok = _project(mu[:, None] + offsets, kind, focal, grid)
    wm = torch.tensor([0.0] + [1 / 6] * 6, dtype=torch.float64)
    wc = torch.tensor([2.0] + [1 / 6] * 6, dtype=torch.float64)
    mean2d = (wm[None, :, None] * pts).sum(1)
    dev = pts - mean2d[:, None]
    cov = (wc[None, :, None, None] * dev[..., :, None] * dev[..., None, :]).sum(1)
    cov = cov + 0.3 * torch.eye(2, dtype=torch.float64)
    b = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
    radius = torch.ceil(3.0 * torch.sqrt(b + torch.sqrt((b * b - det).clamp_min(0.01))))
    valid = ok.all(1) & (opac.double() >= 1 / 255) & torch.isfinite(radius)
    return _box_counts(mean2d, torch.where(valid, radius, torch.zeros_like(radius)), grid.width, grid.height)


# ------------------------------------------------------------------------------------------ geer
def geer_variant(ops, scene, viewmat, grid, cone: bool):
    """(tile counts [T], rgb [R,3], seconds (the forward: preprocess, association, render; the association alone),
    (whiten, o_u, ids, ranges)) on the CPU build."""
    from geer_ns.render.associate import pbf_cull_pieces
    from geer_ns.render.cones import gaussian_cone_form
    from geer_ns.render.cuda_backend import associate_pairs
    from geer_ns.render.pbf import pbf_lambda_sq

    means, quats, scales, opac, colors = scene[:5]
    start = time.perf_counter()
    with torch.no_grad():
        rot = viewmat[:3, :3].contiguous()
        means_c = means @ rot.T + viewmat[:3, 3]
        w, o_u, _rgb, bounds, alive, inside = ops.preprocess_forward(
            means_c.contiguous(), quats, scales, opac, means.new_zeros(means.shape[0], 0, 3), means_c, rot, -1, False)
        form = gaussian_cone_form(w, o_u, pbf_lambda_sq(opac)[0], inside) if cone else None
        t_assoc = time.perf_counter()
        ids, ranges, _, _ = associate_pairs(ops, bounds, alive, means_c.norm(dim=-1), grid, form)
        t_assoc = time.perf_counter() - t_assoc
        rgb, *_ = ops.render_forward(w, o_u, colors.contiguous(), opac, pbf_cull_pieces(bounds), grid.dirs,
                                     grid.ray_cull_bounds(torch.float32), grid.warp_cull_bounds(torch.float32),
                                     grid.valid, ids, ranges, grid.height, grid.width, grid.tile_size, False,
                                     w.new_zeros(0), w.new_zeros(0), 0)
    return (ranges[:, 1] - ranges[:, 0]).long(), rgb, (time.perf_counter() - start, t_assoc), (w, o_u, ids, ranges)


def exact_floor(grid, opac, lists) -> torch.Tensor:
    """[T] per tile, the listed Gaussians that reach at least one of its valid rays with alpha >= 1/255 (float64,
    the half-line rule, every ray of the tile): what a complete tile test cannot go below."""
    w, o_u, ids, ranges = lists
    counts = (ranges[:, 1] - ranges[:, 0]).long()
    tiles = torch.repeat_interleave(torch.arange(grid.num_tiles), counts)
    ids = ids.long()
    whiten, o, q_max = w.double().reshape(-1, 3, 3), o_u.double(), 2 * torch.log(255 * opac.double())
    seen = torch.zeros(ids.numel(), dtype=torch.bool)
    for s in range(0, ids.numel(), 4096):
        g, t = ids[s:s + 4096], tiles[s:s + 4096]
        r = grid.tile_rays[t]
        ok = (r >= 0) & grid.valid[r.clamp_min(0)]
        d_u = torch.einsum("mij,mpj->mpi", whiten[g], grid.dirs.double()[r.clamp_min(0)])
        og = o[g][:, None].expand_as(d_u)
        dist_sq = torch.linalg.cross(og, d_u, dim=-1).square().sum(-1) / d_u.square().sum(-1)
        q = torch.where((og * d_u).sum(-1) < 0, dist_sq, og.square().sum(-1))
        seen[s:s + 4096] = ((q <= q_max[g][:, None]) & ok).any(1)
    return torch.bincount(tiles[seen], minlength=grid.num_tiles)


def _stats(counts: torch.Tensor) -> tuple[float, float]:
    c = counts.double()
    return float(c.mean()), float(c.std())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a geer run's output folder (checkpoint inside)")
    parser.add_argument("--out", type=Path, default=BENCHMARKS / "association_tightness.md")
    args = parser.parse_args()
    from geer_ns.render.cuda_backend import load_cpu_ops

    ops = load_cpu_ops()
    *scene, step = load_scene(args.run)
    viewmat = test_viewmat(args.run)
    rows = []
    for name, (grid, kind, focal) in views().items():
        before, rgb0, t0, _ = geer_variant(ops, scene, viewmat, grid, cone=False)
        after, rgb1, t1, lists = geer_variant(ops, scene, viewmat, grid, cone=True)
        diff = float((rgb0 - rgb1).abs().max())
        floor = exact_floor(grid, scene[3], lists)
        ewa = ewa_counts(scene, viewmat, kind, focal) if kind != "beap" else None
        ut = ut_counts(scene, viewmat, kind, focal, grid)
        rows.append((name, grid, before, after, floor, ewa, ut, t0, t1, diff))
        print(name, _stats(before), _stats(after), _stats(floor), ewa is not None and _stats(ewa), _stats(ut), t0, t1,
              diff, flush=True)
    write_report(args, rows, scene, step)


def write_report(args, rows, scene, step) -> None:
    lines = [
        header("Association tightness: (tile, Gaussian) pairs per tile, geer's PBF against EWA and UT (paper Tab. K.6)",
               "times: one run each (the box / box+cone ratio is measured in one process on the same inputs)",
               f"scene: the dev room (fisheye_room_dev) trained by `ns-train geer` on its 128^2 fisheye views to step "
               f"{step} ({scene[0].shape[0]:,} Gaussians); view: its first held-out pose; 512 x 512 rays, 16 x 16 tiles."),
        "- pairs per tile: mean and standard deviation over all tiles of the image (1024; geer lists nothing on tiles "
        "without a valid ray, EWA/UT count every tile in the image). geer: box = the (theta, phi) PBF test alone "
        "(before), box+cone = with the cone test (docs/association.md). EWA: gsplat 1.4's own projection and "
        "3-sigma squares; UT: 3DGUT-style sigma points through the camera's projection (see the script's docstring).",
        "- exact floor: per tile, the Gaussians that reach at least one of its rays with alpha >= 1/255 (float64 brute "
        "force over every ray of every listed pair): no complete association can list fewer. EWA's 3-sigma squares "
        "are not complete (an opaque Gaussian reaches alpha = 1/255 at 3.33 sigma), so PBF / EWA is bounded below by "
        "floor / EWA, whatever the tile test.",
        "- time: the CPU build's forward (preprocess, association, render) per geer variant and its association "
        "alone, one run each; image "
        "difference: the largest |rgb before - rgb after| over the image (float32).",
        "",
        "| view | geer box (before) | geer box+cone | exact floor | EWA (gsplat) | UT | box+cone / EWA | floor / EWA | box+cone / UT | forward ms, box / box+cone | association ms, box / box+cone | max image diff |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]

    def cell(c):
        if c is None:
            return "n/a"
        m, s = _stats(c)
        return f"{m:.1f} ± {s:.1f}"

    def ratio(a, b):
        return f"{a.sum().item() / max(b.sum().item(), 1):.2f}" if b is not None else "n/a"

    for name, grid, before, after, floor, ewa, ut, t0, t1, diff in rows:
        lines.append(f"| {name} | {cell(before)} | {cell(after)} | {cell(floor)} | {cell(ewa)} | {cell(ut)} | "
                     f"{ratio(after, ewa)} | {ratio(floor, ewa)} | {ratio(after, ut)} | {1e3 * t0[0]:.0f} / {1e3 * t1[0]:.0f} | "
                     f"{1e3 * t0[1]:.0f} / {1e3 * t1[1]:.0f} | "
                     f"{diff:.1e} |")
    args.out.write_text(lines[0] + "\n".join(lines[1:]) + "\n")
    print(args.out.read_text())


if __name__ == "__main__":
    main()
