"""Speed and quality of the lazy synthesis engine (issue 4; Dong 2008, sections 5 and 6.3).

Prints: full-volume times (64^3 from a 64^2 exemplar, 128^3 from a 128^2 one), a cold
single voxel, the dependency chain of one voxel, and the worst-axis neighbourhood energy
of the 64^3 volume next to i.i.d. noise and the exemplar stacked along z. Warp kernels
are compiled and candidates pre-computed before anything is timed.

    python benchmarks/bench_synthesis.py [--exemplars DIR] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from timing import best_of

from warptex import metrics
from warptex.candidates import precompute
from warptex.exemplar import Exemplar
from warptex.metrics import worst_axis_energy
from warptex.synthesis import Synthesizer, dependency_chain

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DIR = ROOT.parent / "shared" / "data" / "exemplars"


def jitter_sweep(folder: Path) -> None:
    """Jitter varies the tiled slab (section 5.1): its effect on quality and repetition."""
    from warptex.metrics import repetition_score

    for name in ("granite_64", "bricks_red_64", "rocks_in_sand_64", "dry_mud_64"):
        ex = Exemplar.load(folder / f"{name}.png")
        cs = precompute(ex)
        cells = []
        for jitter in (0.0, 0.25, 0.5, 1.0, 2.0):
            vol = Synthesizer(cs, seed=3, jitter=jitter).box((0, 0, 0), (48, 48, 48))
            big = Synthesizer(cs, seed=3, jitter=jitter).box((0, 0, 20), (160, 160, 1))
            cells.append(f"jitter {jitter}: energy {worst_axis_energy(vol, ex.colors):.3f}, "
                         f"repetition {repetition_score(big[:, :, 0]):.2f}")
        print(f"{name}: " + "; ".join(cells))


def passes_sweep(folder: Path) -> None:
    """More correction passes per level (section 5.1): quality against time."""
    for name in ("granite_64", "rocks_in_sand_64", "bricks_red_64", "wood_rosewood_64"):
        ex = Exemplar.load(folder / f"{name}.png")
        cs = precompute(ex)
        Synthesizer(cs).box((0, 0, 0), (4, 4, 4))  # compile kernels
        cells = []
        for passes in (2, 3, 4):
            start = time.perf_counter()
            vol = Synthesizer(cs, seed=3, passes=passes).box((0, 0, 0), (64, 64, 64))
            seconds = time.perf_counter() - start
            cells.append(f"{passes} passes: energy {worst_axis_energy(vol, ex.colors):.3f}, "
                         f"{seconds:.2f} s")
        print(f"{name}: " + "; ".join(cells))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--exemplars", type=Path, default=DEFAULT_DIR)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--jitter-sweep", action="store_true",
                        help="only print energy and repetition against the jitter strength")
    parser.add_argument("--passes-sweep", action="store_true",
                        help="only print energy and time of 64^3 against correction passes")
    args = parser.parse_args()
    if args.jitter_sweep:
        jitter_sweep(args.exemplars)
        return
    if args.passes_sweep:
        passes_sweep(args.exemplars)
        return

    for subpasses in (1, 8):
        chain = dependency_chain(2, 2, subpasses, 3)
        print(f"dependency chain of one voxel (N=5, 2 passes, {subpasses} sub-passes, 3 levels): "
              f"{chain} finest first, total {sum(chain)} (paper: 6778)")

    print("\n| exemplar | volume | sub-passes | seconds (best of "
          f"{args.repeat}) | voxels synthesized | worst-axis energy | noise | stacked |")
    print("|---|---|---|---|---|---|---|---|")
    for name, size in [("granite_64", 64), ("rocks_in_sand_64", 64), ("wood_rosewood_128", 128)]:
        ex = Exemplar.load(args.exemplars / f"{name}.png")
        cs = precompute(ex)
        Synthesizer(cs).box((0, 0, 0), (4, 4, 4))  # compile kernels
        for subpasses in (1, 8) if size == 64 else (1,):
            holder = {}

            def run(cs=cs, subpasses=subpasses, holder=holder, size=size) -> None:
                syn = Synthesizer(cs, seed=1, subpasses=subpasses)
                holder["vol"] = syn.box((0, 0, 0), (size,) * 3)
                holder["count"] = sum(syn.voxels_synthesized.values())

            seconds = best_of(run, args.repeat if subpasses == 1 else 1)
            vol = holder["vol"]
            sub = vol[:64, :64, :64]
            stacked = metrics.extrusion(ex.colors[:64, :64], 64, axis=2)
            noise = metrics.iid_noise(ex.colors, (64, 64, 64))
            print(f"| {name} | {size}^3 | {subpasses} | {seconds:.2f} | {holder['count']} | "
                  + " | ".join(f"{worst_axis_energy(v, ex.colors):.3f}"
                               for v in (sub, noise, stacked)) + " |")

    cs = precompute(Exemplar.load(args.exemplars / "granite_64.png"))
    singles = []
    for i in range(5):
        syn = Synthesizer(cs, seed=100 + i)  # a fresh engine: no coarse level is cached
        start = time.perf_counter()
        syn.voxels(np.array([[1000 * i, -37, 512]]))
        singles.append(time.perf_counter() - start)
    print(f"\ncold single voxel: median {1000 * np.median(singles):.1f} ms "
          f"(min {1000 * min(singles):.1f}, max {1000 * max(singles):.1f}) over 5 fresh engines")


if __name__ == "__main__":
    main()
