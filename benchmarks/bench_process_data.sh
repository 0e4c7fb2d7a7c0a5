#!/usr/bin/env bash
# geer-process-data on the dev fisheye room (48 Blender views, 180-degree equidistant fisheye, 384 px):
# run time, pose / focal errors against the renderer's poses, and ns-eval of geer trained on the recovered
# poses vs on the true poses (same schedule, steps and held-out views: every 8th frame). The two trainings
# run side by side, one thread each.
#   bash benchmarks/bench_process_data.sh [steps]     (OUT=dir keeps the outputs)
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${1:-200}
DEV=../shared/data/fisheye_room_dev
OUT=${OUT:-$(mktemp -d)}
PY=.venv/bin/python
export PYTHONPATH=$PWD
$PY -c 'from geer_ns.render.cuda_backend import load_cpu_ops; load_cpu_ops()'  # build outside the timings

TIMEFORMAT="geer-process-data: wall %R s, CPU %U s user + %S s system"
time $PY -m geer_ns.process_data --data "$DEV/images_fisheye" --output-dir "$OUT/recovered" --num-threads 2 \
  --overwrite True > "$OUT/process_data.log" 2>&1
$PY -c "import json; print('stages (s):', json.load(open('$OUT/recovered/process_data_report.json'))['timings_s'])"
$PY -m geer_ns.process_data.evaluate "$OUT/recovered/transforms.json" "$DEV/transforms_fisheye.json"

train() {  # name data
  OMP_NUM_THREADS=1 .venv/bin/ns-train geer --data "$2" --output-dir "$OUT/runs" --experiment-name "$1" \
    --timestamp bench --max-num-iterations "$STEPS" --vis tensorboard --viewer.quit-on-train-completion True \
    --steps-per-eval-image 0 --steps-per-eval-all-images 0 --steps-per-save "$STEPS" \
    --pipeline.model.renderer-backend cpu --pipeline.model.num-downscales 2 \
    --pipeline.model.resolution-schedule 1000000 --pipeline.model.warmup-length 60 \
    --pipeline.model.refine-every 60 --pipeline.model.stop-split-at "$STEPS" \
    --pipeline.model.central-half-angles-deg 60 60 \
    nerfstudio-data --eval-mode interval --eval-interval 8 > "$OUT/train_$1.log" 2>&1
  OMP_NUM_THREADS=1 .venv/bin/ns-eval --load-config "$OUT/runs/$1/geer/bench/config.yml" \
    --output-path "$OUT/eval_$1.json" > "$OUT/eval_$1.log" 2>&1
}
# Control: the recovered poses and intrinsics with the true dataset's seed cloud (20k points), moved into the
# recovered world by the similarity between the camera centres; separates pose accuracy from seeding.
mkdir -p "$OUT/recovered_true_seed"
ln -sfn "$(realpath "$OUT/recovered/images")" "$OUT/recovered_true_seed/images"
ln -sfn "$(realpath "$OUT/recovered/masks")" "$OUT/recovered_true_seed/masks"
$PY - "$OUT" "$DEV" <<'PYEOF'
import json, sys
import numpy as np
from plyfile import PlyData
from geer_ns.process_data.evaluate import umeyama
out, dev = sys.argv[1], sys.argv[2]
rec = json.load(open(f"{out}/recovered/transforms.json"))
true = {f["file_path"].split("/")[-1]: np.array(f["transform_matrix"]) for f in json.load(open(f"{dev}/transforms_fisheye.json"))["frames"]}
c_r = np.array([np.array(f["transform_matrix"])[:3, 3] for f in rec["frames"]])
c_t = np.array([true[f["file_path"].split("/")[-1]][:3, 3] for f in rec["frames"]])
s, r, t = umeyama(c_r, c_t)
ply = PlyData.read(f"{dev}/points3d.ply")
v = ply["vertex"].data
xyz = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
xyz = ((xyz - t) @ r) / s  # true world -> recovered world
for i, a in enumerate("xyz"):
    v[a] = xyz[:, i]
ply.write(f"{out}/recovered_true_seed/points3d.ply")
json.dump(rec, open(f"{out}/recovered_true_seed/transforms.json", "w"))
PYEOF
train true "$DEV/transforms_fisheye.json" & a=$!
train recovered "$OUT/recovered" & b=$!
train recovered_true_seed "$OUT/recovered_true_seed" & c=$!
wait $a && wait $b && wait $c
$PY - "$OUT" <<'PYEOF'
import json, sys
out = sys.argv[1]
res = {k: json.load(open(f"{out}/eval_{k}.json"))["results"] for k in ("true", "recovered", "recovered_true_seed")}
keys = ("psnr", "ssim", "central_psnr", "peripheral_psnr")
for k, r in res.items():
    print(f"{k:19s}", {m: round(r[m], 3) for m in keys})
for k in ("recovered", "recovered_true_seed"):
    print(f"{k} - true:", {m: round(res[k][m] - res["true"][m], 3) for m in keys})
PYEOF
echo "outputs in $OUT"
