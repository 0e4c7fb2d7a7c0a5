"""benchmarks/vs_splatfacto.py's decisions on tables of known runs: which splatfacto variant geer is set against,
how a difference reads (LPIPS: lower is better), and when a row at equal Gaussian counts is trained and at which
cap. No training: geer-compare's calls are recorded instead."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks import vs_splatfacto


def _table(folder: Path, method: str, gaussians, **figures) -> Path:
    """A compare.json of one method's runs (seeds 1, 2, 3) with the given per-run figures."""
    folder.mkdir(parents=True, exist_ok=True)
    runs = [{"method": method, "seed": seed, "steps": 10, "gaussians": count,
             **{key: values[i] for key, values in figures.items()}}
            for i, (seed, count) in enumerate(zip((1, 2, 3), gaussians))]
    (folder / "compare.json").write_text(json.dumps({"results": runs, "skipped": {}, "protocol": []}))
    return folder / "compare.json"


def test_geer_is_set_against_the_best_variant_and_read_by_its_interval(tmp_path):
    tables = {
        "geer": _table(tmp_path / "g", "geer", [10, 10, 10], psnr=[30.0, 30.1, 29.9], ssim=[0.80, 0.81, 0.79],
                       lpips=[0.10, 0.11, 0.09]),
        "splatfacto": _table(tmp_path / "s", "splatfacto", [20, 20, 20], psnr=[25.0, 25.1, 24.9],
                             ssim=[0.90, 0.91, 0.89], lpips=[0.30, 0.31, 0.29]),
        "splatfacto-pinhole": _table(tmp_path / "p", "splatfacto-pinhole", [5, 5, 5], psnr=[29.0, 31.0, 30.0],
                                     ssim=[0.5, 0.5, 0.5], lpips=[0.05, 0.06, 0.04]),
    }
    rows, readings = vs_splatfacto.against_splatfacto("fisheye", tables)
    assert [(g, r) for g, r, _ in readings] == [("geer", "not distinguishable"),  # 30.0 against the best's 30.0
                                                ("geer", "geer behind"),  # SSIM: against splatfacto's 0.90
                                                ("geer", "geer behind")]  # LPIPS 0.10 against splatfacto-pinhole's 0.05
    assert "splatfacto-pinhole: 30" in rows[0] and "| 10 / 5 |" in rows[0] and readings[0][2].startswith("fisheye psnr +0.00 +- ")
    tables.pop("splatfacto-pinhole")
    _, readings = vs_splatfacto.against_splatfacto("fisheye", tables)
    assert [r for _, r, _ in readings] == ["geer ahead", "geer behind", "geer ahead"]
    assert "geer ahead in 2 (fisheye psnr +5.00 +- " in vs_splatfacto.verdict(readings)[0]
    pinhole = {m: _table(tmp_path / f"pin_{m}", m, [1, 1, 1], psnr=[30.0, 30.1, 29.9], central_psnr=[30.0, 30.1, 29.9],
                         peripheral_psnr=[None] * 3) for m in ("geer", "splatfacto")}
    assert [c.split()[1] for _, _, c in vs_splatfacto.against_splatfacto("pinhole", pinhole)[1]] == ["psnr"]
    one = {m: _table(tmp_path / f"one_{m}", m, [1], psnr=[30.0]) for m in ("geer", "splatfacto")}
    assert [r for _, r, _ in vs_splatfacto.against_splatfacto("pinhole", one)[1]] == ["one seed"]


@pytest.mark.parametrize("geer_counts, capped", [([90, 120, 100], True), ([90, 95, 80], False)])
def test_a_row_at_equal_counts_is_trained_where_geer_has_more(tmp_path, monkeypatch, geer_counts, capped):
    calls = []
    counts = {"geer": geer_counts, "geer-beap": [300, 300, 300], "splatfacto": [110, 98, 105],
              "splatfacto-pinhole": [50, 50, 50]}

    def run_cell(work, scene, views, method, steps, seeds, *options):
        calls.append((method, options))
        return _table(tmp_path / method, method, counts.get(method, [1, 1, 1]), psnr=[1.0, 2.0, 3.0])

    monkeypatch.setattr(vs_splatfacto, "run_cell", run_cell)
    tables = vs_splatfacto.train_views(tmp_path, "dev_room", "pinhole",
                                       ("geer", "geer-beap", "splatfacto", "splatfacto-pinhole"), 10, [1, 2, 3])
    assert {calls[0][0], calls[1][0]} == {"splatfacto", "splatfacto-pinhole"}  # first: their counts set the cap
    assert (("geer-capped", ("--max-gaussians", "98")) in calls) == capped  # the fewest of the peer's runs
    assert list(tables)[:2] == (["geer", "geer-capped"] if capped else ["geer", "geer-beap"])


def test_tables_of_single_methods_merge_into_one_table_and_picture(tmp_path):
    """Two geer-compare tables (one without LPIPS, one without its renders file) read back into one table."""
    import torch

    from geer_ns.compare import report
    from geer_ns.compare.capture import load_capture
    from geer_ns.compare.run import Result
    from geer_ns.data.synthetic_room import default_scene_dir

    capture = load_capture(default_scene_dir(), 45.0)
    h, w = capture.views[0].image.shape[:2]
    metrics = {"psnr": 30.0, "ssim": 0.9, "central_psnr": 31.0, "peripheral_psnr": float("nan"), "covered": 1.0,
               "covered_psnr": 30.0}
    tables = {}
    for name, value, lpips in (("geer", 0.25, None), ("splatfacto", 0.75, 0.2)):
        results = [Result(name, f"{name} described", "r", 10, seed, 1.0, 100 * seed,
                          dict(metrics, psnr=30.0 + seed, **({} if lpips is None else {"lpips": lpips})), 5.0,
                          [torch.full((h, w, 3), value)] * 3, "digest") for seed in (1, 2)]
        (tmp_path / name).mkdir()
        report.write(tmp_path / name, capture, results, {}, ["Capture: x", f"LPIPS: {name}"])
        tables[name] = tmp_path / name / "compare.json"
    (tmp_path / "splatfacto" / "renders.npz").unlink()
    text, results = vs_splatfacto.merged_table(tables)
    rows = [line for line in text.splitlines() if line.startswith("| geer ") or line.startswith("| splatfacto ")]
    assert rows[0].startswith("| geer | 2 | 31.50 +- ") and "| n/a |" in rows[0]  # no LPIPS: n/a
    assert rows[1].startswith("| splatfacto | 2 | 31.50 +- ") and "| 0.200 +- 0.000 |" in rows[1] and "| 150 +- " in rows[1]
    assert "- LPIPS: geer" in text and "- LPIPS: splatfacto" in text and text.count("- Capture: x") == 1
    assert [len(r.renders) for r in results] == [3, 0, 0, 0]  # the first seed's, where the file was kept
    assert abs(float(results[0].renders[0].mean()) - 64 / 255) < 1e-6  # 0.25 stored in 8 bits
    vs_splatfacto.picture(default_scene_dir() / "transforms.json", results, tmp_path / "picture.png")
    from PIL import Image

    with Image.open(tmp_path / "picture.png") as image:  # ground truth and geer (splatfacto: no renders), two rows
        assert image.mode == "RGB" and image.width == 2 * max(1, 200 // h) * w


def test_densify_default_reads_the_same_one_method_tables(tmp_path):
    from benchmarks import densify_default

    tables = {}
    for scene, views in densify_default.CELLS:
        for method, offset in (("geer-reference-units", 0.0), ("geer", 1.0)):
            tables[(scene, views, method)] = _table(tmp_path / f"{scene}_{views}_{method}", method, [100, 100, 100],
                                                    psnr=[30.1 + offset, 30.2 + offset, 30.3 + offset],
                                                    ssim=[0.9, 0.9, 0.9], peripheral_psnr=[None] * 3)
    text = densify_default.report(tables, ["geer-reference-units", "geer"])
    # mean 30.20, t(0.975, 2) 4.302653 x sd 0.1 / sqrt(3) = 0.248; no periphery: n/a
    assert "| dev_room | fisheye | geer-reference-units | 30.20 +- 0.25 | 0.900 +- 0.000 | n/a | n/a | 100 +- 0 |" in text
    assert "| geer (psnr) | +1.00 +- 0.23 | +1.00 +- 0.23 | +1.00 +- 0.23 | +1.00 +- 0.23 | +1.000 |" in text
