"""Which densification default geer ships: its statistics in halves of each camera's own image with geer's two
extra rules (`geer`, densify-units image: the default this study chose), in pixels of the 300-pixel reference
camera (`geer-reference-units`, the default before it), or at splatfacto's density (`geer-gsplat-units`: gsplat's
units, neither rule). Each trains on both scenes of benchmarks/vs_splatfacto.py (the dev room and the donut room at
128^2) and both of their cameras, over the same seeds, through geer-compare; the report gives every cell and each
method's difference from the first one.

    python -m benchmarks.densify_default --work DIR [--steps 1000] [--seeds 1 2 3] [--note TEXT ...]

Runs train into DIR/SCENE/VIEWS_METHOD (benchmarks/compare_cells.py); a table there made with today's config, steps
and seeds is kept (with the commit it was made at). Where DIR is also vs_splatfacto.py's --work, its splatfacto runs of
a cell are shown beside geer's (not trained here). Writes benchmarks/densify_default.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Dict, List, Tuple

from benchmarks.common import BENCHMARKS, header
from benchmarks.compare_cells import cell_dir, difference, made_at, run_cell, runs_of
from geer_ns.compare.report import cell, interval

VARIANTS = ("geer-reference-units", "geer", "geer-gsplat-units")
CELLS = [(scene, views) for scene in ("dev_room", "donut_room") for views in ("fisheye", "pinhole")]
FIGURES = ("psnr", "ssim", "central_psnr", "peripheral_psnr")


def report(tables: Dict[Tuple[str, str, str], Path], variants: List[str], default: str = "geer") -> str:
    """The report's tables: every cell (`tables` may also hold a splatfacto peer's runs for a cell, shown beside
    them), each variant's difference from the first, and the default's from the peer where there is one."""
    runs = {key: runs_of(path, key[2]) for key, path in tables.items()}
    lines = ["## Every cell (mean +- 95 % interval over the seeds)", "",
             "| scene | views | method | PSNR | SSIM | central PSNR | peripheral PSNR | Gaussians | train s | table made at |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    formats = [(k, "{:.3f}" if k == "ssim" else "{:.2f}") for k in FIGURES] + [("gaussians", "{:,.0f}"),
                                                                              ("train_seconds", "{:.0f}")]
    for scene, views in CELLS:
        for (s, v, method), path in tables.items():
            if (s, v) != (scene, views):
                continue
            cells = [cell(interval([x.get(key) for x in runs[(s, v, method)]]), fmt) for key, fmt in formats]
            lines.append(f"| {scene} | {views} | {method} | " + " | ".join(cells) + f" | {made_at(path)} |")
    base = variants[0]
    lines += ["", f"## Each variant against `{base}` (difference of the means, 95 % Welch interval)", "",
              "| method | " + " | ".join(f"{s} {v}" for s, v in CELLS) + " | mean over the cells |",
              "| --- | " + " | ".join("---:" for _ in CELLS) + " | ---: |"]
    for key in ("psnr", "ssim"):
        for method in variants[1:]:
            cells, diffs = [], []
            for scene, views in CELLS:
                d, _, text = difference([x[key] for x in runs[(scene, views, method)]],
                                        [x[key] for x in runs[(scene, views, base)]], key)
                diffs.append(d)
                cells.append(text)
            lines.append(f"| {method} ({key}) | " + " | ".join(cells) + f" | {sum(diffs) / len(diffs):+.3f} |")
    peers = [(scene, views, m) for (scene, views, m) in tables if m.startswith("splatfacto")]
    if peers and default in variants:
        lines += ["", f"## `{default}` against splatfacto's runs of the same cell (where DIR holds them)", "",
                  "| scene | views | peer | PSNR | SSIM |", "| --- | --- | --- | ---: | ---: |"]
        for scene, views, peer in peers:
            cells = [difference([x[key] for x in runs[(scene, views, default)]],
                                [x[key] for x in runs[(scene, views, peer)]], key)[2] for key in ("psnr", "ssim")]
            lines.append(f"| {scene} | {views} | {peer} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--methods", nargs="+", default=list(VARIANTS), help="the first is the baseline")
    ap.add_argument("--note", nargs="*", default=[], help="lines for the report's header")
    args = ap.parse_args()
    tables = {}
    for method in args.methods:  # one method over every cell, then the next
        for scene, views in CELLS:
            print(f"[densify_default] {scene} {views} {method}", flush=True)
            tables[(scene, views, method)] = run_cell(args.work, scene, views, method, args.steps, args.seeds)
    for scene, views in CELLS:  # splatfacto's runs of a cell where vs_splatfacto.py left them in DIR (shown, not trained)
        peer = "splatfacto-fisheye" if views == "fisheye" else "splatfacto"
        found = cell_dir(args.work, scene, views, peer) / "compare.json"
        if found.is_file() and {(r["steps"], r["seed"]) for r in runs_of(found, peer)} == {
                (args.steps, s) for s in args.seeds}:
            tables[(scene, views, peer)] = found
    text = header("Densification default: gsplat's units against geer's reference units, two scenes, two cameras",
                  f"every run: {args.steps} steps of nerfstudio's trainer through geer-compare (the same schedule, "
                  f"scoring and pixels as benchmarks/vs_splatfacto.py), seeds {' '.join(map(str, args.seeds))}, 128^2",
                  "methods: " + "; ".join(f"`{m}`" for m in args.methods) + " (geer_ns/compare/methods.py)",
                  *args.note)
    text += "\n" + report(tables, args.methods)
    (BENCHMARKS / "densify_default.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
