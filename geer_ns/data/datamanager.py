"""Full-image datamanager for geer: no undistortion, training views cached as BEAP images.

nerfstudio's FullImageDatamanager undistorts fisheye images (cv2.fisheye, balance 0: the periphery is
cropped) and then treats every camera as a pinhole. geer renders any camera exactly, so here:

* every image keeps its camera type, distortion and size;
* every image gets a validity mask: camera-valid, ``mask_path`` mask, fisheye crop circle
  (``fisheye_crop_radius``, or, for a fisheye without either, the image circle detected from its images);
* training views are cached in the view each camera is supervised in (geer_ns.data.view_choice: BEAP,
  resampled once into the camera's BEAP grid, the same grid object the model renders, or native rays for
  a camera whose rays reach 90 degrees); the choice and the pixel counts are said once at start-up;
* eval views stay in native pixels with their validity mask, so metrics are computed where the camera
  really saw something;
* images are cached as uint8 and masks as bool, on the GPU when there is one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple, Type

import cv2
import numpy as np
import torch

from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.configs.dataparser_configs import AnnotatedDataParserUnion
from nerfstudio.data.dataparsers.base_dataparser import DataParserConfig
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.utils.io import load_from_json
from nerfstudio.utils.rich_utils import CONSOLE

from geer_ns import resume
from geer_ns.cameras import CameraModel
from geer_ns.data.beap import resample_to_beap
from geer_ns.data.dataset_checks import check_transforms_json
from geer_ns.data.depth import TARGET_KEY, sensor_distance
from geer_ns.data.image_circle import detect_image_circle_from_files
from geer_ns.data.nerfstudio_parser import CROP_RADIUS_KEY, GeerNerfstudio, GeerNerfstudioDataParserConfig
from geer_ns.data.view_choice import AUTO_REASON, Supervision, SupervisionReport, beap_covered, choose_view
from geer_ns.data.ply import read_ply_points
from geer_ns.data.views import HOST_MODEL_KEY, beap_view, camera_kind, camera_model, native_view

# Key of Cameras.metadata telling the model in which view a training batch is supervised.
VIEW_KEY = "geer_view"


@dataclass
class GeerDataOptions:
    """geer's own datamanager options, listed first in `ns-train geer --help` (see geer_ns.options.GeerOwnOptions:
    a base after FullImageDatamanagerConfig comes first in the reversed MRO dataclasses collect fields along)."""

    supervision: Supervision = "auto"
    """Training view of every camera: "auto" = its native pixel rays (measured ahead of BEAP:
    geer_ns/data/view_choice.py), "native" the same, "beap" the paper's BEAP images resampled from the captures."""
    mask_edge_fill: int = 2
    """Pixel rings extrapolated beyond the validity mask before BEAP resampling, so that BEAP cells at the
    edge of the image circle (whose bilinear footprint touches the first invalid pixel) stay supervised."""
    image_circle_margin: float = 2.0
    """Pixels kept inside an automatically detected fisheye image circle (its rim pixels are blended)."""
    load_seed_points: bool = True
    """Seed Gaussians from the dataset's point cloud (nerfstudio-data `ply_file_path`)."""
    images_per_step: int = 1
    """Training images each process renders per step; their losses are averaged (gsplat's batch_size). The
    effective batch is this times the number of processes, and step counts scale with it (README: several
    processes and images per step)."""


@dataclass
class GeerDataManagerConfig(FullImageDatamanagerConfig, GeerDataOptions):
    _target: Type = field(default_factory=lambda: GeerDataManager)
    dataparser: AnnotatedDataParserUnion = field(
        default_factory=lambda: GeerNerfstudioDataParserConfig(load_3D_points=False))
    """Dataset parser: nerfstudio's transforms.json parser plus per-frame camera_model (mixed rigs). Its
    load_3D_points stays off (it needs open3d); the seed points are read by this datamanager instead."""
    cache_images_type: Literal["uint8", "float32"] = "uint8"


def check_data_path(config: GeerDataManagerConfig) -> None:
    """Fail early, naming the path, instead of deep inside a dataparser."""
    data = config.data if config.data is not None else config.dataparser.data
    path = Path(data).expanduser()
    if not path.exists():
        raise FileNotFoundError(f"geer: --data {path} does not exist")
    if isinstance(config.dataparser, NerfstudioDataParserConfig) and path.is_dir():
        if not (path / "transforms.json").is_file():
            raise FileNotFoundError(
                f"geer: --data {path} has no transforms.json (nerfstudio-data format expected; "
                "for a COLMAP reconstruction choose the colmap dataparser)"
            )
    if isinstance(config.dataparser, NerfstudioDataParserConfig) and not isinstance(
            config.dataparser, GeerNerfstudioDataParserConfig):  # geer's parser checks the file in its one parse
        # Broken files: one line naming file, frame and field, before anything is parsed or cached.
        check_transforms_json(path if path.suffix == ".json" else path / "transforms.json",
                              config.dataparser.auto_scale_poses)


def native_valid_mask(camera: CameraModel, mask: Optional[torch.Tensor], crop_radius: Optional[float],
                      circle: Optional[np.ndarray] = None) -> torch.Tensor:
    """[H, W] bool: pixels the camera model can unproject, inside `mask`, inside the fisheye crop circle and
    inside the detected image `circle` mask."""
    valid = native_view(camera).rays.valid.reshape(camera.height, camera.width).cpu()  # cached per intrinsics
    if mask is not None:
        valid = valid & mask.reshape(valid.shape).bool().cpu()
    if circle is not None:
        valid = valid & torch.from_numpy(circle)
    if crop_radius is not None and hasattr(camera, "cx"):
        uv = camera.pixel_centers(torch.float64)
        r2 = (uv[..., 0] - camera.cx) ** 2 + (uv[..., 1] - camera.cy) ** 2
        valid = valid & (r2 <= crop_radius**2)
    return valid


def extend_beyond_mask(image: np.ndarray, valid: np.ndarray, rings: int) -> Tuple[np.ndarray, np.ndarray]:
    """Grow `valid` by `rings` pixels, filling each new pixel with the mean of its valid 8-neighbors.

    BEAP resampling is bilinear and only keeps cells whose whole footprint is valid; without this the
    outermost cells of a fisheye circle would be dropped although their centers lie inside it.
    """
    img = image.astype(np.float32).copy()
    ok = valid.copy()
    kernel = np.ones((3, 3), np.uint8)
    for _ in range(rings):
        grown = cv2.dilate(ok.astype(np.uint8), kernel).astype(bool)
        ring = grown & ~ok
        if not ring.any():
            break
        count = cv2.boxFilter(ok.astype(np.float32), -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        weighted = img * ok[..., None]
        total = np.stack(
            [cv2.boxFilter(weighted[..., c], -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
             for c in range(img.shape[-1])], -1)
        img[ring] = total[ring] / count[ring][:, None]
        ok = grown
    return img, ok


def to_beap(image: torch.Tensor, camera: CameraModel, valid: torch.Tensor, rings: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """Native image [H,W,C] (uint8 or float) -> (BEAP image float [h,w,C] in [0,1], valid [h,w])."""
    img = image.float().numpy() / (255.0 if image.dtype == torch.uint8 else 1.0)
    img, ok = extend_beyond_mask(img, valid.numpy(), rings)
    return resample_to_beap(torch.from_numpy(img), camera, beap_view(camera).grid, torch.from_numpy(ok))


def pin_if_possible(tensor: torch.Tensor) -> torch.Tensor:
    """A pinned copy for fast host-to-GPU copies where a GPU exists, else the tensor itself: nerfstudio's
    FullImageDatamanager(cache_images="cpu") pins unconditionally, which raises "Found no NVIDIA driver" with a
    CUDA build of torch on a machine without a GPU."""
    if torch.cuda.is_available() and tensor.device.type == "cpu":
        return tensor.pin_memory()
    return tensor


def as_cache_type(image: torch.Tensor, cache_type: str) -> torch.Tensor:
    if cache_type == "uint8":
        return image if image.dtype == torch.uint8 else (image.clamp(0, 1) * 255.0).round().to(torch.uint8)
    return image.float() / 255.0 if image.dtype == torch.uint8 else image.float()


class GeerDataManager(FullImageDatamanager):
    config: GeerDataManagerConfig

    def __init__(self, config: GeerDataManagerConfig, *args, **kwargs):
        check_data_path(config)
        if isinstance(config.dataparser, NerfstudioDataParserConfig) and config.dataparser.load_3D_points:
            # nerfstudio would import open3d (broken on hosts without libusb); we read the PLY ourselves.
            config.dataparser.load_3D_points = False
            config.load_seed_points = True
        # Set before nerfstudio's __init__, which may cache the images (like FullImageDatamanager's own fields).
        self._circles: Dict[CameraModel, Optional[np.ndarray]] = {}  # detected image circle per camera
        self._report: Dict[str, SupervisionReport] = {}  # per split, filled while caching the images
        super().__init__(config, *args, **kwargs)
        self.train_cameras = self.train_dataset.cameras  # set here, not only by the image cache (on the device there)
        if config.load_seed_points:
            self._add_seed_points()

    # ---------------------------------------------------------------------------------- seed points
    def _transforms_meta(self) -> Tuple[Path, Optional[dict]]:
        """transforms.json and its contents (geer's parser's one read; None when there is no such file)."""
        data = Path(self.config.dataparser.data)
        meta_path = data if data.suffix == ".json" else data / "transforms.json"
        if isinstance(self.dataparser, GeerNerfstudio):
            return meta_path, self.dataparser.parse_once().meta
        return meta_path, load_from_json(meta_path) if meta_path.is_file() else None

    def _ply_path(self) -> Optional[Path]:
        meta_path, meta = self._transforms_meta()
        rel = None if meta is None else meta.get("ply_file_path")
        return None if rel is None else meta_path.parent / rel

    def _ply_transform(self) -> torch.Tensor:
        """[3, 4] from the PLY's frame to the dataparser's output frame.

        The PLY is in the frame of transforms.json's poses (ns-process-data writes it there). nerfstudio's
        dataparser_transform also contains `applied_transform` (original data -> that frame), which nerfstudio
        itself leaves out when it loads the PLY; so do we, including its legacy colmap/sparse/0 default.
        """
        outputs = self.train_dataparser_outputs
        transform = outputs.dataparser_transform.double()
        data = Path(self.config.dataparser.data)
        applied = self._transforms_meta()[1].get("applied_transform")
        if applied is None and (data / "colmap/sparse/0").exists():
            applied = [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]]  # nerfstudio_dataparser's legacy value
        if applied is None:
            return transform
        square = torch.eye(4, dtype=torch.float64)
        square[:3] = torch.tensor(applied, dtype=torch.float64)
        return transform @ torch.linalg.inv(square)

    def _add_seed_points(self) -> None:
        metadata = self.train_dataparser_outputs.metadata
        if "points3D_xyz" in metadata:
            return
        ply = self._ply_path()
        if ply is None or not ply.is_file():
            CONSOLE.print("[yellow]geer: no seed point cloud found; splatfacto's random initialization is used")
            return
        xyz, rgb = read_ply_points(ply)
        outputs = self.train_dataparser_outputs
        pts = torch.from_numpy(xyz)
        pts = (torch.cat([pts, torch.ones_like(pts[:, :1])], -1).double() @ self._ply_transform().T).float()
        metadata["points3D_xyz"] = pts * float(outputs.dataparser_scale)
        metadata["points3D_rgb"] = torch.from_numpy(rgb)
        CONSOLE.log(f"geer: {len(xyz)} seed points from {ply}")

    # ---------------------------------------------------------------------------------- image cache
    def _image_circle(self, dataset, idx: int, camera: CameraModel) -> Optional[np.ndarray]:
        """The detected image circle of a fisheye camera that has neither masks nor fisheye_crop_radius
        (detected once per camera from its train and eval images, said once); None for every other camera."""
        circles = self._circles
        if camera in circles:
            return circles[camera]
        files = [f for ds in (self.train_dataset, self.eval_dataset) for i, f in enumerate(ds.image_filenames)
                 if camera_model(ds.cameras, i) == camera]
        circle = detect_image_circle_from_files(files)
        name = camera_kind(dataset.cameras, idx)
        if circle is None:
            CONSOLE.log(f"geer: {name} {camera.width}x{camera.height} has no mask and no fisheye_crop_radius, and "
                        f"its images show no black border: every pixel the model can unproject is used")
            circles[camera] = None
        else:
            mask = circle.mask(camera.width, camera.height, self.config.image_circle_margin)
            CONSOLE.log(f"geer: {name} {camera.width}x{camera.height} has no mask and no fisheye_crop_radius: image "
                        f"circle detected from its images, center ({circle.cx:.1f}, {circle.cy:.1f}), radius "
                        f"{circle.radius:.1f} px; the {int((~mask).sum())} pixels outside it (less "
                        f"{self.config.image_circle_margin:g} px) never enter the loss or the metrics")
            circles[camera] = mask
        return circles[camera]

    def _valid_mask(self, dataset, idx: int, camera: CameraModel, mask: Optional[torch.Tensor]) -> torch.Tensor:
        radius = _crop_radius(dataset.cameras, idx)
        circle = None
        if mask is None and radius is None and _is_fisheye(dataset.cameras, idx):
            circle = self._image_circle(dataset, idx, camera)
        return native_valid_mask(camera, mask, radius, circle)

    def _load_view(self, dataset, idx: int, split: str) -> Dict[str, torch.Tensor]:
        data = dataset.get_data(idx, image_type=self.config.cache_images_type)
        camera = camera_model(dataset.cameras, idx)
        image = data["image"]
        if tuple(image.shape[:2]) != (camera.height, camera.width):
            raise ValueError(
                f"{dataset.image_filenames[idx]}: image size (h, w) {tuple(image.shape[:2])} does not match "
                f"its camera's height/width ({camera.height}, {camera.width})"
            )
        seen = self._valid_mask(dataset, idx, camera, data.get("mask"))
        view = "native" if split == "eval" else choose_view(self.config.supervision)
        valid, supervised = seen, seen
        if view == "beap":
            image, valid = to_beap(image, camera, seen, self.config.mask_edge_fill)
            supervised = beap_covered(camera, seen, valid)
        name = f"{camera_kind(dataset.cameras, idx)} {camera.width}x{camera.height}"
        self._report[split].add(name, camera, view, seen, supervised)
        data["image"] = as_cache_type(image, self.config.cache_images_type)
        data["mask"] = valid[..., None]
        if dataset.metadata.get("depth_filenames"):  # depth supervision (geer_ns/data/depth.py)
            scale = float(dataset._dataparser_outputs.dataparser_scale)
            data[TARGET_KEY] = sensor_distance(dataset.cameras, idx, camera, dataset.metadata, scale,
                                               self._ply_transform(), view)
        if split == "train":
            data[VIEW_KEY] = view  # moved onto the batch's camera by next_train
        return data

    def _load_images(self, split: Literal["train", "eval"], cache_images_device: Literal["cpu", "gpu"]) -> List[Dict[str, torch.Tensor]]:
        dataset = self.train_dataset if split == "train" else self.eval_dataset
        self._report[split] = SupervisionReport()
        CONSOLE.log(f"geer: caching {len(dataset)} {split} images (no undistortion)")
        views = [self._load_view(dataset, i, split) for i in range(len(dataset))]
        verb = "supervised" if split == "train" else "scored"
        if split == "train" and self.config.supervision == "auto":
            CONSOLE.log(f"geer: {AUTO_REASON}")
        for line in self._report[split].lines(verb):
            CONSOLE.log(f"geer: {split} images, {line}")
        on_gpu = cache_images_device == "gpu" and torch.device(self.device).type == "cuda"
        for view in views:
            for key in ("image", "mask", "depth_image", TARGET_KEY):
                if key in view:
                    view[key] = view[key].to(self.device) if on_gpu else pin_if_possible(view[key])
        self.train_cameras = self.train_dataset.cameras.to(self.device) if on_gpu else self.train_dataset.cameras
        return views

    # Saved with checkpoints so that a resumed run draws the same images next (docs/training.md, resume).
    def get_extra_state(self) -> Dict:
        return resume.sampler_state(self)

    def set_extra_state(self, state: Dict) -> None:
        resume.restore_sampler_state(self, state)

    def use_eval_views(self, dataparser: DataParserConfig, split: str = "test") -> None:
        """Score at other cameras (geer-eval): the eval dataset becomes `dataparser`'s `split`."""
        self.dataparser = dataparser.setup()
        self.test_split = split
        self.eval_dataset = self.create_eval_dataset()
        self.eval_unseen_cameras = list(range(len(self.eval_dataset)))
        self.__dict__.pop("cached_eval", None)  # reloaded (and reported) on first use

    def supervision_report(self, split: Literal["train", "eval"] = "train") -> SupervisionReport:
        """Per camera: view, images, valid and supervised native pixels (loads the images if not yet)."""
        _ = self.cached_train if split == "train" else self.cached_eval
        return self._report[split]

    def next_train(self, step: int) -> Tuple[Cameras, Dict]:
        return self.train_view(self.next_train_indices(1)[0])

    def next_train_indices(self, count: int) -> List[int]:
        """The next `count` training images of the queue (nerfstudio's: each epoch a permutation, drawn from
        train_cameras_sampling_seed). Every process holds the same queue, so processes that each take their
        share of one call's indices see disjoint images, and an epoch still visits every image once."""
        indices = []
        for _ in range(count):
            indices.append(self.train_unseen_cameras.pop(0))
            if not self.train_unseen_cameras:
                self.train_unseen_cameras = self.sample_train_cameras()
        return indices

    def train_view(self, index: int) -> Tuple[Cameras, Dict]:
        """Training image `index` as nerfstudio's next_train gives it (a one-camera batch, its image on the
        device, `cam_idx`), with the view it is supervised in."""
        data = dict(self.cached_train[index])  # a copy: the cache is not mutated (nerfstudio's is)
        data["image"] = data["image"].to(self.device)
        data.pop(VIEW_KEY)
        return self.train_camera(index), data

    def train_camera(self, index: int) -> Cameras:
        """Training camera `index` (`cam_idx` and the view it is supervised in), without its image."""
        camera = self.train_cameras[index : index + 1].to(self.device)
        camera.metadata = dict(camera.metadata or {})
        camera.metadata["cam_idx"] = index
        camera.metadata[VIEW_KEY] = self.cached_train[index][VIEW_KEY]
        camera.metadata[HOST_MODEL_KEY] = camera_model(self.train_dataset.cameras, index)  # the host copy: no sync
        return camera


def _is_fisheye(cameras: Cameras, idx: int) -> bool:
    return int(cameras.camera_type.reshape(-1)[idx]) in (CameraType.FISHEYE.value, CameraType.FISHEYE624.value)


def _crop_radius(cameras: Cameras, idx: int) -> Optional[float]:
    """The fisheye crop radius of camera `idx`: geer's per-camera value (mixed rigs), else nerfstudio's."""
    meta = cameras.metadata or {}
    if CROP_RADIUS_KEY in meta:
        radius = float(meta[CROP_RADIUS_KEY].reshape(-1)[idx])
        return radius if radius > 0 else None
    radius = meta.get("fisheye_crop_radius")
    return float(radius) if radius is not None else None
