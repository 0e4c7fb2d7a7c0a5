"""Per-camera densification memory of Gaussian-parallel training against the fraction of the shard a camera sees:
what one camera of a round builds on a process over its shard of --rows Gaussians, now (over the rows the
camera sees: gaussian_parallel.sharded_outputs) and before (over the whole shard, as commit 764e106 built it).

Per case, in a fresh process (MALLOC_MMAP_THRESHOLD_=1 MiB: freed tensors go back, RSS is what is held): a shard
of --rows Gaussians of which a fraction lies inside a pinhole camera's field of view and the rest behind it, or
all around a 360-degree (equirectangular) camera; the camera's rows (sharded_render.visible_rows), their
parameters, the probe (model.probe), the displaced means and the record (ViewProbe.record), with the two leaves'
gradients a backward leaves (zeros of their size). Figures: the bytes of what stays until the step's backward
(the record, the lateral basis autograd saves, the leaves' gradients), the peak RSS growth while building it
(the float64 temporaries of angular_signal and the rows' gathered parameters included, both), and the times.
Writes its section of benchmarks/distributed_memory.md.

    .venv/bin/python benchmarks/probe_memory.py [--rows 1000000]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import textwrap
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

HEADING = "## Per-camera probe memory against the visible fraction"
CASES = [("pinhole", 0.1), ("pinhole", 0.5), ("pinhole", 1.0), ("360", 1.0)]
MMAP_THRESHOLD = 1 << 20


def camera(kind: str):
    """A 64 x 64 pinhole of 60 degrees, or a 128 x 64 equirectangular camera, at the origin (nerfstudio axes)."""
    import torch
    from nerfstudio.cameras.cameras import Cameras, CameraType

    from geer_ns.data.datamanager import VIEW_KEY

    if kind == "pinhole":
        f = 32 / math.tan(math.radians(30))
        cam = Cameras(camera_to_worlds=torch.eye(4)[:3][None], fx=f, fy=f, cx=32.0, cy=32.0, width=64, height=64,
                      camera_type=CameraType.PERSPECTIVE)
    else:
        cam = Cameras(camera_to_worlds=torch.eye(4)[:3][None], fx=64.0, fy=64.0, cx=64.0, cy=32.0, width=128,
                      height=64, camera_type=CameraType.EQUIRECTANGULAR)
    cam.metadata = {VIEW_KEY: "native"}
    return cam


def shard(n: int, kind: str, fraction: float):
    """n Gaussians (raw parameters as a model holds them): `fraction` of them, spread over the rows, inside the
    pinhole's field of view (a 40-degree cone) 2-4 m away, the rest behind it; for the 360-degree camera all of
    them on a shell 2-4 m around it."""
    import torch

    gen = torch.Generator().manual_seed(0)
    direction = torch.randn(n, 3, generator=gen)
    direction = direction / direction.norm(dim=-1, keepdim=True)
    if kind == "pinhole":
        ahead = torch.rand(n, generator=gen) < fraction
        xy = (torch.rand(n, 2, generator=gen) - 0.5) * 2 * math.tan(math.radians(20))
        cone = torch.cat([xy, -torch.ones(n, 1)], -1)
        behind = direction * torch.tensor([1.0, 1.0, 0.0]) + torch.tensor([0.0, 0.0, 1.0])
        direction = torch.where(ahead[:, None], cone, behind)
        direction = direction / direction.norm(dim=-1, keepdim=True)
    means = direction * (2.0 + 2.0 * torch.rand(n, 1, generator=gen))
    quats = torch.randn(n, 4, generator=gen)
    return {"means": means, "scales": torch.full((n, 3), math.log(0.01)), "quats": quats,
            "features_dc": torch.rand(n, 3, generator=gen), "features_rest": torch.zeros(n, 15, 3),
            "opacities": torch.zeros(n, 1)}


def tiny_model():
    """A GeerModel (its probe, activations, views); its own Gaussians are not used."""
    import torch
    from nerfstudio.data.scene_box import SceneBox

    from geer_ns.model import GeerModelConfig

    config = GeerModelConfig(background_color="black", sh_degree=3, num_downscales=0)
    box = SceneBox(aabb=torch.tensor([[-4.0, -4.0, -4.0], [4.0, 4.0, 4.0]]))
    seed = (torch.rand(64, 3) - 0.5, torch.zeros(64, 3, dtype=torch.uint8))
    model = config.setup(scene_box=box, num_train_data=1, metadata={}, device="cpu", seed_points=seed)
    model.train()
    return model


def held_bytes(record, lateral) -> int:
    """Bytes of the distinct storages of a record, the lateral basis and the leaves' gradients."""
    tensors = [record.offsets, record.absgrad, record.visible, record.scale, record.radius, record.weight,
               record.pixels, record.rows, lateral, record.offsets.grad, record.absgrad.grad]
    storages = {t.untyped_storage().data_ptr(): t.untyped_storage().nbytes() for t in tensors if t is not None}
    return sum(storages.values())


def measure(n: int, kind: str, fraction: float, sparse: bool) -> dict:
    """One case in this process (see the module docstring)."""
    import torch

    from geer_ns.distributed.gaussian_parallel import probe_rows
    from geer_ns.distributed.sharded_render import visible_rows
    from peak_rss import peak_kib, peak_reset

    torch.set_grad_enabled(True)
    model = tiny_model()
    cam = camera(kind)
    view = model.view_for(cam)
    params = {name: torch.nn.Parameter(t) for name, t in shard(n, kind, fraction).items()}
    viewmat = model.viewmat(cam.camera_to_worlds[0], "cpu")
    grid = view.rays
    start = time.perf_counter()
    rows = visible_rows(params, viewmat, grid, model.config.lambda_mode, model.activated)
    search_s = time.perf_counter() - start
    before = peak_reset()
    start = time.perf_counter()
    if sparse:  # sharded_outputs now: the probe over the rows, then their parameters, displacement and record
        probe = probe_rows(model, view, params, viewmat, rows)
        part = {name: torch.index_select(p, 0, rows) for name, p in params.items()}
        scales, opacities = model.activated(part)
        moved = probe.displace(part["means"], viewmat)
        record = probe.record(torch.ones(rows.shape[0], dtype=torch.bool), torch.zeros(rows.shape[0]))
    else:  # before: over the whole shard, then the rows (their parameters gathered as rows_of did)
        with torch.no_grad():
            scales, opacities = model.activated(params)
        probe = model.probe(view, params["means"], viewmat, scales, opacities)
        moved = probe.displace(params["means"], viewmat)[rows]
        part = {name: p[rows] for name, p in params.items()}
        seen = torch.zeros(n, dtype=torch.bool)
        seen[rows] = True
        weight = torch.zeros(n)
        record = probe.record(seen, weight)
        del scales, opacities
    for leaf in (record.offsets, record.absgrad):
        leaf.grad = torch.zeros_like(leaf)  # what the backward leaves
    build_s = time.perf_counter() - start
    peak = peak_kib() - before
    lateral = probe.signal.lateral
    del probe, part
    return {"kind": kind, "fraction": fraction, "sparse": sparse, "n": n, "rows": int(rows.shape[0]),
            "held_bytes": held_bytes(record, lateral), "peak_kib": peak, "search_s": search_s,
            "build_s": build_s, "moved": int(moved.shape[0])}


def section(results, args, commit: str) -> str:
    load = os.getloadavg()[0]
    import torch

    lines = [HEADING, "",
             f"- device: CPU, {platform.machine()}, {os.cpu_count()} cores shared with other jobs (load average "
             f"{load:.1f}; times indicative only), torch {torch.__version__}",
             f"- commit: {commit}",
             f"- command: `PYTHONPATH=$PWD nice -n 10 .venv/bin/python benchmarks/probe_memory.py --rows {args.rows}`",
             f"- one camera of a round on one process whose shard holds {args.rows:,} Gaussians (SH degree 3): "
             "its probe, displaced rows and record, now over the rows it sees, before (764e106) over the whole "
             "shard. held: the record, the lateral basis autograd keeps and the two leaves' gradients, until "
             "the step's backward; peak: RSS growth while building them (float64 temporaries and the rows' gathered "
             "parameters, 236 bytes a row, included); "
             "search: sharded_render.visible_rows over the shard (both)", "",
             "| camera | visible | rows seen | held now MiB | held before MiB | now/before | peak now MiB "
             "| peak before MiB | search s | build now s | build before s |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for kind, fraction in CASES:
        now = next(r for r in results if r["kind"] == kind and r["fraction"] == fraction and r["sparse"])
        old = next(r for r in results if r["kind"] == kind and r["fraction"] == fraction and not r["sparse"])
        name = "pinhole 60 deg" if kind == "pinhole" else "360 deg (equirect)"
        lines.append(
            f"| {name} | {now['rows'] / now['n']:.0%} | {now['rows']:,} | {now['held_bytes'] / 2**20:,.1f} | "
            f"{old['held_bytes'] / 2**20:,.1f} | {now['held_bytes'] / old['held_bytes']:.2f} | "
            f"{now['peak_kib'] / 1024:,.0f} | {old['peak_kib'] / 1024:,.0f} | {now['search_s']:.2f} | "
            f"{now['build_s']:.2f} | {old['build_s']:.2f} |")
    now, old = results[0], results[1]
    lines += ["", f"Held per camera now: {now['held_bytes'] / max(now['rows'], 1):.0f} bytes a row the camera sees "
              f"(before: {old['held_bytes'] / old['n']:.0f} bytes a row of the shard, whatever the camera sees). A "
              "step holds the sum over its cameras; a 360-degree camera sees every row, so there it is the shard's "
              "size (the limit: docs/distributed.md, Limits).", ""]
    return "\n".join(wrapped for line in lines for wrapped in (
        textwrap.wrap(line, 115, subsequent_indent="  " if line.startswith("- ") else "", break_on_hyphens=False)
        if not line.startswith("|") else [line]) or [""])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows", type=int, default=1_000_000, help="Gaussians in the shard")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "distributed_memory.md")
    ap.add_argument("--case", help=argparse.SUPPRESS)  # internal: one case, JSON on stdout
    args = ap.parse_args()
    if args.case:
        kind, fraction, sparse = args.case.split(",")
        print(json.dumps(measure(args.rows, kind, float(fraction), sparse == "1")))
        return
    env = {**os.environ, "MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD)}
    results = []
    for kind, fraction in CASES:
        for sparse in ("1", "0"):
            out = subprocess.run([sys.executable, __file__, "--rows", str(args.rows), "--case",
                                  f"{kind},{fraction},{sparse}"], env=env, capture_output=True, text=True, check=True)
            results.append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(results[-1], flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    text = args.out.read_text() if args.out.is_file() else ""
    head, _, rest = text.partition(HEADING)
    tail = rest[rest.find("\n## "):] if "\n## " in rest else ""
    args.out.write_text(head.rstrip("\n") + "\n\n" + section(results, args, commit) + tail)


if __name__ == "__main__":
    main()
