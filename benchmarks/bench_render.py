"""Render cost of ``lazy_solid`` against Mitsuba's own grid texture of the same voxels.

Scene: ``scenes/bunny_wood.xml`` at 256x256, 16 spp, its bunny made ``diffuse`` in both
variants (Mitsuba's ``volume`` texture has no ``mean()``, which ``roughplastic`` needs).
Renders, each timed after a warm-up render that compiles the kernels:

* cold: a freshly loaded scene, empty brick store, through ``mitsuba_plugin.render``
  (traced renders, the synthesis of what they missed, and the final render);
* warm: the same scene again, every brick it reads already stored: through
  ``mitsuba_plugin.render`` (one symbolic render, lookups traced) and, for reference, in
  wavefront mode (lookups in Warp kernels);
* grid: the same scene with the texture replaced by ``volume`` over a ``gridvolume``
  holding ``Synthesizer.box`` of the voxels around the bunny, rendered both in Mitsuba's
  default (symbolic, megakernel) mode and in wavefront mode.

Prints the figures and the ratio warm / grid in the default mode (target <= 1.5).
``--variant llvm_ad_spectral`` measures both textures in a spectral variant; ``--space object``
looks the texture up in the shapes' own frames (the bunny's are the world's, so the voxels are
the same), which the scalar variants pay per shading point.
"""

from __future__ import annotations

import argparse
import gc
import re
import statistics
import tempfile
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from timing import positive_int, run_record

import mitsuba_plugin
import warptex  # noqa: F401  (before Mitsuba: points Dr.Jit at libLLVM)
from warptex.srgb import srgb_to_linear

SCENES = Path(__file__).resolve().parent.parent / "scenes"
TEXTURE = re.compile(r'<texture type="lazy_solid".*?</texture>', re.S)
PLASTIC = re.compile(r'<bsdf type="roughplastic">\s*<float name="alpha" value="[^"]*"/>')


def timed(render) -> float:
    start = time.perf_counter()
    dr.eval(render())
    dr.sync_thread()
    return time.perf_counter() - start


def texture_box(scene, texture) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Origin and shape of the voxel box around the shapes that ``texture`` colours, with a
    voxel of margin for trilinear lookups (texture coordinates are ``scale`` times world
    ones: the scene gives the texture no ``to_world``)."""
    bounds = [shape.bbox() for shape in scene.shapes()
              if any(t is texture for t in mitsuba_plugin.textures(shape.bsdf()))]
    low = np.min([np.array(b.min) for b in bounds], axis=0) * texture.scale
    high = np.max([np.array(b.max) for b in bounds], axis=0) * texture.scale
    origin = np.floor(low).astype(int) - 1
    return tuple(origin.tolist()), tuple((np.ceil(high).astype(int) + 1 - origin).tolist())


def grid_xml(xml: str, vol: Path, scale: float, origin: tuple, shape: tuple) -> str:
    """The scene with the lazy_solid texture replaced by a gridvolume-backed texture of the
    voxel box ``origin``, ``shape``."""
    o = [v / scale for v in origin]
    s = [v / scale for v in shape]
    grid = (f'<texture type="volume" name="reflectance"><volume type="gridvolume" '
            f'name="volume"><string name="filename" value="{vol}"/>'
            f'<transform name="to_world"><scale x="{s[0]}" y="{s[1]}" z="{s[2]}"/>'
            f'<translate x="{o[0]}" y="{o[1]}" z="{o[2]}"/></transform></volume></texture>')
    return TEXTURE.sub(grid, xml)


def diffuse_xml(xml: str) -> str:
    """The scene with its rough plastic bunny made diffuse, same texture."""
    xml = PLASTIC.sub('<bsdf type="diffuse">', xml)
    return xml.replace('name="diffuse_reflectance"', 'name="reflectance"')


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--res", type=positive_int, default=256)
    parser.add_argument("--spp", type=positive_int, default=16)
    parser.add_argument("--repeat", type=positive_int, default=3)
    parser.add_argument("--variant", help="Mitsuba variant (default: the best RGB one)")
    parser.add_argument("--space", choices=("world", "object"), default="world",
                        help="the texture's space property (default world)")
    args = parser.parse_args()
    print(run_record(), flush=True)
    variant = (mitsuba_plugin.use_variant(args.variant) if args.variant
               else mitsuba_plugin.set_best_variant())
    mitsuba_plugin.register()
    path = SCENES / "bunny_wood.xml"
    size = {"width": args.res, "height": args.res}

    def render(scene, mode="plugin"):
        if mode == "plugin":
            return lambda: mitsuba_plugin.render(scene, spp=args.spp)
        if mode == "wavefront":
            def in_wavefront():
                with mitsuba_plugin.wavefront():
                    return mi.render(scene, spp=args.spp)
            return in_wavefront
        return lambda: mi.render(scene, spp=args.spp)

    mi.file_resolver().prepend(str(SCENES))
    xml = diffuse_xml(path.read_text())
    lazy = '<texture type="lazy_solid" name="reflectance">'
    assert lazy in xml, "the bunny scene's texture is not where this script looks for it"
    xml = xml.replace(lazy, f'{lazy}<string name="space" value="{args.space}"/>')
    # Warm-up on a throw-away scene of the same size, its own empty store, so that the cold
    # figure is synthesis, not compilation: Dr.Jit compiles a program per image size.
    timed(render(mi.load_string(xml, **size)))
    scene = mi.load_string(xml, **size)
    texture = next(t for t in mitsuba_plugin.textures()
                   if t.solid.store.stats()["bricks"] == 0)
    cold = timed(render(scene))
    stats = texture.solid.store.stats()
    rounds = texture.traced_stats()
    scalar = texture.scalar_stats()
    warm = [timed(render(scene)) for _ in range(args.repeat)]
    timed(render(scene, "wavefront"))
    warm_wavefront = [timed(render(scene, "wavefront")) for _ in range(args.repeat)]

    origin, shape = texture_box(scene, texture)
    start = time.perf_counter()
    box = texture.solid.synthesizer.box(origin, shape)[..., :3]
    box_seconds = time.perf_counter() - start
    box = srgb_to_linear(box)  # the colors the plugin renders, decoded from the PNG's sRGB
    scale = texture.scale
    # A symbolic render traces every live BSDF, so no lazy_solid may be left for it.
    del scene, texture
    gc.collect()
    with tempfile.TemporaryDirectory() as tmp:
        vol = Path(tmp) / "bunny.vol"
        mi.VolumeGrid(np.ascontiguousarray(box.transpose(2, 1, 0, 3))).write(str(vol))
        grid = mi.load_string(grid_xml(xml, vol, scale, origin, shape), **size)
        timed(render(grid, "default"))
        grid_default = [timed(render(grid, "default")) for _ in range(args.repeat)]
        timed(render(grid, "wavefront"))
        grid_wavefront = [timed(render(grid, "wavefront")) for _ in range(args.repeat)]

    w, ww, g, gw = (statistics.median(x)
                    for x in (warm, warm_wavefront, grid_default, grid_wavefront))
    print(f"variant {variant}, {args.res}x{args.res}, {args.spp} spp, median of {args.repeat}, "
          f"space {args.space}")
    served = (f"{rounds['renders']} traced renders, {rounds['renders_with_misses']} of them "
              "with misses" if scalar is None else
              f"{scalar['hits']} points from brick copies, {scalar['misses']} left to the store")
    print(f"cold lazy_solid render:   {cold:6.2f} s  "
          f"(synthesis {stats['synthesis_seconds']:.2f} s, {stats['bricks']} bricks, {served})")
    print(f"warm lazy_solid render:   {w:6.2f} s  {[round(x, 2) for x in warm]}")
    print(f"warm, wavefront mode:     {ww:6.2f} s  {[round(x, 2) for x in warm_wavefront]}")
    print(f"gridvolume, default mode: {g:6.2f} s  {[round(x, 2) for x in grid_default]}")
    print(f"gridvolume, wavefront:    {gw:6.2f} s  {[round(x, 2) for x in grid_wavefront]}")
    print(f"grid synthesis (Synthesizer.box {shape} at {origin}): {box_seconds:.2f} s")
    print(f"ratio warm / grid default:   {w / g:.2f}  (target <= 1.5)")
    print(f"ratio warm wavefront / grid wavefront: {ww / gw:.2f}")


if __name__ == "__main__":
    main()
