"""What this machine offers a run: the cores it may use and its memory.

Commands size their work by these before starting it, so that a request too large for
the machine gets one clear error instead of a crash or a swap storm half-way.
"""

from __future__ import annotations

import os
from pathlib import Path

# This process's control groups ("ID:controllers:path" lines) and where their memory limits
# are read: cgroup v2's memory.max ("max" when there is none), v1's memory.limit_in_bytes (a
# huge number when there is none).
_PROC_CGROUP = Path("/proc/self/cgroup")
_CGROUP_ROOT = Path("/sys/fs/cgroup")


def usable_cores() -> int:
    """Cores this process may run on: its CPU affinity where the system has one (a
    container or ``taskset`` may allow fewer than the machine has), else all of them."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def physical_memory() -> int | None:
    """Bytes of memory this process may have: the machine's, or its container's limit
    (cgroup) where that is lower; None where the system says neither."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = None
    known = [n for n in (total, _cgroup_limit()) if n is not None]
    return min(known) if known else None


def _cgroup_limit() -> int | None:
    """The lowest memory limit of this process's cgroup and those above it, as far as the
    cgroup file system shows them (a container sees its own group as the root)."""
    try:
        lines = _PROC_CGROUP.read_text().splitlines()
    except OSError:
        return None
    limits = []
    for line in lines:
        fields = line.split(":", 2)
        if len(fields) != 3:
            continue
        _, controllers, group = fields
        if controllers == "":
            base, name = _CGROUP_ROOT, "memory.max"
        elif "memory" in controllers.split(","):
            base, name = _CGROUP_ROOT / "memory", "memory.limit_in_bytes"
        else:
            continue
        folder = base / group.lstrip("/")
        for level in [folder, *folder.parents]:
            if not level.is_relative_to(base):
                break
            try:
                text = (level / name).read_text().strip()
            except OSError:
                continue
            if text.isdigit():
                limits.append(int(text))
    return min(limits, default=None)


def memory_problem(need: int) -> str | None:
    """Why ``need`` bytes cannot be had here ("needs about 75 GiB, this machine has 24
    GiB"), or None when they fit or the machine's memory is unknown."""
    memory = physical_memory()
    if memory is None or need <= memory:
        return None
    return f"needs about {byte_size(need)}, this machine has {byte_size(memory)}"


def byte_size(n: int) -> str:
    """``n`` bytes in GiB, or MiB below one GiB: "24 GiB", "304 MiB"."""
    return f"{n / 2**30:.0f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"
