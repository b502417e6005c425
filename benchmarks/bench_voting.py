"""Colour voting after lazy synthesis: an experiment for issue 7's energy bar, not in the engine.

Dong 2008 (section 5.1) colours a voxel by averaging the three exemplar colours of its
triple. Kopf 2007 (section 4.2, optimization phase) instead averages, for each voxel, the
colours that every overlapping neighbourhood's match predicts for it. This script applies
that vote once to the engine's final triples: each in-plane neighbour v + d of voxel v
(3 planes, offsets up to ``--radius``) predicts exemplar pixel p(v + d) - d for v. Votes are
averaged plainly, or bilaterally (weight exp(-|c - c_v|^2 / (2 sigma^2 var)) against the
engine's colour c_v, var the exemplar's variance), which keeps edges.

Prints the worst-axis neighbourhood energy of 64^3 boxes per variant beside the bar's
target (1.25x plain Kopf, from docs/comparisons/README.md), and what a 128^2 cut of the
last exemplar costs with and without the vote's extra reach; writes a sheet of crops to
docs/experiments/colour_voting.png.

    python benchmarks/bench_voting.py [--names granite rocks_in_sand] [--passes 2 3]
"""

from __future__ import annotations

import argparse
import re
import time
from pathlib import Path

import numpy as np
from timing import exemplar_files, run_record
from tqdm import tqdm

from warptex import metrics
from warptex.candidate_set import CandidateSet
from warptex.candidates import precompute
from warptex.exemplar import Exemplar
from warptex.sheets import save_png, sheet
from warptex.synthesis import Synthesizer

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DIR = ROOT.parent / "shared" / "data" / "exemplars"
SIZE = 64
SIGMAS = (0.3, 0.5)


def kopf_targets() -> dict[str, float]:
    """1.25x plain Kopf's worst-axis energy per exemplar, from the comparison table."""
    table = (ROOT / "docs" / "comparisons" / "README.md").read_text()
    out = {}
    for line in table.splitlines():
        m = re.match(r"\| \[(\w+)\]\([^)]*\) \| [\d.]+ \| ([\d.]+) \|", line)
        if m:
            out[m.group(1)] = 1.25 * float(m.group(2))
    return out


def vote(cs: CandidateSet, triples: np.ndarray, own: np.ndarray, radius: int,
         sigma: float | None) -> np.ndarray:
    """Voted colours of the inner box of ``triples`` (B, B, B, 3, 2) (rows, columns of each
    axis' exemplar), ``radius`` voxels in from each side; ``own`` holds the engine's
    colours of that inner box."""
    inner = triples.shape[0] - 2 * radius
    var = float(cs.colors[cs.axis_source[0]].reshape(-1, cs.channels).var(axis=0).sum())
    acc = np.zeros_like(own)
    weight = np.zeros((*own.shape[:3], 1), np.float32)
    for k in range(3):
        image = cs.colors[cs.axis_source[k]]
        h, w = image.shape[:2]
        for du in range(-radius, radius + 1):
            for dv in range(-radius, radius + 1):
                d = [0, 0, 0]
                d[(k + 1) % 3], d[(k + 2) % 3] = du, dv
                window = tuple(slice(radius + d[a], radius + d[a] + inner) for a in range(3))
                pix = triples[(*window, k)]
                c = image[(pix[..., 0] - du) % h, (pix[..., 1] - dv) % w]
                wt = np.ones((*c.shape[:3], 1), np.float32)
                if sigma is not None:
                    dist = ((c - own) ** 2).sum(axis=-1, keepdims=True)
                    wt = np.exp(-dist / (2.0 * sigma**2 * var)).astype(np.float32)
                acc += wt * c
                weight += wt
    return acc / weight


def cut_cost(cs: CandidateSet, passes: int, radius: int) -> tuple[int, float]:
    """Finest-level voxels corrected and seconds for a fresh engine to give a 128^2 cut
    (x = 0) whose colours read ``radius`` voxels off the cut."""
    yz = np.indices((128, 128)).reshape(2, -1).T
    slab = np.concatenate([np.column_stack([np.full(len(yz), x), yz])
                           for x in range(-radius, radius + 1)])
    synth = Synthesizer(cs, seed=0, passes=passes)
    start = time.perf_counter()
    synth.triples(slab)
    return synth.voxels_synthesized[synth.finest], time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--exemplars", type=Path, default=DEFAULT_DIR)
    parser.add_argument("--names", nargs="+", default=None,
                        help="exemplar names without _64 (default: every *_64.png)")
    parser.add_argument("--passes", type=int, nargs="+", default=[2, 3])
    parser.add_argument("--radius", type=int, default=1)
    parser.add_argument("--sheet", type=Path, default=ROOT / "docs" / "experiments"
                        / "colour_voting.png")
    args = parser.parse_args()
    files = exemplar_files(parser, args.exemplars, args.names, "_64.png")
    names = args.names or sorted(f.name.removesuffix("_64.png") for f in files)
    print(run_record(), flush=True)
    targets = kopf_targets()
    r = args.radius
    variants = ["average (Dong)", "plain vote", *[f"bilateral {s}" for s in SIGMAS]]
    rows = []
    print(f"worst-axis energy of {SIZE}^3 boxes, seed 0, vote radius {r}")
    print("| exemplar | passes | " + " | ".join(variants) + " | target (1.25x Kopf) |")
    print("|---|---|" + "---|" * (len(variants) + 1))
    for name in tqdm(names, desc="exemplars"):
        ex = Exemplar.load(args.exemplars / f"{name}_64.png")
        cs = precompute(ex)
        for passes in args.passes:
            synth = Synthesizer(cs, seed=0, passes=passes)
            edge = SIZE + 2 * r
            grid = np.indices((edge,) * 3).reshape(3, -1).T - r
            triples = synth.triples(grid).reshape(edge, edge, edge, 3, 2)
            own = synth.box((0, 0, 0), (SIZE,) * 3)
            volumes = [own, vote(cs, triples, own, r, None),
                       *[vote(cs, triples, own, r, s) for s in SIGMAS]]
            energies = [metrics.worst_axis_energy(v, ex.colors) for v in volumes]
            target = targets.get(name, float("nan"))
            print(f"| {name} | {passes} | " + " | ".join(f"{e:.3f}" for e in energies)
                  + f" | {target:.4f} |", flush=True)
            if passes == args.passes[0] and name in ("granite", "rocks_in_sand",
                                                      "wood_rosewood"):
                crop = [("exemplar", ex.colors[:40, :40])]
                crop += [(v_name, metrics.axis_slices(v, 0, 2)[1][:40, :40])
                         for v_name, v in zip(variants, volumes, strict=True)]
                rows.append((name, crop))
    for passes in args.passes:
        (plain, t0), (voted, t1) = cut_cost(cs, passes, 0), cut_cost(cs, passes, r)
        print(f"128^2 cut of {name}, {passes} passes: {plain} finest voxels corrected in "
              f"{t0:.2f} s without the vote, {voted} in {t1:.2f} s with it "
              f"({voted / plain:.2f}x voxels)")
    if rows:
        args.sheet.parent.mkdir(parents=True, exist_ok=True)
        save_png(sheet(rows, cell=120), args.sheet)
        print(f"wrote {args.sheet}")


if __name__ == "__main__":
    main()
