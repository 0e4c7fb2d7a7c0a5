"""geer-compare's outputs: one table (markdown and JSON, with the protocol) and one picture (PNG)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import cv2
import numpy as np
import torch

from geer_ns.compare.capture import Capture
from geer_ns.compare.resample import to_uint8
from geer_ns.compare.run import Result

COLUMNS = (  # (header, key in Result.metrics or attribute, format)
    ("PSNR (full FoV)", "psnr", "{:.2f}"),
    ("SSIM", "ssim", "{:.3f}"),
    ("LPIPS", "lpips", "{:.3f}"),
    ("central PSNR", "central_psnr", "{:.2f}"),
    ("peripheral PSNR", "peripheral_psnr", "{:.2f}"),
    ("covered", "covered", "{:.1%}"),
    ("PSNR (covered px)", "covered_psnr", "{:.2f}"),
)


def protocol(capture: Capture, central_half_angle_deg: float, steps: int, lpips_reason: str,
             seeds: Sequence[int] = (42,)) -> List[str]:
    cam = capture.camera
    return [
        f"Capture: `{capture.transforms}`, {capture.meta.get('camera_model', 'OPENCV')} {cam.width}x{cam.height}, "
        f"{len(capture.views)} test views (the file's test split).",
        f"Every method trains {steps} steps with nerfstudio's trainer on the same training images and poses, once "
        f"per seed ({', '.join(map(str, seeds))}), with the same schedule options (docs/compare.md), and is scored "
        "on the same test images at the capture's own camera and pixels (each method's test split checked to be "
        "the capture's poses). A cell is the mean over the seeds, +- the half-width of its 95 % interval (Student's "
        "t) with two seeds or more.",
        "Scored pixels: the capture's valid pixels (inside the camera model's domain, the image mask and the fisheye "
        "crop circle), the same set for every method. Full-FoV PSNR / SSIM / LPIPS use all of them (SSIM / LPIPS "
        "with the pixels outside set to the ground truth).",
        "A method that renders another camera (the undistorted pinhole) has its render resampled by rays to the "
        "capture's pixels; the valid pixels it cannot see (lost periphery) keep its background color and count "
        "in the full-FoV metrics; `covered` is the share of valid pixels it sees, `PSNR (covered px)` its PSNR on "
        "those alone.",
        f"Central region: rays within +-{central_half_angle_deg:g} degrees of the optical axis horizontally and "
        "vertically (paper App. G rectangle); peripheral: the other valid pixels.",
        "Training time: wall time of nerfstudio's training loop; render time: median wall time of one test view "
        "(including, for splatfacto without CUDA, the PyTorch EWA rasterizer: not a GPU speed).",
        f"LPIPS: {lpips_reason}.",
    ]


@dataclass
class Summary:
    """One method over its seeds: each figure's mean and the half-width of its 95 % interval (NaN: one seed)."""

    name: str
    description: str
    rasterizer: str
    seeds: List[int]
    figures: Dict[str, Tuple[float, float]]  # metric keys, "train_seconds", "gaussians", "render_ms"


def interval(values: Sequence[float]) -> Tuple[float, float]:
    """(mean, half-width of the 95 % Student-t interval of the mean) of the finite values; NaNs where undefined."""
    from scipy.stats import t

    finite = [v for v in values if v is not None and not math.isnan(v)]
    if not finite:
        return float("nan"), float("nan")
    mean = sum(finite) / len(finite)
    if len(finite) < 2:
        return mean, float("nan")
    sd = math.sqrt(sum((v - mean) ** 2 for v in finite) / (len(finite) - 1))
    return mean, float(t.ppf(0.975, len(finite) - 1)) * sd / math.sqrt(len(finite))


def summarize(results: List[Result]) -> List[Summary]:
    """The results grouped by method (in their order), each figure over the method's seeds."""
    names = list(dict.fromkeys(r.name for r in results))
    out = []
    for name in names:
        runs = [r for r in results if r.name == name]
        keys = list(dict.fromkeys(k for r in runs for k in r.metrics))
        figures = {k: interval([r.metrics.get(k, float("nan")) for r in runs]) for k in keys}
        for attr in ("train_seconds", "gaussians", "render_ms"):
            figures[attr] = interval([float(getattr(r, attr)) for r in runs])
        out.append(Summary(name, runs[0].description, runs[0].rasterizer, [r.seed for r in runs], figures))
    return out


def cell(figure: Tuple[float, float] | None, fmt: str) -> str:
    """A table cell of (mean, half-width): "mean +- half", the mean alone without an interval, n/a without a mean."""
    if figure is None or math.isnan(figure[0]):
        return "n/a"
    mean, half = figure
    return fmt.format(mean) if math.isnan(half) else f"{fmt.format(mean)} +- {fmt.format(half)}"


def markdown(results: List[Result], skipped: Dict[str, str], lines: List[str]) -> str:
    header = ["method", "seeds", *[c[0] for c in COLUMNS], "train s", "Gaussians", "render ms/view", "rasterizer"]
    rows = ["| " + " | ".join(header) + " |", "| --- |" + " ---: |" * (len(header) - 2) + " --- |"]
    summaries = summarize(results)
    for m in summaries:
        cells = [cell(m.figures.get(key), fmt) for _, key, fmt in COLUMNS]
        cells += [cell(m.figures["train_seconds"], "{:.1f}"), cell(m.figures["gaussians"], "{:,.0f}"),
                  cell(m.figures["render_ms"], "{:.1f}")]
        rows.append(f"| {m.name} | {len(m.seeds)} | " + " | ".join(cells) + f" | {m.rasterizer} |")
    out = ["## geer-compare", "", *rows, "", "Methods:", ""]
    out += [f"- **{m.name}**: {m.description}" for m in summaries]
    out += [f"- {name}: not run ({why})" for name, why in skipped.items()]
    out += ["", "Protocol:", ""] + [f"- {line}" for line in lines]
    return "\n".join(out) + "\n"


def as_json(results: List[Result], skipped: Dict[str, str], lines: List[str]) -> dict:
    return {
        "protocol": lines,
        "skipped": skipped,
        "summary": [{"method": m.name, "seeds": m.seeds,
                     **{k: [None if math.isnan(v) else v for v in pair] for k, pair in m.figures.items()}}
                    for m in summarize(results)],
        "results": [{"method": r.name, "seed": r.seed, "description": r.description, "rasterizer": r.rasterizer,
                     "steps": r.steps, "config_digest": r.config_digest,
                     "train_seconds": r.train_seconds, "gaussians": r.gaussians, "render_ms": r.render_ms,
                     **{k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in r.metrics.items()}}
                    for r in results],
    }


def _label(image: np.ndarray, text: str, scale: int) -> np.ndarray:
    """The image enlarged `scale` times (nearest), under a white strip with `text`."""
    if scale > 1:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    strip = np.full((16, image.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, text[: max(4, image.shape[1] // 7)], (2, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1,
                cv2.LINE_AA)
    return np.concatenate([strip, image], axis=0)


def _error_map(pred: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor) -> np.ndarray:
    """Mean absolute error per pixel, x4, as a color map (black outside the valid pixels)."""
    err = ((pred - gt).abs().mean(-1) * 4.0).clamp(0, 1)
    colored = cv2.applyColorMap(to_uint8(err), cv2.COLORMAP_INFERNO)[..., ::-1]
    return np.where(valid.numpy()[..., None], colored, 0).astype(np.uint8)


def first_seeds(results: List[Result]) -> List[Result]:
    """Each method's first result (its first seed), in the methods' order: the pictured runs."""
    first: Dict[str, Result] = {}
    for r in results:
        first.setdefault(r.name, r)
    return list(first.values())


def picture(capture: Capture, results: List[Result], path: Path, views: int = 3) -> Path:
    """Per test view: ground truth then each method's render (top), each method's error map (below); a method's
    first seed (a method loaded without its renders is left out)."""
    results = [r for r in first_seeds(results) if len(r.renders) >= min(views, len(capture.views))]  # loaded: may lack them
    blocks = []
    scale = max(1, 200 // capture.camera.height)
    for i, view in enumerate(capture.views[:views]):
        gt = to_uint8(view.image)
        top = [_label(gt, f"GT {view.name}", scale)] + [_label(to_uint8(r.renders[i]), r.name, scale)
                                                        for r in results]
        bottom = [_label(np.zeros_like(gt), "|error| x4", scale)] + [
            _label(_error_map(r.renders[i], view.image, view.valid), f"{r.name} error", scale) for r in results]
        blocks.append(np.concatenate([np.concatenate(top, axis=1), np.concatenate(bottom, axis=1)], axis=0))
    image = np.concatenate(blocks, axis=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    return path


PICTURED_VIEWS = 3


def write(out_dir: Path, capture: Capture, results: List[Result], skipped: Dict[str, str], lines: List[str]) -> str:
    """compare.md, compare.json, compare.png and renders.npz (each method's first seed, the pictured views, 8 bit:
    for pictures of tables merged by `load`) in out_dir; returns the markdown."""
    text = markdown(results, skipped, lines)
    (out_dir / "compare.md").write_text(text)
    (out_dir / "compare.json").write_text(json.dumps(as_json(results, skipped, lines), indent=1) + "\n")
    picture(capture, results, out_dir / "compare.png", PICTURED_VIEWS)
    np.savez_compressed(out_dir / "renders.npz", **{f"{r.name}__{i}": to_uint8(image) for r in first_seeds(results)
                                                     for i, image in enumerate(r.renders[:PICTURED_VIEWS])})
    return text


def load(out_dir: Path) -> Tuple[List[Result], Dict[str, str], List[str]]:
    """The results, skipped methods and protocol lines of a table `write` made in out_dir; each method's first
    seed gets its pictured renders back where renders.npz holds them (tables merged into one: `picture`)."""
    table = json.loads((out_dir / "compare.json").read_text())
    stored = {}
    if (out_dir / "renders.npz").is_file():
        with np.load(out_dir / "renders.npz") as npz:
            stored = {key: npz[key] for key in npz.files}
    attributes = {"method", "seed", "description", "rasterizer", "steps", "config_digest", "train_seconds", "gaussians",
                  "render_ms"}
    results, pictured = [], set()
    for row in table["results"]:
        name = row["method"]
        renders = []
        if name not in pictured:
            pictured.add(name)
            renders = [torch.from_numpy(stored[f"{name}__{i}"]).float() / 255.0 for i in range(PICTURED_VIEWS)
                       if f"{name}__{i}" in stored]
        metrics = {k: float("nan") if v is None else v for k, v in row.items() if k not in attributes}
        results.append(Result(name, row["description"], row["rasterizer"], row["steps"], row["seed"],
                              row["train_seconds"], row["gaussians"], metrics, row["render_ms"], renders,
                              row.get("config_digest", "")))
    return results, table["skipped"], table["protocol"]
