"""Using several CPU cores (up to 8) with Warp, which runs one CPU launch on one thread.

Kernels written for this take the index of their first item as their first argument, so a
launch over items [start, stop) can be cut into contiguous ranges launched from several
threads. Items of such kernels are independent, so the result equals one launch. One long
call into C code that would keep Ctrl-C and SIGTERM waiting runs in a process of its own
(:func:`in_child_process`).
"""

from __future__ import annotations

import contextlib
import functools
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor, wait
from itertools import pairwise
from typing import Any

import numpy as np
import warp as wp
from scipy.spatial import cKDTree

from warptex.float_env import ieee_arithmetic
from warptex.machine import usable_cores
from warptex.stops import blocked, deferred_stops
from warptex.warp_runtime import launch

THREADS = min(usable_cores(), 8)
# A nearest-neighbour query holds Ctrl-C and SIGTERM back until it ends: it runs in parts
# of about this many seconds, the first of so many rows.
QUERY_SECONDS = 0.5
_FIRST_QUERY_ROWS = 256
MIN_SPLIT = 4096  # fewer items than this run as one launch: threads would cost more
WAIT_SECONDS = 0.5  # how often in_child_process calls its while_waiting


@functools.cache
def _pool() -> ThreadPoolExecutor:
    """The CPU launches' threads, kept for the process: starting threads for each of many
    small launches costs more than the launches themselves. All start here, each held at
    a barrier so that the next submission needs a thread of its own, with Ctrl-C and
    SIGTERM held back: one inside ``Thread.start`` left a running thread the pool had not
    recorded, which the interpreter's exit then waited for for ever."""
    pool = ThreadPoolExecutor(THREADS, thread_name_prefix="warptex")
    everyone = threading.Barrier(THREADS + 1)
    with deferred_stops():
        try:
            for _ in range(THREADS):
                pool.submit(everyone.wait)
            everyone.wait()
        except BaseException:  # a thread that could not start: the others let go
            everyone.abort()
            raise
    return pool


# A forked child (multiprocessing's default on Linux) inherits the pool without its
# threads: its launches waited for ever. It makes a pool of its own.
os.register_at_fork(after_in_child=_pool.cache_clear)


def launch_ranges(
    kernel: wp.Kernel,
    start: int,
    stop: int,
    inputs: list,
    outputs: list | None = None,
    *,
    device: str = "cpu",
    per_item: int = 1,
    min_items: int = MIN_SPLIT,
) -> None:
    """Launch ``kernel(first, *inputs, *outputs)`` over items ``start..stop``, each item
    ``per_item`` threads of the launch; split over CPU threads when there are at least
    ``min_items`` items (fewer for kernels whose items are long)."""
    outputs = outputs or []
    n = stop - start
    if n <= 0:
        return
    if device != "cpu" or THREADS == 1 or n < max(2, min_items):
        launch(kernel, n * per_item, [start, *inputs], outputs, device=device)
        return
    # Warp creates a generic kernel's overload and (re)builds its module on first launch,
    # not thread-safely: the overload is made here and the first item launched from this
    # thread, which builds the module as every launch will use it (a CPU launch's block_dim
    # is 1, and ``Module.load`` without one would build another variant), then the threads
    # launch the rest.
    if kernel.is_generic:
        kernel = kernel._add_normalized_overload(
            kernel.infer_argument_types([start, *inputs, *outputs])
        )
    launch(kernel, per_item, [start, *inputs], outputs, device=device)
    bounds = [start + 1 + (n - 1) * i // THREADS for i in range(THREADS + 1)]
    jobs = [
        _pool().submit(launch, kernel, (hi - lo) * per_item, [lo, *inputs], outputs,
                       device=device)
        for lo, hi in pairwise(bounds)
    ]
    try:
        for job in jobs:
            job.result()
    except BaseException:
        # Ctrl-C, or one range's error, while the other ranges run: they read and write
        # arrays that the caller may free or change as the exception goes on (a brick store
        # empties itself), so they are waited for; a launch's range ends soon.
        for job in jobs:
            job.cancel()
        while not all(job.done() for job in jobs):
            with contextlib.suppress(KeyboardInterrupt):
                wait(jobs)
        raise


def kd_tree(data: np.ndarray, **options: Any) -> cKDTree:
    """``cKDTree(data, **options)`` built in IEEE arithmetic: under a caller's
    denormals-are-zero mode (Mitsuba's threads) SciPy's median splits recursed without end
    on some data (:mod:`warptex.float_env`)."""
    with ieee_arithmetic():
        return cKDTree(data, **options)


def nearest(tree: cKDTree, queries: np.ndarray, workers: int | None = None,
            **options: Any) -> tuple[np.ndarray, np.ndarray]:
    """``tree.query(queries, workers=workers or THREADS, **options)``, in parts of rows of
    about ``QUERY_SECONDS`` each, each run to its end when Ctrl-C or SIGTERM comes meanwhile,
    which then goes on: SciPy joins its query threads in a way a KeyboardInterrupt cuts
    short, and the threads went on reading the tree while the interrupt freed it (a
    segmentation fault as the process ended). In one part, a query of many far rows held a
    stop back for minutes (100 s for one axis of ``compare --size 128``'s completeness).
    Each row's neighbours are its own, so the parts give what one query would. Searched in
    IEEE arithmetic, as :func:`kd_tree` builds."""
    queries = np.asarray(queries)
    options["workers"] = workers or THREADS
    if queries.ndim < 2:  # one point
        with deferred_stops(), ieee_arithmetic():
            return tree.query(queries, **options)
    parts, start, rows = [], 0, _FIRST_QUERY_ROWS
    while True:
        began = time.perf_counter()
        with deferred_stops(), ieee_arithmetic():
            parts.append(tree.query(queries[start:start + rows], **options))
        start += rows
        if start >= len(queries):
            break
        took = time.perf_counter() - began  # the next part sized to take QUERY_SECONDS
        rows = int(min(max(rows * QUERY_SECONDS / max(took, 1e-6), 1), 4 * rows))
    if len(parts) == 1:
        return parts[0]
    return tuple(np.concatenate(column) for column in zip(*parts, strict=True))


def in_child_process(function: Callable[..., Any], *args: Any,
                     initializer: Callable[..., None] | None = None, initargs: tuple = (),
                     while_waiting: Callable[[], None] | None = None) -> Any:
    """``function(*args)`` run in a fresh process (set up by ``initializer(*initargs)``),
    ``while_waiting()`` called every ``WAIT_SECONDS`` meanwhile: a long call into C code that
    holds the GIL (xatlas' unwrapping) kept Ctrl-C and SIGTERM waiting to its end, where now
    they stop the child and go on at once. What crosses to the child and back must pickle."""
    context = multiprocessing.get_context("spawn")  # no copy of this process' threads
    with ProcessPoolExecutor(max_workers=1, mp_context=context, initializer=initializer,
                             initargs=initargs) as pool:
        try:
            # Started with Ctrl-C blocked, which the child keeps: a terminal's Ctrl-C reaches
            # the whole group, and the child, cut short while starting, printed a traceback;
            # this process stops it instead.
            with blocked((signal.SIGINT,)):
                job = pool.submit(function, *args)
            # Waited for apart from its result: a TimeoutError that the function raised
            # would pass for the wait's own (the builtin, from 3.11) and loop forever.
            while not wait([job], None if while_waiting is None else WAIT_SECONDS).done:
                while_waiting()
            return job.result()
        except KeyboardInterrupt:  # SIGTERM too (the CLI): the pool would wait for the child
            stop_workers(pool)
            raise


def stop_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate a pool's workers now and wait for them and the pool's thread, a second
    Ctrl-C or SIGTERM held back meanwhile: left to the interpreter's exit, that wait was cut
    short by it, with a traceback. (Python 3.14's ``terminate_workers`` leaves that wait to
    the exit too: it lets go of the pool before it terminates.)"""
    with deferred_stops():
        for process in list((pool._processes or {}).values()):
            process.terminate()
        pool.shutdown(wait=True, cancel_futures=True)
