"""Structure from motion with pycolmap: SIFT extraction, matching, incremental mapping with bundle adjustment.

COLMAP's own stages run in-process (no binary). Feature extraction and matching run in chunks so that each
stage shows a progress bar; the image pairs are generated here (sequential with quadratic overlap for
ordered frames, keyframe loop closure, or exhaustive) and matched and verified by pycolmap.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Set, Tuple

import pycolmap

from geer_ns.process_data.camera import CameraSetup
from geer_ns.process_data.frames import CameraGroup, ProcessDataError, progress

# Below this many keypoints an image can hardly be registered (blurred, untextured, over-exposed).
FEW_KEYPOINTS = 100
_CHUNK_IMAGES = 16
_CHUNK_PAIRS = 64


def _chunks(items: Sequence, size: int) -> Iterator[Sequence]:
    for i in range(0, len(items), size):
        yield items[i : i + size]


def extract_features(db: Path, images_dir: Path, groups: Sequence[CameraGroup], setups: Sequence[CameraSetup],
                     num_threads: int, max_image_size: int) -> None:
    """SIFT keypoints of every image, one COLMAP camera per group, keypoints only inside the feature mask."""
    eo = pycolmap.FeatureExtractionOptions()
    eo.num_threads = num_threads
    eo.max_image_size = max_image_size
    total = sum(len(g.image_names) for g in groups)
    with progress() as bar:
        task = bar.add_task("Extracting SIFT features", total=total)
        for group, setup in zip(groups, setups):
            camera_id = -1
            for chunk in _chunks(list(group.image_names), _CHUNK_IMAGES):
                ro = pycolmap.ImageReaderOptions()
                ro.camera_model = setup.model
                if setup.params is not None:
                    ro.camera_params = ",".join(repr(float(p)) for p in setup.params)
                if setup.feature_mask_file is not None:
                    ro.camera_mask_path = str(setup.feature_mask_file)
                ro.existing_camera_id = camera_id  # later chunks of a group reuse its camera
                pycolmap.extract_features(db, images_dir, image_names=list(chunk),
                                          camera_mode=pycolmap.CameraMode.SINGLE, reader_options=ro,
                                          extraction_options=eo)
                if camera_id < 0:
                    with pycolmap.Database.open(str(db)) as d:
                        camera_id = int(d.read_image_with_name(chunk[0]).camera_id)
                bar.advance(task, len(chunk))
    with pycolmap.Database.open(str(db)) as d:
        missing = [n for g in groups for n in g.image_names if not d.exists_image(n)]
    if missing:
        raise ProcessDataError(f"pycolmap could not read {len(missing)} image(s), e.g. {images_dir / missing[0]}")


def sequential_pairs(names: Sequence[str], overlap: int) -> Set[Tuple[str, str]]:
    """Each frame with its next ``overlap`` frames and the frames 2^k further on (COLMAP's quadratic overlap)."""
    pairs = set()
    n = len(names)
    for i in range(n):
        steps = set(range(1, overlap + 1)) | {2**k for k in range(overlap.bit_length(), n.bit_length() + 1)}
        pairs.update((names[i], names[i + s]) for s in steps if i + s < n)
    return pairs


def loop_pairs(names: Sequence[str], interval: int) -> Set[Tuple[str, str]]:
    """Loop closure without a vocabulary tree: every ``interval``-th frame (a keyframe) with every other."""
    keys = list(names[::interval]) if interval > 0 else []
    return {(a, b) for i, a in enumerate(keys) for b in keys[i + 1 :]}


def exhaustive_pairs(names: Sequence[str]) -> Set[Tuple[str, str]]:
    return {(a, b) for i, a in enumerate(names) for b in names[i + 1 :]}


def match(db: Path, work_dir: Path, pairs: Set[Tuple[str, str]], num_threads: int,
          vocab_tree: Optional[Path] = None, guided: bool = False) -> None:
    """Match and geometrically verify ``pairs`` (plus vocabulary-tree neighbors when a tree is given)."""
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = num_threads
    mo.guided_matching = guided
    ordered = sorted(pairs)
    pair_file = work_dir / "pairs.txt"
    with progress() as bar:
        task = bar.add_task("Matching image pairs", total=len(ordered))
        for chunk in _chunks(ordered, _CHUNK_PAIRS):
            pair_file.write_text("".join(f"{a} {b}\n" for a, b in chunk), encoding="utf8")
            po = pycolmap.ImportedPairingOptions()
            po.match_list_path = str(pair_file)
            pycolmap.match_image_pairs(db, matching_options=mo, pairing_options=po)
            bar.advance(task, len(chunk))
        if vocab_tree is not None:
            task = bar.add_task("Loop closure (vocabulary tree)", total=None)
            vo = pycolmap.VocabTreePairingOptions()
            vo.vocab_tree_path = str(vocab_tree)
            vo.num_threads = num_threads
            pycolmap.match_vocabtree(db, matching_options=mo, pairing_options=vo)
            bar.update(task, total=1, completed=1)


@dataclass
class MappingResult:
    reconstruction: "pycolmap.Reconstruction"
    num_models: int


def incremental_mapping(db: Path, images_dir: Path, work_dir: Path, num_images: int, fixed_intrinsics: bool,
                        refine_principal_point: bool, num_threads: int, seed: int = 0) -> Optional[MappingResult]:
    """COLMAP's incremental mapper (local and global bundle adjustment refine focal length and distortion
    unless the intrinsics are fixed). Returns the largest model, or None when no model was made."""
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads
    opts.random_seed = seed
    opts.min_model_size = min(opts.min_model_size, max(3, num_images // 2))
    opts.ba_refine_principal_point = refine_principal_point and not fixed_intrinsics
    if fixed_intrinsics:
        opts.ba_refine_focal_length = False
        opts.ba_refine_extra_params = False
        opts.mapper.abs_pose_refine_focal_length = False
        opts.mapper.abs_pose_refine_extra_params = False
    out = work_dir / "models"  # not colmap/sparse/0: nerfstudio-data treats that as a legacy COLMAP export
    out.mkdir(parents=True, exist_ok=True)
    with progress() as bar:
        task = bar.add_task("Registering images (incremental mapping)", total=num_images)
        models = pycolmap.incremental_mapping(
            db, images_dir, out, opts,
            initial_image_pair_callback=lambda: bar.advance(task, 2),
            next_image_callback=lambda: bar.advance(task, 1),
        )
        if models:
            best = max(models.values(), key=lambda r: r.num_reg_images())
            bar.update(task, completed=best.num_reg_images())
    if not models:
        return None
    return MappingResult(best, len(models))


def database_stats(db: Path) -> Dict[str, object]:
    """Keypoints per image and verified pairs, to explain a failed or partial reconstruction."""
    with pycolmap.Database.open(str(db)) as d:
        images = {im.image_id: im.name for im in d.read_all_images()}
        keypoints = {name: int(d.num_keypoints_for_image(iid)) for iid, name in images.items()}
        pair_ids, inliers = d.read_two_view_geometry_num_inliers()
    connected: Dict[str, int] = {name: 0 for name in images.values()}
    verified = 0
    for pid, n in zip(pair_ids, inliers):
        if n <= 0:
            continue
        verified += 1
        a, b = pycolmap.pair_id_to_image_pair(pid)
        connected[images[a]] += 1
        connected[images[b]] += 1
    return {"keypoints": keypoints, "verified_pairs": verified, "pairs_per_image": connected}


def explain_failure(stats: Dict[str, object], registered: Set[str], names: Sequence[str], model: str,
                    circle_found: bool) -> str:
    """Why images did not register, and what to try."""
    keypoints: Dict[str, int] = stats["keypoints"]  # type: ignore[assignment]
    per_image: Dict[str, int] = stats["pairs_per_image"]  # type: ignore[assignment]
    lines: List[str] = []
    if stats["verified_pairs"] == 0:
        lines.append("no overlap: no two images share enough geometrically consistent feature matches. Capture "
                     "with more overlap (each part of the scene in several views), move slower, avoid "
                     "untextured views.")
    few = [n for n in names if n not in registered and keypoints.get(n, 0) < FEW_KEYPOINTS]
    if few:
        lines.append(f"{len(few)} image(s) have fewer than {FEW_KEYPOINTS} SIFT keypoints (blurred, dark or "
                     f"untextured), e.g. {', '.join(few[:5])}")
    lonely = [n for n in names if n not in registered and per_image.get(n, 0) == 0 and n not in few]
    if lonely:
        lines.append(f"{len(lonely)} image(s) match no other image, e.g. {', '.join(lonely[:5])}")
    if registered:
        lines.append("more overlap between views, --guided-matching True (more matches per pair) or, for video, "
                     "a larger --num-frames-target often registers the rest")
    lines.append(model_hint(model, circle_found))
    return "\n".join(lines)


def model_hint(model: str, circle_found: bool) -> str:
    if model == "OPENCV_FISHEYE":
        return ("camera model: OPENCV_FISHEYE assumes a fisheye lens; for a narrow (rectilinear) lens try "
                "--camera-model OPENCV, or set --fov-deg to the lens's field of view")
    extra = " (the images have a fisheye image circle)" if circle_found else ""
    return f"camera model: {model} is a pinhole-type model; for a fisheye lens{extra} use --camera-model OPENCV_FISHEYE"
