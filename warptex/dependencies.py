"""Which voxels a request depends on (Dong 2008, section 5.2): a voxel's correction reads
the 3-neighbourhood of its level (three orthogonal N x N planes), so each correction step
widens what must be synthesized before it, and each level's voxels need their parents'.
The engine works on a request grown by the apron these give; ``dependency_mask`` and
``dependency_chain`` are the reference computations on grids that the tests and the
benchmarks compare with (5,037 voxels for N=5, 2 passes, 3 levels, where the paper
reports 6778: BENCHMARKS.md).
"""

from __future__ import annotations

from functools import cache

import numpy as np
from scipy import ndimage

from kernels.synthesis import BLOCK
from warptex.candidate_set import DEFAULT_PARAMS
from warptex.settings import DEFAULT_PASSES


def default_apron_blocks(passes: int = DEFAULT_PASSES) -> int:
    """The blocks of apron that ``passes`` of one sub-pass read around a request, with the
    default neighbourhood (section 5.2)."""
    return apron_blocks(DEFAULT_PARAMS["neighborhood"] // 2, passes, 1)


def neighborhood_shape(half: int) -> np.ndarray:
    """Voxels read by one correction: three orthogonal N x N planes (the 3-neighbourhood)."""
    n = 2 * half + 1
    shape = np.zeros((n, n, n), bool)
    shape[half, :, :] = shape[:, half, :] = shape[:, :, half] = True
    return shape


def correction_steps(passes: int, subpasses: int) -> list[int]:
    """The parity class corrected by each sub-pass step in order; -1 means all voxels."""
    return [-1 if subpasses == 1 else s for _ in range(passes) for s in range(subpasses)]


def dependency_mask(desired: np.ndarray, half: int, steps: list[int]) -> np.ndarray:
    """Section 5.2: voxels of one level needed before ``steps`` to correct ``desired``.

    ``desired`` is a boolean grid with room to grow. Steps are undone from last to
    first; a sub-pass only dilates the voxels of its own parity class, because the
    others keep their value through it.
    """
    shape = neighborhood_shape(half)
    idx = np.indices(desired.shape)
    parity = (idx[0] & 1) + 2 * (idx[1] & 1) + 4 * (idx[2] & 1)
    mask = desired.copy()
    for step in reversed(steps):
        active = mask if step < 0 else mask & (parity == step)
        mask |= ndimage.binary_dilation(active, structure=shape)
    return mask


@cache
def dependency_radius(half: int, passes: int, subpasses: int) -> int:
    """How far (Chebyshev) a voxel's dependencies reach within one level, through all
    its correction steps: the extent of :func:`dependency_mask` of one voxel.

    A voxel joins the mask through a chain of reads, one per step, and which reads a
    step makes depends only on the parity class of the voxel read from (section 5.2,
    sub-passes). So the farthest reach along each axis and sign is carried per parity
    class from step to step instead of dilating grids, whose cost grows with the fourth
    power of the steps (seconds for 2 passes of 8 sub-passes, minutes for 8 passes).
    """
    reads = np.argwhere(neighborhood_shape(half)) - half
    flip = (reads & 1) @ np.array([1, 2, 4])  # what a read does to the parity class
    along = np.concatenate([reads, -reads], axis=1)  # each axis, each sign
    unreached = np.iinfo(np.int64).min // 4
    # gain[f]: how far one read that flips the class by f reaches, along each axis and sign
    gain = np.full((8, 6), unreached, np.int64)
    for f in np.unique(flip):
        gain[f] = along[flip == f].max(axis=0)
    classes = np.arange(8)
    worst = 0
    for start in classes:
        farthest = np.full((8, 6), unreached, np.int64)  # per class of the voxels reached
        farthest[start] = 0
        for step in reversed(correction_steps(passes, subpasses)):
            grown = farthest.copy()
            for c in classes if step < 0 else [step]:
                if farthest[c, 0] > unreached:
                    grown = np.maximum(grown, farthest[c] + gain[c ^ classes])
            farthest = grown
        worst = max(worst, int(farthest.max()))
    return worst


def apron_blocks(half: int, passes: int, subpasses: int) -> int:
    """How many blocks beyond a request its work region reaches at each level: the
    :func:`dependency_radius`, in whole blocks."""
    return -(-dependency_radius(half, passes, subpasses) // BLOCK)


def dependency_chain(half: int, passes: int, subpasses: int, levels: int) -> list[int]:
    """Voxels synthesized at each level to get one finest voxel, finest level first.

    The dependency chain of Dong 2008, section 5.2, which reports 6778 voxels for N=5, 2
    passes, 3 levels; this gives 473 + 1,749 + 2,815 = 5,037 (BENCHMARKS.md).
    """
    steps = correction_steps(passes, subpasses)
    n = 4 * len(steps) * half + 8
    desired = np.zeros((n, n, n), bool)
    desired[n // 2, n // 2, n // 2] = True
    counts = []
    for level in range(levels):
        mask = dependency_mask(desired, half, steps)
        counts.append(int(mask.sum()))
        if level + 1 < levels:
            parents = np.unique(np.argwhere(mask) // 2, axis=0)
            parents += n // 2 - (parents.min(axis=0) + parents.max(axis=0)) // 2
            desired = np.zeros((n, n, n), bool)
            desired[tuple(parents.T)] = True
    return counts
