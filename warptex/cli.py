"""The ``warptex`` command line.

Each subcommand NAME has an ``_add_NAME_parser(subparsers)`` that declares its arguments and a
``_cmd_NAME(args) -> int`` that runs it; :data:`_SUBCOMMANDS` lists them.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import importlib
import itertools
import json
import math
import os
import re
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn, TextIO

import numpy as np

from warptex import __version__
from warptex.archive import (
    endings,
    file_problem,
    file_state,
    folder_problem,
    input_file_problem,
    iso_date,
    one_file_twice,
    overwritten_input,
    write_failure,
)
from warptex.exemplar import (
    Exemplar,
    ExemplarError,
    axis_triple,
    file_names,
    reencoded,
    srgb_encoded,
)
from warptex.llvm import MIN_LLVM_MAJOR
from warptex.parallel import deferred_stops
from warptex.settings import (
    DEFAULT_JITTER,
    DEFAULT_PASSES,
    FILTERS,
    MAX_SAMPLER_SEED,
    MIN_EXEMPLAR_SIZE,
    TILEABLE,
    SettingError,
    check_max_size,
    check_settings,
    names_folder,
)
from warptex.volume_files import VOLUME_FORMATS, write_image, write_volume

# Imported inside the commands that need them, so `warptex info` stays light.
if TYPE_CHECKING:
    from tqdm import tqdm

    from warptex.candidates import CandidateSet


class CliError(Exception):
    """A user error a command reports as ``warptex: error: ...`` with exit code 2."""

    exit_code = 2


class _WorkFailed(CliError):
    """A file that could not be written or deleted once the work was under way (a full
    disk, a lost mount): the input was fine and a rerun may succeed, so the exit code is 1,
    which a script can tell apart from the 2 of input refused before any work."""

    exit_code = 1


def _check_output(path: Path, formats: Sequence[str] | None = None, what: str = "the file") -> str:
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


def _check_inputs_kept(args: argparse.Namespace, outputs: Sequence[Path]) -> None:
    """Refuse, before any work, outputs that are one of the command's input files: -o
    naming the exemplar, or the texture an .obj comes with named like it."""
    inputs = [p for name in _INPUT_ARGUMENTS if isinstance(p := getattr(args, name, None), Path)]
    clash = overwritten_input(outputs, inputs)
    if clash is not None:
        output, source = clash
        written = "" if output == outputs[0] else f" (written with {outputs[0]})"
        raise CliError(f"{output}{written}: would overwrite the input {source}; choose another "
                       "output name")


def _check_writable_folder(folder: Path, target: Path) -> None:
    """Raise CliError unless ``folder`` is, or can be created as, a writable folder."""
    problem = folder_problem(folder)
    if problem is not None:
        raise CliError(f"{target}: {problem}")


def _file_name(text: str) -> Path:
    """An output file argument as a Path, refused where it ends in a slash: Path would drop
    the slash and write a file under the name of the folder asked for."""
    if names_folder(text):
        raise argparse.ArgumentTypeError(f"{text!r} names a folder, not a file; give a file "
                                         "name")
    return Path(text)


def _folder_name(text: str) -> Path:
    """An output folder argument as a Path, refused where it is empty: Path("") names the
    working folder, where the files would land unasked."""
    if not text:
        raise argparse.ArgumentTypeError("empty folder name; give one, '.' for the working "
                                         "folder")
    return Path(text)


def _input_file(text: str) -> Path:
    """A file argument to read, refused where it is empty: Path("") names the working
    folder, which the error would then name instead."""
    if not text:
        raise argparse.ArgumentTypeError("empty file name")
    return Path(text)


def _check_input_file(path: Path, kind: str) -> None:
    """Refuse, naming it, a ``kind`` file ("mesh", "scene") that cannot be read
    (:func:`~warptex.archive.input_file_problem`)."""
    problem = input_file_problem(path, f"{kind} file")
    if problem is not None:
        raise CliError(f"{path}: {problem}")


def _count(n: int, noun: str) -> str:
    """``n`` and ``noun``, plural unless one: "1 channel", "3 channels"."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _check_at_least(name: str, value: int, low: int) -> None:
    if value < low:
        raise CliError(f"{name} must be at least {low}, got {value}")


def _check_finite(name: str, values: Sequence[float]) -> None:
    if not all(math.isfinite(v) for v in values):
        raise CliError(f"{name} must be finite numbers, got {' '.join(map(str, values))}")


_EXEMPLAR_HELP = ("exemplar image: PNG, JPEG or another format Pillow reads, OpenEXR or .npy "
                  "(README, Exemplars: how channels and alpha are read)")


def _add_exemplar_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", type=_input_file, metavar="EXEMPLAR", help=_EXEMPLAR_HELP)
    _add_loading_arguments(parser)


def _add_loading_arguments(parser: argparse.ArgumentParser) -> None:
    """How exemplars are read: part of what decides the voxels, so every command that
    synthesizes offers them."""
    parser.add_argument(
        "--alpha",
        choices=("drop", "keep"),
        default="drop",
        help="drop an alpha channel (default) or keep it as a color channel",
    )
    _add_feature_arguments(parser)
    _add_max_size_argument(parser)
    _add_tileable_argument(parser)


def _add_feature_arguments(parser: argparse.ArgumentParser, advice: str = "") -> None:
    features = parser.add_mutually_exclusive_group()
    features.add_argument(
        "--feature-mask",
        type=_input_file,
        metavar="MASK",
        help="black-and-white image, the exemplar's size, marking features (pixels above half "
        f"its maximum, in its first channel); adds a feature-distance channel{advice}",
    )
    features.add_argument(
        "--feature-distance",
        action="store_const",
        const="auto",
        default=False,
        help="add a feature-distance channel from an automatic luminance threshold"
        f"{advice}",
    )


def _add_tileable_argument(parser: argparse.ArgumentParser, advice: str = "") -> None:
    parser.add_argument(
        "--tileable",
        choices=tuple(TILEABLE),
        default="auto",
        help="whether synthesis may continue the exemplar across its opposite edges: 'auto' "
        "(default) where they differ no more than neighbouring pixels do ('warptex info' "
        "says), 'yes' always (the paper's tori, for a tiling photo taken for a seam), 'no' "
        f"never (candidates keep away from every edge){advice}",
    )


_SCALE_ADVICE = (" (several with --ey/--ez). A voxel is a pixel of the shrunk image, so features "
                 "come out smaller in voxels (dividing bake's and cut's --resolution, or a "
                 "scene's scale, by the same factor keeps their size)")


def _add_max_size_argument(parser: argparse.ArgumentParser, advice: str = _SCALE_ADVICE) -> None:
    parser.add_argument(
        "--exemplar-max-size",
        type=int,
        metavar="PIXELS",
        help="shrink larger exemplars (area-averaged, aspect kept) until their larger side is "
        f"PIXELS (at least {MIN_EXEMPLAR_SIZE}; default: no shrinking), as photographs often "
        "need: pre-computing the "
        "candidates of a 512x512 image takes 5 minutes on 2 CPU cores, of a 256x256 one about a "
        f"minute{advice}",
    )


def _check_max_size(args: argparse.Namespace) -> None:
    """Refuse a bad --exemplar-max-size; ``main`` asks before any command's work."""
    try:
        check_max_size(args.exemplar_max_size)
    except SettingError as error:
        raise CliError(f"--exemplar-max-size {error.problem}") from None


def _candidate_params(args: argparse.Namespace) -> dict:
    """The candidate parameters the command's options set (others keep their defaults)."""
    return {"tileable": TILEABLE[args.tileable]}


def _load_exemplar(args: argparse.Namespace, path: Path) -> Exemplar:
    """The exemplar at ``path``, read with the command's loading options."""
    return Exemplar.load(
        path,
        alpha=args.alpha,
        feature_mask=args.feature_mask,
        feature_distance=args.feature_distance,
        max_size=args.exemplar_max_size,
    )


def _add_info_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "info", help="describe an exemplar and its pyramid",
        description="Print an exemplar's size, channels, value range and encoding (what "
        "renders see of it), Gaussian pyramid, content digest and whether its 3D candidates "
        "are cached.")
    _add_exemplar_arguments(parser)


def _edge_contrast(across_columns: float, across_rows: float) -> str:
    """How much an exemplar's opposite edges differ, against neighbouring pixels; edges
    without a difference are said to be identical, for a ratio of 0 also stands for 0 / 0
    where the pixels never change along an axis (a constant image, stripes)."""
    if across_columns and across_rows:
        return (f"edges differ {across_columns:.1f}x left-right and {across_rows:.1f}x "
                "top-bottom as much as neighbouring pixels")
    return "; ".join(f"{name} edges identical" if ratio == 0.0 else
                     f"{name} edges differ {ratio:.1f}x as much as neighbouring pixels"
                     for name, ratio in (("left-right", across_columns),
                                         ("top-bottom", across_rows)))


def _cmd_info(args: argparse.Namespace) -> int:
    exemplar = _load_exemplar(args, args.path)
    height, width = exemplar.shape
    print(f"file: {exemplar.path}")
    file_height, file_width = exemplar.file_shape
    shrunk = "" if (file_height, file_width) == exemplar.shape else (
        f", shrunk from {file_width} x {file_height}")
    print(f"size: {width} x {height} pixels (width x height){shrunk}")
    feature_note = " + feature distance" if exemplar.features.shape[2] > exemplar.channels else ""
    print(f"channels: {exemplar.channels}{feature_note}")
    print("value range:")
    low = exemplar.colors.min(axis=(0, 1))
    high = exemplar.colors.max(axis=(0, 1))
    for channel, (lo, hi) in enumerate(zip(low, high, strict=True)):
        print(f"  channel {channel}: {lo:.4f} .. {hi:.4f}")
    print("encoding: " + ("sRGB (the Mitsuba plugin decodes it to linear colors unless raw)"
                          if exemplar.srgb else "linear (rendered as stored)"))
    levels = exemplar.pyramid()
    sizes = ", ".join(f"{level.shape[1]}x{level.shape[0]}" for level in levels)
    print(f"pyramid: {len(levels)} levels ({sizes})")
    seams = exemplar.seam_problem()
    own = exemplar.own_edges()
    if seams is None:
        print(f"tiles: yes ({_edge_contrast(*exemplar.seam_contrast())}{own})")
    else:
        print(f"tiles: no: {seams}; candidates keep away from those edges and the pyramid "
              f"does not blur across them, so corrections never continue the seam{own}")
    tileable = TILEABLE[args.tileable]
    if tileable != "auto":
        print(f"--tileable {args.tileable}: " + (
            "synthesis continues the exemplar across its edges all the same"
            if tileable else "candidates keep away from all four edges"))
    print(f"digest: {exemplar.digest()[:16]}")
    print(f"candidates: {_candidate_status(exemplar, tileable)}")
    return 0


def _candidate_status(exemplar: Exemplar, tileable: bool | str) -> str:
    """Where the candidates are cached, or what pre-computing them will cost here."""
    try:
        from warptex.candidates import LARGE_PIXELS, cached_candidate_path, precompute_bytes
    except ModuleNotFoundError as error:
        if error.name != "warptex.candidates":
            raise
        return "not available"
    from warptex.machine import byte_size, memory_problem

    refusal = _precompute_refusal(exemplar)
    if refusal is not None:  # refused by every command that pre-computes, whatever the memory
        return f"cannot be pre-computed: {refusal}"
    cached = cached_candidate_path(exemplar, tileable)
    if cached is not None:
        return f"cached at {cached}"
    need = precompute_bytes([exemplar])
    problem = memory_problem(need)
    if problem is not None:
        return f"not cached; pre-computing them {problem}: shrink it with --exemplar-max-size"
    height, width = exemplar.shape
    side = math.isqrt(LARGE_PIXELS)
    slow = f" and minutes (over {side}x{side} pixels)" if height * width > LARGE_PIXELS else ""
    return f"not cached; pre-computing them takes about {byte_size(need)} of memory{slow}"


def _precompute_refusal(exemplar: Exemplar) -> str | None:
    """Why no command pre-computes the candidates of ``exemplar`` (too many channels), or
    None."""
    from warptex.candidates import check_feature_channels

    try:
        check_feature_channels(exemplar.features.shape[2])
    except ValueError as error:
        return str(error)
    return None


def _add_precompute_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "precompute", help="pre-compute the 3D candidates of an exemplar (Dong 2008, section 4)",
        description="Pre-compute the 3D candidates of an exemplar (Dong 2008, section 4) into "
        "the candidate cache, which every other command reads (WARPTEX_CACHE sets its "
        "folder); prints each pyramid level's candidates per pixel and fallback pixels, "
        "then the time taken and the candidates' size.",
    )
    _add_exemplar_arguments(parser)
    _add_axis_exemplar_arguments(parser, "EXEMPLAR")
    parser.add_argument(
        "-o", "--output", type=_file_name, metavar="FILE",
        help="also write the candidates to FILE (.wtc), to share them with another machine "
        "(warptex.CandidateSet.load reads it)",
    )
    parser.add_argument("--no-cache", action="store_true", help="neither read nor write the cache")


def _cmd_precompute(args: argparse.Namespace) -> int:
    from warptex.candidates import (
        CandidateCacheError,
        cache_file_there,
        cache_path,
        check_candidate_path,
        precompute,
        resolved_params,
    )

    if args.output is not None:
        _check_output(args.output, (".wtc",), "a candidate file")
        _check_inputs_kept(args, [args.output])
        try:
            check_candidate_path(args.output)
        except CandidateCacheError as error:
            raise CliError(str(error)) from None
    exemplars = _load_axis_exemplars(args, _load_exemplar(args, args.path))
    params = _candidate_params(args)
    cache = None if args.no_cache else cache_path(exemplars, resolved_params(params))
    if cache is not None and not cache_file_there(cache):  # read, even where read-only
        _check_cache_folder(cache.parent)
    start = time.perf_counter()
    cs = precompute(*exemplars, cache=not args.no_cache, progress=True, **params)
    elapsed = time.perf_counter() - start
    if args.output is not None:
        with _writing(args.output):
            cs.save(args.output)
    _print_summary(cs, exemplars, elapsed)
    if cs.cache_status == "loaded":
        print(f"loaded from cache: {cache}")
    elif cs.cache_status == "written":
        print(f"written: {cache} (cache)")
    if args.output is not None:
        print(f"written: {args.output}")
    elif cache is None:
        print("written: nothing (--no-cache without -o)")
    if cs.cache_status == "not written":  # the cache is what a job warming it is run for
        raise _WorkFailed(f"{cache}: the candidates could not be cached (the warning above "
                          "says why); WARPTEX_CACHE sets the cache folder")
    return 0


_AXES = ("x", "y", "z")


def _add_axis_exemplar_arguments(parser: argparse.ArgumentParser, first: str) -> None:
    parser.add_argument("--ey", type=_input_file, metavar="FILE",
                        help="exemplar of the y axis: what planes y = const show, its rows "
                        f"along z and its columns along x (default: {first}, which planes "
                        "x = const show, rows along y, columns along z)")
    parser.add_argument("--ez", type=_input_file, metavar="FILE",
                        help="exemplar of the z axis: what planes z = const show, its rows "
                        "along x and its columns along y (default: the y exemplar)")


def _check_one_masked_exemplar(args: argparse.Namespace) -> None:
    if args.feature_mask is not None and (args.ey or args.ez):
        raise CliError("--feature-mask marks one image; use --feature-distance with --ey/--ez")


def _load_axis_exemplars(args: argparse.Namespace, ex: Exemplar) -> list[Exemplar]:
    """The exemplars of the x (``ex``), y and z axes; --ey/--ez are read with the
    command's loading options (a feature mask marks one image only)."""
    _check_one_masked_exemplar(args)
    ey, ez = (None if path is None else _load_exemplar(args, path) for path in (args.ey, args.ez))
    return list(axis_triple(ex, ey, ez))


def _check_cache_folder(folder: Path) -> None:
    """The cache folder exists or can be made, and can be written: before any work."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise CliError(f"{folder}: cannot make the cache folder ({error.strerror or error}); "
                       "WARPTEX_CACHE sets it") from None
    try:
        _check_writable_folder(folder, folder)
    except CliError as error:
        raise CliError(f"{error}; WARPTEX_CACHE sets it") from None


def _print_summary(cs: CandidateSet, exemplars: list[Exemplar], elapsed: float) -> None:
    """Levels, candidates per pixel (section 4.2), fallback pixels, time and bytes."""
    names = [e.name for e in exemplars]
    if cs.shared:
        print(f"exemplar: {names[0]} on all three axes (candidates shared)")
    else:
        print(f"exemplars: x {names[0]}, y {names[1]}, z {names[2]} ({len(cs.roles[0])} roles)")
    print(f"levels: {cs.num_levels}")
    sizes = ["/".join(f"{s.size[1]}x{s.size[0]}" for s in lvl) for lvl in cs.sources]
    width = max(len("size"), *map(len, sizes))
    # Only photos that do not tile have margins; the column would be zeros for the others.
    margins = [" / ".join(f"{s.margins[0]}, {s.margins[1]}" for s in lvl) for lvl in cs.sources]
    kept = any(any(s.margins) for lvl in cs.sources for s in lvl)
    header = "  margins (rows, columns)" if kept else ""
    print(f"  level  {'size':<{width}}  candidates/pixel  fallback pixels{header}")
    for level, roles in enumerate(cs.roles):
        mean = np.concatenate([r.count for r in roles]).mean()
        fallback = sum(int(r.fallback.sum()) for r in roles)
        column = f"  {margins[level]}" if kept else ""
        print(f"  {level:<5}  {sizes[level]:<{width}}  {mean:16.2f}  {fallback:15d}{column}")
    print("  (fallback pixels: no candidate passed the coherence test of section 4.2, so "
          "they keep their best crossbar match)")
    if kept:
        print("  (margins: rows at the top and bottom, columns at the left and right that no "
              "candidate holds, where the photo does not tile)")
    print(f"time: {elapsed:.2f} s")
    print(f"bytes: {cs.nbytes()} ({cs.nbytes() / 1024:.1f} KiB of arrays; a .wtc file adds "
          "its header and layout)")


def _add_cache_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "cache", help="list the candidate cache; prune the files this version never reads",
        description="List the candidate cache (WARPTEX_CACHE, default $XDG_CACHE_HOME/warptex "
        "where that is an absolute path, else ~/.cache/warptex): "
        "each file's date, size, exemplars and status. 'in use': read whenever its "
        "exemplars come up. 'other version': written by another warptex version (or "
        "renamed), which this one never reads. 'damaged': truncated or corrupt, computed "
        "again when needed. 'unfinished': left by a write that died over an hour ago. "
        "'being written': a write of another run, perhaps still going. 'unreadable': not "
        "readable here (another user's file, a folder), left alone. Files stay until "
        "deleted here. Also says where Warp's kernel cache is, how large, and how much of it "
        "holds builds of other warptex or Warp versions.",
        epilog="Deleted candidates are computed again when next needed (a few seconds for a "
        "64 px exemplar, about a minute for 256 px, minutes with one per axis).",
    )
    what = parser.add_mutually_exclusive_group()
    what.add_argument("--prune", action="store_true",
                      help="delete the 'other version', 'damaged' and 'unfinished' files, "
                      "and Warp's builds of other versions of warptex's kernels")
    what.add_argument("--clear", action="store_true",
                      help="delete every candidate file but those 'being written' or "
                      "'unreadable', and what --prune deletes of Warp's kernel cache")
    parser.add_argument("--json", action="store_true",
                        help="print the listing (and what was deleted) as one JSON object")


def _cmd_cache(args: argparse.Namespace) -> int:
    from warptex import candidate_cache as cc

    folder = cc.cache_dir()
    try:
        files = cc.cache_files(folder, progress=True)
    except OSError as error:
        raise CliError(f"{error.filename or folder}: cannot list the candidate cache "
                       f"({error.strerror or error}); WARPTEX_CACHE sets its folder") from None
    never = [f for f in files if f.status in cc.NEVER_READ]
    kept = (cc.BEING_WRITTEN, cc.UNREADABLE)
    doomed = [f for f in files if f.status not in kept] if args.clear else never
    kernels = _kernel_cache()  # refused here, before anything is deleted
    deleted = None
    undeleted: list[OSError] = []
    if args.prune or args.clear:
        try:
            deleted = cc.remove(doomed)
        except OSError as error:
            raise _WorkFailed(f"{error.filename}: cannot delete ({error.strerror or error})"
                              ) from None
        undeleted = _delete_kernel_builds(kernels)
    if args.json:
        print(json.dumps(_cache_report(folder, files, deleted, kernels), indent=2))
    else:
        _print_cache(folder, files, never, deleted, kernels)
    if undeleted:
        first = undeleted[0]
        others = f", and {len(undeleted) - 1} other kernel builds" if len(undeleted) > 1 else ""
        raise _WorkFailed(f"{first.filename}: cannot delete ({first.strerror or first})"
                          f"{others}")
    return 0


def _print_cache(folder: Path, files: list, never: list, deleted: tuple[int, int] | None,
                 kernels: dict) -> None:
    """``warptex cache``'s listing, and what it deleted."""
    from warptex import candidate_cache as cc

    print(f"candidate cache: {folder} (WARPTEX_CACHE sets it)")
    if files:
        print(f"  {'written':<16}  {'size':>9}  {'status':<13}  {'file':<55}  exemplars")
    for f in files:
        written = time.strftime("%Y-%m-%d %H:%M", time.localtime(f.modified))
        settings = "".join(f"; {_setting(k, v)}" for k, v in f.settings.items())
        print(f"  {written:<16}  {_mib_tenths(f.size):>9}  {f.status:<13}  {f.path.name:<55}  "
              f"{_exemplar_names(f.names)}{settings}")
    if not files:
        print("no candidate files")
    else:
        counts = ", ".join(f"{n} {status}" for status in cc.STATUSES
                           if (n := sum(f.status == status for f in files)))
        print(f"{len(files)} files, {_mib_tenths(sum(f.size for f in files))}: {counts}")
    if deleted is not None:
        print(f"deleted: {deleted[0]} files, {_mib_tenths(deleted[1])}")
    elif never:
        print(f"warptex cache --prune deletes the {len(never)} that no run of this warptex "
              f"reads ({_mib_tenths(sum(f.size for f in never))})")
    print(f"Warp's kernel cache: {kernels['folder']} (WARP_CACHE_PATH sets it), "
          f"{_mib_tenths(kernels['bytes'])}; built again when missing, so it may be emptied "
          "between runs")
    stale = kernels["other_builds"]
    if kernels["deleted"] is not None:
        print(f"deleted: {kernels['deleted']['builds']} kernel builds of other warptex or "
              f"Warp versions or left unfinished, {_mib_tenths(kernels['deleted']['bytes'])}")
    elif stale:
        print(f"  of which {len(stale)} kernel builds of other warptex or Warp versions or left "
              f"unfinished, {_mib_tenths(kernels['other_bytes'])}: warptex cache --prune "
              "deletes them")


def _cache_report(folder: Path, files: list, deleted: tuple[int, int] | None,
                  kernels: dict) -> dict:
    """``warptex cache --json``: the listing as data, times in ISO 8601 (UTC)."""
    return {
        "candidate_cache": str(folder),
        "files": [{"file": str(f.path), "written": iso_date(f.modified), "bytes": f.size,
                   "status": f.status, "exemplars": list(f.names),
                   "settings": f.settings} for f in files],
        "deleted": None if deleted is None else {"files": deleted[0], "bytes": deleted[1]},
        "kernel_cache": kernels,
    }


def _setting(name: str, value: object) -> str:
    """A candidate parameter as the command line gives it (``tileable=yes``)."""
    shown = ("yes" if value else "no") if isinstance(value, bool) else value
    return f"{name}={shown}"


def _exemplar_names(names: tuple[str, ...]) -> str:
    if not names:
        return "(not recorded)"
    short = [Path(n).name for n in names]
    if len(set(short)) == 1:
        return short[0]
    return ", ".join(f"{axis} {n}" for axis, n in zip("xyz", short, strict=False))


def _mib_tenths(n: int) -> str:
    return f"{n / 2**20:.1f} MiB"


def _kernel_cache() -> dict:
    """Where Warp keeps the built kernels and how much they take, and the builds of
    warptex's kernels that no run of this version loads (every version builds its own, and
    Warp never deletes old ones); "deleted" is None until they are."""
    import warp as wp

    from warptex import warp_runtime

    try:
        stale = warp_runtime.stale_kernel_builds()
    except OSError as error:
        raise CliError(f"{error.filename}: cannot list Warp's kernel cache "
                       f"({error.strerror or error}); WARP_CACHE_PATH sets its folder") from None
    folder = Path(wp.config.kernel_cache_dir)
    return {"folder": str(folder), "bytes": warp_runtime.folder_bytes(folder),
            "other_builds": [str(f) for f in stale],
            "other_bytes": sum(warp_runtime.folder_bytes(f) for f in stale), "deleted": None}


def _delete_kernel_builds(kernels: dict) -> list[OSError]:
    """Delete the kernel builds :func:`_kernel_cache` found, entering how many and their
    bytes in ``kernels``, and the cache's size after; the errors of those left."""
    from warptex import warp_runtime

    count, freed, failed = warp_runtime.delete_kernel_builds(
        [Path(b) for b in kernels["other_builds"]])
    kernels["deleted"] = {"builds": count, "bytes": freed}
    kernels["bytes"] = warp_runtime.folder_bytes(Path(kernels["folder"]))
    return failed


# Bytes a UV texel takes while baking: its float64 surface point, owner and coverage,
# up to 4 float32 channels three times over (colors, image, filled image), and the
# int64 indices of the nearest covered texel.
_TEXEL_BYTES = 3 * 8 + 4 + 1 + 3 * 4 * 4 + 2 * 8
# Bytes a shell voxel takes at most at once: its coordinates, their copies and sort keys
# while the shell is made, and its stored triple with its share of a partial brick.
_SHELL_VOXEL_BYTES = 64
_MAX_TEXTURE_SIZE = math.isqrt(2**31 - 1)  # texels are numbered by 32-bit integers
_TEXTURE_SIZE = 1024


def _add_volume_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "volume", help="synthesize a cube of solid texture (Dong 2008, section 5)",
        description="Synthesize the cube of voxels [0, SIZE)^3 of the exemplar's solid texture "
        "and write it to a file. Lazy synthesis gives the same voxels as every other command "
        "with the same seed, jitter, passes, --shifted-tiles and --tileable; --method kopf "
        "runs the Kopf 2007 baseline instead.",
    )
    _add_exemplar_arguments(parser)
    _add_texture_arguments(parser, "EXEMPLAR")
    parser.add_argument("--size", type=int, default=64,
                        help="edge of the cube in voxels (default 64; a multiple of 8 with "
                        "--method kopf)")
    parser.add_argument(
        "--method",
        choices=("lazy", "kopf"),
        default="lazy",
        help="lazy synthesis (Dong 2008, default) or the periodic global optimization of "
        "Kopf et al. 2007 (slower: 4 to 28 s for 64^3 on a 2-core CPU, 5 to 39 times lazy "
        "synthesis; BENCHMARKS.md)",
    )
    parser.add_argument("--mean-shift", action="store_true",
                        help="with --method kopf: average only the dominant mean-shift cluster "
                        "of each voxel's texels (Kopf 2007, section 4.1): sharper, slower")
    parser.add_argument("--free-axis", choices=_AXES,
                        help="with --method kopf: leave planes across this axis unconstrained, "
                        "matching the exemplars of the other two only (Kopf 2007, section "
                        "6.2: for a material seen from two sides)")
    parser.add_argument(
        "-o",
        "--output",
        type=_file_name,
        required=True,
        metavar="FILE",
        help="out.npy (x, y, z, channel), out.exr (z-slices side by side) or out.vol (Mitsuba 3)",
    )
    _add_raw_argument(parser, ".exr and .vol (linear) files")


def _cmd_volume(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from warptex.candidates import precompute
    from warptex.synthesis import Synthesizer, box_bytes, work_voxels

    _check_output(args.output, VOLUME_FORMATS, "a volume file")
    _check_inputs_kept(args, [args.output])
    _check_at_least("--size", args.size, 1)
    _check_synthesis_arguments(args.jitter, args.passes, args.seed)
    for flag, given in (("--mean-shift", args.mean_shift), ("--free-axis", args.free_axis)):
        if given and args.method != "kopf":
            raise CliError(f"{flag} applies to --method kopf only")
    if args.free_axis is not None and getattr(args, f"e{args.free_axis}", None) is not None:
        raise CliError(f"--free-axis {args.free_axis} leaves that axis without an exemplar: "
                       f"drop --e{args.free_axis}")
    if args.free_axis == "x" and args.ey is not None:  # EXEMPLAR would be read for nothing
        raise CliError("--free-axis x leaves EXEMPLAR's axis free: give the y axis' exemplar "
                       "as EXEMPLAR, not --ey")
    lazy_only = (args.passes, args.jitter, args.shifted_tiles)
    if args.method == "kopf" and lazy_only != (DEFAULT_PASSES, DEFAULT_JITTER, False):
        raise CliError("--passes, --jitter and --shifted-tiles apply to lazy synthesis only, "
                       "not --method kopf")
    if args.method == "kopf":
        _check_kopf_size(args.size)
    exemplars = _load_axis_exemplars(args, _load_exemplar(args, args.path))
    srgb = bool(_colors_srgb(args, exemplars))
    if args.method == "kopf":
        _check_kopf_memory(args.size, exemplars)
        return _volume_kopf(args, exemplars, srgb)
    # Before the slabs are planned: a size far too large would keep that busy.
    _check_memory(args.size, exemplars[0].features.shape[2])
    edges = _slab_edges(args.size)
    thickness = max(b - a for a, b in itertools.pairwise(edges))
    _check_memory(args.size, exemplars[0].features.shape[2],
                  box_bytes((thickness, args.size, args.size)))  # one slab at a time
    cs = precompute(*exemplars, progress=True, **_candidate_params(args))
    try:
        synth = Synthesizer(cs, seed=args.seed, jitter=args.jitter, passes=args.passes,
                            shifted_tiles=args.shifted_tiles)
    except ValueError as error:
        raise CliError(str(error)) from None
    size = args.size
    # A slow volume of one slab (a small one of many passes) shows its bar too, its clock
    # ticking: its time grows with the aprons of its passes, which thinner slabs would repeat.
    slow = work_voxels((size,) * 3, args.passes) > work_voxels((_SECONDS_OF_WORK,) * 3)
    shown = slow or len(edges) > 2
    with tqdm(total=len(edges) - 1, desc="volume", unit="slab", disable=not shown) as bar:
        slabs = []
        for x0, x1 in itertools.pairwise(edges):
            with _ticking(bar):
                # Results depend on position only, so slabs along x concatenate to the box.
                slabs.append(synth.box((x0, 0, 0), (x1 - x0, size, size)))
            bar.update()
    volume = np.concatenate(slabs, axis=0)
    with _writing(args.output):
        write_volume(args.output, volume, srgb=srgb, alpha=_alpha_kept(exemplars))
    print(f"volume: {size}^3 voxels, {_count(volume.shape[3], 'channel')}, seed {args.seed}")
    print(f"written: {args.output}")
    return 0


def _alpha_kept(exemplars: Sequence[Exemplar]) -> bool:
    """Whether the last channel is an alpha: kept on every axis, as another axis' exemplar
    (a .npy file) may hold data there."""
    return all(e.kept_alpha for e in exemplars)


def _volume_kopf(args: argparse.Namespace, exemplars: list[Exemplar], srgb: bool) -> int:
    from warptex.baselines.kopf import synthesize

    constrained: list[Exemplar | None] = list(exemplars)
    if args.free_axis is not None:
        constrained[_AXES.index(args.free_axis)] = None
    try:
        volume = synthesize(None, exemplars=constrained, size=args.size, seed=args.seed,
                            mean_shift=args.mean_shift, tileable=TILEABLE[args.tileable])
    except ValueError as error:
        raise CliError(str(error)) from None
    with _writing(args.output):
        write_volume(args.output, volume, srgb=srgb, alpha=_alpha_kept(exemplars))
    clustering = ", mean-shift clustering" if args.mean_shift else ""
    clustering += f", {args.free_axis} free" if args.free_axis else ""
    print(f"volume (Kopf 2007{clustering}): {args.size}^3 voxels, "
          f"{_count(volume.shape[3], 'channel')}, "
          f"seed {args.seed}")
    print(f"written: {args.output}")
    return 0


def _check_kopf_size(size: int) -> None:
    from warptex.baselines.kopf import check_size

    try:
        check_size(size)
    except ValueError as error:
        raise CliError(f"--{error}") from None


def _check_kopf_memory(size: int, exemplars: Sequence[Exemplar | None]) -> None:
    """Refuse, before any work, a Kopf volume whose exemplars' search structures, or these
    with the volume, would not fit in this machine's memory."""
    from warptex.baselines.kopf import search_bytes, working_bytes

    search = search_bytes(exemplars)
    given = [e for e in exemplars if e is not None]
    channels = given[0].features.shape[2]
    cube = _volume_bytes(size, channels) + working_bytes(size)
    if search >= cube:  # the photo's windows, more than the cube, are what does not fit
        _check_fits(search + cube, f"{file_names(given)}: Kopf's search over its windows "
                    f"(with the {size}^3 volume)",
                    "shrink the exemplar with --exemplar-max-size")
    _check_memory(size, channels, working_bytes(size) + search)


# The side of a cube that synthesizes in seconds at the default passes (1.4 s for 80^3 on a
# 2-core CPU): the commands show the progress of larger work.
_SECONDS_OF_WORK = 80
_TICK_SECONDS = 0.5  # how often a bar's clock is redrawn during one long call


def _slab_edges(size: int) -> list[int]:
    """Where the x-slabs of a ``size``^3 volume begin, and its end: slabs of about a
    million voxels show progress, but none much thinner than 32 voxels, which would spend more
    on its apron than on itself, and whole blocks thick, which no two slabs share; all about
    as thick (a last slab of one voxel paid a whole apron). A volume larger than
    ``_SECONDS_OF_WORK``^3 takes two at least, so that its bar moves."""
    from warptex.synthesis import BLOCK

    thickness = min(size, max(32, (1 << 20) // size**2))
    count = max(-(-size // thickness), 2 if size > _SECONDS_OF_WORK else 1)
    return sorted({round(i * size / count / BLOCK) * BLOCK for i in range(count)} | {size})


def _check_memory(size: int, channels: int, working: int = 0) -> None:
    """Refuse a cube whose float32 ``channels`` (held twice while the slabs are joined),
    with ``working`` bytes besides, would not fit in this machine's memory."""
    _check_fits(_volume_bytes(size, channels) + working, f"--size {size}: a {size}^3 volume",
                "use a smaller --size, or `warptex slice` and the Python API for parts of it")


def _volume_bytes(size: int, channels: int) -> int:
    """A float32 cube of ``channels``, held twice while its slabs are joined."""
    return 2 * 4 * channels * size**3


def _check_fits(need: int, what: str, advice: str) -> None:
    """Refuse, before any work, what needs more than this machine's memory."""
    from warptex.machine import memory_problem

    problem = memory_problem(need)
    if problem is not None:
        raise CliError(f"{what} {problem}; {advice}")


@contextlib.contextmanager
def _ticking(bar: tqdm) -> Iterator[None]:
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


# The outputs of this run renamed into place so far, for a stop's report.
_WRITTEN: list[Path] = []


@contextlib.contextmanager
def _writing(path: Path, *written_with: Path) -> Iterator[None]:
    """A failed write of the output ``path`` (a full disk, a lost mount) as one error that
    names it, or the file ``written_with`` it that failed; the writers are atomic, so the
    files are left as they were. The files renamed into place are noted (:data:`_WRITTEN`),
    also where a stop came right after the rename, so that the stop's report names them."""
    before = {p: file_state(p) for p in (path, *written_with)}
    try:
        yield
    except OSError as error:
        # A failed rename names its target second (os.replace's filename2).
        failed = {error.filename, error.filename2}
        where = next((p for p in written_with if str(p) in failed), path)
        raise _WorkFailed(write_failure(where, error)) from None
    finally:
        with deferred_stops():  # noted whole: a stop meanwhile comes after
            _WRITTEN.extend(p for p, state in before.items()
                            if p.is_file() and file_state(p) != state)


def _add_texture_arguments(parser: argparse.ArgumentParser, first: str) -> None:
    """The settings of lazy synthesis: every command given the same ones gets the same
    voxels."""
    _add_axis_exemplar_arguments(parser, first)
    parser.add_argument("--seed", type=int, default=0,
                        help="texture variation, 0 to 2147483647 (default 0)")
    _add_tiling_arguments(parser)
    parser.add_argument("--passes", type=int, default=DEFAULT_PASSES,
                        help="correction passes per pyramid level, 0 to 8 (default 2); 3 come "
                        "closer to the exemplar at about twice the time (the repository's "
                        "docs/comparisons)")


def _add_tiling_arguments(parser: argparse.ArgumentParser, advice: str = "") -> None:
    """How lazy synthesis varies the tiling it starts from (Dong 2008, section 5.1)."""
    parser.add_argument("--jitter", type=float, default=DEFAULT_JITTER,
                        help="strength of the random warp that varies the tiling, 0 to 64 "
                        f"(default 1){advice}")
    parser.add_argument("--shifted-tiles", action="store_true",
                        help="shift each tile of the initial tiling by its own offset: "
                        "structured exemplars (rust, cells) then show no bands every exemplar "
                        f"width, but follow their photo less closely (BENCHMARKS.md){advice}")


def _add_raw_argument(parser: argparse.ArgumentParser, formats: str) -> None:
    parser.add_argument("--raw", action="store_true",
                        help=f"write the exemplar's values as stored; by default {formats} "
                        "get colors in the encoding their readers assume, as Mitsuba's bitmap "
                        "does (see `warptex info`)")


def _colors_srgb(args: argparse.Namespace, exemplars: list[Exemplar]) -> bool | None:
    """Whether the colors to write are sRGB-encoded; None where they are written as they
    are (--raw, or a .npy output). Exemplars encoded differently are refused unless --raw,
    as a voxel's color averages colors of all three."""
    if args.raw:
        return None
    srgb = srgb_encoded(exemplars, raw="--raw")
    return None if args.output.suffix.lower() == ".npy" else srgb


def _check_synthesis_arguments(jitter: float, passes: int, seed: int) -> None:
    try:
        check_settings(jitter, passes, seed)
    except SettingError as error:
        raise CliError(f"--{error.name} {error.problem}") from None


def _lookup_exemplars(args: argparse.Namespace,
                      mesh: bool = False) -> tuple[list[Exemplar], bool | None]:
    """The command's exemplars, checked before any work for the points looked up in them,
    and whether their colors are sRGB-encoded (None where they are written as they are:
    see _colors_srgb); for a ``mesh`` command, a warning where its files cannot hold every
    channel."""
    from warptex.store import check_lookup_channels

    exemplars = _load_axis_exemplars(args, _load_exemplar(args, args.exemplar))
    try:  # before pre-computing: the channels are the same on every axis, or it says which
        check_lookup_channels(exemplars[0].channels)
    except ValueError as error:
        advice = "" if _precompute_refusal(exemplars[0]) else "; `warptex volume` synthesizes them"
        raise CliError(f"{args.exemplar}: {error}{advice}") from None
    channels = exemplars[0].channels
    if mesh and channels not in (1, 3):  # mesh files hold RGB (gray repeated)
        lost = channels - 1 if channels == 2 else channels - 3
        what = " (an alpha kept by --alpha keep)" if args.alpha == "keep" else ""
        warnings.warn(f"mesh files hold RGB colors: {_count(lost, 'channel')} of {channels}"
                      f"{what} synthesized but not written", stacklevel=1)
    return exemplars, _colors_srgb(args, exemplars)


def _solid_texture(args: argparse.Namespace, exemplars: list[Exemplar]):
    """The texture of the command's ``exemplars`` (:func:`_lookup_exemplars`), their
    candidates pre-computed."""
    from warptex.candidates import precompute
    from warptex.texture import SolidTexture

    try:
        # slice, bake and cut read thin sets (a plane, a surface): synthesize just those voxels.
        return SolidTexture(precompute(*exemplars, progress=True, **_candidate_params(args)),
                            seed=args.seed, jitter=args.jitter, passes=args.passes,
                            whole_bricks=False, shifted_tiles=args.shifted_tiles,
                            store=getattr(args, "store", None))
    except ValueError as error:
        raise CliError(str(error)) from None


def _add_slice_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "slice",
        help="evaluate the solid texture on a plane and save it as an image",
        description="Evaluate any plane through the solid texture (Dong 2008, 6.4). Pixel "
        "(r, c) shows the texture at ORIGIN + r*U + c*V, in voxels of the finest level.",
    )
    parser.add_argument("exemplar", type=_input_file, metavar="EXEMPLAR", help=_EXEMPLAR_HELP)
    _add_loading_arguments(parser)
    parser.add_argument("--origin", type=float, nargs=3, default=(0.5, 0.5, 0.5),
                        metavar=("X", "Y", "Z"),
                        help="texture point of pixel (0, 0) (default 0.5 0.5 0.5, a voxel centre)")
    parser.add_argument("--u", type=float, nargs=3, default=(1.0, 0.0, 0.0),
                        metavar=("X", "Y", "Z"),
                        help="step between rows (default the x axis, down the z exemplar's "
                        "rows: the default slice shows the texture as the z exemplar's photo "
                        "is oriented; `warptex volume -o out.exr` slices are its transpose, "
                        "x across, as image tools show volumes)")
    parser.add_argument("--v", type=float, nargs=3, default=(0.0, 1.0, 0.0),
                        metavar=("X", "Y", "Z"),
                        help="step between columns (default the y axis, along the z "
                        "exemplar's columns)")
    parser.add_argument("--shape", type=int, nargs=2, default=(256, 256), metavar=("H", "W"),
                        help="image rows and columns (default 256 256)")
    parser.add_argument("--filter", choices=FILTERS, default=FILTERS[0],
                        help="blend the 8 voxels around each point (default) or take the "
                        "voxel containing it")
    _add_texture_arguments(parser, "EXEMPLAR")
    parser.add_argument("-o", "--output", type=_file_name, required=True, metavar="FILE",
                        help="output image: .png (8-bit, with alpha where --alpha keep kept "
                        "one), .exr or .npy (float)")
    _add_raw_argument(parser, ".png (sRGB) and .exr (linear) images")


def _cmd_slice(args: argparse.Namespace) -> int:
    from warptex.sheets import save_png, to_png8
    from warptex.texture import POINT_LIMIT, plane_points, plane_within_limit, query_slabs

    suffix = _check_output(args.output, (".png", ".exr", ".npy"), "the image")
    _check_inputs_kept(args, [args.output])
    h, w = args.shape
    if h < 1 or w < 1:
        raise CliError(f"--shape must be positive, got {h} {w}")
    # Per pixel: its float64 point, its place in the slabs' order and up to 4 float32
    # channels, held twice while the image is assembled.
    _check_fits(h * w * (3 * 8 + 8 + 2 * 4 * 4), f"--shape {h} {w}: a slice of {h} x {w} "
                "pixels", "use a smaller --shape, or several slices")
    for name in ("origin", "u", "v"):
        _check_finite(f"--{name}", getattr(args, name))
    if not plane_within_limit(args.origin, args.u, args.v, (h, w)):
        raise CliError(f"the plane reaches beyond the texture's coordinate range "
                       f"(+-{POINT_LIMIT} voxels): check --origin, --u, --v and --shape")
    if not np.cross(args.u, args.v).any():
        warnings.warn("--u and --v are zero or parallel: the slice shows a line or a point, "
                      "not a plane", stacklevel=1)
    _check_synthesis_arguments(args.jitter, args.passes, args.seed)
    exemplars, srgb = _lookup_exemplars(args)
    tex = _solid_texture(args, exemplars)
    start = time.perf_counter()
    points = plane_points(args.origin, args.u, args.v, (h, w))
    image = query_slabs(tex, points, args.filter, progress="slice").reshape(h, w, -1)
    elapsed = time.perf_counter() - start
    if suffix == ".png":
        alpha = _alpha_kept(exemplars)
        _note_png_losses(image, alpha)
        if srgb is not None:
            image = reencoded(image, srgb=srgb, to_srgb=True)
        with _writing(args.output):
            save_png(to_png8(image, alpha), args.output)
    else:
        with _writing(args.output):
            write_image(args.output, image, srgb=bool(srgb), alpha=_alpha_kept(exemplars))
    print(f"slice: {h} rows x {w} columns in {elapsed:.2f} s; written: {args.output}")
    return 0


_PNG_SLACK = 1e-3  # filtering [0, 1] colors may overshoot by rounding, which is no loss


def _note_png_losses(image: np.ndarray, alpha: bool) -> None:
    """Warn when an 8-bit PNG cannot show all of a slice: values outside [0, 1] (HDR
    exemplars) are clipped, and channels past gray or RGB (and a kept ``alpha``, which the
    PNG keeps) are dropped."""
    lost = []
    if image.min() < -_PNG_SLACK or image.max() > 1.0 + _PNG_SLACK:
        lost.append("values outside [0, 1] are clipped")
    colors = image.shape[2] - alpha
    shown = (1 if colors < 3 else 3) + alpha
    if image.shape[2] > shown:
        lost.append(f"{_count(image.shape[2] - shown, 'channel')} of {image.shape[2]} "
                    "dropped")
    if lost:
        kept = "RGBA" if alpha else "RGB"
        warnings.warn(f"the PNG keeps 8-bit {kept}: {' and '.join(lost)}; .exr or .npy keep "
                      "all", stacklevel=1)


def _add_mesh_arguments(parser: argparse.ArgumentParser,
                        uv_sources: Sequence[str] = ("auto", "mesh", "none")) -> None:
    parser.add_argument("mesh", type=_input_file, metavar="MESH",
                        help="triangle mesh (PLY, OBJ, GLB, STL, ...)")
    parser.add_argument("--exemplar", type=_input_file, required=True, metavar="EXEMPLAR",
                        help=_EXEMPLAR_HELP)
    _add_loading_arguments(parser)
    parser.add_argument("--resolution", type=int, default=1024,
                        help="the mesh's bounding box fills a block of RESOLUTION^3 voxels "
                        "(default 1024)")
    ways = {"mesh": "with the mesh's own UVs (mesh)", "auto": "UVs made by xatlas (auto)"}
    parser.add_argument("--uv", choices=uv_sources, default="none",
                        help="bake a UV texture: "
                        + ", ".join(ways[w] for w in uv_sources if w in ways)
                        + ", or vertex colors only (none, default)"
                        + ("" if "mesh" in uv_sources else "; not the mesh's own UVs, which "
                           "the caps a cut makes lack")
                        + "; xatlas takes a while on "
                        "large meshes (21 s for the 69k-face bunny on 2 cores)")
    parser.add_argument("--texture-size", type=int,
                        help=f"with --uv: edge of the UV texture in pixels (default "
                        f"{_TEXTURE_SIZE})")
    parser.add_argument("--store", type=_file_name, metavar="FILE",
                        help="brick store file: voxels synthesized by an earlier run with the "
                        "same texture are read from it, and all are written back at the end, "
                        "or when Ctrl-C or SIGTERM stops the run (also usable as the "
                        "lazy_solid plugin's cache)")
    _add_texture_arguments(parser, "--exemplar")
    _add_raw_argument(parser, "PNG textures and PLY vertex colors (sRGB) and glTF vertex "
                      "colors (linear)")


def _check_mesh_arguments(args: argparse.Namespace, second_half: bool = False) -> list[Path]:
    """Everything about a bake or cut that can be wrong, checked before the work; returns
    the mesh files to write (a cut's second half gets the suffix _b)."""
    from warptex.mesh_files import (
        UV_TEXTURE_FORMATS,
        VERTEX_COLOR_FORMATS,
        check_obj_name,
        exported_files,
    )
    from warptex.synthesis import COORD_LIMIT

    _check_at_least("--resolution", args.resolution, 1)
    if args.resolution > COORD_LIMIT // 2:
        raise CliError(f"--resolution must be at most {COORD_LIMIT // 2}, got {args.resolution}")
    if args.uv == "none" and args.texture_size is not None:
        raise CliError("--texture-size applies to a UV texture (--uv auto or mesh), not to "
                       "vertex colors")
    size = _texture_size(args)
    _check_at_least("--texture-size", size, 1)
    if args.uv != "none":
        if size > _MAX_TEXTURE_SIZE:
            raise CliError(f"--texture-size must be at most {_MAX_TEXTURE_SIZE}, got {size}")
        _check_fits(size * size * _TEXEL_BYTES, f"--texture-size {size}: a {size}^2 UV texture",
                    "use a smaller --texture-size")
    _check_synthesis_arguments(args.jitter, args.passes, args.seed)
    if args.uv == "none":
        formats, what = VERTEX_COLOR_FORMATS, "a mesh with vertex colors (--uv none)"
    else:
        formats, what = UV_TEXTURE_FORMATS, f"a mesh with a UV texture (--uv {args.uv})"
    _check_output(args.output, formats, what)
    outputs = [args.output]
    if second_half:
        outputs.append(args.output.with_stem(args.output.stem + "_b"))
        _check_output(outputs[1], formats, what)
    for output in outputs:
        files = exported_files(output, uv_texture=args.uv != "none")
        if len(files) > 1:
            try:
                check_obj_name(output)
            except ValueError as error:
                raise CliError(str(error)) from None
        _check_inputs_kept(args, files)
        for side in files[1:]:  # the material library and texture of an .obj
            problem = file_problem(side)
            if problem is not None:
                raise CliError(f"{side} (written with {output}): {problem}")
    written = [f for o in outputs for f in exported_files(o, uv_texture=args.uv != "none")]
    twice = one_file_twice(written)  # links: the second half's name to the first's file, say
    if twice is not None:
        raise CliError(f"{twice[0]} and {twice[1]} are one file (through a link); each file "
                       "of a cut is written once: choose another output name")
    if args.store is not None:
        from warptex.store import StoreFileError, check_store_path

        _check_output(args.store)
        if any(args.store.resolve() == f.resolve() for f in written):
            raise CliError(f"{args.store}: --store names an output file; choose another file")
        try:
            check_store_path(args.store)
        except StoreFileError as error:
            raise CliError(str(error)) from None
    return outputs


def _texture_size(args: argparse.Namespace) -> int:
    return _TEXTURE_SIZE if args.texture_size is None else args.texture_size


def _load_mesh(path: Path, uv: str = "none", weld: bool = False,
               outputs: Sequence[Path] = ()):
    """:func:`warptex.mesh_files.load_mesh`, its refusal the command's."""
    from warptex.mesh_files import MeshFileError, load_mesh

    try:
        return load_mesh(path, uv=uv, weld=weld, outputs=outputs)
    except MeshFileError as error:
        raise CliError(str(error)) from None


def _baked(tex, mesh, transform: np.ndarray, args: argparse.Namespace, name: str) -> dict:
    """Bake ``mesh`` as asked by --uv: the keyword arguments of
    warptex.mesh_files.export, nothing written yet."""
    from tqdm.auto import tqdm

    from warptex.bake import bake_uv_texture, uv_layout_problems, vertex_colors
    from warptex.parallel import in_child_process

    if args.uv == "none":
        return {"mesh": mesh,
                "colors": vertex_colors(tex, mesh, transform, progress=f"colors of {name}")}
    # Unwrapping is one long call: the bar names the step it is in and times it.
    with tqdm(total=2, desc=f"UV texture {name}",
              bar_format="{desc}: step {n}/{total}{postfix} [{elapsed}]") as bar:
        if args.uv == "auto":
            bar.set_postfix_str("unwrapping (xatlas)")
            # Its clock ticks while the child unwraps, so a slow unwrap does not look hung.
            mesh = in_child_process(type(mesh).unwrap, mesh, while_waiting=bar.refresh)
        bar.update()
        uv = mesh.visual.uv  # _load_mesh checked --uv mesh; cut does not offer it
        size = _texture_size(args)
        bar.set_postfix_str(f"baking {size}^2 texels")
        image, covered = bake_uv_texture(tex, mesh, uv, transform, size=size)
        bar.update()
    for problem in uv_layout_problems(uv, mesh.faces, covered) if args.uv == "mesh" else ():
        warnings.warn(f"{args.mesh}: {problem}; --uv auto makes UVs of its own", stacklevel=1)
    return {"mesh": mesh, "image": image, "uv": uv}


def _export_baked(baked: list[dict], outputs: list[Path], srgb: bool | None) -> list[Path]:
    """Write what :func:`_baked` made for each output, together (a cut's two halves: both
    or, where a write fails, neither), its colors in each format's encoding (``srgb``: see
    warptex.mesh_files.export); returns the files written."""
    from warptex.mesh_files import mesh_files, write_files

    files = [f for b, output in zip(baked, outputs, strict=True)
             for f in mesh_files(path=output, srgb=srgb, **b)]
    with _writing(outputs[0], *(f for f, _ in files)):
        write_files(files)
    return [f for f, _ in files]


def _store_saved_when_stopped(tex, args: argparse.Namespace) -> contextlib.AbstractContextManager:
    """A `bake` or `cut` stopped by Ctrl-C or SIGTERM saves its ``--store`` first."""
    if args.store is None:
        return contextlib.nullcontext()
    from warptex.store import saved_when_stopped

    return saved_when_stopped(lambda: [tex.save()])


def _finish_mesh_command(tex, args: argparse.Namespace, files: list[Path], start: float) -> int:
    """What `bake` and `cut` end with: the store's report, the store saved if asked, and
    the files written."""
    _report_store(tex, args.resolution, time.perf_counter() - start)
    unchanged = ""
    if args.store is not None:
        before = file_state(args.store)
        try:
            with _writing(args.store):
                saved = tex.save()
        except _WorkFailed:
            # The meshes stay written (the store only keeps work for later): say so.
            print("written: " + ", ".join(str(f) for f in files) + f"; not {args.store}")
            raise
        # A store that held every voxel already is left as it was (BrickStore.save).
        if before is not None and file_state(saved) == before:
            unchanged = f"; {args.store} unchanged (it held every voxel already)"
        else:
            files.append(args.store)  # as given, like the meshes: saved is absolute
    print("written: " + ", ".join(str(f) for f in files) + unchanged)
    return 0


def _mib(n: float) -> str:
    return f"{n / 2**20:.0f} MiB" if n >= 2**20 else f"{n / 2**20:.2g} MiB"


def _report_store(tex, resolution: int, elapsed: float) -> None:
    stats = tex.store.stats()
    block = resolution**3
    corrected = stats["voxels_synthesized"].get(tex.synthesizer.finest, 0)
    full = block * stats["bytes_per_voxel"]
    made = stats["voxels_added"]
    # Counted against the block's size, not as a part of it: at small resolutions the
    # surface's filter neighbours and their dependencies reach past the block, past 100%.
    print(f"voxels synthesized: {made} ({100 * made / block:.3f}% as many as the "
          f"{resolution}^3 block holds); on the way the finest level corrected {corrected} "
          f"({100 * corrected / block:.3f}% as many: their dependencies, section 5.2)")
    print(f"stored: {stats['voxels']} voxels, {stats['bytes'] / 2**20:.1f} MiB in "
          f"{stats['bricks']} bricks (the full volume would be {_mib(full)}); "
          f"time {elapsed:.1f} s")


def _add_bake_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "bake",
        help="texture a mesh as if carved from a block of matter, and export it",
        description="Synthesize only the voxels around the mesh surface (Dong 2008, 6.2) and "
        "write vertex colors (.ply/.glb) or a UV texture (.glb with embedded PNG, .obj+.mtl).",
    )
    _add_mesh_arguments(parser)
    parser.add_argument("-o", "--output", type=_file_name, required=True, metavar="FILE",
                        help="output mesh: .ply or .glb (vertex colors), .glb or .obj (UV)")


def _synthesize_shell(tex, mesh, resolution: int, transform: np.ndarray) -> int:
    """Synthesize the voxels around ``mesh``'s surface, with a progress bar; returns their
    count. They fill the same brick store that baking and a renderer then read."""
    from tqdm.auto import tqdm

    from warptex.surface import shell
    from warptex.texture import BATCH

    # Finding the voxels is one long call (seconds at 1024^3): the bar names it first.
    with tqdm(desc="surface shell", unit="voxel", unit_scale=True,
              postfix="finding the voxels the surface passes through") as bar:
        with _ticking(bar):
            voxels = shell(mesh, resolution, transform)
        bar.set_postfix_str("synthesizing them", refresh=False)
        bar.reset(total=len(voxels))
        # Not query_slabs: its colors would be thrown away, and holding them, with a point
        # and an order for every shell voxel at once, would double what the shell takes in
        # memory. The shell is sorted along x, so each batch is a slab and one engine request.
        for first in range(0, len(voxels), BATCH):
            part = voxels[first : first + BATCH]
            tex.query(part + 0.5, filter="nearest")
            bar.update(len(part))
    return len(voxels)


def _check_shell(mesh, transform: np.ndarray, resolution: int) -> None:
    """Refuse, before any synthesis, a surface too large at ``resolution`` for one shell
    or for this machine's memory."""
    from warptex.surface import checked_shell_size

    try:
        voxels = checked_shell_size(mesh, transform)
    except ValueError as error:
        raise CliError(f"--resolution {resolution}: {error}; lower --resolution") from None
    _check_fits(voxels * _SHELL_VOXEL_BYTES, f"--resolution {resolution}: the surface passes "
                f"through about {voxels:.3g} voxels, which", "lower --resolution")


def _cmd_bake(args: argparse.Namespace) -> int:
    from warptex.surface import block_transform

    _check_mesh_arguments(args)
    mesh = _load_mesh(args.mesh, args.uv, outputs=[args.output])
    transform = block_transform(mesh, args.resolution)
    _check_shell(mesh, transform, args.resolution)
    exemplars, srgb = _lookup_exemplars(args, mesh=True)
    tex = _solid_texture(args, exemplars)
    start = time.perf_counter()
    with _store_saved_when_stopped(tex, args):
        count = _synthesize_shell(tex, mesh, args.resolution, transform)
        files = _export_baked([_baked(tex, mesh, transform, args, args.output.name)],
                              [args.output], srgb)
        print(f"surface shell: {count} voxels")
        return _finish_mesh_command(tex, args, files, start)


def _add_cut_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "cut",
        help="cut a mesh by a plane and texture both halves, caps included",
        description="Split a mesh by a plane, close both halves with caps and texture them "
        "from the same solid texture: the caps continue the outer surface (Dong 2008, 6.4).",
    )
    _add_mesh_arguments(parser, uv_sources=("auto", "none"))  # caps have no UVs of their own
    parser.add_argument("--origin", type=float, nargs=3, metavar=("X", "Y", "Z"),
                        help="a point of the plane in mesh coordinates (default: box centre)")
    parser.add_argument("--normal", type=float, nargs=3, default=(1.0, 0.0, 0.0),
                        metavar=("X", "Y", "Z"),
                        help="plane normal, pointing into the first half (default x)")
    parser.add_argument("-o", "--output", type=_file_name, required=True, metavar="FILE",
                        help="output mesh for the first half, the side the normal points "
                        "to: .ply or .glb (vertex colors), "
                        ".glb or .obj (--uv auto), e.g. cut.ply; the second half gets the "
                        "suffix _b (cut_b.ply)")


def _cmd_cut(args: argparse.Namespace) -> int:
    from warptex.cut import cut
    from warptex.surface import block_transform

    outputs = _check_mesh_arguments(args, second_half=True)
    _check_finite("--normal", args.normal)
    if not any(args.normal):
        raise CliError("--normal must not be 0 0 0: it is the direction across the cut")
    if args.origin is not None:
        _check_finite("--origin", args.origin)
    mesh = _load_mesh(args.mesh, weld=True, outputs=outputs)
    exemplars, srgb = _lookup_exemplars(args, mesh=True)  # before the cut's work
    origin = np.asarray(args.origin if args.origin else mesh.bounds.mean(axis=0))
    try:
        halves = cut(mesh, origin, np.asarray(args.normal), progress=True)
    except ValueError as error:
        raise CliError(f"{args.mesh}: {error}") from None
    tex = _solid_texture(args, exemplars)
    start = time.perf_counter()
    transform = block_transform(mesh, args.resolution)
    with _store_saved_when_stopped(tex, args):
        # Both halves baked before either is written: a cut stopped half way writes neither.
        baked = [_baked(tex, half, transform, args, output.name)
                 for half, output in zip(halves, outputs, strict=True)]
        return _finish_mesh_command(tex, args, _export_baked(baked, outputs, srgb), start)


def _add_compare_parser(subparsers: argparse._SubParsersAction) -> None:
    from warptex.compare import METHOD_NOTES, METHODS

    parser = subparsers.add_parser(
        "compare",
        help="compare solid texture methods on an exemplar: picture sheet and score table",
        description="Run each method in a fresh process and write DIR/sheet.png (per method: "
        "the middle slices across x, y and z, and a rendered cube: lazy through the "
        "lazy_solid plugin, the others through Mitsuba's grid volume), DIR/table.md and "
        "DIR/table.json: "
        "neighbourhood energy and its converse, completeness (each exemplar patch's distance "
        "to the nearest slice patch), sliced Wasserstein distance and histogram distance per "
        "axis, "
        "a repetition score over a slice of at least 256 voxels (twice the longest period "
        "a method may repeat at), time (the lazy engine's pre-computation apart) and peak "
        "memory. Lower is better in every score; read them together, as each alone rewards "
        "something that is no texture (the reference methods extrude, noise and flat show "
        "what; warptex.metrics says more). Scores of other --size do not compare. With "
        "--ey/--ez each axis has its own exemplar, its slices measured against it. "
        "Methods: " + "; ".join(f"{m}: {METHOD_NOTES[m]}" for m in METHODS) + ".",
    )
    parser.add_argument("exemplar", type=_input_file, metavar="EXEMPLAR", help=_EXEMPLAR_HELP)
    _add_axis_exemplar_arguments(parser, "EXEMPLAR")
    parser.add_argument("--size", type=int, default=64,
                        help="edge of each method's volume in voxels, at least 8 and, with "
                        "Kopf's methods, a multiple of 8 (default 64)")
    parser.add_argument("--methods", default=",".join(METHODS),
                        help="comma-separated methods, of " + ", ".join(METHODS)
                        + " (default: all)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of every randomized method, 0 to 2147483647 (default 0)")
    parser.add_argument("--passes", type=int, default=DEFAULT_PASSES,
                        help="correction passes per pyramid level of lazy synthesis, 0 to 8, "
                        "for the lazy and tiled methods (default 2)")
    _add_tiling_arguments(parser, advice="; for the lazy and tiled methods")
    parser.add_argument("--repeats", type=int, default=1, metavar="N",
                        help="time each method N times and report the median, every run "
                        "kept in table.json (default 1)")
    _add_max_size_argument(parser, advice="; every method reads the shrunk images")
    _add_feature_arguments(parser, advice=", which lazy synthesis and Kopf match beside the "
                           "colors (the measures take colors only)")
    _add_tileable_argument(parser, advice="; for lazy, tiled and Kopf, and for the measures, "
                           "whose exemplar neighbourhoods wrap only where synthesis may")
    parser.add_argument("-o", "--output", type=_folder_name, required=True, metavar="DIR",
                        help="output folder")


def _cmd_compare(args: argparse.Namespace) -> int:
    from warptex.compare import (
        MIN_SIZE,
        Setup,
        check_methods,
        compare,
        report_files,
        table_markdown,
        write_report,
    )

    _check_synthesis_arguments(args.jitter, args.passes, args.seed)
    _check_at_least("--size", args.size, MIN_SIZE)
    _check_at_least("--repeats", args.repeats, 1)
    _check_one_masked_exemplar(args)
    setup = Setup(args.exemplar, args.size, seed=args.seed, passes=args.passes,
                  jitter=args.jitter, shifted_tiles=args.shifted_tiles,
                  max_size=args.exemplar_max_size, tileable=TILEABLE[args.tileable],
                  feature_distance=bool(args.feature_distance),
                  feature_mask=args.feature_mask, ey=args.ey, ez=args.ez)
    # One clear error for a bad image before any work.
    exemplar = setup.exemplars()[0]
    _check_writable_folder(args.output, args.output)
    try:  # a folder in a report file's place: before minutes of work
        report = report_files(args.output)
    except ValueError as error:
        raise CliError(str(error)) from None
    _check_inputs_kept(args, report)
    _check_memory(args.size, exemplar.features.shape[2])  # each method holds its volume
    try:  # before the checks of the methods named (Kopf's sizes)
        methods = check_methods(m.strip() for m in args.methods.split(",") if m.strip())
    except ValueError as error:
        raise CliError(f"--methods: {error}") from None
    if any(m.startswith("kopf") for m in methods):
        _check_kopf_size(args.size)
        _check_kopf_memory(args.size, setup.exemplars())
    try:
        comparison = compare(setup, methods, repeats=args.repeats)
    except ValueError as error:
        raise CliError(str(error)) from None
    with _writing(args.output, *report):
        try:
            files = write_report(comparison, args.output)
        except ValueError as error:  # the folder became unwritable during the work
            raise _WorkFailed(str(error)) from None
    print(table_markdown(comparison.results))
    print("written: " + ", ".join(str(f) for f in files))
    return 0


def _add_render_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "render",
        help="render a Mitsuba 3 scene that uses the lazy_solid texture",
        description="Render a Mitsuba scene (e.g. the repository's scenes/bunny_wood.xml) "
        "with warptex's "
        "lazy_solid plugin, showing progress; the brick-store statistics are printed and "
        "written beside the image as OUTPUT.json. The scene's textures read their exemplars "
        "themselves: shrink a large photograph there, with <integer name=\"exemplar_max_size\" "
        "value=\"256\"/> in its lazy_solid.",
    )
    parser.add_argument("scene", type=_input_file, metavar="SCENE",
                        help="Mitsuba 3 scene file (.xml)")
    parser.add_argument("-o", "--output", type=_file_name, required=True, metavar="FILE",
                        help="image to write: .exr (linear) or .png (sRGB)")
    parser.add_argument("--spp", type=int, help="samples per pixel (default: the scene's); one "
                        "its sampler takes as it is (a stratified sampler takes squares)")
    parser.add_argument("--res", metavar="WxH",
                        help="image size (default: the scene's); sets the scene's $width and "
                        "$height parameters, which the scene must declare: <default "
                        "name=\"width\" value=\"256\"/> and, in its film, <integer "
                        "name=\"width\" value=\"$width\"/>; the same for height")
    parser.add_argument("--variant",
                        help="Mitsuba variant to render in, e.g. llvm_ad_spectral or "
                        "scalar_spectral for spectral rendering, llvm_ad_mono for "
                        f"monochrome (default: llvm_ad_rgb where libLLVM >= {MIN_LLVM_MAJOR} "
                        "is found in the system's library folders or named by "
                        "DRJIT_LIBLLVM_PATH, else scalar_rgb)")
    parser.add_argument("--read-only-stores", action="store_true",
                        help="read the brick stores the scene names (lazy_solid's cache) "
                        "without writing them back: a shared store, or one in a place that "
                        "cannot be written (where there is none yet, rendered without one)")
    parser.add_argument("-D", dest="parameters", action="append", default=[],
                        type=_scene_parameter, metavar="NAME=VALUE",
                        help="set a parameter the scene declares (<default name=\"NAME\" "
                        "value=\"...\"/>, used as $NAME), as Mitsuba's -D; repeatable")
    parser.add_argument("--sampler-seed", type=int, default=0, metavar="N",
                        help="seed of the render's samples, not of the texture (lazy_solid's "
                        f"seed), 0 to {MAX_SAMPLER_SEED}; renders of other seeds at the same "
                        "--spp can be averaged (at other counts their batches may share seeds; "
                        "the scene's own sampler seed adds to it) (default 0)")


def _scene_parameter(text: str) -> tuple[str, str]:
    name, equals, value = text.partition("=")
    if not equals or not re.fullmatch(r"[A-Za-z_]\w*", name):
        raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=VALUE, NAME a parameter "
                                         "of the scene")
    return name, value


def _cmd_render(args: argparse.Namespace) -> int:
    from mitsuba_plugin.command import (
        IMAGE_SUFFIXES,
        OutputError,
        parse_resolution,
        render_scene,
    )

    _check_input_file(args.scene, "scene")
    _check_output(args.output, IMAGE_SUFFIXES, "the image")
    given = [name for name, _ in args.parameters]
    twice = next((name for name in given if given.count(name) > 1), None)
    if twice is not None:  # which one the render used would be left unsaid
        values = ", ".join(v for name, v in args.parameters if name == twice)
        raise CliError(f"-D {twice} is given more than once ({values}): give it once")
    try:
        resolution = None if args.res is None else parse_resolution(args.res)
        render_scene(args.scene, args.output, spp=args.spp, resolution=resolution,
                     variant=args.variant, save_stores=not args.read_only_stores,
                     parameters=dict(args.parameters), seed=args.sampler_seed)
    except ValueError as e:
        raise CliError(str(e)) from e
    except OutputError as e:
        raise _WorkFailed(str(e)) from None
    return 0


_SUBCOMMANDS: dict[
    str,
    tuple[Callable[[argparse._SubParsersAction], None], Callable[[argparse.Namespace], int]],
] = {
    "info": (_add_info_parser, _cmd_info),
    "precompute": (_add_precompute_parser, _cmd_precompute),
    "cache": (_add_cache_parser, _cmd_cache),
    "volume": (_add_volume_parser, _cmd_volume),
    "slice": (_add_slice_parser, _cmd_slice),
    "bake": (_add_bake_parser, _cmd_bake),
    "cut": (_add_cut_parser, _cmd_cut),
    "compare": (_add_compare_parser, _cmd_compare),
    "render": (_add_render_parser, _cmd_render),
}


class _Parser(argparse.ArgumentParser):
    """argparse's, but a mistake on the command line is one line naming the command, as
    every other refusal is, and says where the command's options are explained, instead
    of a usage block of many lines."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="warptex", description="Lazy solid texture synthesis from 2D exemplars.",
        formatter_class=_HelpFormatter,
        epilog="'warptex COMMAND --help' explains a command's options and ends with "
        "examples.\n\n"
        "environment: WARPTEX_DEVICE=cpu|cuda picks the device (default: a GPU when "
        "there is one); WARPTEX_CACHE is the folder of the candidate cache (default "
        "$XDG_CACHE_HOME/warptex where absolute, else ~/.cache/warptex); WARP_CACHE_PATH is "
        "Warp's kernel cache (built on first use).\n\n"
        "Exit codes: 0 done, 1 a file could not be written or deleted during the work (a "
        "full disk, say), 2 input refused before any work, 130 interrupted, 143 terminated "
        "(render, bake and cut save their brick stores first; an output written just before "
        "is named), 141 the reader of its "
        "output closed it (`| head`).\n\n"
        + "\n".join([_EXAMPLES_HEADING, *(e for name in ("slice", "render", "compare")
                                           for e in _EXAMPLES[name][:1])]),
    )
    parser.add_argument("--version", action="version", version=f"warptex {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (add_parser, _) in _SUBCOMMANDS.items():
        add_parser(subparsers)
        command = subparsers.choices[name]
        command.formatter_class = _HelpFormatter
        examples = "\n".join([_EXAMPLES_HEADING, *_EXAMPLES[name]])
        command.epilog = f"{command.epilog}\n\n{examples}" if command.epilog else examples
    return parser


_WOOD = "scenes/textures/wood_rosewood_64.png"
_BUNNY = "scenes/meshes/bunny.ply"
# Each command's --help ends with these, run from a checkout (its scenes/ and their files).
_EXAMPLES_HEADING = "examples, from a checkout's folder:"
_EXAMPLES = {
    "info": [f"warptex info {_WOOD}"],
    "precompute": [f"warptex precompute {_WOOD}",
                   f"warptex precompute {_WOOD} --exemplar-max-size 32 -o out/wood_32.wtc"],
    "cache": ["warptex cache", "warptex cache --prune"],
    "volume": [f"warptex volume {_WOOD} --size 64 -o out/wood.npy",
               f"warptex volume {_WOOD} --size 32 --method kopf -o out/wood_kopf.exr"],
    "slice": [f"warptex slice {_WOOD} -o out/slice.png",
              f"warptex slice {_WOOD} --origin 0.5 0.5 0.5 --u 0 1 0 --v 0 0 1 --shape 128 128 "
              "-o out/across.png"],
    "bake": [f"warptex bake {_BUNNY} --exemplar {_WOOD} --resolution 256 -o out/bunny.ply",
             f"warptex bake {_BUNNY} --exemplar {_WOOD} --resolution 256 --uv auto "
             "-o out/bunny_uv.obj"],
    "cut": [f"warptex cut {_BUNNY} --exemplar {_WOOD} --resolution 256 --normal 1 0 0 "
            "-o out/half.ply"],
    "compare": [f"warptex compare {_WOOD} --size 32 --methods lazy,extrude,noise -o out/compare"],
    "render": ["warptex render scenes/bunny_wood.xml -o out/bunny.png --spp 16 --res 256x256"],
}


class _HelpFormatter(argparse.HelpFormatter):
    """argparse's, but the examples that end an epilog (the lines after its heading) are
    kept as they are, one command each, rather than run together into a paragraph."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        prose, heading, examples = text.partition(_EXAMPLES_HEADING)
        filled = []
        for paragraph in prose.split("\n\n"):  # a loop: a comprehension's super() fails
            if paragraph.strip():
                filled.append(super()._fill_text(paragraph, width, indent))
        if heading:
            filled.append("\n".join([indent + heading, *(f"{indent}  {line}" for line
                                                        in examples.strip("\n").splitlines())]))
        return "\n\n".join(filled)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    # A user of the command needs the message, not the source line that raised it; a
    # message that names warptex for Python's users is not prefixed twice.
    print(f"warptex: warning: {str(message).removeprefix('warptex: ')}", file=sys.stderr)


# Modules nearly every command builds, and whether they run on the CPU whatever the device
# (a CPU launch builds the block_dim 1 variant; CUDA launches the default one).
_KERNEL_MODULES = (("kernels.candidates", True), ("kernels.synthesis", False))


def _check_device() -> None:
    """A device asked for through the environment that cannot be had, or a kernel cache
    folder (WARP_CACHE_PATH) that Warp cannot make as it starts, is a user error."""
    from warptex.warp_runtime import device, init_warp

    try:
        init_warp()
    except OSError as error:
        where = error.filename or os.environ.get("WARP_CACHE_PATH", "Warp's kernel cache")
        raise CliError(f"{where}: Warp cannot make its kernel cache there "
                       f"({error.strerror or error}); WARP_CACHE_PATH sets its folder") from None
    if os.environ.get("WARPTEX_DEVICE", "").strip():
        try:
            device()
        except (ValueError, RuntimeError) as error:
            raise CliError(str(error)) from None


def _note_kernel_build() -> None:
    """Say why a machine's first command pauses: Warp builds the kernels into its kernel
    cache, once (README, "first use"), and until then no bar moves. The candidate and
    synthesis modules are what nearly every command builds; each is looked up under the
    name Warp gives its current code, so a new version of either is noticed too."""
    from warptex.warp_runtime import build_folder, device

    on_cpu = device() == "cpu"
    folders = [build_folder(name, on_cpu or cpu_only) for name, cpu_only in _KERNEL_MODULES]
    if None not in folders and not all(f.is_dir() for f in folders):
        print(f"warptex: Warp is building the kernels into {folders[0].parent} (once for this "
              "version, about half a minute)", file=sys.stderr)


# A value starting as a negative number in any notation ("-1e9", "-inf", "-32x32"); argparse
# takes only plain numbers ("-5", "-0.5") for values and reads the others as unknown options.
_NEGATIVE_NUMBER = re.compile(r"-(\.?\d|inf)", re.IGNORECASE)


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Each command's parser, by name."""
    return next(a for a in parser._actions
                if isinstance(a, argparse._SubParsersAction)).choices


def _number_options(parser: argparse.ArgumentParser) -> dict[str, int]:
    """The options of any subcommand whose values may be negative numbers (floats, integers,
    and text such as --res WxH, refused then in words of its own), and how many values
    each takes."""
    return {option: action.nargs if isinstance(action.nargs, int) else 1
            for sub in _subparsers(parser).values() for action in sub._actions
            if action.type in (float, int, None) and action.nargs != 0 and not action.choices
            for option in action.option_strings}


def _parse(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    """``argv`` parsed; an argument the command does not take is refused by the command's
    parser, which names the command (the top-level parser would show its own usage) and
    the option meant, where one is near."""
    if not argv:  # no command: what the commands are, rather than that one is missing
        parser.print_help(sys.stderr)
        parser.exit(2)
    args, unknown = parser.parse_known_args(_negative_values(argv, parser))
    if unknown:
        command = _subparsers(parser)[args.command]
        # As given, not as _negative_values passed them on.
        joined = {f"{a}={b}": f"{a} {b}" for a, b in itertools.pairwise(argv)}
        given = " ".join(joined.get(u, u.lstrip(" ")) for u in unknown)
        command.error(f"unrecognized arguments: {given}{_meant(unknown[0], parser, command)}")
    return args


def _meant(given: str, parser: argparse.ArgumentParser, command: argparse.ArgumentParser) -> str:
    """What an option ``command`` does not take may be: one of its own spelt nearly so
    (names compared without their dashes, which every long option shares), or one of
    other commands."""
    name = given.partition("=")[0]
    if not name.startswith("-"):
        return ""
    own = {o.lstrip("-"): o for o in command._option_string_actions if o.startswith("--")}
    near = difflib.get_close_matches(name.lstrip("-"), list(own), n=1, cutoff=0.75)
    if near:
        return f"; did you mean {own[near[0]]}?"
    others = [n for n, sub in _subparsers(parser).items() if name in sub._option_string_actions]
    return f"; {name} is an option of {', '.join(others)}" if others else ""


def _negative_values(argv: list[str], parser: argparse.ArgumentParser | None = None) -> list[str]:
    """``argv`` with the values of number options that are negative numbers kept from
    being read as options: joined to an option of one value (``--res=-32x32``), which
    argparse takes as it is, else given a leading space, which float() and int() ignore."""
    options = _number_options(parser or _parser())
    out = []
    i = 0
    while i < len(argv):
        values = argv[i + 1 : i + 1 + options.get(argv[i], 0)]
        if len(values) == 1 and _NEGATIVE_NUMBER.match(values[0]):
            out.append(f"{argv[i]}={values[0]}")
        else:
            out += [argv[i], *(f" {v}" if _NEGATIVE_NUMBER.match(v) else v for v in values)]
        i += 1 + len(values)
    return out


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


@contextlib.contextmanager
def _bars_as_log_lines() -> Iterator[None]:
    stream = sys.stderr
    if stream is None or stream.isatty():
        yield
        return
    sys.stderr = _LogLines(stream)
    try:
        yield
    finally:
        sys.stderr = stream


class _Terminated(KeyboardInterrupt):
    """SIGTERM, as a scheduler stops a job: raised where Ctrl-C's KeyboardInterrupt would be,
    so that the same clean-up runs (temporary files deleted, worker processes stopped)."""


# Set by SIGTERM: a library that wraps the _Terminated raised inside it (Mitsuba's scene
# loader gives its text only) hands on a plain KeyboardInterrupt, still a termination.
_terminated = threading.Event()


def _raise_terminated(signum: int, frame: object) -> None:
    _terminated.set()
    raise _Terminated


@contextlib.contextmanager
def _terminated_like_interrupted() -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():  # signals go to the main one
        yield
        return
    _terminated.clear()
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


# Libraries whose imports would lose a Ctrl-C or SIGTERM (trimesh's optional imports catch
# every exception), imported by the commands that use them before any work, stops held
# back until they are in.
_STOP_LOSING_LIBRARIES = {"bake": ("trimesh",), "cut": ("trimesh",)}


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``warptex`` with ``argv`` (default ``sys.argv[1:]``) and return the exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    _WRITTEN.clear()
    args = _parse(_parser(), argv)
    _, command = _SUBCOMMANDS[args.command]
    with warnings.catch_warnings(), _terminated_like_interrupted(), _bars_as_log_lines():
        warnings.showwarning = _show_warning
        try:
            if "exemplar_max_size" in args:  # before any work, a mesh's loading included
                _check_max_size(args)
            if args.command not in ("info", "cache"):  # the two that use no device
                _check_device()
                _note_kernel_build()
            with deferred_stops():
                for library in _STOP_LOSING_LIBRARIES.get(args.command, ()):
                    importlib.import_module(library)
            code = command(args)
            sys.stdout.flush()  # here, so that a reader gone early is handled below
            return code
        except BrokenPipeError:  # `warptex info ... | head -1`: the reader has all it wants
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 141  # as for a command that SIGPIPE ends
        except (ExemplarError, CliError) as error:
            print(f"warptex: error: {error}", file=sys.stderr)
            return error.exit_code if isinstance(error, CliError) else 2
        except KeyboardInterrupt as stop:  # outputs are renamed into place whole: none partial
            terminated = isinstance(stop, _Terminated) or _terminated.is_set()
            after = ("" if not _WRITTEN else
                     " after writing " + ", ".join(str(f) for f in dict.fromkeys(_WRITTEN)))
            print(f"\nwarptex: {'terminated' if terminated else 'interrupted'}{after}",
                  file=sys.stderr)
            return 143 if terminated else 130  # as for a command that the signal ends
