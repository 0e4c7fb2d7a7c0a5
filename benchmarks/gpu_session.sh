#!/usr/bin/env bash
# The GPU session for issue 3 in one device call: kernels against the twin, memcheck, then the benchmark.
#
# Here first (once, needs the network):  bash ../shared/device/fetch-wheels.sh     (-> .device/, git-ignored)
# Then one device call, from the repository root:
#   run(command="bash benchmarks/gpu_session.sh", carry=[".device"], timeout_s=600)
# Optional: stages as arguments (default: tests memcheck bench), e.g. `bash benchmarks/gpu_session.sh bench`;
# BENCH_ARGS="--scenes garden,donut" is passed to bench_gpu.py; GEER_COMMIT=<sha> is recorded as the commit
# where the copied checkout has no .git; SESSION_LIMIT_S (default 570) is the wall time this script plans for.
#
# Device time (H100, from ../shared/device/README.md and estimates; nothing here has run on a GPU yet):
#   setup (pip install of the carried wheels)      ~30 s
#   gsplat 1.4.0 JIT build                         ~195 s with MAX_JOBS=16, TORCH_CUDA_ARCH_LIST=9.0. It starts in
#                                                  the background right after setup, overlapping the geer build
#                                                  (< 1 min) and the tests, and the benchmark waits for it.
#   tests/test_cuda_gpu.py                         ~1-3 min (includes the geer_cuda JIT build)
#   compute-sanitizer memcheck, small fwd+bwd      ~1-2 min (CUDA/torch start-up under memcheck dominates)
#   benchmarks/bench_gpu.py                        gets what is left of SESSION_LIMIT_S (it stops starting rows
#                                                  when its budget is spent and marks the rest "skipped")
# The device tool caps one command at 600 s, so one call fits setup + build + tests + memcheck + ~4-5 min of
# benchmark. For the full table, a second call `bash benchmarks/gpu_session.sh bench` (fresh machine: setup and
# both JIT builds again, ~4 min, then ~5 min of benchmark; BENCH_ARGS can pick the scenes not yet done) keeps
# the whole session near 20 minutes of the 30-minute device budget.
#
# Everything that must come back is written under $OUT (at most 8 files): summary.txt, setup.log,
# gsplat_build.log, pytest_cuda.log, memcheck.log, bench.log, gpu_results.md, gpu_results.json. The results are
# also written to benchmarks/gpu_results.{md,json} in the (device copy of the) checkout.
set -u
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/geer_gpu_session}  # the device tool sets $OUT
mkdir -p "$OUT"
STAGES=${*:-tests memcheck bench}
LIMIT=${SESSION_LIMIT_S:-570}
RESULTS=${RESULTS:-benchmarks/gpu_results.md}
SUMMARY="$OUT/summary.txt"
: >"$SUMMARY"
note() { echo "[$(date +%T) +${SECONDS}s] $*" | tee -a "$SUMMARY"; }
has_stage() { [[ " $STAGES " == *" $1 "* ]]; }

# JIT build caches inside the checkout (git-ignored .cache/), so a warm machine reuses them between calls.
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-$PWD/.cache/torch_extensions}
export GEER_EXT_DIR=${GEER_EXT_DIR:-$PWD/.cache/geer_ext}
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16}
export PYTHONUNBUFFERED=1

# ---- setup: the carried wheels (nerfstudio, gsplat, plyfile, ...) on PYTHONPATH
if [ -f .device/setup.sh ]; then
  # shellcheck disable=SC1091
  source .device/setup.sh >"$OUT/setup.log" 2>&1 && note "setup ok" || note "setup FAILED (see setup.log)"
else
  note "no .device/setup.sh: run 'bash ../shared/device/fetch-wheels.sh' here and carry .device (gsplat rows will fail)"
fi
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>&1 | tee -a "$SUMMARY"
if python3 -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)"; then
  HAVE_CUDA=1
else  # a smoke test of this script without a GPU: no builds, no sanitizer; the tests skip themselves
  HAVE_CUDA=0
  note "no CUDA device: skipping the gsplat build and memcheck"
fi

# ---- gsplat's CUDA code: JIT build in the background (~195 s), overlapping the stages below
GSPLAT_PID=""
if has_stage bench && [ "$HAVE_CUDA" = 1 ]; then
  ( python3 - <<'EOF'
import time
t = time.time()
from gsplat.cuda._backend import _C
assert _C is not None, "gsplat: no CUDA backend (build failed or no CUDA toolkit)"
print(f"gsplat CUDA backend built/loaded in {time.time() - t:.0f} s")
EOF
  ) >"$OUT/gsplat_build.log" 2>&1 &
  GSPLAT_PID=$!
  note "gsplat JIT build started in the background (pid $GSPLAT_PID)"
fi

# ---- the CUDA kernels against the PyTorch twin (builds geer_cuda first)
if has_stage tests; then
  note "pytest tests/test_cuda_gpu.py"
  timeout 300 python3 -m pytest tests/test_cuda_gpu.py -s -q -rs >"$OUT/pytest_cuda.log" 2>&1
  rc=$?
  note "pytest rc=$rc ($(tail -n 1 "$OUT/pytest_cuda.log"))"
fi

# ---- compute-sanitizer memcheck on a small forward + backward through render(..., backend="cuda")
if has_stage memcheck && [ "$HAVE_CUDA" = 1 ]; then
  cat >/tmp/geer_memcheck.py <<'EOF'
import math
import torch
from geer_ns.cameras import OpenCVFisheyeCamera
from geer_ns.render import RayGrid, render

dev = "cuda"
gen = torch.Generator().manual_seed(0)
n = 300
means = torch.randn(n, 3, generator=gen) * 0.8 + torch.tensor([0.0, 0.0, 3.0])
quats = torch.randn(n, 4, generator=gen)
scales = torch.exp(math.log(0.05) + math.log(6.0) * torch.rand(n, 3, generator=gen))
opacities = 0.05 + 0.9 * torch.rand(n, generator=gen)
rgb = torch.rand(n, 3, generator=gen)
sh = torch.randn(n, 4, 3, generator=gen) * 0.3  # SH degree 1: exercises the SH forward/backward too
fd, fv = OpenCVFisheyeCamera.equidistant(48, 48, 24 / (math.pi / 2), 24 / (math.pi / 2), 24.0, 24.0).pixel_rays()
fv = fv & (fd[..., 2] >= 0)  # the 180 degree circle: inactive corner tiles at tile size 8
cases = [
    ("beap 40x24 tile 16 rgb", RayGrid.beap(40, 24, math.radians(90), math.radians(60), tile_size=16), rgb),
    ("fisheye 48 tile 8 sh1", RayGrid.from_rays(fd, fv, tile_size=8), sh),
    ("fisheye 48 tile 16 rgb", RayGrid.from_rays(fd, fv, tile_size=16), rgb),
]
viewmat = torch.eye(4, device=dev)
for name, grid, colors in cases:
    leaves = [t.to(dev).requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
    out = render(*leaves, viewmat, grid, background=torch.full((3,), 0.1, device=dev), backend="cuda")
    w = torch.rand(out.rgb.shape, generator=gen).to(dev)
    loss = (out.rgb * w).sum() + 0.1 * out.depth.sum() + out.accumulation.sum()
    loss.backward()
    torch.cuda.synchronize()
    ok = all(bool(torch.isfinite(t.grad).all()) for t in leaves)
    print(f"{name}: pairs {int(out.tile_counts.sum())}, loss {float(loss):.4f}, grads finite {ok}", flush=True)
print("memcheck snippet done")
EOF
  note "building/loading geer_cuda outside the sanitizer"
  timeout 240 python3 -c "from geer_ns.render import cuda_backend; cuda_backend.load_extension()" >"$OUT/memcheck.log" 2>&1
  note "compute-sanitizer --tool memcheck (small forward + backward, backend=cuda)"
  timeout 300 compute-sanitizer --tool memcheck --print-limit 50 python3 /tmp/geer_memcheck.py >>"$OUT/memcheck.log" 2>&1
  rc=$?
  note "memcheck rc=$rc ($(grep -m1 'ERROR SUMMARY' "$OUT/memcheck.log" || echo 'no ERROR SUMMARY line'))"
fi

# ---- the benchmark, with whatever time is left
if has_stage bench; then
  if [ -n "$GSPLAT_PID" ]; then
    note "waiting for the gsplat build"
    wait "$GSPLAT_PID"
    rc=$?
    note "gsplat build rc=$rc ($(tail -n 1 "$OUT/gsplat_build.log"))"
  fi
  BUDGET=$((LIMIT - SECONDS - 60))  # rows already started finish; then the files are copied to $OUT
  if [ "$BUDGET" -lt 30 ]; then BUDGET=30; fi
  note "bench_gpu.py with a time budget of ${BUDGET} s ${BENCH_ARGS:-}"
  # shellcheck disable=SC2086
  timeout $((BUDGET + 50)) python3 benchmarks/bench_gpu.py --out "$RESULTS" \
    --time-budget-s "$BUDGET" ${BENCH_ARGS:-} >"$OUT/bench.log" 2>&1
  rc=$?
  note "bench rc=$rc ($(tail -n 1 "$OUT/bench.log"))"
  cp "$RESULTS" "${RESULTS%.md}.json" "$OUT/" 2>/dev/null || note "no benchmark results to copy"
fi
note "done"
