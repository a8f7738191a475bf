#!/usr/bin/env bash
# Runs blender_tests under Blender 5.3 as a Python module (bpy==5.3.0, Python 3.13, numpy 2), beside the
# main venv's bpy 5.0.1 / numpy 1.26.  Not part of CI: the install pulls torch 2.13.0
# for Python 3.13, a CUDA build of about 5 GB (it runs on the CPU); see DEVELOPERS.md.
#
# Usage: bash scripts/test_bpy53.sh [pytest args]
#        (default: blender_tests -q without test_real_blender*.py: those drive Debian's `blender` binary
#        and its own torch folder, the same whichever bpy this venv has; the main venv runs them)
# Env:   PY313   Python 3.13 used to make the venv (default: ~/.pyenv/versions/3.13.0/bin/python)
#        VENV    the venv, outside the repository (default: /work/venv313, else ../venv313)
#        INSTALL_ONLY=1   only build/refresh the venv
# Idempotent: a stamp file holds the requirement list it was built with.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY313="${PY313:-$HOME/.pyenv/versions/3.13.0/bin/python}"
if [ -z "${VENV:-}" ]; then
    if [ -d /work ] && [ -w /work ]; then VENV=/work/venv313; else VENV="$ROOT/../venv313"; fi
fi
if [ ! -x "$PY313" ]; then
    echo "[test_bpy53] no Python 3.13 at $PY313 (set PY313=...)" >&2; exit 2
fi
# the project's own dependencies (pyproject.toml) and test dependencies, with numpy 2
mapfile -t REQS < <("$PY313" - "$ROOT/pyproject.toml" <<'PY'
import sys, tomllib, re
p = tomllib.load(open(sys.argv[1], "rb"))["project"]
out = []
for r in p["dependencies"] + p["optional-dependencies"]["test"]:
    name = re.split(r"[<>=!~;\[ ]", r, maxsplit=1)[0].lower()
    if name in ("torch", "numpy"):
        continue
    out.append(r.split(";", 1)[0].strip())
print("\n".join(["torch==2.13.0", "bpy==5.3.0", "numpy>=2.2"] + out))
PY
)
STAMP="$VENV/.neumesh_reqs"
T0=$(date +%s)
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "${REQS[*]}" ]; then
    echo "[test_bpy53] $VENV up to date"
else
    [ -x "$VENV/bin/python" ] || "$PY313" -m venv "$VENV"
    PIP="$VENV/bin/python -m pip --disable-pip-version-check"
    echo "[test_bpy53] pip install ${REQS[*]}"
    $PIP install "torch==2.13.0"                 # first: the largest download, alone
    $PIP install "${REQS[@]}"
    printf '%s' "${REQS[*]}" > "$STAMP"
    echo "[test_bpy53] install took $(( $(date +%s) - T0 )) s"
fi
"$VENV/bin/python" -c "import sys, bpy, numpy, torch; print('[test_bpy53] python', sys.version.split()[0], '| bpy', bpy.app.version_string, '| numpy', numpy.__version__, '| torch', torch.__version__)"
[ "${INSTALL_ONLY:-0}" = "1" ] && exit 0
cd "$ROOT"
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
if [ "$#" -eq 0 ]; then set -- blender_tests -q --ignore-glob='*test_real_blender*'; fi
exec "$VENV/bin/python" -m pytest -p no:cacheprovider "$@"
