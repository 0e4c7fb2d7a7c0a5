"""``geer-process-data``: a folder of images or a video -> a dataset ``ns-train geer --data`` reads.

Stages: input check (every image decoded before anything is written), frames (copy / sample), masks and
starting intrinsics, SIFT extraction, matching, incremental mapping with bundle adjustment, export, report.
Each failure is raised as a ProcessDataError with its explanation; what a failed run leaves in the output
folder is output.py's rule (nothing, or what its explanation points at, which a re-run replaces).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Literal, Optional

import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from geer_ns.process_data import camera as camera_setup
from geer_ns.process_data import export, frames, readout, sfm
from geer_ns.process_data.frames import ProcessDataError
from geer_ns.process_data.output import OutputRun


@dataclass
class ProcessDataConfig:
    """Structure from motion for fisheye (and other) cameras with pycolmap (no COLMAP binary): writes
    images/, masks/, transforms.json (nerfstudio format, OPENCV_FISHEYE k1..k4), sparse/0 and points3d.ply."""

    data: Path
    """A folder of images (sub-folders allowed) or a video file."""
    output_dir: Path
    """Where the dataset is written (then: ns-train geer --data OUTPUT_DIR)."""
    camera_model: Literal["OPENCV_FISHEYE", "OPENCV", "SIMPLE_RADIAL"] = "OPENCV_FISHEYE"
    """Model refined by bundle adjustment: OPENCV_FISHEYE for fisheye lenses, OPENCV/SIMPLE_RADIAL for narrow."""
    calibration: Optional[Path] = None
    """Your calibration, held fixed: COLMAP cameras.txt (one camera, or one per folder) or nerfstudio .json."""
    camera_per_folder: bool = False
    """One camera per sub-folder (camera rigs; cameras.txt lists them in sorted folder order)."""
    mask: Optional[Path] = None
    """Mask image (white = use) for every camera, or a folder with <sub-folder>.png per camera."""
    auto_mask: bool = True
    """Without --mask: detect the fisheye image circle (black border) and mask what lies outside it."""
    fov_deg: Optional[float] = None
    """Lens field of view for the starting focal length (fisheye default 180, over the circle or diagonal)."""
    matching: Literal["auto", "sequential", "exhaustive"] = "auto"
    """auto: sequential for video and for more than --exhaustive-max-images images, else exhaustive."""
    exhaustive_max_images: int = 150
    """With --matching auto, larger image folders are matched sequentially (in file-name order)."""
    sequential_overlap: int = 10
    """Sequential matching: each frame with its next N frames (and frames 2^k further on)."""
    loop_keyframe_interval: int = 10
    """Sequential matching: every N-th frame is also matched with every other one (loop closure); 0: off."""
    vocab_tree_path: Optional[Path] = None
    """COLMAP vocabulary tree file: adds vocabulary-tree loop-closure matching."""
    guided_matching: bool = False
    """Re-match pairs along their epipolar geometry: more matches (slower); try it if images stay unregistered."""
    num_frames_target: int = 300
    """Video: number of frames to sample."""
    blur_ratio: float = 0.5
    """Video: skip a sampled frame whose sharpness is below this times its neighbors'."""
    refine_principal_point: bool = False
    """Also refine cx, cy in bundle adjustment."""
    max_image_size: int = 3200
    """Images are downscaled to this size for feature extraction only."""
    max_reprojection_error: float = 2.0
    """Mean reprojection error (px) above which the camera model is taken as wrong (no transforms.json)."""
    max_focal_asymmetry: float = 0.05
    """Relative fx/fy difference above which the camera model is taken as wrong (no transforms.json)."""
    min_registered_fraction: float = 0.5
    """Fail when fewer than this fraction of the images register."""
    num_threads: int = -1
    """Threads for pycolmap (-1: all cores)."""
    skip_bad_images: bool = False
    """Go on without input images that cannot be used (not decodable, cut short, another size than their
    camera's) and list them at the end; without it they stop the run before anything is written."""
    rolling_shutter: Literal["global", "top-to-bottom", "bottom-to-top", "left-to-right", "right-to-left"] = "global"
    """The sensor's readout: global, or the direction a rolling shutter reads it (each frame's motion during the
    readout is estimated from its neighbours' poses: docs/rolling_shutter.md)."""
    readout_time: Optional[float] = None
    """Rolling shutter: seconds from the first row (column) read to the last."""
    frame_rate: Optional[float] = None
    """Rolling shutter with a folder of images: frames per second of the capture (images in file-name order); a
    video's own frame rate is read from the file."""
    overwrite: bool = False
    """Replace an existing dataset in output_dir (kept aside until the run has succeeded)."""
    verbose: bool = False
    """Show pycolmap's own log."""

def run(cfg: ProcessDataConfig) -> Dict[str, object]:
    """Run every stage; returns the report (also written to output_dir/process_data_report.json)."""
    import pycolmap

    if not cfg.verbose:
        pycolmap.logging.minloglevel = 1  # warnings and errors only
    if not cfg.data.exists():
        raise ProcessDataError(f"--data {cfg.data} does not exist")
    video = frames.is_video(cfg.data)
    if not video and not cfg.data.is_dir():
        raise ProcessDataError(f"--data {cfg.data}: neither a folder of images nor a video "
                               f"({', '.join(sorted(frames.VIDEO_SUFFIXES))})")
    readout.check_options(cfg.rolling_shutter, cfg.readout_time, cfg.frame_rate, video)
    t0 = time.perf_counter()
    checked = None if video else _checked_images(cfg)
    try:
        with OutputRun(cfg.output_dir, cfg.data, cfg.overwrite):
            report = _run_stages(cfg, checked, t0)
    except ProcessDataError as e:
        if checked is not None and checked.bad:  # said at the end, also of a failed run
            e.args = (f"{e}\n{_left_out(checked.bad)}",)
        raise
    if checked is not None and checked.bad:
        CONSOLE.print(f"[yellow]{_left_out(checked.bad)}")
    return report


def _checked_images(cfg: ProcessDataConfig) -> frames.CheckedImages:
    """Every input image checked before anything is written; bad ones stop the run unless --skip-bad-images."""
    checked = frames.check_images(cfg.data, cfg.camera_per_folder)
    if checked.bad and not cfg.skip_bad_images:
        total = len(checked.bad) + sum(len(g.image_names) for g in checked.groups)
        raise ProcessDataError(
            f"{len(checked.bad)} of {total} input image(s) cannot be used:\n" + "\n".join(checked.bad)
            + f"\nFix or remove them, or pass --skip-bad-images True to go on without them. Nothing was written to "
            f"{cfg.output_dir}.")
    return checked


def _left_out(bad: List[str]) -> str:
    return f"--skip-bad-images: {len(bad)} input image(s) were left out:\n" + "\n".join(bad)


def _run_stages(cfg: ProcessDataConfig, checked: Optional[frames.CheckedImages], t0: float) -> Dict[str, object]:
    """Every stage after the input check, writing into cfg.output_dir (prepared by OutputRun)."""
    timings: Dict[str, float] = {}
    extra: Dict[str, object] = {}
    images_dir = cfg.output_dir / "images"
    images_dir.mkdir()
    work = cfg.output_dir / "colmap"
    work.mkdir()
    if checked is None:
        group, stats = frames.sample_video(cfg.data, images_dir, cfg.num_frames_target, blur_ratio=cfg.blur_ratio)
        groups = [group]
        extra.update(stats)
    else:
        groups = checked.groups
        frames.copy_images(cfg.data, images_dir, groups)
        if checked.bad:
            extra["skipped_bad_images"] = checked.bad
    video = checked is None
    names = [n for g in groups for n in g.image_names]
    if len(names) < 3:
        raise ProcessDataError(f"--data {cfg.data}: {len(names)} usable image(s); structure from motion needs at "
                               "least 3")
    timings["frames"] = time.perf_counter() - t0

    t = time.perf_counter()
    setups = camera_setup.setup_cameras(groups, cfg.output_dir, work, cfg.camera_model, cfg.calibration, cfg.mask,
                                        cfg.auto_mask, cfg.fov_deg)
    db = work / "database.db"
    model = setups[0].model
    circle_found = any(s.circle is not None for s in setups)
    if circle_found and not any(s.model in camera_setup.FISHEYE_MODELS for s in setups):
        CONSOLE.print(f"[bold yellow]The images have a fisheye image circle but the camera model is {model}, "
                      "which cannot describe rays near or beyond 90 degrees: use --camera-model OPENCV_FISHEYE")
    sfm.extract_features(db, images_dir, groups, setups, cfg.num_threads, cfg.max_image_size)
    timings["features"] = time.perf_counter() - t

    t = time.perf_counter()
    sequential = cfg.matching == "sequential" or (
        cfg.matching == "auto" and (video or len(names) > cfg.exhaustive_max_images))
    if sequential:
        pairs = set()
        for g in groups:  # frames of one camera are in capture order; rig cameras are matched across folders
            pairs |= sfm.sequential_pairs(g.image_names, cfg.sequential_overlap)
            pairs |= sfm.loop_pairs(g.image_names, cfg.loop_keyframe_interval)
        for a, b in zip(groups, groups[1:]):
            pairs |= {(x, y) for x, y in zip(a.image_names, b.image_names)}
    else:
        pairs = sfm.exhaustive_pairs(names)
    extra["matching"] = f"{'sequential' if sequential else 'exhaustive'}, {len(pairs)} pairs"
    CONSOLE.print(f"Matching: {extra['matching']}")
    sfm.match(db, work, pairs, cfg.num_threads, cfg.vocab_tree_path, cfg.guided_matching)
    timings["matching"] = time.perf_counter() - t

    t = time.perf_counter()
    fixed = cfg.calibration is not None
    mapped = sfm.incremental_mapping(db, images_dir, work, len(names), fixed, cfg.refine_principal_point,
                                     cfg.num_threads)
    timings["mapping"] = time.perf_counter() - t
    if mapped is None:
        stats = sfm.database_stats(db)
        raise ProcessDataError("structure from motion failed: no initial image pair could be reconstructed.\n"
                               + sfm.explain_failure(stats, set(), names, model, circle_found))
    recon = mapped.reconstruction
    sparse0 = cfg.output_dir / "sparse" / "0"
    sparse0.mkdir(parents=True)
    recon.write(sparse0)
    timings["total"] = time.perf_counter() - t0
    report = export.summary(recon, names, mapped.num_models, timings, extra)
    (cfg.output_dir / "process_data_report.json").write_text(json.dumps(report, indent=2), encoding="utf8")
    export.print_report(report)

    registered = set(n for n in names if n not in report["unregistered_images"])
    if len(registered) < cfg.min_registered_fraction * len(names):
        why = sfm.explain_failure(sfm.database_stats(db), registered, names, model, circle_found)
        split = f" (the images fell into {mapped.num_models} unconnected models)" if mapped.num_models > 1 else ""
        raise ProcessDataError(f"too few images registered: {len(registered)} of {len(names)}{split}.\n{why}\n"
                               f"The partial model is in {sparse0}; no transforms.json was written.", keeps_output=True)
    if report["mean_reprojection_error_px"] > cfg.max_reprojection_error:
        raise ProcessDataError(
            f"mean reprojection error {report['mean_reprojection_error_px']:.2f} px > {cfg.max_reprojection_error} "
            f"px: the camera model does not fit the lens.\n{sfm.model_hint(model, circle_found)}\n"
            f"The model is in {sparse0}; no transforms.json was written (--max-reprojection-error to accept it).",
            keeps_output=True)
    for cid, cam in report["cameras"].items():  # type: ignore[union-attr]
        names_p = [n.strip() for n in cam["params_info"].split(",")]
        if not fixed and "fx" in names_p and "fy" in names_p:  # a user calibration may have fx != fy
            fx, fy = cam["params"][names_p.index("fx")], cam["params"][names_p.index("fy")]
            if abs(fx / fy - 1) > cfg.max_focal_asymmetry:
                # Square pixels give fx ~= fy; a model that cannot describe the lens bends them apart while
                # keeping a low reprojection error on the features it kept.
                raise ProcessDataError(
                    f"camera {cid}: fx = {fx:.1f} and fy = {fy:.1f} px differ by {100 * abs(fx / fy - 1):.0f} %: "
                    f"the camera model does not fit the lens.\n{sfm.model_hint(model, circle_found)}\n"
                    f"The model is in {sparse0}; no transforms.json was written (--max-focal-asymmetry to accept).",
                    keeps_output=True)
    if registered != set(names):
        CONSOLE.print(f"[yellow]{len(names) - len(registered)} image(s) were not registered and are left out of "
                      "transforms.json:\n" + sfm.explain_failure(sfm.database_stats(db), registered, names, model,
                                                                  circle_found))
    masks = {}
    for group, setup in zip(groups, setups):
        for im in recon.images.values():
            if im.name in group.image_names:
                masks[int(im.camera_id)] = setup.mask_file
    export.write_transforms(cfg.output_dir, recon, masks)
    if cfg.rolling_shutter != "global":
        fps = cfg.frame_rate or readout.video_fps(cfg.data)
        count = readout.add_readout(cfg.output_dir / "transforms.json", cfg.rolling_shutter, cfg.readout_time, fps)
        CONSOLE.print(f"Rolling shutter ({cfg.rolling_shutter}, {cfg.readout_time} s): the readout of {count} frames "
                      "estimated from their neighbours' poses")
    CONSOLE.print(f"[bold green]Dataset written to {cfg.output_dir}[/]: ns-train geer --data {cfg.output_dir}")
    return report


def entrypoint() -> None:
    """Console script ``geer-process-data``."""
    tyro.extras.set_accent_color("bright_yellow")
    cfg = tyro.cli(tyro.conf.FlagConversionOff[ProcessDataConfig])
    try:
        run(cfg)
    except ProcessDataError as e:
        CONSOLE.print(f"[bold red]geer-process-data failed:[/] {e}")
        raise SystemExit(1) from None


if __name__ == "__main__":
    entrypoint()
