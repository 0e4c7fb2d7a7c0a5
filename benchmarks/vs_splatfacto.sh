#!/usr/bin/env bash
# geer against splatfacto's variants (geer-compare) on the dev room at 128^2: the 180-degree fisheye views (geer,
# splatfacto as shipped, splatfacto on a 120-degree pinhole undistortion, splatfacto with gsplat's fisheye EWA) and
# the 90-degree pinhole views of the same poses (geer, splatfacto). Both runs at once, niced, one process each.
#
#   STEPS=100 bash benchmarks/vs_splatfacto.sh      # writes benchmarks/vs_splatfacto.md
#
# The 128^2 room is the dev room's images resized with OpenCV's INTER_AREA (benchmarks/densification.py).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
STEPS=${STEPS:-100}
WORK=${WORK:-/tmp/vs_splatfacto}
DEV_ROOM=${DEV_ROOM:-../shared/data/fisheye_room_dev}  # the shared data beside the checkout
ROOM=$("$PY" -c "import sys; sys.path.insert(0, 'benchmarks'); from pathlib import Path; import densification as d; d.DEV_ROOM = Path('$DEV_ROOM'); print(d.resized_room(Path('$WORK'), 128))")
START=$(date -u +%FT%TZ)
COMMIT=$(git rev-parse --short HEAD)  # the code the runs load (the tree may move on while they train)
nice -n 5 "$PY" -m geer_ns.compare --data "$ROOM/transforms_fisheye.json" --steps "$STEPS" \
  --methods geer splatfacto splatfacto-pinhole splatfacto-fisheye --output-dir "$WORK/fisheye" > "$WORK/fisheye.log" 2>&1 &
FISHEYE=$!
nice -n 5 "$PY" -m geer_ns.compare --data "$ROOM/transforms_pinhole.json" --steps "$STEPS" \
  --methods geer splatfacto --output-dir "$WORK/pinhole" > "$WORK/pinhole.log" 2>&1 &
PINHOLE=$!
wait $FISHEYE
wait $PINHOLE
cp "$WORK/fisheye/compare.png" benchmarks/vs_splatfacto_fisheye.png
cp "$WORK/pinhole/compare.png" benchmarks/vs_splatfacto_pinhole.png
"$PY" - "$WORK" "$STEPS" "$START" "$COMMIT" <<'PYEOF'
import platform, sys
from pathlib import Path
work, steps, start, commit = Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4]
def body(name):
    return (work / name / "compare.md").read_text().replace("## geer-compare", "").strip()
text = f"""# geer against splatfacto (geer-compare), dev room at 128^2, CPU

Command: `STEPS={steps} bash benchmarks/vs_splatfacto.sh` (started {start}, commit {commit}, {platform.node()},
2 CPU cores shared with other sessions: times are noisy and only comparable within one table). Every method: {steps}
steps of nerfstudio's trainer, the same schedule options (docs/compare.md). splatfacto runs through gsplat's EWA
rasterization in PyTorch (geer_ns.compare.ewa_cpu), as no CUDA is here.

## 180-degree fisheye views

{body("fisheye")}

![fisheye](vs_splatfacto_fisheye.png)

## 90-degree pinhole views (same poses)

{body("pinhole")}

![pinhole](vs_splatfacto_pinhole.png)
"""
Path("benchmarks/vs_splatfacto.md").write_text(text)
print(text)
PYEOF
