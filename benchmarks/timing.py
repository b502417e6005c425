"""Timing helpers shared by the benchmark scripts (run them from the repository root)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def timed_runs(run: Callable[[T], object], repeat: int, prepare: Callable[[], T]) -> list[float]:
    """Wall-clock seconds of ``repeat`` calls of ``run(prepare())``, each timing ``run``
    alone (``prepare`` makes what it works on afresh: a new engine, say)."""
    times = []
    for _ in range(repeat):
        subject = prepare()
        start = time.perf_counter()
        run(subject)
        times.append(time.perf_counter() - start)
    return times


def best_of(fn: Callable[[], object], repeat: int) -> float:
    """The shortest of ``repeat`` wall-clock timings of ``fn()``, in seconds."""
    return min(timed_runs(lambda _: fn(), repeat, lambda: None))
