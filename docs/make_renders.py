"""Regenerate docs/renders/scenes.png, the example scenes rendered with ``lazy_solid``, and
docs/renders/variants.png, the bunny in Mitsuba's RGB, spectral and monochrome variants.

    python docs/make_renders.py [--spp 64] [--res 256]

Each render starts from an empty brick store, so it synthesizes what it shows.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from tqdm import tqdm

import warptex  # noqa: F401  (before Mitsuba: points Dr.Jit at libLLVM)
from warptex.sheets import save_png, sheet

HERE = Path(__file__).resolve().parent
SCENES = HERE.parent / "scenes"
SHOWN = [("bunny_wood", "bunny carved from rosewood"),
         ("cut_sphere", "sphere cut by a plane"),
         ("wood_medium", "wood as a medium's albedo")]
KINDS = [("rgb", "RGB"), ("spectral", "spectral"), ("mono", "monochrome")]


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    parser.add_argument("--res", type=int, default=256,
                        help="width and height of each render in pixels (default 256)")
    args = parser.parse_args()
    for name in ("spp", "res"):  # else Mitsuba fails deep inside the first render
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be positive, got {getattr(args, name)}")
    import mitsuba as mi

    import mitsuba_plugin

    best = mitsuba_plugin.set_best_variant()

    def rendered(name: str) -> np.ndarray:
        """Scene ``name`` in the current variant, as display colors (H, W, 3)."""
        mitsuba_plugin.register()
        scene = mi.load_file(str(SCENES / f"{name}.xml"), width=args.res, height=args.res)
        image = mitsuba_plugin.render(scene, spp=args.spp, batches=4)
        srgb = np.array(mi.util.convert_to_bitmap(image)) / 255.0
        srgb = srgb.reshape(args.res, args.res, -1)
        return np.repeat(srgb, 3, axis=2) if srgb.shape[2] == 1 else srgb[..., :3]

    scenes = [(label, rendered(name)) for name, label in tqdm(SHOWN, desc="scenes")]
    save_png(sheet([("scenes", scenes)], cell=args.res), HERE / "renders" / "scenes.png")
    # The JIT variants where LLVM works, else the scalar ones (which have no monochrome).
    prefix = best.removesuffix("rgb")
    kinds = [(prefix + kind, label) for kind, label in KINDS if prefix + kind in mi.variants()]
    variants = []
    for variant, label in tqdm(kinds, desc="variants"):
        mitsuba_plugin.use_variant(variant)
        variants.append((f"{label} ({variant})", rendered("bunny_wood")))
    save_png(sheet([("variants", variants)], cell=args.res),
             HERE / "renders" / "variants.png")


if __name__ == "__main__":
    main()
