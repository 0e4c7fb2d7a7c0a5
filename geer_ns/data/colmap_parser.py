"""COLMAP dataparser for geer, built on ``pycolmap.Reconstruction``.

Why not nerfstudio's own ``colmap`` dataparser: nerfstudio 1.1.5 raises for every OPENCV_FISHEYE calibration
with k4 != 0 (a nerfstudio bug: it mistakes the fisheye k4 for OpenCV's rational k4) and maps
FULL_OPENCV, FOV and THIN_PRISM_FISHEYE to NotImplementedError. geer renders exact per-pixel rays of the
calibrated model and never undistorts, so it must take those datasets as they are.

Layout (``data`` is the dataset root)::

    data/
      sparse/0/ | colmap/sparse/0/ | sparse/   COLMAP model, text (commas accepted) or binary, at any usual
      | colmap/ | . | ...                      depth (colmap_files.MODEL_DIRS, or ``colmap_path``);
                                               points3D.{txt,bin} may be missing: seeds are then drawn inside
                                               the camera frusta (frustum_seed)
      images/<name>                            one file per registered COLMAP image (name as in images.txt,
                                               sub-folders allowed; also looked up under data/ and beside the
                                               model, and by file name when unique; misses listed together)
      images_<N>/<name>                        optional downscaled copies (``downscale_factor`` = N)
      masks/<name with .png suffix>            optional masks, same relative names (``masks_N`` when downscaled)
      train_list.txt / test_list.txt /         optional split lists: one image name per line (relative to
      val_list.txt                             images/, as in images.txt)

Cameras
-------
The exact COLMAP model of every image is kept (``metadata["geer_colmap_cameras"]`` and ``Cameras.metadata``)
and geer renders with it; the nerfstudio ``Cameras`` get the closest camera nerfstudio knows (the table, and
the fit where nerfstudio has no equivalent, are in :mod:`geer_ns.data.colmap_cameras`).

Poses, orientation, centring and scale follow nerfstudio's colmap dataparser (OpenCV -> OpenGL camera axes,
COLMAP world -> z-up, ``auto_orient_and_center_poses``, scale to [-1, 1]); ``dataparser_transform`` and
``dataparser_scale`` map COLMAP world points into the output frame, and the seed points
(``points3D_xyz`` / ``points3D_rgb``) are mapped the same way.

Images are ordered by name. Split: the list files above when present (a missing counterpart is "all other
images"), otherwise ``eval_mode`` as in nerfstudio (default ``interval``: every ``eval_interval``-th image,
starting with the first, is eval).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, NamedTuple, Optional, Sequence, Tuple, Type

import numpy as np
import torch
from PIL import Image

from nerfstudio.cameras import camera_utils
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.data.utils.dataparsers_utils import (
    get_train_eval_split_all,
    get_train_eval_split_filename,
    get_train_eval_split_fraction,
    get_train_eval_split_interval,
)
from nerfstudio.plugins.registry_dataparser import DataParserSpecification
from nerfstudio.utils.rich_utils import CONSOLE

from geer_ns.cameras import from_pycolmap
from geer_ns.data import colmap_files
from geer_ns.data.colmap_cameras import (  # re-exported: this module is where users import them from
    DISTORTED_KEY,
    GEER_CAMERAS_KEY,
    MAX_PARAMS,
    MODEL_ID_KEY,
    NS_INTRINSICS_KEY,
    NS_TYPE_KEY,
    PARAMS_KEY,
    ColmapCameraSpec,
    NerfstudioIntrinsics,
    _check_camera,
    _model_id,
    _pycolmap_camera,
    _rescaled,
    camera_model_for_image,
    camera_model_from_cameras,
    nerfstudio_intrinsics,
)
from geer_ns.data.colmap_files import model_file as _model_file
# Looked up here at call time (tests patch colmap_parser._read_reconstruction).
from geer_ns.data.colmap_files import read_reconstruction as _read_reconstruction
from geer_ns.data.rolling_shutter import sfm_readouts
from geer_ns.data.dataset_checks import DatasetError, check_image_file
from geer_ns.data.frustum_seed import frustum_points, seed_count

__all__ = [
    "ColmapCameraSpec",
    "GeerColmapDataParserConfig",
    "GeerColmapDataParser",
    "NerfstudioIntrinsics",
    "camera_model_for_image",
    "camera_model_from_cameras",
    "geer_colmap_dataparser",
    "nerfstudio_intrinsics",
]

MAX_AUTO_RESOLUTION = 1600  # same rule as nerfstudio's colmap dataparser


# ==================================================================================================
# Dataparser
# ==================================================================================================


@dataclass
class GeerColmapDataParserConfig(DataParserConfig):
    """COLMAP dataset (pycolmap reader) keeping the exact camera models; see geer_ns.data.colmap_parser."""

    _target: Type = field(default_factory=lambda: GeerColmapDataParser)
    data: Path = Path()
    """Dataset root."""
    colmap_path: Optional[Path] = None
    """COLMAP model folder relative to data; default: the first of sparse/0, colmap/sparse/0, sparse."""
    images_path: Path = Path("images")
    """Image folder relative to data (downscaled copies in <images_path>_<N>)."""
    masks_path: Optional[Path] = Path("masks")
    """Mask folder relative to data (<name>.png per image, 0 = ignore); used when it exists. None: no masks."""
    downscale_factor: Optional[int] = None
    """Image downscale factor N (images_N/ must exist for N > 1). None: smallest power of two that brings
    the larger image side to <= 1600 px (like nerfstudio)."""
    downscale_rounding_mode: Literal["floor", "round", "ceil"] = "floor"
    """Rounding of the downscaled image size (as nerfstudio's Cameras.rescale_output_resolution)."""
    scale_factor: float = 1.0
    """Extra scale applied to the camera origins (after auto scaling)."""
    scene_scale: float = 1.0
    """Half size of the scene box."""
    orientation_method: Literal["pca", "up", "vertical", "none"] = "up"
    center_method: Literal["poses", "focus", "none"] = "poses"
    auto_scale_poses: bool = True
    """Scale the poses to fit in [-1, 1]."""
    assume_colmap_world_coordinate_convention: bool = True
    """Map COLMAP's usual world (-y is up) to nerfstudio's z-up before orienting, as nerfstudio does."""
    eval_mode: Literal["fraction", "filename", "interval", "all"] = "interval"
    """Split when no train_list.txt / test_list.txt / val_list.txt exists (nerfstudio's modes)."""
    train_split_fraction: float = 0.9
    eval_interval: int = 8
    load_3D_points: bool = True
    """Seed points from points3D (metadata points3D_xyz / points3D_rgb)."""
    check_image_sizes: bool = True
    """Check every image (and mask) file's size against its COLMAP camera (reads only the file headers)."""
    rolling_shutter: Literal["global", "top-to-bottom", "bottom-to-top", "left-to-right", "right-to-left"] = "global"
    """The sensor's readout (docs/rolling_shutter.md): with a rolling shutter, each image's COLMAP pose is taken as
    its mid-readout pose and its motion during the readout is estimated from its neighbours (capture order:
    frame_XXXXX indices, else file names)."""
    readout_time: Optional[float] = None
    """Rolling shutter: seconds from the first row (column) read to the last."""
    frame_rate: Optional[float] = None
    """Rolling shutter: frames per second of the capture."""
    crop_radius: Optional[float] = None
    """Fisheye image-circle radius in pixels (of the full-resolution images), centered on each camera's
    principal point: pixels outside are not supervised. For fisheye captures without masks."""


class _Parsed(NamedTuple):
    key: tuple  # (resolved model file, modification time) of cameras and images
    model_dir: Path
    recon: object
    names: List[str]
    cameras: Cameras
    specs: List[ColmapCameraSpec]
    c2w: torch.Tensor
    transform: torch.Tensor
    scale: float
    image_files: List[Path]
    mask_files: Optional[List[Path]]
    downscale: int


class GeerColmapDataParser(DataParser):
    """See the module docstring."""

    config: GeerColmapDataParserConfig

    def __init__(self, config: GeerColmapDataParserConfig):
        super().__init__(config=config)
        self.config = config

    # --- locating files ---------------------------------------------------------------------------
    def _model_dir(self) -> Path:
        data = Path(self.config.data)
        if not data.is_dir():
            raise FileNotFoundError(f"dataset directory {data} does not exist")
        if self.config.colmap_path is not None:
            model_dir = data / self.config.colmap_path
            if not model_dir.is_dir():
                raise FileNotFoundError(f"COLMAP model directory {model_dir} (colmap_path) does not exist")
            return model_dir
        found = colmap_files.find_model_dir(data)
        if found is not None:
            return found
        tried = ", ".join(str(data / c) for c in colmap_files.MODEL_DIRS)
        raise FileNotFoundError(
            f"no COLMAP model directory (cameras + images .txt or .bin) found; tried {tried} (set colmap_path)"
        )

    def _downscale_factor(self, first_image: Path) -> int:
        if self.config.downscale_factor is not None:
            df = int(self.config.downscale_factor)
            if df < 1:
                raise ValueError(f"downscale_factor must be >= 1, got {self.config.downscale_factor}")
            return df
        with Image.open(first_image) as im:
            max_res = max(im.size)
        df = 1
        while max_res / df > MAX_AUTO_RESOLUTION:
            df *= 2
        if df > 1:
            CONSOLE.log(f"Using image downscale factor of {df} (images above {MAX_AUTO_RESOLUTION} px)")
        return df

    # --- split --------------------------------------------------------------------------------------
    def _split_indices(self, names: List[str], split: str) -> np.ndarray:
        data = Path(self.config.data)
        lists = {"train": data / "train_list.txt", "test": data / "test_list.txt", "val": data / "val_list.txt"}
        present = {k: p for k, p in lists.items() if p.is_file()}
        if present:
            index = {n: i for i, n in enumerate(names)}

            def read(path: Path) -> List[int]:
                wanted = [ln.strip() for ln in path.read_text(encoding="utf8").splitlines() if ln.strip()]
                unknown = [w for w in wanted if w not in index]
                if unknown:
                    raise ValueError(f"{path}: image names not in the COLMAP model: {unknown[:5]}")
                return sorted(index[w] for w in wanted)

            if split == "train":
                if "train" in present:
                    return np.array(read(present["train"]), dtype=np.int64)
                held = set().union(*(read(p) for k, p in present.items() if k != "train"))
                return np.array([i for i in range(len(names)) if i not in held], dtype=np.int64)
            if split not in ("val", "test"):
                raise ValueError(f"unknown dataparser split {split!r}")
            other = "test" if split == "val" else "val"
            eval_file = present.get(split) or present.get(other)
            if eval_file is not None:
                return np.array(read(eval_file), dtype=np.int64)
            train = set(read(present["train"]))
            return np.array([i for i in range(len(names)) if i not in train], dtype=np.int64)
        mode = self.config.eval_mode
        if mode == "fraction":
            i_train, i_eval = get_train_eval_split_fraction(names, self.config.train_split_fraction)
        elif mode == "filename":
            i_train, i_eval = get_train_eval_split_filename(names)
        elif mode == "interval":
            i_train, i_eval = get_train_eval_split_interval(names, self.config.eval_interval)
        elif mode == "all":
            i_train, i_eval = get_train_eval_split_all(names)
        else:
            raise ValueError(f"unknown eval_mode {mode!r}")
        if split == "train":
            return np.asarray(i_train, dtype=np.int64)
        if split in ("val", "test"):
            return np.asarray(i_eval, dtype=np.int64)
        raise ValueError(f"unknown dataparser split {split!r}")

    # --- main -----------------------------------------------------------------------------------------
    def _parse_all(self) -> "_Parsed":
        """Everything that does not depend on the split, read once per parser (nerfstudio asks once per
        split): the model, the cameras and poses of all images, the image and mask files. Memoised on the
        parser by the model files' resolved paths and modification times."""
        model_dir = self._model_dir()
        files = [_model_file(model_dir, stem) for stem in ("cameras", "images")]
        key = tuple((p.resolve(), p.stat().st_mtime_ns if p.is_file() else None) for p in files)
        parsed = getattr(self, "_parsed", None)
        if parsed is not None and parsed.key == key:
            return parsed
        cfg = self.config
        data = Path(cfg.data)
        recon = _read_reconstruction(model_dir)

        images = [im for im in recon.images.values() if im.has_pose]
        if not images:
            raise ValueError(f"{model_dir}: the COLMAP model has no registered images (images with a pose)")
        images.sort(key=lambda im: im.name)
        names = [im.name for im in images]
        for im in images:  # text models were checked line by line; binary ones here
            if not np.isfinite(np.asarray(im.cam_from_world().matrix(), dtype=np.float64)).all():
                raise DatasetError(
                    f"geer: {_model_file(model_dir, 'images')}: image {im.image_id} '{im.name}': the pose "
                    "(quaternion / translation) has NaN or Inf entries; fix or remove this image"
                )

        # Cameras: validated once per COLMAP camera id.
        cameras_file = _model_file(model_dir, "cameras")
        cam_info: Dict[int, Tuple[ColmapCameraSpec, NerfstudioIntrinsics]] = {}
        for im in images:
            cid = int(im.camera_id)
            if cid not in cam_info:
                cam_info[cid] = _check_camera(recon.cameras[cid], cameras_file)
        if len(cam_info) > 1:
            # nerfstudio's FISHEYE624 ray generation handles only one 624 camera and no mixing (see docstring).
            for cid, (spec, ns_cam) in list(cam_info.items()):
                if ns_cam.camera_type == CameraType.FISHEYE624:
                    ns_cam = nerfstudio_intrinsics(
                        spec.model, spec.width, spec.height, spec.params, allow_fisheye624=False
                    )
                    cam_info[cid] = (spec._replace(nerfstudio_exact=False), ns_cam)

        located = colmap_files.locate_images(
            names, colmap_files.image_roots(data, cfg.images_path, model_dir), _model_file(model_dir, "images")
        )
        full_res = [root / rel for root, rel in located]
        df = self._downscale_factor(full_res[0])
        image_files = full_res if df == 1 else [_downscaled(root, df) / rel for root, rel in located]
        for root in {root for root, _ in located}:
            if df > 1 and not _downscaled(root, df).is_dir():
                raise FileNotFoundError(
                    f"downscaled image directory {_downscaled(root, df)} (downscale_factor={df}) does not exist; "
                    "create it (e.g. with ffmpeg or nerfstudio's colmap dataparser) or set downscale_factor 1"
                )
        mask_files: Optional[List[Path]] = None
        if cfg.masks_path is not None and (data / cfg.masks_path).is_dir():
            mask_dir = data / cfg.masks_path
            mask_dir = mask_dir if df == 1 else _downscaled(mask_dir, df)
            mask_files = [(mask_dir / rel).with_suffix(".png") for _, rel in located]

        # nerfstudio cameras at full resolution, then rescaled like nerfstudio does.
        ns = [cam_info[int(im.camera_id)][1] for im in images]
        n_dist = 12 if any(c.camera_type == CameraType.FISHEYE624 for c in ns) else 6
        dist = torch.zeros(len(ns), n_dist, dtype=torch.float32)
        for i, c in enumerate(ns):
            dist[i, : len(c.distortion)] = torch.tensor(c.distortion, dtype=torch.float32)
        c2w, transform, scale = self._poses(images)
        readouts = sfm_readouts(cfg.rolling_shutter, cfg.readout_time, cfg.frame_rate, names, c2w,
                                "geer-colmap --", [int(im.camera_id) for im in images])
        if readouts is not None:  # the model's poses are the images' mid-readout ones; cameras hold the starts
            c2w = readouts[0]
            CONSOLE.log(f"geer: {model_dir}: rolling shutter ({cfg.rolling_shutter}, {cfg.readout_time} s): each "
                        "image's motion during its readout estimated from its neighbours' poses")
        cams = Cameras(
            camera_to_worlds=c2w.float(),
            fx=torch.tensor([[c.fx] for c in ns], dtype=torch.float32),
            fy=torch.tensor([[c.fy] for c in ns], dtype=torch.float32),
            cx=torch.tensor([[c.cx] for c in ns], dtype=torch.float32),
            cy=torch.tensor([[c.cy] for c in ns], dtype=torch.float32),
            width=torch.tensor([[cam_info[int(im.camera_id)][0].width] for im in images], dtype=torch.int64),
            height=torch.tensor([[cam_info[int(im.camera_id)][0].height] for im in images], dtype=torch.int64),
            distortion_params=dist,
            camera_type=torch.tensor([[c.camera_type.value] for c in ns], dtype=torch.int64),
        )
        if df > 1:
            cams.rescale_output_resolution(1.0 / df, scale_rounding_mode=cfg.downscale_rounding_mode)

        specs: List[ColmapCameraSpec] = []
        for i, im in enumerate(images):
            spec = cam_info[int(im.camera_id)][0]
            w, h = int(cams.width[i, 0]), int(cams.height[i, 0])
            if df > 1:
                spec = _rescaled(spec, 1.0 / df, w, h)
            specs.append(spec)

        if cfg.check_image_sizes:  # headers and end markers only (dataset_checks.check_image_file)
            images_file = _model_file(model_dir, "images")
            for i, path in enumerate(image_files):
                where = f"{images_file}: image '{names[i]}' (COLMAP camera {specs[i].camera_id}" + (
                    f", downscaled by {df})" if df > 1 else ")")
                check_image_file(path, where, (specs[i].width, specs[i].height), size_fields="its camera's WIDTH x HEIGHT")
            for i, path in enumerate(mask_files or []):
                check_image_file(path, f"mask of image '{names[i]}'", (specs[i].width, specs[i].height), what="mask",
                                 size_fields="the image's size")

        model_ids = torch.tensor([[_model_id(s.model)] for s in specs], dtype=torch.int64)
        params = torch.zeros(len(specs), MAX_PARAMS, dtype=torch.float64)
        for i, s in enumerate(specs):
            params[i, : len(s.params)] = torch.tensor(s.params, dtype=torch.float64)
        distorted = torch.tensor([[any(v != 0 for v in c.distortion)] for c in ns], dtype=torch.bool)
        cams.metadata = {
            MODEL_ID_KEY: model_ids,
            PARAMS_KEY: params,
            NS_TYPE_KEY: cams.camera_type.clone(),
            DISTORTED_KEY: distorted,
            NS_INTRINSICS_KEY: torch.stack([getattr(cams, k)[:, 0].double() for k in ("fx", "fy", "cx", "cy")], -1),
            **({} if readouts is None else readouts[1]),
        }

        self._parsed = _Parsed(key, model_dir, recon, names, cams, specs, c2w, transform, scale, image_files,
                               mask_files, df)
        return self._parsed

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        cfg = self.config
        parsed = self._parse_all()
        _key, model_dir, recon, names, cams, specs, c2w, transform, scale, image_files, mask_files, df = parsed
        # Split (after orienting / scaling with all images, like nerfstudio).
        idx = self._split_indices(names, split)
        idx_t = torch.as_tensor(idx, dtype=torch.long)
        cams = cams[idx_t]

        if cfg.crop_radius is not None:
            cams.metadata["fisheye_crop_radius"] = float(cfg.crop_radius) / df  # read by the datamanager
        metadata: Dict = {GEER_CAMERAS_KEY: [specs[i] for i in idx]}
        if cfg.load_3D_points:
            metadata.update(_points(recon, transform, scale, model_dir))
            if "points3D_xyz" not in metadata:
                metadata.update(_frustum_seed([specs[i] for i in idx], c2w[idx_t], model_dir))

        n_inexact = sum(not specs[i].nerfstudio_exact for i in idx)
        if n_inexact:
            CONSOLE.log(
                f"[yellow]{n_inexact} image(s) use a COLMAP camera model nerfstudio cannot represent; the "
                "nerfstudio cameras hold a fitted approximation, geer renders the exact model"
            )
        aabb = cfg.scene_scale
        return DataparserOutputs(
            image_filenames=[image_files[i] for i in idx],
            cameras=cams,
            scene_box=SceneBox(aabb=torch.tensor([[-aabb] * 3, [aabb] * 3], dtype=torch.float32)),
            mask_filenames=[mask_files[i] for i in idx] if mask_files is not None else None,
            dataparser_transform=transform.float(),
            dataparser_scale=float(scale),
            metadata=metadata,
        )

    def _poses(self, images) -> Tuple[torch.Tensor, torch.Tensor, float]:
        """c2w [N,3,4] (OpenGL camera axes, float64), the 3x4 COLMAP-world -> output transform and the scale."""
        poses = []
        for im in images:
            w2c = np.eye(4)
            w2c[:3, :4] = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
            c2w = np.linalg.inv(w2c)
            c2w[0:3, 1:3] *= -1  # OpenCV camera axes -> OpenGL
            poses.append(c2w)
        poses_t = torch.from_numpy(np.stack(poses))
        applied = torch.eye(4, dtype=torch.float64)
        if self.config.assume_colmap_world_coordinate_convention:
            # nerfstudio's convention: COLMAP's gravity guess (-y) -> +z: (x, y, z) -> (x, z, -y).
            applied = applied[[0, 2, 1, 3]]
            applied[2] *= -1
        poses_t = applied @ poses_t
        # nerfstudio's orientation / centring (float32 only); apply its transform in float64.
        _, orient = camera_utils.auto_orient_and_center_poses(
            poses_t.float(), method=self.config.orientation_method, center_method=self.config.center_method
        )
        orient4 = torch.eye(4, dtype=torch.float64)
        orient4[:3] = orient.double()
        poses_t = orient4 @ poses_t
        scale = 1.0
        if self.config.auto_scale_poses:
            m = float(torch.max(torch.abs(poses_t[:, :3, 3])))
            scale = 1.0 / m if m > 0 else 1.0
        scale *= self.config.scale_factor
        poses_t[:, :3, 3] *= scale
        transform = (orient4 @ applied)[:3]
        return poses_t[:, :3, :4], transform, scale


geer_colmap_dataparser = DataParserSpecification(
    config=GeerColmapDataParserConfig(),
    description="COLMAP (pycolmap) dataset keeping the exact camera model (fisheye k4, FULL_OPENCV, FOV, thin prism)",
)


# ==================================================================================================
# helpers
# ==================================================================================================


def _downscaled(folder: Path, df: int) -> Path:
    return folder.parent / f"{folder.name}_{df}"


def _frustum_seed(specs: Sequence[ColmapCameraSpec], c2w: torch.Tensor, model_dir: Path) -> Dict[str, torch.Tensor]:
    """Seed points inside the frusta of all images (frustum_seed) when the model has no 3D points."""
    cams = [from_pycolmap(_pycolmap_camera(s.model, s.width, s.height, s.params, s.camera_id)) for s in specs]
    count = seed_count(len(cams))
    xyz, rgb = frustum_points(cams, c2w, count)
    CONSOLE.log(f"geer: {model_dir}: no 3D points; {count} seed points drawn inside the {len(cams)} camera frusta")
    return {"points3D_xyz": xyz, "points3D_rgb": rgb}


def _points(recon, transform: torch.Tensor, scale: float, model_dir: Path) -> Dict[str, torch.Tensor]:
    pts = [p for _, p in sorted(recon.points3D.items(), key=lambda kv: kv[0])]  # by point id, like nerfstudio
    if not pts:
        CONSOLE.log(f"[yellow]{model_dir}: no 3D points; models will not get seed points")
        return {}
    xyz = torch.from_numpy(np.stack([np.asarray(p.xyz, dtype=np.float64) for p in pts]))
    xyz = (xyz @ transform[:, :3].T + transform[:, 3]) * scale
    rgb = torch.from_numpy(np.stack([np.asarray(p.color, dtype=np.uint8) for p in pts]))
    return {
        "points3D_xyz": xyz.float(),
        "points3D_rgb": rgb,
        "points3D_error": torch.tensor([float(p.error) for p in pts], dtype=torch.float32),
        "points3D_num_points2D": torch.tensor([int(p.track.length()) for p in pts], dtype=torch.int64),
    }
