#!/usr/bin/env bash
# Stage, on this machine, what a lent GPU machine lacks for benchmarks/gpu_checks.sh.
#
# The lent machine (see BENCHMARKS.md, "GPU checks") has Python 3.12 with NumPy, SciPy,
# Pillow, tqdm and pytest, no network, and takes at most 64 MiB of files a call; a task gets
# 15 minutes of it, start-up and every call included. It lacks warp-lang (a 149 MB wheel),
# pypng, trimesh, shapely and Mitsuba with Dr.Jit (for the cuda_ad_rgb checks). This script
# downloads their wheels at the versions of .venv and unpacks them into one site folder,
# packed with xz (220 MB of wheels become about 141 MB) and cut into parts of 52 MiB: .gpu/1,
# .gpu/2, one to carry per call, and the last, smaller one in .gpu/data with the 64 px
# exemplars, the 128 px rosewood and their cached candidates, which the checks' call carries
# (their cache keys hold NumPy's and SciPy's versions: where the GPU machine's differ, the
# checks' first step computes them again there, before anything is timed). .gpu/ is
# git-ignored.
# Packing took six minutes on a 2-core machine.
#
#     make setup && benchmarks/gpu_prepare.sh
set -euo pipefail
cd "$(dirname "$0")/.."
py=.venv/bin/python
exemplars=${EXEMPLARS:-../shared/data/exemplars}
warp_version=$($py -c 'import warp; print(warp.__version__)')
pinned=$($py -c 'import importlib.metadata as m
print(" ".join(f"{p}=={m.version(p)}" for p in ("pypng", "trimesh", "shapely", "mitsuba", "drjit")))')

rm -rf .gpu
mkdir -p .gpu/wheels .gpu/site .gpu/data/exemplars .gpu/data/cache
# shellcheck disable=SC2086  # one requirement per word of $pinned
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d .gpu/wheels \
    "warp-lang==$warp_version" $pinned
# A wheel is its packages as they lie in site-packages, so unpacking them is installing them
# there, and one xz stream packs them far tighter than the wheels' zip.
for wheel in .gpu/wheels/*.whl; do
    unzip -q -o "$wheel" -d .gpu/site
done
tar cf - -C .gpu/site . | xz -9 -T0 | split -b 52M -d -a 1 - .gpu/part-
rm -r .gpu/wheels .gpu/site
parts=(.gpu/part-*)
for part in "${parts[@]}"; do
    if [ "$part" = "${parts[-1]}" ]; then
        mv "$part" .gpu/data/
    else
        n=$((${part##*-} + 1))
        mkdir -p ".gpu/$n"
        mv "$part" ".gpu/$n/"
    fi
done

# bench_synthesis.py also times a 128^3 volume from the 128 px rosewood.
cp "$exemplars"/*_64.png "$exemplars"/wood_rosewood_128.png .gpu/data/exemplars/
WARP_CACHE_PATH=$PWD/.cache/warp $py - <<'PY'
import shutil
from pathlib import Path

from warptex.candidates import cached_candidate_path, precompute
from warptex.exemplar import Exemplar

for png in sorted(Path(".gpu/data/exemplars").glob("*.png")):
    ex = Exemplar.load(png)
    path = cached_candidate_path(ex)
    if path is None:
        precompute(ex)
        path = cached_candidate_path(ex)
    shutil.copy(path, Path(".gpu/data/cache") / path.name)
PY
git describe --always --dirty > .gpu/data/commit  # the working tree is what runs there
echo "staged: $(ls -d .gpu/[0-9]* | tr '\n' ' ')and .gpu/data ($(du -sh .gpu/data | cut -f1)," \
     "the last part included); warp-lang $warp_version, $pinned, commit $(cat .gpu/data/commit)"
