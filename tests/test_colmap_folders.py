"""COLMAP folders as they come: model at any usual depth, comma-separated text, errors at file:line, image
names matched with a miss list, seeds without points3D, and the T265 fixture training via geer-colmap."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import pytest
import torch

from geer_ns.cameras import OpenCVFisheyeCamera
from geer_ns.data.colmap_parser import GeerColmapDataParserConfig, camera_model_for_image
from geer_ns.data.dataset_checks import DatasetError

from conftest import shared_data, tiny_trainer_config, train_in_process

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "t265_colmap"
NAMES = sorted(f"{side}raw/frame_00000000{i}.jpg" for side in ("left", "right") for i in (1, 2, 3))


def load(root: Path, split: str = "train", **kw):
    kw.setdefault("eval_mode", "all")
    return GeerColmapDataParserConfig(data=root, **kw).setup().get_dataparser_outputs(split=split)


def _copy_fixture(dst: Path, depth: str = ".") -> Path:
    (dst / depth).mkdir(parents=True, exist_ok=True)
    for name in ("cameras.txt", "images.txt"):
        shutil.copy(FIXTURE / name, dst / depth / name)
    shutil.copytree(FIXTURE / "images", dst / "images", dirs_exist_ok=True)
    return dst


def test_the_t265_sample_as_it_comes_lists_the_images_it_cannot_find():
    src = shared_data("t265_fisheye")
    with pytest.raises(DatasetError) as info:
        load(src)
    msg = str(info.value)
    assert f"{src / 'images.txt'}: 6 image(s) named there were not found" in msg
    assert "'leftraw/frame_000000001.jpg'" in msg and "and 1 more" in msg and f"searched {src}" in msg


def test_t265_fixture_loads_comma_separated_text_at_the_top_level():
    out = load(FIXTURE)
    assert [p.relative_to(FIXTURE / "images").as_posix() for p in out.image_filenames] == NAMES
    calib = {1: (71.117, 71.3775, 106.08875, 98.4355, 0.0008, 0.031, -0.03, 0.005),
             2: (70.99975, 71.3165, 104.3115, 100.1005, -0.002, 0.039, -0.038, 0.007)}
    for i, name in enumerate(NAMES):
        cid = 1 if name.startswith("left") else 2
        assert camera_model_for_image(out, i) == OpenCVFisheyeCamera(212, 200, *calib[cid])
    # stereo baseline of the T265: 0.064 m between the left and right camera of each frame
    c = out.cameras.camera_to_worlds[:, :, 3].double() / out.dataparser_scale
    assert float((c[0] - c[3]).norm()) == pytest.approx(0.064, abs=1e-6)


@pytest.mark.parametrize("depth", [".", "sparse/0", "sparse", "colmap/sparse/0", "colmap/sparse", "colmap", "sparse/3"])
def test_model_found_at_the_usual_depths(tmp_path, depth):
    root = _copy_fixture(tmp_path, depth)
    assert len(load(root).image_filenames) == 6


def test_images_matched_by_unique_file_name_with_a_miss_list(tmp_path):
    root = _copy_fixture(tmp_path, "sparse/0")
    flat = tmp_path / "images_flat"
    flat.mkdir()
    for name in NAMES:  # files named <side>raw_frame_...jpg in one folder; images.txt says capture/<that name>
        shutil.copy(root / "images" / name, flat / name.replace("/", "_"))
    images_txt = root / "sparse/0/images.txt"
    text = images_txt.read_text()
    for name in NAMES:
        text = text.replace(name, "capture/" + name.replace("/", "_"))
    images_txt.write_text(text)
    shutil.rmtree(root / "images")
    out = load(root, images_path=Path("images_flat"))
    assert [p.name for p in out.image_filenames] == [n.replace("/", "_") for n in NAMES]
    (flat / "rightraw_frame_000000002.jpg").unlink()
    with pytest.raises(DatasetError, match=r"images\.txt: 1 image\(s\) named there were not found "
                                           r"\('capture/rightraw_frame_000000002\.jpg'\); searched .*images_flat"):
        load(root, images_path=Path("images_flat"))


def test_ambiguous_file_names_are_not_guessed(tmp_path):
    root = _copy_fixture(tmp_path, "sparse/0")
    for name in NAMES:  # left and right frames share file names: matching by file name would mix them up
        (root / "images" / name).rename(root / "images" / Path(name).name)
    with pytest.raises(DatasetError, match=r"6 image\(s\) named there were not found"):
        load(root)


def _break_line(root: Path, file: str, lineno: int, new: str) -> None:
    path = root / file
    lines = path.read_text().splitlines()
    lines[lineno - 1] = new
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize(
    "file, lineno, new, expected",
    [
        ("images.txt", 5, "1, 0.95, -0.03, -0.29, -0.006, 2.71, 0.13, -2.86, 2", r"images\.txt:5: expected IMAGE_ID .* got 9"),
        ("images.txt", 7, "2, 0.95, x0.03, -0.29, -0.006, 2.71, 0.13, -2.86, 1, leftraw/frame_000000001.jpg",
         r"images\.txt:7: QX = 'x0\.03' is not a number"),
        ("images.txt", 7, "2, 0, 0, 0, 0, 2.71, 0.13, -2.86, 1, leftraw/frame_000000001.jpg",
         r"images\.txt:7: image 2 \(leftraw/frame_000000001\.jpg\): the quaternion QW QX QY QZ is zero"),
        ("images.txt", 7, "2, 0.95, -0.03, -0.29, -0.006, 2.71, 0.13, -2.86, 9, leftraw/frame_000000001.jpg",
         r"images\.txt:7: image 2 .*CAMERA_ID 9 is not in cameras\.txt"),
        ("images.txt", 6, "10.0, 20.0", r"images\.txt:6: POINTS2D of image 1: expected triples"),
        ("images.txt", 7, "1, 0.95, -0.03, -0.29, -0.006, 2.71, 0.13, -2.86, 1, leftraw/frame_000000001.jpg",
         r"images\.txt:7: IMAGE_ID 1 repeats line 5"),
        ("cameras.txt", 4, "1 OPENCV_FISHEYE 212 200 71.1 71.3 106.0 98.4 0.0008 0.031 -0.03",
         r"cameras\.txt:4: camera 1: OPENCV_FISHEYE expects 8 params \(fx, fy, cx, cy, k1, k2, k3, k4\), got 7"),
        ("cameras.txt", 4, "1 KANNALA_BRANDT 212 200 71.1 71.3 106.0 98.4 0.0008 0.031 -0.03 0.005",
         r"cameras\.txt:4: camera 1: unknown COLMAP camera model KANNALA_BRANDT; expected one of .*OPENCV_FISHEYE"),
        ("cameras.txt", 4, "1 OPENCV_FISHEYE 0 200 71.1 71.3 106.0 98.4 0.0008 0.031 -0.03 0.005",
         r"cameras\.txt:4: camera 1: WIDTH = '0'; expected a positive integer"),
    ],
)
def test_malformed_lines_are_reported_with_file_and_line(tmp_path, file, lineno, new, expected):
    root = _copy_fixture(tmp_path)
    _break_line(root, file, lineno, new)
    with pytest.raises(DatasetError, match=expected):
        load(root)


def test_crop_radius_option_masks_outside_the_circle():
    out = load(FIXTURE, crop_radius=96.0)
    assert out.cameras.metadata["fisheye_crop_radius"] == 96.0


def test_truncated_image_is_named(tmp_path):
    root = _copy_fixture(tmp_path)
    image = root / "images" / "leftraw" / "frame_000000002.jpg"
    image.write_bytes(image.read_bytes()[:2000])
    with pytest.raises(DatasetError, match=rf"image 'leftraw/frame_000000002\.jpg'.*{image}.* is truncated"):
        load(root)


def test_geer_colmap_trains_the_t265_fixture(tmp_path, single_thread):
    """nerfstudio's training loop (what ns-train calls) with the geer-colmap dataparser, a couple of steps."""
    config = tiny_trainer_config(FIXTURE, tmp_path, "t265", 3)
    config.pipeline.datamanager.dataparser = GeerColmapDataParserConfig()
    ckpt = torch.load(train_in_process(config), map_location="cpu")
    assert ckpt["step"] == 2
    means = ckpt["pipeline"]["_model.gauss_params.means"]
    assert means.shape[0] == 5000  # frustum seeds: 1000 per training camera (5 of 6; one is eval)
    assert bool(torch.isfinite(means).all())
    assert math.isfinite(float(ckpt["optimizers"]["means"]["state"][0]["step"]))


def test_non_finite_pose_in_a_binary_model(tmp_path):
    import numpy as np
    import pycolmap

    from geer_ns.data.colmap_files import write_strict_text_model

    (tmp_path / "strict").mkdir()
    write_strict_text_model(FIXTURE, tmp_path / "strict")
    rec = pycolmap.Reconstruction()
    rec.read_text(str(tmp_path / "strict"))
    frame = rec.frames[rec.images[3].frame_id]
    frame.rig_from_world = pycolmap.Rigid3d(frame.rig_from_world.rotation, np.array([np.nan, 0.0, 0.0]))
    model = tmp_path / "bin" / "sparse" / "0"
    model.mkdir(parents=True)
    rec.write_binary(str(model))
    shutil.copytree(FIXTURE / "images", tmp_path / "bin" / "images")
    with pytest.raises(DatasetError, match=r"images\.bin: image 3 'rightraw/frame_000000002\.jpg': the pose .* NaN"):
        load(tmp_path / "bin")


def test_the_t265_sample_as_it_comes_stops_before_writing_anything(tmp_path):
    """Through ns-train's order (config.yml saved, then the trainer set up): only config.yml is written."""
    src = shared_data("t265_fisheye")
    config = tiny_trainer_config(src, tmp_path, "t265", 1)
    config.pipeline.datamanager.dataparser = GeerColmapDataParserConfig()
    config.save_config()
    with pytest.raises(DatasetError, match=r"images\.txt: 6 image\(s\) named there were not found"):
        config.setup(local_rank=0, world_size=1).setup()
    written = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file())
    assert written == ["t265/geer/run/config.yml"], written
