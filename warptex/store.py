"""Sparse brick store of finest-level synthesis results (Dong 2008, sections 5.2 and 6.2).

The paper stores synthesized surface voxels in a TileTree and synthesizes each region
once (section 6.2). Here finest voxels are kept in bricks of 8^3, found through a hash
table that the lookup kernels of ``kernels.lookup`` search. A point batch is looked up in
one launch; the bricks it misses are synthesized in one engine call (one union dependency
mask, section 5.2), inserted, and the missed points finished.

A brick holds each voxel's triple of exemplar pixels (section 6.2 keeps triples in 16-bit
targets): 6 bytes per voxel when every exemplar has at most 65536 pixels, else 12, instead
of 4 bytes per color channel. Its color is decoded with exactly the engine's float32
operations, so a stored voxel is bit-identical to ``Synthesizer.voxels``.

Results are position-determined, so eviction, persistence and concurrency only ever
change how much is synthesized, never a color.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import numpy as np
import warp as wp

from kernels import lookup as _k
from warptex.archive import ArchiveError, read_archive, write_archive
from warptex.parallel import launch_ranges
from warptex.synthesis import Synthesizer

FILTERS = ("nearest", "trilinear")
FORMAT_VERSION = 1
_MAGIC = b"WTXBRICK"
_EMPTY = -1
_MIN_BRICKS = 64
_LOCAL = np.indices((_k.BRICK,) * 3).reshape(3, -1).T  # voxel offsets, x slowest
_CORNERS = np.indices((2, 2, 2)).reshape(3, -1).T


class StoreFileError(ArchiveError):
    """A store file is damaged, of another format version, or of another texture."""


def brick_keys(voxels: np.ndarray) -> np.ndarray:
    """Packed coordinates of the bricks holding integer ``voxels`` (N, 3), as
    ``kernels.lookup.brick_key`` packs them."""
    b = (voxels.astype(np.int64) >> 3) + _k.KEY_BIAS
    return (b[:, 0] << (2 * _k.KEY_BITS)) | (b[:, 1] << _k.KEY_BITS) | b[:, 2]


def brick_coords(keys: np.ndarray) -> np.ndarray:
    """Brick coordinates (N, 3) int64 of packed brick ``keys``; inverse of ``brick_keys``."""
    mask = (1 << _k.KEY_BITS) - 1
    b = np.stack([keys >> (2 * _k.KEY_BITS), (keys >> _k.KEY_BITS) & mask, keys & mask], 1)
    return b - _k.KEY_BIAS


def bricks_read(points: np.ndarray, filter: str) -> np.ndarray:
    """Sorted unique keys of the bricks that ``filter`` reads for float64 ``points``."""
    if filter == "nearest":
        return np.unique(brick_keys(np.floor(points)))
    base = np.floor(points - 0.5).astype(np.int64)
    return np.unique(brick_keys((base[:, None, :] + _CORNERS[None]).reshape(-1, 3)))


class Snapshot(NamedTuple):
    """The stored voxels at one moment, for readers outside Warp.

    ``keys[s]`` is the brick key in pool slot ``s`` (-1 where free) and
    ``sums[s * 512 + local]`` the three-color sum (C channels, float32) of that brick's
    voxel ``local`` (x slowest), exactly as the lookup kernels compute it. ``version``
    changes whenever bricks are inserted or evicted.
    """

    version: int
    keys: np.ndarray
    sums: np.ndarray


class _SharedLock:
    """Many lookups or one mutation at a time; a waiting mutation holds back new lookups
    so a steady stream of queries cannot starve insertion."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._readers = 0
        self._writing = False
        self._waiting = 0

    @contextmanager
    def shared(self) -> Iterator[None]:
        with self._cond:
            self._cond.wait_for(lambda: not self._writing and not self._waiting)
            self._readers += 1
        try:
            yield
        finally:
            with self._cond:
                self._readers -= 1
                self._cond.notify_all()

    @contextmanager
    def exclusive(self) -> Iterator[None]:
        with self._cond:
            self._waiting += 1
            self._cond.wait_for(lambda: not self._writing and not self._readers)
            self._waiting -= 1
            self._writing = True
        try:
            yield
        finally:
            with self._cond:
                self._writing = False
                self._cond.notify_all()


class BrickStore:
    """Finest-level voxels of one solid texture in 8^3 bricks, synthesized on first touch.

    ``cache_bytes`` bounds the brick payload; least-recently-used bricks are evicted
    after each batch (a batch may exceed the bound while it is being finished).
    """

    def __init__(self, synthesizer: Synthesizer, *, cache_bytes: int = 256 << 20) -> None:
        if cache_bytes < 0:
            raise ValueError(f"cache_bytes must not be negative, got {cache_bytes}")
        self.synthesizer = synthesizer
        self.cache_bytes = int(cache_bytes)
        cs = synthesizer.candidates
        sources = [cs.colors[cs.axis_source[k]] for k in range(3)]
        self.channels = cs.channels
        if self.channels > _k.MAX_CHANNELS:
            raise ValueError(f"at most {_k.MAX_CHANNELS} color channels, got {self.channels}")
        self._widths = np.array([c.shape[1] for c in sources], np.int64)
        compact = max(c.shape[0] * c.shape[1] for c in sources) <= 1 << 16
        self._dtype = np.dtype(np.uint16 if compact else np.int32)
        self._brick_bytes = _k.BRICK_VOXELS * 3 * self._dtype.itemsize
        self._device = synthesizer.device
        uploaded = {j: wp.array(cs.colors[j].reshape(-1), dtype=wp.float32, device=self._device)
                    for j in set(cs.axis_source)}
        self._colors = [uploaded[j] for j in cs.axis_source]
        self._lock = _SharedLock()
        self._counts = threading.Lock()
        self._tick = itertools.count(1)
        self._keys = np.full(0, _EMPTY, np.int64)  # brick key of each pool slot
        self._pool = wp.zeros(0, dtype=self._wp_dtype, device=self._device)
        self._index = _k.BrickIndex()
        self._index.stamps = wp.zeros(0, dtype=wp.int64, device=self._device)
        self._rebuild_table(_MIN_BRICKS * 2)
        self._hits = self._misses = self._synthesized = self._evicted = 0
        self._version = 0
        self._seconds = 0.0

    # -- public API -------------------------------------------------------------------

    def identity(self) -> str:
        """Digest of everything a stored voxel depends on: exemplars, candidate
        parameters, seed, jitter and engine parameters."""
        s = self.synthesizer
        key = {
            "format": FORMAT_VERSION,
            "brick": _k.BRICK,
            "digests": list(s.candidates.digests),
            "params": s.candidates.params,
            "seed": s.seed,
            "jitter": s.jitter,
            "levels": s.finest - s.start,
            "passes": s.passes,
            "subpasses": s.subpasses,
        }
        return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()

    def sample(self, points: np.ndarray, filter: str, out: np.ndarray) -> None:
        """Colors of float64 ``points`` (N, 3) into ``out`` (N, C) float32."""
        if filter not in FILTERS:
            raise ValueError(f"filter must be one of {FILTERS}, got {filter!r}")
        n = len(points)
        if n == 0:
            return
        kernel = _k.sample_nearest if filter == "nearest" else _k.sample_trilinear
        pts = self._on_device(points, wp.vec3d)
        res = self._on_device(out, wp.float32)
        missed = wp.zeros(n, dtype=wp.int32, device=self._device)
        count = wp.zeros(1, dtype=wp.int32, device=self._device)
        with self._lock.shared():
            self._launch(kernel, pts, res, missed, count)
        misses = int(count.numpy()[0])
        with self._counts:
            self._hits += n - misses
            self._misses += misses
        if self._device != "cpu":
            out[:] = res.numpy()
        if misses:
            rows = missed.numpy().astype(bool)
            self._finish(kernel, points[rows], filter, out, rows)

    @property
    def version(self) -> int:
        """Changes whenever bricks are inserted or evicted."""
        return self._version

    def prefetch(self, voxels: np.ndarray) -> None:
        """Make the bricks holding integer ``voxels`` (N, 3) resident, synthesizing the
        absent ones in one engine call."""
        if len(voxels):
            self._with_resident(np.unique(brick_keys(np.asarray(voxels))), lambda: None)

    def mark_used(self, slots: np.ndarray, version: int) -> None:
        """Count pool ``slots`` of the snapshot of ``version`` as just used, for
        readers outside Warp; ignored if bricks were inserted or evicted since."""
        with self._lock.exclusive():
            if version != self._version or len(slots) == 0:
                return
            stamps = self._index.stamps.numpy()
            stamps[slots] = next(self._tick)
            self._index.stamps.assign(stamps)

    def snapshot(self) -> Snapshot:
        """The stored bricks and their voxels' color sums (see :class:`Snapshot`)."""
        with self._lock.shared():
            dev = self._device
            sums = wp.empty((len(self._keys) * _k.BRICK_VOXELS, self.channels),
                            dtype=wp.float32, device=dev)
            if sums.shape[0]:
                wp.launch(_k.voxel_sums, sums.shape[0],
                          [self._pool, *self._colors, self.channels], [sums], device=dev)
            return Snapshot(self._version, self._keys.copy(), sums.numpy())

    def stats(self) -> dict:
        """Bricks, bytes, lookups served from the store (hits) or not (misses), and the
        synthesis behind them: voxels per level and seconds."""
        with self._lock.shared(), self._counts:
            bricks = int((self._keys != _EMPTY).sum())
            return {
                "bricks": bricks,
                "bytes": bricks * self._brick_bytes + self._index_bytes(),
                "payload_bytes": bricks * self._brick_bytes,
                "index_bytes": self._index_bytes(),
                "bytes_per_voxel": self._dtype.itemsize * 3,
                "hits": self._hits,
                "misses": self._misses,
                "bricks_synthesized": self._synthesized,
                "bricks_evicted": self._evicted,
                "voxels_synthesized": dict(self.synthesizer.voxels_synthesized),
                "synthesis_seconds": self._seconds,
            }

    def save(self, path: str | Path) -> None:
        """Write the bricks to a versioned, checksummed file atomically (temporary name,
        then rename), least recently used first."""
        path = Path(path)
        with self._lock.shared():
            live = np.flatnonzero(self._keys != _EMPTY)
            live = live[np.argsort(self._index.stamps.numpy()[live], kind="stable")]
            pool = self._pool.numpy().reshape(-1, _k.BRICK_VOXELS * 3)
            arrays = {"keys": self._keys[live], "triples": pool[live]}
        write_archive(path, _MAGIC, FORMAT_VERSION,
                      {"identity": np.array(self.identity()), **arrays})

    @classmethod
    def load(cls, path: str | Path, synthesizer: Synthesizer, *,
             cache_bytes: int = 256 << 20) -> BrickStore:
        """A store holding the bricks saved in ``path``; an empty one, with a warning,
        when the file is damaged or belongs to another texture."""
        store = cls(synthesizer, cache_bytes=cache_bytes)
        try:
            keys, triples = store._read(Path(path))
        except StoreFileError as e:
            warnings.warn(f"ignoring brick store file, starting empty: {e}", stacklevel=2)
            return store
        keep = min(len(keys), store._budget_bricks)
        with store._lock.exclusive():
            store._insert(keys[len(keys) - keep :], triples[len(keys) - keep :].reshape(-1))
        return store

    # -- batches ----------------------------------------------------------------------

    def _with_resident(self, keys: np.ndarray, run: Callable[[], None]) -> None:
        """Run ``run`` while every brick of ``keys`` is stored, then evict.

        Absent bricks are synthesized outside the lock, so lookups of stored bricks go
        on meanwhile; bricks evicted by another thread before we get the lock again are
        synthesized in the next round.
        """
        made: list[tuple[np.ndarray, np.ndarray]] = []
        while True:
            with self._lock.exclusive():
                # Everything this batch synthesized goes back in, so each round leaves
                # fewer bricks to make and the loop ends whatever other threads evict.
                for k, payload in made:
                    self._insert(k, payload)
                absent = keys[~np.isin(keys, self._keys)]
                if len(absent) == 0:
                    run()
                    self._evict()
                    return
            made.append((absent, self._synthesize(absent)))

    def _finish(self, kernel, points: np.ndarray, filter: str, out: np.ndarray,
                rows: np.ndarray) -> None:
        """Second half of a batch: the points whose bricks were missing."""
        pts = self._on_device(np.ascontiguousarray(points), wp.vec3d)
        sub = np.empty((len(points), self.channels), np.float32)
        res = self._on_device(sub, wp.float32)
        dev = self._device
        missed = wp.zeros(len(points), dtype=wp.int32, device=dev)
        count = wp.zeros(1, dtype=wp.int32, device=dev)
        self._with_resident(bricks_read(points, filter),
                            lambda: self._launch(kernel, pts, res, missed, count))
        out[rows] = res.numpy()

    def _synthesize(self, keys: np.ndarray) -> np.ndarray:
        """Triples of whole bricks ``keys``, in one engine call."""
        voxels = (brick_coords(keys)[:, None, :] * _k.BRICK + _LOCAL[None]).reshape(-1, 3)
        start = time.perf_counter()
        rc = self.synthesizer.triples(voxels)
        seconds = time.perf_counter() - start
        with self._counts:
            self._seconds += seconds
            self._synthesized += len(keys)
        return (rc[:, :, 0] * self._widths + rc[:, :, 1]).astype(self._dtype).reshape(-1)

    def _launch(self, kernel, points: wp.array, out: wp.array, missed: wp.array,
                count: wp.array) -> None:
        """One lookup launch, split in ranges over CPU threads (Warp runs a CPU launch on
        one thread; points are independent, so ranges give the same result)."""
        inputs = [points, self._index, self._pool, *self._colors, self.channels,
                  wp.int64(next(self._tick))]
        launch_ranges(kernel, 0, len(points), inputs, [out, missed, count],
                      device=self._device)

    # -- mutation (exclusive lock held) -----------------------------------------------

    def _insert(self, keys: np.ndarray, payload: np.ndarray) -> None:
        fresh = ~np.isin(keys, self._keys)
        keys = keys[fresh]
        if len(keys) == 0:
            return
        payload = payload.reshape(-1, _k.BRICK_VOXELS * 3)[fresh].reshape(-1)
        free = np.flatnonzero(self._keys == _EMPTY)
        if len(free) < len(keys):
            live = len(self._keys) - len(free)
            self._grow_pool(max(live + len(keys),
                                min(max(2 * len(self._keys), _MIN_BRICKS), self._budget_bricks)))
            free = np.flatnonzero(self._keys == _EMPTY)
        slots = free[: len(keys)]
        self._keys[slots] = keys
        self._version += 1
        dev = self._device
        slots_wp = wp.array(slots.astype(np.int32), dtype=wp.int32, device=dev)
        wp.launch(_k.store_bricks, (len(keys), _k.BRICK_VOXELS * 3),
                  [slots_wp, wp.array(payload, dtype=self._wp_dtype, device=dev),
                   wp.int64(next(self._tick))], [self._pool, self._index.stamps], device=dev)
        live = int((self._keys != _EMPTY).sum())
        if 2 * live > len(self._index.keys):
            self._rebuild_table(1 << (2 * live).bit_length())
        else:
            wp.launch(_k.insert_keys, 1, [wp.array(keys, dtype=wp.int64, device=dev),
                                          slots_wp], [self._index], device=dev)

    def _evict(self) -> None:
        """Drop least-recently-used bricks until the payload fits ``cache_bytes``."""
        live = np.flatnonzero(self._keys != _EMPTY)
        excess = len(live) - self._budget_bricks
        if excess <= 0:
            return
        stamps = self._index.stamps.numpy()[live]
        self._keys[live[np.argsort(stamps, kind="stable")[:excess]]] = _EMPTY
        self._evicted += excess
        self._version += 1
        if len(self._keys) > max(self._budget_bricks, _MIN_BRICKS):
            self._compact()
        self._rebuild_table(len(self._index.keys))

    def _grow_pool(self, bricks: int) -> None:
        old = len(self._keys)
        per = _k.BRICK_VOXELS * 3
        pool = wp.zeros(bricks * per, dtype=self._wp_dtype, device=self._device)
        stamps = wp.zeros(bricks, dtype=wp.int64, device=self._device)
        if old:
            wp.copy(pool, self._pool, count=old * per)
            wp.copy(stamps, self._index.stamps, count=old)
        self._pool, self._index.stamps = pool, stamps
        self._keys = np.concatenate([self._keys, np.full(bricks - old, _EMPTY, np.int64)])

    def _compact(self) -> None:
        """Give back the pool beyond the budget that a large batch made it grow to."""
        live = np.flatnonzero(self._keys != _EMPTY)
        per = _k.BRICK_VOXELS * 3
        payload = self._pool.numpy().reshape(-1, per)[live]
        stamps = self._index.stamps.numpy()[live]
        keys = self._keys[live]
        self._keys = np.zeros(0, np.int64)
        self._grow_pool(max(self._budget_bricks, _MIN_BRICKS))
        self._keys[: len(live)] = keys
        dev = self._device
        wp.copy(self._pool, wp.array(payload.reshape(-1), dtype=self._wp_dtype, device=dev),
                count=payload.size)
        wp.copy(self._index.stamps, wp.array(stamps, dtype=wp.int64, device=dev),
                count=len(stamps))

    def _rebuild_table(self, capacity: int) -> None:
        dev = self._device
        self._index.keys = wp.full(capacity, _EMPTY, dtype=wp.int64, device=dev)
        self._index.slots = wp.zeros(capacity, dtype=wp.int32, device=dev)
        self._index.mask = capacity - 1
        live = np.flatnonzero(self._keys != _EMPTY)
        if len(live):
            wp.launch(_k.insert_keys, 1, [wp.array(self._keys[live], dtype=wp.int64, device=dev),
                                          wp.array(live.astype(np.int32), dtype=wp.int32,
                                                   device=dev)],
                      [self._index], device=dev)

    # -- helpers ----------------------------------------------------------------------

    @property
    def _wp_dtype(self):
        return wp.uint16 if self._dtype == np.uint16 else wp.int32

    @property
    def _budget_bricks(self) -> int:
        return self.cache_bytes // self._brick_bytes

    def _index_bytes(self) -> int:
        table = len(self._index.keys) * (8 + 4)
        return table + len(self._keys) * (8 + 8)

    def _on_device(self, a: np.ndarray, dtype) -> wp.array:
        """``a`` as a Warp array; on the CPU a view, so results land in ``a`` directly."""
        return wp.array(a, dtype=dtype, device=self._device, copy=self._device != "cpu")

    def _read(self, path: Path) -> tuple[np.ndarray, np.ndarray]:
        z = read_archive(path, _MAGIC, FORMAT_VERSION, "brick store", StoreFileError)
        try:
            identity, keys, triples = str(z["identity"]), z["keys"], z["triples"]
        except KeyError as e:
            raise StoreFileError(f"{path}: unreadable brick store data ({e})") from None
        if identity != self.identity():
            raise StoreFileError(f"{path}: written for another texture (other exemplars, "
                                 "seed, jitter or synthesis parameters)")
        if triples.dtype != self._dtype or triples.shape != (len(keys), _k.BRICK_VOXELS * 3):
            raise StoreFileError(f"{path}: brick payload of unexpected type or shape")
        return keys.astype(np.int64), triples
