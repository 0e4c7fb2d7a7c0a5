#!/usr/bin/env bash
# geer against splatfacto (geer-compare) at 128^2, every method over the same seeds, on one of two scenes:
#
# - SCENE=dev_room (default): the dev room (Blender Cycles): its 180-degree fisheye views (geer, geer on BEAP images,
#   splatfacto with gsplat's fisheye EWA) and the 90-degree pinhole views of the same poses (geer, geer on BEAP
#   images, splatfacto); geer at splatfacto's density (geer-gsplat-units); then what BEAP resampling loses by itself.
#   Writes benchmarks/vs_splatfacto.md and .png.
# - SCENE=donut_room: a capture rendered from real Gaussians (benchmarks/gaussian_scene.py: the trained 3DGS donut
#   in a textured box, float64 ground truth): its 90-degree pinhole views (geer, splatfacto) and 200-degree fisheye
#   views of the same poses (geer, splatfacto with gsplat's fisheye EWA). Writes benchmarks/vs_splatfacto_donut_room.md
#   and .png.
#
#   STEPS=1000 SEEDS="1 2 3" bash benchmarks/vs_splatfacto.sh   # the dev room
#   SCENE=donut_room STEPS=1000 SEEDS="1 2 3" bash benchmarks/vs_splatfacto.sh
#   EXTRA=1 ...   also splatfacto on a 120-degree pinhole undistortion of the fisheye (and, on the dev room, as
#                 shipped: 10-16 dB behind)
#   WORK=DIR ...  keep the scenes in DIR and the runs in DIR/SCENE; a second call with the same DIR, scene, steps and
#                 seeds reuses the finished tables
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-$([ -x .venv/bin/python ] && echo .venv/bin/python || echo python)}
STEPS=${STEPS:-1000}
SEEDS=${SEEDS:-1 2 3}
SCENE=${SCENE:-dev_room}
WORK=${WORK:-$(mktemp -d)}
case $SCENE in
  dev_room)
    ROOM=$("$PY" -m benchmarks.common --dev-room 128 --work "$WORK")
    REPORT=benchmarks/vs_splatfacto TITLE="dev room at 128^2" ;;
  donut_room)
    ROOM=$("$PY" -m benchmarks.gaussian_scene --size 128 --work "$WORK" | tail -n 1)
    REPORT=benchmarks/vs_splatfacto_donut_room
    TITLE="the donut room at 128^2 (real 3DGS Gaussians in a box of Gaussians; fisheye views 200 degrees)" ;;
  *) echo "SCENE: dev_room or donut_room, got $SCENE" >&2; exit 2 ;;
esac
WORK=$WORK/$SCENE  # each scene's runs in a folder of their own: the reuse check below knows steps and seeds only
mkdir -p "$WORK"

compare() {  # VIEWS OUT METHOD...: one geer-compare call into WORK/OUT, unless a table of these steps and seeds is there
  local views=$1 out=$2
  shift 2
  if [ -f "$WORK/$out/compare.json" ] && "$PY" -c "import json, sys; runs = json.load(open(sys.argv[1]))['results']
sys.exit(sorted({(r['steps'], r['seed']) for r in runs}) != sorted((int(sys.argv[2]), int(s)) for s in sys.argv[3:]))" \
      "$WORK/$out/compare.json" "$STEPS" $SEEDS; then
    echo "[vs_splatfacto] $out: the table in $WORK/$out kept"
    return
  fi
  # shellcheck disable=SC2086  # the seed list is words
  "$PY" -m geer_ns.compare --data "$ROOM/transforms_$views.json" --steps "$STEPS" --seeds $SEEDS --methods "$@" \
    --output-dir "$WORK/$out"
  git rev-parse --short HEAD > "$WORK/$out/commit"
}
if [ "$SCENE" = dev_room ]; then
  OUTS="fisheye pinhole fisheye_density pinhole_density"
  # shellcheck disable=SC2086  # EXTRA's methods are words
  compare fisheye fisheye geer geer-beap splatfacto-fisheye ${EXTRA:+splatfacto splatfacto-pinhole}
  compare pinhole pinhole geer geer-beap splatfacto
  compare fisheye fisheye_density geer-gsplat-units
  compare pinhole pinhole_density geer-gsplat-units
else
  OUTS="pinhole fisheye pinhole_density"
  compare pinhole pinhole geer splatfacto
  # shellcheck disable=SC2086  # EXTRA's methods are words
  compare fisheye fisheye geer splatfacto-fisheye ${EXTRA:+splatfacto-pinhole}
  compare pinhole pinhole_density geer-gsplat-units
fi
"$PY" - "$WORK" "$ROOM" "$REPORT" "$SCENE" > "$WORK/summary.md" <<'PYEOF'
import json, sys
from pathlib import Path
from PIL import Image
from scipy.stats import ttest_ind
from geer_ns.compare.capture import load_capture
from geer_ns.data.beap import beap_to_native
from geer_ns.data.datamanager import to_beap
from geer_ns.data.views import beap_view
from geer_ns.metrics.regions import masked_psnr

work, room, report, scene = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], sys.argv[4]
image = Image.open(work / "fisheye" / "compare.png")  # the first test view and its errors, in 128 colours
image.crop((0, 0, image.width, image.height // 3)).quantize(128).save(f"{report}.png", optimize=True)
print("## geer against the best splatfacto variant (difference of the means, 95 % Welch interval)\n")
print("| views | figure | geer row | best splatfacto variant | geer - it | reading |\n| --- | --- | ---: | ---: | ---: | --- |")
for views, geer in [(v, g) for v in ("fisheye", "pinhole") for g in ("geer", "geer-gsplat-units")]:
    outs = [work / out / "compare.json" for out in (views, f"{views}_density")]
    runs = [r for out in outs if out.is_file() for r in json.loads(out.read_text())["results"]]
    for key in ("psnr", "ssim", "central_psnr", "peripheral_psnr", "lpips"):
        by = {}
        for r in runs:
            if r.get(key) is not None:
                by.setdefault(r["method"], []).append(r[key])
        splat = {m: v for m, v in by.items() if m.startswith("splatfacto")}
        if geer not in by or not splat:
            continue
        sign = -1 if key == "lpips" else 1
        best = max(splat, key=lambda m: sign * sum(splat[m]) / len(splat[m]))
        a, b = by[geer], splat[best]
        ma, mb = sum(a) / len(a), sum(b) / len(b)
        low, high = ttest_ind(a, b, equal_var=False).confidence_interval(0.95)  # Welch's interval of a - b
        half = (high - low) / 2
        diff = sign * (ma - mb)
        reading = "geer ahead" if diff - half > 0 else "geer behind" if diff + half < 0 else "not distinguishable"
        print(f"| {views} | {key} | {geer}: {ma:.4g} | {best}: {mb:.4g} | {ma - mb:+.4f} +- {half:.4f} | {reading} |")
if scene != "dev_room":  # the BEAP rows explain the dev room's geer-beap rows
    sys.exit()
print("\n## What BEAP resampling loses by itself (test images to BEAP and back, PSNR against the originals)\n")
print("| views | valid pixels | BEAP cells | round trip PSNR | central |\n| --- | ---: | ---: | ---: | ---: |")
for views in ("fisheye", "pinhole"):
    capture = load_capture(room / f"transforms_{views}.json", 45.0)
    grid = beap_view(capture.camera).grid
    full, central = [], []
    for view in capture.views:
        beap, ok = to_beap(view.image, view.camera, view.valid, 2)
        back, covered = beap_to_native(beap, grid, view.camera, ok)
        full.append(masked_psnr(back.double(), view.image.double(), view.valid & covered))
        central.append(masked_psnr(back.double(), view.image.double(), view.valid & covered & view.central))
    print(f"| {views} | {int(view.valid.sum())} | {grid.width * grid.height} | {sum(full) / len(full):.2f} | "
          f"{sum(central) / len(central):.2f} |")
PYEOF
{
  echo "# geer against splatfacto (geer-compare), $TITLE"
  echo
  echo "- device: $("$PY" -c 'from benchmarks.common import device; print(device())')"
  echo "- commit: $(for out in $OUTS; do echo "$(cat "$WORK/$out/commit" 2>/dev/null || echo '?') ($out)"; done | paste -sd, -)"
  echo "- command: \`$([ "$SCENE" = dev_room ] || echo "SCENE=$SCENE ")STEPS=$STEPS SEEDS=\"$SEEDS\" ${EXTRA:+EXTRA=1 }bash benchmarks/vs_splatfacto.sh\`"
  echo "- every method: $STEPS steps of nerfstudio's trainer, the same schedule options (docs/compare.md), seeds $SEEDS"
  echo
  cat "$WORK/summary.md"
  for out in $OUTS; do
    case $out in *_density) title="${out%_density} views, geer at splatfacto's density" ;; *) title="$out views" ;; esac
    echo; echo "## $title"; echo
    sed -e '/^## geer-compare/d' "$WORK/$out/compare.md"
  done
  echo; echo "![the first fisheye test view: ground truth, each method, its error]($(basename "$REPORT").png)"
} > "$REPORT.md"
cat "$REPORT.md"
