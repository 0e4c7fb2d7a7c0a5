"""geer's transforms.json parser: nerfstudio's own output where nerfstudio can describe the file, per-frame
camera models and distortion for mixed rigs, and poses mapped into another run's frame (cross-camera eval).

References: nerfstudio's NerfstudioDataParser (same file), the frames' own JSON values, and the dev room's
fisheye and pinhole files, which share their poses.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from nerfstudio.cameras.cameras import CameraType
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

from geer_ns.data.nerfstudio_parser import GeerNerfstudioDataParserConfig
from geer_ns.data.synthetic_room import default_scene_dir
from geer_ns.data.views import camera_kind, camera_model

from conftest import shared_data

pytestmark = pytest.mark.filterwarnings("ignore:Using a non-tuple sequence:UserWarning")
FIELDS = ("camera_to_worlds", "fx", "fy", "cx", "cy", "width", "height", "distortion_params", "camera_type")


def _parse(config, split: str = "train"):
    return config.setup().get_dataparser_outputs(split=split)


@pytest.mark.parametrize("name", ["transforms.json", "transforms_fisheye220.json", "dev:transforms_fisheye.json",
                                  "dev:transforms_pinhole.json"])
def test_same_as_nerfstudio_without_frame_camera_fields(name):
    path = shared_data("fisheye_room_dev", name[4:]) if name.startswith("dev:") else default_scene_dir() / name
    for split in ("train", "test"):
        ours = _parse(GeerNerfstudioDataParserConfig(data=path), split)
        theirs = _parse(NerfstudioDataParserConfig(data=path), split)
        assert ours.image_filenames == theirs.image_filenames and ours.mask_filenames == theirs.mask_filenames
        for f in FIELDS:
            assert torch.equal(getattr(ours.cameras, f), getattr(theirs.cameras, f)), f
        assert torch.equal(ours.dataparser_transform, theirs.dataparser_transform)
        assert ours.dataparser_scale == theirs.dataparser_scale
        assert ours.cameras.metadata.get("fisheye_crop_radius") == theirs.cameras.metadata.get("fisheye_crop_radius")


def test_mixed_rig_gets_each_frames_camera():
    path = default_scene_dir() / "transforms_rig.json"
    frames = {str(default_scene_dir() / f["file_path"]): f for f in json.loads(path.read_text())["frames"]}
    out = _parse(GeerNerfstudioDataParserConfig(data=path))
    cams = out.cameras
    kinds = set()
    for i, image in enumerate(out.image_filenames):
        frame = frames[str(image)]
        want = {"OPENCV_FISHEYE": CameraType.FISHEYE, "OPENCV": CameraType.PERSPECTIVE}[frame["camera_model"]]
        assert int(cams.camera_type[i]) == want.value
        assert float(cams.fx[i]) == pytest.approx(frame["fl_x"]) and float(cams.cy[i]) == pytest.approx(frame["cy"])
        k = [frame.get(n, 0.0) for n in ("k1", "k2", "k3", "k4")]
        assert cams.distortion_params[i, :4].tolist() == pytest.approx(k)
        assert camera_kind(cams, i) == frame["camera_model"]
        kinds.add(type(camera_model(cams, i)).__name__)
    assert kinds == {"OpenCVFisheyeCamera", "PinholeCamera"}


def _write_copy(meta: dict, folder: Path) -> None:
    """The room's file with absolute image paths, no split lists and no point cloud, into `folder`."""
    for f in meta["frames"]:
        f["file_path"] = str(default_scene_dir() / f["file_path"])
        f["mask_path"] = str(default_scene_dir() / f["mask_path"])
    meta = {k: v for k, v in meta.items() if not k.endswith("_filenames") and k != "ply_file_path"}
    (folder / "transforms.json").write_text(json.dumps(meta))


def test_frame_values_override_the_top_level(tmp_path):
    meta = json.loads((default_scene_dir() / "transforms.json").read_text())
    frame = meta["frames"][3]
    frame.update(camera_model="OPENCV", fl_x=48.0, fl_y=48.0, k1=0.01, p2=0.002)
    _write_copy(meta, tmp_path)
    out = _parse(GeerNerfstudioDataParserConfig(data=tmp_path, eval_mode="all"))
    i = [p.name for p in out.image_filenames].index(Path(frame["file_path"]).name)
    assert int(out.cameras.camera_type[i]) == CameraType.PERSPECTIVE.value
    assert float(out.cameras.fx[i]) == 48.0 and out.cameras.distortion_params[i].tolist() == pytest.approx(
        [0.01, 0, 0, 0, 0, 0.002])
    other = (i + 1) % len(out.image_filenames)
    assert int(out.cameras.camera_type[other]) == CameraType.FISHEYE.value
    assert float(out.cameras.metadata["geer_crop_radius"][other]) == 48.0  # fisheye_crop_radius kept per camera
    assert float(out.cameras.metadata["geer_crop_radius"][i]) == 0.0  # not for the pinhole frame


def test_unknown_camera_model_names_the_file_and_frame(tmp_path):
    meta = json.loads((default_scene_dir() / "transforms_rig.json").read_text())
    meta["frames"][0]["camera_model"] = "KANNALA"
    _write_copy(meta, tmp_path)
    # geer's parser checks the file first (geer_ns.data.dataset_checks: DatasetError, a ValueError)
    with pytest.raises(ValueError, match=r"transforms\.json: frames\[0\] .*frame_00000.*`camera_model` 'KANNALA'"):
        _parse(GeerNerfstudioDataParserConfig(data=tmp_path))


def test_poses_map_into_another_runs_frame(tmp_path):
    """The dev room's pinhole test views, alone in a file (so nerfstudio would centre and scale them
    differently), land exactly on the fisheye run's test cameras once mapped through its transform."""
    fisheye = shared_data("fisheye_room_dev", "transforms_fisheye.json")
    run_test = _parse(NerfstudioDataParserConfig(data=fisheye), "test")
    run_test.save_dataparser_transform(tmp_path / "dataparser_transforms.json")  # as ns-train writes it
    meta = json.loads(fisheye.with_name("transforms_pinhole.json").read_text())
    test = set(meta["test_filenames"])
    meta["frames"] = [dict(f, file_path=str(fisheye.parent / f["file_path"])) for f in meta["frames"]
                      if f["file_path"] in test]
    meta = {k: v for k, v in meta.items() if not k.endswith("_filenames") and k != "ply_file_path"}
    (tmp_path / "pinhole_test.json").write_text(json.dumps(meta))
    alone = _parse(GeerNerfstudioDataParserConfig(data=tmp_path / "pinhole_test.json", eval_mode="all"), "test")
    mapped = _parse(GeerNerfstudioDataParserConfig(data=tmp_path / "pinhole_test.json", eval_mode="all",
                                                   dataparser_transforms=tmp_path / "dataparser_transforms.json"),
                    "test")
    assert [p.name for p in mapped.image_filenames] == [p.name for p in run_test.image_filenames]
    assert (alone.cameras.camera_to_worlds - run_test.cameras.camera_to_worlds).abs().max() > 0.1
    assert torch.allclose(mapped.cameras.camera_to_worlds, run_test.cameras.camera_to_worlds, atol=1e-5)
    assert torch.allclose(mapped.dataparser_transform, run_test.dataparser_transform)
    assert mapped.dataparser_scale == pytest.approx(run_test.dataparser_scale)


def _room_meta(name: str) -> dict:
    """A transforms file of the embedded room with absolute paths (to be written elsewhere), no point cloud."""
    room = default_scene_dir()
    meta = json.loads((room / name).read_text())
    meta.pop("ply_file_path", None)
    for f in meta["frames"]:
        f["file_path"], f["mask_path"] = str(room / f["file_path"]), str(room / f["mask_path"])
    for key in ("train_filenames", "val_filenames", "test_filenames"):
        if key in meta:
            meta[key] = [str(room / name) for name in meta[key]]
    return meta


def test_split_lists_naming_no_frame_or_missing_name_the_file_and_field(tmp_path):
    from geer_ns.data.dataset_checks import DatasetError

    room = default_scene_dir()
    meta = _room_meta("transforms_rig.json")
    assert "val_filenames" in meta
    meta["val_filenames"].append(str(room / "images" / "not_a_frame.png"))
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"transforms\.json: `val_filenames` names 1 file\(s\) .*not_a_frame\.png"):
        _parse(GeerNerfstudioDataParserConfig(data=tmp_path), "val")
    del meta["val_filenames"]
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"transforms\.json: `val_filenames` is missing"):
        _parse(GeerNerfstudioDataParserConfig(data=tmp_path), "val")


def _said_eval_mode_all(config) -> bool:
    """Whether parsing both splits with `config` prints nerfstudio's warning about --eval-mode all."""
    import re

    from nerfstudio.utils.rich_utils import CONSOLE

    parser = config.setup()
    with CONSOLE.capture() as said:
        for split in ("train", "val"):
            parser.get_dataparser_outputs(split)
    return re.search(r"Be\s+careful\s+with\s+'--eval-mode=all'", said.get()) is not None


@pytest.mark.parametrize("lists", [False, True])
@pytest.mark.parametrize("eval_mode", ["fraction", "all"])
def test_the_eval_mode_all_warning_is_the_users_only(tmp_path, eval_mode, lists):
    """geer's parser parses every image through nerfstudio's once; the warning about --eval-mode all appears
    exactly where nerfstudio's own parser prints it for the user's settings (all, and no split lists in the
    file), never for geer's internal parse. The parse keeps every image either way."""
    meta = _room_meta("transforms.json")
    for key in ("train_filenames", "val_filenames", "test_filenames"):
        assert key in meta
        if not lists:
            meta.pop(key)
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    ours = _said_eval_mode_all(GeerNerfstudioDataParserConfig(data=tmp_path, eval_mode=eval_mode))
    theirs = _said_eval_mode_all(NerfstudioDataParserConfig(data=tmp_path, eval_mode=eval_mode))
    assert ours == theirs == (eval_mode == "all" and not lists)
    everything = GeerNerfstudioDataParserConfig(data=tmp_path, eval_mode=eval_mode).setup().parse_once().everything
    assert len(everything.image_filenames) == len(meta["frames"])
