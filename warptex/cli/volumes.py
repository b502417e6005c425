"""``warptex volume`` and ``warptex slice``: a cube of the solid texture (lazy synthesis or
Kopf 2007) and any plane through it (Dong 2008, section 6.4)."""

from __future__ import annotations

import argparse
import itertools
import time
import warnings

import numpy as np

from warptex.cli.common import (
    CliError,
    check_at_least,
    check_finite,
    check_fits,
    check_inputs_kept,
    check_kopf_memory,
    check_kopf_size,
    check_memory,
    check_output,
    file_name,
    input_file,
    plural,
    volume_bytes,
    writing,
)
from warptex.cli.console import ticking
from warptex.cli.options import (
    AXES,
    EXEMPLAR_HELP,
    add_exemplar_arguments,
    add_loading_arguments,
    add_raw_argument,
    add_texture_arguments,
    alpha_kept,
    candidate_params,
    check_synthesis_arguments,
    colors_srgb,
    lazy_settings_given,
    load_axis_exemplars,
    load_exemplar,
    lookup_exemplars,
    solid_texture,
)
from warptex.exemplar import Exemplar
from warptex.settings import FILTERS, TILEABLE
from warptex.srgb import color_channels, reencoded
from warptex.volume_files import VOLUME_FORMATS, WRITE_COPIES, write_image, write_volume


def add_volume_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "volume", help="synthesize a cube of solid texture (Dong 2008, section 5)",
        description="Synthesize the cube of voxels [0, SIZE)^3 of the exemplar's solid texture "
        "and write it to a file. Lazy synthesis gives the same voxels as every other command "
        "with the same exemplars, loading options (--alpha, --feature-*, --exemplar-max-size), "
        "seed, jitter, passes, --shifted-tiles and --tileable; --method kopf "
        "runs the Kopf 2007 baseline instead.",
    )
    add_exemplar_arguments(parser)
    add_texture_arguments(parser, "EXEMPLAR", unset=True)  # Kopf takes none
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
    parser.add_argument("--free-axis", choices=AXES,
                        help="with --method kopf: leave planes across this axis unconstrained, "
                        "matching the exemplars of the other two only (Kopf 2007, section "
                        "6.2: for a material seen from two sides)")
    parser.add_argument(
        "-o",
        "--output",
        type=file_name,
        required=True,
        metavar="FILE",
        help="out.npy (x, y, z, channel), out.exr (z-slices side by side) or out.vol (Mitsuba 3)",
    )
    add_raw_argument(parser, ".exr and .vol (linear) files")


def run_volume(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from warptex.candidates import precompute
    from warptex.dependencies import default_apron_blocks
    from warptex.synthesis import Synthesizer, box_bytes, work_voxel_cap, work_voxels
    from warptex.warp_runtime import device

    check_output(args.output, VOLUME_FORMATS, "a volume file")
    check_inputs_kept(args, [args.output])
    check_at_least("--size", args.size, 1)
    lazy_given = lazy_settings_given(args)
    check_synthesis_arguments(args.jitter, args.passes, args.seed)
    for flag, given in (("--mean-shift", args.mean_shift), ("--free-axis", args.free_axis)):
        if given and args.method != "kopf":
            raise CliError(f"{flag} applies to --method kopf only")
    if args.free_axis is not None and getattr(args, f"e{args.free_axis}", None) is not None:
        raise CliError(f"--free-axis {args.free_axis} leaves that axis without an exemplar: "
                       f"drop --e{args.free_axis}")
    if args.free_axis == "x" and args.ey is not None:  # EXEMPLAR would be read for nothing
        raise CliError("--free-axis x leaves EXEMPLAR's axis free: give the y axis' exemplar "
                       "as EXEMPLAR, not --ey")
    if args.method == "kopf" and lazy_given:
        raise CliError(f"{', '.join(lazy_given)}: for lazy synthesis only, not --method kopf")
    if args.method == "kopf":
        check_kopf_size(args.size)
    exemplars = load_axis_exemplars(args, load_exemplar(args, args.path))
    srgb = bool(colors_srgb(args, exemplars))
    # The volume, and what writing it holds besides (decoded colors, an EXR's sheets).
    copies = 1 + WRITE_COPIES[args.output.suffix.lower()]
    if args.method == "kopf":
        check_kopf_memory(args.size, exemplars, max(2, copies))
        return _volume_kopf(args, exemplars, srgb)
    # Before the slabs are planned: a size far too large would keep that busy.
    channels = exemplars[0].features.shape[2]
    check_memory(args.size, channels, copies=copies)
    edges = _slab_edges(args.size)
    thickness = max(b - a for a, b in itertools.pairwise(edges))
    # One slab at a time, its work and colors, gone before the write's copies are made.
    slab = (box_bytes((thickness, args.size, args.size), default_apron_blocks(args.passes),
                      channels, work_voxel_cap(device(), channels, args.passes), args.passes)
            + 4 * channels * thickness * args.size**2)
    check_memory(args.size, channels, max(slab, (copies - 1) * volume_bytes(args.size, channels)),
                 copies=1)
    cs = precompute(*exemplars, progress=True, **candidate_params(args))
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
    volume = np.empty((size, size, size, cs.channels), np.float32)
    with tqdm(total=len(edges) - 1, desc="volume", unit="slab", disable=not shown) as bar:
        for x0, x1 in itertools.pairwise(edges):
            with ticking(bar):
                # Results depend on position only, so slabs along x make up the box.
                volume[x0:x1] = synth.box((x0, 0, 0), (x1 - x0, size, size))
            bar.update()
    with writing(args.output):
        write_volume(args.output, volume, srgb=srgb, alpha=alpha_kept(exemplars))
    print(f"volume: {size}^3 voxels, {plural(volume.shape[3], 'channel')}, seed {args.seed}")
    print(f"written: {args.output}")
    return 0


def _volume_kopf(args: argparse.Namespace, exemplars: list[Exemplar], srgb: bool) -> int:
    from warptex.baselines.kopf import synthesize

    constrained: list[Exemplar | None] = list(exemplars)
    if args.free_axis is not None:
        constrained[AXES.index(args.free_axis)] = None
    try:
        volume = synthesize(None, exemplars=constrained, size=args.size, seed=args.seed,
                            mean_shift=args.mean_shift, tileable=TILEABLE[args.tileable])
    except ValueError as error:
        raise CliError(str(error)) from None
    with writing(args.output):
        write_volume(args.output, volume, srgb=srgb, alpha=alpha_kept(exemplars))
    clustering = ", mean-shift clustering" if args.mean_shift else ""
    clustering += f", {args.free_axis} free" if args.free_axis else ""
    print(f"volume (Kopf 2007{clustering}): {args.size}^3 voxels, "
          f"{plural(volume.shape[3], 'channel')}, "
          f"seed {args.seed}")
    print(f"written: {args.output}")
    return 0


# The side of a cube that synthesizes in seconds at the default passes (1.4 s for 80^3 on a
# 2-core CPU): the commands show the progress of larger work.
_SECONDS_OF_WORK = 80


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


def add_slice_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "slice",
        help="evaluate the solid texture on a plane and save it as an image",
        description="Evaluate any plane through the solid texture (Dong 2008, 6.4). Pixel "
        "(r, c) shows the texture at ORIGIN + r*U + c*V, in voxels of the finest level.",
    )
    parser.add_argument("exemplar", type=input_file, metavar="EXEMPLAR", help=EXEMPLAR_HELP)
    add_loading_arguments(parser)
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
    add_texture_arguments(parser, "EXEMPLAR")
    parser.add_argument("-o", "--output", type=file_name, required=True, metavar="FILE",
                        help="output image: .png (8-bit, with alpha where --alpha keep kept "
                        "one), .exr or .npy (float)")
    add_raw_argument(parser, ".png (sRGB) and .exr (linear) images")


def run_slice(args: argparse.Namespace) -> int:
    from warptex.sheets import save_png, to_png8
    from warptex.texture import (
        POINT_LIMIT,
        plane_points,
        plane_within_limit,
        query_slabs,
        warn_unless_a_plane,
    )

    suffix = check_output(args.output, (".png", ".exr", ".npy"), "the image")
    check_inputs_kept(args, [args.output])
    h, w = args.shape
    if h < 1 or w < 1:
        raise CliError(f"--shape must be positive, got {h} {w}")
    # Per pixel: its float64 point, its place in the slabs' order and up to 4 float32
    # channels, held twice while the image is assembled.
    check_fits(h * w * (3 * 8 + 8 + 2 * 4 * 4), f"--shape {h} {w}: a slice of {h} x {w} "
               "pixels", "use a smaller --shape, or several slices")
    for name in ("origin", "u", "v"):
        check_finite(f"--{name}", getattr(args, name))
    if not plane_within_limit(args.origin, args.u, args.v, (h, w)):
        raise CliError(f"the plane reaches beyond the texture's coordinate range "
                       f"(+-{POINT_LIMIT} voxels): check --origin, --u, --v and --shape")
    warn_unless_a_plane(args.u, args.v, "--u and --v")
    check_synthesis_arguments(args.jitter, args.passes, args.seed)
    exemplars, srgb = lookup_exemplars(args)
    tex = solid_texture(args, exemplars)
    start = time.perf_counter()
    points = plane_points(args.origin, args.u, args.v, (h, w))
    image = query_slabs(tex, points, args.filter, progress="slice").reshape(h, w, -1)
    elapsed = time.perf_counter() - start
    if suffix == ".png":
        alpha = alpha_kept(exemplars)
        _note_png_losses(image, alpha)
        if srgb is not None:
            image = reencoded(image, srgb=srgb, to_srgb=True, alpha=alpha)
        with writing(args.output):
            save_png(to_png8(image, alpha), args.output)
    else:
        with writing(args.output):
            write_image(args.output, image, srgb=bool(srgb), alpha=alpha_kept(exemplars))
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
    shown = color_channels(image.shape[2], alpha) + alpha
    if image.shape[2] > shown:
        lost.append(f"{plural(image.shape[2] - shown, 'channel')} of {image.shape[2]} "
                    "dropped")
    if lost:
        kept = "RGBA" if alpha else "RGB"
        warnings.warn(f"the PNG keeps 8-bit {kept}: {' and '.join(lost)}; .exr or .npy keep "
                      "all", stacklevel=1)
