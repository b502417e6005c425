"""Texturing a mesh lazily (issue 8; Dong 2008, sections 6.2 and 6.4).

Prints, for the bunny in a RESOLUTION^3 block: surface-shell voxels, voxels synthesized
per level and as a fraction of the block, time, and bytes stored versus the full volume;
then the time of 256^2 planar cuts through the interior, three planes per filter (each
filter its own), cold and again through the warm coarse-level cache (bricks dropped, so
the finest level is synthesized again).

    python benchmarks/bench_surface.py [--resolution 1024] [--mesh PATH | --rod]
                                       [--exemplar PATH] [--passes 2]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh
from timing import exemplar_files, run_record

from warptex.exemplar import Exemplar
from warptex.store import BrickStore
from warptex.surface import block_transform, shell
from warptex.texture import SolidTexture

SHARED = Path(__file__).resolve().parent.parent.parent / "shared" / "data"


def _rod() -> trimesh.Trimesh:
    rod = trimesh.creation.cylinder(radius=0.01, height=1.0, sections=16)
    rod.apply_transform(trimesh.geometry.align_vectors([0, 0, 1], [1, 1, 1]))
    return rod


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--resolution", type=int, default=1024)
    meshes = parser.add_mutually_exclusive_group()
    meshes.add_argument("--mesh", type=Path, default=SHARED / "meshes" / "stanford_bunny.ply")
    meshes.add_argument("--rod", action="store_true",
                        help="instead of a mesh file, a 64-face rod of radius 0.01 and length 1 "
                        "along the block's diagonal: long slivers, as CAD exports have")
    parser.add_argument("--exemplar", type=Path,
                        default=SHARED / "exemplars" / "marble_black_64.png")
    parser.add_argument("--passes", type=int, default=2,
                        help="correction passes per pyramid level (default 2)")
    args = parser.parse_args()
    exemplar_files(parser, Path(), [args.exemplar], "")
    if not args.rod:  # --rod leaves --mesh its default, unread
        exemplar_files(parser, Path(), [args.mesh], "", what="mesh")
    print(run_record(), flush=True)
    res = args.resolution
    mesh = _rod() if args.rod else trimesh.load(args.mesh, force="mesh")
    tex = SolidTexture(Exemplar.load(args.exemplar), seed=1, cache_bytes=8 << 30,
                       whole_bricks=False, passes=args.passes)  # as `warptex bake` does
    # Kernels compiled outside the timings: the engine's and lookups', and the shell's.
    tex.query(np.full((1, 3), -1000.0))
    cube = trimesh.creation.box()
    shell(cube, 8, block_transform(cube, 8))
    warm = {lv: n for lv, n in tex.synthesizer.voxels_synthesized.items()}

    start = time.perf_counter()
    voxels = shell(mesh, res, block_transform(mesh, res))
    shell_seconds = time.perf_counter() - start
    tex.query(voxels + 0.5, filter="nearest")
    total = time.perf_counter() - start
    stats = tex.store.stats()
    done = {lv: n - warm[lv] for lv, n in stats["voxels_synthesized"].items()}
    finest = tex.synthesizer.finest
    full_bytes = res**3 * stats["bytes_per_voxel"]
    print(f"mesh {'rod' if args.rod else args.mesh.name}, block {res}^3, exemplar "
          f"{args.exemplar.name}, {args.passes} correction passes per level")
    print(f"surface shell: {len(voxels)} voxels ({100 * len(voxels) / res**3:.3f}% of the "
          f"block), found in {shell_seconds:.2f} s")
    print("voxels corrected per level (finest last): "
          + ", ".join(f"L{lv}: {n}" for lv, n in sorted(done.items())))
    # As Dong 2008 counts them (0.42%: 17.9 MB is 4 bytes for each of 0.42% of 1024^3
    # voxels), synthesized voxels are the results kept; corrections along the way are the
    # dependency cones of section 5.2.
    print(f"voxels synthesized (results stored): {stats['voxels_added']} "
          f"({100 * stats['voxels_added'] / res**3:.3f}% of the block)")
    print(f"finest voxels corrected along the way: {100 * done[finest] / res**3:.3f}% of the "
          f"block; all levels: {100 * sum(done.values()) / res**3:.3f}%")
    print(f"time: {total:.1f} s (synthesis {stats['synthesis_seconds']:.1f} s)")
    print(f"stored: {stats['voxels']} voxels, {stats['bytes'] / 1e6:.1f} MB in "
          f"{stats['bricks']} bricks ({stats['allocated_bytes'] / 1e6:.1f} MB held with free "
          f"room); the full volume in the same format: {full_bytes / 1e6:.0f} MB")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bunny.wtb"
        tex.save(path)
        print(f"store file: {path.stat().st_size / 1e6:.1f} MB")

    centre = np.full(3, res / 2.0)
    for k, filter in enumerate(("nearest", "trilinear")):
        cold, warm = [], []
        for i in range(3):
            # Planes of their own, 160 voxels apart: nearer than twice the reach of a voxel's
            # dependencies at the coarsest level (about 75 voxels, 2 passes), a cold cut
            # would find part of its coarse levels cached by the one before.
            origin = centre + np.array([-128.0, -128.0, 160.0 * (3 * k + i) - 400.0 + 0.5])
            t0 = time.perf_counter()
            tex.slice(origin, (1, 0, 0), (0, 1, 0), (256, 256), filter=filter)
            cold.append(time.perf_counter() - t0)
            # The same cut again with the bricks dropped: only the finest level is
            # synthesized, through the coarse levels the first cut cached.
            tex.store = BrickStore(tex.synthesizer, cache_bytes=8 << 30, whole_bricks=False)
            t0 = time.perf_counter()
            tex.slice(origin, (1, 0, 0), (0, 1, 0), (256, 256), filter=filter)
            warm.append(time.perf_counter() - t0)
        print(f"256^2 planar cut ({filter}), interior planes: "
              + ", ".join(f"{t:.2f} s" for t in cold)
              + "; again through the warm coarse cache: " + ", ".join(f"{t:.2f} s" for t in warm))


if __name__ == "__main__":
    main()
