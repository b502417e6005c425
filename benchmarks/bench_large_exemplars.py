"""Time and peak memory of pre-computing the candidates of large exemplars (Dong 2008,
section 4), the figures behind ``Exemplar.load(..., max_size=)`` and the memory check of
``warptex.candidates.precompute``.

Each side runs in a fresh process: photos resampled to SIDE x SIDE pixels (bicubic, so
sides beyond a photo's own are enlarged copies of it), Warp kernels warmed on a tiny
exemplar first, then one uncached pre-computation: of the first photo on all three axes
(default ``dry_mud_256``), or of three photos, one per axis, given three. Prints its wall
seconds, the process's peak resident memory and its growth over the warmed-up process, and
the peak that ``precompute`` estimates before refusing exemplars
(``warptex.candidates.precompute_bytes``).

    .venv/bin/python benchmarks/bench_large_exemplars.py [--photos PATH [PATH PATH]]
                                                         [--sides 128 256 512]
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

from timing import exemplar_files, run_record  # noqa: E402

EXEMPLARS = REPO.parent / "shared" / "data" / "exemplars"
PHOTO = EXEMPLARS / "dry_mud_256.png"


def _peak_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB


def one(photos: list[Path], side: int) -> dict:
    """Pre-compute the resampled exemplars in this process; its figures."""
    import numpy as np
    from PIL import Image

    import warptex.candidates as candidates
    from warptex.exemplar import Exemplar

    exemplars = []
    for photo in photos:
        rgb = Image.open(photo).convert("RGB")
        pixels = np.asarray(rgb.resize((side, side), Image.Resampling.BICUBIC))
        exemplars.append(Exemplar(pixels, name=f"{photo.stem}@{side}"))
    candidates.precompute(Exemplar(pixels[:16, :16], name="warm-up"), cache=False)
    warm = _peak_bytes()
    start = time.perf_counter()
    candidates.precompute(*exemplars, cache=False)
    seconds = time.perf_counter() - start
    peak = _peak_bytes()
    return {"seconds": seconds, "peak": peak, "growth": peak - warm,
            "estimate": candidates.precompute_bytes(exemplars)}


def _photo(text: str) -> Path:
    """A photo's path as given, else its name in the shared exemplar folder."""
    path = Path(text)
    if not path.exists() and (EXEMPLARS / path).exists():
        return EXEMPLARS / path
    if not path.exists():
        raise argparse.ArgumentTypeError(f"{text}: no such file here or in {EXEMPLARS}")
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--photos", nargs="+", type=_photo, default=[PHOTO],
                        help="one photo for all three axes, or three, one per axis: paths, or "
                        f"names of files in {EXEMPLARS}")
    parser.add_argument("--sides", nargs="+", type=int, default=[128, 256, 512])
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # the child's side
    args = parser.parse_args()
    if len(args.photos) not in (1, 3):
        parser.error("give one photo or three")
    exemplar_files(parser, Path(), args.photos, "")  # the default, which _photo never sees
    if args.one is not None:
        print(json.dumps(one(args.photos, args.one)))
        return
    print(run_record(), flush=True)

    mib = 2**20
    names = ", ".join(p.name for p in args.photos)
    print(f"photos {names}, resampled to SIDE x SIDE, one fresh process per side")
    print("\n| side | pixels | seconds | peak MiB | growth MiB | growth KB/pixel "
          "| precompute's estimate MiB |")
    print("|---|---|---|---|---|---|---|")
    for side in args.sides:
        child = subprocess.run(
            [sys.executable, __file__, "--photos", *map(str, args.photos), "--one", str(side)],
            check=False, capture_output=True, text=True,
        )
        if child.returncode != 0:  # its own error, which capturing would hide
            sys.exit(f"side {side}: the measuring process failed:\n{child.stderr}")
        r = json.loads(child.stdout.strip().splitlines()[-1])
        print(f"| {side} | {side * side:,} | {r['seconds']:.1f} | {r['peak'] / mib:.0f} "
              f"| {r['growth'] / mib:.0f} | {r['growth'] / side**2 / 1000:.1f} "
              f"| {r['estimate'] / mib:.0f} |", flush=True)


if __name__ == "__main__":
    main()
