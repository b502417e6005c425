"""Benchmark of point queries on the brick store (Dong 2008, section 5.2; issue 5).

(a) Warm: a 64^3 voxel region is synthesized and stored, then 10M random points inside it
are queried with ``nearest`` and ``trilinear``; points per second, and the ratio to a plain
NumPy gather (and a NumPy trilinear blend) from a dense array of the same voxels.
Targets: >= 5M points/s and <= 3x the dense gather. The store's queries split over the
usable cores (up to 8, ``warptex.parallel``) and NumPy's gather runs on one, so the line
before the figures says how many the store used; ``taskset -c 0`` compares one core with
one.

(b) Cold: points of a Fibonacci sphere of radius 200 voxels, dense enough to touch every
brick the surface crosses, on a fresh texture; voxels synthesized per level divided by the
voxels of the touched bricks (target <= 4 at the finest level), time, and bytes per stored
voxel (target <= 8 for RGB plus <= 10% index).

    .venv/bin/python benchmarks/bench_store.py [--exemplar tests/data/granite_64.png]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
os.environ.setdefault("WARP_CACHE_PATH", str(REPO / ".cache" / "warp"))

import numpy as np  # noqa: E402
from timing import best_of, exemplar_files, run_record  # noqa: E402

from warptex.candidates import precompute  # noqa: E402
from warptex.parallel import THREADS  # noqa: E402
from warptex.texture import SolidTexture  # noqa: E402
from warptex.warp_runtime import device  # noqa: E402

REGION = 64
POINTS = 10_000_000
RADIUS = 200.0


def dense_trilinear(dense: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = pts - np.float32(0.5)
    base = np.floor(q).astype(np.intp)
    t = q - base
    out = np.zeros((len(pts), dense.shape[-1]), np.float32)
    for d in np.indices((2, 2, 2)).reshape(3, -1).T:
        w = np.prod(np.where(d == 1, t, 1 - t), axis=1)
        c = base + d
        out += w[:, None] * dense[c[:, 0], c[:, 1], c[:, 2]]
    return out


def warm(candidates) -> None:
    SolidTexture(candidates).query(np.full((1, 3), -1000.0))  # load the kernels untimed
    tex = SolidTexture(candidates)
    centers = np.indices((REGION,) * 3).reshape(3, -1).T + 0.5
    start = time.perf_counter()
    dense = tex.query(centers, filter="nearest").reshape(REGION, REGION, REGION, -1)
    print(f"fill {REGION}^3 region: {time.perf_counter() - start:.2f} s "
          f"({tex.store.stats()['bricks']} bricks)")
    rng = np.random.default_rng(0)
    # Inside the centers' hull, so the dense trilinear blend never reads past the array.
    pts = rng.uniform(0.5, REGION - 0.51, (POINTS, 3)).astype(np.float32)
    tex.query(pts[:100_000], filter="trilinear")  # compile and load every kernel first
    misses = tex.store.stats()["misses"]
    lookups = "the GPU" if device() == "cuda" else f"{THREADS} thread{'s' * (THREADS > 1)}"
    print(f"store queries on {lookups}, NumPy on one thread")

    def gather() -> np.ndarray:
        v = np.floor(pts).astype(np.intp)
        return dense[v[:, 0], v[:, 1], v[:, 2]]

    t_gather = best_of(gather, 3)
    t_dense_tri = best_of(lambda: dense_trilinear(dense, pts), 1)
    print(f"numpy dense gather:    {t_gather:.3f} s  {POINTS / t_gather / 1e6:6.2f} Mpts/s")
    print(f"numpy dense trilinear: {t_dense_tri:.3f} s  {POINTS / t_dense_tri / 1e6:6.2f} Mpts/s")
    for filter in ("nearest", "trilinear"):
        t = best_of(lambda f=filter: tex.query(pts, filter=f), 3)
        ref = t_gather if filter == "nearest" else t_dense_tri
        print(f"store {filter:9s}:       {t:.3f} s  {POINTS / t / 1e6:6.2f} Mpts/s  "
              f"{t / t_gather:.2f}x dense gather, {t / ref:.2f}x dense {filter}")
    v = np.floor(pts[:100_000]).astype(np.intp)
    got = tex.query(pts[:100_000], filter="nearest")
    assert np.array_equal(got, dense[v[:, 0], v[:, 1], v[:, 2]]), "nearest != dense voxels"
    assert tex.store.stats()["misses"] == misses, "warm queries must not miss"


def fibonacci_sphere(n: int, radius: float) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    phi = np.pi * (1 + 5**0.5) * i
    return radius * np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def cold(candidates) -> None:
    tex = SolidTexture(candidates)
    before = dict(tex.synthesizer.voxels_synthesized)
    # About 4 points per voxel^2 of surface: spacing 0.5 voxel, far below a brick's 8.
    n = int(4 * 4 * np.pi * RADIUS**2)
    pts = fibonacci_sphere(n, RADIUS)
    start = time.perf_counter()
    tex.query(pts, filter="trilinear")
    seconds = time.perf_counter() - start
    s = tex.store.stats()
    touched = s["voxels"]
    print(f"sphere r={RADIUS:.0f}: {n} points, {touched} voxels read and stored in "
          f"{s['bricks']} bricks, {seconds:.1f} s ({s['synthesis_seconds']:.1f} s synthesizing)")
    for level, count in s["voxels_synthesized"].items():
        made = count - before[level]
        print(f"  level {level}: {made} voxels corrected, {made / touched:.2f}x stored")
    per_voxel = s["bytes"] / touched
    print(f"bytes per stored voxel: {per_voxel:.3f} ({s['payload_bytes'] / touched:.1f} "
          f"payload, partly filled bricks included, + {s['index_bytes'] / touched:.3f} index)")


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--exemplar", default=str(REPO / "tests" / "data" / "granite_64.png"))
    parser.add_argument("--skip-cold", action="store_true")
    args = parser.parse_args()
    exemplar_files(parser, Path(), [args.exemplar], "")
    print(run_record(), flush=True)
    candidates = precompute(args.exemplar)
    warm(candidates)
    if not args.skip_cold:
        cold(candidates)


if __name__ == "__main__":
    main()
