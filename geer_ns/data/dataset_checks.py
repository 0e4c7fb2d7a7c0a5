"""Dataset checks that run before anything heavy: one clear line per broken dataset.

A broken dataset otherwise ends ~40 s later in a stack trace that names neither file nor field (sklearn's
"Input X contains NaN" from the seed points, "image file is truncated", nerfstudio's "fx must be > 0" for a
file that says `fl_x`, ...). Here each problem is reported as

    geer: <file>: frames[<i>] (<file_path>): `<field>` <what is wrong>; expected <what>; <what to do>

and raised as :class:`DatasetError` before images are decoded or cached. Only file headers and tails are
read (image size, JPEG/PNG end markers), so the checks take milliseconds per image.

transforms.json: camera fields (``camera_model``, ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``,
``k1``..``k4``, ``p1``, ``p2``, ``distortion_params``, ``fisheye_crop_radius``) may be given at the top
level or per frame; a frame's own value wins (geer's transforms.json parser reads them so).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from geer_ns.errors import DatasetError  # re-exported here
from geer_ns.render.validate import ROTATION_TOLERANCE

__all__ = ["DatasetError", "VALID_CAMERA_MODELS", "check_image_file", "check_transforms_json"]

# Orthonormality of a pose's rotation block: |R R^T - I| (Frobenius, as render/validate.py measures a viewmat)
# <= ROTATION_TOLERANCE, 1e-3: exporters write ~1e-7; beyond it is a scaled, sheared or garbled matrix, not
# rounding. render() refuses viewmats beyond the same bound, so every pose that passes here renders.
_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
_MAX_REPORTED = 20  # stop collecting after this many problems


def _renderable_camera_models() -> Tuple[str, ...]:
    """nerfstudio's camera_model names whose camera types geer renders (geer_ns.cameras.from_nerfstudio)."""
    from nerfstudio.cameras.cameras import CAMERA_MODEL_TO_TYPE, CameraType

    ok = {CameraType.PERSPECTIVE, CameraType.FISHEYE, CameraType.FISHEYE624, CameraType.EQUIRECTANGULAR}
    return tuple(name for name, kind in CAMERA_MODEL_TO_TYPE.items() if kind in ok)


VALID_CAMERA_MODELS = _renderable_camera_models()


class _Problems:
    """Collects problems; raises one DatasetError with the first and the count of the others."""

    def __init__(self) -> None:
        self.lines: List[str] = []

    def add(self, line: str) -> None:
        self.lines.append(line)
        if len(self.lines) >= _MAX_REPORTED:
            self.raise_if_any()

    def raise_if_any(self) -> None:
        if not self.lines:
            return
        more = len(self.lines) - 1
        suffix = f" (+{more} more problem(s); fix this one first)" if more else ""
        raise DatasetError(f"geer: {self.lines[0]}{suffix}")


# ==================================================================================================
# Image files
# ==================================================================================================


def check_image_file(path: Path, where: str, size: Optional[Tuple[int, int]] = None, what: str = "image",
                     size_fields: str = "`w` x `h`") -> Tuple[int, int]:
    """(width, height) of an image file from its header, or DatasetError naming `where`.

    Reads the header and, for JPEG and PNG, the file's tail: a file cut short misses its end marker.
    `size` (width, height) is what the dataset says the image must be, in its fields `size_fields`.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"geer: {where}: {what} file {path} does not exist; fix the path or add the file")
    try:
        with Image.open(path) as im:
            got = (int(im.size[0]), int(im.size[1]))
            fmt = im.format
    except UnidentifiedImageError:
        raise DatasetError(
            f"geer: {where}: {what} file {path} is not an image (unknown format); replace it with a PNG or JPEG"
        ) from None
    except OSError as e:
        raise DatasetError(f"geer: {where}: {what} file {path} cannot be read ({e}); replace the file") from None
    if missing_end_marker(path, fmt):
        raise DatasetError(
            f"geer: {where}: {what} file {path} is truncated ({fmt} end marker missing); re-export or re-copy it"
        )
    if size is not None and got != tuple(size):
        raise DatasetError(
            f"geer: {where}: {what} file {path} is {got[0]}x{got[1]} px, expected {size[0]}x{size[1]} ({size_fields}); "
            f"fix {size_fields} or resize the file"
        )
    return got


def missing_end_marker(path: Path, fmt: Optional[str]) -> bool:
    """Whether a JPEG or PNG file (PIL's format name `fmt`) lacks its end marker: a file cut short."""
    markers = {"JPEG": b"\xff\xd9", "MPO": b"\xff\xd9", "PNG": b"IEND"}
    marker = markers.get(fmt or "")
    if marker is None:
        return False
    with open(path, "rb") as f:
        f.seek(0, 2)
        n = f.tell()
        f.seek(max(0, n - 4096))
        tail = f.read()
    return marker not in tail


# ==================================================================================================
# transforms.json
# ==================================================================================================


def _number(value: Any) -> Optional[float]:
    """The value as nerfstudio reads it (float(...): numbers and numeric strings), else None."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        return None
    try:
        return float(value)
    except ValueError:
        return None


def _load_json(path: Path) -> Any:
    try:
        text = path.read_text(encoding="utf8")
    except UnicodeDecodeError as e:
        raise DatasetError(f"geer: {path}: not a UTF-8 text file ({e}); expected nerfstudio's transforms.json") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise DatasetError(f"geer: {path}:{e.lineno}:{e.colno}: not valid JSON ({e.msg}); fix the syntax there") from None


def check_transforms_json(path: Path, auto_scale_poses: bool = True) -> Dict[str, Any]:
    """Check a nerfstudio-data transforms.json and the files it names; DatasetError on the first problem.
    Returns the file's contents.

    auto_scale_poses: the dataparser's option; it divides by the spread of the camera positions."""
    path = Path(path)
    meta = _load_json(path)
    if not isinstance(meta, dict):
        raise DatasetError(f"geer: {path}: expected a JSON object with `frames` at the top level, got {type(meta).__name__}")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        got = "missing" if frames is None else ("an empty list" if frames == [] else type(frames).__name__)
        raise DatasetError(
            f"geer: {path}: `frames` is {got}; expected a non-empty list of frames with `file_path` and "
            "`transform_matrix` (one per image)"
        )
    problems = _Problems()
    root = path.parent
    seen: Dict[str, int] = {}
    for i, frame in enumerate(frames):
        _check_frame(path, root, meta, i, frame, seen, problems)
    _check_top_level_files(path, root, meta, seen, problems)
    problems.raise_if_any()
    if auto_scale_poses and len(frames) > 1:
        centers = np.array([np.asarray(f["transform_matrix"], dtype=np.float64)[:3, 3] for f in frames])
        if np.ptp(centers, axis=0).max() == 0.0:
            raise DatasetError(
                f"geer: {path}: `transform_matrix`: all {len(frames)} frames have the camera position "
                f"{centers[0].tolist()}; nerfstudio's pose scaling divides by their spread (zero): fix the poses, "
                "or set --pipeline.datamanager.dataparser.auto-scale-poses False for a rotation-only capture"
            )
    return meta


def _check_frame(path: Path, root: Path, meta: dict, i: int, frame: Any, seen: Dict[str, int], problems: _Problems) -> None:
    if not isinstance(frame, dict):
        problems.add(f"{path}: frames[{i}]: expected an object with `file_path` and `transform_matrix`")
        return
    file_path = frame.get("file_path")
    where = f"{path}: frames[{i}]" + (f" ({file_path})" if isinstance(file_path, str) else "")
    if not isinstance(file_path, str) or not file_path:
        problems.add(f"{where}: `file_path` is missing; expected the image path relative to {root}")
        return
    key = str(Path(file_path))
    if key in seen:
        problems.add(f"{where}: `file_path` repeats frames[{seen[key]}]; remove the duplicate frame")
        return
    seen[key] = i
    n_before = len(problems.lines)
    size = _check_camera_fields(where, meta, frame, problems)
    _check_pose(where, frame.get("transform_matrix"), problems)
    if len(problems.lines) > n_before:
        return
    try:
        got = check_image_file(root / file_path, where + ": `file_path`", size)
        mask = frame.get("mask_path")
        if mask is not None:
            if not isinstance(mask, str):
                problems.add(f"{where}: `mask_path` is {mask!r}; expected a path relative to {root}")
            else:
                check_image_file(root / mask, where + ": `mask_path`", got, what="mask", size_fields="the image's size")
        depth = frame.get("depth_file_path")
        if isinstance(depth, str) and not (root / depth).is_file():
            problems.add(f"{where}: `depth_file_path` {root / depth} does not exist; fix the path or remove the field")
    except DatasetError as e:
        problems.add(str(e)[len("geer: "):])


def _field(meta: dict, frame: dict, name: str) -> Tuple[Any, str]:
    """A camera field's value (the frame's own wins) and where it came from."""
    if name in frame:
        return frame[name], "frame"
    return meta.get(name), "top level"


def _check_camera_fields(where: str, meta: dict, frame: dict, problems: _Problems) -> Optional[Tuple[int, int]]:
    model, _ = _field(meta, frame, "camera_model")
    if model is None:
        model = "OPENCV"  # nerfstudio's default
    if model not in VALID_CAMERA_MODELS:
        problems.add(f"{where}: `camera_model` {model!r} is not supported; expected one of {', '.join(VALID_CAMERA_MODELS)}")
    values: Dict[str, float] = {}
    for name in _INTRINSICS:
        raw, origin = _field(meta, frame, name)
        value = _number(raw)
        if raw is None:
            problems.add(f"{where}: `{name}` is missing (neither in the frame nor at the top level); add it")
        elif value is None or not math.isfinite(value):
            problems.add(f"{where}: `{name}` = {raw!r} ({origin}); expected a finite number")
        else:
            values[name] = value
    for name in ("fl_x", "fl_y", "w", "h"):
        if name in values and values[name] <= 0:
            problems.add(f"{where}: `{name}` = {values[name]:g}; expected > 0")
            values.pop(name)
    for name in ("w", "h"):
        if name in values and values[name] != int(values[name]):
            problems.add(f"{where}: `{name}` = {values[name]:g}; expected a whole number of pixels")
            values.pop(name)
    for c, extent in (("cx", "w"), ("cy", "h")):
        if c in values and extent in values and not 0.0 <= values[c] <= values[extent]:
            problems.add(
                f"{where}: `{c}` = {values[c]:g} lies outside the image (0..{values[extent]:g} = `{extent}`); "
                "expected the principal point in pixels"
            )
    for name in _DISTORTION:
        raw, origin = _field(meta, frame, name)
        if raw is not None and not (_number(raw) is not None and math.isfinite(_number(raw))):
            problems.add(f"{where}: `{name}` = {raw!r} ({origin}); expected a finite number")
    params, origin = _field(meta, frame, "distortion_params")
    if params is not None:
        flat = np.asarray(params, dtype=object).reshape(-1) if isinstance(params, list) else None
        if flat is None or not all(_number(v) is not None and math.isfinite(_number(v)) for v in flat):
            problems.add(f"{where}: `distortion_params` = {params!r} ({origin}); expected a list of finite numbers")
    radius, origin = _field(meta, frame, "fisheye_crop_radius")
    if radius is not None and not (_number(radius) is not None and math.isfinite(_number(radius)) and _number(radius) > 0):
        problems.add(f"{where}: `fisheye_crop_radius` = {radius!r} ({origin}); expected a positive number of pixels")
    if "w" in values and "h" in values:
        return int(values["w"]), int(values["h"])
    return None


def _check_pose(where: str, matrix: Any, problems: _Problems) -> None:
    name = "`transform_matrix`"
    if matrix is None:
        problems.add(f"{where}: {name} is missing; expected the 4x4 camera-to-world matrix")
        return
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        problems.add(f"{where}: {name} is not a matrix of numbers; expected 4x4 (or 3x4) camera-to-world")
        return
    if m.shape not in ((4, 4), (3, 4)):
        problems.add(f"{where}: {name} has shape {list(m.shape)}; expected 4x4 (or 3x4) camera-to-world")
        return
    if not np.isfinite(m).all():
        r, c = np.argwhere(~np.isfinite(m))[0]
        problems.add(f"{where}: {name}[{r}][{c}] = {m[r, c]}; expected finite numbers (fix or remove this frame)")
        return
    rot = m[:3, :3]
    lengths = np.linalg.norm(rot, axis=1)
    if (lengths < 1e-8).any():
        problems.add(f"{where}: {name} row {int(np.argmin(lengths))} of the rotation has zero length; expected a rotation")
        return
    err = np.linalg.norm(rot @ rot.T - np.eye(3))
    if err > ROTATION_TOLERANCE or np.linalg.det(rot) <= 0:
        what = f"not orthonormal (|R R^T - I| = {err:.2g})" if err > ROTATION_TOLERANCE else "a reflection (det < 0)"
        problems.add(
            f"{where}: {name} rotation block is {what}; expected a rigid camera-to-world pose (re-export the poses)"
        )


def _check_top_level_files(path: Path, root: Path, meta: dict, seen: Dict[str, int], problems: _Problems) -> None:
    ply = meta.get("ply_file_path")
    if ply is not None and not (isinstance(ply, str) and (root / ply).is_file()):
        problems.add(f"{path}: `ply_file_path` {root / str(ply)} does not exist; fix the path or remove the field")
    for split in ("train", "val", "test"):
        names = meta.get(f"{split}_filenames")
        if names is None:
            continue
        if not isinstance(names, list):
            problems.add(f"{path}: `{split}_filenames` is {type(names).__name__}; expected a list of `file_path` values")
            continue
        unknown = [n for n in names if str(Path(str(n))) not in seen]
        if unknown:
            problems.add(
                f"{path}: `{split}_filenames` names {len(unknown)} file(s) no frame has as `file_path`, e.g. "
                f"{unknown[0]!r}; expected each to be a frame's `file_path`"
            )


def missing_images_error(model_file: Path, missing: Sequence[str], searched: Sequence[Path]) -> DatasetError:
    shown = ", ".join(repr(m) for m in missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
    where = ", ".join(str(s) for s in searched)
    return DatasetError(
        f"geer: {model_file}: {len(missing)} image(s) named there were not found ({shown}); searched {where} "
        "by the full name and by the file name; set images_path or rename the files"
    )
