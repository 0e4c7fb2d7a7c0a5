#!/usr/bin/env bash
# geer against splatfacto's variants (geer-compare) on the dev room at 128^2: the 180-degree fisheye views (geer,
# splatfacto as shipped, splatfacto on a 120-degree pinhole undistortion, splatfacto with gsplat's fisheye EWA) and
# the 90-degree pinhole views of the same poses (geer, splatfacto); one process after the other.
#
#   STEPS=1000 bash benchmarks/vs_splatfacto.sh      # writes benchmarks/vs_splatfacto.md and vs_splatfacto.png
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-$([ -x .venv/bin/python ] && echo .venv/bin/python || echo python)}
STEPS=${STEPS:-1000}
WORK=${WORK:-$(mktemp -d)}
ROOM=$("$PY" -c "from pathlib import Path; from benchmarks.common import dev_room; print(dev_room(Path('$WORK'), 128))")
COMMIT=$(git rev-parse --short HEAD)
"$PY" -m geer_ns.compare --data "$ROOM/transforms_fisheye.json" --steps "$STEPS" \
  --methods geer splatfacto splatfacto-pinhole splatfacto-fisheye --output-dir "$WORK/fisheye"
"$PY" -m geer_ns.compare --data "$ROOM/transforms_pinhole.json" --steps "$STEPS" \
  --methods geer splatfacto --output-dir "$WORK/pinhole"
"$PY" - "$WORK" <<'PYEOF'
from PIL import Image
import sys
image = Image.open(f"{sys.argv[1]}/fisheye/compare.png")  # the first test view and its errors, in 128 colours
image.crop((0, 0, image.width, image.height // 3)).quantize(128).save("benchmarks/vs_splatfacto.png", optimize=True)
PYEOF
{
  echo "# geer against splatfacto (geer-compare), dev room at 128^2"
  echo
  echo "- device: $("$PY" -c 'from benchmarks.common import device; print(device())')"
  echo "- commit: $COMMIT"
  echo "- command: \`STEPS=$STEPS bash benchmarks/vs_splatfacto.sh\`"
  echo "- every method: $STEPS steps of nerfstudio's trainer, the same schedule options (docs/compare.md)"
  for views in fisheye pinhole; do
    echo; echo "## $views views"; echo
    sed -e '/^## geer-compare/d' "$WORK/$views/compare.md"
  done
  echo; echo "![the first fisheye test view: ground truth, each method, its error](vs_splatfacto.png)"
} > benchmarks/vs_splatfacto.md
cat benchmarks/vs_splatfacto.md
