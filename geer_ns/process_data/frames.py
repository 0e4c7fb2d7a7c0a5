"""Input frames: a folder of images (checked, copied) or a video (sampled, blurry frames skipped).

Everything ends up as ``<output>/images/<name>``; the SfM and the dataset refer to those copies only, so
the dataset is self-contained. A camera group is the set of images that share one camera: the whole input
by default, one group per sub-folder for rigs (``camera_per_folder``).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np
from nerfstudio.utils.rich_utils import CONSOLE
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"}
VIDEO_SUFFIXES = {".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm", ".mts", ".wmv", ".mpg", ".mpeg", ".insv", ".360"}


class ProcessDataError(RuntimeError):
    """A failure of geer-process-data with its explanation (what went wrong, what to try)."""


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


def copy_images(src: Path, images_dir: Path, camera_per_folder: bool) -> List[CameraGroup]:
    """Check that every image under ``src`` decodes (naming the first that does not) and copy it."""
    files = list_images(src)
    if not files:
        raise ProcessDataError(
            f"{src}: no images found (looked for {', '.join(sorted(IMAGE_SUFFIXES))} in it and its sub-folders)"
        )
    sizes: Dict[str, Tuple[int, int]] = {}
    with progress() as bar:
        task = bar.add_task("Checking and copying images", total=len(files))
        for path in files:
            rel = path.relative_to(src).as_posix()
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if image is None or image.size == 0:
                raise ProcessDataError(f"{path}: corrupt or unreadable image (OpenCV cannot decode it); remove it")
            sizes[rel] = (int(image.shape[1]), int(image.shape[0]))
            dst = images_dir / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, dst)
            bar.advance(task)
    names = list(sizes)
    if camera_per_folder:
        folders: Dict[str, List[str]] = {}
        for n in names:
            folders.setdefault(str(Path(n).parent.as_posix()) if "/" in n else "", []).append(n)
        if len(folders) == 1:
            CONSOLE.print("[yellow]--camera-per-folder: all images are in one folder, so they share one camera")
    else:
        folders = {"": names}
    return [_group(src, name, members, sizes) for name, members in sorted(folders.items())]


def _group(src: Path, name: str, members: Sequence[str], sizes: Dict[str, Tuple[int, int]]) -> CameraGroup:
    first = members[0]
    for n in members:
        if sizes[n] != sizes[first]:
            where = f"folder '{name}'" if name else "the input (one shared camera)"
            raise ProcessDataError(
                f"{src / n}: size {sizes[n][0]}x{sizes[n][1]} differs from {src / first} "
                f"({sizes[first][0]}x{sizes[first][1]}); images of one camera ({where}) must share a size"
                + ("" if name else " — put each camera's images in its own sub-folder and use --camera-per-folder")
            )
    return CameraGroup(name, tuple(members), *sizes[first])


def sharpness(image: np.ndarray) -> float:
    """Variance of the Laplacian over the central half of the image (inside any fisheye circle)."""
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    h, w = gray.shape
    centre = gray[h // 4 : h - h // 4, w // 4 : w - w // 4]
    return float(cv2.Laplacian(centre, cv2.CV_64F).var())


def blurry(scores: Sequence[float], ratio: float, window: int = 5) -> np.ndarray:
    """Frames whose sharpness is below ``ratio`` times the median of their neighbours (+-window frames):
    relative to the neighbours, so that a scene with little texture is not mistaken for blur."""
    s = np.asarray(scores, dtype=np.float64)
    out = np.zeros(len(s), dtype=bool)
    for i in range(len(s)):
        lo, hi = max(0, i - window), min(len(s), i + window + 1)
        neighbours = np.concatenate([s[lo:i], s[i + 1 : hi]])
        out[i] = len(neighbours) > 0 and s[i] < ratio * float(np.median(neighbours))
    return out


def sample_video(
    video: Path, images_dir: Path, num_frames: int, candidates_per_frame: int = 5, blur_ratio: float = 0.5
) -> Tuple[CameraGroup, Dict[str, int]]:
    """Write about ``num_frames`` frames of ``video`` as ``images/frame_XXXXX.png``.

    The video is cut into ``num_frames`` equal windows; the sharpest of up to ``candidates_per_frame`` frames of
    each window is kept, then kept frames far blurrier than their neighbours are dropped. Returns the camera
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
        CONSOLE.print(f"Skipped {int(drop.sum())} blurry frame(s) (sharpness < {blur_ratio} x their neighbours')")
    h, w = kept[0][2].shape[:2]
    stats = {"video_frames": total, "frames_written": len(names), "frames_skipped_blurry": int(drop.sum())}
    return CameraGroup("", tuple(names), int(w), int(h)), stats
