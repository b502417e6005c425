"""Benchmark of the 3D candidate pre-computation (Dong 2008, sections 4 and 6.1; issue 3).

Prints, per exemplar, the pre-computation time (wall clock and this process's CPU time,
Warp kernels compiled beforehand on a tiny exemplar, cache off), the bytes of the
candidate data (``CandidateSet.nbytes``), where the time goes, and the pixels per level
that found no coherent candidate. Targets (issue 3, a 2-core machine): 64^2 in <= 5 s,
128^2 in <= 25 s, <= 500 KB for 64^2.

    .venv/bin/python benchmarks/bench_candidates.py [--names granite rust] [--sizes 64 128]
                                                    [--degenerate]

``--degenerate`` instead times synthetic photos whose windows tie by the thousand (a flat
grey with one light square, light dots on grey), each in a fresh process with its peak
resident memory beside the estimate that ``warptex info`` gives.
"""

from __future__ import annotations

import argparse
import os
import textwrap
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
os.environ.setdefault("WARP_CACHE_PATH", str(REPO / ".cache" / "warp"))

from timing import exemplar_files, in_a_process, positive_int, run_record  # noqa: E402

import warptex.candidates as candidates  # noqa: E402
from warptex.exemplar import Exemplar  # noqa: E402

EXEMPLARS = REPO.parent / "shared" / "data" / "exemplars"
TARGET_SECONDS = {64: 5.0, 128: 25.0}
TARGET_BYTES = {64: 500_000}
# Stages of candidates._compute, timed by wrapping the module's functions.
PHASES = {
    "_source_level": "PCA+2D",
    "_nearest_strips": "kNN",
    "_filter_coherent": "coherence",
    "_role_level": "3D",
}


@contextmanager
def phase_timer() -> Iterator[dict[str, float]]:
    """Accumulate the wall time spent in each function of :data:`PHASES`."""
    spent = {name: 0.0 for name in PHASES}
    originals = {name: getattr(candidates, name) for name in PHASES}

    def timed(name: str, fn: Callable) -> Callable:
        def run(*args, **kwargs):
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[name] += time.perf_counter() - start

        return run

    for name, fn in originals.items():
        setattr(candidates, name, timed(name, fn))
    try:
        yield spent
    finally:
        for name, fn in originals.items():
            setattr(candidates, name, fn)


def warm_up() -> None:
    """Compile (or load) every Warp kernel of the pre-computation on a tiny exemplar."""
    tiny = Exemplar.load(EXEMPLARS / "granite_64.png").colors[:16, :16]
    candidates.precompute(Exemplar(tiny, name="warm-up"), cache=False)


def measure(path: Path, repeat: int) -> dict:
    """Best of ``repeat`` uncached pre-computations of one exemplar."""
    ex = Exemplar.load(path)
    best: dict | None = None
    for _ in range(repeat):
        with phase_timer() as spent:
            wall, cpu = time.perf_counter(), time.process_time()
            cs = candidates.precompute(ex, cache=False)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        if best is None or wall < best["wall"]:
            # The 3D stage includes the kNN search and coherence filtering it calls.
            crossbar = spent["_role_level"] - spent["_nearest_strips"] - spent["_filter_coherent"]
            best = {
                "wall": wall,
                "cpu": cpu,
                "phases": {**spent, "crossbar": crossbar},
                "bytes": cs.nbytes(),
                "fallback": cs.stats["fallback_pixels"],
                "pixels": [lvl[0].size[0] * lvl[0].size[1] for lvl in cs.sources],
                "mean": [float(lvl[0].count.mean()) for lvl in cs.roles],
            }
    assert best is not None
    return best


def verdict(size: int, result: dict) -> str:
    notes = []
    limit = TARGET_SECONDS.get(size)
    if limit is not None:
        notes.append(f"time {'ok' if result['wall'] <= limit else 'MISSED'} (<= {limit:g} s)")
    limit = TARGET_BYTES.get(size)
    if limit is not None:
        ok = result["bytes"] <= limit
        notes.append(f"bytes {'ok' if ok else 'MISSED'} (<= {limit // 1000} KB)")
    return ", ".join(notes)


# One synthetic photo pre-computed in a fresh process, its kernels built (or loaded) on a
# 16 x 16 warm-up first; argv: kind, size.
_DEGENERATE_IN_A_PROCESS = textwrap.dedent("""
    import json, sys, time
    import numpy as np
    from warptex.candidates import precompute, precompute_bytes
    from warptex.exemplar import Exemplar
    from warptex.machine import PeakMemory
    kind, n = sys.argv[1], int(sys.argv[2])
    rng = np.random.default_rng(0)
    precompute(Exemplar(rng.random((16, 16, 3), np.float32), name="warm-up"), cache=False)
    image = np.full((n, n, 3), 0.5, np.float32)
    if kind == "flat":
        image[10:20, 10:20] = 0.9
    else:
        image[rng.random((n, n)) < 0.05] = 0.9
    exemplar = Exemplar(image, name=kind)
    with PeakMemory() as peak:  # reset: a child starts with its parent's ru_maxrss
        start = time.perf_counter()
        precompute(exemplar, cache=False)
        seconds = time.perf_counter() - start
    print(json.dumps({"seconds": seconds, "mib": peak.peak / 2**20,
                      "estimate": precompute_bytes([exemplar]) / 2**20}))
""")


def degenerate(sizes: list[int]) -> None:
    """Photos whose windows tie by the thousand, each pre-computed in a fresh process."""
    print("| photo | size | wall s | peak resident MiB | estimate MiB |")
    print("|---|---|---|---|---|")
    for kind, label in (("flat", "flat grey, one 10 x 10 light square"),
                        ("dots", "light dots on grey, 5 % of the pixels")):
        for size in sizes:
            r = in_a_process(["-c", _DEGENERATE_IN_A_PROCESS, kind, str(size)],
                             f"{kind} {size}")
            print(f"| {label} | {size}² | {r['seconds']:.1f} | {r['mib']:.0f} | "
                  f"{r['estimate']:.0f} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument(
        "--names", nargs="+", default=["granite", "marble_black", "rust", "bricks_red"]
    )
    parser.add_argument("--sizes", nargs="+", type=positive_int, default=[64, 128])
    parser.add_argument("--repeat", type=positive_int, default=1,
                        help="runs per exemplar; best kept")
    parser.add_argument("--degenerate", action="store_true",
                        help="only time synthetic photos of a flat colour or sparse dots")
    args = parser.parse_args()
    if not args.degenerate:  # which makes its own photos; the rest also reads warm_up's
        exemplar_files(parser, EXEMPLARS, dict.fromkeys(
            ["granite_64", *(f"{name}_{size}" for size in args.sizes for name in args.names)]))
    print(run_record(), flush=True)
    if args.degenerate:
        degenerate(args.sizes)
        return

    warm_up()
    print(
        "| exemplar | size | wall s | CPU s | PCA+2D s | kNN s | crossbar s | coherence s "
        "| bytes | fallback pixels per level (of pixels) | mean candidates, finest | targets |"
    )
    print("|" + "---|" * 12)
    for size in args.sizes:
        for name in args.names:
            r = measure(EXEMPLARS / f"{name}_{size}.png", args.repeat)
            ph = r["phases"]
            fallback = " / ".join(
                f"{f} ({p})" for f, p in zip(r["fallback"], r["pixels"], strict=True)
            )
            print(
                f"| {name} | {size}² | {r['wall']:.2f} | {r['cpu']:.2f} "
                f"| {ph['_source_level']:.2f} | {ph['_nearest_strips']:.2f} "
                f"| {ph['crossbar']:.2f} | {ph['_filter_coherent']:.2f} "
                f"| {r['bytes']:,} | {fallback} | {r['mean'][-1]:.2f} | {verdict(size, r)} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
