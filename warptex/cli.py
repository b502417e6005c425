"""The ``warptex`` command line.

Each subcommand NAME has an ``_add_NAME_parser(subparsers)`` that declares its arguments and a
``_cmd_NAME(args) -> int`` that runs it; :data:`_SUBCOMMANDS` lists them.
"""

from __future__ import annotations

import argparse
import itertools
import os
import struct
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from warptex import __version__
from warptex.exemplar import Exemplar, ExemplarError

# Imported inside the commands that need them, so `warptex info` stays light.
if TYPE_CHECKING:
    from warptex.candidates import CandidateSet


class CliError(Exception):
    """A user error a command reports as ``warptex: error: ...`` with exit code 2."""


def _add_exemplar_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", type=Path, help="exemplar image (PNG, JPEG, OpenEXR or .npy)")
    parser.add_argument(
        "--alpha",
        choices=("drop", "keep"),
        default="drop",
        help="drop an alpha channel (default) or keep it as a color channel",
    )
    features = parser.add_mutually_exclusive_group()
    features.add_argument(
        "--feature-mask",
        type=Path,
        metavar="MASK",
        help="binary image marking features; adds a feature-distance channel",
    )
    features.add_argument(
        "--feature-distance",
        action="store_const",
        const="auto",
        default=False,
        help="add a feature-distance channel from an automatic luminance threshold",
    )


def _load_exemplar(args: argparse.Namespace) -> Exemplar:
    return Exemplar.load(
        args.path,
        alpha=args.alpha,
        feature_mask=args.feature_mask,
        feature_distance=args.feature_distance,
    )


def _add_info_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("info", help="describe an exemplar and its pyramid")
    _add_exemplar_arguments(parser)


def _cmd_info(args: argparse.Namespace) -> int:
    exemplar = _load_exemplar(args)
    height, width = exemplar.shape
    print(f"file: {exemplar.path}")
    print(f"size: {width} x {height} pixels (width x height)")
    feature_note = " + feature distance" if exemplar.features.shape[2] > exemplar.channels else ""
    print(f"channels: {exemplar.channels}{feature_note}")
    print("value range:")
    low = exemplar.colors.min(axis=(0, 1))
    high = exemplar.colors.max(axis=(0, 1))
    for channel, (lo, hi) in enumerate(zip(low, high, strict=True)):
        print(f"  channel {channel}: {lo:.4f} .. {hi:.4f}")
    levels = exemplar.pyramid()
    sizes = ", ".join(f"{level.shape[1]}x{level.shape[0]}" for level in levels)
    print(f"pyramid: {len(levels)} levels ({sizes})")
    print(f"digest: {exemplar.digest()[:16]}")
    print(f"candidates: {_candidate_status(exemplar)}")
    return 0


def _candidate_status(exemplar: Exemplar) -> str:
    try:
        from warptex.candidates import cached_candidate_path
    except ModuleNotFoundError as error:
        if error.name != "warptex.candidates":
            raise
        return "not available"
    cached = cached_candidate_path(exemplar)
    return f"cached at {cached}" if cached is not None else "not cached"


def _add_precompute_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "precompute", help="pre-compute the 3D candidates of an exemplar (Dong 2008, section 4)"
    )
    _add_exemplar_arguments(parser)
    parser.add_argument(
        "--ey", type=Path, metavar="F", help="exemplar of the y axis (default: EXEMPLAR)"
    )
    parser.add_argument(
        "--ez", type=Path, metavar="F", help="exemplar of the z axis (default: the y exemplar)"
    )
    parser.add_argument(
        "-o", "--output", type=Path, metavar="FILE", help="also write the candidates to FILE"
    )
    parser.add_argument("--no-cache", action="store_true", help="neither read nor write the cache")


def _cmd_precompute(args: argparse.Namespace) -> int:
    from warptex.candidates import DEFAULT_PARAMS, cache_path, precompute

    exemplars = _load_axis_exemplars(args)
    cache = None if args.no_cache else cache_path(exemplars, dict(DEFAULT_PARAMS))
    before = _file_identity(cache)
    start = time.perf_counter()
    cs = precompute(*exemplars, cache=not args.no_cache, progress=True)
    elapsed = time.perf_counter() - start
    if args.output is not None:
        try:
            cs.save(args.output)  # atomic itself: temporary name, then rename
        except OSError as error:
            raise CliError(f"{args.output}: cannot write ({error.strerror or error})") from None
    # precompute leaves a good cache file untouched and replaces a missing or damaged one.
    loaded = before is not None and before == _file_identity(cache)
    _print_summary(cs, exemplars, elapsed)
    if loaded:
        print(f"loaded from cache: {cache}")
    elif cache is not None:
        print(f"written: {cache} (cache)")
    if args.output is not None:
        print(f"written: {args.output}")
    elif cache is None:
        print("written: nothing (--no-cache without -o)")
    return 0


def _load_axis_exemplars(args: argparse.Namespace) -> list[Exemplar]:
    """The exemplars of the x, y and z axes; --ey/--ez take the same loading options."""
    ex = _load_exemplar(args)
    if args.feature_mask is not None and (args.ey or args.ez):
        raise CliError("--feature-mask marks one image; use --feature-distance with --ey/--ez")
    others = [
        Exemplar.load(path, alpha=args.alpha, feature_distance=args.feature_distance)
        if path is not None
        else None
        for path in (args.ey, args.ez)
    ]
    ey = others[0] or ex
    return [ex, ey, others[1] or ey]


def _file_identity(path: Path | None) -> tuple[int, int] | None:
    """(inode, mtime) of a file, or None: tells whether a file was replaced meanwhile."""
    if path is None:
        return None
    try:
        stat = path.stat()
    except FileNotFoundError:
        return None
    return stat.st_ino, stat.st_mtime_ns


def _print_summary(cs: CandidateSet, exemplars: list[Exemplar], elapsed: float) -> None:
    """Levels, candidates per pixel (4.2), fallback pixels, time and bytes (issue 3)."""
    names = [e.name for e in exemplars]
    if cs.shared:
        print(f"exemplar: {names[0]} on all three axes (candidates shared)")
    else:
        print(f"exemplars: x {names[0]}, y {names[1]}, z {names[2]} ({len(cs.roles[0])} roles)")
    print(f"levels: {cs.num_levels}")
    sizes = ["/".join(f"{s.size[1]}x{s.size[0]}" for s in lvl) for lvl in cs.sources]
    width = max(len("size"), *map(len, sizes))
    print(f"  level  {'size':<{width}}  candidates/pixel  fallback pixels")
    for level, roles in enumerate(cs.roles):
        mean = np.concatenate([r.count for r in roles]).mean()
        fallback = sum(int(r.fallback.sum()) for r in roles)
        print(f"  {level:<5}  {sizes[level]:<{width}}  {mean:16.2f}  {fallback:15d}")
    print(f"time: {elapsed:.2f} s")
    print(f"bytes: {cs.nbytes()} ({cs.nbytes() / 1024:.1f} KiB)")


_VOLUME_FORMATS = (".npy", ".exr", ".vol")


def _add_volume_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "volume", help="synthesize a cube of solid texture (Dong 2008, section 5)"
    )
    _add_exemplar_arguments(parser)
    parser.add_argument("--size", type=int, default=64, help="edge of the cube in voxels (64)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (0)")
    parser.add_argument("--jitter", type=float, default=1.0, help="initial jitter (1.0)")
    parser.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        metavar="FILE",
        help="out.npy (x, y, z, channel), out.exr (z-slices side by side) or out.vol (Mitsuba 3)",
    )


def _cmd_volume(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from warptex.candidates import precompute
    from warptex.synthesis import Synthesizer

    suffix = args.output.suffix.lower()
    if suffix not in _VOLUME_FORMATS:
        raise CliError(
            f"{args.output}: unknown volume format {suffix or '(no extension)'!r}; "
            f"use {', '.join(_VOLUME_FORMATS)}"
        )
    if args.size < 1:
        raise CliError(f"--size must be at least 1, got {args.size}")
    cs = precompute(_load_exemplar(args), progress=True)
    try:
        synth = Synthesizer(cs, seed=args.seed, jitter=args.jitter)
    except ValueError as error:
        raise CliError(str(error)) from None
    size = args.size
    # Results depend on position only, so slabs along x concatenate to the whole box.
    edges = np.linspace(0, size, min(8, size) + 1).astype(int).tolist()
    slabs = [
        synth.box((x0, 0, 0), (x1 - x0, size, size))
        for x0, x1 in tqdm(list(itertools.pairwise(edges)), desc="volume", unit="slab")
    ]
    volume = np.concatenate(slabs, axis=0)
    writer = {".npy": _write_npy, ".exr": _write_exr, ".vol": _write_vol}[suffix]
    _write_atomically(args.output, lambda path: writer(path, volume))
    print(f"volume: {size}^3 voxels, {volume.shape[3]} channels, seed {args.seed}")
    print(f"written: {args.output}")
    return 0


def _write_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """Write through a temporary name beside ``path``, then rename: readers never see a
    partial file."""
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            write(tmp)
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
    except OSError as error:
        raise CliError(f"{path}: cannot write ({error.strerror or error})") from None


def _write_npy(path: Path, volume: np.ndarray) -> None:
    with open(path, "wb") as file:
        np.save(file, volume)


def _exr_channel_names(channels: int) -> list[str]:
    if channels == 1:
        return ["Y"]
    if channels in (3, 4):
        return list("RGBA"[:channels])
    return [f"C{c}" for c in range(channels)]


def exr_sheet(volume: np.ndarray) -> np.ndarray:
    """The z-slices of an (X, Y, Z, C) volume side by side: pixel (row y, column z*X + x)
    holds voxel (x, y, z), so the sheet is Y rows by Z*X columns."""
    x, y, z, c = volume.shape
    return volume.transpose(1, 2, 0, 3).reshape(y, z * x, c)


def _write_exr(path: Path, volume: np.ndarray) -> None:
    """One single-part scanline OpenEXR image, float32, of the z-slices side by side."""
    import OpenEXR

    sheet = exr_sheet(volume)
    names = _exr_channel_names(sheet.shape[2])
    x, y, z, _ = volume.shape
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "warptexLayout": f"z-slices side by side, {x}x{y}x{z} voxels (x, y, z)",
    }
    pixels = {name: np.ascontiguousarray(sheet[..., c]) for c, name in enumerate(names)}
    with OpenEXR.File(header, pixels) as file:
        file.write(str(path))


def _write_vol(path: Path, volume: np.ndarray) -> None:
    """Mitsuba 3 grid volume: b'VOL', version 3, float32 encoding, x fastest."""
    x, y, z, c = volume.shape
    header = b"VOL" + struct.pack("<B4i", 3, 1, x, y, z) + struct.pack("<i6f", c, 0, 0, 0, 1, 1, 1)
    # Data index ((z * Y + y) * X + x) * C + c: transpose (x, y, z, c) to (z, y, x, c).
    data = np.ascontiguousarray(volume.transpose(2, 1, 0, 3), dtype="<f4")
    with open(path, "wb") as file:
        file.write(header)
        file.write(data.tobytes())


_SUBCOMMANDS: dict[
    str,
    tuple[Callable[[argparse._SubParsersAction], None], Callable[[argparse.Namespace], int]],
] = {
    "info": (_add_info_parser, _cmd_info),
    "precompute": (_add_precompute_parser, _cmd_precompute),
    "volume": (_add_volume_parser, _cmd_volume),
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="warptex", description="Lazy solid texture synthesis from 2D exemplars."
    )
    parser.add_argument("--version", action="version", version=f"warptex {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add_parser, _ in _SUBCOMMANDS.values():
        add_parser(subparsers)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    # A user of the command needs the message, not the source line that raised it.
    print(f"warptex: warning: {message}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``warptex`` with ``argv`` (default ``sys.argv[1:]``) and return the exit code."""
    args = _parser().parse_args(argv)
    _, command = _SUBCOMMANDS[args.command]
    with warnings.catch_warnings():
        warnings.showwarning = _show_warning
        try:
            return command(args)
        except (ExemplarError, CliError) as error:
            print(f"warptex: error: {error}", file=sys.stderr)
            return 2
