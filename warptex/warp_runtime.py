"""Choice of the Warp device that synthesis runs on, one-time quiet Warp start-up, and
launches that survive a damaged kernel cache, name one that cannot take a build, and say
when they are about to build."""

from __future__ import annotations

import contextlib
import functools
import importlib
import json
import os
import pkgutil
import re
import shutil
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any

import warp as wp

from warptex.archive import UNFINISHED_AGE
from warptex.float_env import ieee_arithmetic

_ENV = "WARPTEX_DEVICE"
_CHOICES = ("cpu", "cuda")
_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"
_START_LOCK = threading.Lock()
# CUDA's default memory pool hands its free memory back to the driver at every
# synchronization (release threshold 0), and the engine reads each level's results back
# before it allocates the next level's arrays, so these would be mapped afresh every
# time: tens of milliseconds a GiB (rapidsai/rmm#2510, NVIDIA/cuda-python#771). Warp keeps
# CUDA's default; this share of each GPU's memory stays pooled instead, unless the
# threshold was set to another value (a 0 set on purpose cannot be told from the default).
POOL_KEPT = 0.25


@functools.cache
def init_warp() -> None:
    """Initialise Warp once, without its start-up banner.

    The kernel cache goes to ``WARP_CACHE_PATH`` when that is set, so tests and CI can keep
    compiled kernels in a known project-local folder; it is read as ``WARPTEX_CACHE`` is,
    an empty one unset and ``~`` the home folder. Each GPU's memory pool keeps up to
    ``POOL_KEPT`` of its memory between requests.
    """
    # functools.cache does not lock: two threads' first calls may both get here, and the
    # capture below swaps the process's file descriptor 2.
    with _START_LOCK:
        cache = os.environ.get("WARP_CACHE_PATH")
        if cache == "":  # which Warp takes for the working folder, building kernels into it
            del os.environ["WARP_CACHE_PATH"]
        elif cache and wp.config.kernel_cache_dir is None:
            wp.config.kernel_cache_dir = str(Path(cache).expanduser())
        # Warp replaced ``config.quiet`` with ``config.log_level`` in 1.10; honour both.
        if hasattr(wp.config, "log_level"):
            wp.config.log_level = wp.LOG_WARNING
        else:
            wp.config.quiet = True
        if _requested() == "cuda":
            wp.init()  # a user who asked for CUDA wants to know why it is missing
        else:
            _init_without_driver_warning()
        for gpu in wp.get_cuda_devices():
            # A pool that refuses keeps CUDA's default: slower, never wrong.
            with contextlib.suppress(RuntimeError):
                if gpu.is_mempool_enabled and wp.get_mempool_release_threshold(gpu) == 0:
                    wp.set_mempool_release_threshold(gpu, POOL_KEPT)


def _init_without_driver_warning() -> None:
    """``wp.init()`` without Warp's native warning that no CUDA driver was found.

    Without an NVIDIA GPU the CPU is the expected device, and the warning, written by
    Warp's library straight to file descriptor 2 at every start, would interrupt every
    command's output (in the middle of progress bars, once per worker process). All
    else Warp writes while starting is passed on. Where there is no stderr to capture
    (closed, or none at all), or nowhere to capture it (no temporary folder writable),
    Warp starts as it would: its warning shown is the lesser harm.
    """
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (AttributeError, OSError, ValueError):
        wp.init()
        return
    captured = _capture_file()
    if captured is None:
        os.close(saved)
        wp.init()
        return
    try:
        with captured:
            os.dup2(captured.fileno(), 2)
            try:
                wp.init()
            finally:
                os.dup2(saved, 2)
                captured.seek(0)
                lines = captured.read().decode(errors="replace").splitlines(keepends=True)
                sys.stderr.write("".join(line for line in lines if _NO_DRIVER not in line))
    finally:
        os.close(saved)


def _capture_file() -> IO[bytes] | None:
    """A temporary file to capture Warp's start-up output in; None where no temporary
    folder is writable, which is no fault of the kernel cache's that wp.init() reports."""
    try:
        return tempfile.TemporaryFile()
    except OSError:
        return None


def _requested() -> str:
    return os.environ.get(_ENV, "").strip().lower()


def device() -> str:
    """Return ``"cuda"`` when Warp sees a GPU, else ``"cpu"``; ``WARPTEX_DEVICE`` overrides.

    Raises:
        ValueError: ``WARPTEX_DEVICE`` is set to something other than ``cpu`` or ``cuda``.
        RuntimeError: ``WARPTEX_DEVICE=cuda`` but Warp sees no CUDA device.
    """
    requested = _requested()
    if requested and requested not in _CHOICES:
        raise ValueError(
            f"{_ENV}={os.environ[_ENV]!r} is not valid; use one of: {', '.join(_CHOICES)}"
        )
    if requested == "cpu":
        return "cpu"
    init_warp()
    has_gpu = wp.get_cuda_device_count() > 0
    if requested == "cuda" and not has_gpu:
        raise RuntimeError(f"{_ENV}=cuda but Warp sees no CUDA device")
    return "cuda" if has_gpu else "cpu"


class KernelCacheError(RuntimeError):
    """Warp's kernel cache cannot take or load a build of warptex's kernels: the machine's
    fault, not the input's, which the command reports in one line naming the folder."""


def launch(kernel: wp.Kernel, dim: int, inputs: Sequence, outputs: Sequence = (), *,
           device: str = "cpu") -> None:
    """``wp.launch``, except that a damaged build of the kernel's module in Warp's kernel
    cache (a truncated object file or metadata, after a full disk or a copy cut short) is
    deleted, with a warning, and built again, once; Warp itself would fail on it forever.
    A build that vanishes while Warp loads it, deleted so by another process, is built
    again too, quietly.

    A module is built again once per process and device: a failure after that is no
    damaged file but the machine's (a full disk; on CUDA also a full GPU memory or an older
    driver), and deleting builds then would cost every launch a rebuild and other processes
    theirs.

    Raises:
        KernelCacheError: the module cannot be built into the kernel cache (a read-only
            folder, another user's, a full disk), or built again cannot be loaded either.
    """
    module = kernel.module.name
    if (module, str(device)) not in _LAUNCHED:
        _notice_build(module, str(device))
    for again in (False, True):
        try:
            # A CPU kernel runs on this thread, in its floating-point mode (float_env).
            with ieee_arithmetic() if str(device) == "cpu" else contextlib.nullcontext():
                wp.launch(kernel, dim, list(inputs), list(outputs), device=device)
            return
        except FileNotFoundError as error:
            if again:
                raise _build_failure(module, error) from None
            # Warp found the build, then its files were gone: Warp now builds it again.
        except OSError as error:
            raise _build_failure(module, error) from None
        except Exception as error:
            if not _unloadable(error):
                raise
            if again or (module, str(device)) in _REBUILT:
                raise _load_failure(module, error) from None
            _REBUILT.add((module, str(device)))
            folders = _drop_builds(kernel.module)
            warnings.warn(f"Warp's kernel cache held a damaged build of {module} ({error}); "
                          f"deleted {', '.join(folders) or 'nothing'}, building it again",
                          stacklevel=2)


# Warp modules built again by :func:`launch` in this process, and for which device.
_REBUILT: set[tuple[str, str]] = set()


@contextlib.contextmanager
def kernel_build_notice(notice: Callable[[Path], None]) -> Iterator[None]:
    """Within the block, ``notice(folder)`` is called once, just before the first launch
    that has Warp build one of warptex's kernel modules into its kernel cache ``folder``:
    the pause of a first use (README, "first use") is explained when it comes, and a
    command that ends before any launch (a refused input) says nothing of it. Outside
    such blocks (a script, a Mitsuba scene) :func:`say_kernel_build` is the notice, given
    once and only on a terminal, as ``precompute``'s bars are shown (a block ending before
    it was given leaves it to come after)."""
    with _NOTICE_LOCK:  # launches on other threads may be taking the notice meanwhile
        outside = _BUILD_NOTICE[:]
        _BUILD_NOTICE[:] = [notice]
    try:
        yield
    finally:
        with _NOTICE_LOCK:
            _BUILD_NOTICE[:] = outside


def say_kernel_build(cache: Path) -> None:
    """Say why warptex's first use on a machine pauses, as the pause begins: no bar moves
    while Warp builds the kernels into its kernel cache, once a version. Written as tqdm
    writes, so that a bar being drawn on a terminal is drawn again below."""
    from tqdm.auto import tqdm

    tqdm.write(f"warptex: Warp is building the kernels into {cache} (once for this version, "
               "about half a minute)", file=sys.stderr)


def _say_kernel_build_on_a_terminal(cache: Path) -> None:
    """:func:`say_kernel_build` where stderr is a terminal: a script's or a renderer's log
    keeps its own lines."""
    try:
        shown = sys.stderr is not None and sys.stderr.isatty()
    except ValueError:  # closed
        shown = False
    if shown:
        say_kernel_build(cache)


# The notice until it is given (kernel_build_notice's, else the terminal's), and the
# (module, device) pairs launched in this process: loaded since, or their failure kept by
# Warp, so that Warp builds them no more whatever the kernel cache holds now (launch's
# rebuild warns itself).
_BUILD_NOTICE: list[Callable[[Path], None]] = [_say_kernel_build_on_a_terminal]
_LAUNCHED: set[tuple[str, str]] = set()
_NOTICE_LOCK = threading.Lock()


def _notice_build(module: str, device: str) -> None:
    with _NOTICE_LOCK:  # launches of split ranges start on several threads at once
        if (module, device) in _LAUNCHED:
            return
        _LAUNCHED.add((module, device))
        if not _BUILD_NOTICE:
            return
        folder = build_folder(module, cpu=device == "cpu")
        # os.path.isdir: a folder that cannot be searched (another user's) is no build
        # found; the launch then names the folder (KernelCacheError), not a traceback.
        if folder is None or os.path.isdir(folder):
            return
        notice = _BUILD_NOTICE.pop()
    notice(folder.parent)


def _build_failure(module: str, error: OSError) -> KernelCacheError:
    """The error of a module that Warp cannot build into its kernel cache."""
    return KernelCacheError(
        f"Warp cannot build the kernels of {module} in {wp.config.kernel_cache_dir} "
        f"({error.strerror or error}); set WARP_CACHE_PATH to another folder")


def _load_failure(module: str, error: Exception) -> KernelCacheError:
    """The error of a module that Warp cannot load though built afresh."""
    cuda = ("; the CUDA driver may also refuse it for a full GPU memory or for being older "
            "than the CUDA compiler Warp builds with" if "CUDA" in str(error) else "")
    return KernelCacheError(
        f"Warp cannot load the kernels of {module} that it builds in "
        f"{wp.config.kernel_cache_dir} ({error}); check that the folder is writable and "
        f"its disk not full, or set WARP_CACHE_PATH to another folder{cuda}")


def _unloadable(error: Exception) -> bool:
    """Whether ``error`` is Warp failing to load a module build found in its cache."""
    return (isinstance(error, json.JSONDecodeError)
            or str(error).startswith(("Failed to load CPU module", "Failed to load CUDA module")))


def _drop_builds(module: Any) -> list[str]:
    """Delete every cached build of a Warp module (its folders are named after the module
    and a hash)."""
    cache = Path(wp.config.kernel_cache_dir)
    dropped = []
    for folder in cache.glob(f"wp_{module.name}_*"):
        # Not another module whose name continues this one's, nor a build in progress.
        build = _BUILD_FOLDER.fullmatch(folder.name)
        ours = build and build["module"] == module.name and not build["building"]
        # One that cannot be deleted is named by the error of loading it again.
        with contextlib.suppress(OSError):
            if ours and _delete_build(folder):
                dropped.append(str(folder))
    return dropped


# A build's folder: the module's name and the first digits of its code's hash; Warp builds
# in one named after the process and thread as well, then renames it to this.
_BUILD_FOLDER = re.compile(r"wp_(?P<module>[\w.]+)_[0-9a-f]{7}(?P<building>_p\d+_t\d+)?")
# The folder Warp keeps one version's builds in, inside WARP_CACHE_PATH.
_VERSION_FOLDER = re.compile(r"\d+\.\d+\.\d+[\w.+-]*")


# A build folder being deleted, named so by _delete_build; one left over an hour ago was
# left by a deletion that died.
_DOOMED_FOLDER = re.compile(r"\.deleting-(?P<build>wp_.+)-\d+")


def _delete_build(folder: Path) -> bool:
    """Delete a build folder, renamed first so that no other process loads it half-deleted;
    False when it was gone (deleted by another process).

    Raises:
        OSError: it cannot be renamed or deleted (a read-only cache).
    """
    doomed = folder
    if not _DOOMED_FOLDER.fullmatch(folder.name):
        doomed = folder.with_name(f".deleting-{folder.name}-{os.getpid()}")
        try:
            folder.rename(doomed)
        except FileNotFoundError:
            return False
    elif not folder.exists():
        return False
    # Python 3.12 renamed the handler's argument, deprecating the old name.
    handler = "onexc" if sys.version_info >= (3, 12) else "onerror"
    shutil.rmtree(doomed, **{handler: _unless_gone})
    return True


def _unless_gone(function: Any, path: str, error: BaseException | tuple) -> None:
    """rmtree's error handler: what another process deleted meanwhile is no error.
    ``error`` is the exception (``onexc``) or its ``sys.exc_info()`` (``onerror``)."""
    error = error[1] if isinstance(error, tuple) else error
    if not isinstance(error, FileNotFoundError):
        raise error


def kernel_modules() -> list[str]:
    """The names of warptex's Warp kernel modules (``kernels.*``)."""
    import kernels

    return [f"kernels.{m.name}" for m in pkgutil.iter_modules(kernels.__path__)]


def build_folder(module_name: str, cpu: bool) -> Path | None:
    """The folder of Warp's kernel cache that holds a kernel module's build of its current
    code, for CPU launches (block_dim 1) or CUDA launches (Warp's default); None for a Warp
    that names its builds otherwise."""
    init_warp()  # which settles the cache folder
    importlib.import_module(module_name)  # Warp names a build by the code of its kernels
    try:
        name = wp.get_module(module_name).get_module_identifier(block_dim=1 if cpu else None)
    except (AttributeError, TypeError):
        return None
    return Path(wp.config.kernel_cache_dir) / name


def stale_kernel_builds() -> list[Path]:
    """Folders of Warp's kernel cache that no run of this warptex loads: builds of its
    kernel modules' other code (other warptex versions; Warp never deletes them) and of
    other Warp versions (in the cache's sibling folders named by version), and builds and
    deletions of builds left unfinished over an hour ago. Empty for a Warp that names its
    builds otherwise.

    Raises:
        OSError: the cache folder exists but cannot be listed.
    """
    modules = kernel_modules()
    current = {build_folder(m, cpu) for m in modules for cpu in (True, False)}
    if None in current:
        return []
    cache = Path(wp.config.kernel_cache_dir)
    if not cache.is_dir():
        return []
    folders = sorted(cache.iterdir())
    if cache.name == wp.config.version:  # Warp's folder for its version: others beside it
        folders += _other_version_folders(cache)
    stale = []
    for folder in folders:
        doomed = _DOOMED_FOLDER.fullmatch(folder.name)
        build = _BUILD_FOLDER.fullmatch(doomed["build"] if doomed else folder.name)
        if not build or build["module"] not in modules or folder in current:
            continue
        if build["building"] or doomed:
            try:
                age = time.time() - folder.stat().st_mtime
            except OSError:  # renamed into place meanwhile
                continue
            if age < UNFINISHED_AGE:  # else left by a process that died
                continue
        stale.append(folder)
    return stale


def _other_version_folders(cache: Path) -> list[Path]:
    """What the folders of other Warp versions beside Warp's ``cache`` folder hold; one that
    cannot be listed (another user's) is left alone."""
    found = []
    try:
        others = sorted(cache.parent.iterdir())
    except OSError:
        return []
    for other in others:
        if other != cache and _VERSION_FOLDER.fullmatch(other.name) and other.is_dir():
            try:
                found += sorted(other.iterdir())
            except OSError:
                continue
    return found


def delete_kernel_builds(folders: Sequence[Path]) -> tuple[int, int, list[OSError]]:
    """Delete build folders of Warp's kernel cache: the number deleted, their bytes, and
    the errors of those that could not be (another user's read-only folder, say), each
    tried whatever the others did."""
    count = freed = 0
    failed = []
    for folder in folders:
        size = folder_bytes(folder)
        try:
            if _delete_build(folder):
                count, freed = count + 1, freed + size
        except OSError as error:
            failed.append(error)
    return count, freed, failed


def folder_bytes(folder: Path) -> int:
    """The bytes of the files under ``folder``; unreadable folders count nothing."""
    size = 0
    for parent, _, names in os.walk(folder):
        for name in names:
            with contextlib.suppress(OSError):  # removed by a build meanwhile
                size += os.stat(os.path.join(parent, name), follow_symlinks=False).st_size
    return size
