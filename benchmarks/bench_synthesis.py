"""Speed and quality of the lazy synthesis engine (issue 4; Dong 2008, sections 5 and 6.3).

Prints: full-volume times (64^3 from a 64^2 exemplar, 128^3 from a 128^2 one), a cold
single voxel, the dependency chain of one voxel, and the worst-axis neighbourhood energy
of the 64^3 volume next to i.i.d. noise and the exemplar stacked along z. Warp kernels
are compiled and candidates pre-computed before anything is timed.

    python benchmarks/bench_synthesis.py [--exemplars DIR] [--repeat 3]
                                         [--jitter-sweep [--shifted-tiles] [--seeds S ...]
                                          [--sheet PNG]
                                          | --passes-sweep
                                          | --memory [--boxes DxHxW ...] [--part-voxels N]
                                          | --request-memory | --contrast
                                          | --cold-kernels [--names NAME ...]]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from timing import best_of, exemplar_files, in_a_process, positive_int, run_record

from warptex import metrics
from warptex.candidates import precompute
from warptex.dependencies import dependency_chain
from warptex.exemplar import Exemplar
from warptex.metrics import worst_axis_energy
from warptex.synthesis import MAX_WORK_VOXELS, Synthesizer

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DIR = ROOT.parent / "shared" / "data" / "exemplars"
# Exemplars of the passes sweep, and of the full volumes with the size of each (the default
# run's): named here, as main checks them before any work.
PASSES_SWEEP = ("granite_64", "rocks_in_sand_64", "bricks_red_64", "wood_rosewood_64")
VOLUMES = (("granite_64", 64), ("rocks_in_sand_64", 64), ("wood_rosewood_128", 128))


def jitter_sweep(folder: Path, names: list[str], jitters: list[float], edge: int,
                 shifted: bool, sheet_path: Path | None, seeds: list[int]) -> None:
    """Jitter varies the tiled slab (section 5.1): its effect on quality and repetition,
    averaged over ``seeds``; with ``shifted`` also with shifted tiles, and with
    ``sheet_path`` a picture of each exemplar's slices at the first jitter and seed."""
    from warptex.metrics import repetition_score
    from warptex.sheets import save_png, sheet

    rows = []
    for name in names:
        ex = Exemplar.load(folder / f"{name}.png")
        cs = precompute(ex)
        for tiles in (False, True) if shifted else (False,):
            cells, shown = [], None
            for jitter in jitters:
                energies, scores = [], []
                for seed in seeds:
                    syn = Synthesizer(cs, seed=seed, jitter=jitter, shifted_tiles=tiles)
                    energies.append(worst_axis_energy(syn.box((0, 0, 0), (48, 48, 48)),
                                                      ex.colors))
                    big = syn.box((0, 0, 20), (edge, edge, 1))[:, :, 0]
                    scores.append(repetition_score(big))
                    shown = big if shown is None else shown  # the sheet's: first jitter, seed
                cells.append(f"jitter {jitter}: energy {np.mean(energies):.3f}, "
                             f"repetition {np.mean(scores):.2f}")
            label = f"{name}, shifted tiles" if tiles else name
            print(f"{label}: " + "; ".join(cells))
            if not tiles:
                rows.append((name.removesuffix("_64"), [("exemplar", ex.colors)]))
            rows[-1][1].append(("shifted tiles" if tiles else "tiled slab", shown))
    if sheet_path is not None:
        save_png(sheet(rows), sheet_path)
        print(f"written: {sheet_path}")


def passes_sweep(folder: Path) -> None:
    """More correction passes per level (section 5.1): quality against time."""
    for name in PASSES_SWEEP:
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


def colour_spread(colors: np.ndarray) -> float:
    """The root-mean-square distance of an image's or volume's colours from their mean
    colour: its contrast, whatever its colour cast (a grey and a brown photo of one
    pattern have the same)."""
    pixels = colors.reshape(-1, colors.shape[-1]).astype(np.float64)
    return float(np.sqrt(pixels.var(axis=0).sum()))


def contrast(folder: Path) -> None:
    """The contrast a 64^3 box keeps of its exemplar (README, "Known limitations"): its
    colour spread over the exemplar's, beside the standard deviation of all values with the
    channels pooled, which counts the differences between the channels' means (a colour
    cast, kept by any volume of the exemplar's colours, a flat one too) as contrast."""
    print("| exemplar | colour spread, box over exemplar | all values' std, box over "
          "exemplar | the same of a flat volume of the mean colour |")
    print("|---|---|---|---|")
    for path in sorted(folder.glob("*_64.png")):
        ex = Exemplar.load(path)
        vol = Synthesizer(precompute(ex), seed=0).box((0, 0, 0), (64, 64, 64))
        flat = np.broadcast_to(ex.colors.reshape(-1, ex.channels).mean(axis=0), vol.shape)
        print(f"| {path.stem.removesuffix('_64')} | "
              f"{colour_spread(vol) / colour_spread(ex.colors):.2f} | "
              f"{vol.std() / ex.colors.std():.2f} | {flat.std() / ex.colors.std():.2f} |",
              flush=True)


# One box in a fresh process: its peak memory growth (RSS) and time, engine set up and
# kernels warm before; argv: exemplar, cap of finest work voxels per call, box shape.
# The peak is the box's own (PeakMemory resets it), not one the pre-computation set before.
_BOX_IN_A_PROCESS = textwrap.dedent("""
    import json, sys, time
    from warptex import synthesis
    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar
    from warptex.machine import PeakMemory
    synthesis.MAX_WORK_VOXELS = int(sys.argv[2])
    syn = synthesis.Synthesizer(precompute(Exemplar.load(sys.argv[1])), seed=1)
    syn.box((0, 0, 0), (8, 8, 8))
    start = time.perf_counter()
    with PeakMemory() as peak:
        syn.box((0, 0, 0), tuple(int(a) for a in sys.argv[3:6]))
    seconds = time.perf_counter() - start
    print(json.dumps({"seconds": seconds, "mib": peak.growth / 2**20}))
""")


MEMORY_BOXES = ((64, 256, 256), (128, 256, 256), (256, 256, 256))

# What the memory estimates of a request count beside a box's work: argv: mode, then
# "features" EXEMPLAR CHANNELS (a 56^3 box from the exemplar's 32 px corner, with random
# feature channels added up to CHANNELS: its peak growth per finest work voxel), or
# "scattered" EXEMPLAR N (N voxels a block apart, the engine's synthesis replaced by zeros:
# the request's own arrays and the dilated keys of its parts, per voxel). Each in a fresh
# process, kernels warm first.
_REQUEST_IN_A_PROCESS = textwrap.dedent("""
    import json, sys
    import numpy as np
    from warptex import synthesis
    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar
    from warptex.machine import PeakMemory, map_large_blocks

    def measured_box(syn, shape):
        with PeakMemory() as peak:
            syn.box((100, 100, 100), shape)
        reach = 2 * syn._apron * synthesis.BLOCK
        work = int(np.prod([-(-a // synthesis.BLOCK) * synthesis.BLOCK + reach for a in shape]))
        return {"mib": peak.growth / 2**20, "per": peak.growth / work, "work": work}

    mode, path, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
    if mode == "steps":  # n passes of sys.argv[4] sub-passes over a box of sys.argv[5]^3
        map_large_blocks()
        cs = precompute(Exemplar.load(path))
        synthesis.Synthesizer(cs, seed=1).box((0, 0, 0), (8, 8, 8))
        syn = synthesis.Synthesizer(cs, seed=1, passes=n, subpasses=int(sys.argv[4]))
        print(json.dumps(measured_box(syn, (int(sys.argv[5]),) * 3)))
        sys.exit()
    colors = Exemplar.load(path).colors[:32, :32]
    if mode == "features":
        noise = np.random.default_rng(0).random((32, 32, n - 3), np.float32)
        colors = np.concatenate([colors, noise], axis=2)
    exemplar = Exemplar(np.ascontiguousarray(colors), name=f"{n} channels")
    syn = synthesis.Synthesizer(precompute(exemplar, cache=False), seed=1)
    syn.box((0, 0, 0), (8, 8, 8))
    if mode == "features":
        print(json.dumps(measured_box(syn, (56, 56, 56))))
        sys.exit()
    syn._synthesize = lambda level, keys, voxel_keys, local, work=None: np.zeros(
        (len(voxel_keys), 3), np.int32)
    rng = np.random.default_rng(0)
    blocks = rng.choice(2**20, n, replace=False)
    ijk = np.stack(np.unravel_index(blocks, (2**7,) * 3), axis=1) * 8 * 64
    ijk -= synthesis.COORD_LIMIT // 2
    with PeakMemory() as peak:
        syn.pixel_triples(ijk)
    print(json.dumps({"mib": peak.growth / 2**20, "per": peak.growth / n}))
""")

# The candidates loaded, then two 64^3 boxes of a fresh engine, in a fresh process whose
# kernel cache is empty; argv: exemplar. The candidates come from the candidate cache,
# filled by the caller: loading them builds the kernels that check them, and the first
# box's time holds the engine's kernel builds and nothing of the pre-computation's.
_COLD_BOXES = textwrap.dedent("""
    import json, sys, time
    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar
    from warptex.synthesis import Synthesizer
    exemplar = Exemplar.load(sys.argv[1])
    start = time.perf_counter()
    cs = precompute(exemplar)
    seconds = [time.perf_counter() - start]
    assert cs.cache_status == "loaded", cs.cache_status
    syn = Synthesizer(cs, seed=1)
    for x in (0, 64):
        start = time.perf_counter()
        syn.box((x, 0, 0), (64, 64, 64))
        seconds.append(time.perf_counter() - start)
    print(json.dumps(seconds))
""")


def cold_kernels(folder: Path, names: list[str]) -> None:
    """The first use on a machine: the cached candidates loaded, then two 64^3 boxes of a
    fresh engine, the load and the first box building Warp's kernels (an empty
    WARP_CACHE_PATH of its own), the second not."""
    import os
    import tempfile

    print("| exemplar | cached candidates loaded, kernels built inside | first 64^3 box, "
          "kernels built inside | second box |")
    print("|---|---|---|---|")
    for name in names:
        exemplar = str(folder / f"{name}.png")
        precompute(Exemplar.load(exemplar))  # into the candidate cache the process reads
        with tempfile.TemporaryDirectory() as kernels:
            load, first, second = in_a_process(["-c", _COLD_BOXES, exemplar], name,
                                               env={**os.environ, "WARP_CACHE_PATH": kernels})
        print(f"| {name} | {load:.1f} s | {first:.1f} s | {second:.2f} s |")


def memory(folder: Path, boxes: list[tuple[int, int, int]], part_cap: int) -> None:
    """Requests beyond one engine call are synthesized in parts (MAX_WORK_VOXELS): the peak
    memory and time of boxes in parts and in one call, each in a fresh process."""
    exemplar = str(folder / "granite_64.png")
    print("| box | finest work voxels per call | peak memory growth MiB | seconds |")
    print("|---|---|---|---|")
    for shape in boxes:
        for cap in (part_cap, 1 << 40):
            r = in_a_process(["-c", _BOX_IN_A_PROCESS, exemplar, str(cap), *map(str, shape)],
                             f"the box {shape}")
            label = f"at most {cap}" if cap == part_cap else "one call"
            print(f"| {' x '.join(map(str, shape))} | {label} | {r['mib']:.0f} | "
                  f"{r['seconds']:.1f} |")


def request_memory(folder: Path) -> None:
    """The terms of the engine's memory estimates that vary with the request: working
    memory per finest work voxel against feature channels and against correction steps
    (passes times sub-passes), and the memory of scattered voxels per voxel beside the
    engine's work (``synthesis.work_bytes_per_voxel``, ``REQUEST_BYTES_PER_VOXEL``,
    ``DILATED_KEY_BYTES``)."""
    from warptex.dependencies import default_apron_blocks
    from warptex.synthesis import DILATED_KEY_BYTES, REQUEST_BYTES_PER_VOXEL, work_bytes_per_voxel

    exemplar = str(folder / "granite_64.png")

    def run(*argv: str) -> dict:
        done = subprocess.run([sys.executable, "-c", _REQUEST_IN_A_PROCESS, *argv],
                              capture_output=True, text=True)
        if done.returncode:
            sys.exit(f"{' '.join(argv)} failed in its process:\n{done.stderr}")
        return json.loads(done.stdout.strip().splitlines()[-1])

    print("| feature channels | 56^3 box: peak growth MiB | bytes a finest work voxel "
          "| estimate |")
    print("|---|---|---|---|")
    for channels in (3, 12, 34):
        r = run("features", exemplar, str(channels))
        print(f"| {channels} | {r['mib']:.0f} | {r['per']:.0f} | "
              f"{work_bytes_per_voxel(channels)} |")
    print("\n| passes x sub-passes (correction steps) | box | finest work voxels | peak growth "
          "MiB | bytes a work voxel | estimate |")
    print("|---|---|---|---|---|---|")
    for passes, subpasses, edge in ((2, 1, 56), (8, 1, 32), (2, 8, 32), (4, 8, 16), (8, 8, 8)):
        r = run("steps", exemplar, str(passes), str(subpasses), str(edge))
        steps = passes * subpasses
        print(f"| {passes} x {subpasses} ({steps}) | {edge}^3 | {r['work']} | {r['mib']:.0f} | "
              f"{r['per']:.0f} | {work_bytes_per_voxel(3, steps)} |")
    dilated = (2 * default_apron_blocks(2) + 1) ** 3 * DILATED_KEY_BYTES
    print("\n| scattered voxels (a block apart) | peak growth MiB, synthesis left out "
          "| bytes a voxel | estimate |")
    print("|---|---|---|---|")
    for n in (200_000, 1_000_000):
        r = run("scattered", exemplar, str(n))
        print(f"| {n} | {r['mib']:.0f} | {r['per']:.0f} | "
              f"{REQUEST_BYTES_PER_VOXEL + dilated} |")


def _box(text: str) -> tuple[int, int, int]:
    try:
        box = tuple(int(a) for a in text.lower().split("x"))
    except ValueError:
        box = ()
    if len(box) != 3 or min(box) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected DxHxW, three positive integers")
    return box


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--exemplars", type=Path, default=DEFAULT_DIR)
    parser.add_argument("--repeat", type=positive_int, default=3)
    parser.add_argument("--jitter-sweep", action="store_true",
                        help="only print energy (48^3) and repetition (a slice) against the "
                        "jitter strength")
    parser.add_argument("--names", nargs="+", default=["granite_64", "bricks_red_64",
                                                       "rocks_in_sand_64", "dry_mud_64"],
                        help="exemplars of the jitter sweep and of --cold-kernels (file names "
                        "without .png)")
    parser.add_argument("--jitters", type=float, nargs="+", default=[0.0, 0.25, 0.5, 1.0, 2.0],
                        help="jitter strengths of the jitter sweep")
    parser.add_argument("--slice", type=int, default=160,
                        help="edge of the jitter sweep's repetition slice (default 160; "
                        "warptex compare uses 256)")
    parser.add_argument("--shifted-tiles", action="store_true",
                        help="the jitter sweep also with shifted tiles, as warptex's "
                        "--shifted-tiles")
    parser.add_argument("--seeds", type=int, nargs="+", default=[3],
                        help="seeds the jitter sweep averages over (default 3)")
    parser.add_argument("--sheet", type=Path, metavar="PNG",
                        help="the jitter sweep also writes its slices at the first jitter and "
                        "seed")
    parser.add_argument("--passes-sweep", action="store_true",
                        help="only print energy and time of 64^3 against correction passes")
    parser.add_argument("--memory", action="store_true",
                        help="only print the peak memory and time of large boxes, in parts "
                        "and in one engine call")
    parser.add_argument("--request-memory", action="store_true",
                        help="only print the engine's memory per work voxel against feature "
                        "channels, and that of scattered voxels beside the engine's work")
    parser.add_argument("--contrast", action="store_true",
                        help="the contrast a 64^3 box keeps of each 64 px exemplar in "
                             "--exemplars")
    parser.add_argument("--cold-kernels", action="store_true",
                        help="only print the first and second 64^3 box of a fresh engine on "
                        "an empty kernel cache, for each of --names")
    parser.add_argument("--boxes", type=_box, nargs="+", default=list(MEMORY_BOXES),
                        metavar="DxHxW", help="the boxes of --memory (default "
                        + " ".join("x".join(map(str, b)) for b in MEMORY_BOXES) + ")")
    parser.add_argument("--part-voxels", type=int, default=MAX_WORK_VOXELS, metavar="N",
                        help="--memory's cap of finest work voxels per engine call (default "
                        f"warptex's, {MAX_WORK_VOXELS}; a small one splits small boxes)")
    args = parser.parse_args()
    _, needed, run = next(mode for mode in _modes(args) if mode[0])
    exemplar_files(parser, args.exemplars, needed, "_64.png" if needed is None else ".png")
    print(run_record(), flush=True)
    run()


def _modes(args: argparse.Namespace) -> list[tuple[bool, list[str] | None, Callable[[], None]]]:
    """The benchmark's modes, in the order that picks the first one asked: whether it is
    asked, the exemplars it reads (None: every *_64.png of the folder) and what it runs."""
    return [
        (args.memory, ["granite_64"],
         lambda: memory(args.exemplars, args.boxes, args.part_voxels)),
        (args.cold_kernels, args.names, lambda: cold_kernels(args.exemplars, args.names)),
        (args.contrast, None, lambda: contrast(args.exemplars)),
        (args.request_memory, ["granite_64"], lambda: request_memory(args.exemplars)),
        (args.jitter_sweep, args.names,
         lambda: jitter_sweep(args.exemplars, args.names, args.jitters, args.slice,
                              args.shifted_tiles, args.sheet, args.seeds)),
        (args.passes_sweep, list(PASSES_SWEEP), lambda: passes_sweep(args.exemplars)),
        # granite_64 is among the volumes, for the single voxels
        (True, [name for name, _ in VOLUMES], lambda: volumes(args.exemplars, args.repeat)),
    ]


def volumes(exemplars: Path, repeat: int) -> None:
    """The default mode: the dependency chain, 64^3 and 128^3 volumes at 1 and 8 sub-passes,
    and single voxels of fresh engines."""
    for subpasses in (1, 8):
        chain = dependency_chain(2, 2, subpasses, 3)
        print(f"dependency chain of one voxel (N=5, 2 passes, {subpasses} sub-passes, 3 levels): "
              f"{chain} finest first, total {sum(chain)} (paper: 6778)")

    # 8 sub-passes take about 10x as long, so they run once: the runs column says so.
    print("\n| exemplar | volume | sub-passes | runs | seconds (best of the runs) "
          "| voxels synthesized | worst-axis energy | noise | stacked |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, size in VOLUMES:
        ex = Exemplar.load(exemplars / f"{name}.png")
        cs = precompute(ex)
        Synthesizer(cs).box((0, 0, 0), (4, 4, 4))  # compile kernels
        for subpasses in (1, 8) if size == 64 else (1,):
            holder = {}

            def run(cs=cs, subpasses=subpasses, holder=holder, size=size) -> None:
                syn = Synthesizer(cs, seed=1, subpasses=subpasses)
                holder["vol"] = syn.box((0, 0, 0), (size,) * 3)
                holder["count"] = sum(syn.voxels_synthesized.values())

            runs = repeat if subpasses == 1 else 1
            seconds = best_of(run, runs)
            vol = holder["vol"]
            sub = vol[:64, :64, :64]
            stacked = metrics.extrusion(ex.colors[:64, :64], 64, axis=2)
            noise = metrics.iid_noise(ex.colors, (64, 64, 64))
            print(f"| {name} | {size}^3 | {subpasses} | {runs} | {seconds:.2f} | "
                  f"{holder['count']} | "
                  + " | ".join(f"{worst_axis_energy(v, ex.colors):.3f}"
                               for v in (sub, noise, stacked)) + " |")

    cs = precompute(Exemplar.load(exemplars / "granite_64.png"))
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
