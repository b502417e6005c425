"""Sets of integer keys (packed voxel or block coordinates) as sorted arrays.

``np.unique`` of plain values takes a hash-based path that is about twenty times slower
than a sort on millions of int64 keys, and the engine and the brick store deduplicate
millions of keys per request.
"""

from __future__ import annotations

import numpy as np


def distinct_sorted(a: np.ndarray) -> np.ndarray:
    """The distinct values of the already sorted ``a``."""
    return a[np.concatenate([[True], a[1:] != a[:-1]])] if len(a) else a


def unique(a: np.ndarray) -> np.ndarray:
    """The distinct values of ``a``, sorted (``np.unique(a)``, by sorting)."""
    return distinct_sorted(np.sort(np.asarray(a).reshape(-1)))
