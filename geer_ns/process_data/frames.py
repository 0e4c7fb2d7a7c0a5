"""Input frames: a folder of images (every image checked before anything is written, then copied) or a video
(sampled, blurry frames skipped).

Everything ends up as ``<output>/images/<name>``; the SfM and the dataset refer to those copies only, so
the dataset is self-contained. A camera group is the set of images that share one camera: the whole input
by default, one group per sub-folder for rigs (``camera_per_folder``).
"""

from __future__ import annotations

import shutil
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np
from nerfstudio.utils.rich_utils import CONSOLE
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from geer_ns.data.dataset_checks import missing_end_marker

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"}
VIDEO_SUFFIXES = {".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm", ".mts", ".wmv", ".mpg", ".mpeg", ".insv", ".360"}


class ProcessDataError(RuntimeError):
    """A failure of geer-process-data with its explanation (what went wrong, what to try). `keeps_output`:
    the explanation points at what the run wrote (a model to inspect), so it is left for the re-run to replace."""

    def __init__(self, message: str, keeps_output: bool = False) -> None:
        super().__init__(message)
        self.keeps_output = keeps_output


def progress() -> Progress:
    """The progress bar every long stage uses."""
    return Progress(
        TextColumn("[bold blue]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=CONSOLE,
        transient=False,
    )


@dataclass(frozen=True)
class CameraGroup:
    """Images (names relative to ``images/``) that share one camera, and their size."""

    name: str  # "" for the one shared camera; the sub-folder for per-folder cameras
    image_names: Tuple[str, ...]
    width: int
    height: int


def is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def list_images(folder: Path) -> List[Path]:
    """Image files under ``folder`` (recursively), sorted by relative path."""
    files = [p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda p: p.relative_to(folder).as_posix())


@dataclass(frozen=True)
class CheckedImages:
    """The input images that can be used, by camera, and one line for each that cannot."""

    groups: List[CameraGroup]
    bad: List[str]  # "<file>: <what is wrong>; <what to do>"


def image_problem(path: Path) -> Tuple[Optional[str], Optional[Tuple[int, int]]]:
    """(what is wrong with an image file and what to do, or None; its (width, height)).

    Every byte is decoded: OpenCV returns the rows it could read from a file cut short (libjpeg only prints
    "Premature end of JPEG file", naming no file), PIL raises. JPEG and PNG must also end with their end
    marker, the check ns-train makes at start-up (data/dataset_checks.py), so what passes here trains.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            size, fmt = (int(im.size[0]), int(im.size[1])), im.format
            if fmt == "JPEG":  # decode at 1/8 scale: every entropy-coded byte is still read, 4-5x faster
                im.draft(im.mode, (max(1, size[0] // 8), max(1, size[1] // 8)))
            im.load()
    except UnidentifiedImageError:
        return "not an image (unknown format); remove it", None
    except (OSError, SyntaxError, ValueError) as e:  # PIL: OSError "image file is truncated", SyntaxError headers
        what = "cut short (truncated)" if "truncated" in str(e) else f"cannot be decoded ({e})"
        return f"{what}; copy it again from the camera or remove it", None
    if missing_end_marker(path, fmt):
        return f"cut short ({fmt} end marker missing); copy it again from the camera or remove it", None
    return None, size


def check_images(src: Path, camera_per_folder: bool) -> CheckedImages:
    """Decode every image under ``src`` completely and group the good ones by camera (the whole input, or one
    camera per sub-folder); an image whose size differs from its camera's (the most common) is bad too."""
    from PIL import Image

    files = list_images(src)
    if not files:
        raise ProcessDataError(
            f"{src}: no images found (looked for {', '.join(sorted(IMAGE_SUFFIXES))} in it and its sub-folders)"
        )
    sizes: Dict[str, Tuple[int, int]] = {}
    bad: List[str] = []
    limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None  # a 100 MP panorama is no decompression bomb
    try:
        with progress() as bar:
            task = bar.add_task("Checking images", total=len(files))
            for path in files:
                problem, size = image_problem(path)
                if problem is None:
                    sizes[path.relative_to(src).as_posix()] = size
                else:
                    bad.append(f"{path}: {problem}")
                bar.advance(task)
    finally:
        Image.MAX_IMAGE_PIXELS = limit
    folders: Dict[str, List[str]] = {}
    for n in sizes:
        folders.setdefault(str(Path(n).parent.as_posix()) if camera_per_folder and "/" in n else "", []).append(n)
    if camera_per_folder and len(folders) == 1:
        CONSOLE.print("[yellow]--camera-per-folder: all images are in one folder, so they share one camera")
    groups = []
    for name, members in sorted(folders.items()):
        counts = Counter(sizes[n] for n in members)
        (width, height), count = counts.most_common(1)[0]
        where = f"folder '{name}'" if name else "the input (one shared camera)"
        for n in members:
            if sizes[n] != (width, height):
                bad.append(f"{src / n}: {sizes[n][0]}x{sizes[n][1]} px, but {count} image(s) of {where} are "
                           f"{width}x{height}; one camera, one size: resize or remove it"
                           + ("" if name else ", or put each camera's images in its own sub-folder and use "
                              "--camera-per-folder"))
        kept = tuple(n for n in members if sizes[n] == (width, height))
        groups.append(CameraGroup(name, kept, width, height))
    return CheckedImages(groups, sorted(bad))


def copy_images(src: Path, images_dir: Path, groups: Sequence[CameraGroup]) -> None:
    """Copy the checked images of ``groups`` from ``src`` to ``images_dir`` (same relative paths)."""
    names = [n for g in groups for n in g.image_names]
    with progress() as bar:
        task = bar.add_task("Copying images", total=len(names))
        for rel in names:
            dst = images_dir / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / rel, dst)
            bar.advance(task)


def sharpness(image: np.ndarray) -> float:
    """Variance of the Laplacian over the central half of the image (inside any fisheye circle)."""
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    h, w = gray.shape
    center = gray[h // 4 : h - h // 4, w // 4 : w - w // 4]
    return float(cv2.Laplacian(center, cv2.CV_64F).var())


def blurry(scores: Sequence[float], ratio: float, window: int = 5) -> np.ndarray:
    """Frames whose sharpness is below ``ratio`` times the median of their neighbors (+-window frames):
    relative to the neighbors, so that a scene with little texture is not mistaken for blur."""
    s = np.asarray(scores, dtype=np.float64)
    out = np.zeros(len(s), dtype=bool)
    for i in range(len(s)):
        lo, hi = max(0, i - window), min(len(s), i + window + 1)
        neighbors = np.concatenate([s[lo:i], s[i + 1 : hi]])
        out[i] = len(neighbors) > 0 and s[i] < ratio * float(np.median(neighbors))
    return out


def sample_video(
    video: Path, images_dir: Path, num_frames: int, candidates_per_frame: int = 5, blur_ratio: float = 0.5
) -> Tuple[CameraGroup, Dict[str, int]]:
    """Write about ``num_frames`` frames of ``video`` as ``images/frame_XXXXX.png``.

    The video is cut into ``num_frames`` equal windows; the sharpest of up to ``candidates_per_frame`` frames of
    each window is kept, then kept frames far blurrier than their neighbors are dropped. Returns the camera
    group and statistics (frames in the video, written, skipped as blurry).
    """
    if num_frames < 2:
        raise ProcessDataError(f"--num-frames-target must be at least 2, got {num_frames}")
    cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        raise ProcessDataError(f"{video}: OpenCV cannot open this video (unknown container or codec)")
    total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    if total <= 0:  # some containers do not store a frame count: count by decoding headers
        total = 0
        while cap.grab():
            total += 1
        cap.release()
        cap = cv2.VideoCapture(str(video))
    if total == 0:
        raise ProcessDataError(f"{video}: the video has no frames that OpenCV can decode")
    n = min(num_frames, total)
    edges = np.linspace(0, total, n + 1).round().astype(int)
    window_of = np.searchsorted(edges, np.arange(total), side="right") - 1
    candidates = set()
    for w in range(n):
        k = min(candidates_per_frame, edges[w + 1] - edges[w])
        candidates.update(np.linspace(edges[w], edges[w + 1] - 1, k).round().astype(int).tolist())
    best: List[Optional[Tuple[float, int, np.ndarray]]] = [None] * n
    decoded = 0
    with progress() as bar:
        task = bar.add_task(f"Sampling {n} frames from {video.name}", total=total)
        for i in range(total):
            if not cap.grab():
                CONSOLE.print(f"[yellow]{video}: decoding stopped at frame {i} of {total} (truncated file?)")
                break
            if i in candidates:
                ok, frame = cap.retrieve()
                if ok and frame is not None:
                    decoded += 1
                    score = sharpness(frame)
                    w = int(window_of[i])
                    if best[w] is None or score > best[w][0]:
                        best[w] = (score, i, frame)
            bar.advance(task)
    cap.release()
    kept = [b for b in best if b is not None]
    if len(kept) < 2:
        raise ProcessDataError(f"{video}: fewer than 2 frames could be decoded ({decoded} of {total})")
    drop = blurry([b[0] for b in kept], blur_ratio)
    images_dir.mkdir(parents=True, exist_ok=True)
    names = []
    for (score, index, frame), skip in zip(kept, drop):
        if skip:
            continue
        name = f"frame_{index:05d}.png"
        if not cv2.imwrite(str(images_dir / name), frame):
            raise ProcessDataError(f"cannot write {images_dir / name}")
        names.append(name)
    if drop.any():
        CONSOLE.print(f"Skipped {int(drop.sum())} blurry frame(s) (sharpness < {blur_ratio} x their neighbors')")
    h, w = kept[0][2].shape[:2]
    stats = {"video_frames": total, "frames_written": len(names), "frames_skipped_blurry": int(drop.sum())}
    return CameraGroup("", tuple(names), int(w), int(h)), stats
