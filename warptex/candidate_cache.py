"""The candidate cache folder (``WARPTEX_CACHE``): what its files hold, and which of them no
run of this warptex will ever read again.

A cache file is named by its exemplars' content, the parameters and the code that computed
it (:func:`warptex.candidates.cache_file_name`), so the files of other warptex versions are
never served, and no run removes them either: they stay until pruned here (``warptex
cache --prune``). Only files named like cache files are looked at; a folder shared with
other tools keeps their files.
"""

from __future__ import annotations

import errno
import os
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from tqdm.auto import tqdm

from warptex.archive import UNFINISHED_AGE, archive_version, dead_link, is_temporary
from warptex.candidate_set import (
    DEFAULT_PARAMS,
    FILE_MAGIC,
    FORMAT_VERSION,
    CandidateCacheError,
    read_cache_meta,
)
from warptex.candidates import CACHE_PREFIX, CACHE_SUFFIX, cache_dir, cache_file_name, computed_here

IN_USE = "in use"  # read by this warptex when its exemplars and parameters come up
OTHER_VERSION = "other version"  # written by other warptex code (or renamed): never read
DAMAGED = "damaged"  # truncated, corrupt or not a candidate file: recomputed, never read
UNFINISHED = "unfinished"  # the temporary file of a write that never finished
BEING_WRITTEN = "being written"  # a temporary file young enough to be another run's write
UNREADABLE = "unreadable"  # cannot be read here (permissions, a folder): left alone
STATUSES = (IN_USE, OTHER_VERSION, DAMAGED, UNFINISHED, BEING_WRITTEN, UNREADABLE)
# What ``--prune`` deletes: files no run of this warptex reads, now or later.
NEVER_READ = (OTHER_VERSION, DAMAGED, UNFINISHED)


@dataclass(frozen=True)
class CacheFile:
    """One file of the candidate cache folder."""

    path: Path
    size: int  # bytes
    modified: float  # seconds since the epoch
    status: str  # one of STATUSES
    names: tuple[str, ...] = ()  # the exemplars (x, y, z) as named when computed, if recorded
    settings: dict = field(default_factory=dict)  # its parameters that are not the defaults
    # Inode, modification time (ns) and size when listed: a file replaced since (a damaged
    # one recomputed by another run) is not the file judged, and is not deleted.
    identity: tuple[int, int, int] = (0, 0, 0)


def cache_files(folder: Path | None = None, progress: bool = False) -> list[CacheFile]:
    """The cache files in ``folder`` (default: :func:`warptex.candidates.cache_dir`), oldest
    first; none for a folder that does not exist yet. Each file is read whole (its checksum
    tells a damaged one), seconds for a large cache: ``progress`` shows a bar then.

    Raises:
        NotADirectoryError: ``folder`` is a file.
        OSError: the folder or one of its cache files cannot be read, or it is a link that
            leads nowhere (to a missing folder, or a loop), where no file can be cached.
    """
    folder = cache_dir() if folder is None else Path(folder)
    if not folder.exists():
        dead = dead_link(folder)
        if dead is not None:
            raise FileNotFoundError(errno.ENOENT, dead, str(folder))
        return []
    if not folder.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "not a folder", str(folder))
    now = time.time()
    found = []
    for path in tqdm(list(folder.iterdir()), desc="reading the cache", unit="file",
                     disable=not progress, delay=1.0, leave=False):
        cached = path.name.startswith(CACHE_PREFIX) and path.name.endswith(CACHE_SUFFIX)
        if not cached and not is_temporary(path.name, CACHE_PREFIX, CACHE_SUFFIX):
            continue
        try:
            info = path.stat()
            if cached:
                status, meta = _status(path)
            else:
                old = now - info.st_mtime > UNFINISHED_AGE
                status, meta = (UNFINISHED if old else BEING_WRITTEN), {}
        except FileNotFoundError:  # renamed into place or pruned by another run meanwhile
            continue
        except OSError as error:
            try:  # a link no run can follow either (in a loop, through a file or a closed
                info = path.lstat()  # folder): listed as it is
            except FileNotFoundError:
                continue
            except OSError:  # a folder that cannot be searched: none of its files can be
                raise error from None
            status, meta = UNREADABLE, {}
        names = tuple(str(n) for n in meta.get("names", ()))
        params = meta.get("params")
        settings = ({k: v for k, v in params.items() if DEFAULT_PARAMS.get(k) != v}
                    if isinstance(params, dict) else {})
        found.append(CacheFile(path, info.st_size, info.st_mtime, status, names, settings,
                               _identity(info)))
    return sorted(found, key=lambda f: (f.modified, f.path.name))


def remove(files: Iterable[CacheFile]) -> tuple[int, int, list[OSError]]:
    """Delete ``files`` that are still as listed (those gone or replaced since are left):
    how many were deleted, their bytes, and the errors of those that could not be (another
    user's file, say), each tried whatever the others did."""
    count = freed = 0
    failed = []
    for file in files:
        try:
            if _identity(file.path.stat()) != file.identity:
                continue
            file.path.unlink()
        except FileNotFoundError:  # pruned by another run meanwhile
            continue
        except OSError as error:
            failed.append(error)
            continue
        count += 1
        freed += file.size
    return count, freed, failed


def _identity(info: os.stat_result) -> tuple[int, int, int]:
    return info.st_ino, info.st_mtime_ns, info.st_size


def _status(path: Path) -> tuple[str, dict]:
    """The file's status, and what it says it holds (:func:`read_cache_meta`) where it can
    be read."""
    try:
        version = archive_version(path, FILE_MAGIC)
    except FileNotFoundError:
        raise
    except OSError:  # another user's file in a shared folder, or a folder of that name
        return UNREADABLE, {}
    if version is None:
        return DAMAGED, {}
    if version != FORMAT_VERSION:
        try:  # what it was computed for, where that version recorded it as this one does
            names = read_cache_meta(path, version).get("names")
        except CandidateCacheError:
            names = None
        return OTHER_VERSION, {"names": names} if isinstance(names, list) else {}
    try:
        meta = read_cache_meta(path)
    except CandidateCacheError:
        return DAMAGED, {}
    current = (path.name == cache_file_name(meta["digests"], meta["params"])
               and computed_here(meta))
    return (IN_USE if current else OTHER_VERSION), meta
