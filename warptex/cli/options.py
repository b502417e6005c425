"""The options several commands share: how exemplars are read (each of these decides the
voxels) and the settings of lazy synthesis (Dong 2008, section 5), with the exemplars and
texture they give."""

from __future__ import annotations

import argparse
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from warptex.cli.common import CliError, input_file, plural
from warptex.exemplar import Exemplar, axis_triple, srgb_encoded
from warptex.settings import (
    DEFAULT_JITTER,
    DEFAULT_PASSES,
    MIN_EXEMPLAR_SIZE,
    TILEABLE,
    SettingError,
    check_max_size,
    check_settings,
)
from warptex.srgb import color_channels

if TYPE_CHECKING:  # imported when first used, not as the command line starts
    from warptex.texture import SolidTexture

EXEMPLAR_HELP = ("exemplar image: PNG, JPEG or another format Pillow reads, OpenEXR or .npy "
                 "(README, Exemplars: how channels and alpha are read)")


def add_exemplar_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", type=input_file, metavar="EXEMPLAR", help=EXEMPLAR_HELP)
    add_loading_arguments(parser)


def add_loading_arguments(parser: argparse.ArgumentParser) -> None:
    """How exemplars are read: part of what decides the voxels, so every command that
    synthesizes offers them."""
    parser.add_argument(
        "--alpha",
        choices=("drop", "keep"),
        default="drop",
        help="drop an alpha channel (default) or keep it as a color channel",
    )
    add_feature_arguments(parser)
    add_max_size_argument(parser)
    add_tileable_argument(parser)


def add_feature_arguments(parser: argparse.ArgumentParser, advice: str = "") -> None:
    features = parser.add_mutually_exclusive_group()
    features.add_argument(
        "--feature-mask",
        type=input_file,
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


def add_tileable_argument(parser: argparse.ArgumentParser, advice: str = "") -> None:
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


def add_max_size_argument(parser: argparse.ArgumentParser, advice: str = _SCALE_ADVICE) -> None:
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


def check_max_size_option(args: argparse.Namespace) -> None:
    """Refuse a bad --exemplar-max-size; ``main`` asks before any command's work."""
    try:
        check_max_size(args.exemplar_max_size)
    except SettingError as error:
        raise CliError(f"--exemplar-max-size {error.problem}") from None


def candidate_params(args: argparse.Namespace) -> dict:
    """The candidate parameters the command's options set (others keep their defaults)."""
    return {"tileable": TILEABLE[args.tileable]}


def load_exemplar(args: argparse.Namespace, path: Path) -> Exemplar:
    """The exemplar at ``path``, read with the command's loading options."""
    return Exemplar.load(
        path,
        alpha=args.alpha,
        feature_mask=args.feature_mask,
        feature_distance=args.feature_distance,
        max_size=args.exemplar_max_size,
    )


def precompute_refusal(exemplar: Exemplar) -> str | None:
    """Why no command pre-computes the candidates of ``exemplar`` (too many channels), or
    None."""
    from warptex.candidate_set import check_feature_channels

    try:
        check_feature_channels(exemplar.features.shape[2])
    except ValueError as error:
        return str(error)
    return None


AXES = ("x", "y", "z")


def add_axis_exemplar_arguments(parser: argparse.ArgumentParser, first: str) -> None:
    parser.add_argument("--ey", type=input_file, metavar="FILE",
                        help="exemplar of the y axis: what planes y = const show, its rows "
                        f"along z and its columns along x (default: {first}, which planes "
                        "x = const show, rows along y, columns along z)")
    parser.add_argument("--ez", type=input_file, metavar="FILE",
                        help="exemplar of the z axis: what planes z = const show, its rows "
                        "along x and its columns along y (default: the y exemplar)")


def check_one_masked_exemplar(args: argparse.Namespace) -> None:
    if args.feature_mask is not None and (args.ey or args.ez):
        raise CliError("--feature-mask marks one image; use --feature-distance with --ey/--ez")


def load_axis_exemplars(args: argparse.Namespace, ex: Exemplar) -> list[Exemplar]:
    """The exemplars of the x (``ex``), y and z axes; --ey/--ez are read with the
    command's loading options (a feature mask marks one image only)."""
    check_one_masked_exemplar(args)
    ey, ez = (None if path is None else load_exemplar(args, path) for path in (args.ey, args.ez))
    return list(axis_triple(ex, ey, ez))


def alpha_kept(exemplars: Sequence[Exemplar]) -> bool:
    """Whether the last channel is an alpha: kept on every axis, as another axis' exemplar
    (a .npy file) may hold data there."""
    return all(e.kept_alpha for e in exemplars)


def add_texture_arguments(parser: argparse.ArgumentParser, first: str,
                          unset: bool = False) -> None:
    """The settings of lazy synthesis: every command given the same ones gets the same
    voxels. ``unset``: --passes and --jitter are None where not given, so that a command
    with another method can tell them given (:func:`lazy_settings_given`)."""
    add_axis_exemplar_arguments(parser, first)
    parser.add_argument("--seed", type=int, default=0,
                        help="texture variation, 0 to 2147483647 (default 0), through the "
                        "jitter's warp and --shifted-tiles: at --jitter 0 without "
                        "--shifted-tiles every seed gives the same solid")
    add_tiling_arguments(parser, unset=unset)
    parser.add_argument("--passes", type=int, default=None if unset else DEFAULT_PASSES,
                        help="correction passes per pyramid level, 0 to 8 (default 2); 3 come "
                        "closer to the exemplar at about twice the time (the repository's "
                        "docs/comparisons)")


def add_tiling_arguments(parser: argparse.ArgumentParser, advice: str = "",
                         unset: bool = False) -> None:
    """How lazy synthesis varies the tiling it starts from (Dong 2008, section 5.1)."""
    parser.add_argument("--jitter", type=float, default=None if unset else DEFAULT_JITTER,
                        help="strength of the random warp that varies the tiling, 0 to 64 "
                        f"(default 1){advice}")
    parser.add_argument("--shifted-tiles", action="store_true",
                        help="shift each tile of the initial tiling by its own offset: "
                        "structured exemplars (rust, cells) then show no bands every exemplar "
                        f"width, but follow their photo less closely (BENCHMARKS.md){advice}")


def lazy_settings_given(args: argparse.Namespace) -> list[str]:
    """The options of lazy synthesis given on the command line of a parser made with
    ``unset``, whose defaults are then filled in."""
    given = [flag for flag, value in (("--passes", args.passes), ("--jitter", args.jitter),
                                      ("--shifted-tiles", args.shifted_tiles or None))
             if value is not None]
    args.passes = DEFAULT_PASSES if args.passes is None else args.passes
    args.jitter = DEFAULT_JITTER if args.jitter is None else args.jitter
    return given


def add_raw_argument(parser: argparse.ArgumentParser, formats: str) -> None:
    parser.add_argument("--raw", action="store_true",
                        help=f"write the exemplar's values as stored; by default {formats} "
                        "get colors in the encoding their readers assume, as Mitsuba's bitmap "
                        "does (see `warptex info`)")


def colors_srgb(args: argparse.Namespace, exemplars: list[Exemplar]) -> bool | None:
    """Whether the colors to write are sRGB-encoded; None where they are written as they
    are (--raw, or a .npy output). Exemplars encoded differently are refused unless --raw,
    as a voxel's color averages colors of all three."""
    if args.raw:
        return None
    srgb = srgb_encoded(exemplars, raw="--raw")
    return None if args.output.suffix.lower() == ".npy" else srgb


def check_synthesis_arguments(jitter: float, passes: int, seed: int) -> None:
    try:
        check_settings(jitter, passes, seed)
    except SettingError as error:
        raise CliError(f"--{error.name} {error.problem}") from None


def lookup_exemplars(args: argparse.Namespace,
                     mesh: bool = False) -> tuple[list[Exemplar], bool | None]:
    """The command's exemplars, checked before any work for the points looked up in them,
    and whether their colors are sRGB-encoded (None where they are written as they are:
    see colors_srgb); for a ``mesh`` command, a warning where its files cannot hold every
    channel."""
    from warptex.store import check_lookup_channels

    exemplars = load_axis_exemplars(args, load_exemplar(args, args.exemplar))
    try:  # before pre-computing: the channels are the same on every axis, or it says which
        check_lookup_channels(exemplars[0].channels)
    except ValueError as error:
        advice = "" if precompute_refusal(exemplars[0]) else "; `warptex volume` synthesizes them"
        raise CliError(f"{args.exemplar}: {error}{advice}") from None
    channels, alpha = exemplars[0].channels, alpha_kept(exemplars)
    lost = channels - color_channels(channels, alpha)  # mesh files hold RGB (gray repeated)
    if mesh and lost:
        what = " (an alpha kept by --alpha keep)" if alpha else ""
        warnings.warn(f"mesh files hold RGB colors: {plural(lost, 'channel')} of {channels}"
                      f"{what} synthesized but not written", stacklevel=1)
    return exemplars, colors_srgb(args, exemplars)


def solid_texture(args: argparse.Namespace, exemplars: list[Exemplar]) -> SolidTexture:
    """The texture of the command's ``exemplars`` (:func:`lookup_exemplars`), their
    candidates pre-computed."""
    from warptex.candidates import precompute
    from warptex.texture import SolidTexture

    try:
        # slice, bake and cut read thin sets (a plane, a surface): synthesize just those voxels.
        return SolidTexture(precompute(*exemplars, progress=True, **candidate_params(args)),
                            seed=args.seed, jitter=args.jitter, passes=args.passes,
                            whole_bricks=False, shifted_tiles=args.shifted_tiles,
                            store=getattr(args, "store", None))
    except ValueError as error:
        raise CliError(str(error)) from None
