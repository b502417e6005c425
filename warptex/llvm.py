"""Find a libLLVM that Dr.Jit can JIT with, and pick the Mitsuba variant to use.

Mitsuba's ``llvm_*`` variants compile through Dr.Jit, which loads libLLVM at run time. LLVM 15
(Debian 12's default) aborts with ``LLVM ERROR: Cannot select ... fminimum``; LLVM 16 and newer
work. Dr.Jit reads ``DRJIT_LIBLLVM_PATH`` when its LLVM backend starts, so :func:`configure_drjit`
must run before Mitsuba is first used: ``import warptex`` does that.

Run as a script (``python warptex/llvm.py``) it prints the library found and exits 1 when there
is none; the Makefile uses that to decide whether to install ``libllvm19``, before the project's
dependencies exist, which is why this module imports only the standard library at top level.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import warnings
from pathlib import Path

MIN_LLVM_MAJOR = 16
_ENV = "DRJIT_LIBLLVM_PATH"
_SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
)
# Debian ships both spellings: libLLVM.so.19.1 (llvm >= 18) and libLLVM-17.so.1 (older). A
# lone number after ".so" is no LLVM version: Debian's /usr/lib/llvm-18/lib/libLLVM.so.1.
_NAME = re.compile(r"^libLLVM(?:-(\d+)(?:\.\d+)*\.so(?:\.\d+)*|\.so\.(\d+)(?:\.\d+)+)$")


def _major(path: str | Path) -> int | None:
    match = _NAME.match(Path(path).name)
    if match is None:
        return None
    return int(match.group(1) or match.group(2))


def find_libllvm() -> Path | None:
    """Return the newest libLLVM with major version >= 16 on this machine, or None."""
    found: list[tuple[int, str, Path]] = []
    for directory in _SEARCH_DIRS:
        for candidate in Path(directory).glob("libLLVM*.so*"):
            major = _major(candidate)
            if major is not None and major >= MIN_LLVM_MAJOR and candidate.is_file():
                found.append((major, candidate.name, candidate))
    return max(found)[2] if found else None


def configure_drjit() -> Path | None:
    """Point ``DRJIT_LIBLLVM_PATH`` at a suitable libLLVM unless the user already set it
    (and ``DRJIT_CACHE_DIR`` at the user's home where HOME is unset).

    Returns the library Dr.Jit will use, or None when no suitable one is known.
    """
    _drjit_cache_without_home()
    preset = os.environ.get(_ENV)
    if preset:
        # A user's choice is trusted unless it is no file or its name, or that of the file
        # it links to, says it is too old.
        return None if _preset_problem(preset) else Path(preset)
    library = find_libllvm()
    if library is not None:
        os.environ[_ENV] = str(library)
    return library


def _drjit_cache_without_home() -> None:
    """Dr.Jit keeps its kernels in ``$HOME/.drjit``: with HOME unset (a service, some CI
    containers) it printed a line of its own before a command's output and cached nothing.
    The user's home from the password database, as Python and Warp find it, serves instead."""
    if os.environ.get("HOME") or os.environ.get("DRJIT_CACHE_DIR"):
        return
    with contextlib.suppress(RuntimeError):  # no entry either: Dr.Jit says so, caches nothing
        os.environ["DRJIT_CACHE_DIR"] = str(Path.home() / ".drjit")


def _preset_problem(preset: str) -> str | None:
    """Why the library ``DRJIT_LIBLLVM_PATH`` names cannot serve, or None."""
    # A bare name is looked up on the library path by Dr.Jit's dlopen, not here.
    if os.sep in preset and not Path(preset).is_file():
        return f"{_ENV}={preset} names no file"
    major, named = _major(preset), preset
    if major is None and os.sep in preset:
        # An unversioned link (libLLVM.so, a -dev package's) says its version in the name
        # of the file it leads to: Debian 12's libLLVM.so leads to LLVM 15.
        named = str(Path(preset).resolve())
        major = _major(named)
    if major is not None and major < MIN_LLVM_MAJOR:
        behind = "" if named == preset else f" ({named})"
        return f"{_ENV}={preset} is libLLVM {major}{behind}, older than {MIN_LLVM_MAJOR}"
    return None


def best_mitsuba_variant() -> str:
    """Return ``"llvm_ad_rgb"`` when a suitable LLVM and that variant exist, else ``"scalar_rgb"``.

    The fallback is announced with one warning, since scalar rendering is far slower.
    """
    import mitsuba as mi

    library = configure_drjit()
    if library is not None and "llvm_ad_rgb" in mi.variants():
        return "llvm_ad_rgb"
    preset = os.environ.get(_ENV)
    if library is not None:
        reason = "this Mitsuba build has no llvm_ad_rgb variant"
    elif preset:
        reason = f"{_preset_problem(preset)} (unset it to search, or name libLLVM 16 or newer)"
    else:
        reason = f"no libLLVM >= {MIN_LLVM_MAJOR} found (install libllvm19 or set {_ENV})"
    warnings.warn(f"warptex: Mitsuba falls back to scalar_rgb: {reason}", stacklevel=2)
    return "scalar_rgb"


if __name__ == "__main__":
    _library = find_libllvm()
    print(_library if _library is not None else f"no libLLVM >= {MIN_LLVM_MAJOR} found")
    sys.exit(0 if _library is not None else 1)
