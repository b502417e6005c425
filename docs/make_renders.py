"""Regenerate docs/renders/scenes.png: the example scenes rendered with ``lazy_solid``.

    python docs/make_renders.py [--spp 64] [--res 256]

Each scene starts from an empty brick store, so the render synthesizes what it shows.
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


def main() -> None:
    import mitsuba as mi

    import mitsuba_plugin

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--res", type=int, default=256)
    args = parser.parse_args()
    mitsuba_plugin.set_best_variant()
    mitsuba_plugin.register()
    images = []
    for name, label in tqdm(SHOWN, desc="scenes"):
        scene = mi.load_file(str(SCENES / f"{name}.xml"), width=args.res, height=args.res)
        image = mitsuba_plugin.render(scene, spp=args.spp, batches=4)
        srgb = np.array(mi.util.convert_to_bitmap(image))[..., :3] / 255.0  # display colors
        images.append((label, srgb))
    save_png(sheet([("scenes", images)], cell=args.res), HERE / "renders" / "scenes.png")


if __name__ == "__main__":
    main()
