"""Benchmark of brick store files (Dong 2008, section 6.2's stored results; issue 5).

Times saving a store of N whole bricks to a new file, saving it again over its own file (a
merge that adds nothing), saving a second store of N other bricks over it (a merge of both,
kept to the larger of the store's ``cache_bytes`` and the file's size), and loading that
merged file (up to 2N bricks; the default ``cache_bytes``, 256 MiB, holds about 85,000),
then the memory the merging save and the load hold at their peak beyond what was held
before, once each, apart from the timed runs: NumPy's and Python's allocations as
``tracemalloc`` counts them (the store's Warp arrays are not among them).
The stores are filled with valid triples without synthesizing them (``BrickStore._insert``),
so the figures are the files' costs alone, not synthesis.

    .venv/bin/python benchmarks/bench_store_files.py [--bricks 10000 40000 85000] [--halves]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import tracemalloc
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
os.environ.setdefault("WARP_CACHE_PATH", str(REPO / ".cache" / "warp"))

import numpy as np  # noqa: E402
from timing import best_of, exemplar_files, positive_int, run_record, timed_runs  # noqa: E402

from warptex.candidates import precompute  # noqa: E402
from warptex.keysets import pack  # noqa: E402
from warptex.store import BrickStore, brick_voxels  # noqa: E402
from warptex.synthesis import Synthesizer  # noqa: E402


def filled(synthesizer: Synthesizer, bricks: int, first: int) -> BrickStore:
    """A store of ``bricks`` whole bricks along a row of brick columns from ``first``."""
    store = BrickStore(synthesizer)
    coords = np.stack(np.unravel_index(np.arange(first, first + bricks), (64, 64, 64)), 1) - 32
    voxels = brick_voxels(pack(coords))
    pixels = synthesizer.candidates.colors[0].shape[0] * synthesizer.candidates.colors[0].shape[1]
    triples = np.random.default_rng(first).integers(0, pixels, (len(voxels), 3))
    store._insert(voxels, triples)
    return store


def halves(synthesizer: Synthesizer, bricks: int, upper: bool) -> BrickStore:
    """A store of partly filled bricks (``whole_bricks=False``, as bake and cut make):
    the lower or upper half of each of ``bricks`` bricks, so two such stores of one file
    merge brick by brick, voxel by voxel."""
    store = BrickStore(synthesizer, whole_bricks=False)
    coords = np.stack(np.unravel_index(np.arange(bricks), (64, 64, 64)), 1) - 32
    half = brick_voxels(pack(coords)).reshape(bricks, 512, 3)[:, 256 * upper:256 * (upper + 1)]
    pixels = synthesizer.candidates.colors[0].shape[0] * synthesizer.candidates.colors[0].shape[1]
    voxels = half.reshape(-1, 3)
    store._insert(voxels, np.random.default_rng(upper).integers(0, pixels, (len(voxels), 3)))
    return store


def peak_mib(run) -> float:
    """The most memory ``run()`` holds at once beyond what was held before, in MiB."""
    tracemalloc.start()
    try:
        run()
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--exemplar", default=str(REPO / "tests" / "data" / "granite_64.png"))
    parser.add_argument("--bricks", type=int, nargs="+", default=[10_000, 40_000, 85_000])
    parser.add_argument("--repeat", type=positive_int, default=3)
    parser.add_argument("--halves", action="store_true",
                        help="instead: the merging save of two stores of the same N bricks, "
                             "each holding the other half of each brick")
    args = parser.parse_args()
    exemplar_files(parser, Path(), [args.exemplar], "")
    print(run_record(), flush=True)
    synthesizer = Synthesizer(precompute(args.exemplar), device="cpu")
    if args.halves:
        print("| bricks N, half filled in each store | merged file MiB | "
              "merging save, peak MiB held |")
        print("|---|---|---|")
        with tempfile.TemporaryDirectory() as folder:
            for n in args.bricks:
                path = Path(folder) / f"h{n}.wtb"
                lower, upper = halves(synthesizer, n, False), halves(synthesizer, n, True)
                lower.save(path)
                saving = peak_mib(lambda upper=upper, path=path: upper.save(path))
                print(f"| {n} | {path.stat().st_size / 2**20:.0f} | {saving:.0f} |",
                      flush=True)
        return
    print("| bricks N | save, new file s | save over itself s | save of N other bricks over "
          "it s | merged file MiB | load of the merged file s | merging save, peak MiB held | "
          "load, peak MiB held |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        for n in args.bricks:
            path = Path(folder) / f"s{n}.wtb"
            store, other = filled(synthesizer, n, 0), filled(synthesizer, n, n)

            # The old file deleted before each timed save, not in its time.
            fresh = min(timed_runs(lambda _, store=store, path=path: store.save(path),
                                   args.repeat, lambda path=path: path.unlink(missing_ok=True)))
            again = best_of(lambda store=store, path=path: store.save(path), args.repeat)
            times = []
            for _ in range(args.repeat):
                path.unlink(missing_ok=True)
                store.save(path)
                start = time.perf_counter()
                other.save(path)
                times.append(time.perf_counter() - start)
            size = path.stat().st_size / 2**20
            load = best_of(lambda path=path: BrickStore.load(path, synthesizer), args.repeat)
            path.unlink()
            store.save(path)
            saving = peak_mib(lambda other=other, path=path: other.save(path))
            loading = peak_mib(lambda path=path: BrickStore.load(path, synthesizer))
            print(f"| {n} | {fresh:.2f} | {again:.2f} | {min(times):.2f} | {size:.0f} | "
                  f"{load:.2f} | {saving:.0f} | {loading:.0f} |")


if __name__ == "__main__":
    main()
