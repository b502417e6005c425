"""What this machine offers a run: the cores it may use and its memory.

Commands size their work by these before starting it, so that a request too large for
the machine gets one clear error instead of a crash or a swap storm half-way.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
from collections.abc import Iterator
from pathlib import Path

# This process's control groups ("ID:controllers:path" lines) and where their limits are read:
# cgroup v2's memory.max and cpu.max ("max" where there is none), v1's memory.limit_in_bytes (a
# huge number where there is none) and cpu.cfs_quota_us (-1) over cpu.cfs_period_us.
_PROC_CGROUP = Path("/proc/self/cgroup")
_CGROUP_ROOT = Path("/sys/fs/cgroup")
_CPUINFO = Path("/proc/cpuinfo")


def cpu_model() -> str:
    """The CPU's model name as the system gives it ("AMD EPYC ..."), for reports of figures."""
    try:
        with open(_CPUINFO) as info:
            return next(line.split(":", 1)[1].strip() for line in info
                        if line.startswith("model name"))
    except (OSError, StopIteration):
        import platform

        return platform.processor() or platform.machine()


def usable_cores() -> int:
    """Cores this process may run on: its CPU affinity where the system has one (a
    container or ``taskset`` may allow fewer than the machine has), else all of them; fewer
    where its container's CPU quota (``docker --cpus``, a Kubernetes limit) grants less
    time than that, for threads beyond the quota only take turns."""
    if hasattr(os, "sched_getaffinity"):
        cores = max(1, len(os.sched_getaffinity(0)))
    else:
        cores = os.cpu_count() or 1
    quota = _cgroup_cpus()
    return cores if quota is None else max(1, min(cores, math.ceil(quota)))


def physical_memory() -> int | None:
    """Bytes of memory this process may have: the machine's, or its container's limit
    (cgroup), or what its own limits (``ulimit -v`` or ``-d``, a batch job's) leave it,
    where lower; None where the system says none of these."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = None
    known = [n for n in (total, _cgroup_limit(), _process_limit_room()) if n is not None]
    return min(known) if known else None


# Each limit of a process's memory, and the /proc/self/status field of what it holds of it.
_PROCESS_LIMITS = (("RLIMIT_AS", "VmSize"), ("RLIMIT_DATA", "VmData"))


def _process_limit_room() -> int | None:
    """Bytes more this process may map under its soft address-space and data limits, past
    what it maps already (a started Warp about 0.7 GB of address space); None without
    either limit. A limit it reaches fails allocations anywhere, as a traceback."""
    try:
        import resource
    except ImportError:  # not on Windows
        return None
    limits = [(soft, field) for name, field in _PROCESS_LIMITS
              if (soft := resource.getrlimit(getattr(resource, name))[0]) != resource.RLIM_INFINITY]
    if not limits:  # as most processes run: nothing to read
        return None
    status = _read(Path("/proc/self/status"))
    rooms = []
    for soft, field in limits:
        held = re.search(rf"^{field}:\s+(\d+) kB$", status, re.MULTILINE)
        if held is not None:
            rooms.append(max(soft - int(held[1]) * 1024, 0))
    return min(rooms, default=None)


def _cgroup_limit() -> int | None:
    """The lowest memory limit of this process's cgroup and those above it, as far as the
    cgroup file system shows them (a container sees its own group as the root)."""
    limits = []
    for level, v2 in _cgroup_levels("memory"):
        text = _read(level / ("memory.max" if v2 else "memory.limit_in_bytes"))
        if text.isdigit():
            limits.append(int(text))
    return min(limits, default=None)


def _cgroup_cpus() -> float | None:
    """The fewest cores' time that the CPU quotas of this process's cgroup and those above
    it grant (1.5: one and a half cores' worth each period), or None without a quota."""
    quotas = []
    for level, v2 in _cgroup_levels("cpu"):
        if v2:
            fields = _read(level / "cpu.max").split()
        else:
            fields = [_read(level / "cpu.cfs_quota_us"), _read(level / "cpu.cfs_period_us")]
        if len(fields) == 2 and all(f.isdigit() for f in fields) and int(fields[1]) > 0:
            quotas.append(int(fields[0]) / int(fields[1]))
    return min(quotas, default=None)


def _cgroup_levels(controller: str) -> Iterator[tuple[Path, bool]]:
    """The folders of this process's cgroups that ``controller`` governs and of those above
    them, each with whether it is of cgroup v2."""
    try:
        lines = _PROC_CGROUP.read_text().splitlines()
    except OSError:
        return
    for line in lines:
        fields = line.split(":", 2)
        if len(fields) != 3:
            continue
        _, controllers, group = fields
        if controllers == "":
            base, v2 = _CGROUP_ROOT, True
        elif controller in controllers.split(","):
            base, v2 = _CGROUP_ROOT / controller, False
        else:
            continue
        folder = base / group.lstrip("/")
        for level in [folder, *folder.parents]:
            if not level.is_relative_to(base):
                break
            yield level, v2


def _read(path: Path) -> str:
    """A cgroup file's text, stripped; empty where there is no such file."""
    try:
        return path.read_text().strip()
    except OSError:
        return ""


def memory_problem(need: int) -> str | None:
    """Why ``need`` bytes cannot be had here ("needs about 75 GiB, this machine has 24
    GiB"), or None when they fit or the machine's memory is unknown."""
    memory = physical_memory()
    if memory is None or need <= memory:
        return None
    where = "this machine has" if _process_limit_room() is None else "this process may have"
    return f"needs about {byte_size(need)}, {where} {byte_size(memory)}"


def byte_size(n: int) -> str:
    """``n`` bytes in GiB, or MiB below one GiB: "24 GiB", "304 MiB"."""
    return f"{n / 2**30:.0f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"


def map_large_blocks() -> None:
    """Make glibc's malloc map every block of 128 KiB or more afresh and unmap it when freed,
    in a process that measures its peak memory (:class:`PeakMemory`): by default it keeps
    freed large blocks for reuse, so an array the size of one freed earlier does not raise
    the peak (a 64^3 volume counted 0 MiB). A no-op where there is no glibc."""
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").mallopt(_M_MMAP_THRESHOLD, 128 << 10)


_M_MMAP_THRESHOLD = -3  # mallopt's parameter number, malloc.h


class PeakMemory:
    """How far this process's resident memory rose above its level at the start of a
    ``with`` block, in bytes (``growth`` after the block): the peak memory of the work done
    in it, as ``warptex compare`` reports per method (in processes that
    :func:`map_large_blocks`); ``peak``, the resident memory at that peak.

    On Linux the peak (``VmHWM``) is reset at the start through ``/proc/self/clear_refs``;
    elsewhere the rise of ``ru_maxrss`` over the start, which misses memory below an earlier
    peak.
    """

    _STATUS = Path("/proc/self/status")
    _CLEAR_REFS = Path("/proc/self/clear_refs")

    def __init__(self) -> None:
        self.growth = 0
        self.peak = 0
        self._start = 0
        self._reset = False

    def __enter__(self) -> PeakMemory:
        try:
            self._CLEAR_REFS.write_text("5")  # 5: reset the peak resident set size
            self._start = self._status("VmRSS")
            self._reset = True
        except (OSError, ValueError):
            self._start = self._max_rss()
        return self

    def __exit__(self, *exc: object) -> None:
        self.peak = self._status("VmHWM") if self._reset else self._max_rss()
        self.growth = max(self.peak - self._start, 0)

    def _status(self, key: str) -> int:
        for line in self._STATUS.read_text().splitlines():
            if line.startswith(f"{key}:"):
                return int(line.split()[1]) << 10  # kB
        raise ValueError(f"no {key} in {self._STATUS}")

    @staticmethod
    def _max_rss() -> int:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss << 10  # KiB on Linux


def software_versions() -> dict[str, str]:
    """The versions a report of numbers names: warptex (and the digest of its code, for the
    version stays the same between commits), Warp, Mitsuba, Dr.Jit, NumPy, SciPy, Python
    and the operating system."""
    import platform

    import drjit as dr
    import mitsuba as mi
    import numpy as np
    import scipy
    import warp as wp

    from warptex import __version__
    from warptex.code_digest import installed_code_digest

    return {"warptex": __version__, "warptex_code": installed_code_digest()[:16],
            "warp": wp.__version__, "mitsuba": mi.__version__, "drjit": dr.__version__,
            "numpy": np.__version__, "scipy": scipy.__version__,
            "python": platform.python_version(), "os": platform.platform()}
