"""The GPU session, dry-run on the CPU: what the two device calls will read and run must work before a GPU does.

- benchmarks/gpu_prep.py (the session's CPU-side `prep`) puts every data file configs/bench_gpu.yaml references
  under .device/ (what a device call carries; ../shared does not travel), and the yaml reads nothing else;
- benchmarks/bench_gpu.py --dry-run, reading only that copy (--data-root), writes one row per (scene, camera,
  geer contender) with finite timings, tile statistics and the error against the float64 brute-force
  reference, gsplat rows saying they need CUDA, headline pairs first;
- benchmarks/gpu_session.sh parses, and its two calls run through as a smoke test without CUDA;
- benchmarks/gpu_sanitize.py (the scene the sanitizers run) renders and back-propagates finitely.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest
import torch
import yaml
from conftest import SHARED_DATA, shared_data

ROOT = Path(__file__).resolve().parents[1]
SESSION = ROOT / "benchmarks" / "gpu_session.sh"
sys.path.insert(0, str(ROOT / "benchmarks"))


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    shared_data("donut_3dgs.ply")
    shared_data("test_garden.npz")
    import gpu_prep

    dest = tmp_path_factory.mktemp("device_copy")
    files = gpu_prep.prepare(dest, SHARED_DATA, ROOT / "configs" / "bench_gpu.yaml")
    return dest, files


@pytest.fixture(scope="module")
def dry_run(prepared):
    import bench_gpu

    dest, _ = prepared
    out = dest / "gpu_dry.md"
    threads = torch.get_num_threads()
    try:
        assert bench_gpu.main(["--dry-run", "--out", str(out), "--data-root", str(dest)]) == 0
    finally:
        torch.set_num_threads(threads)
    cfg = yaml.safe_load((ROOT / "configs" / "bench_gpu.yaml").read_text())
    return cfg, out.read_text(), json.loads(out.with_suffix(".json").read_text())


def test_prep_copies_every_referenced_file_under_device(prepared):
    dest, files = prepared
    cfg = yaml.safe_load((ROOT / "configs" / "bench_gpu.yaml").read_text())
    refs = [s["path"] for s in cfg["scenes"] if "path" in s] + [c["intrinsics_from"] for c in cfg["cameras"]
                                                                if "intrinsics_from" in c]
    assert refs and all(r.startswith(".device/data/") for r in refs), refs
    def strings(node):
        if isinstance(node, dict):
            return [s for v in node.values() for s in strings(v)]
        if isinstance(node, list):
            return [s for v in node for s in strings(v)]
        return [node] if isinstance(node, str) else []

    assert not [s for s in strings(cfg) if "shared" in s], "the device has no ../shared"
    for r in refs:
        copy, original = dest / r, SHARED_DATA / Path(r).name
        assert copy.is_file() and copy.read_bytes() == original.read_bytes(), r
    assert {p.resolve() for p in files} == {(dest / r).resolve() for r in refs}
    assert (dest / ".device" / "COMMIT").read_text().strip()


def test_dry_run_rows(dry_run):
    cfg, table, result = dry_run
    assert result["dry_run"] is True and result["device"].startswith("CPU")
    assert result["commit"] and "--dry-run --out " in result["command"]
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


def test_dry_run_headline_rows_first(dry_run):
    cfg, _, result = dry_run
    n_cont = len(cfg["contenders"])
    pairs = [(r["scene"], r["camera"]) for r in result["rows"]][::n_cont]
    assert pairs[: len(cfg["first"])] == [tuple(p) for p in cfg["first"]]
    assert pairs[0] == ("synthetic-1M", "pinhole 1920x1080 (68 deg)") and "fisheye" in pairs[1][1]
    assert len(set(pairs)) == len(pairs) == len(cfg["scenes"]) * len(cfg["cameras"])


def test_dry_run_fisheye_skips_corner_tiles(dry_run):
    _, _, result = dry_run
    fish = [r for r in result["rows"] if "fisheye" in r["camera"] and "active_tiles" in r]
    assert fish and all(r["active_tiles"] < r["tiles"] for r in fish)


def test_missing_device_data_is_named(tmp_path):
    import bench_gpu

    with pytest.raises(FileNotFoundError, match=r"scene garden reads .*test_garden\.npz.*gpu_session\.sh prep"):
        bench_gpu.load_scene({"name": "garden", "kind": "garden_npz", "path": ".device/data/test_garden.npz"}, 10,
                             tmp_path)


def test_session_script_parses_and_smoke_runs_without_cuda(tmp_path):
    """Both calls end cleanly on a machine without CUDA (no builds, GPU tests skipped, no benchmark)."""
    assert subprocess.run(["bash", "-n", str(SESSION)], capture_output=True, text=True).returncode == 0
    for call in ("call1", "call2"):
        out = tmp_path / call
        env = dict(os.environ, PYTHON=sys.executable, OUT=str(out), GEER_SESSION_STATE=str(tmp_path / "state"),
                   CALL_LIMIT_S="120", CUDA_VISIBLE_DEVICES="")
        r = subprocess.run(["bash", str(SESSION), call], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
        text = r.stdout + r.stderr
        assert r.returncode == 0, text[-3000:]
        assert "unbound variable" not in text and "command not found" not in text, text
        summary = (out / "summary.txt").read_text()
        assert "no CUDA device" in summary, summary
        assert f"{call} done" in summary, summary
        assert len(list(out.iterdir())) <= 8 and all(p.is_file() for p in out.iterdir())  # what comes back
    with tarfile.open(tmp_path / "call1" / "logs.tgz") as logs:  # the logs come back in one archive
        log = logs.extractfile("./pytest_cuda.log").read().decode()
    assert "skipped" in log and "failed" not in log and "error" not in log.lower(), log[-2000:]


def test_sanitize_scene_runs_on_cpu():
    import gpu_sanitize

    assert gpu_sanitize.main(["--device", "cpu", "--backend", "torch", "--n", "60"]) == 0
