"""The command line's parser: the commands, their help and examples, and negative numbers
read as values."""

from __future__ import annotations

import argparse
import difflib
import itertools
import re
import sys
from collections.abc import Callable
from typing import IO, NoReturn

from warptex import __version__
from warptex.cli.cache import add_cache_parser, run_cache
from warptex.cli.compare import add_compare_parser, run_compare
from warptex.cli.console import (
    StandardOutputError,
    as_standard_output_error,
    drop_unwritten_output,
)
from warptex.cli.exemplars import add_info_parser, add_precompute_parser, run_info, run_precompute
from warptex.cli.meshes import add_bake_parser, add_cut_parser, run_bake, run_cut
from warptex.cli.render import add_render_parser, run_render
from warptex.cli.volumes import add_slice_parser, add_volume_parser, run_slice, run_volume

SUBCOMMANDS: dict[
    str,
    tuple[Callable[[argparse._SubParsersAction], None], Callable[[argparse.Namespace], int]],
] = {
    "info": (add_info_parser, run_info),
    "precompute": (add_precompute_parser, run_precompute),
    "cache": (add_cache_parser, run_cache),
    "volume": (add_volume_parser, run_volume),
    "slice": (add_slice_parser, run_slice),
    "bake": (add_bake_parser, run_bake),
    "cut": (add_cut_parser, run_cut),
    "compare": (add_compare_parser, run_compare),
    "render": (add_render_parser, run_render),
}


class _Parser(argparse.ArgumentParser):
    """argparse's, but a mistake on the command line is one line naming the command, as
    every other refusal is, and says where the command's options are explained, instead
    of a usage block of many lines."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")

    def _print_message(self, message: str, file: IO[str] | None = None) -> None:
        """argparse's drops a failure to write: help sent to a full disk exited 0, as if
        shown. On standard output it fails as a command's output does: a reader gone early
        ends it quietly (141), another failure is one line and exit code 1."""
        if not message or file is not sys.stdout:
            super()._print_message(message, file)
            return
        try:
            with as_standard_output_error():
                file.write(message)
                file.flush()
        except BrokenPipeError:
            drop_unwritten_output()
            self.exit(141)
        except StandardOutputError as error:
            drop_unwritten_output()
            self.exit(1, f"{self.prog}: error: {error}\n")


def build_parser() -> argparse.ArgumentParser:
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
        "full disk, say; standard output and Warp's kernel cache included) or memory ran "
        "out past the checks' estimates, 2 input "
        "refused (before any work, a WARP_CACHE_PATH folder Warp cannot make included, or "
        "a scene Mitsuba cannot render, whose brick stores are saved first), 130 "
        "interrupted, 143 terminated "
        "(render, bake and cut save their brick stores first; an output written just before "
        "is named), 141 the reader of its "
        "output closed it (`| head`).\n\n"
        + "\n".join([_EXAMPLES_HEADING, *(e for name in ("slice", "render", "compare")
                                           for e in _EXAMPLES[name][:1])]),
    )
    parser.add_argument("--version", action="version", version=f"warptex {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (add_parser, _) in SUBCOMMANDS.items():
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


def parse_arguments(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
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
    options = _number_options(parser or build_parser())
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
