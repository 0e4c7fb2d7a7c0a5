"""Prepare .device/ for the GPU session, here on the CPU side (benchmarks/gpu_session.sh prep runs this).

A device call carries the working tree and the ignored paths named in `carry`, never ../shared. So every data
file configs/bench_gpu.yaml references (scene `path`, camera `intrinsics_from`, all of the form
`.device/data/NAME`) is copied from ../shared/data/NAME into .device/data/, and .device/COMMIT records the
commit the device results belong to (the device copy has no .git). Synthetic scenes need no file: bench_gpu.py
and tests/conftest.py generate them from their seeds on the device.

    python benchmarks/gpu_prep.py [--dest .] [--shared-data ../shared/data] [--config configs/bench_gpu.yaml]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
DEVICE_DIR = ".device"
DATA_PREFIX = f"{DEVICE_DIR}/data/"


def referenced_files(cfg: dict) -> list[str]:
    """Every data path of the config (repository-relative), in config order, without repeats."""
    paths = [s["path"] for s in cfg.get("scenes", []) if "path" in s]
    paths += [c["intrinsics_from"] for c in cfg.get("cameras", []) if "intrinsics_from" in c]
    for p in paths:
        if not p.startswith(DATA_PREFIX):
            raise ValueError(f"configs/bench_gpu.yaml: data path {p!r} must lie under {DATA_PREFIX} (what a device "
                             "call carries); ../shared does not travel")
    return list(dict.fromkeys(paths))


def commit_line(root: Path) -> str:
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=False).stdout.strip()

    rev = git("rev-parse", "HEAD") or "unknown"
    return rev + (" (uncommitted changes)" if git("status", "--porcelain", "--untracked-files=no") else "")


def prepare(dest: Path, shared_data: Path, config: Path) -> list[Path]:
    """Copy the config's data files into dest/.device/data and write dest/.device/COMMIT; returns the files."""
    cfg = yaml.safe_load(config.read_text())
    out = []
    for rel in referenced_files(cfg):
        src = shared_data / rel[len(DATA_PREFIX):]
        if not src.is_file():
            raise FileNotFoundError(f"{config}: {rel} needs {src}, which does not exist")
        target = dest / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        if not target.is_file() or target.stat().st_size != src.stat().st_size:
            shutil.copyfile(src, target)
        out.append(target)
    (dest / DEVICE_DIR / "COMMIT").write_text(commit_line(ROOT) + "\n")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dest", type=Path, default=ROOT, help="folder that receives .device/ (default: the repository)")
    ap.add_argument("--shared-data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "bench_gpu.yaml")
    args = ap.parse_args(argv)
    for path in prepare(args.dest, args.shared_data, args.config):
        print(f"{path} ({path.stat().st_size / 2**20:.1f} MiB)")
    print(f"{args.dest / DEVICE_DIR / 'COMMIT'}: {(args.dest / DEVICE_DIR / 'COMMIT').read_text().strip()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
