"""Warnings of one thread, captured while other threads warn on.

``warnings.catch_warnings`` swaps hooks that are the process's, and Mitsuba builds a
scene's textures on several threads: captures that overlapped lost warnings, gave them to
the wrong texture, or left a dead capture swallowing every later one. warptex's own
warnings therefore go through :func:`warn`, which hands them to the capture this thread
opened with :func:`captured` (no hook involved), and the few a library gives (Pillow's
corrupt EXIF data) are taken by :func:`library_warnings`, one thread at a time.
"""

from __future__ import annotations

import contextlib
import re
import threading
import warnings
from collections.abc import Iterator
from typing import NamedTuple


class Warned(NamedTuple):
    """A warning given while captured: what it says, and its category."""

    message: str
    category: type[Warning]


def warn(message: str, category: type[Warning] = UserWarning, stacklevel: int = 1) -> None:
    """``warnings.warn`` for warptex's warnings: to this thread's innermost
    :func:`captured` where one is open (whatever the process's filters), else to the
    process's warnings; ``stacklevel`` counts as ``warnings.warn``'s does."""
    captures = getattr(_THIS_THREAD, "captures", None)
    if captures:
        captures[-1].append(Warned(message, category))
    else:
        warnings.warn(message, category, stacklevel=stacklevel + 1)


@contextlib.contextmanager
def captured() -> Iterator[list[Warned]]:
    """The warnings :func:`warn` gives on this thread while open, each one, in order; the
    caller gives them again as it sees fit. Other threads' warnings, and libraries', are
    left as they are."""
    said: list[Warned] = []
    captures = _THIS_THREAD.__dict__.setdefault("captures", [])
    captures.append(said)
    try:
        yield said
    finally:
        captures.pop()


@contextlib.contextmanager
def library_warnings(module: str) -> Iterator[list[Warned]]:
    """The warnings the library ``module`` (``"PIL"``) gives on this thread while open,
    each one: the same words said of two files are no repeat. They pass through the
    process's hook, which only one thread swaps at a time; other threads' warnings are
    passed on to the hook found, under the process's filters as before."""
    mine = threading.get_ident()
    said: list[Warned] = []
    with _SWAPPING_HOOK:
        found = warnings.showwarning

        def show(message, category, filename, lineno, file=None, line=None):
            if threading.get_ident() == mine:
                said.append(Warned(str(message), category))
            else:
                found(message, category, filename, lineno, file, line)

        warnings.filterwarnings("always", module=rf"{re.escape(module)}(\..*)?")
        each_one = warnings.filters[0]
        warnings.showwarning = show
        try:
            yield said
        finally:
            warnings.showwarning = found
            # An "always" filter leaves no registry entry behind to invalidate; it is gone
            # already where a capture of another thread put back the filters it found.
            with contextlib.suppress(ValueError):
                warnings.filters.remove(each_one)


_THIS_THREAD = threading.local()
_SWAPPING_HOOK = threading.RLock()
