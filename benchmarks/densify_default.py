"""Which densification default geer ships: its statistics in halves of each camera's own image with geer's two
extra rules (`geer`, densify-units image: the default this study chose), in pixels of the 300-pixel reference
camera (`geer-reference-units`, the default before it), or at splatfacto's density (`geer-gsplat-units`: gsplat's
units, neither rule). Each trains on both scenes of benchmarks/vs_splatfacto.sh (the dev room and the donut room at
128^2) and both of their cameras, over the same seeds, through geer-compare; the report gives every cell and each
method's difference from the first one.

    python -m benchmarks.densify_default --work DIR [--steps 1000] [--seeds 1 2 3] [--note TEXT ...]

Runs train into DIR/SCENE/VIEWS_METHOD; a finished table of the same steps and seeds there is reused (with the
commit it was made at). Where DIR is also vs_splatfacto.sh's WORK, its splatfacto runs of a cell are shown beside
geer's (not trained here). Writes benchmarks/densify_default.md.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from benchmarks.common import BENCHMARKS, ROOT, commit, dev_room, header
from geer_ns.compare.report import interval

VARIANTS = ("geer-reference-units", "geer", "geer-gsplat-units")
CELLS = [(scene, views) for scene in ("dev_room", "donut_room") for views in ("fisheye", "pinhole")]
FIGURES = ("psnr", "ssim", "central_psnr", "peripheral_psnr")


def scene_dir(work: Path, scene: str) -> Path:
    if scene == "dev_room":
        return dev_room(work, 128)
    from benchmarks.gaussian_scene import donut_room

    return donut_room(work, 128)


def find_table(work: Path, scene: str, method: str, views: str, steps: int, seeds: List[int]) -> Optional[Path]:
    """A compare.json with `method`'s runs on `views` at these steps and seeds, or None: geer's in this script's
    work/scene/VIEWS_METHOD (a table elsewhere may hold a former default's rows under the same name), splatfacto's
    anywhere under work/scene."""
    pattern = "*" if method.startswith("splatfacto") else f"{views}_{method}"
    for path in sorted((work / scene).glob(f"{pattern}/compare.json")):
        table = json.loads(path.read_text())
        if not any(f"transforms_{views}.json" in line for line in table["protocol"]):  # its "Capture: ..." line
            continue
        runs = {(r["steps"], r["seed"]) for r in table["results"] if r["method"] == method}
        if runs == {(steps, s) for s in seeds}:
            return path
    return None


def run_cell(work: Path, scene: str, views: str, method: str, steps: int, seeds: List[int]) -> Path:
    """geer-compare of `method` alone on the scene's `views`; its table (compare.json)."""
    out = work / scene / f"{views}_{method}"
    data = scene_dir(work, scene) / f"transforms_{views}.json"
    subprocess.run([sys.executable, "-m", "geer_ns.compare", "--data", str(data), "--steps", str(steps), "--seeds",
                    *map(str, seeds), "--methods", method, "--output-dir", str(out)], cwd=ROOT, check=True)
    (out / "commit").write_text(commit() + "\n")
    return out / "compare.json"


def runs_of(table: Path, method: str) -> List[dict]:
    return [r for r in json.loads(table.read_text())["results"] if r["method"] == method]


def welch(a: List[float], b: List[float]) -> Tuple[float, float]:
    """mean(a) - mean(b) and the half-width of Welch's 95 % interval."""
    from scipy.stats import ttest_ind

    low, high = ttest_ind(a, b, equal_var=False).confidence_interval(0.95)
    return sum(a) / len(a) - sum(b) / len(b), (high - low) / 2


def report(tables: Dict[Tuple[str, str, str], Path], variants: List[str], default: str = "geer") -> str:
    """The report's tables: every cell (`tables` may also hold a splatfacto peer's runs for a cell, shown beside
    them), each variant's difference from the first, and the default's from the peer where there is one."""
    def made_at(path: Path) -> str:
        return (path.parent / "commit").read_text().strip() if (path.parent / "commit").is_file() else "?"

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
            cell = []
            for key, fmt in formats:
                m, h = interval([x.get(key) for x in runs[(s, v, method)]])
                cell.append("n/a" if math.isnan(m) else fmt.format(m) + ("" if math.isnan(h) else " +- " + fmt.format(h)))
            lines.append(f"| {scene} | {views} | {method} | " + " | ".join(cell) + f" | {made_at(path)} |")
    base = variants[0]
    lines += ["", f"## Each variant against `{base}` (difference of the means, 95 % Welch interval)", "",
              "| method | " + " | ".join(f"{s} {v}" for s, v in CELLS) + " | mean over the cells |",
              "| --- | " + " | ".join("---:" for _ in CELLS) + " | ---: |"]
    for key in ("psnr", "ssim"):
        for method in variants[1:]:
            cells, diffs = [], []
            for scene, views in CELLS:
                d, h = welch([x[key] for x in runs[(scene, views, method)]], [x[key] for x in runs[(scene, views, base)]])
                diffs.append(d)
                cells.append(f"{d:+.3f} +- {h:.3f}" if key == "ssim" else f"{d:+.2f} +- {h:.2f}")
            lines.append(f"| {method} ({key}) | " + " | ".join(cells) + f" | {sum(diffs) / len(diffs):+.3f} |")
    peers = [(scene, views, m) for (scene, views, m) in tables if m.startswith("splatfacto")]
    if peers and default in variants:
        lines += ["", f"## `{default}` against splatfacto's runs of the same cell (where DIR holds them)", "",
                  "| scene | views | peer | PSNR | SSIM |", "| --- | --- | --- | ---: | ---: |"]
        for scene, views, peer in peers:
            cells = []
            for key in ("psnr", "ssim"):
                d, h = welch([x[key] for x in runs[(scene, views, default)]], [x[key] for x in runs[(scene, views, peer)]])
                cells.append(f"{d:+.3f} +- {h:.3f}" if key == "ssim" else f"{d:+.2f} +- {h:.2f}")
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
            found = find_table(args.work, scene, method, views, args.steps, args.seeds)
            if found is None:
                print(f"[densify_default] {scene} {views} {method}: training", flush=True)
                found = run_cell(args.work, scene, views, method, args.steps, args.seeds)
            else:
                print(f"[densify_default] {scene} {views} {method}: reusing {found}", flush=True)
            tables[(scene, views, method)] = found
    for scene, views in CELLS:  # splatfacto's runs of a cell, when DIR holds them (not trained here)
        peer = "splatfacto-fisheye" if views == "fisheye" else "splatfacto"
        found = find_table(args.work, scene, peer, views, args.steps, args.seeds)
        if found is not None:
            tables[(scene, views, peer)] = found
    text = header("Densification default: gsplat's units against geer's reference units, two scenes, two cameras",
                  f"every run: {args.steps} steps of nerfstudio's trainer through geer-compare (the same schedule, "
                  f"scoring and pixels as benchmarks/vs_splatfacto.sh), seeds {' '.join(map(str, args.seeds))}, 128^2",
                  "methods: " + "; ".join(f"`{m}`" for m in args.methods) + " (geer_ns/compare/methods.py)",
                  *args.note)
    text += "\n" + report(tables, args.methods)
    (BENCHMARKS / "densify_default.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
