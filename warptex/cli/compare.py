"""``warptex compare``: methods side by side on one exemplar, a picture sheet and a score
table (Dong 2008, sections 6.3-6.4)."""

from __future__ import annotations

import argparse

from warptex.cli.common import (
    CliError,
    WorkFailed,
    check_at_least,
    check_inputs_kept,
    check_kopf_memory,
    check_kopf_size,
    check_memory,
    check_writable_folder,
    folder_name,
    input_file,
    writing,
)
from warptex.cli.options import (
    EXEMPLAR_HELP,
    add_axis_exemplar_arguments,
    add_feature_arguments,
    add_max_size_argument,
    add_tileable_argument,
    add_tiling_arguments,
    check_one_masked_exemplar,
    check_synthesis_arguments,
)
from warptex.settings import DEFAULT_PASSES, TILEABLE


def add_compare_parser(subparsers: argparse._SubParsersAction) -> None:
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
    parser.add_argument("exemplar", type=input_file, metavar="EXEMPLAR", help=EXEMPLAR_HELP)
    add_axis_exemplar_arguments(parser, "EXEMPLAR")
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
    add_tiling_arguments(parser, advice="; for the lazy and tiled methods")
    parser.add_argument("--repeats", type=int, default=1, metavar="N",
                        help="time each method N times and report the median, every run "
                        "kept in table.json (default 1)")
    add_max_size_argument(parser, advice="; every method reads the shrunk images")
    add_feature_arguments(parser, advice=", which lazy synthesis and Kopf match beside the "
                          "colors (the measures take colors only)")
    add_tileable_argument(parser, advice="; for lazy, tiled and Kopf, and for the measures, "
                          "whose exemplar neighbourhoods wrap only where synthesis may")
    parser.add_argument("-o", "--output", type=folder_name, required=True, metavar="DIR",
                        help="output folder")


def run_compare(args: argparse.Namespace) -> int:
    from warptex.compare import (
        MIN_SIZE,
        Setup,
        check_methods,
        compare,
        report_files,
        table_markdown,
        write_report,
    )

    check_synthesis_arguments(args.jitter, args.passes, args.seed)
    check_at_least("--size", args.size, MIN_SIZE)
    check_at_least("--repeats", args.repeats, 1)
    check_one_masked_exemplar(args)
    setup = Setup(args.exemplar, args.size, seed=args.seed, passes=args.passes,
                  jitter=args.jitter, shifted_tiles=args.shifted_tiles,
                  max_size=args.exemplar_max_size, tileable=TILEABLE[args.tileable],
                  feature_distance=bool(args.feature_distance),
                  feature_mask=args.feature_mask, ey=args.ey, ez=args.ez)
    # One clear error for a bad image before any work.
    exemplar = setup.exemplars()[0]
    check_writable_folder(args.output, args.output)
    try:  # a folder in a report file's place: before minutes of work
        report = report_files(args.output)
    except ValueError as error:
        raise CliError(str(error)) from None
    check_inputs_kept(args, report)
    check_memory(args.size, exemplar.features.shape[2])  # each method holds its volume
    try:  # before the checks of the methods named (Kopf's sizes)
        methods = check_methods(m.strip() for m in args.methods.split(",") if m.strip())
    except ValueError as error:
        raise CliError(f"--methods: {error}") from None
    if any(m.startswith("kopf") for m in methods):
        check_kopf_size(args.size)
        check_kopf_memory(args.size, setup.exemplars())
    try:
        comparison = compare(setup, methods, repeats=args.repeats)
    except ValueError as error:
        raise CliError(str(error)) from None
    with writing(args.output, *report):
        try:
            files = write_report(comparison, args.output)
        except ValueError as error:  # the folder became unwritable during the work
            raise WorkFailed(str(error)) from None
    print(table_markdown(comparison.results))
    print("written: " + ", ".join(str(f) for f in files))
    return 0
