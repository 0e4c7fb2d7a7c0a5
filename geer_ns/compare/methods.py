"""The methods geer-compare trains: each one's nerfstudio config, the capture it trains on and the camera its
test renders are in (to be brought back to the capture's own pixels)."""

from __future__ import annotations

import copy
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from geer_ns.compare.capture import Capture, write_resampled
from geer_ns.compare.resample import equidistant_like, widest_pinhole
from geer_ns.errors import OptionError

METHODS = ("geer", "geer-native", "geer-beap", "geer-gsplat-units", "geer-reference-units", "geer-capped", "geer-mcmc",
           "splatfacto", "splatfacto-pinhole", "splatfacto-fisheye")
DEFAULT_METHODS = ("geer", "splatfacto", "splatfacto-pinhole", "splatfacto-fisheye")


@dataclass
class Method:
    name: str
    description: str
    data: Path  # the transforms.json it trains on
    config: object  # nerfstudio TrainerConfig
    render_camera: Optional[str]  # None: its test renders are the capture's own pixels; "pinhole" / "equidistant"


def gsplat_units(model):
    """`model` (a GeerModelConfig) at splatfacto's density: its statistics in gsplat's units (densify-units image,
    the default: halves of each camera's own image, geer_ns/densify/signal.py), so the same Gaussians cross
    splatfacto's thresholds, and geer's two extra rules (min pixels, unseen prune) off."""
    model.densify_units = "image"
    model.densify_min_pixels, model.prune_unseen = 0.0, False
    return model


def config_digest(method: Method) -> str:
    """A fingerprint of what the method trains: its nerfstudio config as planned (every option and default, no
    paths), the bytes of the transforms file it trains on (intrinsics, poses, splits: a resampled capture's too)
    and the camera it renders in. A table whose runs carry today's digest was made with today's options and
    defaults (geer-compare --keep-finished)."""
    import yaml

    config = copy.deepcopy(method.config)
    config.data = None
    config.pipeline.datamanager.data = None
    config.pipeline.datamanager.dataparser.data = Path(".")
    data = hashlib.sha256(method.data.read_bytes()).hexdigest()
    text = yaml.dump(config) + f"\n{data}\n{method.render_camera}"
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def plan(capture: Capture, names: Tuple[str, ...], work: Path, pinhole_fov_deg: float,
         max_gaussians: int = 0) -> Tuple[List[Method], Dict[str, str]]:
    """The methods to train on this capture, and the ones that do not apply with the reason. `max_gaussians` is
    geer-capped's cap (required by it, used by no other method)."""
    import torch

    from geer_ns.compare.splatfacto import splatfacto_trainer_config
    from geer_ns.config import geer_trainer_config
    from geer_ns.model import GeerModelConfig

    unknown = [n for n in names if n not in METHODS]
    if unknown:
        raise OptionError(f"geer-compare: unknown method(s) {unknown}; choose from {list(METHODS)}")
    if "geer-capped" in names and max_gaussians < 1:
        raise OptionError(f"geer-compare: --max-gaussians {max_gaussians}: the method geer-capped needs its cap, "
                          "a positive count (e.g. the fewest Gaussians of splatfacto's runs)")
    gpu = torch.cuda.is_available()
    raster = "gsplat's CUDA kernels" if gpu else "gsplat's EWA rasterization on the CPU (geer_ns.compare.ewa_cpu)"
    distorted = any(float(capture.meta.get(k, 0.0)) != 0.0 for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
    methods, skipped = [], {}
    for name in names:
        if name == "geer":
            methods.append(Method(name, "3DGEER, exact rendering of the capture's own camera", capture.transforms,
                                  geer_trainer_config("geer", GeerModelConfig()), None))
        elif name in ("geer-native", "geer-beap"):  # geer on the capture's own pixels, or on BEAP resamples
            view = name.removeprefix("geer-")
            config = geer_trainer_config(name, GeerModelConfig())
            config.pipeline.datamanager.supervision = view
            what = "the capture's own pixel rays" if view == "native" else "BEAP images resampled from the capture"
            methods.append(Method(name, f"3DGEER supervised on {what} (--pipeline.datamanager.supervision {view})",
                                  capture.transforms, config, None))
        elif name == "geer-gsplat-units":
            methods.append(Method(name, "3DGEER densified by splatfacto's rules in gsplat's units at this image size "
                                  "(--pipeline.model.densify-units image, no min-pixels or unseen-prune rule): "
                                  "splatfacto's density", capture.transforms,
                                  geer_trainer_config(name, gsplat_units(GeerModelConfig())), None))
        elif name == "geer-reference-units":
            methods.append(Method(name, "3DGEER densified in pixels of the 300-pixel reference camera "
                                  "(--pipeline.model.densify-units reference, geer's default before "
                                  "benchmarks/densify_default.md)", capture.transforms,
                                  geer_trainer_config(name, GeerModelConfig(densify_units="reference")), None))
        elif name == "geer-capped":  # an equal-count row: geer's defaults, densification stopped at the cap
            methods.append(Method(name, f"3DGEER with at most {max_gaussians:,} Gaussians (--pipeline.model."
                                  f"max-gaussians {max_gaussians}: the strongest densification candidates first)",
                                  capture.transforms,
                                  geer_trainer_config(name, GeerModelConfig(max_gaussians=max_gaussians)), None))
        elif name == "geer-mcmc":
            methods.append(Method(name, "3DGEER with gsplat's MCMCStrategy", capture.transforms,
                                  geer_trainer_config("geer-mcmc", GeerModelConfig(strategy="mcmc")), None))
        elif name == "splatfacto":
            what = ("nerfstudio undistorts the images to a cropped pinhole (cv2, balance 0)" if distorted else
                    "nerfstudio passes the images through and splatfacto renders them as a pinhole"
                    if capture.is_fisheye else "pinhole images")
            methods.append(Method(name, f"splatfacto as shipped: {what}; {raster}", capture.transforms,
                                  splatfacto_trainer_config("pinhole"), "pinhole" if distorted else None))
        elif not capture.is_fisheye:
            skipped[name] = "the capture is not a fisheye"
        elif name == "splatfacto-pinhole":
            target = widest_pinhole(capture.camera, pinhole_fov_deg)
            data = write_resampled(capture, target, "OPENCV", work / "data" / f"pinhole_{pinhole_fov_deg:g}deg")
            methods.append(Method(name, f"splatfacto on the capture undistorted to a {pinhole_fov_deg:g}-degree pinhole "
                                  f"(same poses and splits); {raster}", data, splatfacto_trainer_config("pinhole"),
                                  "pinhole"))
        elif name == "splatfacto-fisheye":
            data, render = capture.transforms, None
            if not capture.is_equidistant:
                data = write_resampled(capture, equidistant_like(capture.camera), "OPENCV_FISHEYE",
                                       work / "data" / "equidistant")
                render = "equidistant"
            methods.append(Method(name, "splatfacto with gsplat's fisheye EWA projection (camera_model=\"fisheye\", "
                                  f"equidistant; FisheyeGS-like); {raster}", data,
                                  splatfacto_trainer_config("fisheye"), render))
    return methods, skipped
