#!/usr/bin/env bash
# Training step time on a CPU: the PyTorch renderer (backend torch) against the CPU build of the kernels (backend
# cpu, what auto picks for CPU tensors), on the embedded synthetic room at the demo's CPU resolution (48x48 BEAP)
# and refinement schedule through ns-train; figure: nerfstudio's profiler mean of Trainer.train_iteration (data
# loading, loss, backward, optimiser and densification included). Writes benchmarks/cpu_training.md.
#   bash benchmarks/cpu_training.sh [steps]
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${1:-100}
PY=${PY:-$([ -x .venv/bin/python ] && echo .venv/bin/python || echo python)}
OUT=$(mktemp -d)
DATA=$("$PY" -c 'from geer_ns.data.synthetic_room import default_scene_dir; print(default_scene_dir())')
"$PY" -c 'from geer_ns.render.cuda_backend import load_cpu_ops; load_cpu_ops()'  # build outside the timing
declare -A secs
for backend in torch cpu; do
  "$PY" -m nerfstudio.scripts.train geer --data "$DATA" --output-dir "$OUT/runs" --max-num-iterations "$STEPS" \
    --vis tensorboard --viewer.quit-on-train-completion True --steps-per-eval-all-images 0 \
    --steps-per-eval-image 1000000 --pipeline.model.num-downscales 1 --pipeline.model.resolution-schedule 1000000 \
    --pipeline.model.warmup-length 100 --pipeline.model.refine-every 50 --pipeline.model.stop-split-at 251 \
    --pipeline.model.renderer-backend "$backend" > "$OUT/$backend.log" 2>&1
  secs[$backend]=$(grep -oP 'Trainer.train_iteration: \K[0-9.]+' "$OUT/$backend.log")
done
cat > benchmarks/cpu_training.md <<MD
# CPU training step time: PyTorch renderer vs the CPU build of the kernels

- device: CPU ($(uname -m)), $(nproc) cores (load average $(cut -d' ' -f1 /proc/loadavg) when written: absolute times
  are noisy; the ratio compares the two backends within one run), torch $("$PY" -c 'import torch; print(torch.__version__)')
- commit: $(git rev-parse --short HEAD)
- command: \`bash benchmarks/cpu_training.sh $STEPS\`
- ns-train on the embedded synthetic room (21 training views, 4000 seed Gaussians, 48x48 BEAP, refinement every
  50 steps, splits from 100 to 250 as in scripts/demo.sh); nerfstudio's profiler mean of Trainer.train_iteration
  over $STEPS steps.

| backend | s per training step | speed-up over torch |
| --- | ---: | ---: |
| torch | ${secs[torch]} | 1.0x |
| cpu | ${secs[cpu]} | $(awk "BEGIN {printf \"%.1f\", ${secs[torch]} / ${secs[cpu]}}")x |
MD
cat benchmarks/cpu_training.md
