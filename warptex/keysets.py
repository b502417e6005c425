"""Integer coordinates packed into int64 keys, and sets of keys as sorted arrays.

``np.unique`` of plain values takes a hash-based path that is about twenty times slower
than a sort on millions of int64 keys, and the engine and the brick store deduplicate
millions of keys per request.
"""

from __future__ import annotations

import numpy as np

from kernels.common import KEY_BIAS, KEY_BITS

_MASK = (1 << KEY_BITS) - 1


def pack(coords: np.ndarray) -> np.ndarray:
    """Keys of integer coordinates (N, 3), packed as ``kernels.common`` describes; the keys
    of coordinates keep their order when x, then y, then z are compared."""
    c = np.asarray(coords, np.int64) + KEY_BIAS
    return (c[:, 0] << (2 * KEY_BITS)) | (c[:, 1] << KEY_BITS) | c[:, 2]


def unpack(keys: np.ndarray) -> np.ndarray:
    """Coordinates (N, 3) int64 of packed ``keys``; the inverse of :func:`pack`."""
    keys = np.asarray(keys, np.int64)
    return np.stack([keys >> (2 * KEY_BITS), (keys >> KEY_BITS) & _MASK, keys & _MASK],
                    axis=1) - KEY_BIAS


def cell_offsets(size: int) -> np.ndarray:
    """Offsets (size^3, 3) of the voxels of a ``size``^3 cell (a block or a brick), x
    slowest: the order the kernels number them in."""
    return np.indices((size,) * 3).reshape(3, -1).T


def local_index(voxels: np.ndarray, size: int) -> np.ndarray:
    """Position of each integer voxel (N, 3) in its ``size``^3 cell (a power of two), in
    the order of :func:`cell_offsets`."""
    v = voxels & (size - 1)
    return (v[:, 0] * size + v[:, 1]) * size + v[:, 2]


def run_starts(a: np.ndarray) -> np.ndarray:
    """Index of the first of each run of equal values in ``a``."""
    if len(a) == 0:
        return np.zeros(0, np.int64)
    return np.flatnonzero(np.concatenate([[True], a[1:] != a[:-1]]))


def distinct_sorted(a: np.ndarray) -> np.ndarray:
    """``a`` without the values equal to the one before them: the distinct values of an
    already sorted ``a``."""
    return a[run_starts(a)]


def lookup(keys: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Position (int64) of each of ``query`` in the sorted distinct ``keys``, -1 where
    absent."""
    if len(keys) == 0:
        return np.full(len(query), -1, np.int64)
    pos = np.minimum(np.searchsorted(keys, query), len(keys) - 1)
    return np.where(keys[pos] == query, pos, -1)


def lookup_runs(keys: np.ndarray, query: np.ndarray) -> np.ndarray:
    """:func:`lookup` for a ``query`` that comes in runs of equal values, as the voxels of a
    request do block by block (a box's rows hold four voxels of a block in a row): each
    run is searched once."""
    if len(query) == 0:
        return np.zeros(0, np.int64)
    starts = run_starts(query)
    return np.repeat(lookup(keys, query[starts]), np.diff(starts, append=len(query)))


def unique(a: np.ndarray) -> np.ndarray:
    """The distinct values of ``a``, sorted: ``np.unique(a)`` for keys (a NaN is never
    equal to another, so repeated NaNs are all kept), by sorting."""
    a = np.asarray(a).reshape(-1)
    # Neighbouring voxels of a request share their block's key: dropping repeats in a row
    # first (one pass) leaves a quarter of a box's keys to sort.
    return distinct_sorted(np.sort(distinct_sorted(a)))
