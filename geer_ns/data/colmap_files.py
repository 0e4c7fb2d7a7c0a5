"""COLMAP folders as users have them: where the model is, lenient text models, where the images are.

* the model (cameras + images, .txt or .bin) is looked for at the usual depths below ``--data``
  (``.``, ``sparse/0``, ``sparse``, ``colmap/sparse/0``, ...);
* text models are read leniently and rewritten in COLMAP's strict form before pycolmap reads them: commas
  as separators (kapture and some exporters write them) are accepted, and anything else malformed is
  reported with its file and line number instead of pycolmap's bare C++ check message;
* an image name is looked up under the usual image folders, by its full relative name and by its file
  name; the images that cannot be found are listed together;
* the model is then read with ``pycolmap.Reconstruction`` (``read_reconstruction``).
"""

from __future__ import annotations

import math
import re
import shutil
import struct
import tempfile
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

from nerfstudio.utils.rich_utils import CONSOLE

from geer_ns.data.dataset_checks import DatasetError, missing_images_error

MODEL_DIRS = (
    Path("sparse/0"), Path("colmap/sparse/0"), Path("sparse"), Path("colmap/sparse"), Path("colmap"), Path("."),
    Path("distorted/sparse/0"),
)
_SEPARATORS = re.compile(r"[,\s]+")
_IMAGE_FIELDS = ("IMAGE_ID", "QW", "QX", "QY", "QZ", "TX", "TY", "TZ", "CAMERA_ID")


def param_names(model: str) -> List[str]:
    """COLMAP's parameter names of a camera model (pycolmap's params_info)."""
    import pycolmap

    cam = pycolmap.Camera.create_from_model_name(0, model, 1.0, 2, 2)
    return [n.strip() for n in cam.params_info.split(",")]


def model_format(model_dir: Path) -> Optional[str]:
    if (model_dir / "cameras.bin").is_file() and (model_dir / "images.bin").is_file():
        return "bin"
    if (model_dir / "cameras.txt").is_file() and (model_dir / "images.txt").is_file():
        return "txt"
    return None


def find_model_dir(data: Path) -> Optional[Path]:
    """The first usual model folder below data holding cameras + images (then any sparse/<n>)."""
    extra = sorted(p.relative_to(data) for p in (data / "sparse").glob("*") if p.is_dir()) if (data / "sparse").is_dir() else []
    for candidate in (*MODEL_DIRS, *extra):
        if (data / candidate).is_dir() and model_format(data / candidate) is not None:
            return data / candidate
    return None


# ==================================================================================================
# Text models
# ==================================================================================================


def _tokens(line: str) -> List[str]:
    return [t for t in _SEPARATORS.split(line.strip()) if t]


def _numbers(path: Path, lineno: int, names: Sequence[str], texts: Sequence[str], what: str = "") -> List[float]:
    values = []
    for name, text in zip(names, texts):
        try:
            value = float(text)
        except ValueError:
            raise DatasetError(f"geer: {path}:{lineno}: {what}{name} = {text!r} is not a number") from None
        if not math.isfinite(value):
            raise DatasetError(f"geer: {path}:{lineno}: {what}{name} = {text} is not finite")
        values.append(value)
    return values


def normalize_cameras_txt(path: Path) -> Tuple[str, Dict[int, str]]:
    """(strict cameras.txt text, {camera id: model}) or DatasetError at file:line."""
    import pycolmap

    known = sorted(set(pycolmap.CameraModelId.__members__) - {"INVALID"})
    out, models = [], {}
    for lineno, line in enumerate(path.read_text(encoding="utf8").splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        tok = _tokens(line)
        if len(tok) < 4:
            raise DatasetError(f"geer: {path}:{lineno}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got {line.strip()!r}")
        cid, model = tok[0], tok[1]
        if model not in known:
            raise DatasetError(
                f"geer: {path}:{lineno}: camera {cid}: unknown COLMAP camera model {model}; expected one of {', '.join(known)}"
            )
        if not cid.isdigit():
            raise DatasetError(f"geer: {path}:{lineno}: CAMERA_ID = {cid!r}; expected a positive integer")
        for name, text in (("WIDTH", tok[2]), ("HEIGHT", tok[3])):
            if not text.isdigit() or int(text) == 0:
                raise DatasetError(f"geer: {path}:{lineno}: camera {cid}: {name} = {text!r}; expected a positive integer")
        names = param_names(model)
        if len(tok) - 4 != len(names):
            raise DatasetError(
                f"geer: {path}:{lineno}: camera {cid}: {model} expects {len(names)} params ({', '.join(names)}), "
                f"got {len(tok) - 4}"
            )
        _numbers(path, lineno, names, tok[4:], what=f"camera {cid}: {model} parameter ")
        if int(cid) in models:
            raise DatasetError(f"geer: {path}:{lineno}: camera {cid} is defined twice; remove one line")
        models[int(cid)] = model
        out.append(" ".join(tok))
    return "\n".join(out) + "\n", models


def normalize_images_txt(path: Path, cameras: Dict[int, str]) -> str:
    """Strict images.txt text (two lines per image) or DatasetError at file:line."""
    lines = path.read_text(encoding="utf8").splitlines()
    out: List[str] = []
    ids: Dict[int, int] = {}
    names: Dict[str, int] = {}
    i = 0
    while i < len(lines):
        line, lineno = lines[i], i + 1
        i += 1
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        tok = _tokens(line)
        if len(tok) < 10:
            raise DatasetError(
                f"geer: {path}:{lineno}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME (10 fields, spaces or "
                f"commas), got {len(tok)}: {line.strip()[:80]!r}"
            )
        values = _numbers(path, lineno, _IMAGE_FIELDS, tok[:9])
        image_id, camera_id, name = int(values[0]), int(values[8]), " ".join(tok[9:])
        if values[0] != image_id or values[8] != camera_id:
            raise DatasetError(f"geer: {path}:{lineno}: IMAGE_ID and CAMERA_ID must be integers, got {tok[0]}, {tok[8]}")
        if math.fsum(v * v for v in values[1:5]) == 0.0:
            raise DatasetError(f"geer: {path}:{lineno}: image {image_id} ({name}): the quaternion QW QX QY QZ is zero")
        if camera_id not in cameras:
            raise DatasetError(
                f"geer: {path}:{lineno}: image {image_id} ({name}): CAMERA_ID {camera_id} is not in cameras.txt "
                f"(cameras: {sorted(cameras)})"
            )
        if image_id in ids:
            raise DatasetError(f"geer: {path}:{lineno}: IMAGE_ID {image_id} repeats line {ids[image_id]}")
        if name in names:
            raise DatasetError(f"geer: {path}:{lineno}: image name {name!r} repeats line {names[name]}")
        ids[image_id], names[name] = lineno, lineno
        points = ""
        if i < len(lines):  # the POINTS2D line (may be empty)
            ptok = _tokens(lines[i])
            if lines[i].lstrip().startswith("#"):
                ptok = []
            elif len(ptok) % 3:
                raise DatasetError(
                    f"geer: {path}:{i + 1}: POINTS2D of image {image_id}: expected triples X Y POINT3D_ID, "
                    f"got {len(ptok)} values"
                )
            else:
                _numbers(path, i + 1, ["POINTS2D"] * len(ptok), ptok)
                i += 1
            points = " ".join(ptok)
        out.append(" ".join(tok[:9] + [name]))
        out.append(points)
    if not out:
        raise DatasetError(f"geer: {path}: no images; expected lines IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
    return "\n".join(out) + "\n"


def normalize_points_txt(path: Path) -> str:
    """points3D.txt with commas turned into spaces (the values are checked by pycolmap)."""
    out = []
    for line in path.read_text(encoding="utf8").splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            out.append(" ".join(_tokens(line)))
    return "\n".join(out) + ("\n" if out else "")


def write_strict_text_model(model_dir: Path, dst: Path) -> bool:
    """Strict copies of model_dir's text model in dst; returns whether it has a points3D.txt."""
    cameras_text, models = normalize_cameras_txt(model_dir / "cameras.txt")
    (dst / "cameras.txt").write_text(cameras_text)
    (dst / "images.txt").write_text(normalize_images_txt(model_dir / "images.txt", models))
    points = model_dir / "points3D.txt"
    (dst / "points3D.txt").write_text(normalize_points_txt(points) if points.is_file() else "")
    return points.is_file()


# ==================================================================================================
# Images
# ==================================================================================================


def image_roots(data: Path, images_path: Path, model_dir: Path) -> List[Path]:
    """Folders an image name may be relative to, most specific first."""
    roots = [data / images_path, data / "images", data, model_dir, model_dir.parent, model_dir / "images"]
    seen, out = set(), []
    for root in roots:
        key = root.resolve()
        if key not in seen and root.is_dir():
            seen.add(key)
            out.append(root)
    return out


def locate_images(names: Sequence[str], roots: Sequence[Path], model_file: Path) -> List[Tuple[Path, Path]]:
    """(root, relative path) of every image: by the full name under each root, then by the file name when
    no other image has the same file name. DatasetError listing every name that is found nowhere."""
    basenames: Dict[str, int] = {}
    for name in names:
        basenames[Path(name).name] = basenames.get(Path(name).name, 0) + 1
    found, missing = [], []
    for name in names:
        hit = None
        unique = basenames[Path(name).name] == 1
        for rel in (Path(name), Path(Path(name).name)) if unique else (Path(name),):
            hit = next(((root, rel) for root in roots if (root / rel).is_file()), None)
            if hit is not None:
                break
        if hit is None:
            missing.append(name)
        found.append(hit)
    if missing:
        raise missing_images_error(model_file, missing, roots)
    return found


def model_file(model_dir: Path, stem: str) -> Path:
    fmt = model_format(model_dir) or "txt"
    return model_dir / f"{stem}.{fmt}"


def read_reconstruction(model_dir: Path):
    """pycolmap.Reconstruction of model_dir; a missing points3D file counts as no points.

    Text models are first rewritten strictly (commas accepted, errors at file:line)."""
    import pycolmap

    fmt = model_format(model_dir)
    if fmt is None:
        raise FileNotFoundError(
            f"COLMAP model directory {model_dir} has no cameras.bin + images.bin or cameras.txt + images.txt"
        )
    with tempfile.TemporaryDirectory(prefix="geer_colmap_") as tmp:
        src = Path(tmp)
        if fmt == "txt":
            has_points = write_strict_text_model(model_dir, src)
        else:
            has_points = (model_dir / "points3D.bin").is_file()
            for name in ("cameras.bin", "images.bin", "points3D.bin"):
                if (model_dir / name).is_file():
                    shutil.copy(model_dir / name, src / name)
            if not has_points:
                (src / "points3D.bin").write_bytes(struct.pack("<Q", 0))
        if not has_points:
            CONSOLE.log(f"[yellow]geer: {model_dir} has no points3D.{fmt}: seed points are drawn in the camera frusta")
        recon = pycolmap.Reconstruction()
        try:
            if fmt == "txt":
                recon.read_text(str(src))
            else:
                recon.read_binary(str(src))
        except Exception as e:  # pycolmap raises ValueError / RuntimeError with a C++ check message
            raise DatasetError(f"geer: pycolmap could not read the COLMAP model in {model_dir}: {e}") from e
    return recon
