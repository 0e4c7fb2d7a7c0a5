"""benchmarks/bench_gpu.py --dry-run: the GPU benchmark's whole pipeline on the CPU at tiny sizes.

Checks that the table has one row per (scene, camera, geer contender) of configs/bench_gpu.yaml with finite
timings, tile statistics and the error against the float64 brute-force reference, and that gsplat rows say
they need CUDA. Runs in-process (about 20 s on 2 cores).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest
import torch
import yaml
from conftest import shared_data

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def dry_run(tmp_path_factory):
    shared_data("donut_3dgs.ply")
    shared_data("test_garden.npz")
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_gpu

    out = tmp_path_factory.mktemp("bench") / "gpu_dry.md"
    threads = torch.get_num_threads()
    try:
        assert bench_gpu.main(["--dry-run", "--out", str(out)]) == 0
    finally:
        torch.set_num_threads(threads)
    cfg = yaml.safe_load((ROOT / "configs" / "bench_gpu.yaml").read_text())
    return cfg, out.read_text(), json.loads(out.with_suffix(".json").read_text())


def test_dry_run_rows(dry_run):
    cfg, table, result = dry_run
    assert result["dry_run"] is True and result["device"].startswith("CPU")
    assert result["commit"] and result["command"].endswith(" --dry-run --out " + result["command"].split()[-1])
    rows = {(r["scene"], r["camera"], r["contender"]): r for r in result["rows"]}
    geer = [c for c in cfg["contenders"] if c["renderer"] == "geer"]
    assert geer
    for scene in cfg["scenes"]:
        for cam in cfg["cameras"]:
            for c in geer:
                r = rows[(scene["name"], cam["name"], c["name"])]
                assert r["width"] <= 64 and r["height"] <= 64 and r["n_gaussians"] <= 5000
                timed = [r.get(k) for k in ("forward_ms", "fwd_bwd_ms", "backward_ms") if r.get(k) is not None]
                assert timed and all(math.isfinite(t) and t > 0 for t in timed), r
                assert r["finite"] and r["pairs"] > 0 and math.isfinite(r["gpt_mean"]) and math.isfinite(r["gpt_std"])
                assert math.isfinite(r["err_max"]) and r["err_rays"] > 0 and r["err_psnr"] > 0
                if c.get("lambda_mode", "opacity") == "opacity":  # the exact renderer: float32 rounding only
                    assert r["err_max"] < 1e-3, r
                line = f"| {scene['name']} | {cam['name']} | {c['name']} |"
                assert line in table
            gs = rows[(scene["name"], cam["name"], "gsplat")]
            assert "needs CUDA" in gs["note"] and "forward_ms" not in gs


def test_dry_run_fisheye_skips_corner_tiles(dry_run):
    _, _, result = dry_run
    fish = [r for r in result["rows"] if "fisheye" in r["camera"] and "active_tiles" in r]
    assert fish and all(r["active_tiles"] < r["tiles"] for r in fish)
