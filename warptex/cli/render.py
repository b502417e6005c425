"""``warptex render``: a Mitsuba 3 scene rendered with the ``lazy_solid`` texture."""

from __future__ import annotations

import argparse
import re

from warptex.cli.common import (
    CliError,
    WorkFailed,
    check_input_file,
    check_output,
    file_name,
    input_file,
)
from warptex.llvm import MIN_LLVM_MAJOR
from warptex.settings import MAX_SAMPLER_SEED


def add_render_parser(subparsers: argparse._SubParsersAction) -> None:
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
    parser.add_argument("scene", type=input_file, metavar="SCENE",
                        help="Mitsuba 3 scene file (.xml)")
    parser.add_argument("-o", "--output", type=file_name, required=True, metavar="FILE",
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


def run_render(args: argparse.Namespace) -> int:
    from mitsuba_plugin.command import (
        IMAGE_SUFFIXES,
        OutputError,
        parse_resolution,
        render_scene,
    )

    check_input_file(args.scene, "scene")
    check_output(args.output, IMAGE_SUFFIXES, "the image")
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
        raise WorkFailed(str(e)) from None
    return 0
