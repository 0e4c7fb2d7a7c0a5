"""nerfstudio's ``transforms.json`` parser, plus mixed rigs: per-frame ``camera_model`` and distortion.

nerfstudio 1.1.5 takes one ``camera_model`` for the whole file and reads a frame's distortion only when
the file has none at the top level, so a fisheye + pinhole capture cannot be described. This parser is
nerfstudio's (``Nerfstudio``: the same splits, orientation, centring, scaling, downscaling, masks, depth,
point cloud) with one step added after it: every frame may carry its own camera fields

    camera_model, fl_x, fl_y, cx, cy, w, h, k1, k2, k3, k4, p1, p2, distortion_params, fisheye_crop_radius

and a frame's own value wins over the top-level one (nerfstudio ignores a frame's value when the top level
has one; this parser says so once when a file relies on it). A file without such frame fields gives exactly
nerfstudio's cameras. ``Cameras.metadata`` gets two per-camera tensors: ``geer_camera_model`` (index into
``CAMERA_MODELS``, the name used to split metrics by camera kind) and ``geer_crop_radius`` (the fisheye crop
radius in pixels at the loaded resolution, 0 = none).

``dataparser_transforms``: map the poses into the frame of another run (its ``dataparser_transforms.json``)
instead of orienting, centring and scaling them anew; used to score a model on the cameras of another
transforms file of the same scene (geer_ns.eval_views).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, NamedTuple, Optional, Tuple, Type

import torch

from nerfstudio.cameras import camera_utils
from nerfstudio.cameras.cameras import CAMERA_MODEL_TO_TYPE, Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers import nerfstudio_dataparser
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig
from nerfstudio.data.utils.dataparsers_utils import (
    get_train_eval_split_all,
    get_train_eval_split_filename,
    get_train_eval_split_fraction,
    get_train_eval_split_interval,
)
from nerfstudio.plugins.registry_dataparser import DataParserSpecification
from nerfstudio.utils.rich_utils import CONSOLE

from geer_ns.data.dataset_checks import DatasetError, check_transforms_json
from geer_ns.data.rolling_shutter import READOUT_KEY, readout_metadata

__all__ = ["CAMERA_MODELS", "CAMERA_MODEL_KEY", "CROP_RADIUS_KEY", "GeerNerfstudio", "GeerNerfstudioDataParserConfig",
           "geer_nerfstudio_dataparser", "map_to_run_frame"]

CAMERA_MODELS = list(CAMERA_MODEL_TO_TYPE)
CAMERA_MODEL_KEY = "geer_camera_model"  # int64 [N, 1]: index into CAMERA_MODELS
CROP_RADIUS_KEY = "geer_crop_radius"  # float32 [N, 1]: fisheye crop radius in pixels, 0 = none
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_FRAME_CAMERA_KEYS = ("camera_model", *_INTRINSIC_KEYS, *_DISTORTION_KEYS, "distortion_params", "fisheye_crop_radius")
_FISHEYE_TYPES = (CameraType.FISHEYE, CameraType.FISHEYE624)


@dataclass
class GeerNerfstudioDataParserConfig(NerfstudioDataParserConfig):
    """nerfstudio-data (transforms.json) with per-frame camera_model, intrinsics and distortion."""

    _target: Type = field(default_factory=lambda: GeerNerfstudio)
    dataparser_transforms: Optional[Path] = None
    """A run's dataparser_transforms.json: map the poses into that run's frame (instead of orienting,
    centring and scaling them) to render that run's model at these cameras."""


_SPLIT_KEYS = ("train_filenames", "val_filenames", "test_filenames")


class _Parse(NamedTuple):
    key: tuple  # (resolved transforms.json, its modification time)
    meta: dict  # the checked file
    everything: DataparserOutputs  # every image; each split is a subset


@dataclass
class GeerNerfstudio(Nerfstudio):
    """nerfstudio's parser, then per-frame cameras (see the module docstring). The file is read, checked and
    parsed once per run, though nerfstudio asks once per split."""

    config: GeerNerfstudioDataParserConfig
    _parsed: Optional[_Parse] = field(default=None, init=False, repr=False)

    def transforms_path(self) -> Path:
        return self.config.data if self.config.data.suffix == ".json" else self.config.data / "transforms.json"

    def _generate_dataparser_outputs(self, split="train", **kwargs) -> DataparserOutputs:
        parsed = self.parse_once()
        return _subset(parsed.everything, self._split_indices(parsed.everything.image_filenames, parsed.meta, split))

    def parse_once(self) -> _Parse:
        """transforms.json checked (geer_ns.data.dataset_checks: one line naming file, frame and field) and
        parsed, memoized on the parser by the file's resolved path and modification time."""
        path = self.transforms_path()
        try:
            key = (path.resolve(), path.stat().st_mtime_ns)
        except OSError:
            key = (path, None)  # check_transforms_json says what is wrong
        if self._parsed is None or self._parsed.key != key:
            meta = check_transforms_json(path, self.config.auto_scale_poses)
            self._parsed = _Parse(key, meta, self._finish(self._nerfstudio_parse_all(meta), meta))
        return self._parsed

    def _nerfstudio_parse_all(self, meta: dict) -> DataparserOutputs:
        """nerfstudio's parse of every image. It orients, centers and scales with every pose whatever the split,
        so each split is a subset of this one parse. nerfstudio reads the file itself: it is handed the checked
        contents instead, without the split lists, and a split that keeps every image: eval_mode "fraction" with
        fraction 1.0, or "all" where the user's choice of "all" is what splits the file (no split lists): then,
        and only then, nerfstudio's warning about "all" (camera optimization may diverge) is printed, as
        nerfstudio's own parser would."""
        everything = {k: v for k, v in meta.items() if k not in _SPLIT_KEYS}
        own, read = self.config, nerfstudio_dataparser.load_from_json
        users_all = own.eval_mode == "all" and not any(k in meta for k in _SPLIT_KEYS)
        keep_all = {} if users_all else {"eval_mode": "fraction", "train_split_fraction": 1.0}
        self.config = dataclasses.replace(own, **keep_all)
        nerfstudio_dataparser.load_from_json = lambda _path: copy.deepcopy(everything)
        try:
            return super()._generate_dataparser_outputs("train")
        finally:
            self.config, nerfstudio_dataparser.load_from_json = own, read

    def _split_indices(self, filenames: List[Path], meta: dict, split: str) -> torch.Tensor:
        """nerfstudio's split of the sorted images (nerfstudio_dataparser): the file's split lists, else
        eval_mode."""
        if split not in ("train", "val", "test"):
            raise ValueError(f"Unknown dataparser split {split}")
        lists = [k for k in _SPLIT_KEYS if k in meta]
        if lists:
            path, key = self.transforms_path(), f"{split}_filenames"
            if key not in meta:
                raise DatasetError(f"geer: {path}: `{key}` is missing but the file lists its splits "
                                   f"({', '.join(lists)}); add `{key}` or remove the lists to split by eval_mode")
            names = {self._get_fname(Path(x), path.parent) for x in meta[key]}
            unmatched = sorted(str(n) for n in names.difference(filenames))
            if unmatched:
                raise DatasetError(f"geer: {path}: `{key}` names {len(unmatched)} file(s) that no frame has: "
                                   f"{', '.join(unmatched[:5])}; use the frames' `file_path` values")
            return torch.tensor([i for i, name in enumerate(filenames) if name in names], dtype=torch.long)
        cfg = self.config
        splits = {
            "fraction": lambda: get_train_eval_split_fraction(filenames, cfg.train_split_fraction),
            "filename": lambda: get_train_eval_split_filename(filenames),
            "interval": lambda: get_train_eval_split_interval(filenames, cfg.eval_interval),
            "all": lambda: get_train_eval_split_all(filenames),
        }
        if cfg.eval_mode not in splits:
            raise ValueError(f"Unknown eval mode {cfg.eval_mode}")
        i_train, i_eval = splits[cfg.eval_mode]()
        return torch.as_tensor(i_train if split == "train" else i_eval, dtype=torch.long)

    def _finish(self, outputs: DataparserOutputs, meta: dict) -> DataparserOutputs:
        path = self.transforms_path()
        frames = self._frames_of(outputs.image_filenames, meta, path)
        outputs.cameras = self._per_frame_cameras(outputs.cameras, meta, frames, path)
        # nerfstudio scales the positions by dataparser_scale without the file's applied_scale
        moved = float(outputs.dataparser_scale) / float(meta.get("applied_scale", 1.0))
        readouts = readout_metadata(meta, frames, path, moved)
        if readouts is not None:
            if self.config.dataparser_transforms is not None:
                raise DatasetError(f"geer: {path}: rolling-shutter frames cannot be mapped into another run's frame "
                                   "(dataparser_transforms) yet; score them in their own run")
            outputs.cameras.metadata = {**(outputs.cameras.metadata or {}), **readouts}
            rolling = int((readouts[READOUT_KEY] >= 0).sum())
            CONSOLE.log(f"geer: {path}: {rolling} of {len(frames)} frames have a rolling shutter: each of their rays "
                        "is rendered at its own readout time (the viewer and exports show the static scene)")
        if self.config.dataparser_transforms is not None:
            map_to_run_frame(outputs, self.config.dataparser_transforms, meta, path)
        return outputs

    def _frames_of(self, image_filenames: List[Path], meta: dict, path: Path) -> List[dict]:
        """The transforms.json frame of every output image (nerfstudio sorts and splits them)."""
        by_name = {self._get_fname(Path(f["file_path"]), path.parent): f for f in meta["frames"]}
        return [by_name[name] for name in image_filenames]

    def _per_frame_cameras(self, cameras: Cameras, meta: dict, frames: List[dict], path: Path) -> Cameras:
        own = [k for f in frames for k in _FRAME_CAMERA_KEYS if k in f and k in meta and f[k] != meta[k]]
        if own:
            CONSOLE.log(f"[yellow]geer: {path}: frames give their own {sorted(set(own))} as well as the top level; "
                        "each frame's own value is used (nerfstudio would ignore it)")
        specs = [_frame_camera(meta, f, path) for f in frames]
        names = [s[0] for s in specs]
        per_frame = any(k in f for f in frames for k in ("camera_model", *_DISTORTION_KEYS, "distortion_params",
                                                          "fisheye_crop_radius")) or own
        scale = 1.0 / float(self.downscale_factor)
        radius = torch.tensor([[s[3] * scale if CAMERA_MODEL_TO_TYPE[s[0]] in _FISHEYE_TYPES and s[3] else 0.0]
                               for s in specs], dtype=torch.float32)
        model_idx = torch.tensor([[CAMERA_MODELS.index(n)] for n in names], dtype=torch.int64)
        if per_frame:
            cameras = self._cameras_from_specs(cameras, specs)
            kinds = sorted(set(names))
            if len(kinds) > 1:
                CONSOLE.log(f"geer: {path}: mixed rig, {', '.join(f'{names.count(k)} {k}' for k in kinds)} frames")
        cameras.metadata = {**(cameras.metadata or {}), CAMERA_MODEL_KEY: model_idx, CROP_RADIUS_KEY: radius}
        return cameras

    def _cameras_from_specs(self, cameras: Cameras, specs: List[tuple]) -> Cameras:
        """nerfstudio Cameras with every frame's own type, intrinsics and distortion (same poses)."""
        n_dist = max(len(s[2]) for s in specs)
        dist = torch.zeros(len(specs), n_dist)
        for i, s in enumerate(specs):
            dist[i, : len(s[2])] = s[2]
        intr = torch.tensor([s[1] for s in specs], dtype=torch.float64)
        out = Cameras(
            camera_to_worlds=cameras.camera_to_worlds,
            fx=intr[:, 0:1].float(), fy=intr[:, 1:2].float(), cx=intr[:, 2:3].float(), cy=intr[:, 3:4].float(),
            width=intr[:, 4:5].long(), height=intr[:, 5:6].long(),
            distortion_params=dist,
            camera_type=torch.tensor([[CAMERA_MODEL_TO_TYPE[s[0]].value] for s in specs], dtype=torch.int64),
            metadata={k: v for k, v in (cameras.metadata or {}).items() if k != "fisheye_crop_radius"},
        )
        out.rescale_output_resolution(scaling_factor=1.0 / float(self.downscale_factor))
        return out


def _frame_camera(meta: dict, frame: dict, path: Path) -> Tuple[str, List[float], torch.Tensor, Optional[float]]:
    """(camera_model, [fx, fy, cx, cy, w, h], distortion_params, fisheye_crop_radius) of one frame."""
    where = f"{path}: frame {frame.get('file_path')!r}"

    def get(key: str, default=None):
        return frame[key] if key in frame else meta.get(key, default)

    name = get("camera_model", "OPENCV")
    if name not in CAMERA_MODEL_TO_TYPE:
        raise ValueError(f"{where}: camera_model {name!r} is not one of {', '.join(CAMERA_MODELS)}")
    intrinsics = []
    for key in _INTRINSIC_KEYS:
        value = get(key)
        if value is None:
            raise ValueError(f"{where}: {key} is missing (neither in the frame nor at the top level)")
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"{where}: {key} must be a finite number, got {value!r}")
        intrinsics.append(float(value))
    # The frame's own distortion, when it gives any, replaces the top level's as a whole.
    source = frame if any(k in frame for k in (*_DISTORTION_KEYS, "distortion_params")) else meta
    if "distortion_params" in source:
        dist = torch.tensor(source["distortion_params"], dtype=torch.float32)
    else:
        dist = camera_utils.get_distortion_params(**{k: float(source.get(k, 0.0)) for k in _DISTORTION_KEYS})
    return name, intrinsics, dist, get("fisheye_crop_radius")


def _subset(outputs: DataparserOutputs, idx: torch.Tensor) -> DataparserOutputs:
    """The images `idx` of a parse: their files, cameras and depth files; the rest is shared."""
    keep = idx.tolist()

    def pick(files):
        return None if files is None else [files[i] for i in keep]

    metadata = dict(outputs.metadata)
    if metadata.get("depth_filenames") is not None:
        metadata["depth_filenames"] = pick(metadata["depth_filenames"])
    return dataclasses.replace(outputs, image_filenames=pick(outputs.image_filenames), cameras=outputs.cameras[idx],
                               mask_filenames=pick(outputs.mask_filenames), metadata=metadata)


def map_to_run_frame(outputs: DataparserOutputs, transforms_json: Path, meta: dict, path: Path) -> None:
    """Re-express the poses (and transform, scale) of `outputs` in the output frame of another run.

    Both parsers map the file's coordinates x to out = s (R x + t) (dataparser_transform [R|t], scale s), so
    a pose in this parse's frame goes back to the file's coordinates and forward into the run's frame.
    """
    if "applied_scale" in meta:
        raise ValueError(f"{path}: applied_scale is not supported when mapping into another run's frame")
    try:
        run = json.loads(Path(transforms_json).read_text())
        run_t, run_s = torch.tensor(run["transform"], dtype=torch.float64), float(run["scale"])
    except (OSError, ValueError, KeyError) as err:
        raise ValueError(f"{transforms_json}: not a dataparser_transforms.json with 'transform' and 'scale' ({err})")
    own_t, own_s = outputs.dataparser_transform.double(), float(outputs.dataparser_scale)
    c2w = outputs.cameras.camera_to_worlds.double()
    rot = own_t[:3, :3].T @ c2w[..., :3, :3]
    pos = (own_t[:3, :3].T @ (c2w[..., :3, 3:] / own_s - own_t[:3, 3:]))
    new = torch.cat([run_t[:3, :3] @ rot, run_s * (run_t[:3, :3] @ pos + run_t[:3, 3:])], -1)
    outputs.cameras.camera_to_worlds = new.to(outputs.cameras.camera_to_worlds.dtype)
    outputs.dataparser_transform = run_t[:3].float()
    outputs.dataparser_scale = run_s


geer_nerfstudio_dataparser = DataParserSpecification(
    config=GeerNerfstudioDataParserConfig(),
    description="nerfstudio-data (transforms.json) with per-frame camera_model, intrinsics and distortion (mixed rigs)",
)
