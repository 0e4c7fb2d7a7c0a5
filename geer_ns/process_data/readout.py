"""``geer-process-data --rolling-shutter READOUT --readout-time T``: each frame's readout from its neighbours.

Each registered frame's pose is taken as the camera's at mid-readout, its motion during the readout estimated from
its neighbours (geer_ns/data/rolling_shutter.py readout_poses), and the frame written with the poses at the start
and end of its readout (that module's fields). Capture times: a video's frame index over its frame rate; an image
folder's file-name order over --frame-rate.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np

from geer_ns.cameras.shutter import READOUTS
from geer_ns.data.rolling_shutter import capture_times, readout_poses
from geer_ns.process_data.frames import ProcessDataError


def check_options(readout: str, readout_time: Optional[float], frame_rate: Optional[float], video: bool) -> None:
    """ProcessDataError naming the option unless the rolling-shutter options are complete and sane."""
    if readout == "global":
        return
    if readout not in READOUTS:
        raise ProcessDataError(f"--rolling-shutter: expected global or one of {', '.join(READOUTS)}, got {readout!r}")
    if readout_time is None or not readout_time > 0:
        raise ProcessDataError(f"--rolling-shutter {readout} needs --readout-time (seconds from the first row read to "
                               f"the last, > 0; e.g. 0.03 for many action cameras), got {readout_time}")
    if not video and (frame_rate is None or not frame_rate > 0):
        raise ProcessDataError(f"--rolling-shutter {readout} with a folder of images needs --frame-rate (frames per "
                               "second of the capture, the images in file-name order)")


def video_fps(video: Path) -> float:
    import cv2

    fps = cv2.VideoCapture(str(video)).get(cv2.CAP_PROP_FPS)
    if not fps or not np.isfinite(fps) or fps <= 0:
        raise ProcessDataError(f"{video}: the video does not store its frame rate; pass --frame-rate")
    return float(fps)


def add_readout(transforms: Path, readout: str, readout_time: float, fps: float) -> int:
    """Rewrite `transforms` (geer-process-data's) with every frame's readout; returns the frames changed."""
    meta = json.loads(transforms.read_text())
    frames = meta["frames"]
    if len(frames) < 2:
        raise ProcessDataError(f"--rolling-shutter: {len(frames)} registered frame(s); the motion during a readout "
                               "is estimated from neighbouring frames, so at least 2 are needed")
    times_of = capture_times([f["file_path"] for f in frames], fps)
    order = sorted(range(len(frames)), key=lambda i: times_of[frames[i]["file_path"]])
    times = np.array([times_of[frames[i]["file_path"]] for i in order])
    gap = float(np.min(np.diff(times)))
    if gap <= 0:
        raise ProcessDataError(f"--rolling-shutter: two frames share a capture time in {transforms}")
    if readout_time >= 1.0 / fps:
        raise ProcessDataError(f"--readout-time {readout_time} s is not shorter than a frame interval "
                               f"({1.0 / fps:.4f} s at {fps:g} frames per second): a readout fits within its frame")
    c2w = np.array([frames[i]["transform_matrix"] for i in order], dtype=np.float64)
    start, end = readout_poses(c2w, times, readout_time)
    for j, i in enumerate(order):
        frames[i]["transform_matrix"] = start[j].tolist()
        frames[i]["transform_matrix_end"] = end[j].tolist()
    meta["rolling_shutter"] = {"readout": readout, "readout_time": readout_time}
    transforms.write_text(json.dumps(meta, indent=2), encoding="utf8")
    return len(frames)
