#!/usr/bin/env bash
# geer-process-data on the dev fisheye room (48 Blender views, 180-degree equidistant fisheye, 384 px):
# run time, pose / focal errors against the renderer's poses, and ns-eval of geer trained on the recovered
# poses vs on the true poses (same schedule, steps and held-out views: every 8th frame). The trainings run side
# by side, one thread each. Writes what it prints to benchmarks/process_data.md.
#   bash benchmarks/process_data.sh [steps]     (OUT=dir keeps the outputs)
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${1:-200}
OUT=${OUT:-$(mktemp -d)}
PY=${PY:-$([ -x .venv/bin/python ] && echo .venv/bin/python || echo python)}
BIN=$(dirname "$(command -v "$PY")")
export PYTHONPATH=$PWD
DEV=$("$PY" -c 'from benchmarks.common import test_data; print(test_data("fisheye_room_dev"))')
$PY -c 'from geer_ns.render.cuda_backend import load_cpu_ops; load_cpu_ops()'  # build outside the timings

measure() {
TIMEFORMAT="geer-process-data: wall %R s, CPU %U s user + %S s system"
time $PY -m geer_ns.process_data --data "$DEV/images_fisheye" --output-dir "$OUT/recovered" --num-threads 2 \
  --overwrite True > "$OUT/process_data.log" 2>&1
$PY -c "import json; print('stages (s):', json.load(open('$OUT/recovered/process_data_report.json'))['timings_s'])"
$PY -m geer_ns.process_data.evaluate "$OUT/recovered/transforms.json" "$DEV/transforms_fisheye.json"

train() {  # name data
  OMP_NUM_THREADS=1 "$BIN/ns-train" geer --data "$2" --output-dir "$OUT/runs" --experiment-name "$1" \
    --timestamp bench --max-num-iterations "$STEPS" --vis tensorboard --viewer.quit-on-train-completion True \
    --steps-per-eval-image 0 --steps-per-eval-all-images 0 --steps-per-save "$STEPS" \
    --pipeline.model.renderer-backend cpu --pipeline.model.num-downscales 2 \
    --pipeline.model.resolution-schedule 1000000 --pipeline.model.warmup-length 60 \
    --pipeline.model.refine-every 60 --pipeline.model.stop-split-at "$STEPS" \
    --pipeline.model.central-half-angles-deg 60 60 \
    nerfstudio-data --eval-mode interval --eval-interval 8 > "$OUT/train_$1.log" 2>&1
  OMP_NUM_THREADS=1 "$BIN/ns-eval" --load-config "$OUT/runs/$1/geer/bench/config.yml" \
    --output-path "$OUT/eval_$1.json" > "$OUT/eval_$1.log" 2>&1
}
train true "$DEV/transforms_fisheye.json" & a=$!
train recovered "$OUT/recovered" & b=$!
wait $a && wait $b
$PY - "$OUT" <<'PYEOF'
import json, sys
out = sys.argv[1]
res = {k: json.load(open(f"{out}/eval_{k}.json"))["results"] for k in ("true", "recovered")}
keys = ("psnr", "ssim", "central_psnr", "peripheral_psnr")
for k, r in res.items():
    print(f"{k:19s}", {m: round(r[m], 3) for m in keys})
print("recovered - true:", {m: round(res["recovered"][m] - res["true"][m], 3) for m in keys})
PYEOF
}

measure 2>&1 | tee "$OUT/summary.txt"
{ printf '# geer-process-data on the dev fisheye room\n\n- device: CPU (%s), %s cores (load average %s)\n' \
    "$(uname -m)" "$(nproc)" "$(cut -d' ' -f1 /proc/loadavg)"
  printf -- '- commit: %s\n- command: `bash benchmarks/process_data.sh %s`\n\n```text\n' "$(git rev-parse --short HEAD)" "$STEPS"
  cat "$OUT/summary.txt"; printf '```\n'; } > benchmarks/process_data.md
echo "outputs in $OUT"
