"""Warnings of one thread, captured while other threads warn on.

``warnings.catch_warnings`` swaps hooks that are the process's, and Mitsuba builds a
scene's textures on several threads: captures that overlapped lost warnings, gave them to
the wrong texture, or left a dead capture swallowing every later one. warptex's own
warnings therefore go through :func:`warn`, which hands them to the capture this thread
opened with :func:`captured` (no hook involved), and the few a library gives (Pillow's
corrupt EXIF data) are taken by :func:`library_warnings` through one shared hook that
tells threads apart. (A capture of another library's that overlaps it still swaps the
process's hook for a while: what it takes meanwhile is its own.)
"""

from __future__ import annotations

import contextlib
import re
import sys
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
    """The warnings this thread gives while open, a library ``module``'s (``"PIL"``) each
    one: the same words said of two files are no repeat. They pass through the process's
    hook, which one shared dispatcher holds while any thread has such a capture open; other
    threads' warnings are passed on to the hook it found, under the process's filters."""
    said: list[Warned] = []
    _hold_hook(module)
    captures = _THIS_THREAD.__dict__.setdefault("library", [])
    captures.append(said)
    try:
        yield said
    finally:
        captures.pop()
        _release_hook(module)


def _dispatch(message, category, filename, lineno, file=None, line=None) -> None:
    """The process's ``showwarning`` while library captures are open (and, harmlessly,
    where another's capture put it back later): to this thread's capture, else on."""
    captures = getattr(_THIS_THREAD, "library", None)
    if captures:
        captures[-1].append(Warned(str(message), category))
    else:
        _found_hook(message, category, filename, lineno, file, line)


def _hold_hook(module: str) -> None:
    global _found_hook
    with _HOOK:
        # Also where it is held already: a capture of another's (pytest's, Warp's logger)
        # may have put its own hook in meanwhile.
        if warnings.showwarning is not _dispatch:
            _found_hook = warnings.showwarning
            warnings.showwarning = _dispatch
        if _holders.get(module, 0) == 0:
            pattern = rf"{re.escape(module)}(\..*)?\Z"
            each_one = ("always", None, Warning, re.compile(pattern), 0)
            if each_one not in warnings.filters:  # else one of the user's, to be kept
                # Not through filterwarnings, which makes every module forget the words it
                # said: the plugin's words of two textures of one file would be said twice
                # or once as threads met. The library's own are forgotten, to be said again.
                warnings.filters.insert(0, each_one)
                _added_filters[module] = each_one
                _forget_said(module)
        _holders[module] = _holders.get(module, 0) + 1


def _release_hook(module: str) -> None:
    with _HOOK:
        _holders[module] -= 1
        if _holders[module] == 0:
            del _holders[module]
            added = _added_filters.pop(module, None)
            # An "always" filter leaves no said words behind to forget; it is gone already
            # where another's capture put back the filters it found.
            if added is not None:
                with contextlib.suppress(ValueError):
                    warnings.filters.remove(added)
        if not _holders and warnings.showwarning is _dispatch:
            warnings.showwarning = _found_hook


def _forget_said(module: str) -> None:
    """Empty the records of words said once (``__warningregistry__``) of ``module`` and
    its submodules, which the "default" action keeps and an "always" filter never reads."""
    for name, loaded in list(sys.modules.items()):
        if name == module or name.startswith(f"{module}."):
            registry = getattr(loaded, "__warningregistry__", None)
            if isinstance(registry, dict):
                registry.clear()


_THIS_THREAD = threading.local()
_HOOK = threading.Lock()
_found_hook = warnings.showwarning
_holders: dict[str, int] = {}  # open library captures, by module
_added_filters: dict[str, tuple] = {}
