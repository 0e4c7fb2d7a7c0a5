"""geer-doctor: what a bug report needs, in a few lines. The environment, the devices, which renderer each
device gets with backend="auto" and why, the recorded self-test verdicts (`--selftest` runs them again), and
the time of one training step per renderer (forward + backward of a small synthetic view).

    geer-doctor [--selftest] [--no-timing] [--gaussians N] [--size S]
    python -m geer_ns.doctor ...
"""

from __future__ import annotations

import argparse
import importlib.metadata
import math
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch

from geer_ns.render import RayGrid, render
from geer_ns.render import backend as backends
from geer_ns.render import extensions, verdict
from geer_ns.selftest.scenes import random_gaussians


def _version(package: str) -> str:
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def _first_line(cmd: list[str]) -> str:
    if shutil.which(cmd[0]) is None:
        return "not found"
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return "did not answer"
    lines = [line for line in (out.stdout + out.stderr).splitlines() if line.strip()]
    return lines[-1].strip() if cmd[0] == "nvcc" and lines else (lines[0].strip() if lines else "?")


def _commit() -> str:
    root = Path(__file__).resolve().parents[1]
    try:
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short=12", "HEAD"], capture_output=True,
                             text=True, timeout=10)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def environment_lines() -> list[str]:
    cuda = f"CUDA {torch.version.cuda} build" if torch.version.cuda else "CPU-only build"
    return [
        f"geer_ns {_version('geer-ns')} at {Path(__file__).resolve().parent} (commit {_commit()})",
        f"Python {platform.python_version()} on {platform.platform()}; torch {torch.__version__} ({cuda}), "
        f"nerfstudio {_version('nerfstudio')}, gsplat {_version('gsplat')}",
        f"compilers: c++ {_first_line(['c++', '--version'])}; nvcc {_first_line(['nvcc', '--version'])}",
        f"extension cache: {extensions.build_root()}; self-test verdicts: {verdict.verdict_dir()}",
    ]


def devices() -> list[torch.device]:
    return [torch.device("cpu")] + [torch.device("cuda", i) for i in range(torch.cuda.device_count())
                                    if torch.cuda.is_available()]


def _describe(device: torch.device) -> str:
    if device.type == "cpu":
        facts = verdict.device_facts("cpu", device)
        return f"{facts['device']} ({facts['capability']}, {torch.get_num_threads()} threads)"
    props = torch.cuda.get_device_properties(device)
    return (f"{props.name} (compute capability {props.major}.{props.minor}, {props.total_memory / 2**30:.0f} GiB, "
            f"driver {verdict.device_facts('cuda', device)['driver']})")


def choice(device: torch.device, run_selftest: bool) -> tuple[str, str]:
    """(the renderer auto gives `device`, why), running its self-test when asked (or, for a GPU, when none is
    recorded and `run_selftest`)."""
    kind = device.type
    try:
        (extensions.load_cpu_ops if kind == "cpu" else extensions.load_extension)()
    except Exception as exc:  # noqa: BLE001 - reported
        return "torch", f"the compiled renderer does not build or load here ({extensions.build_error(verdict.EXTENSION[kind]) or exc})"
    found = verdict.verify(kind, device, rerun=True) if run_selftest else verdict.cached_verdict(kind, device)
    test = "no self-test recorded for this build" if found is None else f"self-test {found.line()}"
    if kind == "cpu":
        gated = os.environ.get("GEER_VERIFY_CPU_BUILD", "") not in ("", "0")
        if gated and found is not None and not found.passed:
            return "torch", test
        return "cpu", f"the kernels' code compiled for the CPU ({'' if gated else 'checked by the test suite; '}{test})"
    if found is None:
        return "cuda after its self-test", "auto runs the self-test on first use (geer-doctor --selftest runs it now)"
    return ("cuda" if found.passed else "torch"), test


def time_step(backend: str, device: torch.device, gaussians: int, size: int, repeats: int = 3) -> float:
    """Median seconds of one training step's render (forward and backward, float32) with `backend`."""
    scene = [t.to(device, torch.float32) for t in random_gaussians(gaussians, 0, around=False)]
    grid = RayGrid.beap(size, size, math.radians(90), math.radians(90), tile_size=16, dtype=torch.float32).to(device)
    viewmat = torch.eye(4, device=device)
    times = []
    for _ in range(repeats + 1):  # the first is a warm-up
        leaves = [t.clone().requires_grad_(True) for t in scene]
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        out = render(*leaves, viewmat, grid, backend=backend)
        (out.rgb.sum() + out.depth.sum()).backward()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - start)
    return sorted(times[1:])[len(times[1:]) // 2]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="geer-doctor", description=__doc__.splitlines()[0])
    parser.add_argument("--selftest", action="store_true", help="run the self-test on every device now")
    parser.add_argument("--no-timing", action="store_true", help="skip the training-step timings")
    parser.add_argument("--gaussians", type=int, default=2000, help="Gaussians of the timed step (default 2000)")
    parser.add_argument("--size", type=int, default=64, help="rays per side of the timed step's view (default 64)")
    args = parser.parse_args(argv)
    for line in environment_lines():
        print(line)
    if not torch.cuda.is_available():
        print("cuda: no usable device (torch.cuda.is_available() is False)")
    for device in devices():
        chosen, why = choice(device, args.selftest)
        print(f"{device}: {_describe(device)}")
        print(f"  auto -> {chosen}: {why}")
        if args.no_timing:
            continue
        timed = []
        for name in (["cpu", "torch"] if device.type == "cpu" else ["cuda", "torch"]):
            if name != "torch" and chosen.startswith("torch") and "does not build" in why:
                continue
            try:
                timed.append(f"{name} {1e3 * time_step(name, device, args.gaussians, args.size):.1f} ms")
            except Exception as exc:  # noqa: BLE001 - reported, the other renderers are still timed
                timed.append(f"{name} failed ({type(exc).__name__}: {str(exc).splitlines()[0][:80] if str(exc) else ''})")
        print(f"  one training step ({args.gaussians} Gaussians, {args.size}x{args.size} rays, forward + backward, "
              f"median of 3): {', '.join(timed)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
