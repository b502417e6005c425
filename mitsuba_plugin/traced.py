"""Warm brick-store lookups inside Dr.Jit's traced programs (Dong 2008, section 6.2).

The Warp lookups need concrete points, which Mitsuba only hands over in wavefront mode
(one kernel per bounce and per BSDF call), about 3x slower than its default symbolic
mode. So :func:`mitsuba_plugin.render` first renders symbolically with the lookup traced
into Mitsuba's own program: a dense page table of the stored bricks and every stored
voxel's three-color sum are Dr.Jit arrays, gathered like any grid texture. A lane whose
voxel is not stored gets a stand-in color and logs it; the store then synthesizes the
logged voxels' bricks (Warp) and the render is repeated. An image is kept only from a render
that logged nothing, so each of its colors is a stored voxel, computed with the same
float operations as ``kernels.lookup`` and therefore bit-identical to
:meth:`warptex.texture.SolidTexture.query`.

The mirror costs 4 bytes per channel for each of the 512 voxels of every brick slot of the
store (free slots and voxels not stored included, not counted in ``cache_bytes``), 4 bytes
per slot, and 4 bytes per brick of the stored bricks' bounding box; it is rebuilt whole
whenever bricks were inserted or evicted.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from kernels.lookup import BRICK, BRICK_SHIFT, BRICK_VOXELS
from warptex.keysets import pack, unique
from warptex.store import CORNERS, BrickStore, brick_coords, brick_voxels
from warptex.synthesis import COORD_LIMIT

# Page table entries (4 bytes each) beyond which the stored bricks are too scattered for
# a dense table; such a texture renders in wavefront mode instead.
MAX_PAGES = 1 << 25
# Slots of the miss log (8 MiB); bricks that collide take another round.
_SLOT_BITS = 20
LOG_CAPACITY = 1 << _SLOT_BITS
# A miss log word: three 20-bit brick coordinates, biased (bricks lie within +-2^19 of the
# origin, voxels within COORD_LIMIT), then 3 bits of brick edges; never 0, an empty slot.
_LOG_BITS = 20
_LOG_BIAS = 1 << (_LOG_BITS - 1)
_LOG_MASK = (1 << _LOG_BITS) - 1
_LOG_SHIFTS = (3 + 2 * _LOG_BITS, 3 + _LOG_BITS, 3)
assert COORD_LIMIT >> BRICK_SHIFT < _LOG_BIAS
_MAX_SUMS = 1 << 31  # the mirror's sums are gathered at 32-bit positions


class TracedLookup:
    """Symbolic-mode reads of one brick store, refreshed from its :meth:`~BrickStore.snapshot`
    whenever bricks were inserted or evicted."""

    def __init__(self, store: BrickStore, filter: str, fallback: tuple[float, float, float],
                 max_pages: int = MAX_PAGES) -> None:
        self.store = store
        self.filter = filter
        # What a missed lane shows in a render that will be discarded: a typical color
        # rather than black, so its paths go on and reach (and log) deeper bricks too.
        self.fallback = fallback
        self.max_pages = max_pages
        self._version = -1
        self.usable = False
        self.renders = self.renders_with_misses = 0
        self._reset_log()

    def refresh(self) -> bool:
        """Mirror the store as it is now; False when its bricks need more than
        ``max_pages`` table entries, or its slots more sums than 32-bit indices reach."""
        if self.store.version == self._version:
            return self.usable
        snap = self.store.snapshot()
        live = np.flatnonzero(snap.keys >= 0)
        coords = brick_coords(snap.keys[live])
        lo = coords.min(0) if len(live) else np.zeros(3, np.int64)
        dims = coords.max(0) - lo + 1 if len(live) else np.ones(3, np.int64)
        usable = int(np.prod(dims)) <= self.max_pages and snap.sums.size < _MAX_SUMS
        if usable:
            pages = np.full(int(np.prod(dims)), -1, np.int32)
            rel = coords - lo
            pages[(rel[:, 0] * dims[1] + rel[:, 1]) * dims[2] + rel[:, 2]] = live
            self._pages = mi.Int32(pages)
            self._used = dr.zeros(mi.UInt32, max(len(snap.keys), 1))
            self._sums = mi.Float(snap.sums.reshape(-1) if snap.sums.size
                                  else np.zeros(1, np.float32))
            self._channels = snap.sums.shape[1]
            # Opaque, so a refreshed table reuses the compiled kernels.
            self._lo = [dr.opaque(mi.Int32, int(v)) for v in lo]
            self._dims = [dr.opaque(mi.Int32, int(v)) for v in dims]
        # Last: a refresh stopped before here (Ctrl-C) is done again by the next, so no
        # table is used with another version's sums.
        self._version, self.usable = snap.version, usable
        return usable

    def colors(self, p: tuple[mi.Float64, mi.Float64, mi.Float64],
               active: mi.Bool) -> mi.Color3f:
        """RGB at texture-space points ``p``; ``fallback``, and logged, where a voxel
        read is not stored."""
        # Dr.Jit turns division by a literal into a multiplication, one ulp away from the
        # kernels' division; opaque divisors keep it a division.
        if self.filter == "nearest":
            voxel = [mi.Int32(dr.floor(c)) for c in p]
            sums, hit = self._voxel_sums(voxel, active, mi.Bool(True))
            rgb = [s / dr.opaque(mi.Float, 3.0) for s in sums]
        else:
            q = [c - 0.5 for c in p]
            voxel = [mi.Int32(dr.floor(c)) for c in q]
            t = [c - mi.Float64(v) for c, v in zip(q, voxel, strict=True)]
            edge = [(v & (BRICK - 1)) == BRICK - 1 for v in voxel]
            acc = [mi.Float64(0.0)] * self._channels
            hit = mi.Bool(True)
            for d in CORNERS:
                corner = [v + int(o) for v, o in zip(voxel, d, strict=True)]
                # Each brick read is marked once: the first corner's, and the others'
                # where they cross into a neighbour brick.
                mark = mi.Bool(not d.any())
                for k in np.flatnonzero(d):
                    mark |= edge[k]
                sums, found = self._voxel_sums(corner, active, mark)
                hit &= found
                # The weight and accumulation order of kernels.lookup.sample_trilinear.
                w = t[0] if d[0] else 1.0 - t[0]
                w = w * (t[1] if d[1] else 1.0 - t[1])
                w = w * (t[2] if d[2] else 1.0 - t[2])
                acc = [a + w * mi.Float64(s) for a, s in zip(acc, sums, strict=True)]
            rgb = [mi.Float(a / dr.opaque(mi.Float64, 3.0)) for a in acc]
        self._log(voxel, active & ~hit)
        if len(rgb) < 3:
            rgb = [rgb[0]] * 3
        return dr.select(hit, mi.Color3f(*rgb[:3]), mi.Color3f(*self.fallback))

    def take_misses(self) -> np.ndarray:
        """Every voxel (N, 3) of the bricks the logged lanes read, and a cleared log;
        called once per traced render, which it counts, and whose bricks it marks as
        used. Whole bricks, so a render's misses are filled in few rounds."""
        words = self._log_voxels.numpy()
        words = words[words != 0]
        self.renders += 1
        self.renders_with_misses += bool(len(words))
        self._reset_log()
        if self.usable:
            self.store.mark_used(np.flatnonzero(self._used.numpy()), self._version)
            self._used = dr.zeros(mi.UInt32, dr.width(self._used))
        fields = [(words >> np.uint64(shift)) & np.uint64(_LOG_MASK) for shift in _LOG_SHIFTS]
        bricks = np.stack(fields, axis=1).astype(np.int64) - _LOG_BIAS
        if self.filter == "trilinear":  # a corner beyond a brick's last voxel is in the next
            edges = (words[:, None] >> np.arange(3, dtype=np.uint64)[::-1]) & np.uint64(1)
            bricks = (bricks[:, None, :] + CORNERS[None] * edges[:, None, :].astype(np.int64))
        return brick_voxels(unique(pack(bricks.reshape(-1, 3))))

    def _voxel_sums(self, voxel: list[mi.Int32], active: mi.Bool,
                    mark: mi.Bool) -> tuple[list[mi.Float], mi.Bool]:
        """Color sums of integer ``voxel`` and whether it is stored; where ``mark``,
        its brick is flagged as used, for least-recently-used eviction."""
        rel = [(v >> BRICK_SHIFT) - lo for v, lo in zip(voxel, self._lo, strict=True)]
        inside = mi.Bool(active)
        for r, n in zip(rel, self._dims, strict=True):
            inside &= (r >= 0) & (r < n)
        page = (rel[0] * self._dims[1] + rel[1]) * self._dims[2] + rel[2]
        slot = dr.gather(mi.Int32, self._pages, mi.UInt32(page), inside)
        found = inside & (slot >= 0)
        dr.scatter(self._used, mi.UInt32(1), mi.UInt32(slot), found & mark)
        x, y, z = (v & (BRICK - 1) for v in voxel)
        local = (x * BRICK + y) * BRICK + z
        at = mi.UInt32(slot * BRICK_VOXELS + local) * self._channels
        sums = [dr.gather(mi.Float, self._sums, at + c, found) for c in range(self._channels)]
        return sums, found & ~dr.isnan(sums[0])  # NaN: a voxel its brick does not hold

    def _log(self, voxel: list[mi.Int32], missed: mi.Bool) -> None:
        """Record the brick of each missed voxel and whether it is its brick's last along
        each axis (a trilinear corner then reads the next brick), packed in one word (so
        racing lanes cannot mix coordinates), at a slot hashed from both: lanes that read
        the same bricks overwrite each other. The hash changes every render, so bricks that
        collide are logged the next one. (Plain scatters: a counter could not be advanced
        twice in one traced program.)"""
        b = [v >> BRICK_SHIFT for v in voxel]
        edge = [mi.UInt32((v & (BRICK - 1)) == BRICK - 1) for v in voxel]
        edges = edge[0] * 4 + edge[1] * 2 + edge[2]
        at = ((mi.UInt32(b[0]) * 73856093 ^ mi.UInt32(b[1]) * 19349663
               ^ mi.UInt32(b[2]) * 83492791
               ^ edges * 2654435761) * self._salt
              >> (32 - _SLOT_BITS))  # a multiplicative hash's best bits are its highest
        word = mi.UInt64(edges)
        for c, shift in zip(b, _LOG_SHIFTS, strict=True):
            word |= mi.UInt64(mi.UInt32(c + _LOG_BIAS) & _LOG_MASK) << shift
        dr.scatter(self._log_voxels, word, at, missed)

    def _reset_log(self) -> None:
        self._log_voxels = dr.zeros(mi.UInt64, LOG_CAPACITY)  # 0: empty slot
        self._salt = dr.opaque(mi.UInt32, (2 * self.renders + 1) * 0x9E3779B1 & 0xFFFFFFFF)
