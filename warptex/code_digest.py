"""Digests of the code that decides what a cache holds: a cache written by other code, even
under the same format version, is keyed otherwise and never served (caches are never
silently wrong), at the price of recomputing it after each change to that code. The
versions of Warp, NumPy and SciPy are part of that code: another Warp compiles the same
kernels to other instructions, and another NumPy or SciPy may sum, filter or decompose in
another order (the pyramid's filters, the PCA), either of which may round otherwise."""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Sequence
from pathlib import Path
from types import ModuleType


def module_sources(modules: Iterable[ModuleType]) -> list[Path] | None:
    """The source files of ``modules``; None where one has none (a frozen application)."""
    files = [getattr(m, "__file__", None) for m in modules]
    return None if None in files else [Path(f) for f in files]


def code_digest(sources: Sequence[Path] | None, constants: str) -> str:
    """SHA-256 of the ``sources``' bytes, of ``constants`` (values set outside them) and of
    the versions of Warp, NumPy and SciPy; of those and warptex's version where the sources
    cannot be read."""
    return _digest(sources, f"{constants} {_library_versions()}")


def _digest(sources: Sequence[Path] | None, constants: str) -> str:
    if sources is not None:
        try:
            return sources_digest(sources, constants)
        except OSError:  # listed but unreadable (a zip)
            pass
    return hashlib.sha256(f"{constants} {_package_version()}".encode()).hexdigest()


def sources_digest(paths: Sequence[Path], constants: str) -> str:
    """SHA-256 of ``constants`` and the bytes of ``paths``, in order."""
    digest = hashlib.sha256(constants.encode())
    for path in paths:
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _library_versions() -> str:
    import numpy as np
    import scipy
    import warp as wp

    return f"warp {wp.config.version} numpy {np.__version__} scipy {scipy.__version__}"


def _package_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("warptex")
    except PackageNotFoundError:
        return "unknown"


def installed_code_digest() -> str:
    """SHA-256 of every Python source of warptex, its kernels and its Mitsuba plugin, as they
    are installed: what a report names beside the version, which stays the same from one
    commit to the next."""
    import kernels
    import mitsuba_plugin
    import warptex

    roots = [Path(m.__file__).parent for m in (warptex, kernels, mitsuba_plugin)]
    files = [f for root in roots for f in sorted(root.rglob("*.py"))]
    return _digest(files, "")
