#!/usr/bin/env bash
# The checks that need a CUDA GPU, as one script for one call of a lent GPU machine
# (BENCHMARKS.md, "GPU checks"; stage its inputs with benchmarks/gpu_prepare.sh):
#   - issue 7's speed bar first: Kopf and the lazy engine at 64^3 in the same run, every
#     64 px exemplar (benchmarks/bench_kopf.py);
#   - where the lazy engine's time goes on the GPU, host bookkeeping or device work
#     (benchmarks/profile_synthesis.py);
#   - CPU and CUDA synthesize bit-identical voxels (tests/test_synthesis.py), and agree on
#     brick-store queries, surface shells and texel points (tests/test_cuda.py); the
#     plugin's cuda_ad_rgb lookups equal SolidTexture.query (tests/test_plugin.py), and its
#     cuda_* variants register, evaluate and upsample spectra as Mitsuba does
#     (tests/test_spectral.py);
#   - the engine's own figures (benchmarks/bench_synthesis.py);
#   - not by default (STEPS=hostpaths, when time is left): the point queries and the
#     plugin's LLVM lookups with the engine and store on the GPU, warptex's default on such
#     a machine (tests/test_texture.py, tests/test_plugin.py), which no step above runs.
# First (step precompute) the candidates of every staged exemplar are made where the staged
# cache does not serve (its keys hold NumPy's and SciPy's versions, which the machine's may
# not match), outside any timing. Each step has its time limit, so that the whole ends
# within about 585 s (unpacking included) and what finished comes back; each step's exit
# status goes to $OUT/steps.txt (124: cut off by its limit), and the script fails if any
# step did, or if Warp finds no CUDA device (the CUDA tests would skip, and the benchmarks
# run on the CPU). PARTS is the folder holding the staged parts carried by the earlier calls
# (the last part travels in .gpu/data); results go to $OUT (or out/gpu). NAMES limits
# bench_kopf's exemplars (names without .png; default every *_64.png); STEPS picks steps by
# name (default "precompute kopf profile tests synthesis"), for a rerun of what did not
# finish. Stage from the commit to be measured: .gpu/data/commit labels the
# results.
#
#     benchmarks/gpu_checks.sh PARTS
set -uo pipefail
cd "$(dirname "$0")/.."
parts=${1:?usage: benchmarks/gpu_checks.sh PARTS}
out=${OUT:-out/gpu}
data=.gpu/data
mkdir -p "$out" /tmp/site
if [ ! -e /tmp/site/.installed ]; then
    # Python's lzma, as the machine may lack the xz command.
    cat "$parts"/part-* "$data"/part-* \
        | python3 -c 'import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.stdin.buffer), sys.stdout.buffer)' \
        | tar xf - -C /tmp/site || exit 1
    touch /tmp/site/.installed
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
export WARP_CACHE_PATH=/tmp/warp-cache WARPTEX_CACHE=$data/cache
names=${NAMES:-$(cd "$data/exemplars" && ls ./*_64.png | xargs -n1 basename | sed 's/\.png$//')}
steps=" ${STEPS:-precompute kopf profile tests synthesis} "
failed=0
: > "$out/steps.txt"

# noted NAME RC: a step's exit status RC (its pipe's first command's) into steps.txt; any
# other than 0 fails the script once every step has run.
noted() {
    local name=$1 rc=$2
    echo "$name rc=$rc$([ "$rc" = 124 ] && echo ' (cut off by its time limit)')" \
        | tee -a "$out/steps.txt"
    [ "$rc" = 0 ] || failed=1
}

{
    echo "commit $(cat "$data/commit"), $(date -u '+%Y-%m-%d %H:%M UTC')"
    nvidia-smi -L 2>&1
    lscpu 2>/dev/null | grep 'Model name'
    echo "$(nproc) CPU cores; $(python3 --version); numpy $(python3 -c 'import numpy; print(numpy.__version__)')"
} | tee "$out/machine.txt"
python3 -c 'import warp as wp; wp.init(); assert wp.get_cuda_device_count() > 0, "no CUDA device"' \
    2>&1 | tee -a "$out/machine.txt"
[ "${PIPESTATUS[0]}" = 0 ] || { echo "Warp sees no CUDA device: nothing measured" | tee -a "$out/steps.txt"; exit 1; }

if [[ $steps == *" precompute "* ]]; then
    timeout 40 python3 -c '
import sys
from pathlib import Path
from warptex.candidates import precompute
from warptex.exemplar import Exemplar
for png in sorted(Path(sys.argv[1]).glob("*.png")):
    precompute(Exemplar.load(png), progress=False)
    print("candidates of", png.name)
' "$data/exemplars" 2>&1 | tee "$out/precompute.txt"
    noted precompute "${PIPESTATUS[0]}"
fi

if [[ $steps == *" kopf "* ]]; then
    # shellcheck disable=SC2086  # one exemplar name per word
    timeout 160 python3 benchmarks/bench_kopf.py --exemplars "$data/exemplars" --sizes 64 \
        --names $names 2>&1 | tee "$out/bench_kopf.txt"
    noted kopf "${PIPESTATUS[0]}"
fi
if [[ $steps == *" profile "* ]]; then
    timeout 60 python3 benchmarks/profile_synthesis.py --exemplars "$data/exemplars" \
        --names granite_64 rocks_in_sand_64 --sizes 64 2>&1 | tee "$out/profile.txt"
    noted profile-64 "${PIPESTATUS[0]}"
    timeout 40 python3 benchmarks/profile_synthesis.py --exemplars "$data/exemplars" \
        --names wood_rosewood_128 --sizes 128 2>&1 | tee -a "$out/profile.txt"
    noted profile-128 "${PIPESTATUS[0]}"
fi
if [[ $steps == *" tests "* ]]; then
    timeout 180 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py \
        tests/test_synthesis.py tests/test_plugin.py tests/test_spectral.py -k cuda -rs 2>&1 \
        | tee "$out/pytest_cuda.txt"
    noted tests "${PIPESTATUS[0]}"
fi
if [[ $steps == *" hostpaths "* ]]; then
    WARPTEX_DEVICE=cuda timeout 150 python3 -m pytest -q -p no:cacheprovider \
        tests/test_texture.py tests/test_plugin.py -rs 2>&1 | tee "$out/pytest_hostpaths.txt"
    noted hostpaths "${PIPESTATUS[0]}"
fi
if [[ $steps == *" synthesis "* ]]; then
    timeout 90 python3 benchmarks/bench_synthesis.py --exemplars "$data/exemplars" --repeat 2 \
        2>&1 | tee "$out/bench_synthesis.txt"
    noted synthesis "${PIPESTATUS[0]}"
fi
exit "$failed"
