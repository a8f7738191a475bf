#!/usr/bin/env bash
# The GPU check of the fused Triton renderer, in one go, from the repository root:
#
#     bash benchmarks/gpu_check.sh                     # a field made on the spot (no data needed)
#     FIELD=runs/lego/field.neumesh DATA=path/to/nerf_synthetic/lego bash benchmarks/gpu_check.sh
#
# 1. the CUDA tests: tests/kernels/ (the kernels compiled for the GPU, against the torch
#    path on the same GPU) and tests/test_device.py (the CUDA path against the CPU path);
# 2. benchmarks/bench/bench_render_gpu.py: a short sweep of the kernel's launch options (static and refill
#    schedules, block sizes, a register cap, the neighbour search's early out), then both backends,
#    both interpolation modes, at rest and deformed, 400² and 800², launches/syncs per frame, PSNR,
#    the first frame after a new pose, training steps with each marcher, and a breakdown (the neighbour
#    search and the decoders timed alone on a frame's samples);
# 3. the precision sweep (--sweep-set precision: fp32, fp16 and tf32 products) in a process of its own,
#    last: tf32 once poisoned the CUDA context on an H200 (triton 3.6.0), so nothing else may share it;
# 4. a summary.  Logs and JSON go to $OUT (the device tool's folder that comes back), else to
#    benchmarks/results/log/gpu_check/.  Meant to finish in about 5 minutes, at most 9.7 (the steps'
#    timeouts, under the device tool's 10 a call); the benchmark stops starting new configurations
#    after BENCH_BUDGET_S seconds (default 200).
#
# Wheels: the GPU machine's image (python3 3.12, torch 2.11.0+cu130, triton 3.6.0, numpy 2, scipy,
# pytest, pillow, opencv, scikit-image, safetensors) has everything this script needs; pykdtree, trimesh
# and xatlas are NOT needed (without pykdtree the CPU KD-tree falls back to scipy's cKDTree).  Any wheel
# put in .whl/ is installed first (carry ".whl"; `echo /.whl/ >> .git/info/exclude` here).  Optional, to
# run the CPU reference with pykdtree as on a workstation:
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
#     -d .whl pykdtree==1.4.3
# A lego field to carry (64 MiB limit on all that travels, the ~10 MB tree included): the trained file
# holds Adam's state (93 MB); saved again without it, 53 MB, into an ignored folder:
#   mkdir -p .gpu && echo /.gpu/ >> .git/info/exclude
#   .venv/bin/python -c "import neumesh_core as nm; nm.save_field(nm.load_field('/work/runs/lego/field.neumesh'), '.gpu/lego.neumesh')"
#   run(carry=[".gpu"], command="FIELD=.gpu/lego.neumesh bash benchmarks/gpu_check.sh", timeout_s=560)
# (with no DATA the lego views are cameras on a circle around the field; the JSON is then
# render_gpu_lego.json, the name of the file the docs cite: move it to benchmarks/results/figures/ and update
# the docs with it).
# The results' machine record names the commit measured; the lent machine's copy of the tree has no git,
# so pass it, as `git rev-parse HEAD` prints it here: run(command="NEUMESH_COMMIT=<sha> NEUMESH_DIRTY=0
# bash benchmarks/gpu_check.sh") (NEUMESH_DIRTY=1 when the tree has uncommitted changes).
set -uo pipefail
OUT="${OUT:-benchmarks/results/log/gpu_check}"
mkdir -p "$OUT"
T0=$(date +%s)
export PYTHONUNBUFFERED=1
export TRITON_CACHE_DIR="${TRITON_CACHE_DIR:-/tmp/neumesh_triton_cache}"
unset TRITON_INTERPRET
PY="${PYTHON:-python3}"
if ls .whl/*.whl >/dev/null 2>&1; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        && export PYTHONPATH="/tmp/site:${PYTHONPATH:-}"
fi
export PYTHONPATH="$PWD:${PYTHONPATH:-}"
{
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    $PY -c "import sys, torch, triton, numpy; print('python', sys.version.split()[0], '| torch', torch.__version__, '| triton', triton.__version__, '| numpy', numpy.__version__, '| cuda', torch.cuda.is_available())"
    $PY -c "import pykdtree" 2>/dev/null && echo "pykdtree: yes" || echo "pykdtree: no (scipy cKDTree fallback)"
} 2>&1 | tee "$OUT/env.txt"

echo "== tests (kernels compiled for the GPU; first calls include Triton's compilation)"
timeout "${TEST_TIMEOUT_S:-120}" $PY -m pytest -q -p no:cacheprovider --durations=8 \
    tests/kernels tests/test_device.py 2>&1 | tee "$OUT/tests.log"
TEST_RC=${PIPESTATUS[0]}
echo "tests exit code: $TEST_RC (124: timed out)" | tee -a "$OUT/tests.log"

echo "== benchmark"
ARGS=(--train-steps "${TRAIN_STEPS:-20}" --sweep --breakdown --budget-s "${BENCH_BUDGET_S:-200}" --results-dir "$OUT")
[ -n "${FIELD:-}" ] && ARGS+=(--field "$FIELD")
[ -n "${DATA:-}" ] && ARGS+=(--data "$DATA")
timeout "${BENCH_TIMEOUT_S:-290}" $PY benchmarks/bench/bench_render_gpu.py "${ARGS[@]}" 2>&1 | tee "$OUT/bench.log"
BENCH_RC=${PIPESTATUS[0]}

echo "== precision sweep (own process; tf32 may crash the CUDA context, which only ends this step)"
PARGS=(--sweep --sweep-set precision --sweep-only --results-dir "$OUT")
[ -n "${FIELD:-}" ] && PARGS+=(--field "$FIELD")
timeout "${PREC_TIMEOUT_S:-170}" $PY benchmarks/bench/bench_render_gpu.py "${PARGS[@]}" 2>&1 | tee "$OUT/bench_precision.log"
PREC_RC=${PIPESTATUS[0]}

echo "== summary ($(( $(date +%s) - T0 )) s)" | tee "$OUT/summary.txt"
{
    head -2 "$OUT/env.txt"
    echo "tests: exit $TEST_RC; $(grep -E '[0-9]+ (passed|failed)' "$OUT/tests.log" | tail -1)"
    echo "benchmark: exit $BENCH_RC; precision sweep: exit $PREC_RC"
    grep -E "sweep|kernel options|fps|PSNR|skipped|breakdown|deformation|training step" "$OUT/bench.log" | head -50
    grep -E "sweep|kernel options|error" "$OUT/bench_precision.log" | head -14
} 2>&1 | tee -a "$OUT/summary.txt"
