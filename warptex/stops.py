"""Work that Ctrl-C or SIGTERM must not cut short, run to its end before they go on: a
brick store's change, the renames of files that belong together, a stop's own clean-up."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from typing import Any


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
    nothing where one raises, so it is called again."""
    raised: BaseException | None = None
    for number, handler in handlers.items():
        while True:
            try:
                signal.signal(number, handler)
                break
            except BaseException as error:  # KeyboardInterrupt, the CLI's SIGTERM
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
