"""Peak memory of building Kopf's search structure (Kopf 2007, section 4.2: 8x8 windows of
the exemplar, PCA, ANN tree), which grows with the exemplar's pixels, not the solid's size.

Prints, per exemplar, the peak that Python's allocations reach while one search structure
is built at full resolution with the exemplar's own seams (``tileable="auto"``, the default;
tracemalloc: NumPy's and SciPy's arrays), per pixel, and what the commands' memory check
counts for it (``warptex.baselines.kopf.search_bytes``).

    python benchmarks/bench_kopf_search_memory.py [--exemplars DIR] [--names rust_256 ...]
"""

from __future__ import annotations

import argparse
import tracemalloc
from pathlib import Path

import numpy as np
from timing import run_record

from warptex.baselines import kopf
from warptex.exemplar import Exemplar

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DIR = ROOT.parent / "shared" / "data" / "exemplars"


def search_peak(exemplar: Exemplar) -> tuple[int, int]:
    """Peak bytes while the search structure of ``exemplar`` is built, and its PCA's kept
    coefficients."""
    features = np.ascontiguousarray(exemplar.features)
    seams = exemplar.seams("auto")
    tracemalloc.start()
    try:
        axis = kopf._search_structure(features, seams)
        return tracemalloc.get_traced_memory()[1], axis.dims
    finally:
        tracemalloc.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--exemplars", type=Path, default=DEFAULT_DIR)
    parser.add_argument("--names", nargs="+",
                        default=["granite_64", "bricks_red_128", "rust_256", "wood_rosewood_256"])
    args = parser.parse_args()
    print(run_record(), flush=True)
    print("\n| exemplar | pixels | seams (rows, columns) | PCA coefficients | peak MiB | "
          "bytes per pixel | search_bytes MiB |")
    print("|---|---|---|---|---|---|---|")
    for name in args.names:
        exemplar = Exemplar.load(args.exemplars / f"{name}.png")
        peak, dims = search_peak(exemplar)
        pixels = exemplar.shape[0] * exemplar.shape[1]
        seams = ", ".join("yes" if s else "no" for s in exemplar.seams("auto"))
        print(f"| {name} | {exemplar.shape[1]}x{exemplar.shape[0]} | {seams} | {dims} | "
              f"{peak / 2**20:.1f} | {peak / pixels:.0f} | "
              f"{kopf.search_bytes([exemplar]) / 2**20:.1f} |", flush=True)


if __name__ == "__main__":
    main()
