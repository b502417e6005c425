"""Choice of the Warp device that synthesis runs on, one-time quiet Warp start-up, and
launches that survive a damaged kernel cache."""

from __future__ import annotations

import functools
import json
import os
import re
import shutil
import sys
import tempfile
import threading
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import warp as wp

_ENV = "WARPTEX_DEVICE"
_CHOICES = ("cpu", "cuda")
_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"
_START_LOCK = threading.Lock()


@functools.cache
def init_warp() -> None:
    """Initialise Warp once, without its start-up banner.

    The kernel cache goes to ``WARP_CACHE_PATH`` when that is set, so tests and CI can keep
    compiled kernels in a known project-local folder.
    """
    # functools.cache does not lock: two threads' first calls may both get here, and the
    # capture below swaps the process's file descriptor 2.
    with _START_LOCK:
        cache = os.environ.get("WARP_CACHE_PATH")
        if cache and wp.config.kernel_cache_dir is None:
            wp.config.kernel_cache_dir = cache
        # Warp replaced ``config.quiet`` with ``config.log_level`` in 1.10; honour both.
        if hasattr(wp.config, "log_level"):
            wp.config.log_level = wp.LOG_WARNING
        else:
            wp.config.quiet = True
        if _requested() == "cuda":
            wp.init()  # a user who asked for CUDA wants to know why it is missing
        else:
            _init_without_driver_warning()


def _init_without_driver_warning() -> None:
    """``wp.init()`` without Warp's native warning that no CUDA driver was found.

    Without an NVIDIA GPU the CPU is the expected device, and the warning, written by
    Warp's library straight to file descriptor 2 at every start, would interrupt every
    command's output (in the middle of progress bars, once per worker process). All
    else Warp writes while starting is passed on. Where there is no stderr to capture
    (closed, or none at all), Warp starts as it would.
    """
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (AttributeError, OSError, ValueError):
        wp.init()
        return
    try:
        with tempfile.TemporaryFile() as captured:
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


def launch(kernel: Any, dim: int, inputs: Sequence, outputs: Sequence = (), *,
           device: str = "cpu") -> None:
    """``wp.launch``, except that a damaged build of the kernel's module in Warp's kernel
    cache (a truncated object file or metadata, after a full disk or a copy cut short) is
    deleted, with a warning, and built again, once; Warp itself would fail on it forever.

    Raises:
        RuntimeError: the module built again cannot be loaded either.
    """
    try:
        wp.launch(kernel, dim, list(inputs), list(outputs), device=device)
        return
    except Exception as error:
        if not _unloadable(error):
            raise
        folders = _drop_builds(kernel.module)
        warnings.warn(f"Warp's kernel cache held a damaged build of {kernel.module.name} "
                      f"({error}); deleted {', '.join(folders) or 'nothing'}, building it "
                      "again", stacklevel=2)
    try:
        wp.launch(kernel, dim, list(inputs), list(outputs), device=device)
    except Exception as error:
        if not _unloadable(error):
            raise
        raise RuntimeError(
            f"Warp cannot load the kernels of {kernel.module.name} that it builds in "
            f"{wp.config.kernel_cache_dir} ({error}); check that the folder is writable and "
            "its disk not full, or set WARP_CACHE_PATH to another folder") from None


def _unloadable(error: Exception) -> bool:
    """Whether ``error`` is Warp failing to load a module build found in its cache."""
    return (isinstance(error, json.JSONDecodeError)
            or str(error).startswith(("Failed to load CPU module", "Failed to load CUDA module")))


def _drop_builds(module: Any) -> list[str]:
    """Delete every cached build of a Warp module (its folders are named after the module
    and a hash), renamed first so that no other process loads a half-deleted one."""
    cache = Path(wp.config.kernel_cache_dir)
    prefix = f"wp_{module.name}_"
    dropped = []
    for folder in cache.glob(f"{prefix}*"):
        # Not another module whose name continues this one's, nor a build in progress
        # (Warp builds in a folder named after the process and thread, then renames it).
        if not re.fullmatch("[0-9a-f]{7}", folder.name[len(prefix):]):
            continue
        doomed = folder.with_name(f".deleting-{folder.name}-{os.getpid()}")
        try:
            folder.rename(doomed)
        except OSError:
            continue
        shutil.rmtree(doomed, ignore_errors=True)
        dropped.append(str(folder))
    return dropped
