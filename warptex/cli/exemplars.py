"""``warptex info`` and ``warptex precompute``: an exemplar, and its 3D candidates (Dong 2008,
section 4)."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from warptex.cli.common import (
    CliError,
    WorkFailed,
    check_inputs_kept,
    check_output,
    check_writable_folder,
    file_name,
    writing,
)
from warptex.cli.options import (
    add_axis_exemplar_arguments,
    add_exemplar_arguments,
    candidate_params,
    load_axis_exemplars,
    load_exemplar,
    precompute_refusal,
)
from warptex.exemplar import Exemplar
from warptex.settings import TILEABLE

# Imported inside the commands that need them, so `warptex info` stays light.
if TYPE_CHECKING:
    from warptex.candidate_set import CandidateSet


def add_info_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "info", help="describe an exemplar and its pyramid",
        description="Print an exemplar's size, channels, value range and encoding (what "
        "renders see of it), Gaussian pyramid, content digest and whether its 3D candidates "
        "are cached.")
    add_exemplar_arguments(parser)


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


def run_info(args: argparse.Namespace) -> int:
    exemplar = load_exemplar(args, args.path)
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

    refusal = precompute_refusal(exemplar)
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


def add_precompute_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "precompute", help="pre-compute the 3D candidates of an exemplar (Dong 2008, section 4)",
        description="Pre-compute the 3D candidates of an exemplar (Dong 2008, section 4) into "
        "the candidate cache, which every other command reads (WARPTEX_CACHE sets its "
        "folder); prints each pyramid level's candidates per pixel and fallback pixels, "
        "then the time taken and the candidates' size.",
    )
    add_exemplar_arguments(parser)
    add_axis_exemplar_arguments(parser, "EXEMPLAR")
    parser.add_argument(
        "-o", "--output", type=file_name, metavar="FILE",
        help="also write the candidates to FILE (.wtc), to share them with another machine "
        "(warptex.CandidateSet.load reads it)",
    )
    parser.add_argument("--no-cache", action="store_true", help="neither read nor write the cache")


def run_precompute(args: argparse.Namespace) -> int:
    from warptex.candidate_set import CandidateCacheError, check_candidate_path, resolved_params
    from warptex.candidates import cache_file_there, cache_path, precompute

    if args.output is not None:
        check_output(args.output, (".wtc",), "a candidate file")
        check_inputs_kept(args, [args.output])
        try:
            check_candidate_path(args.output)
        except CandidateCacheError as error:
            raise CliError(str(error)) from None
    exemplars = load_axis_exemplars(args, load_exemplar(args, args.path))
    params = candidate_params(args)
    cache = None if args.no_cache else cache_path(exemplars, resolved_params(params))
    if cache is not None and not cache_file_there(cache):  # read, even where read-only
        _check_cache_folder(cache.parent)
    start = time.perf_counter()
    cs = precompute(*exemplars, cache=not args.no_cache, progress=True, **params)
    elapsed = time.perf_counter() - start
    if args.output is not None:
        with writing(args.output):
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
        raise WorkFailed(f"{cache}: the candidates could not be cached (the warning above "
                         "says why); WARPTEX_CACHE sets the cache folder")
    return 0


def _check_cache_folder(folder: Path) -> None:
    """The cache folder exists or can be made, and can be written: before any work."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise CliError(f"{folder}: cannot make the cache folder ({error.strerror or error}); "
                       "WARPTEX_CACHE sets it") from None
    try:
        check_writable_folder(folder, folder)
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
