#!/usr/bin/env bash
# geer-process-data on the dev fisheye room (48 Blender views, 180-degree equidistant fisheye, 384 px):
# run time, pose / focal errors against the renderer's poses, and ns-eval of geer trained on the recovered
# poses vs on the true poses (same schedule, steps and held-out views: every 8th frame).
#   bash benchmarks/bench_process_data.sh [steps]     (OUT=dir keeps the outputs)
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${1:-300}
DEV=../shared/data/fisheye_room_dev
OUT=${OUT:-$(mktemp -d)}
PY=.venv/bin/python
export PYTHONPATH=$PWD
$PY -c 'from geer_ns.render.cuda_backend import load_cpu_ops; load_cpu_ops()'  # build outside the timings

start=$(date +%s.%N)
$PY -m geer_ns.process_data --data "$DEV/images_fisheye" --output-dir "$OUT/recovered" --num-threads 2 \
  --overwrite True > "$OUT/process_data.log" 2>&1
end=$(date +%s.%N)
echo "geer-process-data wall time: $(echo "$end - $start" | bc) s (stages: $(grep -oP '"timings_s": \K\{[^}]*\}' \
  <(tr -d '\n ' < "$OUT/recovered/process_data_report.json")))"
$PY -m geer_ns.process_data.evaluate "$OUT/recovered/transforms.json" "$DEV/transforms_fisheye.json"

train() {  # name data
  .venv/bin/ns-train geer --data "$2" --output-dir "$OUT/runs" --experiment-name "$1" --timestamp bench \
    --max-num-iterations "$STEPS" --vis tensorboard --viewer.quit-on-train-completion True \
    --steps-per-eval-image 0 --steps-per-eval-all-images 0 --steps-per-save "$STEPS" \
    --pipeline.model.renderer-backend cpu --pipeline.model.num-downscales 1 \
    --pipeline.model.resolution-schedule 1000000 --pipeline.model.warmup-length 100 \
    --pipeline.model.refine-every 100 --pipeline.model.stop-split-at "$STEPS" \
    --pipeline.model.central-half-angles-deg 60 60 \
    nerfstudio-data --eval-mode interval --eval-interval 8 > "$OUT/train_$1.log" 2>&1
  .venv/bin/ns-eval --load-config "$OUT/runs/$1/geer/bench/config.yml" --output-path "$OUT/eval_$1.json" \
    > "$OUT/eval_$1.log" 2>&1
  $PY -c "import json,sys; r=json.load(open('$OUT/eval_$1.json'))['results']; \
print('$1', {k: round(r[k], 3) for k in ('psnr', 'ssim', 'central_psnr', 'peripheral_psnr')})"
}
train true "$DEV/transforms_fisheye.json"
train recovered "$OUT/recovered"
echo "outputs in $OUT"
