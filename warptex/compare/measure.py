"""One method of a comparison measured in a process of its own, so that its time and peak
memory are its own, and :func:`compare`, which measures each in turn: its volume, its scores
(:mod:`warptex.metrics`), time and memory, with the phase it is in on the progress bar."""

from __future__ import annotations

import contextlib
import functools
import multiprocessing
import multiprocessing.queues
import pickle
import queue
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from tqdm import std
from tqdm.auto import tqdm

from warptex import metrics
from warptex.compare.methods import (
    _KOPF,
    _LAZY,
    _RUN,
    METHODS,
    _candidates,
    _cube_texture,
    _engine_device,
    _Job,
    _middle,
    check_methods,
    render_cube,
)
from warptex.compare.setup import Comparison, MethodResult, Setup
from warptex.exemplar import AlphaDropped, Exemplar, ExemplarError
from warptex.machine import PeakMemory, map_large_blocks
from warptex.parallel import in_child_process
from warptex.settings import check_count, check_flag
from warptex.thread_warnings import captured


def _check_unchanged(setup: Setup) -> None:
    """An ExemplarError naming the file unless each exemplar file still holds the image
    ``setup`` read: the lazy cube's plugin reads the files again, and would otherwise show
    an image the scores never saw."""
    for path, e in dict(zip(setup.paths(), setup.exemplars(), strict=True)).items():
        with captured():  # said when first read
            now = Exemplar.load(path, **setup.load_options())
        if now.digest() != e.digest():  # of the features too: a changed mask shows here
            raise ExemplarError(f"{path}: changed while the comparison ran; run it again")


def _precomputed(job: _Job) -> tuple[_Job, float]:
    """The job with the candidates of its exemplars computed afresh, and the seconds that
    took, its kernels compiled first on a small exemplar of as many channels."""
    from warptex.candidate_set import resolved_params
    from warptex.candidates import cache_path, precompute

    channels = job.axes[0].colors.shape[2]
    warm = np.random.default_rng(0).random((16, 16, channels), dtype=np.float32)
    precompute(Exemplar(warm), cache=False)
    start = time.perf_counter()
    candidates = precompute(*job.axes, tileable=job.setup.tileable, cache=False)
    seconds = time.perf_counter() - start
    # Cached as the lazy cube's plugin would cache them, which then reads them rather than
    # compute them again (minutes for a large exemplar); a cache that cannot be written
    # leaves the plugin to compute them as before.
    path = cache_path(list(job.axes), resolved_params({"tileable": job.setup.tileable}))
    if not path.exists():
        with contextlib.suppress(OSError):
            candidates.save(path)
    return replace(job, candidates=candidates), seconds


def _device_peak_mib(device: str) -> float | None:
    """High-water mark of Warp's memory pool on ``device`` in this process, in MiB; None on
    the CPU or where the device has no memory pool."""
    if not device.startswith("cuda"):
        return None
    import warp as wp

    try:
        return wp.get_mempool_used_mem_high(device) / 2**20
    except (ValueError, RuntimeError):
        return None


def _measure(method: str, s: Setup, repeats: int = 1) -> dict:
    """Run one method in this (fresh) process: volume, scores, time (of ``repeats`` runs)
    and peak memory."""
    job = _Job(s, s.exemplars())
    axes, size = job.axes, s.size
    make_volume, make_large = _RUN[method]
    precompute_seconds = None
    if method == "lazy":
        _phase("pre-computing candidates")
        job, precompute_seconds = _precomputed(job)
    elif method in _LAZY:  # the same candidates, from the cache where a lazy run left them
        _phase("candidates, from the cache where they are")
        job = replace(job, candidates=_candidates(job))
    # Compile or load the Warp kernels outside the timing (cheap for the numpy methods).
    make_volume(job, 8)
    _phase(f"{size}^3, timed")
    runs = []
    with PeakMemory() as memory:
        for _ in range(repeats):
            volume = None  # not held while the next run makes its own: each run's peak
            start = time.perf_counter()
            volume = make_volume(job, size)
            runs.append(time.perf_counter() - start)
    device = _engine_device() if method in _LAZY else "cpu"
    device_peak = _device_peak_mib(device)
    _phase("its large slice, for the repetition score")
    large = make_large(job, volume)
    _phase("rendering its cube")
    render = render_cube(_cube_texture(method, job, volume))
    if method == "lazy":
        _check_unchanged(s)

    def per_axis(name: str, measure: Callable[[int], float]) -> list[float]:
        # Each axis' slices against its own Exemplar, whose seams are decided once.
        _phase(f"measuring {name}")
        return [measure(a) for a in range(3)]

    scores = {
        "energy": per_axis("energy", lambda a: metrics.neighborhood_energy(
            volume, axes[a], a, tileable=s.tileable)),
        "completeness": per_axis("completeness", lambda a: metrics.completeness_energy(
            volume, axes[a], a, tileable=s.tileable)),
        "swd": per_axis("sliced Wasserstein", lambda a: metrics.sliced_wasserstein(
            volume, axes[a], a, tileable=s.tileable)),
        "histogram": per_axis("histograms", lambda a: metrics.histogram_distance(
            volume, axes[a], a)),
    }
    _phase("measuring repetition")
    return {
        "method": method,
        **scores,
        "repetition": metrics.repetition_score(large),
        "seconds": float(np.median(runs)),
        "seconds_runs": runs,
        "peak_mib": memory.growth / 2**20,
        "slices": [metrics.axis_slice(volume, a, _middle(size)) for a in range(3)],
        "render": render,
        "notes": f"correction passes per level: {s.passes}" if method in _LAZY else "",
        "device": device,
        "precompute_seconds": precompute_seconds,
        "device_peak_mib": device_peak,
    }


def compare(setup: Setup, methods: Sequence[str] = METHODS, *, progress: bool = True,
            repeats: int = 1) -> Comparison:
    """Score every method of ``methods`` on the exemplars of ``setup``, each in a fresh
    process (started by ``spawn``: a script calling this needs an ``if __name__ ==
    "__main__":`` guard), with the median of ``repeats`` timed runs as its seconds. A bad
    exemplar is refused before any method runs."""
    if not isinstance(setup, Setup):
        raise TypeError(f"setup must be a warptex.compare.Setup, got {setup!r}")
    methods = check_methods(methods)
    check_count("repeats", repeats, low=1)
    check_flag("progress", progress)
    axes = setup.exemplars()
    if any(m in _LAZY for m in methods):  # before any method's minutes of work
        from warptex.candidate_set import check_feature_channels
        from warptex.store import check_lookup_channels

        try:
            check_feature_channels(axes[0].features.shape[2])
            if "lazy" in methods:  # its cube is rendered through the plugin's lookups
                check_lookup_channels(axes[0].channels)
        except ValueError as error:
            raise ValueError(f"{setup.paths()[0]}: {error}") from None
    if any(m in _KOPF for m in methods):
        from warptex.baselines.kopf import check_channels, check_size

        check_size(setup.size)
        check_channels(axes)
    results = []
    ctx = multiprocessing.get_context("spawn")  # in_child_process's, for the phases' queue
    bar = tqdm(methods, desc="methods", disable=not progress)
    for method in bar:
        bar.set_postfix_str(method)  # one method can take minutes: the bar says which
        phases = ctx.Queue()  # and what it is doing: candidates alone can take a minute
        show = functools.partial(_show_phases, bar, method, phases)
        out = in_child_process(_measure_in_child, method, setup, repeats,
                               initializer=_start_worker,
                               initargs=(_shown_as_here(), phases), while_waiting=show)
        show()
        results.append(MethodResult(**out))
    return Comparison(setup, results)


_phases: multiprocessing.queues.Queue | None = None  # where a method's process says it


def _measure_in_child(method: str, s: Setup, repeats: int) -> dict:
    """:func:`_measure` in a method's process, which says on the bar when it first has Warp
    build the kernels (the command's own note would be drawn over by the bar)."""
    from warptex.warp_runtime import kernel_build_notice

    def building(cache: object) -> None:  # before the phase it interrupts, which goes on
        then = f", then {_said}" if _said else ""
        _phase(f"Warp builds the kernels (once a version){then}")

    with kernel_build_notice(building):
        return _measure(method, s, repeats)


def _phase(text: str) -> None:
    """Say, on the bar of the process that runs the comparison, what this method's process
    does now; nothing where it is not one (a test measuring in its own process)."""
    global _said
    _said = text
    if _phases is not None:
        _phases.put(text)


_said = ""  # what this method's process said last, which a kernel build interrupts


def _show_phases(bar: tqdm, method: str, phases: multiprocessing.queues.Queue) -> None:
    """Show on ``bar`` each phase the method's process said since last looked."""
    with contextlib.suppress(queue.Empty, OSError, ValueError):
        while True:
            bar.set_postfix_str(f"{method}: {phases.get_nowait()}")


def _start_worker(show_warning: Callable | None,
                  phases: multiprocessing.queues.Queue | None = None) -> None:
    """A method's process: large blocks mapped afresh, for its peak memory; progress bars
    locked between threads only, for tqdm's default lock between processes is a semaphore
    that a worker stopped by :func:`~warptex.parallel.stop_workers` leaves to a warning at
    exit. Warnings are shown as the caller's process shows them (the command's one line),
    but for a dropped alpha, which :meth:`Setup.exemplars` reported already in compare's
    words."""
    map_large_blocks()
    std.tqdm.set_lock(threading.RLock())  # every kind of bar's
    if show_warning is not None:
        warnings.showwarning = show_warning
    warnings.simplefilter("ignore", AlphaDropped)
    global _phases
    _phases = phases


def _shown_as_here() -> Callable | None:
    """How this process shows warnings, where a worker can be given it (a function of a
    module, not one made in a notebook)."""
    try:
        pickle.dumps(warnings.showwarning)
    except (pickle.PicklingError, AttributeError, TypeError):
        return None
    return warnings.showwarning
