"""Affine maps of points in one fixed order of operations, each a correctly rounded float64
step: a point's voxel must not depend on the machine that maps it (BLAS and LAPACK
kernels, chosen per CPU, fuse and order their sums otherwise), nor on whether one point or
many, NumPy or Dr.Jit, map it."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def apply_affine(rows: Any, x: Any, y: Any, z: Any) -> tuple[Any, Any, Any]:
    """The affine map of ``rows`` (3 rows of 4 coefficients: numbers, or per-point
    arrays) applied to coordinates ``x, y, z`` (floats, or NumPy or Dr.Jit float64 arrays)."""
    return tuple(r[0] * x + r[1] * y + r[2] * z + r[3] for r in list(rows)[:3])


def affine_inverse(matrix: Any) -> np.ndarray | None:
    """The inverse of a 4x4 affine ``matrix`` (its last row 0 0 0 1, taken as such), by
    Gauss-Jordan elimination with partial pivoting in Python floats; None where it has none
    in finite numbers (a scale of zero). A scale's inverse is its correctly rounded
    reciprocal, so a point on a face of the block of matter maps onto its voxel border
    exactly (cofactors over a determinant were an ulp off for a third of scales)."""
    rows = np.asarray(matrix, np.float64).reshape(4, 4)[:3]
    work = [[float(v) for v in row[:3]] + [float(i == j) for j in range(3)]
            for i, row in enumerate(rows)]
    for column in range(3):
        pivot = max(range(column, 3), key=lambda r: abs(work[r][column]))  # first of equals
        if work[pivot][column] == 0.0 or not math.isfinite(work[pivot][column]):
            return None
        work[column], work[pivot] = work[pivot], work[column]
        lead = work[column][column]
        work[column] = [v / lead for v in work[column]]
        for r in range(3):
            factor = work[r][column]
            if r != column and factor != 0.0:
                work[r] = [x - factor * y for x, y in zip(work[r], work[column], strict=True)]
    tx, ty, tz = (float(t) for t in rows[:, 3])
    linear = [row[3:] for row in work]
    inverse = np.array([[*row, -(row[0] * tx + row[1] * ty + row[2] * tz)] for row in linear]
                       + [[0.0, 0.0, 0.0, 1.0]])
    return inverse if np.isfinite(inverse).all() else None
