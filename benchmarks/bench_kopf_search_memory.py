"""Peak memory of building Kopf's search structure (Kopf 2007, section 4.2: 8x8 windows of
the exemplar, PCA, ANN tree), which grows with the exemplar's pixels, not the solid's size.

Prints, per exemplar, how far memory rises while one search structure is built at full
resolution with the exemplar's own seams (``tileable="auto"``, the default), each in a
process of its own: the resident memory's peak over its start (``warptex.machine.
PeakMemory``: all of it, LAPACK's and the ANN tree's C++ included), per pixel, and the peak
of Python's allocations alone (tracemalloc: NumPy's and SciPy's arrays); and what the
commands' memory check counts for it (``warptex.baselines.kopf.search_bytes``).

    python benchmarks/bench_kopf_search_memory.py [--exemplars DIR] [--names rust_256 ...]
"""

from __future__ import annotations

import argparse
import json
import tracemalloc
from pathlib import Path

import numpy as np
from timing import exemplar_files, in_a_process, run_record

from warptex.baselines import kopf
from warptex.exemplar import Exemplar
from warptex.machine import PeakMemory

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DIR = ROOT.parent / "shared" / "data" / "exemplars"


def search_peak(path: Path) -> dict:
    """Peak bytes over the start while the search structure of the exemplar ``path`` is
    built: resident, and (in a second build, as tracing takes memory of its own) of
    Python's allocations; and its PCA's kept coefficients."""
    exemplar = Exemplar.load(path)
    features = np.ascontiguousarray(exemplar.features)
    seams = exemplar.seams("auto")
    with PeakMemory() as resident:
        axis = kopf._search_structure(features, seams)
    del axis
    tracemalloc.start()
    try:
        axis = kopf._search_structure(features, seams)
        return {"resident": resident.growth, "python": tracemalloc.get_traced_memory()[1],
                "dims": axis.dims}
    finally:
        tracemalloc.stop()


def _in_a_process(path: Path) -> dict:
    """:func:`search_peak` in a fresh process: memory freed by an earlier build would
    hide part of the next one's rise."""
    return in_a_process([__file__, "--one", str(path)], f"{path}: the build")


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--exemplars", type=Path, default=DEFAULT_DIR)
    parser.add_argument("--names", nargs="+",
                        default=["granite_64", "bricks_red_128", "rust_256", "wood_rosewood_256"])
    parser.add_argument("--one", type=Path, help=argparse.SUPPRESS)  # _in_a_process's
    args = parser.parse_args()
    if args.one is not None:
        print(json.dumps(search_peak(args.one)))
        return
    exemplar_files(parser, args.exemplars, args.names)
    print(run_record(), flush=True)
    print("\n| exemplar | pixels | seams (rows, columns) | PCA coefficients | resident peak MiB | "
          "bytes per pixel | Python's allocations MiB | search_bytes MiB |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.names:
        path = args.exemplars / f"{name}.png"
        exemplar = Exemplar.load(path)
        peak = _in_a_process(path)
        pixels = exemplar.shape[0] * exemplar.shape[1]
        seams = ", ".join("yes" if s else "no" for s in exemplar.seams("auto"))
        print(f"| {name} | {exemplar.shape[1]}x{exemplar.shape[0]} | {seams} | "
              f"{peak['dims']} | {peak['resident'] / 2**20:.1f} | "
              f"{peak['resident'] / pixels:.0f} | {peak['python'] / 2**20:.1f} | "
              f"{kopf.search_bytes([exemplar]) / 2**20:.1f} |", flush=True)


if __name__ == "__main__":
    main()
