"""What the benchmarks share: where the repository and the test data are, the header every report starts with
(device, commit, command), the dev room at a chosen size, and geer runs trained in this process."""

from __future__ import annotations

import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"


def test_data(*parts: str) -> Path:
    """A path under the external test data (docs/test_data.md): $GEER_TEST_DATA, else ../shared/data beside the
    checkout."""
    path = Path(os.environ.get("GEER_TEST_DATA", ROOT.parent / "shared" / "data")).joinpath(*parts)
    if not path.exists():
        raise SystemExit(f"{path}: not found; point GEER_TEST_DATA at the test data (docs/test_data.md)")
    return path


def commit() -> str:
    """HEAD's short hash, marked when tracked files differ from it."""
    git = lambda *args: subprocess.run(["git", *args], capture_output=True, text=True, cwd=ROOT).stdout.strip()  # noqa: E731
    return (git("rev-parse", "--short", "HEAD") or "unknown") + (
        " (+ uncommitted changes)" if git("status", "--porcelain", "--untracked-files=no") else "")


def device() -> str:
    import torch

    if torch.cuda.is_available():
        return f"{torch.cuda.get_device_name()}, torch {torch.__version__} (CUDA {torch.version.cuda})"
    return (f"CPU ({platform.processor() or platform.machine()}), {os.cpu_count()} cores (load average "
            f"{os.getloadavg()[0]:.1f} when written), torch {torch.__version__}, {torch.get_num_threads()} threads")


def header(title: str, *notes: str) -> str:
    """A report's start: its title, device, commit, the command as run, then `notes` (one bullet each)."""
    module = Path(sys.argv[0]).stem
    command = shlex.join(["python", "-m", f"benchmarks.{module}", *sys.argv[1:]])
    lines = [f"# {title}", "", f"- device: {device()}", f"- commit: {commit()}", f"- command: `{command}`"]
    return "\n".join(lines + [f"- {note}" for note in notes]) + "\n"


def dev_room(work: Path, size: int) -> Path:
    """The dev fisheye room (test data) at size^2: images, masks and intrinsics (fisheye and pinhole views)
    resized from 384^2 with OpenCV's INTER_AREA."""
    import cv2

    src, out = test_data("fisheye_room_dev"), work / f"dev_room_{size}"
    if (out / "transforms_pinhole.json").is_file():
        return out
    scale = size / 384.0
    for name in ("transforms_fisheye.json", "transforms_pinhole.json"):
        meta = json.loads((src / name).read_text())
        for key in ("fl_x", "fl_y", "cx", "cy", "fisheye_crop_radius"):
            if key in meta:
                meta[key] = meta[key] * scale
        meta["w"] = meta["h"] = size
        for frame in meta["frames"]:
            for key in ("file_path", "mask_path"):
                if key in frame and not (out / frame[key]).exists():
                    (out / frame[key]).parent.mkdir(parents=True, exist_ok=True)
                    small = cv2.resize(cv2.imread(str(src / frame[key]), cv2.IMREAD_UNCHANGED), (size, size),
                                       interpolation=cv2.INTER_AREA)
                    if key == "mask_path":
                        small = ((small >= 128) * 255).astype("uint8")  # a mask stays binary
                    cv2.imwrite(str(out / frame[key]), small, [cv2.IMWRITE_JPEG_QUALITY, 95])
        (out / name).write_text(json.dumps(meta))
    shutil.copy(src / "points3d.ply", out / "points3d.ply")
    return out


def run_config(data: Path, out: Path, name: str, steps: int, options: dict | None = None, seed: int = 42,
               load_dir: Path | None = None):
    """geer's TrainerConfig for a benchmark run: no viewer, no evaluation or checkpoint during training, images
    cached on the CPU; `options` set model options (dotted names reach into sub-configs: camera_optimizer.mode);
    `seed` nerfstudio's machine seed and the training images' order; `load_dir` a checkpoint folder to start from."""
    from geer_ns.config import geer_trainer_config
    from geer_ns.model import GeerModelConfig

    config = geer_trainer_config("geer", GeerModelConfig())
    config.data = config.pipeline.datamanager.data = data
    config.pipeline.datamanager.cache_images = "cpu"
    config.output_dir, config.experiment_name, config.timestamp = out, name, "run"
    config.vis = "tensorboard"
    config.max_num_iterations = steps
    config.steps_per_eval_image = config.steps_per_eval_batch = config.steps_per_eval_all_images = 0
    config.steps_per_save = 10**9
    config.machine.seed = config.pipeline.datamanager.train_cameras_sampling_seed = seed
    config.load_dir = load_dir
    for key, value in (options or {}).items():
        target = config.pipeline.model
        *path, leaf = key.split(".")
        for part in path:
            target = getattr(target, part)
        setattr(target, leaf, value)
    return config


def train_and_score(config):
    """Train `config` in this process with nerfstudio's loop; (ns-eval's averaged metrics of the eval split,
    seconds of training, the trained pipeline)."""
    from nerfstudio.utils import writer

    from geer_ns.compare.run import train_timed

    trainer, seconds = train_timed(config)
    metrics = trainer.pipeline.get_average_eval_image_metrics(step=config.max_num_iterations)
    writer.EVENT_WRITERS.clear()
    return metrics, seconds, trainer.pipeline


def short_schedule(densify_until: int = 1000) -> dict:
    """Model options for runs of a few thousand steps: densification every 100 steps from step 300 to
    `densify_until`, full resolution throughout."""
    return {"warmup_length": 300, "refine_every": 100, "stop_split_at": densify_until, "num_downscales": 0}


def main() -> None:
    """`python -m benchmarks.common --dev-room SIZE [--work DIR]`: make the dev room at SIZE^2, print its folder."""
    import argparse

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("--dev-room", type=int, required=True, metavar="SIZE")
    ap.add_argument("--work", type=Path, default=Path("/tmp/geer_bench"))
    args = ap.parse_args()
    print(dev_room(args.work, args.dev_room))


if __name__ == "__main__":
    main()
