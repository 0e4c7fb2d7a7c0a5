"""Rolling-shutter captures through the nerfstudio path: the file fields, their errors, the synthetic capture and
the model's rays (geer_ns/data/rolling_shutter.py, geer_ns/data/synthetic_rolling.py, geer_ns/shutter_views.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from geer_ns.data.dataset_checks import DatasetError
from geer_ns.data.nerfstudio_parser import GeerNerfstudioDataParserConfig
from geer_ns.data.rolling_shutter import MOTION_KEY, READOUT_KEY, end_pose
from geer_ns.data.synthetic_rolling import write_rolling_room
from geer_ns.data.views import host_camera_model
from geer_ns.render.transforms import world_to_camera_opencv
from geer_ns.shutter_views import shutter_view


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("rolling") / "room"
    write_rolling_room(root, n_views=9, size=16, turn_deg=8.0, move=0.05, seed=0)
    return root


def _parse(path, split="train"):
    return GeerNerfstudioDataParserConfig(data=path).setup().get_dataparser_outputs(split=split)


def test_the_capture_parses_with_its_readouts_and_end_poses(capture):
    meta = json.loads((capture / "transforms.json").read_text())
    out = _parse(capture / "transforms.json")
    cams = out.cameras
    assert cams.metadata[READOUT_KEY].reshape(-1).tolist() == [0] * 7  # top-to-bottom; views 0 and 8 held out
    by_name = {f["file_path"]: f for f in meta["frames"]}
    scale = float(out.dataparser_scale)
    for i, name in enumerate(out.image_filenames):
        frame = by_name[str(name.relative_to(capture))]
        start_file, end_file = (torch.tensor(frame[k], dtype=torch.float64) for k in
                                ("transform_matrix", "transform_matrix_end"))
        start = cams.camera_to_worlds[i].double()
        end = end_pose(start, cams.metadata[MOTION_KEY][i])
        # orientation "none": the parser only centres and scales; the end pose must follow the start's map
        turn = Rotation.from_matrix((start_file[:3, :3].T @ end_file[:3, :3]).numpy()).magnitude()
        assert turn == pytest.approx(np.deg2rad(8.0), abs=1e-6)
        assert torch.allclose(end[:, :3], start[:, :3] @ (start_file[:3, :3].T @ end_file[:3, :3]), atol=1e-6)
        moved = (end[:, 3] - start[:, 3]).norm() / scale
        assert float(moved) == pytest.approx(0.05, rel=1e-5)
    test = _parse(capture / "transforms.json", "test")
    assert READOUT_KEY in test.cameras.metadata and (test.cameras.metadata[READOUT_KEY] == -1).all()


def test_as_global_and_global_files_have_no_readout(capture):
    for name in ("transforms_as_global.json", "transforms_global.json"):
        assert READOUT_KEY not in (_parse(capture / name).cameras.metadata or {})


def _edited(capture, tmp_path, edit):
    meta = json.loads((capture / "transforms.json").read_text())
    edit(meta)
    for sub in ("images_rolling", "images_global", "masks", "points3d.ply"):
        (tmp_path / sub).symlink_to(capture / sub)
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    return tmp_path / "transforms.json"


def _rolling_frames(meta):
    return [f for f in meta["frames"] if "rolling_shutter" in f]


@pytest.mark.parametrize("edit, message", [
    (lambda m: _rolling_frames(m)[0].pop("transform_matrix_end"), "needs `transform_matrix_end`"),
    (lambda m: _rolling_frames(m)[0].pop("rolling_shutter"), "has no `rolling_shutter.readout`"),
    (lambda m: _rolling_frames(m)[0].update(rolling_shutter={"readout": "diagonal"}),
     "`rolling_shutter.readout` must be one of"),
    (lambda m: _rolling_frames(m)[0].update(rolling_shutter="top-to-bottom"), "must be an object with a `readout`"),
    (lambda m: _rolling_frames(m)[0].update(transform_matrix_end=[[1, 2], [3, 4]]), "must be a finite 4x4"),
])
def test_bad_rolling_shutter_fields_name_file_frame_and_field(capture, tmp_path, edit, message):
    path = _edited(capture, tmp_path, edit)
    with pytest.raises(DatasetError, match=message) as e:
        _parse(path)
    assert str(path) in str(e.value) and "frame 'images_rolling/frame_" in str(e.value)


def test_the_model_renders_a_rolling_view_from_its_mid_readout_pose(capture):
    out = _parse(capture / "transforms.json")
    camera = out.cameras[0:1]
    from geer_ns.data.views import native_view

    grid = native_view(host_camera_model(camera)).rays
    pose = camera.camera_to_worlds[0]
    viewmat, motion = shutter_view(camera, pose, grid, "cpu")
    start = pose.double()
    end = end_pose(start, camera.metadata[MOTION_KEY][0])
    mid_centre = 0.5 * (start[:, 3] + end[:, 3])
    assert torch.allclose(torch.linalg.inv(viewmat)[:3, 3], mid_centre, atol=1e-9)
    assert motion is not None and motion.offset == pytest.approx(0.025 * float(out.dataparser_scale), rel=1e-5)
    # the first sensor row is read at the start pose: its rays leave from the start's centre
    first = motion.origins[: grid.width]
    start_in_mid = (viewmat[:3, :3] @ start[:, 3] + viewmat[:3, 3])
    assert torch.allclose(first, start_in_mid.expand_as(first), atol=1e-9)
    still = out.cameras[0:1]
    still.metadata = {}
    viewmat_g, none = shutter_view(still, pose, grid, "cpu")
    assert none is None and torch.equal(viewmat_g, world_to_camera_opencv(pose.double()))


def test_velocities_give_the_same_motion_as_the_end_pose(capture, tmp_path):
    """A frame given by its start pose, velocities and readout time reads as the same motion as its end pose."""
    readout_time = 0.03

    def to_velocities(meta):
        for f in _rolling_frames(meta):
            start, end = (np.array(f[k], dtype=np.float64) for k in ("transform_matrix", "transform_matrix_end"))
            turn = Rotation.from_matrix(start[:3, :3].T @ end[:3, :3]).as_rotvec()  # about the camera's axes
            f["angular_velocity"] = (turn / readout_time).tolist()
            f["linear_velocity"] = ((end[:3, 3] - start[:3, 3]) / readout_time).tolist()
            f["rolling_shutter"] = {"readout": "top-to-bottom", "readout_time": readout_time}
            del f["transform_matrix_end"]

    ours = _parse(_edited(capture, tmp_path, to_velocities)).cameras.metadata[MOTION_KEY]
    ref = _parse(capture / "transforms.json").cameras.metadata[MOTION_KEY]
    assert torch.allclose(ours, ref, atol=1e-6)


@pytest.mark.parametrize("edit, message", [
    (lambda m: _rolling_frames(m)[0].update(angular_velocity=[0, 0, 1], linear_velocity=[0, 0, 0]),
     "give `transform_matrix_end` or the velocities, not both"),
    (lambda m: [_rolling_frames(m)[0].pop("transform_matrix_end"),
                _rolling_frames(m)[0].update(angular_velocity=[0, 0, 1], linear_velocity=[0, 0, 0])],
     "velocities need `rolling_shutter.readout_time`"),
    (lambda m: [_rolling_frames(m)[0].pop("transform_matrix_end"),
                _rolling_frames(m)[0].update(angular_velocity=[0, 0, 1])], "missing linear_velocity"),
])
def test_bad_velocity_fields_are_clear_errors(capture, tmp_path, edit, message):
    with pytest.raises(DatasetError, match=message):
        _parse(_edited(capture, tmp_path, edit))


# ------------------------------------------------------------------ geer-process-data --rolling-shutter
def _trajectory(times, omega, velocity):
    """Camera-to-world poses of a camera turning at `omega` (about its own axes) and moving at `velocity`."""
    r0 = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    out = np.tile(np.eye(4), (len(times), 1, 1))
    for k, t in enumerate(times):
        out[k, :3, :3] = r0 @ Rotation.from_rotvec(np.asarray(omega) * t).as_matrix()
        out[k, :3, 3] = np.array([0.5, -1.0, 2.0]) + np.asarray(velocity) * t
    return out


def test_process_data_readouts_recover_a_constant_motion(tmp_path):
    from geer_ns.process_data.readout import add_readout

    fps, readout_time = 30.0, 0.02
    omega, velocity = [0.4, -1.1, 2.0], [0.3, 0.0, -0.2]
    times = np.arange(6) / fps
    mids = _trajectory(times, omega, velocity)
    frames = [{"file_path": f"images/frame_{k * 1:05d}.png", "transform_matrix": mids[k].tolist()}
              for k in (3, 0, 5, 1, 4, 2)]  # any order in the file
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": frames}))
    assert add_readout(tmp_path / "transforms.json", "top-to-bottom", readout_time, fps) == 6
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert meta["rolling_shutter"] == {"readout": "top-to-bottom", "readout_time": readout_time}
    for f in meta["frames"]:
        k = int(f["file_path"][-9:-4])
        want_start = _trajectory([times[k] - readout_time / 2], omega, velocity)[0]
        want_end = _trajectory([times[k] + readout_time / 2], omega, velocity)[0]
        assert np.abs(np.array(f["transform_matrix"]) - want_start).max() < 1e-9
        assert np.abs(np.array(f["transform_matrix_end"]) - want_end).max() < 1e-9


@pytest.mark.parametrize("args, message", [
    (("top-to-bottom", None, 30.0, False), "needs --readout-time"),
    (("top-to-bottom", 0.03, None, False), "needs --frame-rate"),
    (("diagonal", 0.03, 30.0, False), "--rolling-shutter: expected global or one of"),
])
def test_process_data_rolling_shutter_options_are_checked(args, message):
    from geer_ns.process_data.frames import ProcessDataError
    from geer_ns.process_data.readout import check_options

    with pytest.raises(ProcessDataError, match=message):
        check_options(*args)
    check_options("top-to-bottom", 0.03, None, True)  # a video has its own frame rate
    check_options("global", None, None, False)


def test_a_readout_longer_than_a_frame_is_refused(tmp_path):
    from geer_ns.process_data.frames import ProcessDataError
    from geer_ns.process_data.readout import add_readout

    mids = _trajectory(np.arange(3) / 30.0, [0, 0, 1], [0, 0, 0])
    frames = [{"file_path": f"images/frame_{k:05d}.png", "transform_matrix": mids[k].tolist()} for k in range(3)]
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": frames}))
    with pytest.raises(ProcessDataError, match="is not shorter than a frame interval"):
        add_readout(tmp_path / "transforms.json", "top-to-bottom", 0.05, 30.0)


def test_readout_refinement_gets_the_gradient_of_its_image(capture):
    """--pipeline.model.readout-refinement: a render's loss reaches the image's 6 motion adjustments through the
    rays (against float64 central differences), and no other image's."""
    from geer_ns.data.views import native_view
    from geer_ns.refinement.readout import ReadoutRefinement
    from geer_ns.render import render

    out = _parse(capture / "transforms.json")
    camera = out.cameras[2:3]
    camera.metadata["cam_idx"] = 2
    grid = native_view(host_camera_model(camera)).rays
    g = torch.Generator().manual_seed(0)
    n = 200
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.8 + camera.camera_to_worlds[0, :, 3].double()
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=-1)
    scales = 0.05 + 0.1 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    opacities = 0.3 + 0.6 * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    weights = torch.rand(grid.num_rays, 3, generator=g, dtype=torch.float64)
    refine = ReadoutRefinement(7)

    def loss():
        viewmat, motion = shutter_view(camera, camera.camera_to_worlds[0], grid, "cpu", refine)
        rgb = render(means, quats, scales, opacities, colors, viewmat, grid, backend="cpu", motion=motion).rgb
        return (rgb.reshape(-1, 3) * weights).sum()

    loss().backward()
    grad = refine.adjustments.grad
    assert grad[2].abs().max() > 1e-3 and torch.isfinite(grad).all()
    assert (grad[[0, 1, 3, 4, 5, 6]] == 0).all()
    eps = 1e-6
    with torch.no_grad():
        for k in range(6):
            refine.adjustments[2, k] = eps
            plus = loss()
            refine.adjustments[2, k] = -eps
            minus = loss()
            refine.adjustments[2, k] = 0.0
            assert float((plus - minus) / (2 * eps)) == pytest.approx(float(grad[2, k]), rel=1e-4, abs=1e-6)


def test_a_frame_rolling_shutter_inherits_the_top_level_readout_time(capture, tmp_path):
    """A frame's own `rolling_shutter` object is merged over the top level's: velocities with a frame-level readout
    read the file's readout_time."""
    def velocities(meta):
        meta["rolling_shutter"] = {"readout": "top-to-bottom", "readout_time": 0.03}
        for frame in meta["frames"]:
            if "rolling_shutter" not in frame:  # the held-out global-shutter frames
                frame["rolling_shutter"] = {"readout": "global"}
        f = _rolling_frames(meta)[0]
        f.pop("transform_matrix_end")
        f.update(angular_velocity=[0.0, 0.0, 1.0], linear_velocity=[0.0, 0.0, 0.0],
                 rolling_shutter={"readout": "bottom-to-top"})

    cams = _parse(_edited(capture, tmp_path, velocities)).cameras
    readouts = cams.metadata[READOUT_KEY].reshape(-1).tolist()
    assert sorted(set(readouts)) == [0, 1]  # the edited frame reads bottom to top, the others top to bottom
    i = readouts.index(1)
    turn = Rotation.from_matrix(cams.metadata[MOTION_KEY][i].reshape(3, 4)[:, :3].double().numpy()).as_rotvec()
    assert np.allclose(turn, [0.0, 0.0, 0.03], atol=1e-7)


def test_sfm_readouts_stay_within_each_camera_and_refuse_ties():
    from geer_ns.data.rolling_shutter import sfm_readouts

    fps, readout_time = 30.0, 0.01
    names = ["left/frame_00001.png", "right/frame_00001.png", "left/frame_00002.png", "right/frame_00002.png"]
    mids = torch.tensor(_trajectory(np.array([0.0, 0.0, 1.0, 1.0]) / fps, [0.0, 0.0, 0.6], [0.3, 0.0, 0.0]))[:, :3]
    mids[1::2, :3, :3] = mids[1::2, :3, :3] @ torch.tensor(Rotation.from_euler("y", 90, degrees=True).as_matrix())
    starts, meta = sfm_readouts("top-to-bottom", readout_time, fps, names, mids, "--x.", groups=[1, 2, 1, 2])
    assert torch.isfinite(starts).all() and torch.isfinite(meta[MOTION_KEY]).all()
    mount = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    for i in range(4):  # the rig turns at 0.6 rad/s about the left camera's z; the 90 degrees between them is no motion
        turn = Rotation.from_matrix(meta[MOTION_KEY][i].reshape(3, 4)[:, :3].double().numpy()).as_rotvec()
        axis = np.array([0.0, 0.0, 0.6]) if i % 2 == 0 else mount.T @ np.array([0.0, 0.0, 0.6])  # in its own axes
        assert np.allclose(turn, axis * readout_time, atol=1e-6), (i, turn)
    with pytest.raises(DatasetError, match="two at the same capture time"):
        sfm_readouts("top-to-bottom", readout_time, fps, names, mids, "--x.")  # one camera: the times repeat


def test_render_paths_without_per_ray_poses_refuse_rolling_shutter_images(capture):
    from geer_ns.errors import OptionError
    from geer_ns.shutter_views import refuse_rolling_shutter

    cams = _parse(capture / "transforms.json").cameras
    with pytest.raises(OptionError, match="--pipeline.model.distributed gaussians does not render rolling-shutter"):
        refuse_rolling_shutter([cams[0:1]], "--pipeline.model.distributed gaussians")
    refuse_rolling_shutter([_parse(capture / "transforms_global.json").cameras[0:1]], "anything")


def test_an_offset_below_the_origins_is_refused():
    from geer_ns.render import MovingRays

    origins = torch.zeros(4, 3, dtype=torch.float64)
    origins[2, 0] = 0.3
    with pytest.raises(ValueError, match="motion.offset: 0.1 is below the farthest origin's distance 0.3"):
        MovingRays(origins, torch.zeros(4, 3, dtype=torch.float64), 0.1).check(4, origins)
    MovingRays(origins, torch.zeros(4, 3, dtype=torch.float64), 0.3).check(4, origins)
