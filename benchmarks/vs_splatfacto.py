"""geer against splatfacto through geer-compare at 128^2, every method over the same seeds, on one of two scenes:

- dev_room: the dev room (Blender Cycles): its 180-degree fisheye views (geer, geer on BEAP images, splatfacto with
  gsplat's fisheye EWA) and the 90-degree pinhole views of the same poses (geer, geer on BEAP images, splatfacto);
  then what BEAP resampling loses by itself. Writes benchmarks/vs_splatfacto.md and .png.
- donut_room: a capture rendered from real Gaussians (benchmarks/gaussian_scene.py: the trained 3DGS donut in a
  textured box, float64 ground truth): its 90-degree pinhole views (geer, splatfacto) and 200-degree fisheye views
  of the same poses (geer, splatfacto-fisheye). Writes benchmarks/vs_splatfacto_donut_room.md and .png.

Where geer's runs end with more Gaussians than splatfacto's, geer-capped (geer's defaults, densification stopped at
the fewest Gaussians of the views' splatfacto runs: splatfacto-fisheye on fisheye views, splatfacto on pinhole
views) is trained too: a row at equal counts.

    python -m benchmarks.vs_splatfacto --work DIR [--scene dev_room] [--steps 1000] [--seeds 1 2 3] [--extra]
                                       [--note TEXT ...]

--extra: also splatfacto on a 120-degree pinhole undistortion of the fisheye (and, on the dev room, splatfacto as
shipped: 10-16 dB behind). Each method trains into a table of its own, DIR/SCENE/VIEWS_METHOD
(benchmarks/compare_cells.py), kept while it was made with today's config, steps and seeds (benchmarks/
densify_default.py trains its geer cells in the same folders when given the same DIR).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Dict, List, Tuple

from benchmarks.common import BENCHMARKS, header
from benchmarks.compare_cells import SCENES, difference, made_at, run_cell, runs_of, scene_dir

METHODS = {"dev_room": {"fisheye": ("geer", "geer-beap", "splatfacto-fisheye"),
                        "pinhole": ("geer", "geer-beap", "splatfacto")},
           "donut_room": {"pinhole": ("geer", "splatfacto"), "fisheye": ("geer", "splatfacto-fisheye")}}
EXTRA = {"dev_room": ("splatfacto", "splatfacto-pinhole"), "donut_room": ("splatfacto-pinhole",)}  # fisheye views
PEER = {"fisheye": "splatfacto-fisheye", "pinhole": "splatfacto"}  # its runs set geer-capped's cap
REPORTS = {"dev_room": ("vs_splatfacto", "the dev room at 128^2"),
           "donut_room": ("vs_splatfacto_donut_room", "the donut room at 128^2 (real 3DGS Gaussians in a box of "
                          "Gaussians; fisheye views 200 degrees)")}
FIGURES = ("psnr", "ssim", "central_psnr", "peripheral_psnr", "lpips")
GEER_ROWS = ("geer", "geer-capped")  # set against the best splatfacto variant


def train_views(work: Path, scene: str, views: str, methods: Tuple[str, ...], steps: int,
                seeds: List[int]) -> Dict[str, Path]:
    """Each method's table on the scene's views (splatfacto's first), plus geer-capped where geer's runs end with
    more Gaussians than the fewest of the views' PEER runs (the cap)."""
    tables = {}
    for method in sorted(methods, key=lambda m: not m.startswith("splatfacto")):
        print(f"[vs_splatfacto] {scene} {views}: {method}", flush=True)
        tables[method] = run_cell(work, scene, views, method, steps, seeds)
    cap = min(r["gaussians"] for r in runs_of(tables[PEER[views]], PEER[views]))
    if max(r["gaussians"] for r in runs_of(tables["geer"], "geer")) > cap:
        print(f"[vs_splatfacto] {scene} {views}: geer-capped at {cap:,} Gaussians", flush=True)
        tables["geer-capped"] = run_cell(work, scene, views, "geer-capped", steps, seeds, "--max-gaussians", str(cap))
    return {m: tables[m] for m in sorted(tables, key=_order)}


def _order(method: str) -> Tuple[int, str]:
    """The tables' order: geer's rows, geer's other variants, splatfacto's."""
    return (0 if method in GEER_ROWS else 1 if method.startswith("geer") else 2), method


def against_splatfacto(views: str, tables: Dict[str, Path]) -> Tuple[List[str], List[Tuple[str, str, str]]]:
    """Table rows of each geer row against the best splatfacto variant (by mean), figure by figure, and the
    readings as (geer row, reading, cell): "geer ahead" / "not distinguishable" / "geer behind" by the 95 % Welch
    interval, "one seed" without one."""
    rows, readings = [], []
    splat = [m for m in tables if m.startswith("splatfacto")]
    for geer in [m for m in GEER_ROWS if m in tables]:
        mine = runs_of(tables[geer], geer)
        periphery = any(r.get("peripheral_psnr") is not None for r in mine)
        for key in [k for k in FIGURES if periphery or k != "central_psnr"]:  # no periphery: the centre is psnr
            sign = -1 if key == "lpips" else 1  # lower LPIPS is better
            theirs = {m: [r[key] for r in runs_of(tables[m], m) if r.get(key) is not None] for m in splat}
            theirs = {m: v for m, v in theirs.items() if v}
            a = [r[key] for r in mine if r.get(key) is not None]
            if not a or not theirs:
                continue
            best = max(theirs, key=lambda m: sign * sum(theirs[m]) / len(theirs[m]))
            diff, half, cell = difference(a, theirs[best], key)
            reading = ("one seed" if math.isnan(half) else "geer ahead" if sign * diff - half > 0 else
                       "geer behind" if sign * diff + half < 0 else "not distinguishable")
            counts = [sum(r["gaussians"] for r in runs) / len(runs) for runs in (mine, runs_of(tables[best], best))]
            rows.append(f"| {views} | {key} | {geer}: {sum(a) / len(a):.4g} | {best}: "
                        f"{sum(theirs[best]) / len(theirs[best]):.4g} | {cell} | {counts[0]:,.0f} / {counts[1]:,.0f} | "
                        f"{reading} |")
            readings.append((geer, reading, f"{views} {key} {cell}"))
    return rows, readings


def verdict(readings: List[Tuple[str, str, str]]) -> List[str]:
    """One line per geer row: how many figures read each way, and which."""
    lines = []
    for geer in dict.fromkeys(g for g, _, _ in readings):
        by = {}
        for g, reading, cell in readings:
            if g == geer:
                by.setdefault(reading, []).append(cell)
        lines.append(f"`{geer}` against the best splatfacto variant, figure by figure: " + "; ".join(
            f"{reading} in {len(cells)} ({', '.join(cells)})" for reading, cells in by.items()))
    return lines


def merged_table(tables: Dict[str, Path]) -> Tuple[str, List]:
    """One geer-compare table of every method in `tables` (and the results, with their pictured renders); the
    protocol lists each distinct line of the tables' protocols once."""
    from geer_ns.compare import report

    results, skipped, lines = [], {}, []
    for table in tables.values():
        found, skip, protocol = report.load(table.parent)
        results += found
        skipped.update(skip)
        lines += [line for line in protocol if line not in lines]
    text = report.markdown(results, skipped, lines).replace("## geer-compare\n", "")
    made = ", ".join(f"{m} {made_at(t)}" for m, t in tables.items())
    return f"Tables trained at: {made}.\n" + text, results


def beap_loss(room: Path) -> str:
    """What BEAP resampling loses by itself: the test images to BEAP cells and back, PSNR against the originals."""
    from geer_ns.compare.capture import load_capture
    from geer_ns.data.beap import beap_to_native
    from geer_ns.data.datamanager import to_beap
    from geer_ns.data.views import beap_view
    from geer_ns.metrics.regions import masked_psnr

    lines = ["## What BEAP resampling loses by itself (test images to BEAP and back, PSNR against the originals)", "",
             "| views | valid pixels | BEAP cells | round trip PSNR | central |", "| --- | ---: | ---: | ---: | ---: |"]
    for views in ("fisheye", "pinhole"):
        capture = load_capture(room / f"transforms_{views}.json", 45.0)
        grid = beap_view(capture.camera).grid
        full, central = [], []
        for view in capture.views:
            beap, ok = to_beap(view.image, view.camera, view.valid, 2)
            back, covered = beap_to_native(beap, grid, view.camera, ok)
            full.append(masked_psnr(back.double(), view.image.double(), view.valid & covered))
            central.append(masked_psnr(back.double(), view.image.double(), view.valid & covered & view.central))
        lines.append(f"| {views} | {int(view.valid.sum())} | {grid.width * grid.height} | "
                     f"{sum(full) / len(full):.2f} | {sum(central) / len(central):.2f} |")
    return "\n".join(lines) + "\n"


def picture(transforms: Path, results: List, path: Path) -> None:
    """The capture's first test view: ground truth, each method's render and its error (full colour: a shared
    palette shifted the renders' hues away from the ground truth's)."""
    from geer_ns.compare import report
    from geer_ns.compare.capture import load_capture

    report.picture(load_capture(transforms, 45.0), results, path, views=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="scenes in DIR, runs in DIR/SCENE/VIEWS_METHOD")
    ap.add_argument("--scene", choices=SCENES, default="dev_room")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--extra", action="store_true", help="also splatfacto on pinhole undistortions of the fisheye")
    ap.add_argument("--note", nargs="*", default=[], help="lines for the report's header")
    args = ap.parse_args()
    room = scene_dir(args.work, args.scene)
    name, title = REPORTS[args.scene]
    summary = ["| views | figure | geer row | best splatfacto variant | geer - it | Gaussians (geer / it) | reading |",
               "| --- | --- | ---: | ---: | ---: | ---: | --- |"]
    sections, readings = [], []
    for views, methods in METHODS[args.scene].items():
        methods += EXTRA[args.scene] if args.extra and views == "fisheye" else ()
        tables = train_views(args.work, args.scene, views, methods, args.steps, args.seeds)
        rows, found = against_splatfacto(views, tables)
        summary += rows
        readings += found
        text, results = merged_table(tables)
        sections.append(f"## {views} views\n\n{text}")
        if views == "fisheye":
            pictured = results
    text = header(f"geer against splatfacto (geer-compare), {title}",
                  f"every method: {args.steps} steps of nerfstudio's trainer, the same schedule options "
                  f"(docs/compare.md), seeds {' '.join(map(str, args.seeds))}; `geer`: geer at its defaults",
                  *verdict(readings), *args.note)
    picture(room / "transforms_fisheye.json", pictured, BENCHMARKS / f"{name}.png")  # after the header's commit
    text += "\n## geer against the best splatfacto variant (difference of the means, 95 % Welch interval)\n\n"
    text += "\n".join(summary) + "\n"
    if args.scene == "dev_room":
        text += "\n" + beap_loss(room)
    text += "".join(f"\n{section}" for section in sections)
    text += f"\n![the first fisheye test view: ground truth, each method, its error]({name}.png)\n"
    (BENCHMARKS / f"{name}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
