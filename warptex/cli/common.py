"""What every command refuses before any work (output and input files, numbers, memory) and
how it writes its outputs: whole or not at all, a failure naming the file."""

from __future__ import annotations

import argparse
import contextlib
import math
from collections.abc import Iterator, Sequence
from pathlib import Path

from warptex.archive import (
    endings,
    file_problem,
    file_state,
    folder_problem,
    input_file_problem,
    overwritten_input,
    write_failure,
)
from warptex.exemplar import Exemplar, file_names
from warptex.settings import names_folder
from warptex.stops import deferred_stops


class CliError(Exception):
    """A user error a command reports as ``warptex: error: ...`` with exit code 2."""

    exit_code = 2


class WorkFailed(CliError):
    """A file that could not be written or deleted once the work was under way (a full
    disk, a lost mount): the input was fine and a rerun may succeed, so the exit code is 1,
    which a script can tell apart from the 2 of input refused before any work."""

    exit_code = 1


def check_output(path: Path, formats: Sequence[str] | None = None, what: str = "the file") -> str:
    """The lower-case suffix of an output file, after checking, before any work is done,
    that it is one of ``formats`` and that the file can be written where it is asked for
    (missing folders are created then)."""
    suffix = path.suffix.lower()
    with contextlib.suppress(OSError):  # file_problem says why it cannot be looked up
        if path.is_dir():  # before its name's suffix, which a folder's need not have
            raise CliError(f"{path}: is a folder, expected a file name")
    if formats is not None and not suffix and path.name.lower() in formats:
        raise CliError(f"{path}: {what} needs a name before {path.name} (out{path.name}, say)")
    if formats is not None and suffix not in formats:
        raise CliError(f"{path}: {what} must end in {endings(formats)}")
    problem = file_problem(path)
    if problem is not None:
        raise CliError(f"{path}: {problem}")
    return suffix


_INPUT_ARGUMENTS = ("path", "exemplar", "ey", "ez", "feature_mask", "mesh", "scene")


def check_inputs_kept(args: argparse.Namespace, outputs: Sequence[Path],
                      named: Path | None = None) -> None:
    """Refuse, before any work, outputs that are one of the command's input files: -o
    naming the exemplar, or the texture an .obj comes with named like it. ``named`` is the
    output the command line names where ``outputs`` derive from it (``cut``'s second
    half), else the first of them."""
    inputs = [p for name in _INPUT_ARGUMENTS if isinstance(p := getattr(args, name, None), Path)]
    clash = overwritten_input(outputs, inputs)
    if clash is not None:
        output, source = clash
        named = outputs[0] if named is None else named
        written = "" if output == named else f" (written with {named})"
        raise CliError(f"{output}{written}: would overwrite the input {source}; choose another "
                       "output name")


def check_writable_folder(folder: Path, target: Path) -> None:
    """Raise CliError unless ``folder`` is, or can be created as, a writable folder."""
    problem = folder_problem(folder)
    if problem is not None:
        raise CliError(f"{target}: {problem}")


def file_name(text: str) -> Path:
    """An output file argument as a Path, refused where it ends in a slash: Path would drop
    the slash and write a file under the name of the folder asked for."""
    if names_folder(text):
        raise argparse.ArgumentTypeError(f"{text!r} names a folder, not a file; give a file "
                                         "name")
    return Path(text)


def folder_name(text: str) -> Path:
    """An output folder argument as a Path, refused where it is empty: Path("") names the
    working folder, where the files would land unasked."""
    if not text:
        raise argparse.ArgumentTypeError("empty folder name; give one, '.' for the working "
                                         "folder")
    return Path(text)


def input_file(text: str) -> Path:
    """A file argument to read, refused where it is empty: Path("") names the working
    folder, which the error would then name instead."""
    if not text:
        raise argparse.ArgumentTypeError("empty file name")
    return Path(text)


def check_input_file(path: Path, kind: str) -> None:
    """Refuse, naming it, a ``kind`` file ("mesh", "scene") that cannot be read
    (:func:`~warptex.archive.input_file_problem`)."""
    problem = input_file_problem(path, f"{kind} file")
    if problem is not None:
        raise CliError(f"{path}: {problem}")


def plural(n: int, noun: str) -> str:
    """``n`` and ``noun``, plural unless one: "1 channel", "3 channels"."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def check_at_least(name: str, value: int, low: int) -> None:
    if value < low:
        raise CliError(f"{name} must be at least {low}, got {value}")


def check_finite(name: str, values: Sequence[float]) -> None:
    if not all(math.isfinite(v) for v in values):
        raise CliError(f"{name} must be finite numbers, got {' '.join(map(str, values))}")


def check_kopf_size(size: int) -> None:
    from warptex.baselines.kopf import check_size

    try:
        check_size(size)
    except ValueError as error:
        raise CliError(f"--{error}") from None


def check_kopf_memory(size: int, exemplars: Sequence[Exemplar | None], copies: int = 2) -> None:
    """Refuse, before any work, a Kopf volume whose exemplars' search structures, or these
    with ``copies`` of the volume (two as Kopf works; a file's writer may hold more), would
    not fit in this machine's memory."""
    from warptex.baselines.kopf import search_bytes, working_bytes

    search = search_bytes(exemplars)
    given = [e for e in exemplars if e is not None]
    channels = given[0].features.shape[2]
    cube = copies * volume_bytes(size, channels) + working_bytes(size)
    if search >= cube:  # the photo's windows, more than the cube, are what does not fit
        check_fits(search + cube, f"{file_names(given)}: Kopf's search over its windows "
                   f"(with the {size}^3 volume)",
                   "shrink the exemplar with --exemplar-max-size")
    check_memory(size, channels, working_bytes(size) + search, copies)


def check_memory(size: int, channels: int, working: int = 0, copies: int = 2) -> None:
    """Refuse a cube of float32 ``channels`` held ``copies`` times (the volume and what
    is made of it: another method's, a file's), with ``working`` bytes besides, that would
    not fit in this machine's memory."""
    check_fits(copies * volume_bytes(size, channels) + working,
               f"--size {size}: a {size}^3 volume",
               "use a smaller --size, or `warptex slice` and the Python API for parts of it")


def volume_bytes(size: int, channels: int) -> int:
    """A float32 cube of ``channels``."""
    return 4 * channels * size**3


def check_fits(need: int, what: str, advice: str) -> None:
    """Refuse, before any work, what needs more than this machine's memory."""
    from warptex.machine import memory_problem

    problem = memory_problem(need)
    if problem is not None:
        raise CliError(f"{what} {problem}; {advice}")


# The outputs of this run renamed into place so far, for a stop's report.
WRITTEN: list[Path] = []


@contextlib.contextmanager
def writing(path: Path, *written_with: Path) -> Iterator[None]:
    """A failed write of the output ``path`` (a full disk, a lost mount) as one error that
    names it, or the file ``written_with`` it that failed; the writers are atomic, so the
    files are left as they were. The files renamed into place are noted (:data:`WRITTEN`),
    also where a stop came right after the rename, so that the stop's report names them."""
    before = {p: file_state(p) for p in (path, *written_with)}
    try:
        yield
    except OSError as error:
        # A failed rename names its target second (os.replace's filename2).
        failed = {error.filename, error.filename2}
        where = next((p for p in written_with if str(p) in failed), path)
        raise WorkFailed(write_failure(where, error)) from None
    finally:
        with deferred_stops():  # noted whole: a stop meanwhile comes after
            WRITTEN.extend(p for p, state in before.items()
                           if p.is_file() and file_state(p) != state)
