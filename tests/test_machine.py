"""What a command may use of this machine (warptex.machine) and the memory checks that
refuse a job too large for it before any work."""

import pytest


def test_volume_memory_counts_the_join_and_the_working_bytes(monkeypatch):
    from warptex import cli, machine

    size, channels = 64, 3
    one_copy = 4 * channels * size**3
    for memory, working, refused in [
        (3 * one_copy, 0, False),        # two copies fit
        (1.5 * one_copy, 0, True),       # one copy fits, the joined second does not
        (2 * one_copy + 10, 100, True),  # the working bytes tip it over
        (2 * one_copy + 100, 100, False),
    ]:
        monkeypatch.setattr(machine, "physical_memory", lambda m=memory: int(m))
        if refused:
            with pytest.raises(cli.CliError, match=f"--size {size}: a {size}\\^3 volume needs"):
                cli._check_memory(size, channels, working)
        else:
            cli._check_memory(size, channels, working)


@pytest.mark.parametrize(("v2", "v1", "expected"), [
    ("max\n", None, "total"),                      # cgroup v2 without a limit
    ("1073741824\n", None, 1 << 30),               # a container of 1 GiB
    (None, "2147483648\n", 2 << 30),               # cgroup v1
    (None, "9223372036854771712\n", "total"),      # v1 without a limit: the machine's
    (None, None, "total"),                          # no cgroup files
])
def test_physical_memory_is_a_containers_limit_where_lower(tmp_path, monkeypatch, v2, v1,
                                                          expected):
    from warptex import machine

    monkeypatch.setattr(machine, "_CGROUP_LIMITS", ())
    total = machine.physical_memory()
    paths = []
    for name, text in (("memory.max", v2), ("memory.limit_in_bytes", v1)):
        paths.append(tmp_path / name)
        if text is not None:
            paths[-1].write_text(text)
    monkeypatch.setattr(machine, "_CGROUP_LIMITS", tuple(paths))
    assert machine.physical_memory() == (total if expected == "total" else expected)


def test_physical_memory_is_the_systems_total():
    import os

    from warptex.machine import physical_memory

    if not os.path.exists("/proc/meminfo"):
        pytest.skip("no /proc/meminfo")
    with open("/proc/meminfo") as info:
        total = next(int(line.split()[1]) * 1024 for line in info
                     if line.startswith("MemTotal:"))
    assert abs(physical_memory() - total) <= 0.02 * total
