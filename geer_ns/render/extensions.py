"""JIT builds of csrc/: the CUDA extension and its CPU build, each configuration cached in its own folder.

torch.utils.cpp_extension.load keeps one build per folder and runs ninja on every load, which rebuilds when the
command line differs from the last build's: other sources or flags, but also another path to the same torch
(a venv reached through a symlink, as /work/main/.venv and the worktree's .venv, or ns-viewer's interpreter
against pytest's), so two processes on one checkout rebuilt for minutes, alternately. Here the folder, and the
module name, carry a key: a hash of the sources' and headers' contents, the flags, torch's version and build,
Python's version and the compiler. A configuration is built once; after that its module is imported from its
folder directly (no ninja, so no path or timestamp can start a rebuild), and two configurations never share a
folder. geer holds its own OS file lock in the folder (`geer.lock`: a killed process leaves no stale lock) from
the check for a finished build to the build's end, so it never imports a module being written and two processes
never build one folder; inside it, torch's build takes torch's own lock (a file lock, or up to torch 2.11 a
FileBaton, whose file a killed build leaves behind: removed before a build). A build is said before it starts
(it takes a minute or more) and when it ends, with its time.

Folders: $GEER_EXT_DIR, else <repo>/.cache/geer_ext (git-ignored), one `<name>_<key>` per configuration; old
ones can be deleted at any time. TORCH_CUDA_ARCH_LIST defaults to the first GPU's compute capability ("9.0"
without one). Importing this module builds nothing.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import platform
import sys
import threading
import time
from pathlib import Path
from types import ModuleType
from typing import Sequence

import torch

CSRC = Path(__file__).resolve().parents[2] / "csrc"
_CUDA_SOURCES = ("bindings.cpp", "preprocess.cu", "associate.cu", "render.cu", "render_order.cu",
                 "preprocess_backward.cu", "launch_probe.cu")
_CPU_SOURCES = ("cpu_ops.cpp", "cpu_render.cpp", "cpu_render_backward.cpp", "cpu_render_order.cpp")
_HEADER_SUFFIXES = (".h", ".cuh", ".hpp")
# What a build is called when it announces itself, and how long it takes on a cold cache.
_WHAT = {"geer_cpu_ops": ("the CPU renderer", "about a minute"), "geer_cuda": ("the CUDA kernels", "a few minutes")}

# The folder's own OS lock (released by the kernel when its process dies), held from the check for a finished
# build to its end; torch's build lock is torch's own (a file lock, or up to torch 2.11 a FileBaton).
_GEER_LOCK = "geer.lock"
_lock = threading.Lock()
_modules: dict[str, ModuleType] = {}  # by extension name: one configuration per process
_errors: dict[str, BaseException] = {}


def build_root() -> Path:
    """Where JIT builds are cached: $GEER_EXT_DIR, else <repo>/.cache/geer_ext (git-ignored)."""
    env = os.environ.get("GEER_EXT_DIR")
    return Path(env) if env else CSRC.parent / ".cache" / "geer_ext"


def cpu_cflags() -> list[str]:
    """C++ flags of both builds. -ffp-contract=off: pair decisions without FMA drift (geer_math.h);
    -fno-math-errno: sqrt inline. -mavx2 where the CPU has it (torch's own dispatch level): the CPU build's
    render then evaluates packs of 8 float32 / 4 float64 rays (csrc/geer_packs.h). No -march=native: see
    cpu_render_backward.cpp warp_grad_sum on GCC 12's -O3 AVX-512 code."""
    flags = ["-O3", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math"]
    if platform.machine() in ("x86_64", "AMD64"):
        avx2 = torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512")
        # Without AVX2 GCC notes that 256-bit pack arguments change the ABI: harmless here (inline functions of
        # one translation unit), and the render stage then runs one ray at a time anyway.
        flags.append("-mavx2" if avx2 else "-Wno-psabi")
    return flags


def build_key(sources: Sequence[Path], include_dir: Path, cflags: Sequence[str], cuda_cflags: Sequence[str],
              cuda: bool) -> str:
    """16 hex digits naming one configuration: everything that changes what the compiler produces."""
    digest = hashlib.sha256()
    headers = sorted(p for p in include_dir.iterdir() if p.suffix in _HEADER_SUFFIXES)
    for path in [*sources, *headers]:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    facts = {"cflags": list(cflags), "cuda_cflags": list(cuda_cflags), "cuda": cuda, "torch": torch.__version__,
             "torch_cuda": torch.version.cuda, "python": sys.version, "cxx": os.environ.get("CXX", ""),
             "arch": os.environ.get("TORCH_CUDA_ARCH_LIST", "") if cuda else ""}
    digest.update(json.dumps(facts, sort_keys=True).encode())
    return digest.hexdigest()[:16]


def default_cuda_arch() -> str:
    """The compute capability to build for when TORCH_CUDA_ARCH_LIST is unset: the first GPU's, so that the
    kernels load on the GPU at hand (an sm_90 build has no kernel image for an sm_89 card); "9.0" without one."""
    if torch.cuda.is_available():
        major, minor = torch.cuda.get_device_capability(0)
        return f"{major}.{minor}"
    return "9.0"


def _cuda_cflags(cuda: bool) -> list[str]:
    return ["-O3", "-lineinfo"] if cuda else []  # no --use_fast_math: round like the twin


def configuration_key(name: str) -> str:
    """The build key of extension `name` ("geer_cuda" or "geer_cpu_ops") as this process would build it,
    without building anything: what a self-test verdict is recorded for (verdict.py)."""
    cuda = name == "geer_cuda"
    if cuda:
        os.environ.setdefault("TORCH_CUDA_ARCH_LIST", default_cuda_arch())
    sources = [CSRC / s for s in (_CUDA_SOURCES if cuda else _CPU_SOURCES)]
    return build_key(sources, CSRC, cpu_cflags(), _cuda_cflags(cuda), cuda)


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _import_built(module_name: str, folder: Path) -> ModuleType | None:
    """The module of a finished build in `folder`, or None when there is none (or it cannot be loaded). Called
    with the folder's geer lock held."""
    library = folder / f"{module_name}.so"
    if not library.exists():
        return None
    spec = importlib.util.spec_from_file_location(module_name, library)
    try:
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except ImportError:  # a link cut short (a killed build): build it again
        library.unlink()
        return None
    return module


def build_and_load(name: str, sources: Sequence[Path], *, cuda: bool, cflags: Sequence[str],
                   include_dir: Path | None = None, verbose: bool = False) -> ModuleType:
    """Load configuration (sources, flags) of extension `name` from its own folder, building it first if that
    folder holds no build yet (said before and after). Not memoized: see _load."""
    sources = [Path(s) for s in sources]
    include_dir = sources[0].parent if include_dir is None else include_dir
    cuda_cflags = _cuda_cflags(cuda)
    module_name = f"{name}_{build_key(sources, include_dir, cflags, cuda_cflags, cuda)}"
    folder = build_root() / module_name
    folder.mkdir(parents=True, exist_ok=True)
    what, how_long = _WHAT.get(name, (name, "a minute or more"))
    from filelock import FileLock, Timeout  # a torch dependency

    lock = FileLock(str(folder / _GEER_LOCK))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        _say(f"geer: waiting for another process building {what} in {folder} ...")
        lock.acquire()
    try:
        module = _import_built(module_name, folder)
        if module is not None:
            return module
        from torch.utils import cpp_extension

        # torch up to 2.11 guards a build with a FileBaton: the file `lock` itself, which a killed build leaves
        # behind and every later build then waits on for ever (fixed in torch's own lock after 2.11). Holding
        # the geer lock, no one else builds here.
        (folder / "lock").unlink(missing_ok=True)
        _say(f"geer: building {what} (first use of this configuration, {how_long}) in {folder} ...")
        start = time.perf_counter()
        try:
            module = cpp_extension.load(
                name=module_name, sources=[str(s) for s in sources], extra_cflags=list(cflags),
                extra_cuda_cflags=cuda_cflags or None, extra_include_paths=[str(include_dir)],
                build_directory=str(folder), with_cuda=cuda, verbose=verbose,
            )
        except BaseException:
            _say(f"geer: building {what} failed after {time.perf_counter() - start:.0f} s")
            raise
        _say(f"geer: built {what} in {time.perf_counter() - start:.0f} s")
        return module
    finally:
        lock.release()


def _load(name: str, sources: tuple[str, ...], cuda: bool, verbose: bool) -> ModuleType:
    """Extension `name` from csrc/, built or loaded once per process; a failure is remembered, not retried."""
    with _lock:
        if name in _modules:
            return _modules[name]
        if name in _errors:
            raise RuntimeError(f"building {name} failed earlier in this process") from _errors[name]
        if cuda:
            os.environ.setdefault("TORCH_CUDA_ARCH_LIST", default_cuda_arch())
        try:
            module = build_and_load(name, [CSRC / s for s in sources], cuda=cuda, cflags=cpu_cflags(),
                                    include_dir=CSRC, verbose=verbose)
        except BaseException as exc:  # remember: a failed build is not retried on every render
            _errors[name] = exc
            raise
        _modules[name] = module
        return module


def build_error(name: str) -> str:
    """One line on why building extension `name` failed in this process ('' if it did not)."""
    exc = _errors.get(name)
    return "" if exc is None else f"{type(exc).__name__}: {str(exc).strip().splitlines()[-1] if str(exc).strip() else ''}"


def load_extension(verbose: bool = False) -> ModuleType:
    """The CUDA extension (built on first call; minutes on a cold cache)."""
    return _load("geer_cuda", _CUDA_SOURCES, cuda=True, verbose=verbose)


def load_cpu_ops(verbose: bool = False) -> ModuleType:
    """csrc/ compiled for the CPU with the CUDA extension's operations: the kernels' math and per-block
    orchestration checked without a GPU, and `backend="cpu"` (multi-threaded C++, analytic backward)."""
    return _load("geer_cpu_ops", _CPU_SOURCES, cuda=False, verbose=verbose)


def extension_available() -> bool:
    """Whether the CUDA extension can be used here: a GPU is present and the extension builds and loads.
    Never raises; on a machine without CUDA it returns False without trying to build."""
    if not torch.cuda.is_available():
        return False
    try:
        load_extension()
    except Exception:  # noqa: BLE001 - any build/load failure means "not available"
        return False
    return True
