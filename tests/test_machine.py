"""What a command may use of this machine (warptex.machine) and the memory checks that
refuse a job too large for it before any work."""

from pathlib import Path

import pytest


def test_volume_memory_counts_its_copies_and_the_working_bytes(monkeypatch):
    from warptex import machine
    from warptex.cli import common

    size, channels = 64, 3
    one_copy = 4 * channels * size**3
    for memory, working, copies, refused in [
        (3 * one_copy, 0, 2, False),        # two copies fit
        (1.5 * one_copy, 0, 2, True),       # one copy fits, the second does not
        (2 * one_copy + 10, 100, 2, True),  # the working bytes tip it over
        (2 * one_copy + 100, 100, 2, False),
        (3 * one_copy, 0, 4, True),         # a writer's copies do not fit
    ]:
        monkeypatch.setattr(machine, "physical_memory", lambda m=memory: int(m))
        if refused:
            with pytest.raises(common.CliError, match=f"--size {size}: a {size}\\^3 volume needs"):
                common.check_memory(size, channels, working, copies)
        else:
            common.check_memory(size, channels, working, copies)


@pytest.mark.parametrize(("suffix", "copies"), [(".npy", 1), (".vol", 3), (".exr", 4)])
def test_the_volume_command_counts_what_writing_its_file_holds(tmp_path, granite_32_file,
                                                                monkeypatch, suffix, copies):
    """The volume and the copies its file's writer holds besides it (decoded colors, an
    EXR's sheets): only two were counted, so a large .exr or .vol ran out of memory once
    all its voxels were synthesized. Once the slabs are planned, the volume and the larger
    of a slab's work and the writer's copies, which never coexist, are counted."""
    from warptex.cli import main, volumes
    from warptex.cli.common import volume_bytes

    counted = []

    def stop_at_the_second_check(size, channels, working=0, copies=2):
        counted.append((copies, working))
        if len(counted) == 2:
            raise volumes.CliError("checked")

    monkeypatch.setattr(volumes, "check_memory", stop_at_the_second_check)
    assert main(["volume", str(granite_32_file), "--size", "16", "-o",
                 str(tmp_path / f"v{suffix}")]) == 2
    from warptex.dependencies import default_apron_blocks
    from warptex.synthesis import box_bytes

    (first, none), (one, working) = counted
    assert (first, none, one) == (copies, 0, 1)
    slab = box_bytes((16, 16, 16), default_apron_blocks(2)) + volume_bytes(16, 3)  # one slab
    assert working == max(slab, (copies - 1) * volume_bytes(16, 3))  # not their sum


@pytest.mark.parametrize(("groups", "files", "expected"), [
    ("0::/\n", {"memory.max": "max"}, "total"),                      # v2 without a limit
    ("0::/\n", {"memory.max": "1073741824"}, 1 << 30),               # a container of 1 GiB
    ("0::/user/job\n", {"user/job/memory.max": "max", "user/memory.max": "1073741824",
                        "memory.max": "max"}, 1 << 30),               # a limit further up
    ("0::/job\n", {"job/memory.max": "2147483648", "memory.max": "1073741824"}, 1 << 30),
    ("5:cpu:/x\n4:memory:/job\n", {"memory/job/memory.limit_in_bytes": "2147483648"},
     2 << 30),                                                         # cgroup v1
    ("4:memory,pids:/\n", {"memory/memory.limit_in_bytes": "9223372036854771712"},
     "total"),                                                         # v1 without a limit
    ("4:cpu:/\n", {"memory.max": "1073741824"}, "total"),            # no memory controller
    (None, {}, "total"),                                              # no cgroups at all
    ("garbled\n0::/\n", {"memory.max": "1073741824"}, 1 << 30),     # a line it cannot read
])
def test_physical_memory_is_a_containers_limit_where_lower(tmp_path, monkeypatch, groups,
                                                          files, expected):
    from warptex import machine

    monkeypatch.setattr(machine, "_PROC_CGROUP", tmp_path / "missing")
    total = machine.physical_memory()
    root = tmp_path / "cgroup"
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text + "\n")
    if groups is not None:
        (tmp_path / "proc_cgroup").write_text(groups)
        monkeypatch.setattr(machine, "_PROC_CGROUP", tmp_path / "proc_cgroup")
    monkeypatch.setattr(machine, "_CGROUP_ROOT", root)
    assert machine.physical_memory() == (total if expected == "total" else expected)


@pytest.mark.parametrize(("groups", "files", "expected"), [
    ("0::/\n", {"cpu.max": "max 100000"}, 16),                        # v2 without a quota
    ("0::/\n", {"cpu.max": "200000 100000"}, 2),                      # docker --cpus 2
    ("0::/\n", {"cpu.max": "150000 100000"}, 2),                      # a part core counts
    ("0::/\n", {"cpu.max": "20000 100000"}, 1),
    ("0::/\n", {"cpu.max": "6400000 100000"}, 16),                    # more than the cores
    ("0::/a/b\n", {"a/b/cpu.max": "max 100000", "a/cpu.max": "300000 100000"}, 3),
    ("1:cpu,cpuacct:/job\n", {"cpu/job/cpu.cfs_quota_us": "400000",
                               "cpu/job/cpu.cfs_period_us": "100000"}, 4),  # cgroup v1
    ("1:cpu,cpuacct:/\n", {"cpu/cpu.cfs_quota_us": "-1",
                            "cpu/cpu.cfs_period_us": "100000"}, 16),   # v1 without a quota
    ("1:cpu:/\n", {"cpu/cpu.cfs_quota_us": "400000"}, 16),            # no period: unread
    ("4:memory:/\n", {"cpu.max": "200000 100000"}, 16),               # no cpu controller
    ("3:cpuset:/pinned\n1:cpu,cpuacct:/\n",                          # cpuset is not cpu
     {"cpu/pinned/cpu.cfs_quota_us": "100000", "cpu/pinned/cpu.cfs_period_us": "100000"}, 16),
    (None, {}, 16),                                                   # no cgroups at all
])
def test_usable_cores_are_a_containers_cpu_quota_where_fewer(tmp_path, monkeypatch, groups,
                                                            files, expected):
    """A quota of 2 cores on a 16-core machine: 8 threads only took turns, and `warptex
    compare` reported 16 cores."""
    import os

    from warptex import machine

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(16)), raising=False)
    root = tmp_path / "cgroup"
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text + "\n")
    proc = tmp_path / "proc_cgroup"
    if groups is not None:
        proc.write_text(groups)
    monkeypatch.setattr(machine, "_PROC_CGROUP", proc)
    monkeypatch.setattr(machine, "_CGROUP_ROOT", root)
    assert machine.usable_cores() == expected


def _limited(monkeypatch, limits: dict[int, int]) -> None:
    """The process's soft limits read as ``limits`` (resource: bytes, read at each call, so
    the test may change them), the others as they are, and no cgroup."""
    import resource

    from warptex import machine

    real = resource.getrlimit
    monkeypatch.setattr(resource, "getrlimit",
                        lambda which: (limits[which], resource.RLIM_INFINITY)
                        if which in limits else real(which))
    monkeypatch.setattr(machine, "_PROC_CGROUP", Path("/nonexistent"))


def test_physical_memory_is_what_the_process_limits_leave(monkeypatch):
    """Under ulimit -v (a batch job's limit) the checks compared their estimates with the
    machine's memory: a 512^3 volume was accepted, then failed with a traceback."""
    import re
    import resource

    from warptex import machine

    status = Path("/proc/self/status")
    if not status.exists():
        pytest.skip("no /proc/self/status")

    def held(field: str) -> int:  # what the process maps now, which the limit counts
        return int(re.search(rf"^{field}:\s+(\d+) kB$", status.read_text(), re.M)[1]) << 10

    limits = {resource.RLIMIT_AS: held("VmSize") + (3 << 30),
              resource.RLIMIT_DATA: resource.RLIM_INFINITY}
    _limited(monkeypatch, limits)
    room = machine.physical_memory()
    assert abs(room - (3 << 30)) < (256 << 20)  # the limit less what is mapped already
    assert machine.memory_problem(10 << 30) == ("needs about 10 GiB, this process may have "
                                                f"{machine.byte_size(room)}")
    limits[resource.RLIMIT_DATA] = held("VmData") + (1 << 30)  # the lower of the two
    assert abs(machine.physical_memory() - (1 << 30)) < (256 << 20)


def test_a_process_limit_below_what_is_mapped_leaves_no_room(monkeypatch):
    """Not a negative room, which a refusal would name as "may have -x MiB"."""
    import resource

    from warptex import machine

    if not Path("/proc/self/status").exists():
        pytest.skip("no /proc/self/status")
    _limited(monkeypatch, {resource.RLIMIT_AS: 1 << 20,
                           resource.RLIMIT_DATA: resource.RLIM_INFINITY})
    assert machine.physical_memory() == 0


def test_cpu_model_is_the_model_name_line(tmp_path, monkeypatch):
    """x86's /proc/cpuinfo has a "model" line (a number) before "model name"."""
    from warptex import machine

    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nmodel\t\t: 2\nmodel name\t: AMD EPYC 9654\n")
    monkeypatch.setattr(machine, "_CPUINFO", info)
    assert machine.cpu_model() == "AMD EPYC 9654"


def test_physical_memory_is_the_systems_total(monkeypatch):
    import os

    from warptex import machine
    from warptex.machine import physical_memory

    monkeypatch.setattr(machine, "_PROC_CGROUP", Path("/nonexistent"))  # no container limit

    if not os.path.exists("/proc/meminfo"):
        pytest.skip("no /proc/meminfo")
    with open("/proc/meminfo") as info:
        total = next(int(line.split()[1]) * 1024 for line in info
                     if line.startswith("MemTotal:"))
    assert abs(physical_memory() - total) <= 0.02 * total


def test_peak_memory_counts_arrays_the_size_of_ones_freed_before():
    """The memory of the work in the block, also where the process freed as much before it,
    which glibc would otherwise hand out again without the peak rising (0 MiB here, and for
    the 64^3 volumes of `warptex compare`)."""
    import subprocess
    import sys

    script = """
import numpy as np
from warptex.machine import PeakMemory, map_large_blocks
{setup}
np.ones(2 << 20)  # 16 MiB mapped and unmapped: glibc then keeps blocks of this size
np.ones(1 << 20)  # 8 MiB, freed and kept
with PeakMemory() as memory:
    volume = np.ones(1 << 20)  # 8 MiB
print(memory.growth / 2**20)
"""
    grown = {}
    for setup in ("map_large_blocks()", "pass"):
        grown[setup] = float(subprocess.run(
            [sys.executable, "-c", script.format(setup=setup)], capture_output=True, text=True,
            check=True).stdout)
    assert 8 <= grown["map_large_blocks()"] <= 9
    assert grown["pass"] < 1  # what the peak missed before
