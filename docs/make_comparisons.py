"""Regenerate docs/comparisons/: `warptex compare` on every exemplar at 64^3, and an index.

The index also reports lazy synthesis with 3 correction passes per level: a second
`compare` of the lazy method alone, whose sheet is not kept.

    python docs/make_comparisons.py [--exemplars DIR] [--size 64]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from warptex.archive import write_atomically
from warptex.baselines.kopf import check_size
from warptex.compare import (
    METHODS,
    REPORT_FILES,
    Setup,
    compare,
    large_edge,
    run_line,
    run_summary,
    write_report,
)

HERE = Path(__file__).resolve().parent
MORE_PASSES = 3  # the quality setting the index reports beside the default


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    shared = HERE.parent.parent / "shared" / "data" / "exemplars"
    parser.add_argument("--exemplars", type=Path, default=shared,
                        help=f"folder of the exemplar photos, *_64.png (default {shared})")
    parser.add_argument("--size", type=int, default=64,
                        help="edge of each method's volume in voxels (default 64)")
    args = parser.parse_args()
    try:  # every method runs, Kopf's among them: its size rule, before minutes of work
        check_size(args.size)
    except ValueError as error:
        parser.error(f"--size: {error}")
    if not any(args.exemplars.glob("*_64.png")):
        parser.error(f"{args.exemplars} holds no *_64.png exemplars: give the folder of the "
                     "exemplar photos with --exemplars")
    out = HERE / "comparisons"
    run = run_line(run_summary(args.size, 0))
    lines = [
        f"# Comparisons at {args.size}^3",
        "",
        "`warptex compare` on each exemplar (64 px version); per exemplar a picture sheet",
        "(the middle slices across x, y, z and a rendered cube per method) and a table.",
        "Regenerate with `python docs/make_comparisons.py`. Worst-axis neighbourhood energy",
        "(lower is better, but it rewards blur: `flat`, the exemplar's mean color everywhere,",
        "is no texture),",
        "the worst-axis bidirectional energy (the neighbourhood energy plus completeness,",
        "each exemplar patch's distance to the nearest slice patch, which blur does not win;",
        "`warptex.metrics`),",
        "time (one run in a fresh process; the lazy engine's pre-computation of candidates,",
        "computed afresh, apart) and the repetition score over a slice at least "
        f"{large_edge(args.size)} voxels wide (twice a larger exemplar's edge: each "
        "table.json's `repetition_slice`); `kopf`",
        "averages plainly, `kopf-ms` is Kopf with mean-shift clustering (`kopf-meanshift` in",
        f"the sheets); `lazy-{MORE_PASSES}` is lazy synthesis with {MORE_PASSES} correction "
        f"passes per level (`--passes {MORE_PASSES}`, not in the sheets). Measured on {run}:",
        "",
        "| exemplar | lazy energy | kopf energy | lazy / kopf | kopf-ms energy | lazy / kopf-ms "
        f"| lazy-{MORE_PASSES} energy | lazy-{MORE_PASSES} / kopf | flat energy "
        "| lazy bidirectional | kopf bidirectional | lazy / kopf | flat bidirectional "
        "| lazy s | lazy pre-computation s | kopf s | kopf-ms s | kopf / lazy time "
        f"| kopf-ms / lazy time | lazy-{MORE_PASSES} s | lazy repetition | tiled repetition |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
        "---|",
    ]
    # Minutes per exemplar, an hour in all: a bar over the exemplars, and compare's own,
    # which names the method and what it does.
    photos = sorted(args.exemplars.glob("*_64.png"))
    for path in tqdm(photos, desc="exemplars"):
        name = path.stem.removesuffix("_64")
        comparison = compare(Setup(path, args.size), METHODS)
        write_report(comparison, out / name)
        r = {m.method: m for m in comparison.results}
        (more,) = compare(Setup(path, args.size, passes=MORE_PASSES), ["lazy"]).results
        lazy, kopf, ms, flat = (max(r[m].energy) for m in ("lazy", "kopf", "kopf-meanshift",
                                                           "flat"))
        seconds = {m: r[m].seconds for m in ("lazy", "kopf", "kopf-meanshift")}
        both = {m: max(e + c for e, c in zip(r[m].energy, r[m].completeness, strict=True))
                for m in ("lazy", "kopf", "flat")}
        lines.append(
            f"| [{name}]({name}/sheet.png) | {lazy:.3f} | {kopf:.3f} | {lazy / kopf:.2f} | "
            f"{ms:.3f} | {lazy / ms:.2f} | {max(more.energy):.3f} | "
            f"{max(more.energy) / kopf:.2f} | {flat:.3f} | {both['lazy']:.3f} | "
            f"{both['kopf']:.3f} | {both['lazy'] / both['kopf']:.2f} | {both['flat']:.3f} | "
            f"{seconds['lazy']:.2f} | "
            f"{r['lazy'].precompute_seconds:.2f} | {seconds['kopf']:.1f} | "
            f"{seconds['kopf-meanshift']:.1f} | {seconds['kopf'] / seconds['lazy']:.0f} | "
            f"{seconds['kopf-meanshift'] / seconds['lazy']:.0f} | {more.seconds:.2f} | "
            f"{r['lazy'].repetition:.3f} | {r['tiled'].repetition:.3f} |"
        )
        tqdm.write(lines[-1])
    text = "\n".join(lines) + "\n"
    write_atomically(out / "README.md", lambda tmp: tmp.write_text(text))
    _remove_unlisted(out, {path.stem.removesuffix("_64") for path in photos})


def _remove_unlisted(out: Path, names: set[str]) -> None:
    """Remove the reports of exemplars this run did not compare: the index no longer
    lists them, and their numbers came from another run, perhaps of other code."""
    for folder in sorted(p for p in out.iterdir() if p.is_dir() and p.name not in names):
        files = [folder / name for name in REPORT_FILES]
        if all(f.is_file() for f in files):
            for f in files:
                f.unlink()
            if not any(folder.iterdir()):
                folder.rmdir()
            tqdm.write(f"removed {folder}: an exemplar this run did not compare", file=sys.stderr)


if __name__ == "__main__":
    main()
