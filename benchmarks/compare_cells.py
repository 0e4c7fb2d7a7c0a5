"""Cells of geer-compare studies: one method trained on one scene's views over the seeds, in a table of its own
(WORK/SCENE/VIEWS_METHOD), kept while its runs carry today's config (geer-compare --keep-finished). Used by
benchmarks/vs_splatfacto.py and benchmarks/densify_default.py."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import List, Sequence, Tuple

from benchmarks.common import ROOT, commit, dev_room

SCENES = ("dev_room", "donut_room")


def scene_dir(work: Path, scene: str) -> Path:
    """The scene's capture at 128^2 under work (written once): the dev room or the donut room."""
    if scene == "dev_room":
        return dev_room(work, 128)
    if scene == "donut_room":
        from benchmarks.gaussian_scene import donut_room

        return donut_room(work, 128)
    raise ValueError(f"scene: one of {SCENES}, got {scene!r}")


def cell_dir(work: Path, scene: str, views: str, method: str) -> Path:
    """The folder of a method's table on a scene's views. Studies sharing WORK share their cells (one table per
    method and views: another --steps or --seeds trains it anew, in place)."""
    return work / scene / f"{views}_{method}"


def run_cell(work: Path, scene: str, views: str, method: str, steps: int, seeds: Sequence[int],
             *options: str) -> Path:
    """geer-compare of `method` alone on the scene's `views` (extra geer-compare `options`), unless its folder
    holds a table of these runs made with today's config; the table (compare.json). A trained table gets a
    `commit` file beside it."""
    out = cell_dir(work, scene, views, method)
    before = (out / "compare.json").stat().st_mtime_ns if (out / "compare.json").is_file() else None
    data = scene_dir(work, scene) / f"transforms_{views}.json"
    subprocess.run([sys.executable, "-m", "geer_ns.compare", "--data", str(data), "--steps", str(steps), "--seeds",
                    *map(str, seeds), "--methods", method, "--output-dir", str(out), "--keep-finished", *options],
                   cwd=ROOT, check=True)
    if (out / "compare.json").stat().st_mtime_ns != before:
        (out / "commit").write_text(commit() + "\n")
    return out / "compare.json"


def made_at(table: Path) -> str:
    """The commit a table was trained at ("?" when not recorded)."""
    path = table.parent / "commit"
    return path.read_text().strip() if path.is_file() else "?"


def runs_of(table: Path, method: str) -> List[dict]:
    """The method's runs (one row per seed) in a compare.json."""
    return [r for r in json.loads(table.read_text())["results"] if r["method"] == method]


def welch(a: List[float], b: List[float]) -> Tuple[float, float]:
    """mean(a) - mean(b) and the half-width of Welch's 95 % interval (NaN with fewer than two runs a side)."""
    from scipy.stats import ttest_ind

    diff = sum(a) / len(a) - sum(b) / len(b)
    if min(len(a), len(b)) < 2:
        return diff, float("nan")
    low, high = ttest_ind(a, b, equal_var=False).confidence_interval(0.95)
    return diff, (high - low) / 2


def difference(a: List[float], b: List[float], key: str) -> Tuple[float, float, str]:
    """welch(a, b) and its cell, e.g. "+0.37 +- 0.25" (SSIM and LPIPS to three decimals; "+0.37 (no interval)"
    with one run a side)."""
    diff, half = welch(a, b)
    fmt = "{:+.3f}" if key in ("ssim", "lpips") else "{:+.2f}"
    interval = " (no interval)" if math.isnan(half) else " +- " + fmt.format(half).lstrip("+")
    return diff, half, fmt.format(diff) + interval
