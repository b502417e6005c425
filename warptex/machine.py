"""What this machine offers a run: the cores it may use and its memory.

Commands size their work by these before starting it, so that a request too large for
the machine gets one clear error instead of a crash or a swap storm half-way.
"""

from __future__ import annotations

import os


def usable_cores() -> int:
    """Cores this process may run on: its CPU affinity where the system has one (a
    container or ``taskset`` may allow fewer than the machine has), else all of them."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def physical_memory() -> int | None:
    """Bytes of physical memory, or None where the system does not say."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def memory_problem(need: int) -> str | None:
    """Why ``need`` bytes cannot be had here ("needs about 75 GiB, this machine has 24
    GiB"), or None when they fit or the machine's memory is unknown."""
    memory = physical_memory()
    if memory is None or need <= memory:
        return None
    return f"needs about {_gib(need)}, this machine has {_gib(memory)}"


def _gib(n: int) -> str:
    return f"{n / 2**30:.0f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"
