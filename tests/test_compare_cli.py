"""geer-compare end to end on the embedded room at 48 x 48 pixels for a dozen steps: every method trains, every
table cell is filled, the picture is written, and splatfacto's work-arounds are undone afterwards. Also the
resampling between cameras against directions known in closed form."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import pytest
import torch

from geer_ns.cameras import EquidistantCamera, PinholeCamera
from geer_ns.compare.resample import resample, widest_pinhole


def _direction_colour(dirs: torch.Tensor) -> torch.Tensor:
    """A smooth colour of the ray direction alone: any camera at the same pose sees the same colour on a ray."""
    return torch.stack([0.5 + 0.5 * dirs[..., 0], 0.5 + 0.5 * dirs[..., 1], dirs[..., 2].clamp(0, 1)], dim=-1)


def test_resample_moves_colours_along_rays():
    fisheye = EquidistantCamera(64, 64, 64 / math.pi, 64 / math.pi, 32.0, 32.0)
    pinhole = widest_pinhole(fisheye, 120.0)
    assert isinstance(pinhole, PinholeCamera) and abs(pinhole.fx - 32 / math.tan(math.radians(60))) < 1e-9
    for src, dst in ((fisheye, pinhole), (pinhole, fisheye)):
        image = _direction_colour(src.pixel_rays(torch.float64)[0])
        moved, covered = resample(image, src, dst, fill=-1.0)
        expected = _direction_colour(dst.pixel_rays(torch.float64)[0])
        inner = covered.clone()
        inner[[0, -1], :] = inner[:, [0, -1]] = False  # bilinear at the image's border is clamped
        assert float((moved - expected)[inner].abs().max()) < 0.02
        assert bool((moved[~covered] == -1.0).all())
    _, covered = resample(torch.zeros(64, 64, 3), pinhole, fisheye)
    assert 0.3 < float(covered.float().mean()) < 0.6  # a 120-degree pinhole sees part of the 180-degree circle


@pytest.fixture(scope="module")
def small_room(tmp_path_factory):
    """The embedded room's fisheye capture resampled to 48 x 48 (masks written where the circle ends)."""
    from geer_ns.compare.capture import load_capture, write_resampled
    from geer_ns.data.synthetic_room import default_scene_dir

    capture = load_capture(default_scene_dir(), 45.0)
    cam = capture.camera
    s = 48 / cam.width
    small = EquidistantCamera(48, 48, cam.fx * s, cam.fy * s, cam.cx * s, cam.cy * s)
    return write_resampled(capture, small, "OPENCV_FISHEYE", tmp_path_factory.mktemp("room48"))


def test_geer_compare_runs_every_method(small_room, tmp_path, single_thread):
    import gsplat.rendering
    from nerfstudio.models import splatfacto

    from geer_ns.compare.cli import Compare

    cuda = torch.Tensor.cuda
    methods = ("geer", "geer-gsplat-units", "splatfacto", "splatfacto-pinhole", "splatfacto-fisheye")
    text = Compare(data=small_room, steps=12, methods=methods, output_dir=tmp_path).main()
    table = json.loads((tmp_path / "compare.json").read_text())
    assert [r["method"] for r in table["results"]] == list(methods)
    for row in table["results"]:
        for key in ("psnr", "ssim", "central_psnr", "peripheral_psnr", "covered", "covered_psnr", "train_seconds",
                    "gaussians", "render_ms"):
            assert row[key] is not None and math.isfinite(row[key]) and row[key] > 0, (row["method"], key)
        assert 5 < row["psnr"] < 60 and row["steps"] == 12
        assert (row["covered"] < 0.9) == (row["method"] == "splatfacto-pinhole")  # the lost periphery
        if not torch.cuda.is_available() and row["method"].startswith("splatfacto"):
            assert "CPU" in row["rasterizer"]
    assert table["protocol"] and "central region" in text.lower()
    for line in text.splitlines():
        if line.startswith("| ") and not line.startswith("| ---") and not line.startswith("| method"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            assert all(cells), line
            assert all(c != "n/a" for i, c in enumerate(cells) if i != 4), line  # LPIPS: only with cached weights
    picture = (tmp_path / "compare.png").read_bytes()
    assert picture[:8] == b"\x89PNG\r\n\x1a\n" and len(picture) > 10_000
    # the work-arounds were scoped to splatfacto's own calls
    assert splatfacto.rasterization is gsplat.rendering.rasterization and torch.Tensor.cuda is cuda


def test_interval_is_students_t_over_the_seeds():
    from geer_ns.compare.report import interval

    mean, half = interval([27.0, 28.0, 29.0])  # sd 1, t(0.975, 2 df) = 4.302653 (tables)
    assert mean == pytest.approx(28.0) and half == pytest.approx(4.302653 / math.sqrt(3), rel=1e-6)
    mean, half = interval([25.5, float("nan")])  # one finite value: a mean, no interval
    assert mean == 25.5 and math.isnan(half)


def test_scored_cameras_are_the_captures_test_split(small_room, tmp_path):
    """nerfstudio's eval dataset is the val split; geer-compare renders the test split and refuses another one."""
    from types import SimpleNamespace

    from geer_ns.compare.capture import load_capture
    from geer_ns.compare.methods import Method
    from geer_ns.compare.run import test_cameras
    from geer_ns.data.nerfstudio_parser import GeerNerfstudioDataParserConfig

    capture = load_capture(small_room, 45.0)
    meta = json.loads(small_room.read_text())
    meta["val_filenames"] = meta["train_filenames"][:2]  # val differs from test: the renders follow test
    other = dict(meta, test_filenames=meta["train_filenames"][-3:])
    for name, content in (("val_differs", meta), ("test_differs", other)):
        path = small_room.parent / f"{name}.json"
        path.write_text(json.dumps(content))

    def pipeline(path):
        parser = GeerNerfstudioDataParserConfig(data=path, load_3D_points=False, downscale_factor=1).setup()
        return SimpleNamespace(datamanager=SimpleNamespace(dataparser=parser))

    method = Method("geer", "", small_room.parent / "val_differs.json", None, None)
    cameras = test_cameras(method, pipeline(method.data), capture)
    assert len(cameras) == len(capture.views) == len(meta["test_filenames"])
    with pytest.raises(RuntimeError, match="test split of .*test_differs.json is not the capture's"):
        test_cameras(method, pipeline(small_room.parent / "test_differs.json"), capture)


def test_native_and_beap_rows_over_two_seeds(small_room, tmp_path, single_thread):
    from geer_ns.compare.cli import Compare

    text = Compare(data=small_room, steps=8, methods=("geer-native", "geer-beap"), seeds=(1, 2),
                   output_dir=tmp_path).main()
    table = json.loads((tmp_path / "compare.json").read_text())
    assert [(r["method"], r["seed"]) for r in table["results"]] == [
        ("geer-native", 1), ("geer-native", 2), ("geer-beap", 1), ("geer-beap", 2)]
    for summary in table["summary"]:
        runs = [r["psnr"] for r in table["results"] if r["method"] == summary["method"]]
        assert summary["seeds"] == [1, 2] and summary["psnr"][0] == pytest.approx(sum(runs) / 2)
        assert summary["psnr"][1] == pytest.approx(12.706205 * abs(runs[0] - runs[1]) / 2)  # t(0.975, 1) sd/sqrt(2)
    assert "+-" in text and "supervision native" in text and "supervision beap" in text


def test_a_bad_option_or_capture_ends_in_one_line(small_room, tmp_path):
    meta = json.loads(small_room.read_text())
    del meta["fl_x"]
    broken = small_room.parent / "no_focal.json"
    broken.write_text(json.dumps(meta))
    for argv, message in ((["--data", str(small_room), "--seeds", "1", "1"], "--seeds 1 1: give one or more distinct"),
                          (["--data", str(broken)], f"{broken}: top-level field 'fl_x' is missing")):
        done = subprocess.run([sys.executable, "-m", "geer_ns.compare", *argv, "--output-dir", str(tmp_path)],
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
        assert message in done.stderr.strip().splitlines()[-1], done.stderr


def test_geer_capped_needs_its_cap_and_trains_with_it(small_room, tmp_path):
    from geer_ns.compare.capture import load_capture
    from geer_ns.compare.methods import plan
    from geer_ns.errors import OptionError

    capture = load_capture(small_room, 45.0)
    with pytest.raises(OptionError, match="--max-gaussians 0: the method geer-capped needs its cap"):
        plan(capture, ("geer", "geer-capped"), tmp_path, 120.0)
    (geer, capped), _ = plan(capture, ("geer", "geer-capped"), tmp_path, 120.0, max_gaussians=1234)
    assert capped.config.pipeline.model.max_gaussians == 1234 and geer.config.pipeline.model.max_gaussians == 0
    assert "at most 1,234 Gaussians" in capped.description


def test_config_digest_names_what_a_run_was_made_with(small_room, tmp_path):
    from geer_ns.compare.capture import load_capture
    from geer_ns.compare.methods import config_digest, plan

    capture = load_capture(small_room, 45.0)
    names = ("geer", "geer-reference-units", "splatfacto", "splatfacto-fisheye")
    first, _ = plan(capture, names, tmp_path / "a", 120.0)
    again, _ = plan(capture, names, tmp_path / "b", 120.0)  # another work folder: paths are not part of it
    digests = [config_digest(m) for m in first]
    assert digests == [config_digest(m) for m in again] and len(set(digests)) == len(names)
    first[0].config.pipeline.model.densify_units = "reference"  # a changed default is another config
    assert config_digest(first[0]) != digests[0]
    # each cell of a study is its own process: the digest must not depend on the process (hash seeds, ids)
    code = ("import sys; from pathlib import Path; from geer_ns.compare.capture import load_capture; "
            "from geer_ns.compare.methods import config_digest, plan; "
            f"methods, _ = plan(load_capture(Path(sys.argv[1]), 45.0), {names!r}, Path(sys.argv[2]), 120.0); "
            "print(' '.join(config_digest(m) for m in methods))")
    done = subprocess.run([sys.executable, "-c", code, str(small_room), str(tmp_path / "c")], text=True,
                          capture_output=True, timeout=300, env={**os.environ, "PYTHONHASHSEED": "12345"})
    assert done.stdout.strip().splitlines()[-1].split() == digests, done.stdout + done.stderr[-2000:]


def test_keep_finished_keeps_only_a_table_of_todays_runs(small_room, tmp_path, single_thread, monkeypatch):
    from geer_ns.compare import report, run
    from geer_ns.compare.cli import Compare

    options = dict(data=small_room, steps=4, methods=("geer",), seeds=(1,), output_dir=tmp_path)
    text = Compare(**options).main()
    results, skipped, lines = report.load(tmp_path)
    assert [(r.name, r.seed, len(r.renders)) for r in results] == [("geer", 1, report.PICTURED_VIEWS)]
    table = [line for line in text.splitlines() if line.startswith("| geer ")]
    assert table and table == [line for line in report.markdown(results, skipped, lines).splitlines()
                               if line.startswith("| geer ")]

    def no_training(*args, **kwargs):
        raise AssertionError("trained again")

    monkeypatch.setattr(run, "run_method", no_training)
    assert Compare(**options, keep_finished=True).main() == text
    for changed in (dict(options, steps=5), dict(options, seeds=(1, 2)), dict(options, methods=("geer-beap",)),
                    dict(options, central_half_angle_deg=30.0)):  # another protocol
        with pytest.raises(AssertionError, match="trained again"):
            Compare(**changed, keep_finished=True).main()
    stale = json.loads((tmp_path / "compare.json").read_text())
    stale["results"][0]["config_digest"] = "made-before"  # a table made with other defaults
    (tmp_path / "compare.json").write_text(json.dumps(stale))
    with pytest.raises(AssertionError, match="trained again"):
        Compare(**options, keep_finished=True).main()
