"""Bricks as lists of stored voxels (Dong 2008, section 6.2: synthesized voxels kept as
triples): keys, each brick's stored-voxel bits, and the triples of its stored voxels packed
brick after brick in local order, so that only stored voxels take room. A brick store's pool
and its files lay bricks out so; here are the gathers, the packing of new voxels, and the
union of two lists that merging a store file takes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from kernels import lookup as _k
from warptex.keysets import lookup

# Bricks gathered at a time (a million voxels at most): positions for every voxel of a
# store at once, 8 bytes each and three times over while made, outweighed its voxels.
_GATHER_BRICKS = 2048


def ranges_of(first: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenated ``first[i] .. first[i] + counts[i]`` ranges."""
    counts = np.asarray(counts, np.int64)
    if counts.sum() == 0:
        return np.zeros(0, np.int64)
    starts = range_starts(counts)
    return np.repeat(np.asarray(first, np.int64) - starts, counts) + np.arange(counts.sum())


def gathered(source: np.ndarray, first: np.ndarray, counts: np.ndarray,
             out: np.ndarray | None = None) -> np.ndarray:
    """``source[ranges_of(first, counts)]``, into ``out`` if given, :data:`_GATHER_BRICKS`
    ranges at a time."""
    counts = np.asarray(counts, np.int64)
    if out is None:
        out = np.empty((int(counts.sum()), *source.shape[1:]), source.dtype)
    at = 0
    for start in range(0, len(counts), _GATHER_BRICKS):
        part = slice(start, start + _GATHER_BRICKS)
        rows = ranges_of(first[part], counts[part])
        out[at: at + len(rows)] = source[rows]
        at += len(rows)
    return out


class Bricks(NamedTuple):
    """Bricks as a store file lists them, least recently used first: their keys, the
    triples of their stored voxels brick after brick, and their stored-voxel words."""

    keys: np.ndarray
    triples: np.ndarray
    valid: np.ndarray


def stored_bits(valid: np.ndarray) -> np.ndarray:
    """Bricks' stored-voxel words (N, VALID_WORDS) as bits (N, 512), in local order."""
    return np.unpackbits(valid.view(np.uint8), bitorder="little").reshape(
        len(valid), _k.BRICK_VOXELS).astype(bool)


def packed(cells: np.ndarray, bricks: int) -> tuple[np.ndarray, np.ndarray]:
    """For voxels numbered ``brick * 512 + local`` in ``bricks`` bricks, repeats allowed:
    the index of each distinct voxel's first appearance, in (brick, local) order (the
    order a brick's voxels take in the pool), and the bricks' stored-voxel words."""
    cells, first = np.unique(cells, return_index=True)
    bits = np.zeros(bricks * _k.BRICK_VOXELS, bool)
    bits[cells] = True
    valid = np.packbits(bits, bitorder="little").view(np.uint32)
    return first, valid.reshape(bricks, _k.VALID_WORDS)


def bricks_union(older: Bricks, newer: Bricks,
                 kept: Callable[[np.ndarray], int] | None = None) -> Bricks:
    """The bricks of two lists, each least recently used first, as one such list:
    ``newer``'s bricks the more recent, a brick in both holding the voxels of either
    (their triples are the same, as voxels are position-determined). Bricks are copied
    whole; only those whose older copy holds voxels the newer lacks are merged voxel by
    voxel. ``kept``: how many of the most recent bricks of the union to keep, given its
    stored-voxel words; the others are never gathered (all are kept without it)."""
    order = np.argsort(newer.keys)
    found = lookup(newer.keys[order], older.keys)
    twin = np.full(len(found), -1, np.int64)  # newer's copy of each older brick, if any
    twin[found >= 0] = order[found[found >= 0]]
    alone = twin < 0
    both = np.flatnonzero(~alone)
    grown = both[(older.valid[both] & ~newer.valid[twin[both]]).any(axis=1)]
    if len(grown) == 0 and len(both) == len(older.keys):
        # The older list adds nothing: a store saved over the file it loaded.
        return newer if kept is None else most_recent(newer, kept(newer.valid))
    old_counts, new_counts = voxels_per_brick(older.valid), voxels_per_brick(newer.valid)
    old_first, new_first = range_starts(old_counts), range_starts(new_counts)
    # The older list's own bricks, then the newer's, a grown one holding both copies' voxels.
    kept_older = int(alone.sum())
    valid = np.concatenate([older.valid[alone], newer.valid])
    valid[kept_older + twin[grown]] |= older.valid[grown]
    drop = 0 if kept is None else len(valid) - kept(valid)  # the least recent, left out
    counts = voxels_per_brick(valid)
    triples = np.empty((int(counts[drop:].sum()), *newer.triples.shape[1:]),
                       newer.triples.dtype)
    split = int(counts[drop:kept_older].sum())
    older_kept = np.flatnonzero(alone)[drop:]
    gathered(older.triples, old_first[older_kept], old_counts[older_kept], out=triples[:split])
    older_twin = np.full(len(newer.keys), -1, np.int64)  # the older copy of a grown brick
    older_twin[twin[grown]] = grown
    at = split
    for start in range(max(drop - kept_older, 0), len(newer.keys), _GATHER_BRICKS):
        part = np.arange(start, min(start + _GATHER_BRICKS, len(newer.keys)))
        own = newer.triples[new_first[part[0]]: new_first[part[-1]] + new_counts[part[-1]]]
        merged = counts[kept_older + part]
        if (older_twin[part] >= 0).any():
            own = _with_grown(own, part, older_twin[part], merged, (older, newer),
                              (old_first, new_first))
        triples[at: at + len(own)] = own
        at += len(own)
    keys = np.concatenate([older.keys[alone], newer.keys])
    return Bricks(keys[drop:], triples, valid[drop:])


def most_recent(bricks: Bricks, count: int) -> Bricks:
    """The ``count`` most recently used of ``bricks`` (the tail of the list), as views."""
    first = len(bricks.keys) - count
    skipped = int(voxels_per_brick(bricks.valid[:first]).sum())
    return Bricks(bricks.keys[first:], bricks.triples[skipped:], bricks.valid[first:])


def _with_grown(own: np.ndarray, part: np.ndarray, twins: np.ndarray, merged: np.ndarray,
                lists: tuple[Bricks, Bricks], firsts: tuple[np.ndarray, np.ndarray]
                ) -> np.ndarray:
    """The voxels of the newer list's bricks ``part`` (``own``: theirs alone, brick after
    brick), each brick with an older copy (``twins``, -1 for none) holding the voxels of both
    in local order; ``merged``: the voxels each then holds; ``lists``: the older and newer
    lists, ``firsts`` where each of their bricks' triples start."""
    rows = (twins[twins >= 0], part[twins >= 0])  # the grown bricks in either list
    # Both copies' voxels, old then new, each brick after brick in local order; a voxel in
    # both appears twice with one triple (voxels are position-determined).
    cells = [np.flatnonzero(stored_bits(b.valid[r])) for b, r in zip(lists, rows, strict=True)]
    first, _ = packed(np.concatenate(cells), len(rows[1]))
    both = np.concatenate([b.triples[ranges_of(f[r], voxels_per_brick(b.valid[r]))]
                           for b, f, r in zip(lists, firsts, rows, strict=True)])[first]
    source = np.concatenate([own, both])
    starts = firsts[1][part] - firsts[1][part[0]]
    starts[twins >= 0] = len(own) + range_starts(merged[twins >= 0])
    return source[ranges_of(starts, merged)]


def voxels_per_brick(valid: np.ndarray) -> np.ndarray:
    """Stored voxels of each brick of stored-voxel words ``valid`` (N, VALID_WORDS)."""
    return np.bitwise_count(valid).sum(axis=1).astype(np.int64)


def range_starts(counts: np.ndarray) -> np.ndarray:
    """Where each of consecutive ranges of ``counts`` items begins: their exclusive sums."""
    return np.cumsum(counts) - counts
