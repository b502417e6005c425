"""Peak memory of a whole Kopf synthesis (Kopf 2007, sections 4 and 5) against what the
commands' memory check counts for it before any work (``warptex volume --method kopf``,
``warptex compare``): the volume and its copy, ``kopf.working_bytes`` and
``kopf.search_bytes``.

Prints, per exemplar and volume size, each run in a process of its own (its Warp kernels
compiled first by an 8^3 run): the rise of the resident memory's peak over its start
(``warptex.machine.PeakMemory``, large blocks mapped afresh), the PCA coefficients kept at the
finest level, what the check counts, and the rise beyond the volume and its copy per voxel,
which ``WORK_BYTES_PER_VOXEL`` is to cover. Two iterations a level by default: a level's
second search is the first bounded by the current matches (its float64 distances to them,
taken in parts of rows), and later ones repeat it.

    python benchmarks/bench_kopf_memory.py [--exemplars DIR] [--names granite_64 noise8 ...]
                                           [--sizes 32 64] [--iterations 2]

``noiseC`` names C channels of uniform noise, 32 x 32, which keep every coefficient the
kernels hold (the most memory an exemplar of that size takes).
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np
from timing import exemplar_files, in_a_process, positive_int, run_record

from warptex.baselines import kopf
from warptex.exemplar import Exemplar
from warptex.machine import PeakMemory, map_large_blocks

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DIR = ROOT.parent / "shared" / "data" / "exemplars"


def _exemplar(folder: Path, name: str) -> Exemplar:
    if name.startswith("noise"):
        channels = int(name.removeprefix("noise"))
        return Exemplar(np.random.default_rng(0).random((32, 32, channels), np.float32),
                        name=name)
    return Exemplar.load(folder / f"{name}.png")


def synthesis_peak(exemplar: Exemplar, size: int, iterations: int) -> dict:
    """Peak bytes over the start while a ``size^3`` volume of ``exemplar`` is synthesized,
    and the coefficients its finest level's PCA kept."""
    map_large_blocks()
    with warnings.catch_warnings():  # noise keeps fewer coefficients than the paper's share
        warnings.simplefilter("ignore")
        kopf.synthesize(exemplar, size=8, iterations=1, progress=False)
        with PeakMemory() as resident:
            kopf.synthesize(exemplar, size=size, iterations=iterations, progress=False)
    finest = kopf._search_structure(np.ascontiguousarray(exemplar.features),
                                    exemplar.seams("auto"))
    return {"resident": resident.growth, "dims": finest.dims}


def _in_a_process(folder: Path, name: str, size: int, iterations: int) -> dict:
    """:func:`synthesis_peak` in a fresh process: memory freed by an earlier run would hide
    part of the next one's rise."""
    return in_a_process([__file__, "--exemplars", str(folder), "--one", name, "--sizes",
                         str(size), "--iterations", str(iterations)], f"{name} at {size}^3")


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--exemplars", type=Path, default=DEFAULT_DIR)
    parser.add_argument("--names", nargs="+",
                        default=["granite_64", "bricks_red_128", "noise3", "noise8"])
    parser.add_argument("--sizes", nargs="+", type=positive_int, default=[32, 64])
    parser.add_argument("--iterations", type=positive_int, default=2)
    parser.add_argument("--one", help=argparse.SUPPRESS)  # _in_a_process's
    args = parser.parse_args()
    if args.one is not None:
        exemplar = _exemplar(args.exemplars, args.one)
        print(json.dumps(synthesis_peak(exemplar, args.sizes[0], args.iterations)))
        return
    exemplar_files(parser, args.exemplars,
                   [name for name in args.names if not name.startswith("noise")])
    for size in args.sizes:
        kopf.check_size(size)
    print(run_record(), flush=True)
    print(f"\n{args.iterations} iteration(s) a level; counted: the volume and its copy, "
          f"working_bytes ({kopf.WORK_BYTES_PER_VOXEL} bytes a voxel) and search_bytes\n")
    print("| exemplar | size | PCA coefficients (finest) | resident peak MiB | counted MiB | "
          "counted / peak | peak beyond the volume and its copy, bytes a voxel |")
    print("|---|---|---|---|---|---|---|")
    for name in args.names:
        exemplar = _exemplar(args.exemplars, name)
        channels = exemplar.features.shape[2]
        for size in args.sizes:
            peak = _in_a_process(args.exemplars, name, size, args.iterations)
            volumes = 2 * 4 * channels * size**3
            counted = volumes + kopf.working_bytes(size) + kopf.search_bytes([exemplar])
            beyond = (peak["resident"] - volumes) / size**3
            print(f"| {name} | {size}^3 | {peak['dims']} | {peak['resident'] / 2**20:.1f} | "
                  f"{counted / 2**20:.1f} | {counted / peak['resident']:.2f} | "
                  f"{beyond:.0f} |", flush=True)


if __name__ == "__main__":
    main()
