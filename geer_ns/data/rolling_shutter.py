"""Rolling-shutter fields of a nerfstudio ``transforms.json``: each image's readout and its camera's motion.

    "rolling_shutter": {"readout": "top-to-bottom"}     top level (every frame) or a frame's own (it wins);
                                                         readout: top-to-bottom, bottom-to-top, left-to-right,
                                                         right-to-left, or "global" (a frame without motion)
    "transform_matrix_end": [[...4x4...]]                per rolling-shutter frame: the camera-to-world at the end
                                                         of the readout; "transform_matrix" is the start's
    or, instead of the end pose, the camera's velocities at the start and the readout's duration:
    "angular_velocity": [wx, wy, wz]                     rad/s, about the axes of the frame's camera
    "linear_velocity": [vx, vy, vz]                      the camera centre's, in the file's units per second
    "rolling_shutter": {"readout": ..., "readout_time": T}   seconds from the first row to the last

Both poses are in the file's convention (nerfstudio's OpenGL camera-to-world). What is kept is the motion over the
readout in the start camera's frame, end = start @ [R | t], with t in the parsed scene's units; so orienting,
centring and scaling the scene, and any pose adjustment of the start, carry the end along. ``Cameras.metadata``
gets ``geer_readout`` (int64 [N, 1], index into cameras/shutter.READOUTS, -1 global) and ``geer_readout_motion``
(float32 [N, 12]: R row-major, then t). For structure-from-motion poses (one per image: geer-process-data, the
geer-colmap parser) the readouts are estimated from neighbouring frames (readout_poses). Conventions:
docs/rolling_shutter.md.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from geer_ns.cameras.shutter import READOUTS, so3_exp
from geer_ns.data.dataset_checks import DatasetError

_VELOCITY_KEYS = ("angular_velocity", "linear_velocity")
READOUT_KEY = "geer_readout"
MOTION_KEY = "geer_readout_motion"
GLOBAL = -1


def _spec(meta: dict, frame: dict) -> Optional[dict]:
    """The frame's rolling_shutter object: its own fields over the top level's (a readout_time given once)."""
    top, own = meta.get("rolling_shutter"), frame.get("rolling_shutter")
    if isinstance(top, dict) and isinstance(own, dict):
        return {**top, **own}
    return own if own is not None else top


def _readout_of(meta: dict, frame: dict, where: str) -> int:
    spec = _spec(meta, frame)
    if spec is None:
        return GLOBAL
    if not isinstance(spec, dict) or "readout" not in spec:
        raise DatasetError(f"geer: {where}: `rolling_shutter` must be an object with a `readout` "
                           f"({', '.join(READOUTS)} or global), got {spec!r}")
    readout = spec["readout"]
    if readout == "global":
        return GLOBAL
    if readout not in READOUTS:
        raise DatasetError(f"geer: {where}: `rolling_shutter.readout` must be one of {', '.join(READOUTS)} or "
                           f"global, got {readout!r}")
    return READOUTS.index(readout)


def _pose(frame: dict, key: str, where: str) -> torch.Tensor:
    try:
        pose = torch.tensor(frame[key], dtype=torch.float64)
    except (TypeError, ValueError) as e:
        raise DatasetError(f"geer: {where}: `{key}` must be a 4x4 matrix of numbers ({e})") from None
    if tuple(pose.shape) not in ((4, 4), (3, 4)) or not torch.isfinite(pose).all():
        raise DatasetError(f"geer: {where}: `{key}` must be a finite 4x4 matrix, got shape {tuple(pose.shape)}")
    return pose[:3]


def _vector(frame: dict, key: str, where: str) -> torch.Tensor:
    try:
        v = torch.tensor(frame[key], dtype=torch.float64)
    except (TypeError, ValueError) as e:
        raise DatasetError(f"geer: {where}: `{key}` must be 3 numbers ({e})") from None
    if tuple(v.shape) != (3,) or not torch.isfinite(v).all():
        raise DatasetError(f"geer: {where}: `{key}` must be 3 finite numbers, got {frame[key]!r}")
    return v


def _end_from_velocities(meta: dict, frame: dict, where: str) -> torch.Tensor:
    """[3, 4] end pose of a frame given by its start pose, velocities and the readout time."""
    missing = [k for k in _VELOCITY_KEYS if k not in frame]
    if missing:
        raise DatasetError(f"geer: {where}: a rolling-shutter frame needs `transform_matrix_end` or both "
                           f"{' and '.join(f'`{k}`' for k in _VELOCITY_KEYS)} (missing {', '.join(missing)})")
    duration = (_spec(meta, frame) or {}).get("readout_time")
    if not isinstance(duration, (int, float)) or not (0.0 < float(duration) < float("inf")):
        raise DatasetError(f"geer: {where}: velocities need `rolling_shutter.readout_time` (seconds > 0), "
                           f"got {duration!r}")
    start = _pose(frame, "transform_matrix", where)
    omega = _vector(frame, "angular_velocity", where) * float(duration)
    turn = so3_exp(omega)
    centre = start[:, 3] + _vector(frame, "linear_velocity", where) * float(duration)
    return torch.cat([start[:, :3] @ turn, centre[:, None]], dim=1)


def readout_metadata(meta: dict, frames: List[dict], path: Path, translation_scale: float) -> Optional[Dict]:
    """Cameras.metadata entries for the frames (in the parsed order), or None when no frame has a rolling shutter.
    translation_scale: the factor nerfstudio scaled the file's positions by. DatasetError naming the file, frame
    and field for a readout without an end pose, an end pose without a readout, or a malformed value."""
    readouts, motions = [], []
    for frame in frames:
        where = f"{path}: frame {frame.get('file_path')!r}"
        readout = _readout_of(meta, frame, where)
        has_end = "transform_matrix_end" in frame
        given = [k for k in ("transform_matrix_end", *_VELOCITY_KEYS) if k in frame]
        if readout == GLOBAL and given:
            raise DatasetError(f"geer: {where}: `{given[0]}` is given but the frame has no "
                               "`rolling_shutter.readout`; add one (e.g. top-to-bottom) or remove the motion")
        if has_end and len(given) > 1:
            raise DatasetError(f"geer: {where}: give `transform_matrix_end` or the velocities, not both")
        motion = torch.eye(3, 4, dtype=torch.float64).reshape(12)
        if readout != GLOBAL:
            start = _pose(frame, "transform_matrix", where)
            end = (_pose(frame, "transform_matrix_end", where) if has_end
                   else _end_from_velocities(meta, frame, where))
            motion = motion_between(start, end, translation_scale)
        readouts.append(readout)
        motions.append(motion)
    if all(r == GLOBAL for r in readouts):
        return None
    return {READOUT_KEY: torch.tensor(readouts, dtype=torch.int64)[:, None],
            MOTION_KEY: torch.stack(motions).float()}


def motion_between(start: torch.Tensor, end: torch.Tensor, translation_scale: float = 1.0) -> torch.Tensor:
    """The motion [12] (R row-major, then t) from camera-to-world start to end [3, 4]: end = start @ [R | t], t
    scaled by translation_scale; end_pose's inverse."""
    r0 = start[:, :3]
    return torch.cat([r0.T @ end[:, :3], (r0.T @ (end[:, 3:] - start[:, 3:])) * translation_scale], 1).reshape(12)


def end_pose(start: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """[3, 4] camera-to-world at the end of the readout from the start's [3, 4] and the motion [12]."""
    m = motion.to(start).reshape(3, 4)
    return torch.cat([start[:, :3] @ m[:, :3], (start[:, :3] @ m[:, 3:] + start[:, 3:])], dim=1)


# ------------------------------------------------------------------ readouts from structure from motion
# Structure from motion gives one pose per image, as if the whole frame were taken at once; for a rolling-shutter
# capture that pose is close to the camera's at mid-readout. The motion during a readout is estimated from the
# frames before and after it in capture order: the angular velocity (about the camera's own axes) from the
# geodesic between their rotations, the linear velocity from their centres, over their capture times (central
# differences, one-sided at the ends; exact for a camera turning and moving at constant rates).
def capture_times(names: List[str], fps: float) -> Dict[str, float]:
    """Seconds of each image: `frame_XXXXX` names (video frames: their index) over fps, else file-name order."""
    indices = [re.fullmatch(r"frame_(\d+)\.\w+", Path(n).name) for n in names]
    if all(indices):
        return {n: int(m.group(1)) / fps for n, m in zip(names, indices)}
    return {n: k / fps for k, n in enumerate(sorted(names))}


def readout_poses(c2w: np.ndarray, times: np.ndarray, readout_time: float) -> tuple[np.ndarray, np.ndarray]:
    """(start, end) [K, 3 or 4, 4] camera-to-world of K frames (c2w [K, 3 or 4, 4] at mid-readout, times [K]
    seconds, in capture order): the estimate described above."""
    k = len(c2w)
    start, end = c2w.copy(), c2w.copy()
    for i in range(k):
        a, b = max(i - 1, 0), min(i + 1, k - 1)
        dt = times[b] - times[a]
        turn = Rotation.from_matrix(c2w[a, :3, :3].T @ c2w[b, :3, :3]).as_rotvec() / dt  # about the camera's axes
        velocity = (c2w[b, :3, 3] - c2w[a, :3, 3]) / dt
        half = Rotation.from_rotvec(turn * readout_time / 2).as_matrix()
        start[i, :3, :3], end[i, :3, :3] = c2w[i, :3, :3] @ half.T, c2w[i, :3, :3] @ half
        start[i, :3, 3] = c2w[i, :3, 3] - velocity * readout_time / 2
        end[i, :3, 3] = c2w[i, :3, 3] + velocity * readout_time / 2
    return start, end


def sequences(names: List[str], groups: List[object], fps: float, where: str) -> List[tuple]:
    """[(indices into names in capture order, their times)] per group (one camera of a rig each): capture times by
    capture_times within the group, strictly increasing (else DatasetError naming `where`), 2 or more images."""
    out = []
    for group in sorted(set(groups), key=str):
        members = [i for i, g in enumerate(groups) if g == group]
        times_of = capture_times([names[i] for i in members], fps)
        order = sorted(members, key=lambda i: times_of[names[i]])
        times = np.array([times_of[names[i]] for i in order])
        if len(order) < 2 or (np.diff(times) <= 0).any():
            raise DatasetError(f"geer: {where}: the motion during a readout is estimated from neighbouring frames of "
                               f"one camera; camera {group} has {len(order)} image(s) or two at the same capture time "
                               "(frame_XXXXX indices, else file-name order)")
        out.append((order, times))
    return out


def sfm_readouts(readout: str, readout_time: Optional[float], frame_rate: Optional[float], names: List[str],
                 c2w: torch.Tensor, where: str, groups: Optional[List[object]] = None) -> Optional[tuple]:
    """For a structure-from-motion model read with a rolling shutter (options readout, readout_time, frame_rate;
    `where` names them for errors): (start poses [N, 3, 4] float64, Cameras.metadata entries) of the images
    `names` with their mid-readout poses c2w [N, 3, 4] (the parsed scene's frame), each image's neighbours taken
    within its group (`groups`: one value per image, e.g. its camera id; None: one camera); None for a global
    shutter."""
    if readout == "global":
        return None
    if readout not in READOUTS:
        raise DatasetError(f"geer: {where}rolling-shutter: expected global or one of {', '.join(READOUTS)}, "
                           f"got {readout!r}")
    if readout_time is None or not readout_time > 0 or frame_rate is None or not frame_rate > 0:
        raise DatasetError(f"geer: {where}rolling-shutter {readout} needs {where}readout-time (seconds, > 0) and "
                           f"{where}frame-rate (frames per second, > 0), got {readout_time} and {frame_rate}")
    if readout_time >= 1.0 / frame_rate:
        raise DatasetError(f"geer: {where}readout-time {readout_time} s must be shorter than a frame interval "
                           f"({1.0 / frame_rate:.4f} s)")
    starts = torch.empty(len(names), 3, 4, dtype=torch.float64)
    motions = torch.empty(len(names), 12, dtype=torch.float64)
    for order, times in sequences(names, [0] * len(names) if groups is None else groups, frame_rate,
                                  f"{where}rolling-shutter"):
        mids = np.tile(np.eye(4), (len(order), 1, 1))
        mids[:, :3] = c2w.double().numpy()[order]
        start, end = readout_poses(mids, times, readout_time)
        for j, i in enumerate(order):
            starts[i] = torch.from_numpy(start[j, :3])
            motions[i] = motion_between(starts[i], torch.from_numpy(end[j, :3]))
    index = READOUTS.index(readout)
    return starts, {READOUT_KEY: torch.full((len(names), 1), index, dtype=torch.int64), MOTION_KEY: motions.float()}
