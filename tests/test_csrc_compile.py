"""Every CUDA source in csrc/ builds, and every kernel can launch at the largest block the bindings allow:
CI's guarantee that a kernel that does not compile, or one a GPU would refuse to launch, cannot land.

The .cu files hold no torch headers, so plain nvcc compiles them (sm_90, C++17) without a GPU, all in parallel
and once per test run (`build` fixture). ptxas's resource report (-Xptxas -v) and the PTX (.maxntid: the
kernel's __launch_bounds__) give each kernel's registers per thread, spills and largest block; a block needs
registers x threads <= 65,536 (the register file of one multiprocessor, sm_50 to sm_90), and float32 kernels
must not spill (float64 may, a little, in the 1024-thread tile build). A kernel without __launch_bounds__ can
be launched with up to 1024 threads, so that is its block. Two mutated builds of render.cu (launch bounds
stripped; registers capped at 24) show that the check fails when it should. bindings.cpp (the torch glue,
built by the JIT loader on a GPU machine) gets a syntax-only pass with the host compiler. Without nvcc the
tests skip, saying why, except in CI (CI=true), where a missing nvcc is a failure.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import sysconfig
from dataclasses import dataclass
from pathlib import Path

import pytest

CSRC = Path(__file__).resolve().parents[1] / "csrc"
CU_SOURCES = sorted(CSRC.glob("*.cu"))
REGISTERS_PER_SM = 65536
MAX_BLOCK = 1024  # the hardware limit: the block of a kernel that declares no __launch_bounds__


def _nvcc() -> Path | None:
    candidates = []
    if os.environ.get("CUDA_HOME"):
        candidates.append(Path(os.environ["CUDA_HOME"]) / "bin" / "nvcc")
    candidates.append(Path("/usr/local/cuda/bin/nvcc"))
    which = shutil.which("nvcc")
    if which:
        candidates.append(Path(which))
    return next((c for c in candidates if c.is_file() and os.access(c, os.X_OK)), None)


def _require_nvcc() -> Path:
    nvcc = _nvcc()
    if nvcc is None:
        msg = "nvcc not found ($CUDA_HOME/bin/nvcc, /usr/local/cuda/bin/nvcc, PATH): cannot compile csrc/*.cu"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"{msg}; CI must have the CUDA toolkit")
        pytest.skip(msg)
    return nvcc


@dataclass
class Kernel:
    name: str  # mangled
    base: str  # e.g. render_backward_kernel
    dtype: str | None  # "float32" / "float64" (first template argument), None when not a float template
    flags: tuple[bool, ...] = ()  # the bool template arguments (render_backward_kernel's kAbsgrad, kDirGrad, kOrigin)
    registers: int = -1
    spill_bytes: int = 0  # stores + loads
    max_threads: int = MAX_BLOCK  # .maxntid of the PTX entry (__launch_bounds__)

    def label(self) -> str:
        flags = "".join(f", {str(f).lower()}" for f in self.flags)
        return f"{self.base}<{self.dtype or '-'}, block {self.max_threads}{flags}>"


def _demangle(mangled: str) -> tuple[str, str | None, tuple[bool, ...]]:
    """(unqualified name, dtype of the first template argument, bool template arguments) of an Itanium-mangled
    kernel name."""
    pos = mangled.index("Z") + 1
    pos += mangled[pos] == "N"
    base = mangled
    while pos < len(mangled) and mangled[pos].isdigit():
        digits = re.match(r"\d+", mangled[pos:]).group()
        pos += len(digits)
        base = mangled[pos : pos + int(digits)]
        pos += int(digits)
    dtype, flags = None, ()
    if mangled[pos : pos + 1] == "I":
        dtype = {"f": "float32", "d": "float64"}.get(mangled[pos + 1])
        args = re.match(r"I((?:[fd]|Li\d+E|Lb[01]E)+)E", mangled[pos:])  # the template arguments this repo uses
        flags = tuple(b == "1" for b in re.findall(r"Lb([01])E", args.group(1))) if args else ()
    return base, dtype, flags


def parse_resources(ptxas_log: str, ptx: str) -> dict[str, Kernel]:
    """Kernels of one translation unit: registers and spills from `ptxas -v`, largest block from the PTX."""
    kernels: dict[str, Kernel] = {}
    for line in ptx.splitlines():  # ".visible .entry NAME(" ... ".maxntid X, Y, Z" ... "{"
        m = re.match(r"\s*(?:\.visible\s+)?\.entry\s+(\w+)\(", line)
        if m:
            current = kernels[m.group(1)] = Kernel(m.group(1), *_demangle(m.group(1)))
            continue
        m = re.match(r"\s*\.maxntid\s+(\d+)\s*,\s*(\d+)\s*,\s*(\d+)", line)
        if m:
            current.max_threads = int(m.group(1)) * int(m.group(2)) * int(m.group(3))
    current = None
    for line in ptxas_log.splitlines():
        m = re.search(r"Compiling entry function '(\w+)'", line)
        if m:
            current = kernels.get(m.group(1))
            assert current is not None, f"ptxas compiled {m.group(1)}, which is not an entry of the PTX"
            continue
        if current is None:
            continue
        m = re.search(r"(\d+) bytes spill stores, (\d+) bytes spill loads", line)
        if m:
            current.spill_bytes = int(m.group(1)) + int(m.group(2))
        m = re.search(r"Used (\d+) registers", line)
        if m:
            current.registers = int(m.group(1))
            current = None
    return kernels


def violations(kernels: dict[str, Kernel]) -> list[str]:
    out = []
    for k in kernels.values():
        if k.registers < 0:
            out.append(f"{k.label()}: no register count in the ptxas report")
        elif k.registers * k.max_threads > REGISTERS_PER_SM:
            out.append(f"{k.label()}: {k.registers} registers x {k.max_threads} threads = "
                       f"{k.registers * k.max_threads} > {REGISTERS_PER_SM}: cannot launch")
        if k.dtype != "float64" and k.spill_bytes > _allowed_spill(k):
            out.append(f"{k.label()}: spills {k.spill_bytes} bytes to local memory")
    return out


def _allowed_spill(k: Kernel) -> int:
    """Bytes a float32 kernel may spill: none, except the opt-in builds at 1024 threads (tiles over 16 pixels):
    the backward's ray-direction build (lens refinement, render.cu kDirGrad), whose 3 extra per-ray sums do not
    fit the 64 registers (measured 40 bytes with nvcc 13.0; docs/refinement.md), and the per-ray-origin builds
    (rolling shutter, kOrigin: 32 bytes, 100 with kDirGrad; docs/rolling_shutter.md); and the per-ray order's
    backward with ray gradients at either block (docs/compositing_order.md)."""
    opt_in = (k.base == "render_backward_kernel" and len(k.flags) == 3 and (k.flags[1] or k.flags[2])) or \
        (k.base == "render_forward_kernel" and k.flags == (True,))
    if k.base == "render_backward_ordered_kernel" and k.flags[:1] == (True,):
        # the per-ray order's backward with ray gradients (render_order.cu): it keeps its window of pending pairs
        # in local memory anyway; measured 68-72 bytes, 366 with per-ray origins at 1024 threads (nvcc 13.0)
        return 512
    return 128 if opt_in and k.max_threads == 1024 else 0


def _run_all(jobs: dict[str, list[str]]) -> dict[str, subprocess.CompletedProcess]:
    """Run the commands concurrently (the machines have few cores; nvcc is mostly single-threaded)."""
    procs = {name: subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for name, cmd in jobs.items()}
    results = {}
    for name, p in procs.items():
        out, _ = p.communicate(timeout=600)
        results[name] = subprocess.CompletedProcess(p.args, p.returncode, out, None)
    return results


# Mutations of render.cu that a correct check must reject (label -> (source transform, extra nvcc flags)).
MUTATIONS = {
    "render_unbounded": (lambda src: re.sub(r"__launch_bounds__\(\w+\)", "", src), []),
    "render_24_registers": (lambda src: re.sub(r"__launch_bounds__\(\w+\)", "", src), ["-maxrregcount=24"]),
}


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    """Compile every .cu (+ the mutations, + bindings.cpp's syntax pass) once, in parallel."""
    nvcc = _require_nvcc()
    tmp = tmp_path_factory.mktemp("csrc_build")
    units = {src.stem: (src, []) for src in CU_SOURCES}
    for label, (transform, flags) in MUTATIONS.items():
        mutated = tmp / f"{label}.cu"
        mutated.write_text(transform((CSRC / "render.cu").read_text()))
        units[label] = (mutated, flags)
    jobs = {}
    for stem, (src, flags) in units.items():
        keep = tmp / stem
        keep.mkdir()
        jobs[stem] = [str(nvcc), "-std=c++17", "-O3", "-arch=sm_90", "-Xptxas", "-v", "--keep", "--keep-dir", str(keep),
                      *flags, "-I", str(CSRC), "-c", str(src), "-o", str(keep / (stem + ".o"))]
    # The torch glue: syntax only (its object needs torch's full build flags; the JIT loader links it).
    cxx = shutil.which("c++") or shutil.which("g++")
    torch_include = Path(__import__("torch").__file__).parent / "include"
    if cxx and torch_include.is_dir():
        jobs["bindings.cpp"] = [
            cxx, "-std=c++20", "-fsyntax-only", "-I", str(CSRC), "-I", str(torch_include),
            "-I", str(torch_include / "torch" / "csrc" / "api" / "include"), "-I", str(nvcc.parent.parent / "include"),
            "-I", sysconfig.get_paths()["include"], "-DTORCH_EXTENSION_NAME=geer_cuda", str(CSRC / "bindings.cpp"),
        ]
    results = _run_all(jobs)
    kernels = {}
    for stem, (src, _) in units.items():
        ptx = next((tmp / stem).glob("*.ptx"), None)
        if results[stem].returncode == 0 and ptx is not None:
            kernels[stem] = parse_resources(results[stem].stdout, ptx.read_text())
    return tmp, results, kernels


def test_cuda_sources_exist():
    names = {p.name for p in CU_SOURCES}
    assert {"preprocess.cu", "associate.cu", "render.cu", "preprocess_backward.cu"} <= names
    assert (CSRC / "geer_math.h").is_file() and (CSRC / "bindings.cpp").is_file()


def test_csrc_compiles(build):
    tmp, results, _ = build
    failed = {name: r.stdout for name, r in results.items() if r.returncode != 0}
    for name, r in results.items():
        warnings = [ln for ln in r.stdout.splitlines() if "ptxas info" not in ln and not re.match(r"\s+\d+ bytes", ln)]
        if r.returncode == 0 and any(ln.strip() for ln in warnings):
            print(f"--- {name} (warnings)\n" + "\n".join(warnings), file=sys.stderr)
    assert not failed, "\n".join(f"--- {name}\n{out[-4000:]}" for name, out in failed.items())
    for src in CU_SOURCES:
        assert (tmp / src.stem / (src.stem + ".o")).stat().st_size > 0


def test_every_kernel_launches_at_its_largest_block(build):
    """registers x largest block <= 65,536 for every kernel and dtype; no float32 spills."""
    _, _, kernels = build
    found = {k.label(): k for stem in (s.stem for s in CU_SOURCES) for k in kernels.get(stem, {}).values()}
    report = "\n".join(f"{label}: {k.registers} registers, {k.spill_bytes} spill bytes" for label, k in sorted(found.items()))
    print(report, file=sys.stderr)
    bad = [v for stem in (s.stem for s in CU_SOURCES) for v in violations(kernels.get(stem, {}))]
    assert not bad, "\n".join(bad) + "\n\n" + report
    for base in ("render_forward_kernel", "render_backward_kernel"):
        for dtype in ("float32", "float64"):  # every tile size 1..32 has a build: up to 256 and up to 1024 threads
            blocks = {k.max_threads for k in found.values() if k.base == base and k.dtype == dtype}
            assert blocks == {256, 1024}, (base, dtype, blocks)
    # The backward with and without absgrad (kAbsgrad), ray-direction gradients (kDirGrad) and per-ray origins
    # (kOrigin), the forward with and without per-ray origins, at both blocks and in both precisions.
    flags = (False, True)
    variants = {(k.dtype, k.max_threads, k.flags) for k in found.values() if k.base == "render_backward_kernel"}
    assert variants == {(d, b, (f, g, o)) for d in ("float32", "float64") for b in (256, 1024) for f in flags
                        for g in flags for o in flags}
    variants = {(k.dtype, k.max_threads, k.flags) for k in found.values() if k.base == "render_forward_kernel"}
    assert variants == {(d, b, (o,)) for d in ("float32", "float64") for b in (256, 1024) for o in flags}
    # The per-ray order's (render_order.cu): forward [per-ray origins], backward [ray gradients, per-ray origins].
    variants = {(k.dtype, k.max_threads, k.flags) for k in found.values() if k.base == "render_backward_ordered_kernel"}
    assert variants == {(d, b, (g, o)) for d in ("float32", "float64") for b in (256, 1024) for g in flags for o in flags}
    variants = {(k.dtype, k.max_threads, k.flags) for k in found.values() if k.base == "render_forward_ordered_kernel"}
    assert variants == {(d, b, (o,)) for d in ("float32", "float64") for b in (256, 1024) for o in flags}
    for base in ("preprocess_forward_kernel", "preprocess_backward_kernel", "count_tiles_kernel", "emit_pairs_kernel"):
        assert {k.dtype for k in found.values() if k.base == base} == {"float32", "float64"}, base


def test_resource_check_rejects_mutated_kernels(build):
    """The check is not vacuous: render.cu without launch bounds cannot launch its float64 backward at 1024
    threads (96-odd registers), and capped at 24 registers its float32 kernels spill."""
    _, results, kernels = build
    for label in MUTATIONS:
        assert results[label].returncode == 0, results[label].stdout[-3000:]
    unbounded = violations(kernels["render_unbounded"])
    assert any("render_backward_kernel<float64" in v and "cannot launch" in v for v in unbounded), unbounded
    assert all(k.max_threads == MAX_BLOCK for k in kernels["render_unbounded"].values())
    capped = violations(kernels["render_24_registers"])
    assert any("<float32" in v and "spills" in v for v in capped), capped


def test_every_launch_and_cub_call_is_checked():
    """A launch that fails must raise at its own call (geer_launchers.h): the line after every <<<...>>> is
    GEER_KERNEL_LAUNCH_CHECK, and every CUB call is wrapped in GEER_CUDA_CHECK."""
    launches = 0
    for src in CU_SOURCES:
        lines = src.read_text().splitlines()
        for i, line in enumerate(lines):
            if "<<<" in line:
                launches += 1
                nxt = next((ln for ln in lines[i + 1 :] if ln.strip()), "")
                assert "GEER_KERNEL_LAUNCH_CHECK(" in nxt, f"{src.name}:{i + 1}: launch without a check: {line.strip()}"
            if re.search(r"\bcub::\w+::\w+\(", line):
                context = " ".join(lines[max(0, i - 1) : i + 1])
                assert "GEER_CUDA_CHECK(" in context, f"{src.name}:{i + 1}: unchecked CUB call: {line.strip()}"
    assert launches >= 7


def test_missing_nvcc_fails_in_ci(monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "_nvcc", lambda: None)
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="CI must have the CUDA toolkit"):
        _require_nvcc()
    monkeypatch.delenv("CI")
    with pytest.raises(pytest.skip.Exception, match="nvcc not found"):
        _require_nvcc()


def test_parse_resources_on_a_known_report():
    """The parser on a fixed ptxas/PTX pair (independent of the compiler at hand)."""
    ptx = (".visible .entry _ZN4geer1kIdLi1024EEEvv(\n)\n.maxntid 1024, 1, 1\n{\n}\n"
           ".visible .entry _ZN4geer1kIfLi256ELb1EEEvv(\n)\n.maxntid 256, 1, 1\n{\n}\n"
           ".visible .entry _ZN4geer6rangesEPKmlPi(\n)\n{\n}\n")
    log = ("ptxas info    : Compiling entry function '_ZN4geer1kIdLi1024EEEvv' for 'sm_90'\n"
           "ptxas info    : Function properties for _ZN4geer1kIdLi1024EEEvv\n"
           "    0 bytes stack frame, 0 bytes spill stores, 0 bytes spill loads\n"
           "ptxas info    : Used 96 registers, used 1 barriers, 30212 bytes smem\n"
           "ptxas info    : Compiling entry function '_ZN4geer1kIfLi256ELb1EEEvv' for 'sm_90'\n"
           "ptxas info    : Function properties for _ZN4geer1kIfLi256ELb1EEEvv\n"
           "    8 bytes stack frame, 8 bytes spill stores, 4 bytes spill loads\n"
           "ptxas info    : Used 255 registers, used 1 barriers, 30212 bytes smem\n"
           "ptxas info    : Compiling entry function '_ZN4geer6rangesEPKmlPi' for 'sm_90'\n"
           "ptxas info    : Used 70 registers, used 0 barriers\n")
    kernels = parse_resources(log, ptx)
    k64, k32, kr = kernels.values()
    assert (k64.base, k64.dtype, k64.registers, k64.max_threads) == ("k", "float64", 96, 1024)
    assert (k32.dtype, k32.registers, k32.spill_bytes, k32.max_threads) == ("float32", 255, 12, 256)
    assert k64.flags == () and k32.flags == (True,) and k32.label() == "k<float32, block 256, true>"
    assert (kr.base, kr.dtype, kr.max_threads) == ("ranges", None, MAX_BLOCK)
    v = violations(kernels)
    assert len(v) == 3 and "96 registers x 1024" in v[0] and "spills 12 bytes" in v[1] and "70 registers x 1024" in v[2]


def test_cuda_extension_jit_builds():
    """The whole extension (bindings.cpp + kernels, torch's flags, C++20, sm_90) builds and links with the same
    loader the backend uses; importing it needs no GPU. Cached under .cache/geer_ext like a normal load."""
    nvcc = _require_nvcc()
    env = dict(os.environ, CUDA_HOME=str(nvcc.parent.parent), PATH=f"{nvcc.parent}{os.pathsep}{os.environ.get('PATH', '')}")
    code = ("from geer_ns.render import cuda_backend; m = cuda_backend.load_extension(); "
            "print(sorted(n for n in dir(m) if not n.startswith('_')))")
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=900, check=False)
    assert r.returncode == 0, (r.stdout + r.stderr)[-6000:]
    assert "render_backward" in r.stdout and "associate" in r.stdout
