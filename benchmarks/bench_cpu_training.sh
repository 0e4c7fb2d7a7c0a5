#!/usr/bin/env bash
# Training step time on a CPU for each renderer backend (auto = PyTorch renderer, cpu = csrc/cpu_ops.cpp),
# same data, schedule and step count; the figure is nerfstudio's own profiler average of
# Trainer.train_iteration. Writes benchmarks/cpu_training.md.
#   bash benchmarks/bench_cpu_training.sh [steps]
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${1:-150}
DATA=$(.venv/bin/python -c 'from geer_ns.data.synthetic_room import default_scene_dir; print(default_scene_dir())')
OUT=$(mktemp -d)
.venv/bin/python -c 'from geer_ns.render.cuda_backend import load_cpu_ops; load_cpu_ops()'  # build outside the timing
rows=""
for backend in auto cpu; do
  log="$OUT/$backend.log"
  .venv/bin/ns-train geer --data "$DATA" --output-dir "$OUT/runs" --max-num-iterations "$STEPS" \
    --vis tensorboard --viewer.quit-on-train-completion True --steps-per-eval-all-images 0 \
    --pipeline.model.num-downscales 1 --pipeline.model.resolution-schedule 1000000 \
    --pipeline.model.warmup-length 100 --pipeline.model.refine-every 50 --pipeline.model.stop-split-at 201 \
    --pipeline.model.renderer-backend "$backend" > "$log" 2>&1
  secs=$(grep -oP 'Trainer.train_iteration: \K[0-9.]+' "$log")
  rows="$rows| $backend | $secs |"$'\n'
done
cat > benchmarks/cpu_training.md <<MD
# CPU training step time by renderer backend

- device: CPU, $(uname -m), $(nproc) cores; torch $(.venv/bin/python -c 'import torch; print(torch.__version__)')
- commit: $(git rev-parse --short HEAD)
- command: \`bash benchmarks/bench_cpu_training.sh $STEPS\`
- scene: the embedded synthetic room (21 training views, 48x48 BEAP = half resolution, 4000 seed Gaussians,
  refinement at steps 100-200), $STEPS steps; figure: nerfstudio's profiler mean of Trainer.train_iteration
  (includes data loading, loss, backward, optimiser and densification steps), one run each, same machine.

| --pipeline.model.renderer-backend | s per training iteration |
| --- | ---: |
$rows
MD
cat benchmarks/cpu_training.md
