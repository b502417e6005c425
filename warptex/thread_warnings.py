"""Warnings of one thread, captured while other threads warn on.

``warnings.catch_warnings`` swaps hooks that are the process's, and Mitsuba builds a
scene's textures on several threads: captures that overlapped lost warnings, gave them to
the wrong texture, or left a dead capture swallowing every later one. warptex's own
warnings therefore go through :func:`warn`, which hands them to the capture this thread
opened with :func:`captured` (no hook involved). The few a library gives (Pillow's
corrupt EXIF data) can only be taken through the process's hook: :func:`library_warnings`
puts in a dispatcher that tells threads apart while its captures, which take turns, are
open, so that another's capture that overlaps them (Warp's logger swaps the hook for a
while) leaves the hook as it found it.
"""

from __future__ import annotations

import contextlib
import os
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
def given_again(stacklevel: int) -> Iterator[None]:
    """warptex's warnings in the block given again, also where it raises, at the line
    ``stacklevel`` frames above the function using this: said of what that function was
    asked (its exemplars, its store, its engine), at the line that asked it."""
    caught: list[Warned] = []
    try:
        with captured() as caught:
            yield
    finally:
        for warned in caught:
            # Two frames more: this generator and contextlib's __exit__ that runs it.
            warn(warned.message, warned.category, stacklevel=stacklevel + 2)


@contextlib.contextmanager
def library_warnings(module: str) -> Iterator[list[Warned]]:
    """The warnings the library ``module`` (``"PIL"``) gives on this thread while open,
    under the process's filters, with the words it said before forgotten: the same words
    said of two files are no repeat. Such captures take turns (the library's record of
    words said is one for all threads: another's would be hidden by it). The warnings pass
    through the process's hook, which a dispatcher holds while a capture is open; it passes
    other threads' warnings, and other modules', on to the hook it found."""
    said: list[Warned] = []
    with _TAKING_TURNS:
        captures = _THIS_THREAD.__dict__.setdefault("library", [])
        captures.append((_source_folder(module), said))
        held = False
        try:
            _hold_hook(module)
            held = True
            yield said
        finally:
            captures.pop()
            if held:
                _release_hook()


def _dispatch(message, category, filename, lineno, file=None, line=None) -> None:
    """The process's ``showwarning`` while library captures are open (and, harmlessly,
    where another's capture put it back later): a library's warning to this thread's
    capture of it, others on."""
    captures = getattr(_THIS_THREAD, "library", None)
    if captures and captures[-1][0] and str(filename).startswith(captures[-1][0]):
        captures[-1][1].append(Warned(str(message), category))
    elif getattr(_THIS_THREAD, "passing_on", False):
        # Back from a hook that passes warnings on to the one it found, this one (as
        # logging.captureWarnings does): shown as Python shows them, not passed on again.
        (file or sys.stderr).write(warnings.formatwarning(message, category, filename,
                                                          lineno, line))
    else:
        _THIS_THREAD.passing_on = True
        try:
            _found_hook(message, category, filename, lineno, file, line)
        finally:
            _THIS_THREAD.passing_on = False


def _hold_hook(module: str) -> None:
    global _found_hook, _holders
    # Put in by the outermost capture only: where another's capture (Warp's logger) swapped
    # it for a while since, the hook in place now is that one's, not to be restored.
    if _holders == 0 and warnings.showwarning is not _dispatch:
        _found_hook = warnings.showwarning
        warnings.showwarning = _dispatch
    _holders += 1
    _forget_said(module)


def _release_hook() -> None:
    global _holders
    _holders -= 1
    if _holders == 0 and warnings.showwarning is _dispatch:
        warnings.showwarning = _found_hook


def _forget_said(module: str) -> None:
    """Empty the records of words said once (``__warningregistry__``, which the "default"
    action keeps) of ``module`` and its submodules."""
    for name, loaded in list(sys.modules.items()):
        if name == module or name.startswith(f"{module}."):
            registry = getattr(loaded, "__warningregistry__", None)
            if isinstance(registry, dict):
                registry.clear()


def _source_folder(module: str) -> str | None:
    """The folder of the imported package ``module``'s files, with a trailing separator;
    None where it is not imported from files."""
    file = getattr(sys.modules.get(module), "__file__", None)
    return None if file is None else os.path.join(os.path.dirname(file), "")


_THIS_THREAD = threading.local()
_TAKING_TURNS = threading.RLock()  # of library captures; one thread's may nest
_found_hook = warnings.showwarning
_holders = 0  # library captures open
