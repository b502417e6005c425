"""Brick store files (Dong 2008, section 6.2: synthesize once, here across runs): their
format, the settings that name the texture whose voxels a file holds, the turns that saves
to one file take, and saving when work stops early.

A file holds a texture's identity, its settings in plain words (a file of another texture
is refused naming the settings that differ) and its bricks (:mod:`warptex.bricks`), least
recently used first; it is written atomically and checksummed.
"""

from __future__ import annotations

import fcntl
import functools
import json
import os
import sys
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from kernels import lookup as _k
from warptex.archive import (
    ArchiveError,
    overwrite_problem,
    read_archive,
    write_archive,
    write_failure,
)
from warptex.bricks import Bricks
from warptex.code_digest import code_digest, module_sources
from warptex.keysets import unpack
from warptex.synthesis import COORD_LIMIT, ENGINE_VERSION, Synthesizer
from warptex.thread_warnings import warn

if TYPE_CHECKING:
    from warptex.store import BrickStore


FORMAT_VERSION = 3  # 2: bricks may be partly filled; 3: only stored voxels are written
_MAGIC = b"WTXBRICK"
# The first and last bricks that voxels of the coordinates' range [-COORD_LIMIT, COORD_LIMIT)
# lie in.
_BRICK_RANGE = (-(COORD_LIMIT >> _k.BRICK_SHIFT), (COORD_LIMIT - 1) >> _k.BRICK_SHIFT)


class StoreFileError(ArchiveError):
    """A store file is damaged, of another format version, or of another texture."""


def empty_file(path: Path) -> bool:
    """Whether ``path`` is an empty file (made by mktemp, say): a place to save a store to,
    not a damaged one."""
    return path.is_file() and path.stat().st_size == 0


@contextmanager
def taking_turns(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``path``'s folder: every process's saves there take turns,
    so a merge reads the file that the previous save wrote. Where the folder cannot be
    locked (a file system without locks), saves go on without turns, as a warning says
    once a folder: two at once may then keep only the bricks of the later, which costs
    voxels synthesized again, never a wrong one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        folder = os.open(path.parent, os.O_RDONLY)
    except OSError as error:
        _without_turns(path.parent, error)
        yield
        return
    try:
        try:
            fcntl.flock(folder, fcntl.LOCK_EX)
        except OSError as error:
            _without_turns(path.parent, error)
        yield
    finally:
        os.close(folder)  # releases the lock


def _without_turns(folder: Path, error: OSError) -> None:
    """Say, once a folder, that saves there go on without turns: a render farm sharing one
    store on such a file system would lose voxels to its saves without a word."""
    if folder in _UNLOCKED:
        return
    _UNLOCKED.add(folder)
    warn(f"{folder}: brick stores saved here do not take turns, as the folder cannot be "
         f"locked ({error.strerror or error}): processes saving one store at once may each "
         "keep only their own voxels, and the others' are synthesized again when next read")


_UNLOCKED: set[Path] = set()  # the folders _without_turns spoke of


_SETTING_NAMES = {"digests": "exemplars", "params": "candidate parameters",
                  "candidates": "pre-computed candidates", "engine": "engine version",
                  "engine_code": "engine code",
                  "format": "file format", "brick": "brick size",
                  "levels": "synthesized levels", "passes": "correction passes",
                  "subpasses": "sub-passes", "shifted_tiles": "shifted tiles"}


def _differences(stored: dict, current: dict, where: str = "in the file") -> str:
    """The settings in which a store file's texture (or another texture, ``where``)
    differs from this one, in words."""
    out = []
    for name in sorted(set(stored) | set(current)):
        there, here = stored.get(name), current.get(name)
        if there != here:
            words = _SETTING_NAMES.get(name, name)
            if name not in stored:  # a file written before this setting was kept
                words += f" (not recorded {where})"
            elif name not in current:  # a file of a later warptex
                words += f" ({where}, not kept here)"
            elif isinstance(here, int | float) and isinstance(there, int | float):
                words += f" {there} {where}, {here} here"
            out.append(words)
    return ", ".join(out) or "equal settings with another identity digest"


def store_settings(synthesizer: Synthesizer) -> dict:
    """Everything a stored voxel depends on: exemplars, candidate parameters and algorithm
    version, seed, jitter, tile shifts, engine version and parameters; digested by
    :meth:`~warptex.store.BrickStore.identity` and kept in store files in plain words, so
    that a file of another texture can be told apart by the settings that differ."""
    s = synthesizer
    return {
        "format": FORMAT_VERSION,
        "candidates": s.candidates.content_digest,
        "engine": ENGINE_VERSION,
        "engine_code": _engine_code(),
        "brick": _k.BRICK,
        "digests": list(s.candidates.digests),
        "params": s.candidates.params,
        "seed": s.seed,
        "jitter": s.jitter_steps / 256,  # as the engine takes it
        "shifted_tiles": s.shifted_tiles,
        "levels": s.finest - s.start,
        "passes": s.passes,
        "subpasses": s.subpasses,
    }


@functools.cache
def _engine_code() -> str:
    """Digest of the engine's code (``warptex.code_digest``): stores of another engine's
    voxels are never reused, also where ``ENGINE_VERSION`` was not raised."""
    from kernels import common
    from kernels import synthesis as engine_kernels
    from warptex import dependencies, keysets, parallel, synthesis, warp_runtime

    # How launches are split over threads decides voxels as much as the kernels do.
    modules = (synthesis, dependencies, engine_kernels, common, keysets, parallel,
               warp_runtime)
    return code_digest(module_sources(modules), str(ENGINE_VERSION))


_engine_code()  # now: the code this process runs, even if its files are edited meanwhile


def settings_differences(other: Synthesizer, this: Synthesizer) -> str:
    """The settings in which ``other``'s stored voxels would differ from ``this``'s, in
    words; empty when they would be the same."""
    theirs, mine = store_settings(other), store_settings(this)
    return "" if theirs == mine else _differences(theirs, mine, "in the other texture")


def check_store_path(path: str | Path, saving: bool = True) -> None:
    """Raise StoreFileError if ``path`` holds a folder or a file of another kind, which
    saving a store there would destroy (or, not ``saving``, which is no store to read); a
    missing file or any brick store file is fine."""
    problem = overwrite_problem(path, _MAGIC, "brick store", ", choose another store path",
                                written=saving)
    if problem is not None:
        raise StoreFileError(f"{path}: {problem}")


def saved_if_any(store: BrickStore, path: Path | None,
                 save: Callable[[], Path | None]) -> list[Path]:
    """What a stop's save of ``store`` to ``path`` writes (``save()``'s file) where it keeps
    any work, whether the store holds voxels; a store of none (stopped before any was
    synthesized) leaves its file as it was, and says so on stderr, as a job's log would
    otherwise say nothing of it. A file of an empty store would keep no work, and be said
    to hold the voxels synthesized before stopping (:func:`saved_when_stopped`)."""
    if path is None:
        return []
    if store.stats()["voxels"] == 0:
        print(f"warptex: brick store {path} left as it was: no voxel was synthesized yet",
              file=sys.stderr)
        return []
    saved = save()
    return [] if saved is None else [saved]


@contextmanager
def saved_when_stopped(save: Callable[[], Iterable[Path] | Path | None]) -> Iterator[None]:
    """A KeyboardInterrupt in the block (Ctrl-C; the commands raise one on SIGTERM too,
    where a script of your own ends as Python does) first writes brick stores to their
    files with ``save`` (``lambda: tex.save()``, or a list of such saves' paths), then stops
    as asked: the voxels synthesized so far are kept, so the next run starts from them
    (section 6.2's synthesize-once, across runs); a stop waits for a change of the bricks
    under way to end (:class:`~warptex.store.BrickStore`). What was saved, or why nothing
    was, is said on stderr; a save that fails never takes the interrupt's place."""
    try:
        yield
    except KeyboardInterrupt:
        print(file=sys.stderr)  # below the progress line that the stop cut short
        saved_and_said(save, "stopping")
        raise


def saved_and_said(save: Callable[[], Iterable[Path] | Path | None], before: str) -> None:
    """Write brick stores with ``save`` as work ends early (``before``: "stopping"), and say
    on stderr which hold the voxels synthesized so far, or why none was saved."""
    try:
        result = save()
        saved = ([] if result is None else [result] if isinstance(result, str | os.PathLike)
                 else list(result))
    except OSError as error:  # a full disk: the file is left as it was
        print(f"warptex: brick store not saved: {write_failure(error.filename, error)}",
              file=sys.stderr)
    except ValueError as error:  # a texture without a store path; StoreFileError's kind
        print(f"warptex: brick store not saved: {error}", file=sys.stderr)
    except Exception as error:  # whatever else: named, and the stop goes on all the same
        print(f"warptex: brick store not saved: {type(error).__name__}: {error}",
              file=sys.stderr)
    else:
        for path in saved:
            # Not "saved": a file that held every voxel already is left as it was.
            print(f"warptex: brick store {path} holds the voxels synthesized before {before}: "
                  "the next run starts from them", file=sys.stderr)


def read_bricks(path: Path, identity: str, settings_json: str, dtype: np.dtype,
                pixels: np.ndarray) -> Bricks:
    """The bricks of the store file ``path``, least recently used first, after a
    StoreFileError where it is damaged, of another format version, or of another texture
    than the one of ``identity`` and settings ``settings_json`` (:func:`store_settings`):
    the differing settings are named. ``dtype`` and ``pixels`` (each exemplar's pixel count)
    are those of the store's triples, which the lookup kernels read unchecked."""
    z = read_archive(path, _MAGIC, FORMAT_VERSION, "brick store", StoreFileError)
    try:
        theirs, keys, triples = str(z["identity"]), z["keys"], z["triples"]
        valid = z["valid"]
    except KeyError as e:
        raise StoreFileError(f"{path}: unreadable brick store data ({e})") from None
    if theirs != identity:
        differences = "other exemplars, seed, jitter or synthesis parameters"
        try:  # files written before the settings were kept lack them
            stored = json.loads(str(z["settings"]))
            # Through JSON, as the file's went: tuples become lists, so equal compares equal.
            current = json.loads(settings_json)
            if isinstance(stored, dict):
                differences = _differences(stored, current)
        except (KeyError, ValueError):
            pass
        raise StoreFileError(f"{path}: written for another texture ({differences})")
    if keys.dtype != np.int64 or keys.ndim != 1:
        raise StoreFileError(f"{path}: brick keys of unexpected type or shape")
    valid = np.ascontiguousarray(valid)  # viewed as bytes
    if valid.dtype != np.uint32 or valid.shape != (len(keys), _k.VALID_WORDS):
        raise StoreFileError(f"{path}: stored-voxel bits of unexpected type or shape")
    if triples.dtype != dtype or triples.shape != (int(np.bitwise_count(valid).sum()), 3):
        raise StoreFileError(f"{path}: voxel triples of unexpected type or shape")
    # The lookup kernels read exemplar colors at these pixels and bricks at these keys:
    # a file that passed its checksum but holds others (written by hand) is refused.
    if len(triples) and (triples.min() < 0 or (triples.max(axis=0) >= pixels).any()):
        raise StoreFileError(f"{path}: voxel triples outside the exemplars")
    bricks = unpack(keys)
    if len(keys) and (len(np.unique(keys)) != len(keys) or bricks.min() < _BRICK_RANGE[0]
                      or bricks.max() > _BRICK_RANGE[1]):
        raise StoreFileError(f"{path}: repeated bricks or bricks beyond the texture range")
    return Bricks(keys, triples, valid)


def write_bricks(path: Path, identity: str, settings_json: str, bricks: Bricks) -> None:
    """Write ``bricks`` to the store file ``path`` atomically (temporary name, then rename),
    under the texture's ``identity`` and settings ``settings_json``."""
    write_archive(path, _MAGIC, FORMAT_VERSION, {"identity": np.array(identity),
                                                 "settings": np.array(settings_json),
                                                 **bricks._asdict()})
