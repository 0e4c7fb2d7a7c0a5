"""cameras_refined.json and colmap/ (geer_ns/refinement/refined_cameras.py) read back by geer's transforms.json parser (mapped
into the run's frame), by `geer-process-data --calibration` and by pycolmap: the refined intrinsics and poses
come back. The reference is what was written (the lens module's refined cameras, nerfstudio's camera optimizer),
read through code that does not write; and the model-level hook: a training step of a tiny model refines the lens
and the per-camera vignetting."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig

from geer_ns.cameras import FOVCamera, Fisheye624Camera, MeiCamera, OpenCVFisheyeCamera, PinholeCamera, from_pycolmap
from geer_ns.data.nerfstudio_parser import GeerNerfstudioDataParserConfig
from geer_ns.data.synthetic_room import default_scene_dir
from geer_ns.data.views import camera_model
from geer_ns.data.rolling_shutter import MOTION_KEY, READOUT_KEY
from geer_ns.refinement.lens import LensRefinement
from geer_ns.refinement.readout import ReadoutRefinement
from geer_ns.process_data.camera import read_calibration
from geer_ns.refinement.refined_cameras import FILE_NAME, colmap_camera, nerfstudio_intrinsics, refined_poses, write_refined_cameras

pytestmark = pytest.mark.filterwarnings("ignore:Using a non-tuple sequence:UserWarning")


def _fields_close(a, b, rel=1e-6):
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        assert getattr(a, f.name) == pytest.approx(getattr(b, f.name), rel=rel, abs=1e-9), f.name


def _refined_run(tmp_path, rolling: bool = False):
    """A refined 'run' of the embedded room: parsed cameras, lens deltas and pose corrections set at random;
    `rolling`: every frame read out top to bottom while turning 2 degrees and moving 3 cm, and the readout
    refinement's adjustments set at random too."""
    room = default_scene_dir()
    meta = json.loads((room / "transforms.json").read_text())
    meta.pop("ply_file_path", None)
    for f in meta["frames"]:
        f["file_path"], f["mask_path"] = str(room / f["file_path"]), str(room / f["mask_path"])
        if rolling:
            start = np.asarray(f["transform_matrix"], dtype=np.float64)
            turn = Rotation.from_rotvec(np.radians(2.0) * np.array([0.6, 0.8, 0.0])).as_matrix()
            end = start.copy()
            end[:3, :3] = start[:3, :3] @ turn
            end[:3, 3] += [0.03, 0.0, 0.01]
            f["transform_matrix_end"] = end.tolist()
    if rolling:
        meta["rolling_shutter"] = {"readout": "top-to-bottom"}
    meta = {k: v for k, v in meta.items() if not k.endswith("_filenames")}
    data = tmp_path / "data"
    data.mkdir()
    (data / "transforms.json").write_text(json.dumps(meta))
    outputs = GeerNerfstudioDataParserConfig(data=data, eval_mode="all").setup().get_dataparser_outputs("train")
    cameras = outputs.cameras
    lens = LensRefinement.from_cameras([camera_model(cameras, i) for i in range(len(cameras))], "full")
    gen = torch.Generator().manual_seed(0)
    optimizer = CameraOptimizerConfig(mode="SO3xR3").setup(num_cameras=len(cameras), device="cpu")
    with torch.no_grad():
        lens.deltas.copy_(0.01 * torch.randn(lens.deltas.shape, generator=gen, dtype=torch.float64))
        optimizer.pose_adjustment.copy_(0.02 * torch.randn(optimizer.pose_adjustment.shape, generator=gen))
    readout = ReadoutRefinement(len(cameras)) if rolling else None
    if readout is not None:
        with torch.no_grad():
            readout.adjustments.copy_(0.01 * torch.randn(readout.adjustments.shape, generator=gen, dtype=torch.float64))
    model = SimpleNamespace(lens=lens, camera_optimizer=optimizer, step=7, refined_frame=None, readout=readout,
                            config=SimpleNamespace(lens_refinement="full"))
    datamanager = SimpleNamespace(train_dataparser_outputs=outputs, train_dataset=SimpleNamespace(cameras=cameras),
                                  config=SimpleNamespace(dataparser=SimpleNamespace(data=data)))
    pipeline = SimpleNamespace(model=model, datamanager=datamanager)
    out = tmp_path / "run"
    path = write_refined_cameras(pipeline, out)
    outputs.save_dataparser_transform(tmp_path / "dataparser_transforms.json")
    return SimpleNamespace(pipeline=pipeline, path=path, out=out, lens=lens, tmp=tmp_path, outputs=outputs)


@pytest.fixture()
def run(tmp_path):
    return _refined_run(tmp_path)


def test_cameras_refined_json_parses_back_to_the_refined_cameras(run):
    back = GeerNerfstudioDataParserConfig(data=run.path, eval_mode="all",
                                          dataparser_transforms=run.tmp / "dataparser_transforms.json")
    parsed = back.setup().get_dataparser_outputs("train")
    assert [p.name for p in parsed.image_filenames] == [p.name for p in run.outputs.image_filenames]
    assert all(p.is_file() for p in parsed.image_filenames)
    refined = refined_poses(run.pipeline).float()
    assert (refined - run.outputs.cameras.camera_to_worlds).abs().max() > 1e-3  # the poses did move
    assert torch.allclose(parsed.cameras.camera_to_worlds, refined, atol=2e-5)
    truth = run.lens.refined_camera(0)
    assert truth != run.lens.cameras[0]
    for i in range(len(parsed.cameras)):
        _fields_close(camera_model(parsed.cameras, i), truth)  # float32 storage in nerfstudio's Cameras


def test_calibration_and_colmap_read_the_refined_lens(run):
    import pycolmap

    truth = run.lens.refined_camera(0)
    cal = read_calibration(run.path)[0]  # geer-process-data --calibration
    assert cal.model == "OPENCV_FISHEYE" and (cal.width, cal.height) == (truth.width, truth.height)
    np.testing.assert_allclose(cal.params, colmap_camera(truth)[1], rtol=1e-12)
    cal_txt = read_calibration(run.out / "colmap" / "cameras.txt")[0]
    np.testing.assert_allclose(cal_txt.params, cal.params, rtol=1e-12)
    recon = pycolmap.Reconstruction(str(run.out / "colmap"))
    assert len(recon.cameras) == 1 and len(recon.images) == len(run.outputs.image_filenames)
    _fields_close(from_pycolmap(recon.cameras[1]), truth, rel=1e-12)
    frames = json.loads(run.path.read_text())["frames"]
    for image_id, image in recon.images.items():
        c2w = np.asarray(frames[image_id - 1]["transform_matrix"])
        c2w[:3, 1:3] *= -1  # OpenGL -> OpenCV
        w2c = image.cam_from_world
        w2c = w2c() if callable(w2c) else w2c
        np.testing.assert_allclose(w2c.matrix()[:, :3], c2w[:3, :3].T, atol=1e-6)  # float32 poses: not exactly orthonormal
        np.testing.assert_allclose(w2c.matrix()[:, 3], -c2w[:3, :3].T @ c2w[:3, 3], atol=1e-6)


@pytest.mark.parametrize("camera", [
    PinholeCamera(40, 30, 30.0, 31.0, 20.0, 15.0, k1=-0.1, k2=0.01, p1=0.001, p2=0.002, k3=0.001),
    PinholeCamera(40, 30, 30.0, 31.0, 20.0, 15.0, k1=-0.1, k4=0.01),
    OpenCVFisheyeCamera(40, 30, 12.0, 12.5, 20.0, 15.0, k1=0.01, k4=-0.001),
    Fisheye624Camera(40, 30, 12.0, 12.5, 20.0, 15.0, k0=0.01, p0=1e-3, s2=1e-4),
    FOVCamera(40, 30, 20.0, 20.0, 20.0, 15.0, omega=0.8)])
def test_colmap_and_nerfstudio_forms_are_the_same_camera(camera):
    """Every refined camera COLMAP can hold comes back from pycolmap unchanged; a Mei camera has no COLMAP form."""
    import pycolmap

    name, params = colmap_camera(camera)
    back = pycolmap.Camera.create_from_model_name(1, name, 1.0, camera.width, camera.height)
    back.params = params
    assert from_pycolmap(back) == camera
    assert nerfstudio_intrinsics(camera)["w"] == 40
    assert colmap_camera(MeiCamera(40, 30, 12.0, 12.0, 20.0, 15.0, xi=0.5)) is None


def test_a_run_without_refinement_writes_nothing(run):
    run.pipeline.model.lens = None
    run.pipeline.model.camera_optimizer.config.mode = "off"
    assert write_refined_cameras(run.pipeline, run.tmp / "none") is None
    assert not (run.tmp / "none" / FILE_NAME).exists()


def test_a_rolling_shutter_runs_refined_readouts_parse_back(tmp_path):
    """Each frame's readout and refined end-of-readout pose: parsed back on its own (the parser's motion from the
    written start and end poses, in its own scale), the motion is the data's with the readout refinement's
    adjustment applied (rotation as is, travel per unit of each parse's scale)."""
    run = _refined_run(tmp_path, rolling=True)
    frames = json.loads(run.path.read_text())["frames"]
    assert all(f["rolling_shutter"] == {"readout": "top-to-bottom"} and "transform_matrix_end" in f for f in frames)
    parsed = GeerNerfstudioDataParserConfig(data=run.path, eval_mode="all").setup().get_dataparser_outputs("train")
    given, refinement = run.outputs.cameras.metadata, run.pipeline.model.readout
    assert torch.equal(parsed.cameras.metadata[READOUT_KEY], given[READOUT_KEY])
    with torch.no_grad():
        expected = torch.stack([refinement.adjusted(given[MOTION_KEY][i].double(), i) for i in range(len(frames))])
    assert (expected - given[MOTION_KEY].double()).abs().max() > 1e-3  # the adjustments moved the motion
    back = parsed.cameras.metadata[MOTION_KEY].double().reshape(-1, 3, 4)
    expected = expected.reshape(-1, 3, 4)
    assert torch.allclose(back[..., :3], expected[..., :3], atol=2e-6)
    travel = lambda m, scale: m[..., 3] / float(scale)  # noqa: E731 - in the file's units
    assert torch.allclose(travel(back, parsed.dataparser_scale), travel(expected, run.outputs.dataparser_scale),
                          atol=1e-6)


def test_readout_refinement_alone_writes_the_refined_cameras(tmp_path):
    run = _refined_run(tmp_path, rolling=True)
    run.pipeline.model.lens = None
    run.pipeline.model.camera_optimizer.config.mode = "off"
    path = write_refined_cameras(run.pipeline, run.tmp / "readouts_only")
    assert path is not None and all("transform_matrix_end" in f for f in json.loads(path.read_text())["frames"])
