"""Files written atomically, and versioned, checksummed files of NumPy arrays.

Every single file warptex writes goes through :func:`write_atomically`, or
:func:`write_together` for files that belong together (a render's image and statistics; a
mesh with its material and texture files, both halves of a cut), then each file is renamed
into place. The candidate cache and the brick store persist through archives: a header
holds a magic string, a format version and the SHA-256 of the payload (an uncompressed
``.npz``), so a truncated, corrupt or foreign file is detected and never used, and a reader
never sees a half-written file (it is written under a temporary name, then renamed).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import io
import os
import re
import secrets
import stat
import tempfile
import time
import zipfile
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from warptex.stops import deferred_stops

_TEMPORARY = ".tmp"  # before the suffix of a file being written
_NAME_BYTES = 255  # the longest file name of Linux's and macOS's file systems
_TOKEN_BYTES = 6  # of the random part of a temporary name
_LONGEST_TAG = f"{2**22}.{'f' * 2 * _TOKEN_BYTES}"  # Linux's pids stay below 2^22
# A write renames its temporary file within seconds (:func:`write_together`); one older than
# this was left by a process that died, even on a slow shared folder.
UNFINISHED_AGE = 3600.0
_VERSION_BYTES = 4
_DIGEST_BYTES = 32


class ArchiveError(ValueError):
    """A file is unreadable, damaged, of another kind or of another format version."""


def overwritten_input(outputs: Sequence[str | Path],
                      inputs: Sequence[str | Path]) -> tuple[Path, Path] | None:
    """The first (output, input) pair of files that are one and the same file (by path,
    link or hard link): writing that output would destroy an input of the same work.
    Missing paths are no input and overwrite nothing."""
    for output in map(Path, outputs):
        for source in map(Path, inputs):
            with contextlib.suppress(OSError):
                if output.is_file() and source.is_file() and output.samefile(source):
                    return output, source
    return None


def dead_link(folder: str | Path) -> str | None:
    """What is wrong where ``folder``, or a folder above it that does not exist either, is
    a symbolic link that leads nowhere (to a missing target, an unmounted disk, or round a
    loop), so that no folder can be made there; None where none is."""
    existing = Path(folder).absolute()
    while not existing.exists():
        if existing.is_symlink():
            return f"{existing} is a symbolic link to {os.readlink(existing)}, which leads nowhere"
        existing = existing.parent
    return None


def folder_problem(folder: str | Path) -> str | None:
    """Why files cannot be written in ``folder`` (which need not exist yet:
    :func:`write_atomically` makes it), or None when they can."""
    existing = Path(folder).absolute()
    try:
        dead = dead_link(existing)
        if dead is not None:
            return f"cannot write there: {dead}"
        while not existing.exists():
            existing = existing.parent
    except OSError as error:
        return f"cannot look up {existing} ({error.strerror or error})"
    if not existing.is_dir():
        return f"cannot write, {existing} is a file, not a folder"
    try:  # a trial file: permission bits do not tell for root or special file systems
        tempfile.TemporaryFile(dir=existing).close()
    except OSError as error:
        return f"cannot write in {existing} ({error.strerror or error})"
    return None


def file_problem(path: str | Path) -> str | None:
    """Why a file cannot be written at ``path``, or None when it can."""
    try:
        # The longest temporary name it may be written under, whose stem is cut to fit.
        longest = os.fsencode(_temporary_name(Path(path), _LONGEST_TAG))
        name = os.fsencode(Path(path).name)
    except UnicodeEncodeError as error:
        return f"file name cannot be encoded ({error.reason})"
    if len(name) > _NAME_BYTES:
        return f"file name too long (over {_NAME_BYTES} bytes)"
    if len(longest) > _NAME_BYTES:
        return (f"suffix too long: the temporary name the file is written under would pass "
                f"{_NAME_BYTES} bytes")
    try:
        if stat.S_ISDIR(os.stat(path).st_mode):
            return "is a folder, expected a file name"
    except FileNotFoundError:  # to be made, through a link to nowhere too
        pass
    except OSError as error:
        # A loop of links: no file can be made there. (A file on the way: folder_problem.)
        if isinstance(error, PermissionError) or error.errno == errno.ELOOP:
            return f"cannot look up ({error.strerror or error})"
    # Where a link points, the file is written: in its target's folder, made if missing.
    return folder_problem(written_through(Path(path)).parent)


def endings(suffixes: Sequence[str]) -> str:
    """``suffixes`` as a message lists them: ".npy, .exr or .vol"."""
    *others, last = suffixes
    return f"{', '.join(others)} or {last}" if others else last


def iso_date(seconds: float | None = None) -> str:
    """The date that reports and listings write: ISO 8601 in UTC, to the second, of
    ``seconds`` since the epoch (a file's modification time), else of now."""
    when = datetime.now(UTC) if seconds is None else datetime.fromtimestamp(seconds, UTC)
    return when.strftime("%Y-%m-%dT%H:%M:%SZ")


def write_failure(where: str | Path, error: OSError) -> str:
    """How a write that failed once the work was under way (a full disk, a lost mount) is
    reported: the file ``where`` it failed, and why."""
    return f"{where}: cannot write ({error.strerror or error})"


def file_state(path: Path) -> tuple | None:
    """What tells a file apart from one renamed to its name since (as every save does):
    its device, inode, size and modification time; None when there is none."""
    try:
        st = path.stat()
    except OSError:
        return None
    return (str(path.resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def write_atomically(path: str | Path, write: Callable[[Path], None]) -> None:
    """Let ``write`` fill a temporary file beside ``path``, then rename it to ``path``:
    readers never see a partial file, and a failed write leaves nothing behind. The
    temporary name keeps the suffix, lower-cased, for writers that pick the format from it
    (Mitsuba's bitmap writer takes ``.PNG`` for an unknown format)."""
    write_together([(path, write)])


def write_together(writes: Sequence[tuple[str | Path, Callable[[Path], None]]]) -> None:
    """:func:`write_atomically` for files that belong together (an image and its
    statistics): every temporary file is written before any is renamed, so a write that
    fails (a full disk) leaves all of them as they were, never a new one beside an old,
    and no folder made for them; Ctrl-C or SIGTERM during the renames comes after the
    last. Only a rename that fails after an earlier one went through (the file's place
    taken by a folder between the check and the rename) can still leave them mixed."""
    # Random, as the pid and thread of writers in two containers sharing a folder may agree.
    tag = f"{os.getpid()}.{secrets.token_hex(_TOKEN_BYTES)}"
    staged = [(Path(path), write) for path, write in writes]
    targets = [written_through(path) for path, _ in staged]
    twice = one_file_twice([path for path, _ in staged])
    if twice is not None:
        raise ValueError(f"{twice[0]} and {twice[1]} are one file (a link to the other): "
                         "write each once")
    # Beside the file replaced, for the rename; named as asked, for writers that take the
    # format from the suffix.
    temporary = [target.with_name(_temporary_name(path, tag))
                 for (path, _), target in zip(staged, targets, strict=True)]
    current = None  # the file being written or renamed, as the caller named it
    made: list[Path] = []  # folders made here, outermost first
    done = False
    try:
        for (path, write), target, tmp in zip(staged, targets, temporary, strict=True):
            current = path
            made += [f for f in reversed([target.parent, *target.parent.parents])
                     if not f.exists()]
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                write(tmp)
            except RuntimeError as error:
                raise _library_failure(error, tmp, path) from error
            _synced(tmp, os.O_RDWR)  # writable: Windows syncs no file opened for reading
        for (path, _), target in zip(staged, targets, strict=True):
            if target.is_dir():  # refused before any file is replaced, not half way
                current = path
                raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(target))
        # A stop between two renames would leave them mixed, one before the folders are
        # synced would leave the renames to a power cut.
        with deferred_stops():
            for (path, _), target, tmp in zip(staged, targets, temporary, strict=True):
                current = path
                os.replace(tmp, target)
            done = True
            for folder in {target.parent for target in targets}:
                # The renames are kept over a power cut too; the files are written by then.
                with contextlib.suppress(OSError):  # where folders cannot be opened (Windows)
                    _synced(folder, os.O_RDONLY)
    except OSError as error:
        if error.errno is None:
            raise
        # Named after the file asked for: the temporary name means nothing to a user.
        raise type(error)(error.errno, error.strerror, str(current)) from error
    finally:
        for tmp in temporary:
            with contextlib.suppress(OSError):  # where the write failed, so may this
                tmp.unlink(missing_ok=True)
        if not done:
            for folder in reversed(made):
                with contextlib.suppress(OSError):  # not empty: another writer's files
                    folder.rmdir()


def _synced(path: Path, mode: int) -> None:
    """Have the system write ``path``'s data (a file's, or a folder's entries) to its disk,
    opened in ``mode``: renamed unsynced, a file may be found empty or cut short under its
    name after a power cut, the old one gone."""
    fd = os.open(path, mode)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _temporary_name(path: Path, tag: str) -> str:
    """The hidden name ``path`` is written under by the writer ``tag``. The stem is cut
    where the whole would be longer than a file name may be, so that a long name that fits
    can be written (it would otherwise fail only after the work); one whose suffix alone
    is too long for that is refused by :func:`file_problem`."""
    end = f".{tag}{_TEMPORARY}{path.suffix.lower()}"
    room = _NAME_BYTES - len(os.fsencode("." + end))
    stem = path.stem
    while stem and len(os.fsencode(stem)) > room:
        stem = stem[:-1]
    return f".{stem}{end}"


def _temporary_match(name: str, suffix: str) -> re.Match | None:
    """``name`` split into stem and writer tag where it is a temporary name
    (:func:`_temporary_name`) of a file ending in ``suffix``; None otherwise. The tag's
    second part is any hexadecimal, as earlier versions' thread ids were, whose leftovers
    are as dead."""
    pattern = rf"\.(?P<stem>.*)\.(?P<tag>\d+\.[0-9a-f]+){re.escape(_TEMPORARY + suffix.lower())}"
    return re.fullmatch(pattern, name, re.DOTALL)


def dead_writes(path: str | Path) -> list[Path]:
    """The temporary files of ``path`` (those :func:`write_atomically` writes it under)
    older than :data:`UNFINISHED_AGE`: left by writers that died, as a killed process
    cannot delete its own."""
    path, now = Path(path), time.time()
    found = []
    with contextlib.suppress(OSError):  # no folder: no leftovers
        for entry in os.scandir(path.parent):
            match = _temporary_match(entry.name, path.suffix)
            if match is None or entry.name != _temporary_name(path, match["tag"]):
                continue
            with contextlib.suppress(OSError):  # renamed into place or removed meanwhile
                if now - entry.stat(follow_symlinks=False).st_mtime > UNFINISHED_AGE:
                    found.append(path.parent / entry.name)
    return found


# Reasons a failed write gives that an image library's words may carry.
_WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EIO)


def _library_failure(error: RuntimeError, tmp: Path, path: Path) -> OSError:
    """A failed write of an image library (OpenEXR and Mitsuba's bitmap raise RuntimeError,
    a full disk among its causes) as the OSError of any failed write: the system's reason
    where the library's words give it, else those words, naming ``path`` instead of the
    temporary file, which means nothing to a user."""
    text = str(error)
    for code in _WRITE_ERRNOS:
        if os.strerror(code) in text:
            return OSError(code, os.strerror(code), str(path))
    return OSError(errno.EIO, text.replace(str(tmp), str(path)), str(path))


def one_file_twice(paths: Sequence[str | Path]) -> tuple[Path, Path] | None:
    """The first two of ``paths`` that writing would write as one file (the same name, or
    one a link to the other's file), which :func:`write_together` refuses; None if none."""
    places = [os.path.abspath(written_through(Path(path))) for path in paths]
    for n, place in enumerate(places):
        if place in places[:n]:
            return Path(paths[places.index(place)]), Path(paths[n])
    return None


def written_through(path: Path) -> Path:
    """The file that writing ``path`` replaces: a symbolic link's target, as ``open``
    writes through a link. Renaming onto the link itself would replace the link and leave
    its target, perhaps shared, as it was."""
    return Path(os.path.realpath(path)) if path.is_symlink() else path


def is_temporary(name: str, prefix: str, suffix: str) -> bool:
    """Whether ``name`` is one :func:`write_atomically` gives a file while writing it, of a
    file whose name starts with ``prefix`` and ends in ``suffix``: one a write that died
    may have left."""
    match = _temporary_match(name, suffix)
    return match is not None and match["stem"].startswith(prefix)


def write_archive(path: str | Path, magic: bytes, version: int,
                  arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` to ``path`` under ``magic`` and ``version``, atomically. The payload
    streams to the file as it is hashed: no copy of it is held, as a store file may take
    much of the memory that the store itself does."""
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as file:
            file.write(magic + version.to_bytes(_VERSION_BYTES, "little") + bytes(_DIGEST_BYTES))
            digest = hashlib.sha256()
            # np.savez's members, written by hand: it takes only files it can read back.
            with zipfile.ZipFile(_Hashed(file, digest), "w", allowZip64=True) as payload:
                for name, array in arrays.items():
                    with payload.open(f"{name}.npy", "w", force_zip64=True) as member:
                        np.lib.format.write_array(member, np.asanyarray(array),
                                                  allow_pickle=False)
            file.seek(len(magic) + _VERSION_BYTES)
            file.write(digest.digest())

    write_atomically(path, write)


class _Hashed:
    """A file written only forwards, adding what it is given to ``digest``. ZIP, unable to
    seek in it, streams each member and writes its sizes after it, so the bytes hashed are
    the bytes written, and the payload's offsets count from its own start, as a payload
    that was written on its own."""

    def __init__(self, file: io.BufferedWriter, digest: hashlib._Hash) -> None:
        self._file, self._digest = file, digest

    def write(self, data: bytes) -> int:
        self._digest.update(data)
        return self._file.write(data)

    def flush(self) -> None:
        self._file.flush()


def _is_foreign(path: str | Path, magic: bytes) -> bool:
    """Whether ``path`` holds something other than a ``magic`` archive, which writing one
    there would destroy: a folder, a device or pipe, or a file that starts otherwise. A
    missing path, an empty file or one cut short within the magic is not foreign.

    Raises:
        OSError: the path cannot be looked up or read.
    """
    path = Path(path)
    if not path.exists():
        return False
    if not path.is_file():
        return True
    with open(path, "rb") as file:
        head = file.read(len(magic))
    # A start of the magic alone is an archive cut short, damaged rather than another's.
    return not magic.startswith(head)


def overwrite_problem(path: str | Path, magic: bytes, kind: str,
                      advice: str = "", written: bool = True) -> str | None:
    """Why writing a ``magic`` archive, a ``kind`` file, to ``path`` would destroy what is
    there (a folder, or a file of another kind, followed by ``advice``), or why that cannot
    be told; None where it is missing or such a file already. Where the file is only to be
    read (not ``written``), a file of another kind is refused as such, without the
    overwriting that does not happen."""
    try:
        foreign = _is_foreign(path, magic)
    except OSError as e:
        return f"cannot read ({e.strerror or e})"
    if foreign and Path(path).is_dir():
        return f"is a folder, expected a {kind} file"
    if foreign:
        overwritten = "; it would be overwritten" if written else ""
        return f"exists and is not a warptex {kind} file{overwritten}{advice}"
    return None


def archive_version(path: str | Path, magic: bytes) -> int | None:
    """The format version in the header of a ``magic`` archive; None for a file too short to
    hold a header or one that starts otherwise. Only the header is read, so a whole file
    of the version is not vouched for (:func:`read_archive` checks that).

    Raises:
        OSError: the file cannot be read.
    """
    with open(_regular_file(path), "rb") as file:
        return _header_version(file.read(_header_bytes(magic)), magic)


def input_file_problem(path: Path, kind: str) -> str | None:
    """Why ``path`` cannot be read as a ``kind`` ("image file", "mesh file"), in words that follow
    it: missing (a broken link said so), not to be looked up (a folder on the way that
    cannot be searched, a link loop), a folder, or no regular file, whose reading would wait
    for a writer (a pipe); None for a regular file."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        broken = False
        with contextlib.suppress(OSError):
            broken = path.is_symlink()
        return f"{kind} not found" + (" (a broken symbolic link)" if broken else "")
    except OSError as error:
        return f"cannot look up {kind} ({error.strerror or error})"
    if stat.S_ISDIR(mode):
        return f"is a folder, expected {_with_article(kind)}"
    if not stat.S_ISREG(mode):
        return f"is not a regular file (a pipe or a device), expected {_with_article(kind)}"
    return None


def _with_article(noun: str) -> str:
    return f"{'an' if noun[0] in 'aeiou' else 'a'} {noun}"


def _regular_file(path: str | Path) -> Path:
    """``path``, or an OSError where it is no regular file: reading a pipe named like a
    cache file would wait for a writer for ever."""
    path = Path(path)
    if not stat.S_ISREG(path.stat().st_mode):
        raise OSError(errno.EINVAL, "not a regular file", str(path))
    return path


def _header_bytes(magic: bytes) -> int:
    return len(magic) + _VERSION_BYTES + _DIGEST_BYTES


def _header_version(data: bytes, magic: bytes) -> int | None:
    """The version in the header that ``data`` starts with; None if it holds no header."""
    if len(data) < _header_bytes(magic) or data[: len(magic)] != magic:
        return None
    return int.from_bytes(data[len(magic) : len(magic) + _VERSION_BYTES], "little")


def read_archive(path: str | Path, magic: bytes, version: int, kind: str,
                 error: type[ArchiveError] = ArchiveError) -> dict[str, np.ndarray]:
    """The arrays of a file written by :func:`write_archive`; ``error`` (naming the file
    and the ``kind`` of file expected) when it cannot be trusted. The file is hashed, then
    its arrays read, in parts: the arrays alone are held in memory."""
    path = Path(path)
    try:
        with open(_regular_file(path), "rb") as file:
            header = file.read(_header_bytes(magic))
            found = _header_version(header, magic)
            if found is None:
                raise error(f"{path}: not a warptex {kind} file")
            if found != version:
                raise error(f"{path}: {kind} file version {found}, expected {version}")
            if hashlib.file_digest(file, "sha256").digest() != header[-_DIGEST_BYTES:]:
                raise error(f"{path}: checksum mismatch (truncated or corrupt file)")
            file.seek(len(header))
            arrays = _arrays(file, f"{path}: unreadable {kind} data", error)
    except OSError as e:
        raise error(f"{path}: cannot read {kind} file ({e.strerror or e})") from None
    # NumPy gives the bytes of a member that is no .npy file (one another tool wrote) as is.
    loose = sorted(k for k, value in arrays.items() if not isinstance(value, np.ndarray))
    if loose:
        raise error(f"{path}: unreadable {kind} data ({loose[0]} is not an array)")
    return arrays


def _arrays(file: io.BufferedReader, unreadable: str,
            error: type[ArchiveError]) -> dict[str, np.ndarray]:
    """The members of the ``.npz`` payload that ``file`` is at the start of (ZIP finds a
    payload's offsets past a header, as in a self-extracting archive); ``error``, with the
    words ``unreadable``, where they cannot be read."""
    try:
        loaded = np.load(file, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):  # a single array's .npy
            raise ValueError("one array, not an archive of arrays")
        with loaded:
            return {k: loaded[k] for k in loaded.files}
    except (ValueError, KeyError, OSError, EOFError, zipfile.BadZipFile) as e:
        raise error(f"{unreadable} ({e})") from None
