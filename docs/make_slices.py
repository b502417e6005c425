"""Regenerate docs/slices/*.png: exemplars beside slices of 64^3 lazily synthesized volumes.

    python docs/make_slices.py [--exemplars DIR]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tqdm import tqdm

from warptex.candidates import precompute
from warptex.exemplar import Exemplar
from warptex.sheets import save_png, sheet, volume_row
from warptex.synthesis import Synthesizer

HERE = Path(__file__).resolve().parent
NAMES = ["granite_64", "rocks_in_sand_64", "gravel_gray_64", "marble_black_64", "rust_64",
         "dry_mud_64", "cells_ihc_64", "wood_rosewood_64", "bricks_red_64", "onyx_banded_64"]


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    shared = HERE.parent.parent / "shared" / "data" / "exemplars"
    parser.add_argument("--exemplars", type=Path, default=shared,
                        help=f"folder of the exemplar photos (default {shared})")
    args = parser.parse_args()
    missing = [f"{n}.png" for n in NAMES if not (args.exemplars / f"{n}.png").is_file()]
    if missing:
        parser.error(f"{args.exemplars} lacks {', '.join(missing)}: give the folder of the "
                     "exemplar photos with --exemplars")
    rows = []
    for name in tqdm(NAMES, desc="volumes"):
        ex = Exemplar.load(args.exemplars / f"{name}.png")
        vol = Synthesizer(precompute(ex), seed=1).box((0, 0, 0), (64, 64, 64))
        rows.append((name.removesuffix("_64"), [("exemplar", ex.colors), *volume_row(vol)]))
    # The sheets say what they show: a picture is often seen away from the README.
    title = ("lazy solid synthesis (Dong 2008), 64^3 from voxel (0, 0, 0), seed 1: each "
             "exemplar, then the middle slice across x, y and z")
    save_png(sheet(rows[:5], title=title), HERE / "slices" / "isotropic.png")
    save_png(sheet(rows[5:], title=title), HERE / "slices" / "structured.png")


if __name__ == "__main__":
    main()
