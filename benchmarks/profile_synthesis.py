"""Where the lazy engine's time goes for a box (Dong 2008, section 5): host or device.

For each exemplar and box size, fresh engines synthesize the box: once plainly (the wall
time the other benchmarks report); five times with the time inside the engine's kernel
launches taken out (the host's bookkeeping, on the CPU); and once under cProfile, whose
per-function time is summed by where it is spent:

- Warp: launches, copies between host and device, and waiting for them. On the CPU a
  launch's kernel runs inside it (or in the worker threads it waits for); on a GPU
  launches return at once and the kernels' time shows where the host waits for a result.
- NumPy and SciPy: the host's bookkeeping of keys, dependency lists and gathers.
- warptex: the engine's own Python lines, NumPy's operators (``a // b``, ``a[idx]``)
  among them, which cProfile does not count apart.

On a CUDA device, the profiled run also records the device's activity
(``wp.timing_begin``): the time of each kernel and copy, summed by name; and the box is
timed again (a median of fresh engines) with the memory pool giving its free memory back
at every synchronization, as CUDA's default does.
Kernels are compiled and candidates pre-computed before anything is timed.

    python benchmarks/profile_synthesis.py [--exemplars DIR] [--names granite_64 ...]
                                           [--sizes 64 128] [--device cuda:0]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import statistics
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from unittest import mock

import warp as wp
from timing import exemplar_files, positive_int, run_record, timed_runs

import warptex.synthesis
from warptex.candidates import precompute
from warptex.exemplar import Exemplar
from warptex.synthesis import Synthesizer

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DIR = ROOT.parent / "shared" / "data" / "exemplars"
TOP = 12  # host functions and device activities listed per box
OUTSIDE_RUNS = 5  # fresh engines whose time outside the launches is measured


def place(filename: str, function: str) -> str:
    """Which part of the stack a cProfile entry belongs to."""
    if "/warp/" in filename or "_thread.lock" in function:
        return "Warp"
    if any(f"/{lib}/" in filename for lib in ("numpy", "scipy")) or "numpy" in function:
        return "NumPy and SciPy"
    if "/warptex/" in filename or "/kernels/" in filename:
        return "warptex"
    return "other Python"


def host_profile(profile: cProfile.Profile) -> tuple[dict[str, float], list[tuple[float, str]]]:
    """Seconds spent in each part, and the most expensive functions by own time."""
    stats = pstats.Stats(profile).stats
    parts: dict[str, float] = defaultdict(float)
    functions = []
    for (filename, line, function), (_, _, own, _, _) in stats.items():
        parts[place(filename, function)] += own
        where = f"{Path(filename).name}:{line}" if filename != "~" else "builtin"
        functions.append((own, f"{function} ({where})"))
    return dict(parts), sorted(functions, reverse=True)[:TOP]


def device_activity(results: list) -> list[tuple[float, int, str]]:
    """Milliseconds and count of each CUDA activity (kernel, copy, memset), largest first."""
    total: dict[str, list[float]] = defaultdict(list)
    for r in results:
        total[r.name].append(r.elapsed)
    return sorted(((sum(v), len(v), k) for k, v in total.items()), reverse=True)


def released_pool_seconds(candidates, size: int, device: str) -> float:
    """Median seconds of the box from ``OUTSIDE_RUNS`` fresh engines with the device's
    memory pool at CUDA's release threshold of 0, which ``warp_runtime.init_warp`` raises."""

    def fresh() -> Synthesizer:
        wp.synchronize_device(device)  # gives back what the pool held
        return Synthesizer(candidates, device=device)

    kept = wp.get_mempool_release_threshold(device)
    wp.set_mempool_release_threshold(device, 0)
    try:
        return statistics.median(timed_runs(box_of(size), OUTSIDE_RUNS, fresh))
    finally:
        wp.set_mempool_release_threshold(device, kept)


def outside_launches_seconds(candidates, size: int, device: str) -> tuple[float, float]:
    """Median wall time of the box from a fresh engine, and the median part of it spent
    outside the engine's kernel launches (``launch_ranges``), without cProfile's overhead.
    On the CPU that part is the host's bookkeeping; on a GPU, where launches return at
    once, it includes waiting for the results the host reads back."""
    real = warptex.synthesis.launch_ranges
    inside: list[float] = []  # seconds in launches, per run

    def timed(*args, **kwargs) -> None:
        start = time.perf_counter()
        try:
            real(*args, **kwargs)
        finally:
            inside[-1] += time.perf_counter() - start

    def fresh() -> Synthesizer:
        inside.append(0.0)
        return Synthesizer(candidates, device=device)

    with mock.patch.object(warptex.synthesis, "launch_ranges", timed):
        walls = timed_runs(box_of(size), OUTSIDE_RUNS, fresh)
    outside = [wall - launches for wall, launches in zip(walls, inside, strict=True)]
    return statistics.median(walls), statistics.median(outside)


def box_of(size: int) -> Callable[[Synthesizer], object]:
    """What synthesizes the ``size``^3 box at the origin with the engine it is given."""
    return lambda engine: engine.box((0, 0, 0), (size,) * 3)


def profile_box(candidates, size: int, device: str) -> None:
    [wall] = timed_runs(box_of(size), 1, lambda: Synthesizer(candidates, device=device))

    wall_median, outside = outside_launches_seconds(candidates, size, device)
    print(f"\n{size}^3 on {device}: median of {OUTSIDE_RUNS} fresh engines {wall_median:.3f} s, "
          f"of which {outside * 1000:.1f} ms outside the kernel launches")
    cuda = wp.get_device(device).is_cuda
    if cuda and wp.is_mempool_enabled(device):
        # Both medians of warm runs: the pool kept has held a box's memory by then.
        print(f"\n{size}^3 on {device}: {wall_median:.3f} s with the memory pool warptex keeps, "
              f"{released_pool_seconds(candidates, size, device):.3f} s with CUDA's default "
              "(free memory released at every synchronization), medians of "
              f"{OUTSIDE_RUNS} fresh engines")

    engine = Synthesizer(candidates, device=device)
    if cuda:
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    profile = cProfile.Profile()
    start = time.perf_counter()
    profile.enable()
    engine.box((0, 0, 0), (size,) * 3)
    profile.disable()
    profiled = time.perf_counter() - start
    activity = device_activity(wp.timing_end()) if cuda else []

    parts, functions = host_profile(profile)
    print(f"\n### {size}^3 on {device}: {wall:.3f} s plainly, {profiled:.3f} s profiled")
    print("\n| part | seconds | share |\n|---|---|---|")
    for name, seconds in sorted(parts.items(), key=lambda kv: -kv[1]):
        print(f"| {name} | {seconds:.3f} | {seconds / profiled:.0%} |")
    print("\n| host function | own seconds |\n|---|---|")
    for seconds, name in functions:
        print(f"| `{name}` | {seconds:.4f} |")
    if cuda:
        kernels = sum(ms for ms, _, name in activity if not name.startswith(("memcpy", "memset")))
        print(f"\ndevice activity: {sum(ms for ms, _, _ in activity):.1f} ms in all, "
              f"kernels {kernels:.1f} ms")
        print("\n| device activity | ms | count |\n|---|---|---|")
        for ms, count, name in activity[:TOP]:
            print(f"| `{name}` | {ms:.2f} | {count} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--exemplars", type=Path, default=DEFAULT_DIR)
    parser.add_argument("--names", nargs="+", default=["granite_64"])
    parser.add_argument("--sizes", nargs="+", type=positive_int, default=[64, 128])
    parser.add_argument("--device", default=None,
                        help="Warp device (default: a GPU when there is one, else the CPU)")
    args = parser.parse_args()
    exemplar_files(parser, args.exemplars, args.names)
    print(run_record(), flush=True)
    device = str(wp.get_device(args.device)) if args.device else None

    for name in args.names:
        candidates = precompute(Exemplar.load(args.exemplars / f"{name}.png"), progress=False)
        engine = Synthesizer(candidates, device=device)
        engine.box((0, 0, 0), (4, 4, 4))  # compile kernels
        print(f"\n## {name}")
        for size in args.sizes:
            profile_box(candidates, size, engine.device)


if __name__ == "__main__":
    main()
