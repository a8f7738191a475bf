#!/usr/bin/env bash
# One command to set everything up on a fresh machine (Debian, Python 3.11, root or sudo for apt):
#   * .venv with torch==2.13.0 (the local CPU wheel; pinned FIRST so nothing pulls CUDA builds),
#     neumesh (editable) + test deps + bpy==5.0.1 (Blender 5.0 as a Python module, for blender_tests)
#     + transformers (the DINO extractor's architecture; its tests use random weights)
#     + pycolmap and opencv-python-headless (real captures: COLMAP models, poses from photos, undistortion;
#       pulled by pyproject.toml, OpenCV kept below 4.12 whose wheels need numpy>=2)
#     + triton (the fused GPU renderer; on the CPU its tests run through Triton's interpreter)
#     + ruff (the linter tests/test_lint.py runs)
#   * Debian's `blender` binary (3.4) and a torch folder for its Python (scripts/setup_blender.sh)
# Idempotent: re-running only installs what is missing.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cd "$ROOT"
PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
VPIP=".venv/bin/python -m pip --disable-pip-version-check -q"
$VPIP install "torch==2.13.0"
$VPIP install "numpy<2" -e ".[test,lint,blender,dino,gpu,shape-diameter,decimate]"   # lint: ruff (tests/test_lint.py); gpu: triton (~290 MB wheel, no CUDA; its kernels' tests run in its interpreter); shape-diameter: libigl; decimate: fast-simplification (bake)
bash scripts/setup_blender.sh
.venv/bin/python -c "import torch, neumesh_core, bpy, pycolmap, cv2; print('setup ok: torch', torch.__version__, '| bpy', bpy.app.version_string, '| pycolmap', pycolmap.__version__, '| opencv', cv2.__version__)"
