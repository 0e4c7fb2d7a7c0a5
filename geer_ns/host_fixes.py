"""Narrow work-arounds for bugs of the host stack (nerfstudio 1.1.5, torch >= 2.6, torchmetrics, open3d,
splines 0.3.0, a missing system ffmpeg).

Each fix names the host issue it is for and is covered by a test (tests/test_nerfstudio_host_fixes.py,
tests/test_viewer_robustness.py, tests/test_render_without_ffmpeg.py).
Nothing here changes behaviour that works: each fix only takes effect where the host would fail.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from geer_ns.errors import DatasetError

_LOG = logging.getLogger("geer_ns")

# --------------------------------------------------------------------------------------------------
# nerfstudio issue 3683: torch >= 2.6 loads with weights_only=True by default, and nerfstudio's
# checkpoint loaders (ns-eval, ns-viewer, ns-render, ns-train --load-dir) call torch.load without
# weights_only. A nerfstudio checkpoint is dicts of tensors, numbers and strings plus the few
# non-tensor globals below; allow-listing exactly those keeps the safe loader for everything else.
# --------------------------------------------------------------------------------------------------


def _checkpoint_globals() -> list:
    """numpy scalars (pickled as multiarray.scalar + dtype) in the optimizer/scheduler state."""
    try:
        from numpy._core import multiarray as np_multiarray  # numpy >= 2
    except ImportError:  # pragma: no cover - numpy 1.x
        from numpy.core import multiarray as np_multiarray

    found = [np_multiarray.scalar, np.dtype]
    for name in ("Float64DType", "Float32DType", "Int64DType", "Int32DType", "BoolDType"):
        dtype_class = getattr(np.dtypes, name, None)
        if dtype_class is not None:
            found.append(dtype_class)
    return found


def allow_nerfstudio_checkpoints() -> bool:
    """Allow-list the globals nerfstudio checkpoints contain for torch's weights_only loader.

    Returns False (and does nothing) on a torch without `add_safe_globals` (< 2.4), which does not
    default to weights_only either.
    """
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:
        return False
    add(_checkpoint_globals())
    return True


# --------------------------------------------------------------------------------------------------
# splatfacto builds torchmetrics' LPIPS in populate_modules, which downloads AlexNet through
# torch.hub: with no network the model constructor fails. geer builds it lazily, only from weights
# already in the torch hub cache; otherwise LPIPS is reported as missing (logged once).
# --------------------------------------------------------------------------------------------------

_lpips_warned = False


def alexnet_weights_path() -> Path:
    import torchvision

    url = torchvision.models.AlexNet_Weights.DEFAULT.url
    return Path(torch.hub.get_dir()) / "checkpoints" / os.path.basename(url)


def build_lpips_if_cached() -> Optional[torch.nn.Module]:
    """torchmetrics LPIPS (AlexNet) when its weights are cached locally, else None (logged once)."""
    global _lpips_warned
    path = alexnet_weights_path()
    if path.is_file():
        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

        return LearnedPerceptualImagePatchSimilarity(normalize=True)
    if not _lpips_warned:
        _lpips_warned = True
        message = f"LPIPS unavailable: AlexNet weights not found at {path} (no download attempted); lpips is omitted"
        _LOG.warning(message)
        _console_print(f"[yellow]{message}")
    return None


def _console_print(message: str) -> None:
    try:
        from nerfstudio.utils.rich_utils import CONSOLE

        CONSOLE.print(message)
    except Exception:  # pragma: no cover - logging already happened
        pass


# --------------------------------------------------------------------------------------------------
# FullImageDatamanager(cache_images="cpu") calls pin_memory(), which raises "Found no NVIDIA driver"
# with a CUDA build of torch on a machine without a GPU.
# --------------------------------------------------------------------------------------------------


def pin_if_possible(tensor: torch.Tensor) -> torch.Tensor:
    """Pinned copy for fast host-to-GPU transfers when a GPU exists, the tensor itself otherwise."""
    if torch.cuda.is_available() and tensor.device.type == "cpu":
        return tensor.pin_memory()
    return tensor


# --------------------------------------------------------------------------------------------------
# nerfstudio-data reads `ply_file_path` with open3d, whose import fails here without Debian's
# libusb-1.0-0. The seed point cloud is read with plyfile instead.
# --------------------------------------------------------------------------------------------------


def read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(xyz float32 [N,3], rgb uint8 [N,3]) from a PLY point cloud (white where it has no colour)."""
    from plyfile import PlyData

    vertex = PlyData.read(str(path))["vertex"]
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=-1).astype(np.float32)
    names = vertex.data.dtype.names
    if all(c in names for c in ("red", "green", "blue")):
        rgb = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=-1)
        rgb = rgb if rgb.dtype == np.uint8 else np.clip(np.round(rgb * 255.0), 0, 255)
    else:
        rgb = np.full_like(xyz, 255.0)
    return xyz, rgb.astype(np.uint8)


# --------------------------------------------------------------------------------------------------
# nerfstudio's viewer builds its camera-path spline with splines 0.3.0's quaternion KochanekBartels,
# which raises for exactly two keyframes ("truth value of an empty array is ambiguous": `assert not tcb`
# on its empty TCB array; numpy 2 made that an error). Two rotations need no TCB values: the spline is
# the slerp between them, which is what the patched constructor builds (a one-segment De Casteljau
# curve, splines' own class).
# --------------------------------------------------------------------------------------------------


def install_two_keyframe_spline_fix() -> bool:
    """Patch splines.quaternion.KochanekBartels for two open keyframes; False if splines is absent."""
    try:
        import splines.quaternion as sq
    except ImportError:  # pragma: no cover - nerfstudio depends on it
        return False
    cls = sq.KochanekBartels
    if getattr(cls, "_geer_two_keyframes", False):
        return True
    original = cls.__init__

    def __init__(self, quaternions, grid=None, *, tcb=(0, 0, 0), alpha=None, endconditions="natural"):
        if endconditions != "closed" and len(quaternions) == 2:
            quaternions = sq._check_quaternions(quaternions, closed=False)  # same hemisphere
            sq.DeCasteljau.__init__(self, [quaternions], sq._check_grid(grid, alpha, quaternions))
            return
        original(self, quaternions, grid, tcb=tcb, alpha=alpha, endconditions=endconditions)

    cls.__init__ = __init__
    cls._geer_two_keyframes = True
    return True


# --------------------------------------------------------------------------------------------------
# ns-render (interpolate, camera-path, spiral) exits with "Could not find ffmpeg" when no `ffmpeg` is on
# PATH, even with --output-format images (install_checks.check_ffmpeg_installed), and mediapy writes
# videos through the same program. geer depends on imageio-ffmpeg, which ships an ffmpeg binary: when
# there is no system ffmpeg, a link named `ffmpeg` to it is put first on PATH (and given to mediapy).
# Every ns-render imports geer_ns.model (through config.yml) before that check.
# --------------------------------------------------------------------------------------------------

_ffmpeg_said = False


def provide_ffmpeg() -> Optional[str]:
    """The `ffmpeg` program nerfstudio will run: the system one, else imageio-ffmpeg's; None if neither."""
    global _ffmpeg_said
    found = shutil.which("ffmpeg")
    if found is not None:
        return found
    try:
        import imageio_ffmpeg

        exe = Path(imageio_ffmpeg.get_ffmpeg_exe())
    except Exception:  # not installed, or no binary for this platform
        return None
    link = _ffmpeg_link(exe)
    os.environ["PATH"] = f"{link.parent}{os.pathsep}{os.environ.get('PATH', '')}"
    try:
        import mediapy

        mediapy.set_ffmpeg(str(link))
    except ImportError:  # pragma: no cover - nerfstudio depends on it
        pass
    if not _ffmpeg_said:
        _ffmpeg_said = True
        _LOG.info("no system ffmpeg: using imageio-ffmpeg's %s", exe)
    return str(link)


def _ffmpeg_link(exe: Path) -> Path:
    """A folder holding `ffmpeg` -> exe: in geer's cache, else in a fresh temporary folder."""
    candidates = [Path(os.environ.get("GEER_NS_CACHE", "~/.cache/geer_ns")).expanduser() / "ffmpeg_bin"]
    for folder in candidates + [Path(tempfile.mkdtemp(prefix="geer_ffmpeg_"))]:
        link = folder / "ffmpeg"
        try:
            folder.mkdir(parents=True, exist_ok=True)
            if link.is_symlink() and Path(os.readlink(link)) != exe:
                link.unlink()
            if not link.is_symlink():
                link.symlink_to(exe)
            return link
        except OSError:
            continue
    return exe  # unreachable in practice: a fresh temporary folder is writable


# --------------------------------------------------------------------------------------------------
# Known noise of the host stack in every run: torch deprecation FutureWarnings raised by nerfstudio's own
# code at import (camera_utils' torch.jit.script, activations' custom_fwd / custom_bwd) and at start-up
# (the trainer's GradScaler), and nerfstudio turning loss tensors into floats. Each filter is exactly one
# message, category and warning module; the same warnings from any other module are still shown.
# Installed when geer_ns is imported (geer_ns/__init__.py), so before nerfstudio wherever geer comes first
# (tests, `import geer_ns.config`, geer's own scripts). ns-train imports geer when it discovers dataparser
# plugins, after nerfstudio's camera code: its torch.jit.script warning comes before any plugin code runs, so
# the environment's start-up hook (install_startup_hook, below) installs the same filters.
# --------------------------------------------------------------------------------------------------

KNOWN_NOISE = (  # (category, message, module): regular expressions matched at the start
    (FutureWarning, r"`torch\.jit\.script` is deprecated", r"torch\.jit\._script\Z"),
    (FutureWarning, r"`torch\.cuda\.amp\.custom_(fwd|bwd)\(args\.\.\.\)` is deprecated",
     r"nerfstudio\.field_components\.activations\Z"),
    (FutureWarning, r"`torch\.cuda\.amp\.GradScaler\(args\.\.\.\)` is deprecated", r"nerfstudio\.engine\.trainer\Z"),
    (UserWarning, r"Converting a tensor with requires_grad=True to a scalar may lead to unexpected behavior",
     r"nerfstudio\."),
)


def quiet_known_warnings() -> None:
    import warnings

    for category, message, module in KNOWN_NOISE:
        warnings.filterwarnings("ignore", message=message, category=category, module=module)


# The same filters at interpreter start-up, for what nerfstudio prints before it loads any plugin (ns-train's
# torch.jit.script warning): a .pth file in the environment's site-packages whose one `import` line installs
# them (Python's site module runs such lines). scripts/setup.sh installs it into .venv; nothing is imported.
STARTUP_HOOK_NAME = "geer_ns_host_warnings.pth"


def startup_hook_line() -> str:
    calls = "; ".join(f"_w.filterwarnings('ignore', message={message!r}, category={category.__name__}, "
                      f"module={module!r})" for category, message, module in KNOWN_NOISE)
    return f"import warnings as _w; {calls}\n"


def install_startup_hook(site_packages: Optional[Path] = None) -> Path:
    """Write the start-up hook into `site_packages` (default: this interpreter's purelib) and return its path."""
    import sysconfig

    folder = Path(site_packages) if site_packages is not None else Path(sysconfig.get_paths()["purelib"])
    path = folder / STARTUP_HOOK_NAME
    path.write_text("# geer-ns: nerfstudio's known import-time warnings (geer_ns/host_fixes.py KNOWN_NOISE)\n"
                    + startup_hook_line())
    return path


def report_dataset_errors_without_traceback() -> None:
    """ns-train gives a plugin no place to catch a broken dataset, so a geer DatasetError would end the run
    under a page of nerfstudio's stack. It ends it with its one line (file, frame, field, what to do) and exit
    status 1 instead; every other exception keeps its traceback."""
    import sys

    previous = sys.excepthook
    if getattr(previous, "geer_dataset_hook", False):
        return

    def hook(kind, value, traceback):
        if isinstance(value, DatasetError):
            print(value, file=sys.stderr)
        else:
            previous(kind, value, traceback)

    hook.geer_dataset_hook = True  # type: ignore[attr-defined]
    sys.excepthook = hook


# --------------------------------------------------------------------------------------------------
# nerfstudio's launcher (`ns-train --machine.num-devices N`, nerfstudio/scripts/train.py): its worker
# `_distributed_worker` asserts torch.cuda.is_available() and num_devices <= torch.cuda.device_count(), so N
# gloo processes on a CPU machine fail; it never selects each process's GPU (every NCCL process would use
# GPU 0); its timeout is a fixed 30 minutes; and a failed process ends the run in pages of tracebacks, or
# "process 1 terminated with signal SIGKILL". For geer's configs (those with `machine.timeout_s`) the worker
# is replaced by one doing nerfstudio's set-up without the CUDA-only asserts: gloo on CPU (each process with
# its share of the cores), NCCL on CUDA (each process on its own GPU), the config's timeout; and the launch
# ends with one line naming the process that failed. Other methods keep nerfstudio's launcher.
# --------------------------------------------------------------------------------------------------


def install_distributed_launch_fix() -> None:
    """Route nerfstudio's `mp.spawn(_distributed_worker, ...)` for geer configs to `distributed_worker`."""
    import torch.multiprocessing as mp

    if getattr(mp.spawn, "_geer_launch_fix", False):
        return
    original = mp.spawn

    def spawn(fn, args=(), nprocs=1, join=True, daemon=False, start_method="spawn"):
        nerfstudio_worker = getattr(fn, "__module__", "") == "nerfstudio.scripts.train" and \
            getattr(fn, "__name__", "") == "_distributed_worker"
        config = args[5] if nerfstudio_worker and len(args) > 5 else None
        timeout_s = getattr(getattr(config, "machine", None), "timeout_s", None)
        if timeout_s is None:
            return original(fn, args, nprocs, join, daemon, start_method)
        context = original(distributed_worker, args, nprocs, join=False, daemon=daemon, start_method=start_method)
        reporting = ReportingContext(context, machine_rank=int(args[3]), grace_s=float(timeout_s) + 10.0)
        return reporting.join() if join else reporting

    spawn._geer_launch_fix = True  # type: ignore[attr-defined]
    mp.spawn = spawn


def distributed_worker(local_rank, main_func, world_size, num_devices_per_machine, machine_rank, dist_url, config,
                       timeout, device_type="cuda"):
    """nerfstudio's _distributed_worker (same arguments) without its CUDA-only asserts: see above."""
    import sys
    from datetime import timedelta

    import torch.distributed as dist
    from nerfstudio.utils import comms

    global_rank = machine_rank * num_devices_per_machine + local_rank
    if device_type == "cuda":
        found = torch.cuda.device_count()
        if num_devices_per_machine > found:
            print(f"geer: --machine.num-devices {num_devices_per_machine} but this machine has {found} CUDA "
                  "device(s); use --machine.device-type cpu for processes on the CPU", file=sys.stderr, flush=True)
            raise SystemExit(2)
        torch.cuda.set_device(local_rank)
    else:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        torch.set_num_threads(max(1, cores // num_devices_per_machine))
    timeout = timedelta(seconds=float(getattr(config.machine, "timeout_s", timeout.total_seconds())))
    try:
        dist.init_process_group(backend="nccl" if device_type == "cuda" else "gloo", init_method=dist_url,
                                world_size=world_size, rank=global_rank, timeout=timeout)
    except Exception as error:  # noqa: BLE001 - one line: which rank could not join, where, why
        print(f"geer: rank {global_rank} of {world_size} could not join the others at {dist_url} within "
              f"{timeout.total_seconds():g} s: {str(error).strip().splitlines()[0]}", file=sys.stderr, flush=True)
        raise SystemExit(1)
    for machine in range(world_size // num_devices_per_machine):  # nerfstudio's per-machine groups
        ranks = list(range(machine * num_devices_per_machine, (machine + 1) * num_devices_per_machine))
        group = dist.new_group(ranks)
        if machine == machine_rank:
            comms.LOCAL_PROCESS_GROUP = group
    try:
        # No barrier at the end (nerfstudio has one): rank 0 may stay to serve the viewer after training.
        return main_func(local_rank, world_size, config, global_rank)
    finally:
        dist.destroy_process_group()


class ReportingContext:
    """torch's spawn context whose join waits for every process and ends a failed launch with one line."""

    def __init__(self, context, machine_rank: int, grace_s: float):
        self.context, self.machine_rank, self.grace_s = context, machine_rank, grace_s
        self.processes = context.processes

    def join(self, timeout=None) -> bool:
        import sys

        from torch.multiprocessing import ProcessExitedException, ProcessRaisedException

        n = len(self.processes)
        try:
            while not self.context.join(timeout, grace_period=self.grace_s):
                if timeout is not None:
                    return False
        except ProcessRaisedException as error:
            print(error.msg, file=sys.stderr)  # the process's traceback (nerfstudio would have printed it)
            lines = [line for line in error.msg.strip().splitlines() if line.strip()]
            self._stopped(error.error_index, f"raised {lines[-1].strip() if lines else 'an exception'}", n)
        except ProcessExitedException as error:
            what = (f"was killed by signal {error.signal_name}" if error.signal_name else
                    f"exited with status {error.exit_code} (its message is above)")
            self._stopped(error.error_index, what, n)
        return True

    def _stopped(self, index: int, what: str, n: int) -> None:
        import sys

        rank = self.machine_rank * n + index
        print(f"geer: training stopped: rank {rank} (pid {self.processes[index].pid}) {what}; the other "
              f"{n - 1} process(es) of this machine were stopped", file=sys.stderr, flush=True)
        raise SystemExit(1)
