"""Memory that writing a volume file holds besides the volume (warptex.volume_files).

Prints, per format and encoding, the growth of the peak resident memory while
``write_volume`` writes a random SIZE^3 RGB volume, in copies of the volume: what
``WRITE_COPIES`` (the `volume` command's memory check) must cover. Each write runs in a
process of its own, its libraries imported and its peak reset (``PeakMemory``) before the
write.

    python benchmarks/bench_write_memory.py [--size 256]
"""

from __future__ import annotations

import argparse
import multiprocessing
import tempfile
from pathlib import Path

import numpy as np
from timing import run_record

from warptex.machine import PeakMemory
from warptex.volume_files import WRITE_COPIES, write_volume


def _copies_held(path: Path, size: int, srgb: bool) -> float:
    """Peak resident memory gained by one write, in copies of the volume."""
    import OpenEXR  # noqa: F401  (imported here so that its loading is not counted)

    volume = np.random.default_rng(0).random((size, size, size, 3), dtype=np.float32)
    # Its peak reset first: a spawned process starts with the parent's ru_maxrss, which
    # hid any write peaking below the parent's size.
    with PeakMemory() as held:
        write_volume(path, volume, srgb=srgb)
    return held.growth / volume.nbytes


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--size", type=int, default=256, help="edge of the volume in voxels")
    args = parser.parse_args()
    print(run_record(), flush=True)
    print(f"a {args.size}^3 RGB volume, {args.size**3 * 12 / 2**20:.0f} MiB")
    print("| format | colors | copies held (measured) | WRITE_COPIES |")
    print("|---|---|---|---|")
    context = multiprocessing.get_context("spawn")  # a fresh peak for each write
    with tempfile.TemporaryDirectory() as folder:
        for suffix, allowed in WRITE_COPIES.items():
            for srgb in (False, True):
                with context.Pool(1) as pool:
                    held = pool.apply(_copies_held,
                                      (Path(folder) / f"v{suffix}", args.size, srgb))
                colors = "sRGB, decoded" if srgb else "linear"
                print(f"| {suffix} | {colors} | {held:.2f} | {allowed} |", flush=True)


if __name__ == "__main__":
    main()
