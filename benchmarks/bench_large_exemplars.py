"""Time and peak memory of pre-computing the candidates of large exemplars (Dong 2008,
section 4), the figures behind ``Exemplar.load(..., max_size=)`` and the memory check of
``warptex.candidates.precompute``.

Each side runs in a fresh process: a photo (default ``dry_mud_256``) resampled to SIDE x
SIDE pixels (bicubic, so sides beyond the photo's own are enlarged copies of it), Warp
kernels warmed on a tiny exemplar first, then one uncached pre-computation. Prints its wall
seconds, the process's peak resident memory and its growth over the warmed-up process, and
the peak that ``precompute`` estimates before refusing an exemplar.

    .venv/bin/python benchmarks/bench_large_exemplars.py [--photo PATH] [--sides 128 256 512]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
os.environ.setdefault("WARP_CACHE_PATH", str(REPO / ".cache" / "warp"))
PHOTO = REPO.parent / "shared" / "data" / "exemplars" / "dry_mud_256.png"


def _peak_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB


def one(photo: Path, side: int) -> dict:
    """Pre-compute one resampled exemplar in this process; its figures."""
    import numpy as np
    from PIL import Image

    import warptex.candidates as candidates
    from warptex.exemplar import Exemplar

    rgb = Image.open(photo).convert("RGB")
    pixels = np.asarray(rgb.resize((side, side), Image.Resampling.BICUBIC))
    ex = Exemplar(pixels, name=f"{photo.stem}@{side}")
    candidates.precompute(Exemplar(pixels[:16, :16], name="warm-up"), cache=False)
    warm = _peak_bytes()
    start = time.perf_counter()
    candidates.precompute(ex, cache=False)
    seconds = time.perf_counter() - start
    peak = _peak_bytes()
    estimate = candidates._BASE_BYTES + side * side * candidates._BYTES_PER_PIXEL
    return {"seconds": seconds, "peak": peak, "growth": peak - warm, "estimate": estimate}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photo", type=Path, default=PHOTO)
    parser.add_argument("--sides", nargs="+", type=int, default=[128, 256, 512])
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # the child's side
    args = parser.parse_args()
    if args.one is not None:
        print(json.dumps(one(args.photo, args.one)))
        return

    mib = 2**20
    print(f"photo {args.photo.name}, resampled to SIDE x SIDE, one fresh process per side")
    print("\n| side | pixels | seconds | peak MiB | growth MiB | growth KB/pixel "
          "| precompute's estimate MiB |")
    print("|---|---|---|---|---|---|---|")
    for side in args.sides:
        child = subprocess.run(
            [sys.executable, __file__, "--photo", str(args.photo), "--one", str(side)],
            check=True, capture_output=True, text=True,
        )
        r = json.loads(child.stdout.strip().splitlines()[-1])
        print(f"| {side} | {side * side:,} | {r['seconds']:.1f} | {r['peak'] / mib:.0f} "
              f"| {r['growth'] / mib:.0f} | {r['growth'] / side**2 / 1000:.1f} "
              f"| {r['estimate'] / mib:.0f} |", flush=True)


if __name__ == "__main__":
    main()
