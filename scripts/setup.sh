#!/usr/bin/env bash
# Create (or update) the project's virtual environment in .venv and install geer-ns into it.
# Idempotent: a second run only checks. Usage: bash scripts/setup.sh
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3.11}
command -v "$PYTHON" >/dev/null || PYTHON=python3
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $($PYTHON --version)"
  "$PYTHON" -m venv .venv
fi
PIP=(.venv/bin/python -m pip --disable-pip-version-check -q)
# Some machines' pip config lists local package folders that do not exist; drop those warnings only.
quiet() { "$@" 2>&1 | { grep -v "is ignored: it is neither a file nor a directory" || true; }; }
stamp=.venv/.geer_ns_installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ constraints.txt -nt "$stamp" ]; then
  echo "[setup] installing geer-ns and its dependencies, the versions of constraints.txt (torch, nerfstudio, gsplat, ...)"
  quiet "${PIP[@]}" install -e '.[test]' -c constraints.txt
  # nerfstudio pins opencv-python-headless and nuscenes-devkit pulls opencv-python: all three wheels
  # write the same cv2/ package and whichever pip installed last wins. Put the contrib build back on top
  # so cv2.omnidir and cv2.fisheye exist whatever pip's install order was.
  quiet "${PIP[@]}" install --force-reinstall --no-deps "$(grep '^opencv-contrib-python-headless==' constraints.txt)"
  touch "$stamp"
fi
# Earlier versions wrote a start-up hook into site-packages; geer changes nothing outside its own runs now.
rm -f .venv/lib/python*/site-packages/geer_ns_host_warnings.pth
.venv/bin/python -c "import cv2; cv2.omnidir; cv2.fisheye; import geer_ns, nerfstudio, gsplat" \
  || { echo "[setup] the environment is broken: delete .venv and run again" >&2; exit 1; }
echo "[setup] ready: $(.venv/bin/python -c 'import torch, nerfstudio, cv2; print("torch", torch.__version__, "| cv2", cv2.__version__)')"
