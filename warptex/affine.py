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
    cofactors in Python floats; None where it has none in finite numbers (a scale of zero)."""
    rows = np.asarray(matrix, np.float64).reshape(4, 4)[:3]
    # The linear part scaled by a power of two (exactly) to entries below 1, so that its
    # determinant neither overflows nor underflows where the inverse is within float64.
    _, power = math.frexp(float(np.abs(rows[:, :3]).max()))
    (a, b, c), (d, e, f), (g, h, i) = ([math.ldexp(float(v), -power) for v in row[:3]]
                                       for row in rows)
    tx, ty, tz = (float(t) for t in rows[:, 3])
    cofactors = ((e * i - f * h, c * h - b * i, b * f - c * e),
                 (f * g - d * i, a * i - c * g, c * d - a * f),
                 (d * h - e * g, b * g - a * h, a * e - b * d))
    det = a * cofactors[0][0] + b * cofactors[1][0] + c * cofactors[2][0]
    if det == 0.0 or not math.isfinite(det):
        return None
    linear = [[math.ldexp(v / det, -power) for v in row] for row in cofactors]
    inverse = np.array([[*row, -(row[0] * tx + row[1] * ty + row[2] * tz)] for row in linear]
                       + [[0.0, 0.0, 0.0, 1.0]])
    return inverse if np.isfinite(inverse).all() else None
