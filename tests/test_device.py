"""Device choice and Warp start-up."""

from __future__ import annotations

import contextlib
import errno
import io
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest
import warp as wp

import warptex
import warptex.warp_runtime as device_module


@pytest.fixture
def gpus(monkeypatch):
    """Pretend Warp sees the given number of CUDA devices."""

    def set_count(count: int) -> None:
        monkeypatch.setattr(wp, "get_cuda_device_count", lambda: count)

    monkeypatch.delenv("WARPTEX_DEVICE", raising=False)
    return set_count


def test_picks_cuda_when_warp_sees_a_gpu(gpus):
    gpus(1)
    assert warptex.device() == "cuda"


def test_picks_cpu_without_gpu(gpus):
    gpus(0)
    assert warptex.device() == "cpu"


@pytest.mark.parametrize("value", ["cpu", "CPU", " cpu "])
def test_env_forces_cpu(gpus, monkeypatch, value):
    gpus(1)
    monkeypatch.setenv("WARPTEX_DEVICE", value)
    assert warptex.device() == "cpu"


def test_env_forces_cuda(gpus, monkeypatch):
    gpus(2)
    monkeypatch.setenv("WARPTEX_DEVICE", "cuda")
    assert warptex.device() == "cuda"


def test_env_cuda_without_gpu_is_a_clear_error(gpus, monkeypatch):
    gpus(0)
    monkeypatch.setenv("WARPTEX_DEVICE", "cuda")
    with pytest.raises(RuntimeError, match="WARPTEX_DEVICE=cuda but Warp sees no CUDA device"):
        warptex.device()


@pytest.mark.parametrize("value", ["gpu", "cuda:0", "metal"])
def test_env_invalid_value_names_the_variable(gpus, monkeypatch, value):
    gpus(0)
    monkeypatch.setenv("WARPTEX_DEVICE", value)
    with pytest.raises(ValueError, match=r"WARPTEX_DEVICE=.* is not valid; use one of: cpu, cuda"):
        warptex.device()


def test_real_device_is_valid():
    assert warptex.device() in ("cpu", "cuda")


def test_warp_device_fixture_runs_on_cpu_with_project_cache(warp_device):
    assert warp_device == "cpu"
    assert wp.get_device().is_cpu
    # Warp adds a per-version folder below the cache path it is given.
    given = Path(os.environ["WARP_CACHE_PATH"]).resolve()  # which may be relative
    assert Path(wp.config.kernel_cache_dir).resolve().is_relative_to(given)


def test_init_warp_runs_once(warp_device, monkeypatch):
    calls = []
    monkeypatch.setattr(wp, "init", lambda: calls.append(1))
    device_module.init_warp()
    assert calls == []


def test_start_keeps_gpu_memory_pooled_unless_set_otherwise(monkeypatch):
    """CUDA's default pool gives its memory back at every synchronization; at start-up each
    GPU with a pool left at that default keeps ``POOL_KEPT`` of its memory instead, and a
    threshold someone chose is kept."""
    from types import SimpleNamespace

    gpus = [SimpleNamespace(name="default", is_mempool_enabled=True, threshold=0),
            SimpleNamespace(name="chosen", is_mempool_enabled=True, threshold=1 << 30),
            SimpleNamespace(name="no pool", is_mempool_enabled=False, threshold=0)]
    set_to = {}
    monkeypatch.setattr(wp, "init", lambda: None)
    monkeypatch.setattr(wp, "get_cuda_devices", lambda: gpus)
    monkeypatch.setattr(wp, "get_mempool_release_threshold", lambda gpu: gpu.threshold)
    monkeypatch.setattr(wp, "set_mempool_release_threshold",
                        lambda gpu, value: set_to.__setitem__(gpu.name, value))
    device_module.init_warp.__wrapped__()
    assert set_to == {"default": device_module.POOL_KEPT}

    def refuse(gpu, value):
        raise RuntimeError(f"Failed to set memory pool release threshold for device {gpu}")

    monkeypatch.setattr(wp, "set_mempool_release_threshold", refuse)
    device_module.init_warp.__wrapped__()  # slower on such a GPU, not an error


def _noisy_init() -> None:
    """Stands in for ``wp.init`` on a machine without an NVIDIA driver: Warp's library
    writes its warning to file descriptor 2, beside anything else worth seeing."""
    os.write(2, b"Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU "
                b"execution will not be available.\nsomething else Warp said\n")


@pytest.mark.parametrize("requested", [None, "cpu"])
def test_start_drops_only_the_missing_driver_warning(requested, monkeypatch, capfd):
    if requested is None:
        monkeypatch.delenv("WARPTEX_DEVICE", raising=False)
    else:
        monkeypatch.setenv("WARPTEX_DEVICE", requested)
    monkeypatch.setattr(wp, "init", _noisy_init)
    device_module.init_warp.__wrapped__()
    err = capfd.readouterr().err
    assert "NVIDIA CUDA driver" not in err
    assert "something else Warp said" in err


def test_start_keeps_the_warning_when_cuda_is_asked_for(monkeypatch, capfd):
    monkeypatch.setenv("WARPTEX_DEVICE", "cuda")
    monkeypatch.setattr(wp, "init", _noisy_init)
    device_module.init_warp.__wrapped__()
    assert "Could not find or load the NVIDIA CUDA driver" in capfd.readouterr().err


def test_a_command_starts_without_the_missing_driver_warning():
    env = {k: v for k, v in os.environ.items() if k != "WARPTEX_DEVICE"}
    run = subprocess.run([sys.executable, "-c", "import warptex; warptex.device()"],
                         env=env, capture_output=True, text=True, check=True)
    assert "NVIDIA CUDA driver" not in run.stderr


@pytest.mark.parametrize("no_stderr", ["os.close(2)", "sys.stderr = None"])
def test_warp_starts_without_a_stderr(no_stderr):
    code = f"import os, sys; {no_stderr}; import warptex; print(warptex.device())"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0 and run.stdout.strip() in ("cpu", "cuda")


def test_warp_starts_where_no_temporary_file_can_be_made(monkeypatch, capfd):
    """No temporary folder writable: the capture is given up, not Warp's start (which the
    command reported as a kernel cache folder it could not make)."""
    monkeypatch.delenv("WARPTEX_DEVICE", raising=False)
    monkeypatch.setattr(wp, "init", _noisy_init)

    def no_room(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", "/tmp/tmpx")

    monkeypatch.setattr(device_module.tempfile, "TemporaryFile", no_room)
    device_module.init_warp.__wrapped__()
    assert "something else Warp said" in capfd.readouterr().err


def test_an_empty_kernel_cache_variable_is_unset_for_warp_too(monkeypatch):
    """Warp takes a WARP_CACHE_PATH that is set, empty, for the working folder, and built
    its kernels into it."""
    seen = []
    monkeypatch.setattr(wp, "init", lambda: seen.append(os.environ.get("WARP_CACHE_PATH")))
    monkeypatch.setattr(wp.config, "kernel_cache_dir", None)
    monkeypatch.setenv("WARP_CACHE_PATH", "")
    device_module.init_warp.__wrapped__()
    assert seen == [None] and wp.config.kernel_cache_dir is None


def test_the_kernel_cache_variable_starts_at_home_as_warptex_cache_does(tmp_path, monkeypatch):
    monkeypatch.setattr(wp, "init", lambda: None)
    monkeypatch.setattr(wp.config, "kernel_cache_dir", None)
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("WARP_CACHE_PATH", "~/kernels")
    device_module.init_warp.__wrapped__()
    assert wp.config.kernel_cache_dir == str(tmp_path / "kernels")


_DOUBLING = '''
import numpy as np
import warp as wp
from warptex.warp_runtime import init_warp, launch

@wp.kernel
def double(a: wp.array(dtype=float), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = 2.0 * a[i]

init_warp()
out = wp.zeros(3, dtype=float, device="cpu")
launch(double, 3, [wp.array(np.arange(3, dtype=np.float32), device="cpu")], [out])
print(out.numpy().tolist())
'''


_NOTICED_BUILD = '''
from pathlib import Path

import numpy as np
import warp as wp
from warptex.warp_runtime import init_warp, kernel_build_notice, launch

@wp.kernel
def double(a: wp.array(dtype=float)):
    i = wp.tid()
    a[i] = 2.0 * a[i]

def notice(cache):
    built = any(cache.glob("wp___main__*"))
    print("notice", cache == Path(wp.config.kernel_cache_dir), "built" if built else "unbuilt")

init_warp()
a = wp.array(np.arange(3, dtype=np.float32), device="cpu")
with kernel_build_notice(notice):
    print("launching")
    launch(double, 3, [a])
    launch(double, 3, [a])
# Loaded in this process, the module is not built again, whatever the cache holds now.
wp.config.kernel_cache_dir = str(Path(wp.config.kernel_cache_dir).parent / "elsewhere")
with kernel_build_notice(notice):
    launch(double, 3, [a])
print(a.numpy().tolist())
'''


def test_a_kernel_build_is_noticed_once_as_it_begins(tmp_path):
    """Before Warp builds the module into its cache, once; not where the build is there,
    nor for a module this process launched already."""
    script = tmp_path / "noticed.py"
    script.write_text(_NOTICED_BUILD)
    env = {**os.environ, "WARP_CACHE_PATH": str(tmp_path / "kernels")}
    runs = [subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                           env=env, timeout=300) for _ in range(2)]
    assert [r.returncode for r in runs] == [0, 0], runs[-1].stderr
    assert runs[0].stdout.split("\n") == ["launching", "notice True unbuilt",
                                          "[0.0, 8.0, 16.0]", ""]
    assert runs[1].stdout.split("\n") == ["launching", "[0.0, 8.0, 16.0]", ""]


def test_a_kernel_build_notice_looks_for_the_launch_devices_build(tmp_path, monkeypatch,
                                                                 warp_device):
    """A CPU launch builds Warp's block_dim 1 variant, a CUDA launch its default one."""
    import importlib

    importlib.import_module("kernels.lookup")
    module = wp.get_module("kernels.lookup")
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    (tmp_path / module.get_module_identifier(block_dim=1)).mkdir()
    monkeypatch.setattr(device_module, "_LAUNCHED", set())
    monkeypatch.setattr(device_module, "_BUILD_NOTICE", [])  # none outside the blocks
    notes = []
    with device_module.kernel_build_notice(notes.append):
        device_module._notice_build("kernels.lookup", "cpu")
        assert notes == []
        device_module._notice_build("kernels.lookup", "cuda:0")
        assert notes == [tmp_path]
    (tmp_path / module.get_module_identifier(block_dim=None)).mkdir()
    monkeypatch.setattr(device_module, "_LAUNCHED", set())
    with device_module.kernel_build_notice(notes.append):
        device_module._notice_build("kernels.lookup", "cuda:0")
    device_module._notice_build("kernels.synthesis", "cpu")  # outside a block: never
    assert notes == [tmp_path]


_UNNOTICED_BUILD = '''
import numpy as np
import warp as wp
from warptex.warp_runtime import init_warp, launch

@wp.kernel
def double(a: wp.array(dtype=float)):
    i = wp.tid()
    a[i] = 2.0 * a[i]

init_warp()
a = wp.array(np.arange(3, dtype=np.float32), device="cpu")
launch(double, 3, [a])
launch(double, 3, [a])
print(a.numpy().tolist())
'''


def test_a_script_on_a_terminal_is_told_of_a_kernel_build_once(tmp_path):
    """A script or a Mitsuba scene outside the commands pauses as they do on a fresh kernel
    cache: said on a terminal, once, as precompute's bars are shown there."""
    import pty

    script = tmp_path / "unnoticed.py"
    script.write_text(_UNNOTICED_BUILD)
    env = {**os.environ, "WARP_CACHE_PATH": str(tmp_path / "kernels")}
    said = []
    for _ in range(2):
        terminal, stderr = pty.openpty()
        with os.fdopen(terminal, "rb", buffering=0) as reader:
            run = subprocess.run([sys.executable, str(script)], stdout=subprocess.PIPE,
                                 stderr=stderr, text=True, env=env, timeout=300)
            os.close(stderr)
            chunks = []
            with contextlib.suppress(OSError):  # EIO once the writer's side is closed
                while chunk := reader.read(4096):
                    chunks.append(chunk)
        assert (run.returncode, run.stdout) == (0, "[0.0, 4.0, 8.0]\n")
        said.append(b"".join(chunks).decode())
    assert said[0].count("warptex: Warp is building the kernels") == 1, said[0]
    assert f"into {tmp_path / 'kernels'}" in said[0]
    assert "building" not in said[1], said[1]


def test_a_kernel_build_outside_a_block_is_said_on_a_terminal_only(tmp_path, monkeypatch):
    """Logs and pipes keep their own lines; a block's notice leaves the terminal's for
    after it."""
    class Stream(io.StringIO):
        terminal = False

        def isatty(self) -> bool:
            return super().isatty() or self.terminal  # a closed one raises, as files do

    def fresh_process() -> None:
        monkeypatch.setattr(device_module, "_BUILD_NOTICE",
                            [device_module._say_kernel_build_on_a_terminal])
        monkeypatch.setattr(device_module, "_LAUNCHED", set())

    monkeypatch.setattr(device_module, "build_folder", lambda name, cpu: tmp_path / name)
    stream = Stream()
    monkeypatch.setattr(sys, "stderr", stream)
    fresh_process()
    device_module._notice_build("kernels.lookup", "cpu")
    assert stream.getvalue() == ""
    stream.terminal = True
    fresh_process()
    with device_module.kernel_build_notice(lambda cache: None):
        device_module._notice_build("kernels.synthesis", "cpu")
    assert stream.getvalue() == ""
    device_module._notice_build("kernels.bake", "cpu")
    device_module._notice_build("kernels.surface", "cpu")
    assert stream.getvalue() == (f"warptex: Warp is building the kernels into {tmp_path} "
                                 "(once for this version, about half a minute)\n")
    stream.close()
    fresh_process()
    device_module._notice_build("kernels.kopf", "cpu")  # a closed stderr: nowhere to say it


@pytest.mark.parametrize("damage", ["object file", "metadata"])
def test_a_damaged_kernel_build_is_built_again_with_a_warning(tmp_path, damage):
    """Warp alone fails on such a build in every later run, until someone deletes it."""
    script = tmp_path / "doubling.py"
    script.write_text(_DOUBLING)
    env = {**os.environ, "WARP_CACHE_PATH": str(tmp_path / "kernels")}

    def run() -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                              env=env, timeout=300)

    first = run()
    assert first.returncode == 0, first.stderr
    assert first.stdout.strip() == "[0.0, 2.0, 4.0]"
    suffix = ".o" if damage == "object file" else ".meta"
    (built,) = (tmp_path / "kernels").rglob(f"wp___main__*/*{suffix}")
    built.write_bytes(built.read_bytes()[:100])
    healed = run()
    assert healed.returncode == 0, healed.stderr
    assert healed.stdout.strip() == "[0.0, 2.0, 4.0]"
    assert "damaged build of __main__" in healed.stderr
    again = run()
    assert again.returncode == 0 and "damaged" not in again.stderr
    assert again.stdout.strip() == "[0.0, 2.0, 4.0]"


def test_an_unloadable_kernel_build_is_a_clear_error(tmp_path, monkeypatch, warp_device):
    """When building again does not help (a full disk, say), the error names the folder."""
    calls = []

    def failing_launch(kernel, *args, **kwargs):
        calls.append(kernel)
        raise Exception("Failed to load CPU module 'kernels.lookup' (device='cpu')")

    monkeypatch.setattr(wp, "launch", failing_launch)
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    from kernels import lookup

    monkeypatch.setattr(device_module, "_REBUILT", set())
    refusal = f"kernels of kernels.lookup.*{tmp_path}.*WARP_CACHE_PATH"
    with (pytest.warns(UserWarning, match="damaged build of kernels.lookup"),
          pytest.raises(device_module.KernelCacheError, match=refusal)):
        device_module.launch(lookup.insert_keys, 1, [], [])
    assert len(calls) == 2


@pytest.mark.parametrize("error", [
    OSError(errno.EROFS, "Read-only file system", "/cache/wp_kernels.lookup_1234567_p1_t2"),
    PermissionError(errno.EACCES, "Permission denied", "/cache/wp_kernels.lookup_1234567"),
    OSError(errno.ENOSPC, "No space left on device")])
def test_a_kernel_cache_that_cannot_take_a_build_is_a_clear_error(tmp_path, monkeypatch,
                                                                  warp_device, error):
    """A read-only folder, another user's or a full disk: Warp's OSError named a build
    folder, if any, and not the variable that picks another."""
    calls = []

    def failing_launch(kernel, *args, **kwargs):
        calls.append(kernel)
        raise error

    monkeypatch.setattr(wp, "launch", failing_launch)
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    monkeypatch.setattr(device_module, "_REBUILT", set())
    from kernels import lookup

    refusal = (f"kernels of kernels.lookup in {tmp_path} \\({error.strerror}\\); set "
               "WARP_CACHE_PATH to another folder")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no damaged build: nothing deleted
        with pytest.raises(device_module.KernelCacheError, match=refusal):
            device_module.launch(lookup.insert_keys, 1, [], [])
    assert len(calls) == 1


def test_a_module_is_built_again_once_per_process(tmp_path, monkeypatch, warp_device):
    """On CUDA a full GPU memory or an old driver fails the load too: every launch deleted
    the module's builds (other processes' too) and built it again, for tens of seconds."""
    calls, dropped = [], []

    def failing_launch(kernel, *args, **kwargs):
        calls.append(kernel)
        raise Exception("Failed to load CUDA module 'kernels.lookup' (device='cuda:0')")

    monkeypatch.setattr(wp, "launch", failing_launch)
    monkeypatch.setattr(device_module, "_REBUILT", set())
    monkeypatch.setattr(device_module, "_drop_builds",
                        lambda module: dropped.append(module) or [])
    from kernels import lookup

    refusal = "WARP_CACHE_PATH to another folder; the CUDA driver may also refuse it"
    with pytest.warns(UserWarning, match="damaged build"), pytest.raises(RuntimeError,
                                                                         match=refusal):
        device_module.launch(lookup.insert_keys, 1, [], [])
    for _ in range(2):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(RuntimeError, match=refusal):
                device_module.launch(lookup.insert_keys, 1, [], [])
    assert len(calls) == 4 and len(dropped) == 1


_DELETED_WHILE_LOADED = """
import shutil
from warp._src.context import Module

compile_ = Module._compile


def deleted_by_another_process(self, device, module_dir, *args, **kwargs):
    compiled = compile_(self, device, module_dir, *args, **kwargs)
    Module._compile = compile_
    shutil.rmtree(module_dir)  # it found the build damaged
    return compiled


Module._compile = deleted_by_another_process
"""


def test_a_build_deleted_while_warp_loads_it_is_built_again_quietly(tmp_path):
    """Another process that found a build damaged deletes it: this one, which found it
    whole a moment before (Warp's ``_compile``, which builds a module only if its folder
    is missing), misses its files. It builds the module again without warning of damage;
    Warp alone fails."""
    from warp._src.context import Module

    assert hasattr(Module, "_compile"), "this Warp builds modules otherwise: test anew"
    script = tmp_path / "doubling.py"
    script.write_text(_DOUBLING.replace("init_warp()\n", "init_warp()\n" + _DELETED_WHILE_LOADED))
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                         env={**os.environ, "WARP_CACHE_PATH": str(tmp_path / "kernels")},
                         timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[0.0, 2.0, 4.0]"
    assert "damaged" not in run.stderr


def _kernel_cache(folder, loaded: list[str]) -> dict[str, object]:
    """A kernel cache holding this warptex's builds ``loaded``, a build of other code of one
    of its modules, a build and a deletion left unfinished two hours ago, a build and a
    deletion in progress, and builds of another program's modules."""
    for name in loaded:
        (folder / name).mkdir()
    other = folder / "wp_kernels.synthesis_0000000"
    other.mkdir()
    (other / "wp_kernels.synthesis_0000000.o").write_bytes(b"x" * 100)
    dead = folder / "wp_kernels.lookup_1234567_p1_t2"
    dead.mkdir()
    two_hours_ago = time.time() - 7200
    os.utime(dead, (two_hours_ago, two_hours_ago))
    abandoned = folder / ".deleting-wp_kernels.synthesis_7654321-999"
    abandoned.mkdir()
    (abandoned / "wp_kernels.synthesis_7654321.o").write_bytes(b"x" * 50)
    os.utime(abandoned, (two_hours_ago, two_hours_ago))
    building = folder / "wp_kernels.lookup_1234567_p3_t4"
    deleting = folder / ".deleting-wp_kernels.synthesis_7654321-998"
    foreign = [folder / "wp_other.kernels_0000000", folder / "wp_kernelsx.synthesis_0000000",
               folder / ".deleting-wp_other.kernels_0000000-5"]
    for f in [building, deleting, *foreign]:
        f.mkdir()
    os.utime(foreign[2], (two_hours_ago, two_hours_ago))
    return {"other": other, "dead": dead, "abandoned": abandoned, "building": building,
            "deleting": deleting, "foreign": foreign}


def test_stale_kernel_builds_are_other_code_and_dead_builds(granite_32, tmp_path, monkeypatch):
    """Every build this process loaded is kept; a build of other code of warptex's kernel
    modules and a build or deletion left unfinished an hour ago are stale; nothing else is
    touched."""
    from warptex.candidates import precompute
    from warptex.synthesis import Synthesizer

    Synthesizer(precompute(granite_32), seed=0).box((0, 0, 0), (4, 4, 4))
    loaded = [f"wp_{name}_{e.module_hash.hex()[:7]}" for name in device_module.kernel_modules()
              for e in wp.get_module(name).execs.values()]
    assert any(name.startswith("wp_kernels.synthesis_") for name in loaded)
    assert not {f.name for f in device_module.stale_kernel_builds()} & set(loaded)

    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    made = _kernel_cache(tmp_path, loaded)
    stale = [made["abandoned"], made["dead"], made["other"]]
    assert device_module.stale_kernel_builds() == stale
    assert device_module.delete_kernel_builds(stale) == (3, 150, [])
    kept = ({tmp_path / name for name in loaded}
            | {made["building"], made["deleting"], *made["foreign"]})
    assert set(tmp_path.iterdir()) == kept
    assert device_module.stale_kernel_builds() == []


def test_builds_of_other_warp_versions_are_stale_and_nothing_else_beside_them(tmp_path,
                                                                             monkeypatch):
    """Warp keeps each version's builds in a folder of its own inside WARP_CACHE_PATH: after
    an upgrade of Warp, warptex's builds in the old version's folder were never listed or
    pruned. Only warptex's builds in folders named as versions are."""
    device_module.init_warp()  # which names the folder after the version once, at start
    current = tmp_path / wp.config.version
    current.mkdir()
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(current))
    old = tmp_path / "1.7.2"
    notes = tmp_path / "notes"
    for folder in (old, notes):
        folder.mkdir()
        for name in ("wp_kernels.lookup_89abcde", "wp_other.kernels_0000000"):
            (folder / name).mkdir()
    (tmp_path / "1.7.1").write_text("a file named as a version")
    assert device_module.stale_kernel_builds() == [old / "wp_kernels.lookup_89abcde"]
    # Another user's version folder, unreadable here, is left alone, not an error.
    unreadable = tmp_path / "1.8.0"
    unreadable.mkdir()
    listing = Path.iterdir

    def iterdir(path):
        if path == unreadable:
            raise PermissionError(13, "Permission denied", str(path))
        return listing(path)

    monkeypatch.setattr(Path, "iterdir", iterdir)
    assert device_module.stale_kernel_builds() == [old / "wp_kernels.lookup_89abcde"]
    # A cache folder not named as Warp's version has no siblings of other versions.
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(notes))
    assert device_module.stale_kernel_builds() == [notes / "wp_kernels.lookup_89abcde"]


def test_cache_command_lists_and_prunes_stale_kernel_builds(tmp_path, monkeypatch, capsys):
    from warptex.cli import main

    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path / "candidates"))
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    made = _kernel_cache(tmp_path, [])
    assert main(["cache"]) == 0
    out = capsys.readouterr().out
    assert "of which 3 kernel builds of other warptex or Warp versions or left unfinished" in out
    assert all(made[k].is_dir() for k in ("other", "dead", "abandoned"))  # listing deletes nothing
    assert main(["cache", "--prune"]) == 0
    assert "deleted: 3 kernel builds" in capsys.readouterr().out
    assert not any(made[k].exists() for k in ("other", "dead", "abandoned"))
    assert made["building"].is_dir() and made["deleting"].is_dir()
    assert all(f.is_dir() for f in made["foreign"])


def test_an_engine_on_the_default_device_names_the_variable_not_an_argument(gpus, monkeypatch):
    from warptex.synthesis import engine_device

    gpus(0)
    monkeypatch.setenv("WARPTEX_DEVICE", "gpu")
    with pytest.raises(ValueError, match=r"^WARPTEX_DEVICE='gpu' is not valid"):
        engine_device(None)
    monkeypatch.setenv("WARPTEX_DEVICE", "cuda")
    with pytest.raises(RuntimeError, match=r"^WARPTEX_DEVICE=cuda but Warp sees no CUDA device"):
        engine_device(None)
    with pytest.raises(ValueError, match=r"^device must be a Warp device .* got 'gpu'"):
        engine_device("gpu")
