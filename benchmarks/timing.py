"""Timing helpers shared by the benchmark scripts (run them from the repository root)."""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")
ROOT = Path(__file__).resolve().parent.parent


def positive_int(text: str) -> int:
    """An argparse type: an integer of at least 1 (a count of runs, pixels, samples), refused
    before any work rather than failing in ``min()`` after it."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def exemplar_files(parser: argparse.ArgumentParser, folder: Path,
                   names: Iterable[str | Path] | None, suffix: str = ".png",
                   what: str = "exemplar") -> list[Path]:
    """The files ``folder / (name + suffix)`` of ``names``, or the parser's error naming
    those missing, before any work (not when the run reaches them, minutes later).
    ``names`` None: every ``*suffix`` file of ``folder``, sorted, the error where there is
    none (a glob of a missing folder finds nothing, silently). Paths of their own: ``folder``
    ``Path()`` and ``suffix`` ``""``; ``what`` names them in the error."""
    if names is None:
        files = sorted(folder.glob(f"*{suffix}"))
        if not files:
            parser.error(f"{folder} holds no *{suffix} exemplars: give their folder with "
                         "--exemplars")
        return files
    files = [folder / f"{name}{suffix}" for name in names]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        parser.error(f"no such {what}: {', '.join(missing)}")
    return files


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


def in_a_process(arguments: list[str], what: str, env: dict[str, str] | None = None) -> Any:
    """What a Python process of ``arguments`` (a script and its options, or ``-c`` and
    code) prints as JSON on its last line: measured in a fresh process, where memory freed
    or kernels compiled by an earlier run hide nothing. Exits naming ``what`` where it
    fails."""
    run = subprocess.run([sys.executable, *arguments], capture_output=True, text=True, env=env)
    if run.returncode:
        sys.exit(f"{what} failed in its process:\n{run.stderr}")
    return json.loads(run.stdout.strip().splitlines()[-1])


def run_record() -> str:
    """The commit (``-dirty`` with uncommitted changes), date, machine and versions of this
    run: what BENCHMARKS.md records beside its figures. Refuses (SystemExit) to label a run
    whose warptex is imported from another checkout than the script's."""
    import numpy as np
    import warp as wp

    import warptex
    from warptex.machine import cpu_model, physical_memory, usable_cores
    from warptex.warp_runtime import device

    # An interpreter whose install points at another checkout (a clone run with the main
    # checkout's .venv) measures that checkout's code: its commit would be a false label.
    measured = Path(warptex.__file__).resolve().parent.parent
    if measured != ROOT:
        raise SystemExit(f"this script is in {ROOT} but imports warptex from {measured}: "
                         f"run it with an interpreter that imports {ROOT}'s own (set "
                         f"PYTHONPATH={ROOT})")
    try:
        commit = subprocess.run(["git", "-C", str(ROOT), "describe", "--always", "--dirty"],
                                capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown (not a git checkout)"
    memory = physical_memory()
    gib = "memory unknown" if memory is None else f"{memory / 2**30:.0f} GiB"
    cores = usable_cores()
    return (f"commit {commit}, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC; "
            f"{cpu_model()}, {cores} core{'s' * (cores > 1)}, {gib}; "
            f"Warp {wp.__version__} on {device()}, NumPy {np.__version__}, "
            f"Python {platform.python_version()}")
