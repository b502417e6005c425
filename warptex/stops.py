"""Work that Ctrl-C or SIGTERM must not cut short, run to its end before they go on: a
brick store's change, the renames of files that belong together, a stop's own clean-up.
And the ``warptex`` command's Ctrl-C before its work begins and after it has ended, which
Python would answer with a traceback or a failed exit."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any


def is_the_command() -> bool:
    """Whether this process runs the ``warptex`` command: its script, or ``python -m
    warptex``, as the interpreter was started (a process the command starts, given the
    command's arguments, was started otherwise)."""
    given = getattr(sys, "orig_argv", [])[1:]
    while given and given[0].startswith("-") and given[0] not in ("-m", "-c", "-"):
        # Options of the interpreter; -X and -W take a value apart.
        given = given[2:] if given[0] in ("-X", "-W") else given[1:]
    if given[:1] == ["-m"]:
        return given[1:2] == ["warptex"]
    return bool(given) and os.path.basename(given[0]) in ("warptex", "warptex.exe")


def quiet_while_starting() -> None:
    """As the command, a Ctrl-C while its libraries load (about a second: Warp, SciPy)
    ends it with the command's one line and exit code 130, not a traceback of the import
    under way; :func:`started` gives Ctrl-C back to Python once the command runs."""
    if (is_the_command() and threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
        signal.signal(signal.SIGINT, _interrupted_while_starting)


def started() -> None:
    """Ctrl-C raises KeyboardInterrupt again, as the command's stops expect."""
    if signal.getsignal(signal.SIGINT) is _interrupted_while_starting:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def _interrupted_while_starting(signum: int, frame: Any) -> None:
    # The process ends here, not by SystemExit: an import it cut short may catch what that
    # becomes (NumPy's C extension makes it an ImportError) and go on, or blame the
    # environment. Nothing is written before the work, so nothing is left to flush.
    with contextlib.suppress(OSError, ValueError):
        print("\nwarptex: interrupted", file=sys.stderr, flush=True)
    os._exit(130)


def stops_ignored_after_the_work() -> None:
    """As the command, once its work has ended: a Ctrl-C or SIGTERM while Python shuts down
    (a few tenths of a second: Mitsuba, Dr.Jit and Warp let go) leaves the process to end
    with the command's exit code, its files written and said to be, rather than 130 or 143
    without a word. The signals are ignored, not handled: Python puts back the
    default action of a signal it handles early in its shutdown, which the signal then
    took, killing the process."""
    if not is_the_command() or threading.current_thread() is not threading.main_thread():
        return
    for stream in (sys.stdout, sys.stderr):
        if stream is None:  # closed when the process started (`2>&-`)
            continue
        with contextlib.suppress(OSError):  # a reader gone: not this function's to report
            stream.flush()
    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, signal.SIG_IGN)


def deferred_stops() -> contextlib.AbstractContextManager[None]:
    """The block run to its end when Ctrl-C or SIGTERM comes meanwhile, which then goes
    on (see :func:`_signals_deferred`)."""
    return _signals_deferred((signal.SIGINT, signal.SIGTERM))


@contextlib.contextmanager
def _signals_deferred(signals: tuple[int, ...]) -> Iterator[None]:
    """Hold back ``signals`` whose handlers are Python's in the block, then let those that
    came go to their handlers as before. Handlers can only be set in the main thread, which
    is also the only one that they interrupt. The handlers are swapped with the signals
    blocked, and given back before any is delivered; as blocking holds them from the calling
    thread only, one sent to the process can still reach a handler between two swaps, which
    then all complete (one that raised there left the others swapped for good)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came: list[int] = []
    before = {number: handler for number in signals
              if (handler := signal.getsignal(number)) is not None}
    try:
        with blocked(signals):
            _set_handlers(dict.fromkeys(before, lambda n, _frame: came.append(n)))
        yield
    finally:
        with blocked(signals):  # those that came go on once all handlers are back
            try:
                _set_handlers(before)
            finally:  # a SIGTERM held back stays one, though a Ctrl-C came meanwhile
                for number in dict.fromkeys(came):
                    signal.raise_signal(number)


def _set_handlers(handlers: dict[int, Any]) -> None:
    """Set every one of ``handlers`` (signal: handler), then raise what a handler raised
    meanwhile: ``signal.signal`` first runs the handlers of signals that came, and sets
    nothing where one raises, so it is called again. Its own refusals (a handler it does
    not take, a thread other than the main one) come again on the next try: they are
    raised then, where retrying went on for ever."""
    raised: BaseException | None = None
    for number, handler in handlers.items():
        last: BaseException | None = None
        while True:
            try:
                signal.signal(number, handler)
                break
            except BaseException as error:  # KeyboardInterrupt, the CLI's SIGTERM
                # A handler's error comes once; two signals whose handlers both raise the
                # same TypeError or ValueError in a row are not told from a refusal.
                if isinstance(error, TypeError | ValueError) and type(error) is type(last):
                    raise
                last = error
                raised = raised or error
    if raised is not None:
        raise raised


@contextlib.contextmanager
def blocked(signals: tuple[int, ...]) -> Iterator[None]:
    """The block with ``signals`` held pending by the system, where it can."""
    if not hasattr(signal, "pthread_sigmask"):  # Windows
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, signals)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
