#!/usr/bin/env bash
# Training step time on a CPU, PyTorch renderer (backend torch) vs the CPU build of the kernels (backend cpu,
# what auto picks on CPU tensors), in one run; writes benchmarks/cpu_training.md.
#   1. the dev fisheye room at 256x256 BEAP, 20k Gaussians: benchmarks/cpu_training_step.py (render, masked L1,
#      backward, Adam; both backends in one process, same start);
#   2. the synthetic room at the demo's CPU resolution (48x48 BEAP cells) and refinement schedule through
#      ns-train; figure: nerfstudio's profiler mean of Trainer.train_iteration (data loading, loss, backward,
#      optimiser and densification included).
#   bash benchmarks/bench_cpu_training.sh [ns-train steps] [dev-room steps]
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${1:-300}
ROOM_STEPS=${2:-2}
export PYTHONPATH=$PWD
DATA=$(.venv/bin/python -c 'from geer_ns.data.synthetic_room import default_scene_dir; print(default_scene_dir())')
OUT=$(mktemp -d)
.venv/bin/python -c 'from geer_ns.render.cuda_backend import load_cpu_ops; load_cpu_ops()'  # build outside the timing
room_rows=$(.venv/bin/python benchmarks/cpu_training_step.py --size 256 --steps "$ROOM_STEPS" 2>/dev/null | grep '^|')
rows=""
for backend in torch cpu; do
  log="$OUT/$backend.log"
  .venv/bin/ns-train geer --data "$DATA" --output-dir "$OUT/runs" --max-num-iterations "$STEPS" \
    --vis tensorboard --viewer.quit-on-train-completion True --steps-per-eval-all-images 0 \
    --steps-per-eval-image 1000000 --pipeline.model.num-downscales 1 --pipeline.model.resolution-schedule 1000000 \
    --pipeline.model.warmup-length 100 --pipeline.model.refine-every 50 --pipeline.model.stop-split-at 251 \
    --pipeline.model.renderer-backend "$backend" > "$log" 2>&1
  secs=$(grep -oP 'Trainer.train_iteration: \K[0-9.]+' "$log")
  rows="$rows$backend $secs"$'\n'
done
torch_s=$(echo "$rows" | awk '$1=="torch"{print $2}')
synth_rows=$(echo "$rows" | awk -v t="$torch_s" 'NF==2{printf "| synthetic room, 48x48 BEAP (demo schedule, %s steps) | %s | %s | %.1fx | |\n", "'"$STEPS"'", $1, $2, t/$2}')
cat > benchmarks/cpu_training.md <<MD
# CPU training step time: PyTorch renderer vs the CPU build of the kernels

- device: CPU, $(uname -m), $(nproc) cores shared with other jobs (load average $(cut -d' ' -f1 /proc/loadavg) when
  written: absolute times are inflated and noisy; each ratio compares the two backends within one run);
  torch $(.venv/bin/python -c 'import torch; print(torch.__version__)'), $(.venv/bin/python -c 'import torch; print(torch.get_num_threads())') threads
- commit: $(git rev-parse --short HEAD)
- command: \`bash benchmarks/bench_cpu_training.sh $STEPS $ROOM_STEPS\`
- dev room rows: \`benchmarks/cpu_training_step.py\`, one 256x256 BEAP view of the dev fisheye room, its 20k
  seed points as Gaussians (kNN scales, opacity 0.1: the large, faint Gaussians of a training start),
  render + masked L1 + backward + Adam, median of $ROOM_STEPS steps after a warm-up step.
- synthetic room rows: ns-train on the embedded synthetic room (21 training views, 4000 seed Gaussians,
  refinement every 50 steps, splits from 100 to 250 as in scripts/demo.sh), nerfstudio's profiler mean of
  Trainer.train_iteration over $STEPS steps.

| case | backend | s per training step | speed-up over torch | final loss |
| --- | --- | ---: | ---: | ---: |
$room_rows
$synth_rows
MD
cat benchmarks/cpu_training.md
