"""Warm brick-store lookups for Mitsuba's scalar variants, one shading point at a time.

A scalar render evaluates a texture once per shading point. Through
:meth:`warptex.texture.SolidTexture.query` every point would be a Warp launch of its own
(0.27 ms each on the project's CPU; a lookup here takes about 18 us: BENCHMARKS, "Scalar
variants").
So the texture keeps the color sums of the bricks it reads (:meth:`BrickStore.brick_sums`) as
host arrays and blends them in plain Python with the float operations of
``kernels.lookup``: the colors are bit-identical to the store's. A point whose voxels are
not all stored is left to the store, which synthesizes them; the mirror then reads those
bricks afresh. Stored voxels never change value, so a mirrored brick stays right even
after the store evicts it; the mirror starts over when its copies' floats reach
``max_bytes`` (6.8 KB a brick of RGB sums, Python's objects included). The store counts a
brick as used when it is copied, not at each read, so under a tight ``cache_bytes`` it may
evict bricks the copies still serve, and synthesize them again once the mirror has started
over.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from kernels.lookup import BRICK, BRICK_SHIFT, BRICK_VOXELS
from warptex.store import CORNERS, BrickStore, brick_keys, voxels_read
from warptex.texture import POINT_LIMIT

_MASK = BRICK - 1
_CORNERS = [tuple(int(v) for v in d) for d in CORNERS]  # plain ints: this runs per point


class ScalarLookup:
    """Colors of single texture-space points from mirrored bricks of one brick store."""

    def __init__(self, store: BrickStore, filter: str, max_bytes: int) -> None:
        self.store = store
        self.filter = filter
        self._channels = store.channels
        self.max_bricks = max(1, max_bytes // (BRICK_VOXELS * 4 * self._channels))
        self._bricks: dict[tuple[int, int, int], memoryview] = {}
        self._lock = threading.Lock()  # Mitsuba's render threads share the mirror
        # [served, left to the store] per render thread: no increment races another.
        self._counts: list[list[int]] = []
        self._local = threading.local()

    def stats(self) -> dict:
        """Points served from the copies (``hits``) and left to the store (``misses``)."""
        with self._lock:
            return {"hits": sum(c[0] for c in self._counts),
                    "misses": sum(c[1] for c in self._counts)}

    def color(self, p: tuple[float, float, float]) -> list[float] | None:
        """Channel values at point ``p``, or None where a voxel it reads is not stored
        (or ``p`` lies beyond the texture's range, which the store then reports); the
        arithmetic of ``kernels.lookup.sample_nearest`` / ``sample_trilinear``."""
        inside = all(abs(c) < POINT_LIMIT for c in p)  # False for NaN too
        color = self._color(p) if inside else None
        counts = getattr(self._local, "counts", None)
        if counts is None:
            counts = self._local.counts = [0, 0]
            with self._lock:
                self._counts.append(counts)
        counts[color is None] += 1
        return color

    def _color(self, p: tuple[float, float, float]) -> list[float] | None:
        if self.filter == "nearest":
            sums = self._voxel_sums(math.floor(p[0]), math.floor(p[1]), math.floor(p[2]))
            return None if sums is None else [s / 3.0 for s in sums]
        q = (p[0] - 0.5, p[1] - 0.5, p[2] - 0.5)
        b0, b1, b2 = math.floor(q[0]), math.floor(q[1]), math.floor(q[2])
        t = (q[0] - b0, q[1] - b1, q[2] - b2)
        u = (1.0 - t[0], 1.0 - t[1], 1.0 - t[2])
        acc = [0.0] * self._channels
        for d in _CORNERS:
            sums = self._voxel_sums(b0 + d[0], b1 + d[1], b2 + d[2])
            if sums is None:
                return None
            w = (t[0] if d[0] else u[0]) * (t[1] if d[1] else u[1])
            w = w * (t[2] if d[2] else u[2])
            for c, s in enumerate(sums):
                acc[c] += w * s
        # Rounded to float32 by the caller's Color3f, as the kernel's float32() of the double.
        return [a / 3.0 for a in acc]

    def forget(self, p: tuple[float, float, float]) -> None:
        """Drop the mirrored bricks that point ``p`` reads, to be read afresh once the
        store has synthesized what they lacked."""
        read = voxels_read(np.array([p], np.float64), self.filter) >> BRICK_SHIFT
        for brick in {tuple(b) for b in read.tolist()}:
            self._bricks.pop(brick, None)

    def _voxel_sums(self, x: int, y: int, z: int) -> list[float] | None:
        """The three-color sums of voxel (x, y, z), None if it is not stored."""
        brick = (x >> BRICK_SHIFT, y >> BRICK_SHIFT, z >> BRICK_SHIFT)
        sums = self._bricks.get(brick)
        if sums is None:
            sums = self._mirror(brick)
        local = ((x & _MASK) << (2 * BRICK_SHIFT)) + ((y & _MASK) << BRICK_SHIFT) + (z & _MASK)
        at = local * self._channels
        values = sums[at:at + self._channels].tolist()
        return None if values[0] != values[0] else values  # NaN: not stored

    def _mirror(self, brick: tuple[int, int, int]) -> memoryview:
        voxel = np.array([brick], np.int64) << BRICK_SHIFT
        # A compact copy: a view would keep the store's whole result array alive.
        sums = memoryview(self.store.brick_sums(brick_keys(voxel)).tobytes()).cast("f")
        with self._lock:
            if len(self._bricks) >= self.max_bricks:
                self._bricks.clear()
            self._bricks[brick] = sums
        return sums
