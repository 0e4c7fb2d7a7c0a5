#!/usr/bin/env bash
# Cross-camera evaluation on the Blender dev room (paper Tab. 3 style): train geer on the 180-degree fisheye
# views, score it on the pinhole test views; train on the pinhole views, score it on the full fisheye test
# views (the periphery is what a pinhole never saw). Each run is also scored on its own test views (ns-eval).
# CPU schedule: 1/8 resolution (48 x 48 BEAP / pinhole), STEPS steps. Writes benchmarks/cross_camera.md.
#   bash benchmarks/bench_cross_camera.sh [steps]
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${1:-150}
DATA=../shared/data/fisheye_room_dev
OUT=${GEER_BENCH_OUT:-$(mktemp -d)}
mkdir -p "$OUT"
export PYTHONPATH=$PWD
PY=.venv/bin/python
# The central region for both cameras: +-45 degrees (the pinhole's field of view); beyond is the periphery.
COMMON=(--vis tensorboard --viewer.quit-on-train-completion True --steps-per-eval-image 0
  --steps-per-eval-all-images 0 --max-num-iterations "$STEPS"
  --pipeline.model.num-downscales 3 --pipeline.model.resolution-schedule 1000000
  --pipeline.model.warmup-length 50 --pipeline.model.refine-every 50 --pipeline.model.stop-split-at "$STEPS"
  --pipeline.model.renderer-backend cpu --pipeline.model.central-half-angles-deg 45 45)
declare -A OTHER=([fisheye]=pinhole [pinhole]=fisheye)
for cam in fisheye pinhole; do
  .venv/bin/ns-train geer --data "$DATA/transforms_$cam.json" --output-dir "$OUT" --experiment-name "$cam" \
    --timestamp run "${COMMON[@]}" > "$OUT/train_$cam.log" 2>&1
  cfg="$OUT/$cam/geer/run/config.yml"
  .venv/bin/ns-eval --load-config "$cfg" --output-path "$OUT/${cam}_on_$cam.json" > "$OUT/eval_$cam.log" 2>&1
  $PY -m geer_ns.eval_views --load-config "$cfg" --views "$DATA/transforms_${OTHER[$cam]}.json" \
    --output-path "$OUT/${cam}_on_${OTHER[$cam]}.json" > "$OUT/eval_${cam}_other.log" 2>&1
done
$PY - "$OUT" "$STEPS" <<'PY' > benchmarks/cross_camera.md
import json, subprocess, sys
from pathlib import Path
out, steps = Path(sys.argv[1]), sys.argv[2]
commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
def cell(r, key):
    return f"{r[key]:.2f}" if key in r else "-"
rows = []
for train in ("fisheye", "pinhole"):
    for test in ("fisheye", "pinhole"):
        r = json.loads((out / f"{train}_on_{test}.json").read_text())["results"]
        how = "ns-eval" if train == test else "geer-eval"
        rows.append(f"| {train} | {test} | {how} | {cell(r, 'psnr')} | {cell(r, 'ssim')} | {cell(r, 'central_psnr')} "
                    f"| {cell(r, 'peripheral_psnr')} |")
print(f"""# Cross-camera evaluation on the dev room (CPU)

Train on one camera of `../shared/data/fisheye_room_dev`, score on the other camera's test views (same poses,
mapped through the run's `dataparser_transforms.json`), as in the paper's Tab. 3.

- device: CPU, 2 shared cores; commit {commit}
- command: `bash benchmarks/bench_cross_camera.sh {steps}`; per direction:
  `ns-train geer --data ../shared/data/fisheye_room_dev/transforms_fisheye.json ...` then
  `python -m geer_ns.eval_views --load-config .../config.yml --views ../shared/data/fisheye_room_dev/transforms_pinhole.json`
  (`geer-eval` once installed)
- schedule: {steps} steps at 1/8 resolution (fisheye: 48x48 BEAP cells of 3.75 deg; pinhole: 48x48), gsplat
  DefaultStrategy refinement every 50 steps from step 50, renderer backend `cpu`, 20k seed points; metrics at full
  resolution (384x384) over the 6 test views, valid pixels only; central = within +-45 deg of the axis in
  both BEAP angles (the pinhole's field of view), peripheral = the rest (fisheye only).
- a short CPU schedule: absolute PSNRs are far below a full 30k-step run; the comparison between rows is
  the point (render noise of the dataset ~40 dB).

| trained on | scored on | command | PSNR | SSIM | central PSNR | peripheral PSNR |
| --- | --- | --- | ---: | ---: | ---: | ---: |
""" + "\n".join(rows))
PY
cat benchmarks/cross_camera.md
