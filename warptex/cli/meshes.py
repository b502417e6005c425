"""``warptex bake`` and ``warptex cut``: meshes textured as if carved from the solid texture,
through the voxels around their surfaces only (Dong 2008, sections 6.2 and 6.4)."""

from __future__ import annotations

import argparse
import contextlib
import math
import time
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from warptex.archive import file_problem, file_state, one_file_twice, overwritten_input
from warptex.cli.common import (
    CliError,
    WorkFailed,
    check_at_least,
    check_finite,
    check_fits,
    check_inputs_kept,
    check_output,
    file_name,
    input_file,
    writing,
)
from warptex.cli.console import ticking
from warptex.cli.options import (
    EXEMPLAR_HELP,
    add_loading_arguments,
    add_raw_argument,
    add_texture_arguments,
    alpha_kept,
    check_synthesis_arguments,
    lookup_exemplars,
    solid_texture,
)
from warptex.exemplar import Exemplar
from warptex.srgb import color_channels

# Bytes a UV texel takes while baking: its float64 surface point, owner and coverage,
# up to 4 float32 channels three times over (colors, image, filled image), and the
# int64 indices of the nearest covered texel.
_TEXEL_BYTES = 3 * 8 + 4 + 1 + 3 * 4 * 4 + 2 * 8


# Bytes a shell voxel takes at most at once: its coordinates, their copies and sort keys
# while the shell is made, and its stored triple with its share of a partial brick (the
# bunny's shell peaked at 108-119 bytes a voxel at 1024^3 and 4096^3; 64 were counted).
_SHELL_VOXEL_BYTES = 128
# And the engine's work for one batch of shell voxels (texture.BATCH), per voxel: 1.9 GB
# for a batch of 2^20 at 2048^3, which the check left out.
_SHELL_BATCH_VOXEL_BYTES = 2048


_MAX_TEXTURE_SIZE = math.isqrt(2**31 - 1)  # texels are numbered by 32-bit integers


_TEXTURE_SIZE = 1024


def _add_mesh_arguments(parser: argparse.ArgumentParser,
                        uv_sources: Sequence[str] = ("auto", "mesh", "none")) -> None:
    parser.add_argument("mesh", type=input_file, metavar="MESH",
                        help="triangle mesh (PLY, OBJ, GLB, STL, ...)")
    parser.add_argument("--exemplar", type=input_file, required=True, metavar="EXEMPLAR",
                        help=EXEMPLAR_HELP)
    add_loading_arguments(parser)
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
    parser.add_argument("--store", type=file_name, metavar="FILE",
                        help="brick store file: voxels synthesized by an earlier run with the "
                        "same texture are read from it, and all are written back at the end, "
                        "or when Ctrl-C or SIGTERM stops the run (also usable as the "
                        "lazy_solid plugin's cache)")
    add_texture_arguments(parser, "--exemplar")
    add_raw_argument(parser, "PNG textures and PLY vertex colors (sRGB) and glTF vertex "
                     "colors (linear)")


def _check_mesh_arguments(args: argparse.Namespace, second_half: bool = False) -> list[Path]:
    """Everything about a bake or cut that can be wrong, checked before the work; returns
    the mesh files to write (a cut's second half gets the suffix _b)."""
    from warptex.mesh_files import (
        UV_TEXTURE_FORMATS,
        VERTEX_COLOR_FORMATS,
        check_obj_name,
        exported_files,
        referenced_files,
    )
    from warptex.synthesis import COORD_LIMIT

    check_at_least("--resolution", args.resolution, 1)
    if args.resolution > COORD_LIMIT // 2:
        raise CliError(f"--resolution must be at most {COORD_LIMIT // 2}, got {args.resolution}")
    if args.uv == "none" and args.texture_size is not None:
        uv = "--uv auto" + (" or mesh" if args.command == "bake" else "")  # cut makes its own
        raise CliError(f"--texture-size applies to a UV texture ({uv}), not to vertex colors")
    size = _texture_size(args)
    check_at_least("--texture-size", size, 1)
    if args.uv != "none":
        if size > _MAX_TEXTURE_SIZE:
            raise CliError(f"--texture-size must be at most {_MAX_TEXTURE_SIZE}, got {size}")
        check_fits(size * size * _TEXEL_BYTES, f"--texture-size {size}: a {size}^2 UV texture",
                   "use a smaller --texture-size")
    check_synthesis_arguments(args.jitter, args.passes, args.seed)
    if args.uv == "none":
        formats, what = VERTEX_COLOR_FORMATS, "a mesh with vertex colors (--uv none)"
    else:
        formats, what = UV_TEXTURE_FORMATS, f"a mesh with a UV texture (--uv {args.uv})"
    check_output(args.output, formats, what)
    outputs = [args.output]
    if second_half:
        outputs.append(args.output.with_stem(args.output.stem + "_b"))
        check_output(outputs[1], formats, what)
    for output in outputs:
        files = exported_files(output, uv_texture=args.uv != "none")
        if len(files) > 1:
            try:
                check_obj_name(output)
            except ValueError as error:
                raise CliError(str(error)) from None
        check_inputs_kept(args, files, args.output)
        for side in files[1:]:  # the material library and texture of an .obj
            problem = file_problem(side)
            if problem is not None:
                raise CliError(f"{side} (written with {output}): {problem}")
    written = [f for o in outputs for f in exported_files(o, uv_texture=args.uv != "none")]
    clash = overwritten_input(written, referenced_files(args.mesh))
    if clash is not None:  # an OBJ's material library or texture, say
        output, source = clash
        alias = "" if output == source else f" (as {source})"
        raise CliError(f"{output}: {args.mesh} reads this file{alias}; choose another output "
                       "name")
    twice = one_file_twice(written)  # links: the second half's name to the first's file, say
    if twice is not None:
        raise CliError(f"{twice[0]} and {twice[1]} are one file (through a link); each file "
                       "of a cut is written once: choose another output name")
    if args.store is not None:
        from warptex.store_files import StoreFileError, check_store_path

        check_output(args.store)
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

    from warptex.bake import bake_uv_texture, unwrapped, uv_layout_problems, vertex_colors
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
            mesh = in_child_process(unwrapped, mesh, while_waiting=bar.refresh)
        bar.update()
        uv = mesh.visual.uv  # _load_mesh checked --uv mesh; cut does not offer it
        size = _texture_size(args)
        bar.set_postfix_str(f"baking {size}^2 texels")
        image, covered = bake_uv_texture(tex, mesh, uv, transform, size=size)
        bar.update()
    if args.uv == "mesh":  # xatlas' own are laid out as they should be
        for problem in uv_layout_problems(uv, mesh.faces, covered, mesh.area_faces):
            warnings.warn(f"{args.mesh}: {problem}; --uv auto makes UVs of its own",
                          stacklevel=1)
    return {"mesh": mesh, "image": image, "uv": uv}


def _export_baked(baked: list[dict], outputs: list[Path], srgb: bool | None,
                  exemplars: Sequence[Exemplar]) -> list[Path]:
    """Write what :func:`_baked` made for each output, together (a cut's two halves: both
    or, where a write fails, neither), its colors in each format's encoding (``srgb``: see
    warptex.mesh_files.export); returns the files written. Mesh files hold colors only:
    data channels and a kept alpha are left out here, where they are told apart."""
    from warptex.mesh_files import mesh_files, write_files

    colors = color_channels(exemplars[0].channels, alpha_kept(exemplars))
    files = [f for b, output in zip(baked, outputs, strict=True)
             for f in mesh_files(path=output, srgb=srgb, **_colors_only(b, colors))]
    with writing(outputs[0], *(f for f, _ in files)):
        write_files(files)
    return [f for f, _ in files]


def _colors_only(baked: dict, colors: int) -> dict:
    """What :func:`_baked` made, its vertex colors or UV texture cut to the first
    ``colors`` channels."""
    return {name: value[..., :colors] if name in ("colors", "image") and value is not None
            else value for name, value in baked.items()}


@contextlib.contextmanager
def _store_saved_when_stopped(tex, args: argparse.Namespace) -> Iterator[None]:
    """A `bake` or `cut` stopped by Ctrl-C or SIGTERM, or by a kernel cache that cannot
    take a later kernel's build, saves its ``--store`` first, unless nothing was
    synthesized (:func:`~warptex.store_files.saved_if_any`): the next run starts from its
    voxels."""
    if args.store is None:
        yield
        return
    from warptex.store_files import saved_and_said, saved_if_any, saved_when_stopped
    from warptex.warp_runtime import KernelCacheError

    def save() -> list[Path]:
        return saved_if_any(tex.store, args.store, tex.save)

    with saved_when_stopped(save):
        try:
            yield
        except KernelCacheError:
            saved_and_said(save, "the kernel cache failed")
            raise


def _finish_mesh_command(tex, args: argparse.Namespace, files: list[Path], start: float) -> int:
    """What `bake` and `cut` end with: the store's report, the store saved if asked, and
    the files written."""
    _report_store(tex, args.resolution, time.perf_counter() - start)
    unchanged = ""
    if args.store is not None:
        before = file_state(args.store)
        try:
            with writing(args.store):
                saved = tex.save()
        except WorkFailed:
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


def add_bake_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "bake",
        help="texture a mesh as if carved from a block of matter, and export it",
        description="Synthesize only the voxels around the mesh surface (Dong 2008, 6.2) and "
        "write vertex colors (.ply/.glb) or a UV texture (.glb with embedded PNG, .obj+.mtl).",
    )
    _add_mesh_arguments(parser)
    parser.add_argument("-o", "--output", type=file_name, required=True, metavar="FILE",
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
        with ticking(bar):
            voxels = shell(mesh, resolution, transform)
        bar.set_postfix_str("synthesizing them", refresh=False)
        bar.reset(total=len(voxels))
        # Not query_slabs: its colors would be thrown away, and holding them, with a point
        # and an order for every shell voxel at once, would double what the shell takes in
        # memory. The shell is sorted along x, so each batch is a slab and one engine request;
        # the shell of a 512^3 block is one, of minutes, whose bar's clock must run.
        with ticking(bar):
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
    from warptex.texture import BATCH

    check_fits(voxels * _SHELL_VOXEL_BYTES + min(voxels, BATCH) * _SHELL_BATCH_VOXEL_BYTES,
               f"--resolution {resolution}: the surface passes through about {voxels:.3g} "
               "voxels, which", "lower --resolution")


def run_bake(args: argparse.Namespace) -> int:
    from warptex.surface import block_transform

    _check_mesh_arguments(args)
    mesh = _load_mesh(args.mesh, args.uv, outputs=[args.output])
    transform = block_transform(mesh, args.resolution)
    _check_shell(mesh, transform, args.resolution)
    exemplars, srgb = lookup_exemplars(args, mesh=True)
    tex = solid_texture(args, exemplars)
    start = time.perf_counter()
    with _store_saved_when_stopped(tex, args):
        count = _synthesize_shell(tex, mesh, args.resolution, transform)
        files = _export_baked([_baked(tex, mesh, transform, args, args.output.name)],
                              [args.output], srgb, exemplars)
        print(f"surface shell: {count} voxels")
        return _finish_mesh_command(tex, args, files, start)


def add_cut_parser(subparsers: argparse._SubParsersAction) -> None:
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
    parser.add_argument("-o", "--output", type=file_name, required=True, metavar="FILE",
                        help="output mesh for the first half, the side the normal points "
                        "to: .ply or .glb (vertex colors), "
                        ".glb or .obj (--uv auto), e.g. cut.ply; the second half gets the "
                        "suffix _b (cut_b.ply)")


def run_cut(args: argparse.Namespace) -> int:
    from warptex.cut import cut
    from warptex.surface import block_transform

    outputs = _check_mesh_arguments(args, second_half=True)
    check_finite("--normal", args.normal)
    if not any(args.normal):
        raise CliError("--normal must not be 0 0 0: it is the direction across the cut")
    if args.origin is not None:
        check_finite("--origin", args.origin)
    mesh = _load_mesh(args.mesh, weld=True, outputs=outputs)
    exemplars, srgb = lookup_exemplars(args, mesh=True)  # before the cut's work
    origin = np.asarray(args.origin if args.origin else mesh.bounds.mean(axis=0))
    try:
        halves = cut(mesh, origin, np.asarray(args.normal), progress=True)
    except ValueError as error:
        raise CliError(f"{args.mesh}: {error}") from None
    tex = solid_texture(args, exemplars)
    start = time.perf_counter()
    transform = block_transform(mesh, args.resolution)
    with _store_saved_when_stopped(tex, args):
        # Both halves baked before either is written: a cut stopped half way writes neither.
        baked = [_baked(tex, half, transform, args, output.name)
                 for half, output in zip(halves, outputs, strict=True)]
        return _finish_mesh_command(tex, args, _export_baked(baked, outputs, srgb, exemplars),
                                    start)
