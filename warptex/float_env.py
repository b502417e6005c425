"""IEEE 754 arithmetic for warptex's work, whatever mode the calling thread is in.

Mitsuba's threads (and Dr.Jit's, which later run on the main thread too) compute with
denormals read as zero and results flushed to zero. Under that mode SciPy's k-d tree, built
with its default median splits, recursed without end on some exemplars' windows and ended
the process with a segmentation fault (a ``lazy_solid`` nested in a medium is built on
such a thread), and any arithmetic that meets a denormal would give other values
than the same work on another thread: the candidates and colours of a point must not
depend on who asks. Work run inside :func:`ieee_arithmetic` gets the C library's default
floating-point environment, and the caller's is restored after it; threads started inside
(SciPy's query threads) inherit the default. warptex's launch threads may have started
anywhere, so each CPU launch sets it itself (``warp_runtime.launch``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
from collections.abc import Iterator
from contextlib import contextmanager


def _default_environment() -> tuple[ctypes.CDLL, ctypes.c_void_p] | None:
    """The C library and its ``FE_DFL_ENV``, where this platform's C headers say what it
    is: ``(const fenv_t *) -1`` in glibc and musl, the ``_FE_DFL_ENV`` object on macOS."""
    try:
        if sys.platform.startswith("linux"):
            libm = ctypes.CDLL(ctypes.util.find_library("m") or "libm.so.6")
            return libm, ctypes.c_void_p(-1)
        if sys.platform == "darwin":
            libc = ctypes.CDLL(ctypes.util.find_library("c"))
            return libc, ctypes.c_void_p(ctypes.addressof(
                ctypes.c_char.in_dll(libc, "_FE_DFL_ENV")))
    except (OSError, ValueError):
        pass
    return None


_DEFAULT = _default_environment()
# Larger than fenv_t on every platform (32 bytes on x86-64 Linux, 8 on arm64).
_ENV_BYTES = 256


@contextmanager
def ieee_arithmetic() -> Iterator[None]:
    """Run the block in the default floating-point environment (denormals kept, rounding
    to nearest), restoring the caller's after it. Where the C library's environment cannot
    be reached (Windows), the block runs in the caller's."""
    if _DEFAULT is None:
        yield
        return
    lib, default = _DEFAULT
    saved = ctypes.create_string_buffer(_ENV_BYTES)
    if lib.fegetenv(saved) != 0:
        yield
        return
    lib.fesetenv(default)
    try:
        yield
    finally:
        lib.fesetenv(saved)
