"""Broken transforms.json datasets fail at start-up with one line naming the file, the frame and the field.

Each case breaks a copy of four frames of the embedded room and starts training the way ns-train does
(config.yml saved, then Trainer.setup): the error must come from geer_ns.data.dataset_checks, name the file
and the field, and leave nothing in the output directory but config.yml. Nothing trains.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from PIL import Image

from geer_ns.data.dataset_checks import VALID_CAMERA_MODELS, DatasetError, check_transforms_json

from conftest import copy_room, tiny_trainer_config

N_FRAMES = 4


@pytest.fixture
def dataset(tmp_path) -> Path:
    """Four frames of the room (images, shared mask, seed points), valid as they are."""
    return copy_room(tmp_path / "data", N_FRAMES)


def _edit(root: Path, change) -> dict:
    meta = json.loads((root / "transforms.json").read_text())
    change(meta)
    (root / "transforms.json").write_text(json.dumps(meta))
    return meta


def _start_training(root: Path, out: Path) -> str:
    """ns-train's order: config.yml written, then the trainer set up. Returns the DatasetError message."""
    config = tiny_trainer_config(root, out, "broken", 1)
    config.save_config()
    with pytest.raises(DatasetError) as info:
        config.setup(local_rank=0, world_size=1).setup()
    written = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert written == ["broken/geer/run/config.yml"], written
    message = str(info.value)
    assert "\n" not in message
    return message


def _set(path, value):
    """Change meta at a path like ("frames", 1, "fl_x")."""
    def change(meta):
        target = meta
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value
    return change


def _jpeg(root: Path, frame: int, keep_bytes=None) -> str:
    """Frame's image re-saved as JPEG (optionally cut after keep_bytes); returns its file_path."""
    meta = json.loads((root / "transforms.json").read_text())
    src = root / meta["frames"][frame]["file_path"]
    dst = src.with_suffix(".jpg")
    Image.open(src).convert("RGB").save(dst, quality=95)
    if keep_bytes is not None:
        dst.write_bytes(dst.read_bytes()[:keep_bytes])
    rel = dst.relative_to(root).as_posix()
    _edit(root, _set(("frames", frame, "file_path"), rel))
    return rel


def _resize(path: Path, size) -> None:
    Image.open(path).resize(size).save(path)


def test_the_intact_copy_passes(dataset):
    check_transforms_json(dataset / "transforms.json")


def test_nan_in_a_pose(dataset, tmp_path):
    _edit(dataset, lambda m: m["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan")))
    msg = _start_training(dataset, tmp_path / "out")
    assert "transforms.json: frames[1]" in msg and "`transform_matrix`[0][3]" in msg and "nan" in msg


def test_empty_frames_list(dataset, tmp_path):
    _edit(dataset, _set(("frames",), []))
    msg = _start_training(dataset, tmp_path / "out")
    assert "transforms.json" in msg and "`frames` is an empty list" in msg


def test_truncated_jpeg(dataset, tmp_path):
    rel = _jpeg(dataset, 2, keep_bytes=800)
    msg = _start_training(dataset, tmp_path / "out")
    assert rel in msg and "frames[2]" in msg and "`file_path`" in msg and "truncated" in msg


def test_an_intact_jpeg_passes(dataset):
    _jpeg(dataset, 2)
    check_transforms_json(dataset / "transforms.json")


def test_mask_of_the_wrong_size(dataset, tmp_path):
    mask = dataset / "masks" / "fisheye_mask.png"
    _resize(mask, (64, 64))
    msg = _start_training(dataset, tmp_path / "out")
    assert str(mask) in msg and "`mask_path`" in msg and "64x64" in msg and "96x96" in msg


def test_image_of_the_wrong_size(dataset, tmp_path):
    meta = json.loads((dataset / "transforms.json").read_text())
    image = dataset / meta["frames"][3]["file_path"]
    _resize(image, (80, 96))
    msg = _start_training(dataset, tmp_path / "out")
    assert str(image) in msg and "frames[3]" in msg and "80x96" in msg and "`w`" in msg


def test_unknown_camera_model_lists_the_valid_ones(dataset, tmp_path):
    _edit(dataset, _set(("camera_model",), "KANNALA_BRANDT"))
    msg = _start_training(dataset, tmp_path / "out")
    assert "`camera_model` 'KANNALA_BRANDT'" in msg and "transforms.json" in msg
    assert all(name in msg for name in VALID_CAMERA_MODELS) and "OPENCV_FISHEYE" in msg


def test_per_frame_camera_model_overrides_the_top_level(dataset, tmp_path):
    _edit(dataset, _set(("frames", 2, "camera_model"), "VR180_L"))
    msg = _start_training(dataset, tmp_path / "out")
    assert "frames[2]" in msg and "`camera_model` 'VR180_L'" in msg


def test_per_frame_intrinsics_are_accepted(dataset):
    _edit(dataset, lambda m: m["frames"][0].update(camera_model="OPENCV", fl_x=40.0, fl_y=40.0, k1=0.01))
    check_transforms_json(dataset / "transforms.json")


def test_zero_focal_length_says_fl_x(dataset, tmp_path):
    _edit(dataset, _set(("fl_x",), 0))
    msg = _start_training(dataset, tmp_path / "out")
    assert "`fl_x` = 0" in msg and "expected > 0" in msg and "transforms.json" in msg


def test_zero_focal_length_in_a_frame(dataset, tmp_path):
    _edit(dataset, _set(("frames", 1, "fl_y"), 0.0))
    msg = _start_training(dataset, tmp_path / "out")
    assert "frames[1]" in msg and "`fl_y` = 0" in msg


def test_missing_image(dataset, tmp_path):
    meta = json.loads((dataset / "transforms.json").read_text())
    image = dataset / meta["frames"][1]["file_path"]
    image.unlink()
    msg = _start_training(dataset, tmp_path / "out")
    assert str(image) in msg and "does not exist" in msg and "`file_path`" in msg


def test_missing_mask(dataset, tmp_path):
    mask = dataset / "masks" / "fisheye_mask.png"
    mask.unlink()
    msg = _start_training(dataset, tmp_path / "out")
    assert str(mask) in msg and "does not exist" in msg and "`mask_path`" in msg


def test_non_image_bytes(dataset, tmp_path):
    meta = json.loads((dataset / "transforms.json").read_text())
    image = dataset / meta["frames"][0]["file_path"]
    image.write_bytes(b"<html>404 not found</html>" * 20)
    msg = _start_training(dataset, tmp_path / "out")
    assert str(image) in msg and "not an image" in msg and "frames[0]" in msg


def test_duplicate_frames(dataset, tmp_path):
    _edit(dataset, lambda m: m["frames"].append(dict(m["frames"][1])))
    msg = _start_training(dataset, tmp_path / "out")
    assert f"frames[{N_FRAMES}]" in msg and "`file_path` repeats frames[1]" in msg


def test_rotation_with_a_zero_length_row(dataset, tmp_path):
    _edit(dataset, lambda m: m["frames"][2]["transform_matrix"].__setitem__(1, [0.0, 0.0, 0.0, 0.5]))
    msg = _start_training(dataset, tmp_path / "out")
    assert "frames[2]" in msg and "`transform_matrix`" in msg and "zero length" in msg


def test_non_orthonormal_rotation(dataset, tmp_path):
    def scale(m):
        rows = m["frames"][0]["transform_matrix"]
        rows[0] = [2.0 * v for v in rows[0][:3]] + [rows[0][3]]
    _edit(dataset, scale)
    msg = _start_training(dataset, tmp_path / "out")
    assert "frames[0]" in msg and "`transform_matrix`" in msg and "not orthonormal" in msg


def test_principal_point_outside_the_image(dataset, tmp_path):
    _edit(dataset, _set(("cx",), 480.0))
    msg = _start_training(dataset, tmp_path / "out")
    assert "`cx` = 480" in msg and "outside the image" in msg and "`w`" in msg


def test_json_syntax_error_names_the_line(dataset, tmp_path):
    text = json.dumps(json.loads((dataset / "transforms.json").read_text()), indent=1)
    lines = text.splitlines()
    lines[5] = lines[5].rstrip(",")  # a missing comma on line 6
    (dataset / "transforms.json").write_text("\n".join(lines))
    msg = _start_training(dataset, tmp_path / "out")
    assert "transforms.json:7:" in msg and "not valid JSON" in msg


def test_missing_transform_matrix(dataset, tmp_path):
    _edit(dataset, lambda m: m["frames"][3].pop("transform_matrix"))
    msg = _start_training(dataset, tmp_path / "out")
    assert "frames[3]" in msg and "`transform_matrix` is missing" in msg


def test_split_list_naming_no_frame(dataset, tmp_path):
    _edit(dataset, _set(("val_filenames",), ["images_fisheye/frame_09999.png"]))
    msg = _start_training(dataset, tmp_path / "out")
    assert "`val_filenames`" in msg and "frame_09999.png" in msg


def test_missing_point_cloud(dataset, tmp_path):
    (dataset / "points3d.ply").unlink()
    msg = _start_training(dataset, tmp_path / "out")
    assert "`ply_file_path`" in msg and "points3d.ply" in msg


def test_non_finite_distortion(dataset, tmp_path):
    _edit(dataset, _set(("k2",), float("inf")))
    msg = _start_training(dataset, tmp_path / "out")
    assert "`k2` = inf" in msg


def test_several_problems_are_counted(dataset, tmp_path):
    def break_two(m):
        m["frames"][0]["transform_matrix"][0][0] = float("nan")
        m["frames"][1]["transform_matrix"][0][0] = float("nan")
    _edit(dataset, break_two)
    msg = _start_training(dataset, tmp_path / "out")
    assert "frames[0]" in msg and "+1 more problem" in msg


def test_numbers_written_as_strings_are_read_as_nerfstudio_reads_them(dataset):
    _edit(dataset, lambda m: m.update(fl_x=str(m["fl_x"]), w="96"))
    check_transforms_json(dataset / "transforms.json")


def test_all_cameras_at_one_position(dataset, tmp_path):
    def same_place(m):
        for frame in m["frames"]:
            for row in frame["transform_matrix"][:3]:
                row[3] = 0.5
    _edit(dataset, same_place)
    msg = _start_training(dataset, tmp_path / "out")
    assert "transforms.json: `transform_matrix`: all 4 frames have the camera position [0.5, 0.5, 0.5]" in msg
    assert "auto-scale-poses False" in msg
    check_transforms_json(dataset / "transforms.json", auto_scale_poses=False)


def test_ns_train_ends_on_a_broken_dataset_with_its_line_not_a_traceback():
    """What a user sees: the one line, exit status 1; other errors keep their traceback."""
    import subprocess
    import sys

    def run(error: str) -> subprocess.CompletedProcess:
        # What ns-train's main does first for a geer config (GeerTrainerConfig.set_timestamp installs the run fixes).
        code = ("from geer_ns.training.trainer import install_run_fixes\ninstall_run_fixes()\n"
                f"from geer_ns.data.dataset_checks import DatasetError\nraise {error}")
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)

    broken = run("DatasetError('geer: data/transforms.json: frames[0] (a.png): `fl_x` = 0; expected > 0')")
    assert broken.returncode == 1
    assert "Traceback" not in broken.stderr
    assert broken.stderr.strip().splitlines()[-1] == "geer: data/transforms.json: frames[0] (a.png): `fl_x` = 0; expected > 0"
    other = run("RuntimeError('a bug')")
    assert other.returncode == 1 and "Traceback" in other.stderr and "RuntimeError: a bug" in other.stderr
