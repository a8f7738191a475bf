#!/usr/bin/env bash
# Installs what the Blender side of the project needs:
#   * the Debian `blender` binary (3.4, headless `blender -b`), used by blender_tests/test_real_blender.py
#   * Xvfb (`xvfb-run`), a virtual display in which blender_tests/test_real_blender_ui.py opens a real
#     Blender window (software OpenGL) and takes screenshots of the add-on's panels
#   * xdotool: real X input (pointer, clicks, keys) for blender_tests/test_real_blender_redo.py
#   * a `pip install --target` folder (<repo>/.blender_torch) with torch & co for that binary's Python:
#     the add-on's dependency list (addon/runtime/deps.py), every feature's packages included
# The add-on finds the folder through NEUMESH_PYTHONPATH (the tests set it) or the add-on preference
# "Existing environment". bpy==5.0.1 for the in-venv tests is installed by the top-level setup.
#
# Usage: bash scripts/setup_blender.sh            (idempotent; re-running is cheap)
# Env:   PYTHON   python 3.11 with pip used to run `pip install --target` (default: .venv/bin/python)
#        NEUMESH_BLENDER_TORCH  target folder (default: <repo>/.blender_torch)
#        SKIP_APT=1  do not apt-get install blender
#        DRY_RUN=1   only say what would be installed
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${PYTHON:-$ROOT/.venv/bin/python}"
TARGET="${NEUMESH_BLENDER_TORCH:-$ROOT/.blender_torch}"

APT_PKGS=()
command -v blender >/dev/null 2>&1 || APT_PKGS+=(blender)
command -v xvfb-run >/dev/null 2>&1 || APT_PKGS+=(xvfb xauth libgl1-mesa-dri)  # software OpenGL for the window
command -v xdotool >/dev/null 2>&1 || APT_PKGS+=(xdotool)  # real clicks and key presses in that window
if [ "${#APT_PKGS[@]}" -gt 0 ]; then
    if [ "${SKIP_APT:-0}" != "1" ] && command -v apt-get >/dev/null 2>&1; then
        echo "[setup_blender] installing Debian ${APT_PKGS[*]}"
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq
        apt-get install -y -qq --no-install-recommends "${APT_PKGS[@]}" >/dev/null
    fi
fi
if ! command -v xvfb-run >/dev/null 2>&1; then
    echo "[setup_blender] no xvfb-run; the real-window test will be skipped"
fi
if ! command -v xdotool >/dev/null 2>&1; then
    echo "[setup_blender] no xdotool; the real-input window test (test_real_blender_redo.py) will be skipped"
fi
if ! command -v blender >/dev/null 2>&1; then
    echo "[setup_blender] no blender binary; the real-Blender test will be skipped"
    exit 0
fi

FACTS="$(blender -b --factory-startup --python-expr 'import sys, bpy, importlib.util as u
print("PYVER=%d.%d" % sys.version_info[:2]); print("BVER=%d.%d.%d" % tuple(bpy.app.version))
print("NUMPY=" + (__import__("numpy").__version__ if u.find_spec("numpy") else ""))' 2>/dev/null)"
BPYVER="$(echo "$FACTS" | sed -n 's/^PYVER=//p' | head -1)"
BVER="$(echo "$FACTS" | sed -n 's/^BVER=//p' | head -1)"
BNUMPY="$(echo "$FACTS" | sed -n 's/^NUMPY=//p' | head -1)"
echo "[setup_blender] blender's python: ${BPYVER:-unknown}"
if [ "$BPYVER" != "3.11" ]; then
    echo "[setup_blender] blender's python is not 3.11; not installing torch for it (real-Blender test will skip)"
    exit 0
fi
PYVER="$("$PY" -c 'import sys;print("%d.%d" % sys.version_info[:2])')"
if [ "$PYVER" != "3.11" ]; then
    echo "[setup_blender] $PY is python $PYVER, need 3.11 to install wheels for blender's python" >&2
    exit 1
fi

STAMP="$TARGET/.neumesh_deps_ok"
# the add-on's own dependency list (addon/runtime/deps.py, also behind its "Install dependencies"): every
# feature's packages (semantics: scikit-image, scikit-learn; bake: xatlas), numpy<2 for Blender 3.4-4.x
mapfile -t REQS < <("$PY" -c 'import runpy, sys
d = runpy.run_path(sys.argv[1])
print("\n".join(d["full_requirements"](tuple(int(x) for x in sys.argv[2].split(".")))))' \
    "$ROOT/addon/runtime/deps.py" "${BVER:-3.4.0}")
KEEP_OUT=()
if [ -n "$BNUMPY" ]; then   # this Blender ships numpy: resolve against it, never shadow it
    mapfile -t REQS < <(printf '%s\n' "${REQS[@]}" | grep -v '^numpy'; echo "numpy==$BNUMPY")
    KEEP_OUT=(numpy)
fi
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "${REQS[*]}" ]; then
    echo "[setup_blender] $TARGET up to date"
elif [ "${DRY_RUN:-0}" = "1" ]; then
    echo "[setup_blender] would run: pip install --target $TARGET ${REQS[*]} (then remove: ${KEEP_OUT[*]:-nothing})"
    exit 0
else
    echo "[setup_blender] pip install --target $TARGET ${REQS[*]}"
    # a fresh folder beside the old one, swapped in when complete (the old one keeps working meanwhile)
    NEW="$TARGET.new.$$"
    rm -rf "$NEW"
    # CPU wheel of torch: the local wheel cache / PyPI mirror is configured in pip.conf; add the
    # PyTorch CPU index only when asked (NEUMESH_TORCH_INDEX=https://download.pytorch.org/whl/cpu).
    EXTRA=()
    if [ -n "${NEUMESH_TORCH_INDEX:-}" ]; then EXTRA+=(--extra-index-url "$NEUMESH_TORCH_INDEX"); fi
    "$PY" -m pip install -q --no-input --target "$NEW" "${EXTRA[@]}" "${REQS[@]}"
    for d in "${KEEP_OUT[@]}"; do rm -rf "$NEW/$d" "$NEW/$d".libs "$NEW/$d"-*.dist-info; done
    echo "${REQS[*]}" > "$NEW/.neumesh_deps_ok"
    rm -rf "$TARGET.old"
    if [ -e "$TARGET" ]; then mv "$TARGET" "$TARGET.old"; fi
    mv "$NEW" "$TARGET"
    rm -rf "$TARGET.old"
fi

# check: blender's python imports torch from the folder
NEUMESH_PYTHONPATH="$TARGET" blender -b --factory-startup --python-expr \
 'import os,sys; sys.path.insert(0, os.environ["NEUMESH_PYTHONPATH"]); import torch, numpy, skimage, sklearn, xatlas; print("TORCH_OK", torch.__version__, numpy.__version__)' \
 2>&1 | grep TORCH_OK || { echo "[setup_blender] blender cannot import torch from $TARGET" >&2; exit 1; }
