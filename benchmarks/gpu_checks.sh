#!/usr/bin/env bash
# The checks that need a CUDA GPU, as one script for a lent GPU machine (BENCHMARKS.md,
# "GPU checks"; stage its inputs with benchmarks/gpu_prepare.sh):
#   - CPU and CUDA synthesize bit-identical voxels (tests/test_synthesis.py), and agree on
#     brick-store queries, surface shells and texel points (tests/test_cuda.py); the
#     plugin's cuda_ad_rgb lookups equal SolidTexture.query (tests/test_plugin.py);
#   - issue 7's speed bar: Kopf and the lazy engine at 64^3 in the same run, every 64 px
#     exemplar (benchmarks/bench_kopf.py);
#   - the engine's own figures (benchmarks/bench_synthesis.py).
# PARTS is the folder holding every part-N of the staged wheels; results go to $OUT (or
# out/gpu). NAMES limits bench_kopf's exemplars (names without .png; default every *_64.png).
# WHAT is "tests" or "benchmarks": each fits one call of the machine (600 s at most), and
# the second call finds the wheels the first installed.
#
#     benchmarks/gpu_checks.sh PARTS tests|benchmarks
set -uo pipefail
cd "$(dirname "$0")/.."
parts=${1:?usage: benchmarks/gpu_checks.sh PARTS tests|benchmarks}
what=${2:?usage: benchmarks/gpu_checks.sh PARTS tests|benchmarks}
out=${OUT:-out/gpu}
data=.gpu/data
mkdir -p "$out" /tmp/gpu-wheels /tmp/site
if [ ! -e /tmp/site/.installed ]; then
    cat "$parts"/part-* | tar xf - -C /tmp/gpu-wheels || exit 1
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site /tmp/gpu-wheels/*.whl || exit 1
    touch /tmp/site/.installed
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
export WARP_CACHE_PATH=/tmp/warp-cache WARPTEX_CACHE=$data/cache
names=${NAMES:-$(cd "$data/exemplars" && ls ./*_64.png | xargs -n1 basename | sed 's/\.png$//')}

{
    echo "commit $(cat "$data/commit"), $(date -u '+%Y-%m-%d %H:%M UTC')"
    nvidia-smi -L 2>&1
    lscpu 2>/dev/null | grep 'Model name'
    echo "$(nproc) CPU cores; $(python3 --version)"
} | tee "$out/machine.txt"

if [ "$what" = tests ]; then
    timeout 480 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py \
        tests/test_synthesis.py tests/test_plugin.py -k cuda -rs 2>&1 | tee "$out/pytest_cuda.txt"
    exit 0
fi
# shellcheck disable=SC2086  # one exemplar name per word
timeout 400 python3 benchmarks/bench_kopf.py --exemplars "$data/exemplars" --sizes 64 \
    --names $names 2>&1 | tee "$out/bench_kopf.txt"
timeout 150 python3 benchmarks/bench_synthesis.py --exemplars "$data/exemplars" --repeat 2 2>&1 \
    | tee "$out/bench_synthesis.txt"
