"""geer-process-data on the Blender-rendered dev fisheye room: poses and focal length against the renderer's
ground truth (after a similarity alignment), the video path, a fixed user calibration, explained failures, and
a few geer training steps on the output.

Subsets of the 48 views keep this file fast on 2 cores; the accuracy bounds are the issue's.
"""

from __future__ import annotations

import copy
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from geer_ns.process_data import ProcessDataConfig, ProcessDataError, run
from geer_ns.process_data.evaluate import pose_errors
from conftest import shared_data

TRUE_FOCAL = 384 / math.pi  # 180-degree equidistant fisheye over 384 px (docs/test_data.md)


def _dev_room() -> Path:
    return shared_data("fisheye_room_dev")


def _true_poses() -> dict:
    meta = json.loads((_dev_room() / "transforms_fisheye.json").read_text())
    return {Path(f["file_path"]).name: np.array(f["transform_matrix"]) for f in meta["frames"]}


def _copy_frames(indices, dst: Path) -> Path:
    dst.mkdir(parents=True)
    for i in indices:
        shutil.copy(_dev_room() / "images_fisheye" / f"frame_{i:05d}.jpg", dst)
    return dst


def _pose_errors(transforms: dict, truth: dict):
    """Mean rotation error (deg) and mean position error relative to the true path's extent, after the
    similarity SfM cannot recover (fitted to the poses: evaluate.align_poses); OpenGL camera axes in both."""
    est = {f["file_path"]: np.array(f["transform_matrix"]) for f in transforms["frames"]}
    rot, pos, _ = pose_errors(est, truth)
    return rot, pos


@pytest.fixture(scope="module")
def folder_run(tmp_path_factory):
    """16 of the 48 views (every second of the first 32), an unordered folder: exhaustive matching. A 17th
    photo cut in half lies among them; --skip-bad-images leaves it out."""
    root = tmp_path_factory.mktemp("process_data")
    src = _copy_frames(range(0, 32, 2), root / "input")
    whole = (src / "frame_00002.jpg").read_bytes()
    (src / "frame_00001.jpg").write_bytes(whole[: len(whole) // 2])
    out = root / "dataset"
    report = run(ProcessDataConfig(data=src, output_dir=out, num_threads=2, skip_bad_images=True))
    return out, report


def test_every_image_registers_with_accurate_poses_and_focal(folder_run):
    out, report = folder_run
    transforms = json.loads((out / "transforms.json").read_text())
    assert report["num_registered_images"] == report["num_input_images"] == 16
    assert len(transforms["frames"]) == 16
    truth = {f"images/{k}": v for k, v in _true_poses().items()}
    rot_deg, pos_rel = _pose_errors(transforms, truth)
    print(f"rotation error {rot_deg:.3f} deg, position error {100 * pos_rel:.3f} % of the path, "
          f"focal {transforms['fl_x']:.3f} / {transforms['fl_y']:.3f} px (true {TRUE_FOCAL:.3f})")
    assert rot_deg < 0.5
    assert pos_rel < 0.01
    assert transforms["camera_model"] == "OPENCV_FISHEYE"
    for key in ("fl_x", "fl_y"):
        assert abs(transforms[key] - TRUE_FOCAL) < 0.01 * TRUE_FOCAL, key
    assert report["mean_reprojection_error_px"] < 1.0


def test_output_is_a_complete_dataset(folder_run):
    import pycolmap

    out, _ = folder_run
    transforms = json.loads((out / "transforms.json").read_text())
    for key in ("k1", "k2", "k3", "k4"):
        assert key in transforms
    assert "applied_transform" not in transforms  # poses, points3d.ply and sparse/0 share COLMAP's world
    assert (out / transforms["ply_file_path"]).is_file()
    recon = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert recon.num_reg_images() == 16 and recon.num_points3D() > 1000
    # The automatic mask is the lens's image circle: compare with the renderer's own circle mask.
    mask = cv2.imread(str(out / transforms["frames"][0]["mask_path"]), cv2.IMREAD_GRAYSCALE) > 127
    true_mask = cv2.imread(str(_dev_room() / "masks" / "fisheye_mask.png"), cv2.IMREAD_GRAYSCALE) > 127
    assert (mask & true_mask).sum() / (mask | true_mask).sum() > 0.98
    for frame in transforms["frames"]:
        assert (out / frame["file_path"]).is_file()


def test_a_photo_cut_in_half_is_left_out_with_skip_bad_images_and_listed(folder_run):
    out, report = folder_run
    (line,) = report["skipped_bad_images"]
    assert line.endswith("frame_00001.jpg: cut short (truncated); copy it again from the camera or remove it")
    assert not (out / "images" / "frame_00001.jpg").exists() and len(list((out / "images").iterdir())) == 16
    assert json.loads((out / "process_data_report.json").read_text())["skipped_bad_images"] == [line]
    assert sorted(p.name for p in out.iterdir()) == ["colmap", "images", "masks", "points3d.ply",
                                                      "process_data_report.json", "sparse", "transforms.json"]


def test_geer_trains_on_the_output(folder_run, tmp_path, single_thread):
    """A few geer training steps on the dataset (its first 4 frames, to keep the BEAP caching short)."""
    from geer_ns.config import geer_method

    out, _ = folder_run
    data = tmp_path / "data"
    data.mkdir()
    for name in ("images", "masks", "points3d.ply"):
        (data / name).symlink_to(out / name)
    transforms = json.loads((out / "transforms.json").read_text())
    transforms["frames"] = transforms["frames"][:4]
    (data / "transforms.json").write_text(json.dumps(transforms))
    cfg = copy.deepcopy(geer_method.config)
    cfg.pipeline.datamanager.data = data
    cfg.output_dir = tmp_path / "outputs"
    cfg.max_num_iterations = 3
    cfg.vis = "tensorboard"
    cfg.viewer.quit_on_train_completion = True
    cfg.steps_per_eval_image = cfg.steps_per_eval_all_images = 0
    cfg.pipeline.model.num_downscales = 2
    cfg.set_timestamp()
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    _assert_seeds_project_onto_their_keypoints(trainer.pipeline.datamanager, out)
    trainer.train()
    model = trainer.pipeline.model
    assert model.num_points > 1000  # seeded from points3d.ply
    assert all(bool(p.isfinite().all()) for p in model.parameters())
    assert any(cfg.output_dir.rglob("step-*.ckpt"))


def _assert_seeds_project_onto_their_keypoints(datamanager, dataset: Path) -> None:
    """The seed points geer's datamanager made from points3d.ply, seen through its first training camera,
    land on the SIFT keypoints COLMAP measured them at (whole chain: export, nerfstudio-data, seeding)."""
    import pycolmap
    import torch

    from geer_ns.cameras import from_nerfstudio

    outputs = datamanager.train_dataparser_outputs
    name = Path(outputs.image_filenames[0]).name
    recon = pycolmap.Reconstruction(str(dataset / "sparse" / "0"))
    row_of = {pid: i for i, pid in enumerate(sorted(recon.points3D))}  # points3d.ply is in point-id order
    image = next(im for im in recon.images.values() if im.name == name)
    obs = [(p.xy, row_of[p.point3D_id]) for p in image.points2D if p.has_point3D()]
    keypoints = torch.tensor(np.array([xy for xy, _ in obs]), dtype=torch.float64)
    seeds = outputs.metadata["points3D_xyz"][[row for _, row in obs]].double()
    c2w = outputs.cameras.camera_to_worlds[0].double()
    cam = (seeds - c2w[:, 3]) @ c2w[:, :3] * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)  # OpenGL->OpenCV
    px, valid = from_nerfstudio(outputs.cameras, 0).project(cam)
    err = (px - keypoints).norm(dim=-1)[valid]
    assert len(obs) > 100 and bool(valid.all())
    assert float(err.median()) < 1.0, float(err.median())


def test_video_path_samples_sharp_frames_and_registers_them(tmp_path):
    """A video of 12 views (every second of the first 24) with one blurred copy inserted: the blurred frame is
    skipped, the others register at the true poses."""
    indices = list(range(0, 24, 2))
    video = tmp_path / "capture.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (384, 384))
    writer.set(cv2.VIDEOWRITER_PROP_QUALITY, 95)
    order = []
    for i in indices:
        frame = cv2.imread(str(_dev_room() / "images_fisheye" / f"frame_{i:05d}.jpg"))
        writer.write(frame)
        order.append(i)
        if i == 10:
            writer.write(cv2.GaussianBlur(frame, (0, 0), 3.0))
            order.append(None)
    writer.release()
    out = tmp_path / "dataset"
    report = run(ProcessDataConfig(data=video, output_dir=out, num_frames_target=len(order), num_threads=2))
    assert report["matching"].startswith("sequential")
    assert report["frames_skipped_blurry"] == 1
    transforms = json.loads((out / "transforms.json").read_text())
    names = [f["file_path"] for f in transforms["frames"]]
    blurred = f"images/frame_{order.index(None):05d}.png"
    assert blurred not in names and len(names) == len(indices)
    truth = _true_poses()
    truth = {f"images/frame_{k:05d}.png": truth[f"frame_{i:05d}.jpg"] for k, i in enumerate(order) if i is not None}
    rot_deg, pos_rel = _pose_errors(transforms, truth)
    print(f"video: rotation error {rot_deg:.3f} deg, position error {100 * pos_rel:.3f} %")
    assert rot_deg < 0.5 and pos_rel < 0.01


def test_user_calibration_is_held_fixed_for_each_rig_camera(tmp_path):
    """--calibration with the renderer's intrinsics (nerfstudio transforms.json) and --camera-per-folder on two
    folders: two COLMAP cameras, both keep the calibration exactly; per-frame intrinsics and masks."""
    import pycolmap

    src = tmp_path / "input"
    _copy_frames(range(0, 24, 8), src / "left")
    _copy_frames(range(4, 24, 8), src / "right")
    out = tmp_path / "dataset"
    run(ProcessDataConfig(data=src, output_dir=out, calibration=_dev_room() / "transforms_fisheye.json",
                          camera_per_folder=True, num_threads=2))
    recon = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert recon.num_reg_images() == 6 and len(recon.cameras) == 2
    for camera in recon.cameras.values():
        assert camera.model.name == "OPENCV_FISHEYE"
        np.testing.assert_allclose(camera.params, [TRUE_FOCAL, TRUE_FOCAL, 192, 192, 0, 0, 0, 0], atol=1e-9)
    transforms = json.loads((out / "transforms.json").read_text())
    for frame in transforms["frames"]:
        folder = frame["file_path"].split("/")[1]
        assert frame["mask_path"] == f"masks/{folder}.png" and frame["fl_x"] == pytest.approx(TRUE_FOCAL)


def _noise_images(src: Path, n: int = 4, suffix: str = ".png") -> Path:
    """Independent noise images (no shared data needed): SIFT finds keypoints, no pair verifies."""
    src.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        noise = cv2.GaussianBlur(rng.integers(0, 256, (160, 160), dtype=np.uint8), (0, 0), 1.5)
        cv2.imwrite(str(src / f"noise_{i}{suffix}"), cv2.normalize(noise, None, 0, 255, cv2.NORM_MINMAX))
    return src


def _with_bad_images(src: Path) -> dict:
    """Noise JPEGs plus three that cannot be used: {file name: the start of its line's reason}."""
    _noise_images(src, 4, ".jpg")
    whole = (src / "noise_0.jpg").read_bytes()
    (src / "cut.jpg").write_bytes(whole[: len(whole) // 2])  # a copy cut short: OpenCV still decodes it
    assert cv2.imread(str(src / "cut.jpg")) is not None
    (src / "not_an_image.jpg").write_bytes(b"\xff\xd8 not a jpeg")
    cv2.imwrite(str(src / "small.jpg"), np.zeros((120, 160, 3), np.uint8))
    return {"cut.jpg": "cut short (truncated)", "not_an_image.jpg": "not an image (unknown format)",
            "small.jpg": "160x120 px, but 4 image(s) of the input (one shared camera) are 160x160"}


def _old_dataset(out: Path) -> dict:
    (out / "images").mkdir(parents=True)
    files = {"images/old.png": "old image", "transforms.json": "old dataset", "notes.txt": "mine"}
    for name, text in files.items():
        (out / name).write_text(text)
    return files


def _files(out: Path) -> dict:
    return {p.relative_to(out).as_posix(): p.read_text() for p in sorted(out.rglob("*")) if p.is_file()}


def test_bad_images_stop_the_run_before_anything_is_written_and_a_fixed_input_reruns(tmp_path):
    """One line per bad image, naming it and what to do; nothing written (a user's file stays, a new output
    folder is not even created); with the bad images removed the same command runs (no --overwrite)."""
    src = tmp_path / "input"
    bad = _with_bad_images(src)
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "notes.txt").write_text("mine")
    for out in (kept, tmp_path / "new"):
        with pytest.raises(ProcessDataError) as caught:
            run(ProcessDataConfig(data=src, output_dir=out, camera_model="OPENCV", num_threads=2))
        lines = str(caught.value).splitlines()
        assert lines[0] == "3 of 7 input image(s) cannot be used:"
        for name, reason in bad.items():
            (line,) = [line for line in lines if name in line]
            assert line.startswith(f"{src / name}: {reason}") and ("remove it" in line), line
        assert lines[-1].startswith("Fix or remove them, or pass --skip-bad-images True to go on without them.")
    assert [p.name for p in kept.iterdir()] == ["notes.txt"] and not (tmp_path / "new").exists()
    for name in bad:
        (src / name).unlink()
    with pytest.raises(ProcessDataError, match="no overlap"):  # past the check: on to structure from motion
        run(ProcessDataConfig(data=src, output_dir=kept, camera_model="OPENCV", num_threads=2))
    assert [p.name for p in kept.iterdir()] == ["notes.txt"]  # the failed run removed what it wrote


def test_skip_bad_images_goes_on_and_a_failure_puts_the_replaced_dataset_back(tmp_path):
    """--skip-bad-images: the run goes on to structure from motion without them and lists them at the end of
    its message; the run then fails, so the dataset --overwrite was replacing comes back as it was."""
    src = tmp_path / "input"
    bad = _with_bad_images(src)
    out = tmp_path / "dataset"
    before = _old_dataset(out)
    with pytest.raises(ProcessDataError, match="no overlap") as caught:
        run(ProcessDataConfig(data=src, output_dir=out, camera_model="OPENCV", num_threads=2, skip_bad_images=True,
                              overwrite=True))
    tail = str(caught.value).split("--skip-bad-images: 3 input image(s) were left out:\n")[1].splitlines()
    assert [line.split(": ")[0] for line in tail] == [str(src / name) for name in sorted(bad)]
    assert _files(out) == before and sorted(p.name for p in out.iterdir()) == ["images", "notes.txt", "transforms.json"]


def test_a_kept_output_over_a_replaced_dataset_and_a_killed_run_are_undone_by_the_rerun(tmp_path):
    """The output folder's rules (process_data/output.py) without structure from motion: a failure that keeps
    its output while --overwrite was replacing a dataset keeps both; a run killed mid-way leaves its marker.
    Either way the re-run without --overwrite puts the folder back as it was before that run."""
    from geer_ns.process_data.output import OutputRun

    data, out = tmp_path / "input", tmp_path / "dataset"
    data.mkdir()
    before = _old_dataset(out)
    with pytest.raises(ProcessDataError) as caught:
        with OutputRun(out, data, overwrite=True):
            (out / "sparse").mkdir()
            (out / "sparse" / "cameras.txt").write_text("the model to look at")
            raise ProcessDataError("the camera model does not fit the lens", keeps_output=True)
    assert str(caught.value).endswith("a re-run with --overwrite replaces both, a re-run without puts it back.")
    assert (out / "sparse" / "cameras.txt").is_file() and (out / "notes.txt").is_file()
    with pytest.raises(ProcessDataError, match="already holds a dataset .*use --overwrite"):
        with OutputRun(out, data, overwrite=False):
            pass
    assert _files(out) == before and sorted(p.name for p in out.iterdir()) == ["images", "notes.txt", "transforms.json"]
    killed = OutputRun(out, data, overwrite=True).__enter__()  # a run killed after writing images: no __exit__
    (out / "images").mkdir()
    (out / "images" / "new.png").write_text("half-written")
    assert killed.previous is not None and _files(out)["notes.txt"] == "mine"
    with pytest.raises(ProcessDataError, match="already holds a dataset"):
        with OutputRun(out, data, overwrite=False):
            pass
    assert _files(out) == before


def test_images_without_overlap_are_explained(tmp_path):
    src = _noise_images(tmp_path / "input")
    with pytest.raises(ProcessDataError, match="no overlap"):
        run(ProcessDataConfig(data=src, output_dir=tmp_path / "out", camera_model="OPENCV", num_threads=2))
    assert not (tmp_path / "out").exists()  # the folder the failed run had created is gone


def test_a_pinhole_model_on_fisheye_images_is_refused_with_the_fisheye_suggestion(tmp_path):
    """OPENCV on 180-degree views registers with a low reprojection error (it keeps only the features it can
    explain) but bends fx and fy apart (measured on 16 views: 140 vs 158 px, poses 24 degrees off)."""
    src = _copy_frames(range(0, 20, 2), tmp_path / "input")
    out = tmp_path / "dataset"
    with pytest.raises(ProcessDataError, match=r"(?s)does not fit the lens.*--camera-model OPENCV_FISHEYE") as caught:
        run(ProcessDataConfig(data=src, output_dir=out, camera_model="OPENCV", num_threads=2))
    assert not (out / "transforms.json").exists() and (out / "sparse" / "0").is_dir()
    assert str(caught.value).endswith(f"A re-run into {out} replaces what this run left there (no --overwrite needed).")
    # The re-run (here with other input, which fails at once) replaces the kept model without --overwrite.
    with pytest.raises(ProcessDataError, match="no overlap"):
        run(ProcessDataConfig(data=_noise_images(tmp_path / "noise"), output_dir=out, camera_model="OPENCV",
                              num_threads=2))
    assert list(out.iterdir()) == []


def test_help_runs_as_a_module():
    result = subprocess.run([sys.executable, "-m", "geer_ns.process_data", "--help"], capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    for flag in ("--data", "--camera-model", "--calibration", "--camera-per-folder", "--mask", "--skip-bad-images"):
        assert flag in result.stdout


def test_umeyama_recovers_a_known_similarity():
    from geer_ns.process_data.evaluate import umeyama

    rng = np.random.default_rng(1)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rot = q * np.sign(np.linalg.det(q))  # a proper rotation
    src = rng.normal(size=(20, 3))
    dst = (2.5 * (rot @ src.T)).T + np.array([1.0, -2.0, 0.5])
    s, r, t = umeyama(src, dst)
    assert s == pytest.approx(2.5, rel=1e-12)
    np.testing.assert_allclose(r, rot, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, -2.0, 0.5], atol=1e-12)


def test_align_poses_recovers_a_known_similarity_of_noisy_poses():
    """Poses on a nearly planar path, moved by a known similarity, with 0.1 deg of rotation noise: the
    pose-fitted alignment finds the similarity and measures about that noise."""
    from geer_ns.process_data.evaluate import align_poses, pose_errors

    rng = np.random.default_rng(2)

    def rotation(axis_angle):
        return cv2.Rodrigues(np.asarray(axis_angle, dtype=np.float64))[0]

    sim_r, sim_s, sim_t = rotation([0.3, -0.2, 1.1]), 0.4, np.array([2.0, 0.0, -1.0])
    truth, est = {}, {}
    for i in range(30):
        pose = np.eye(4)
        pose[:3, :3] = rotation(rng.normal(size=3))
        pose[:3, 3] = [i * 0.2, np.sin(i / 5), 1.6 + 0.01 * rng.normal()]
        truth[str(i)] = pose
        noisy = pose.copy()
        noisy[:3, :3] = rotation(rng.normal(size=3) * math.radians(0.1) / math.sqrt(3)) @ pose[:3, :3]
        moved = np.eye(4)  # est = similarity^-1 applied to the truth
        moved[:3, :3] = sim_r.T @ noisy[:3, :3]
        moved[:3, 3] = sim_r.T @ (noisy[:3, 3] - sim_t) / sim_s
        est[str(i)] = moved
    s, r, t = align_poses([est[k] for k in sorted(est)], [truth[k] for k in sorted(est)])
    assert s == pytest.approx(sim_s, rel=1e-4)  # up to the rotation noise
    np.testing.assert_allclose(r, sim_r, atol=1e-3)
    rot, pos, _ = pose_errors(est, truth)
    assert 0.03 < rot < 0.15 and pos < 1e-3
