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
from nerfstudio.utils.rich_utils import CONSOLE

from geer_ns.data.dataset_checks import DatasetError
from geer_ns.data.rolling_shutter import readout_poses, sequences
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
    """Rewrite `transforms` (geer-process-data's) with every frame's readout; returns the frames changed. The
    neighbours of a frame are taken among its own camera's (a rig: the images' sub-folder)."""
    meta = json.loads(transforms.read_text())
    frames = meta["frames"]
    if readout_time >= 1.0 / fps:
        raise ProcessDataError(f"--readout-time {readout_time} s is not shorter than a frame interval "
                               f"({1.0 / fps:.4f} s at {fps:g} frames per second): a readout fits within its frame")
    names = [f["file_path"] for f in frames]
    try:
        runs = sequences(names, [str(Path(n).parent) for n in names], fps, f"{transforms}")
    except DatasetError as e:
        raise ProcessDataError(f"--rolling-shutter: {e}") from None
    for order, times in runs:
        if len(times) > 1 and float(np.median(np.diff(times))) > 20 * readout_time:
            CONSOLE.print(f"[yellow]--rolling-shutter: neighbouring frames are {float(np.median(np.diff(times))):.2f} "
                          "s apart: the motion during a readout is their average motion (more frames: "
                          "--num-frames-target)")
        c2w = np.array([frames[i]["transform_matrix"] for i in order], dtype=np.float64)
        start, end = readout_poses(c2w, times, readout_time)
        for j, i in enumerate(order):
            frames[i]["transform_matrix"] = start[j].tolist()
            frames[i]["transform_matrix_end"] = end[j].tolist()
    meta["rolling_shutter"] = {"readout": readout, "readout_time": readout_time}
    transforms.write_text(json.dumps(meta, indent=2), encoding="utf8")
    return len(frames)
