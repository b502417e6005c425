"""The terminal and the log: warnings as one line, progress bars in logs, a clock that ticks
during long calls, standard streams closed or failing, and SIGTERM stopping a command as
Ctrl-C does."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, TextIO

# Imported where a bar is made, so that `warptex info` stays light.
if TYPE_CHECKING:
    from tqdm import tqdm

_TICK_SECONDS = 0.5  # how often a bar's clock is redrawn during one long call


@contextlib.contextmanager
def ticking(bar: tqdm) -> Iterator[None]:
    """Redraw ``bar`` every ``_TICK_SECONDS`` while the block runs one long call (Warp's
    CPU launches let other threads run), so that its clock shows the work going on."""
    if getattr(bar, "disable", False):
        yield
        return
    done = threading.Event()

    def tick() -> None:
        while not done.wait(_TICK_SECONDS):
            bar.refresh()

    ticker = threading.Thread(target=tick, name="warptex-bar", daemon=True)
    ticker.start()
    try:
        yield
    finally:
        done.set()
        ticker.join()


def show_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                 file: TextIO | None = None, line: str | None = None) -> None:
    """``warnings.showwarning`` for the commands: a user of the command needs the message,
    not the source line that raised it; a message that names warptex for Python's users is
    not prefixed twice."""
    print(f"warptex: warning: {str(message).removeprefix('warptex: ')}", file=sys.stderr)


_CURSOR_UP = "\x1b[A"  # what tqdm writes to go back to a bar above


class _LogLines:
    """stderr where it is no terminal (a log): a progress bar's redraws ("\\r" and the bar)
    become lines of their own instead of one line of carriage returns: its first, then at
    most one every ``_LOG_SECONDS`` unless it says it does something else (a step or phase
    that may take long), and its last."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream
        self._bar = False  # a bar is being drawn
        self._pending: str | None = None  # its last redraw, not yet written
        self._written = 0.0  # when a redraw was last written
        self._shown = ""  # the progress of the redraw last written (see _without_times)
        self._doing = ""  # what it said it was doing (see _activity)

    def write(self, text: str) -> int:
        given = len(text)
        # Bars of several threads at once are drawn on lines of their own, reached by moving
        # the cursor up: a log has no cursor, and the lines follow one another.
        text = text.replace(_CURSOR_UP, "")
        if not text:  # tqdm writes nothing at times, which must not end a bar
            return given
        if text.startswith("\r"):
            line = text[1:].rstrip(" ")
            now = time.monotonic()
            if not line:  # a bar cleared, as one that is not to be left: it has ended
                self._pending, self._bar = None, False
                return given
            if (not self._bar or now - self._written >= _LOG_SECONDS
                    or _activity(line) != self._doing):
                self._write_line(line)
                self._pending, self._written = None, now
            else:
                self._pending = line
            self._bar = True
            return given
        if self._pending is not None:
            # A bar's closing redraw repeats its last update, if written, but for the rate.
            if _without_times(self._pending) != self._shown:
                self._write_line(self._pending)
            self._pending = None
        if not (self._bar and text == "\n"):  # not the newline that ends a finished bar
            self._stream.write(text)
        self._bar = False
        return given

    def _write_line(self, line: str) -> None:
        self._stream.write(line + "\n")
        self._shown, self._doing = _without_times(line), _activity(line)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


_LOG_SECONDS = 10.0


def _without_times(line: str) -> str:
    """A bar's line without its times and rate, tqdm's last "[...]"."""
    return line.rsplit(" [", 1)[0]


def _activity(line: str) -> str:
    """What a bar's line says its command is doing: its text without counts, percentages
    and the bar itself, and the postfix tqdm puts after its times and rate ("[00:01<?,
    ?it/s, lazy: measuring]"), which a bar of its own format puts before them."""
    head, _, times = line.rpartition(" [")
    if not head:
        head, times = line, ""
    postfix = times.rstrip("]").split(", ", 2)[2:]
    head = re.sub(r"\d+%\|[^|]*\|", "", head)  # the percentage and the bar, however full
    return re.sub(r"[\d.]+[kMGTPEZY]?", "", head).replace(" ", "") + "".join(postfix)


def missing_streams_to_devnull() -> None:
    """A command started with its standard output or error closed (``2>&-``) has them as
    None in Python, which ``print`` passes over but progress bars and flushes fail on:
    they go to the null device instead. Opened now, it also takes the closed descriptor,
    which a file opened later would otherwise get, for Warp's library to write into."""
    # Each closed descriptor of 0, 1 and 2 (stdin closed too, `<&-`) is filled first: the
    # lowest free one is what the next file opened gets.
    while (held := os.open(os.devnull, os.O_RDWR)) <= 2:
        pass
    os.close(held)
    for name in ("stdout", "stderr"):
        if getattr(sys, name) is None:
            setattr(sys, name, open(os.devnull, "w"))  # noqa: SIM115 (open for the process)


def drop_unwritten_output() -> None:
    """Send what standard output still holds to the null device: the flush as Python
    exits would fail on it again, into a second message and exit code 120."""
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, sys.stdout.fileno())
    os.close(null)


class StandardOutputError(Exception):
    """Standard output that cannot be written (a full disk, a lost mount), told apart from
    the OSErrors of the command's own files, which name them."""


class _StandardOutput:
    """sys.stdout, whose failures to write raise :class:`StandardOutputError`; a reader
    gone (EPIPE) stays a BrokenPipeError, which the command ends quietly on."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        with as_standard_output_error():
            return self._stream.write(text)

    def flush(self) -> None:
        with as_standard_output_error():
            self._stream.flush()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


@contextlib.contextmanager
def as_standard_output_error() -> Iterator[None]:
    """The block's failures to write standard output as :class:`StandardOutputError`; a
    reader gone (EPIPE) stays a BrokenPipeError."""
    try:
        yield
    except BrokenPipeError:
        raise
    except OSError as error:
        raise StandardOutputError(f"standard output: {error.strerror or error}") from None


@contextlib.contextmanager
def standard_output_errors() -> Iterator[None]:
    """The block with its failures to write standard output raising
    :class:`StandardOutputError`."""
    stream = sys.stdout
    sys.stdout = _StandardOutput(stream)
    try:
        yield
    finally:
        sys.stdout = stream


@contextlib.contextmanager
def bars_as_log_lines() -> Iterator[None]:
    stream = sys.stderr
    if stream is None or stream.isatty():
        yield
        return
    sys.stderr = _LogLines(stream)
    try:
        yield
    finally:
        sys.stderr = stream


class SigtermInterrupt(KeyboardInterrupt):
    """SIGTERM, as a scheduler stops a job: raised where Ctrl-C's KeyboardInterrupt would be,
    so that the same clean-up runs (temporary files deleted, worker processes stopped).
    mitsuba_plugin.command finds its name in the text of the error Mitsuba wraps it in."""


# Set by SIGTERM: a library that wraps the SigtermInterrupt raised inside it (Mitsuba's scene
# loader gives its text only) hands on a plain KeyboardInterrupt, still a termination.
SIGTERM_RECEIVED = threading.Event()


def _raise_terminated(signum: int, frame: object) -> None:
    SIGTERM_RECEIVED.set()
    raise SigtermInterrupt


@contextlib.contextmanager
def terminated_like_interrupted() -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():  # signals go to the main one
        yield
        return
    SIGTERM_RECEIVED.clear()
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
