"""The ``warptex`` command line.

Each subcommand NAME has an ``_add_NAME_parser(subparsers)`` that declares its arguments and a
``_cmd_NAME(args) -> int`` that runs it; :data:`_SUBCOMMANDS` lists them.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

from warptex import __version__
from warptex.exemplar import Exemplar, ExemplarError


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


_SUBCOMMANDS: dict[
    str,
    tuple[Callable[[argparse._SubParsersAction], None], Callable[[argparse.Namespace], int]],
] = {
    "info": (_add_info_parser, _cmd_info),
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
        except ExemplarError as error:
            print(f"warptex: error: {error}", file=sys.stderr)
            return 2
