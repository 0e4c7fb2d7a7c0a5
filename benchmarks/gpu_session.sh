#!/usr/bin/env bash
# The GPU session (issue 11; issue 8 item 7): two device calls, back to back on one warm machine, inside the 15
# device-minutes a session has (the machine's start, 1-2 min, included); what each session brought back is in
# benchmarks/gpu_sessions.md. A GPU at hand runs this first: its first stage after the build is the self-test
# verdict (docs/cuda.md).
#
# 1. Here, on the CPU side, once per commit (fetching the wheels needs the network; later runs reuse them):
#        bash benchmarks/gpu_session.sh prep
#    fills .device/ (git-ignored; ../shared does not travel): the wheels for gsplat/nerfstudio and setup.sh
#    (../shared/device/fetch-wheels.sh), every data file configs/bench_gpu.yaml references (.device/data/, via
#    benchmarks/gpu_prep.py) and .device/COMMIT. Synthetic scenes are generated on the device from seeds.
# 2. Then exactly these two `run` calls, the second issued as soon as the first returns (a machine stays warm
#    only ~30 s after a call; a cold second call rebuilds everything and gets little benchmark time):
#        run(command="CALL_LIMIT_S=290 bash benchmarks/gpu_session.sh call1", carry=[".device"], timeout_s=310)
#        run(command="CALL_LIMIT_S=400 bash benchmarks/gpu_session.sh call2", carry=[".device"], timeout_s=420)
#    then give_back. Each call plans for CALL_LIMIT_S (default 300 s) and stops its stages in time, so that
#    start (~2 min) + 5 + 7 min + the gap stay under 15 minutes.
#
# call1 (~5 min)  the wheels into /tmp/site; gsplat 1.4.0's JIT build started DETACHED (setsid: it outlives this
#                 call and is ready for call 2; ~195 s with 16 jobs); geer's CUDA extension built at the same time;
#                 then FIRST the self-test verdict (geer-doctor --selftest: the suite of docs/cuda.md in a child
#                 process, the kernels against the PyTorch renderer, capacity case included; SELFTEST_S, default
#                 100 s), then, in parallel: tests/test_cuda_gpu.py (kernels vs the PyTorch twin, every tile build, a
#                 refused launch raising at its call, float64 backward repeatability) and compute-sanitizer
#                 memcheck, racecheck and synccheck on benchmarks/gpu_sanitize.py with
#                 PYTORCH_NO_CUDA_MEMORY_CACHING=1 ("Device not supported" is recorded, not fatal).
#                 $OUT: summary.txt and logs.tgz (setup.log build_geer.log doctor.log selftest/ pytest_cuda.log
#                 memcheck.log racecheck.log synccheck.log gsplat_build.log): a call brings back 8 files at most.
# call2 (~6 min)  waits for the gsplat build (builds it again on a fresh machine); trains on the dev room (carried:
#                 the pose refinement step time on the CUDA kernels, benchmarks/pose_refinement_step.py, and
#                 geer-compare: geer against splatfacto and splatfacto-fisheye); then benchmarks/bench_gpu.py
#                 with the time left: headline rows first (1M Gaussians, pinhole 1920x1080 and 180 degree fisheye,
#                 geer-cuda vs gsplat `rasterization`; configs/bench_gpu.yaml `first`), each row written as it ends.
#                 $OUT: summary.txt gpu_results.md gpu_results.json compare.md pose_refinement_gpu.md and logs.tgz
#                 (setup.log build_geer.log gsplat_build.log pose_step.log compare.log bench.log).
# Builds and state live in /tmp (kept on a warm machine between calls, away from the copied tree).
# Without a GPU the calls run as a smoke test (stages that need CUDA say so and skip).
set -u
cd "$(dirname "$0")/.."
STAGE=${1:-}
PY=${PYTHON:-python3}
OUT=${OUT:-/tmp/geer_gpu_session/out}  # the device tool sets $OUT
STATE=${GEER_SESSION_STATE:-/tmp/geer_gpu_session}
LIMIT=${CALL_LIMIT_S:-300}
mkdir -p "$OUT" "$STATE"
SUMMARY="$OUT/summary.txt"
note() { echo "[$(date +%T) +${SECONDS}s] $*" | tee -a "$SUMMARY"; }
left() { echo $((LIMIT - SECONDS)); }

export TORCH_EXTENSIONS_DIR=$STATE/torch_extensions GEER_EXT_DIR=$STATE/geer_ext
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} PYTHONUNBUFFERED=1
export PYTHONPATH=$STATE/site:$PWD${PYTHONPATH:+:$PYTHONPATH}
export PATH=$PATH:${CUDA_HOME:-/usr/local/cuda}/bin  # nvcc (JIT builds) and compute-sanitizer
[ -f .device/COMMIT ] && export GEER_COMMIT="$(cat .device/COMMIT)"

prep() {  # CPU side
  "${PYTHON:-.venv/bin/python}" benchmarks/gpu_prep.py || return 1
  # fetch-wheels.sh writes .git/info/exclude: run it from a main checkout (in a git worktree .git is a file).
  ls .device/whl/*.whl >/dev/null 2>&1 || bash ../shared/device/fetch-wheels.sh \
    || { echo "prep: no wheels in .device/whl (gsplat rows need them): run ../shared/device/fetch-wheels.sh" >&2; return 1; }
  cp ../shared/device/setup.sh .device/ 2>/dev/null
  # the dev fisheye room (call 2 trains on it: pose refinement step, geer-compare)
  [ -d .device/data/fisheye_room_dev ] || cp -r ../shared/data/fisheye_room_dev .device/data/
  du -sh .device
}

HAVE_CUDA=""
have_cuda() {  # asked once (importing torch takes seconds)
  if [ -z "$HAVE_CUDA" ]; then
    "$PY" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)" 2>/dev/null && HAVE_CUDA=1 || HAVE_CUDA=0
  fi
  [ "$HAVE_CUDA" = 1 ]
}

setup() {  # the carried wheels into $STATE/site, once per machine
  if [ -f "$STATE/site.ok" ]; then note "wheels already in $STATE/site (warm machine)"; return 0; fi
  if ! ls .device/whl/*.whl >/dev/null 2>&1; then note "no .device/whl: run 'bash benchmarks/gpu_session.sh prep' here first"; return 1; fi
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$STATE/site" \
    .device/whl/*.whl >"$OUT/setup.log" 2>&1 && touch "$STATE/site.ok"
  local rc=$?
  note "wheels installed rc=$rc"
  return $rc
}

gsplat_build_start() {  # detached: survives the end of this call (the device tool keeps setsid processes)
  if [ -f "$STATE/gsplat.done" ]; then return 0; fi
  if [ -f "$STATE/gsplat.pid" ] && kill -0 "$(cat "$STATE/gsplat.pid")" 2>/dev/null; then return 0; fi
  # Never two builds at once: gsplat's loader deletes the build folder's lock and, with no .so yet, the folder.
  MAX_JOBS=${GSPLAT_JOBS:-10} setsid nohup bash -c "echo \$\$ >'$STATE/gsplat.pid'
    '$PY' -c 'import time; t = time.time()
from gsplat.cuda._backend import _C
assert _C is not None, \"gsplat: no CUDA backend\"
print(f\"gsplat CUDA backend built/loaded in {time.time() - t:.0f} s\")' >'$STATE/gsplat_build.log' 2>&1
    echo \$? >'$STATE/gsplat.done'" </dev/null >/dev/null 2>&1 &
  sleep 1
  note "gsplat JIT build started detached (pid $(cat "$STATE/gsplat.pid" 2>/dev/null), log $STATE/gsplat_build.log)"
}

gsplat_wait() {  # $1: latest second of this call to wait until; returns 0 when gsplat's backend is built
  while [ ! -f "$STATE/gsplat.done" ] && [ "$SECONDS" -lt "$1" ]; do sleep 5; done
  cp "$STATE/gsplat_build.log" "$OUT/" 2>/dev/null
  if [ -f "$STATE/gsplat.done" ]; then
    note "gsplat build rc=$(cat "$STATE/gsplat.done") ($(tail -n 1 "$STATE/gsplat_build.log" 2>/dev/null))"
    [ "$(cat "$STATE/gsplat.done")" = 0 ]
  else
    note "gsplat build still running at +${SECONDS}s"
    return 1
  fi
}

build_geer() {
  note "building geer_cuda (MAX_JOBS=16)"
  MAX_JOBS=16 timeout "$1" "$PY" -c "import time; t = time.time()
from geer_ns.render import cuda_backend
cuda_backend.load_extension(verbose=True)
print(f'geer_cuda built/loaded in {time.time() - t:.0f} s')" >"$OUT/build_geer.log" 2>&1
  local rc=$?
  note "geer_cuda build rc=$rc ($(tail -n 1 "$OUT/build_geer.log"))"
  # A build cut short: what its folders hold (objects written, a lock left) says where it stood.
  [ "$rc" = 0 ] || ls -la "$GEER_EXT_DIR"/geer_cuda_* >>"$OUT/build_geer.log" 2>&1
  return $rc
}

selftest() {  # the verdict backend="auto" will use: geer-doctor runs the self-test now, in its child process
  note "self-test (geer-doctor --selftest, suite limit ${SELFTEST_S:-100} s)"
  GEER_SELFTEST_TIMEOUT_S=${SELFTEST_S:-100} timeout $(( ${SELFTEST_S:-100} + 60 )) "$PY" -m geer_ns.doctor --selftest \
    >"$OUT/doctor.log" 2>&1
  note "doctor rc=$? ($(grep -m1 'auto -> cuda\|auto -> torch' "$OUT/doctor.log" | cut -c1-300 || echo 'no CUDA line'))"
  mkdir -p "$OUT/selftest" && cp "$GEER_EXT_DIR"/selftest/cuda_* "$OUT/selftest/" 2>/dev/null
  grep -h '^FAIL\|^ok' "$OUT"/selftest/*.log 2>/dev/null | head -n 20 >>"$SUMMARY"
}

sanitize() {  # $1 tool, $2 seconds
  (
    export PYTORCH_NO_CUDA_MEMORY_CACHING=1
    timeout "$2" compute-sanitizer --tool "$1" --print-limit 50 --error-exitcode 3 \
      "$PY" benchmarks/gpu_sanitize.py >"$OUT/$1.log" 2>&1
    rc=$?
    if grep -q "Device not supported" "$OUT/$1.log"; then
      note "$1: NOT AVAILABLE on this machine (Device not supported), rc=$rc"
    else
      note "$1 rc=$rc ($(grep -m1 'ERROR SUMMARY\|RACECHECK SUMMARY' "$OUT/$1.log" || echo 'no summary line'); $(grep -c 'finite True' "$OUT/$1.log")/3 cases finite)"
    fi
  )
}

call1() {
  if command -v nvidia-smi >/dev/null; then
    nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm --format=csv,noheader 2>&1 | tee -a "$SUMMARY"
  fi
  note "commit: ${GEER_COMMIT:-unknown}"
  if ! have_cuda; then note "no CUDA device: smoke test only (no builds, no sanitizers; the GPU tests skip)"; fi
  (setup && have_cuda && gsplat_build_start) &  # a subshell: the detached build is no child to wait for
  local setup_pid=$! built=1
  if have_cuda; then build_geer $(( $(left) - 150 )) || built=0; fi
  wait "$setup_pid"
  if have_cuda && [ "$built" = 1 ]; then selftest; fi
  note "pytest tests/test_cuda_gpu.py and the sanitizers, in parallel"
  timeout $(( $(left) - 15 )) "$PY" -m pytest tests/test_cuda_gpu.py \
    tests/test_pose_gradients.py::test_cuda_kernels_give_pose_and_ray_gradients -s -q -rfEs -p no:cacheprovider \
    >"$OUT/pytest_cuda.log" 2>&1 &
  local pids=() pytest_pid=$!
  if have_cuda && [ "$built" = 0 ]; then
    note "no sanitizer runs: geer_cuda did not build (build_geer.log); pytest may finish a build cut short"
  elif have_cuda && command -v compute-sanitizer >/dev/null; then
    local t=$(( $(left) - 20 ))
    for tool in memcheck racecheck synccheck; do sanitize "$tool" "$t" & pids+=($!); done
  elif have_cuda; then
    note "compute-sanitizer not on PATH: no sanitizer runs"
  fi
  wait "$pytest_pid"
  note "pytest rc=$? ($(tail -n 1 "$OUT/pytest_cuda.log"))"
  grep -E "^(FAILED|ERROR|SKIPPED)|float64 backward|CUDA 512x384|built/loaded" "$OUT/pytest_cuda.log" | head -n 40 >>"$SUMMARY"
  [ "${#pids[@]}" = 0 ] || wait "${pids[@]}"
  cp "$STATE/gsplat_build.log" "$OUT/" 2>/dev/null
  local gs="not started"
  [ -f "$STATE/gsplat.pid" ] && gs="still running, detached"
  [ -f "$STATE/gsplat.done" ] && gs="rc $(cat "$STATE/gsplat.done")"
  note "call1 done (gsplat build: $gs)"
}

training() {  # $1: 1 when gsplat's backend is built (splatfacto's runs need it)
  local room=.device/data/fisheye_room_dev methods=(geer)
  if [ ! -f "$room/transforms_fisheye.json" ]; then note "no $room: no training stages (prep copies it)"; return 0; fi
  note "pose refinement step time (SO3xR3 vs fixed, CUDA kernels, dev room 384^2)"
  timeout 60 "$PY" benchmarks/pose_refinement_step.py --device cuda --size 384 --rounds 50 --room "$room" \
    --out "$OUT/pose_refinement_gpu.md" >"$OUT/pose_step.log" 2>&1
  note "pose step rc=$? ($(grep 'pose refinement (SO3xR3)' "$OUT/pose_step.log" || tail -n 1 "$OUT/pose_step.log"))"
  [ "$1" = 1 ] && methods+=(splatfacto splatfacto-fisheye)
  note "geer-compare on the dev room (${methods[*]}, ${COMPARE_STEPS:-1000} steps, limit ${COMPARE_S:-170} s)"
  timeout "${COMPARE_S:-170}" "$PY" -m geer_ns.compare --data "$room/transforms_fisheye.json" \
    --steps "${COMPARE_STEPS:-1000}" --methods "${methods[@]}" --output-dir "$STATE/compare" >"$OUT/compare.log" 2>&1
  note "compare rc=$?"
  cp "$STATE/compare/compare.md" "$OUT/" 2>/dev/null && grep '^|' "$OUT/compare.md" | head -n 8 >>"$SUMMARY"
}

call2() {
  note "commit: ${GEER_COMMIT:-unknown}"
  if ! have_cuda; then note "no CUDA device: smoke test only, no benchmark; call2 done"; return 0; fi
  setup || note "setup failed: gsplat rows will fail"
  (gsplat_build_start)  # no-op when call 1 started it on this (warm) machine; a subshell, as in call 1
  build_geer 240 &  # a no-op load on a warm machine, unless the copied sources look newer to ninja
  local geer_pid=$! gsplat_ok=1
  gsplat_wait $(( LIMIT - 150 )) || gsplat_ok=0
  wait "$geer_pid"
  local extra=()
  [ "$gsplat_ok" = 1 ] || extra+=(--no-gsplat)  # never import gsplat's backend while its build runs
  training "$gsplat_ok"
  local budget=$(( $(left) - 45 ))
  [ "$budget" -lt 30 ] && budget=30
  note "bench_gpu.py, time budget ${budget} s ${extra[*]:-} ${BENCH_ARGS:-}"
  # shellcheck disable=SC2086
  timeout $(( budget + 30 )) "$PY" benchmarks/bench_gpu.py --out "$OUT/gpu_results.md" --time-budget-s "$budget" \
    "${extra[@]}" ${BENCH_ARGS:-} >"$OUT/bench.log" 2>&1
  note "bench rc=$? ($(tail -n 1 "$OUT/bench.log"))"
  note "$(grep -c '"forward_ms"' "$OUT/gpu_results.json" 2>/dev/null || echo 0) rows with a forward time in gpu_results.json"
  note "call2 done: copy \$OUT/gpu_results.{md,json} to benchmarks/ with the device, commit and command they record"
}

pack() {  # at most 8 files come back from a call: the logs go into one archive beside the summary and results
  local keep=" summary.txt gpu_results.md gpu_results.json compare.md pose_refinement_gpu.md "
  ( cd "$OUT" || exit 1
    tar czf "$STATE/logs.tgz" --exclude=./logs.tgz . 2>/dev/null
    for f in * .[!.]*; do [ -e "$f" ] && [[ "$keep" != *" $f "* ]] && rm -rf -- "$f"; done
    mv "$STATE/logs.tgz" logs.tgz )
}

case "$STAGE" in
  prep) prep ;;
  call1) : >"$SUMMARY"; call1; pack ;;
  call2) : >"$SUMMARY"; call2; pack ;;
  *) echo "usage: bash benchmarks/gpu_session.sh prep|call1|call2 (see the header)" >&2; exit 2 ;;
esac
