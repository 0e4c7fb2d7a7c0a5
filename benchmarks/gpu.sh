#!/usr/bin/env bash
# The GPU benchmark, for any machine with a CUDA GPU: from the repository root, with geer-ns installed (the
# project's .venv from scripts/setup.sh, or your nerfstudio environment: PY=python),
#
#     bash benchmarks/gpu.sh        # writes benchmarks/gpu.md (STEPS=N: geer-compare's steps, default 2000)
#
# 1. the self-test: geer-doctor --selftest, the kernels against the PyTorch renderer on this GPU (docs/cuda.md);
# 2. geer against gsplat: python -m benchmarks.gpu_speed (configs/bench_gpu.yaml: time, tile pairs, memory, error);
# 3. geer-compare on the dev room's fisheye views: geer against splatfacto and splatfacto with gsplat's fisheye EWA.
# Steps 2 and 3 read the test data (docs/test_data.md). The first call of gsplat builds its CUDA code (minutes).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-$([ -x .venv/bin/python ] && echo .venv/bin/python || echo python)}
STEPS=${STEPS:-2000}
WORK=${WORK:-$(mktemp -d)}
"$PY" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 'benchmarks/gpu.sh: no CUDA GPU here')"
"$PY" -m geer_ns.doctor --selftest 2>&1 | tee "$WORK/doctor.txt"
"$PY" -m benchmarks.gpu_speed --out "$WORK/speed.md"
ROOM=$("$PY" -c "from benchmarks.common import test_data; print(test_data('fisheye_room_dev'))")
"$PY" -m geer_ns.compare --data "$ROOM/transforms_fisheye.json" --steps "$STEPS" \
  --methods geer splatfacto splatfacto-fisheye --output-dir "$WORK/compare"
{
  echo "# The GPU benchmark: self-test, geer against gsplat, geer against splatfacto"
  echo
  echo "- device: $("$PY" -c 'from benchmarks.common import device; print(device())')"
  echo "- commit: $(git rev-parse --short HEAD)"
  echo "- command: \`STEPS=$STEPS bash benchmarks/gpu.sh\`"
  echo; echo "## Self-test (geer-doctor --selftest)"; echo; echo '```text'; cat "$WORK/doctor.txt"; echo '```'
  echo; echo "## geer against gsplat (python -m benchmarks.gpu_speed)"; echo
  sed -e '1,/^$/d' "$WORK/speed.md"
  echo; echo "## geer-compare on the dev room's 384^2 fisheye views, $STEPS steps"; echo
  sed -e '/^## geer-compare/d' "$WORK/compare/compare.md"
} > benchmarks/gpu.md
echo "wrote benchmarks/gpu.md (outputs in $WORK)"
