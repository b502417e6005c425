"""Sparse brick store of finest-level synthesis results (Dong 2008, sections 5.2 and 6.2).

The paper stores synthesized surface voxels in a TileTree and synthesizes each region
once (section 6.2). Here finest voxels are kept in bricks of 8^3, found through a hash
table that the lookup kernels of ``kernels.lookup`` search; a brick may be partly filled
(one bit per voxel), and only its stored voxels take room: each brick's voxels are packed
in one range of a shared pool, so a thin surface costs what its voxels cost. A point batch
is looked up in one launch; the voxels it misses are synthesized in one engine request (one
union dependency mask, section 5.2, in parts beyond ``synthesis.MAX_WORK_VOXELS``),
inserted, and the missed points finished. So only
the voxels that queries read are ever synthesized.

A brick holds each voxel's triple of exemplar pixels (section 6.2 keeps triples in 16-bit
targets): 6 bytes per voxel when every exemplar has at most 65536 pixels, else 12, instead
of 4 bytes per color channel. Its color is decoded with exactly the engine's float32
operations, so a stored voxel is bit-identical to ``Synthesizer.voxels``.

Results are position-determined, so eviction, persistence and concurrency only ever
change how much is synthesized, never a color.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple, TypedDict, TypeVar

import numpy as np
import warp as wp

from kernels import lookup as _k
from warptex.archive import (
    dead_writes,
    file_state,
    written_through,
)
from warptex.bricks import (
    Bricks,
    bricks_union,
    gathered,
    most_recent,
    packed,
    range_starts,
    ranges_of,
    stored_bits,
    voxels_per_brick,
)
from warptex.keysets import cell_offsets, local_index, lookup, pack, unique, unpack
from warptex.parallel import launch_ranges
from warptex.settings import DEFAULT_CACHE_BYTES, FILTERS, check_count, check_flag
from warptex.stops import deferred_stops
from warptex.store_files import (
    StoreFileError,
    check_store_path,
    empty_file,
    read_bricks,
    store_settings,
    taking_turns,
    write_bricks,
)
from warptex.synthesis import COORD_LIMIT, Synthesizer, check_voxels
from warptex.thread_warnings import warn
from warptex.warp_runtime import launch

_EMPTY = int(_k.EMPTY)  # the key of a free slot, as the hash table marks free entries
_MIN_BRICKS = 64
_MAX_POOL_VOXELS = ((1 << 31) - 1) // 3  # the kernels index the pool's entries in int32
# Voxels that one batch of lookups synthesizes at most; a batch whose points need more is
# finished in halves. Points far apart each bring a whole brick: a query batch's 2^20 points
# could need 2^29 voxels, whose request arrays alone would not fit.
BATCH_VOXELS = 1 << 22
# Exemplars of up to this many pixels each: pixel indices fit uint16, 6 bytes a voxel.
_COMPACT_PIXELS = 1 << 16
_SLOT_BYTES = _k.VALID_WORDS * 4 + 4  # per brick beside its voxels: stored bits, pool base
_LOCAL = cell_offsets(_k.BRICK)
_T = TypeVar("_T")
# Points lie strictly within +-POINT_LIMIT voxels: trilinear reads a voxel beyond the point.
POINT_LIMIT = COORD_LIMIT - 2
CORNERS = np.indices((2, 2, 2)).reshape(3, -1).T
"""Offsets of the 8 voxels a trilinear lookup blends, in the kernels' order:
corner c is ((c >> 2) & 1, (c >> 1) & 1, c & 1)."""


def brick_keys(voxels: np.ndarray) -> np.ndarray:
    """Packed coordinates of the bricks holding integer ``voxels`` (N, 3), as
    ``kernels.lookup.brick_key`` packs them."""
    return pack(voxels.astype(np.int64) >> _k.BRICK_SHIFT)


def brick_coords(keys: np.ndarray) -> np.ndarray:
    """Brick coordinates (N, 3) int64 of packed brick ``keys``; inverse of ``brick_keys``."""
    return unpack(keys)


def voxels_read(points: np.ndarray, filter: str) -> np.ndarray:
    """Integer voxels (M, 3) that ``filter`` reads for float64 ``points``, repeats included."""
    if filter == "nearest":
        return np.floor(points).astype(np.int64)
    return _corner_voxels(np.floor(points - 0.5).astype(np.int64))


def _corner_voxels(base: np.ndarray) -> np.ndarray:
    """The 8 voxels (N * 8, 3) that trilinear lookups with lower corners ``base`` read."""
    return (base[:, None, :] + CORNERS[None]).reshape(-1, 3)


def unique_voxels(voxels: np.ndarray) -> np.ndarray:
    """The distinct rows of integer ``voxels`` (N, 3), grouped by brick; two 1D sorts,
    much faster than sorting rows."""
    keys, brick = np.unique(brick_keys(voxels), return_inverse=True)
    packed = unique(brick.astype(np.int64) * _k.BRICK_VOXELS + local_index(voxels, _k.BRICK))
    return brick_coords(keys[packed // _k.BRICK_VOXELS]) * _k.BRICK + _LOCAL[
        packed % _k.BRICK_VOXELS]


def brick_voxels(keys: np.ndarray) -> np.ndarray:
    """Every voxel (N * 512, 3) of the bricks ``keys``, x slowest within a brick."""
    return (brick_coords(keys)[:, None, :] * _k.BRICK + _LOCAL[None]).reshape(-1, 3)


class StoreStats(TypedDict):
    """What :meth:`BrickStore.stats` reports of a store."""

    bricks: int
    voxels: int  # stored voxels
    bytes: int  # what the stored voxels take: payload_bytes + index_bytes
    payload_bytes: int  # their triples, their bricks' stored-voxel bits and pool bases
    index_bytes: int  # hash table, brick keys and stamps
    allocated_bytes: int  # all the store holds, free room included
    bytes_per_voxel: int  # of a stored voxel's triple: 6, or 12 past 65536 pixels
    hits: int  # points looked up whose voxels the store held
    misses: int  # points that needed a voxel synthesized first
    voxels_added: int
    bricks_evicted: int
    voxels_synthesized: dict[int, int]  # voxels the engine corrected, per level
    synthesis_seconds: float


class Snapshot(NamedTuple):
    """The stored voxels at one moment, for readers outside Warp.

    ``keys[s]`` is the brick key in pool slot ``s`` (-1 where free) and
    ``sums[s * 512 + local]`` the three-color sum (C channels, float32) of that brick's
    voxel ``local`` (x slowest), exactly as the lookup kernels compute it, NaN where that
    voxel is not stored. ``version`` changes whenever voxels are inserted or evicted.
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

    # A Ctrl-C between taking the lock and the block (the lock's own release raises it)
    # must not leave a reader or writer counted for ever: every later change or lookup
    # would wait for it. Hence the counts change inside the ``try`` their ``finally`` undoes.

    @contextmanager
    def shared(self) -> Iterator[None]:
        entered = False
        try:
            with self._cond:
                self._cond.wait_for(lambda: not self._writing and not self._waiting)
                self._readers += 1
                entered = True
            yield
        finally:
            if entered:
                with self._cond:
                    self._readers -= 1
                    self._cond.notify_all()

    @contextmanager
    def exclusive(self) -> Iterator[None]:
        entered = False
        try:
            with self._cond:
                self._waiting += 1
                try:
                    self._cond.wait_for(lambda: not self._writing and not self._readers)
                finally:
                    self._waiting -= 1
                self._writing = entered = True
            yield
        finally:
            with self._cond:  # also a wait stopped: it held back lookups while it waited
                if entered:
                    self._writing = False
                self._cond.notify_all()


def check_lookup_channels(channels: int) -> None:
    """Raise ValueError unless the voxels of exemplars of ``channels`` color channels can be
    stored and looked up: the lookup kernels filter at most four."""
    if channels > _k.MAX_CHANNELS:
        raise ValueError(f"{channels} color channels; points are looked up in at most "
                         f"{_k.MAX_CHANNELS} (gray, RGB or RGBA)")


def check_store_settings(cache_bytes: object, whole_bricks: object) -> tuple[int, bool]:
    """``cache_bytes`` and ``whole_bricks`` as :class:`BrickStore` keeps them, after a
    SettingError unless they are a byte count and a bool."""
    return check_count("cache_bytes", cache_bytes), check_flag("whole_bricks", whole_bricks)


class BrickStore:
    """Finest-level voxels of one solid texture in 8^3 bricks, synthesized on first touch
    (Dong 2008, section 6.2: synthesis focused on the voxels a surface needs, kept as triples).

    ``cache_bytes`` bounds the stored voxels and their bricks' bits, up to what the pool's
    int32 indices reach (about 700 million voxels; a larger one is warned of and kept to
    that); least-recently-used bricks are evicted after each batch (a batch may exceed the
    bound while it is being finished). ``whole_bricks``: a miss synthesizes the whole brick
    of each voxel read,
    best when queries come back near each other (renders, volumes); else only the voxels
    read, best for thin sets such as mesh surfaces and cuts. Either way a stored voxel
    costs 6 bytes (12 with exemplars over 65536 pixels).
    """

    def __init__(self, synthesizer: Synthesizer, *, cache_bytes: int = DEFAULT_CACHE_BYTES,
                 whole_bricks: bool = True) -> None:
        if not isinstance(synthesizer, Synthesizer):
            raise TypeError(f"a BrickStore stores the voxels of a Synthesizer (a SolidTexture's "
                            f"is its .synthesizer), got {type(synthesizer).__name__}")
        self.synthesizer = synthesizer
        self.cache_bytes, self.whole_bricks = check_store_settings(cache_bytes, whole_bricks)
        cs = synthesizer.candidates
        sources = [cs.colors[cs.axis_source[k]] for k in range(3)]
        self.channels = cs.channels
        check_lookup_channels(self.channels)
        self._pixels = np.array([c.shape[0] * c.shape[1] for c in sources])
        compact = self._pixels.max() <= _COMPACT_PIXELS
        self._dtype = np.dtype(np.uint16 if compact else np.int32)
        self._voxel_bytes = 3 * self._dtype.itemsize
        # The pool's int32 indices bound the voxels kept, whatever cache_bytes asks: room is
        # left for a batch stored before eviction and the voxels of the bricks it repacks.
        # Beyond it, a store filled up and refused every miss (a render failed half way).
        self._most_bytes = (_MAX_POOL_VOXELS - 2 * BATCH_VOXELS) * self._voxel_bytes
        if self.cache_bytes > self._most_bytes:
            warn(f"cache_bytes {self.cache_bytes} is more than a brick store's pool can index: "
                 f"the store keeps at most {self._most_bytes} bytes of voxels", stacklevel=2)
        self._device = synthesizer.device
        uploaded = {j: wp.array(cs.colors[j].reshape(-1), dtype=wp.float32, device=self._device)
                    for j in set(cs.axis_source)}
        self._colors = _k.ExemplarColors()
        self._colors.x, self._colors.y, self._colors.z = (uploaded[j] for j in cs.axis_source)
        self._colors.channels = self.channels
        self._lock = _SharedLock()
        self._counts = threading.Lock()
        self._tick = itertools.count(1)
        self._index = _k.BrickIndex()
        self._index.reach = float(POINT_LIMIT)
        self._empty()
        # Set while the bricks change: still set afterwards where the change was cut short.
        self._torn = False
        self._hits = self._misses = self._added = self._evicted = 0
        self._version = 0
        # The store file last loaded from or written (file_state) and the version then.
        self._synced: tuple | None = None
        # The store file that loading reported and ignored (file_state): replaced unsaid.
        self._ignored: tuple | None = None
        self._seconds = 0.0

    @property
    def brick_bytes(self) -> int:
        """What one whole brick takes of ``cache_bytes``: its voxels' triples and its slot."""
        return _k.BRICK_VOXELS * self._voxel_bytes + _SLOT_BYTES

    @property
    def _budget(self) -> int:
        """The bytes of bricks kept: ``cache_bytes``, within what the pool can index."""
        return min(self.cache_bytes, self._most_bytes)

    # -- public API -------------------------------------------------------------------

    def identity(self) -> str:
        """Digest of everything a stored voxel depends on (:func:`store_settings`)."""
        return hashlib.sha256(self._settings_json().encode()).hexdigest()

    def _settings_json(self) -> str:
        return json.dumps(store_settings(self.synthesizer), sort_keys=True)

    def sample(self, points: np.ndarray, filter: str, out: np.ndarray) -> None:
        """Colors of float64 ``points`` (N, 3) into ``out`` (N, C) float32."""
        if not (isinstance(out, np.ndarray) and out.dtype == np.float32
                and out.flags.c_contiguous and out.shape == (len(points), self.channels)):
            # On the CPU the kernels write into ``out`` itself: any other array would be
            # copied by Warp, and the colors lost with the copy.
            got = (f"{out.dtype} {out.shape}" if isinstance(out, np.ndarray)
                   else type(out).__name__)
            raise ValueError(f"out must be a C-contiguous float32 array of shape "
                             f"{(len(points), self.channels)}, got {got}")
        if filter not in FILTERS:
            raise ValueError(f"filter must be one of {FILTERS}, got {filter!r}")
        n = len(points)
        if n == 0:
            return
        kernel = _k.sample_nearest if filter == "nearest" else _k.sample_trilinear
        pts, res, missed, count = self._lookup_arrays(points, out)
        with self._reading():
            misses = self._launch(kernel, pts, res, missed, count)
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
        """Changes whenever voxels are inserted or bricks evicted."""
        return self._version

    def prefetch(self, voxels: np.ndarray) -> None:
        """Store integer ``voxels`` (N, 3) (their whole bricks with ``whole_bricks``),
        synthesizing the absent ones in one engine request; coordinates the engine refuses
        are refused here, before a brick key could wrap them onto other voxels."""
        voxels = check_voxels(voxels)
        if len(voxels):
            self._with_voxels(self._to_store(voxels), lambda: None)

    def mark_used(self, slots: np.ndarray, version: int) -> None:
        """Count pool ``slots`` of the snapshot of ``version`` as just used, for
        readers outside Warp; ignored if bricks were inserted or evicted since."""
        slots = np.asarray(slots)
        with self._lock.exclusive():
            if version != self._version or len(slots) == 0 or self._torn:
                return
            # A slot NumPy would wrap (negative) or not have would stamp another brick.
            if slots.min() < 0 or slots.max() >= len(self._keys):
                raise IndexError(f"slots must be those of the snapshot, 0 to "
                                 f"{len(self._keys) - 1}, got {slots.min()} to {slots.max()}")
            self._stamp(slots)

    def snapshot(self) -> Snapshot:
        """The stored bricks and their voxels' color sums (see :class:`Snapshot`)."""
        with self._reading():
            slots = np.arange(len(self._keys))
            return Snapshot(self._version, self._keys.copy(), self._voxel_sums(slots))

    def brick_sums(self, keys: np.ndarray) -> np.ndarray:
        """Color sums (len(keys) * 512, C) of the voxels of bricks ``keys``, in the layout
        and with the NaNs of :class:`Snapshot`'s; all NaN for a brick not stored. The
        stored ones count as just used, for least-recently-used eviction."""
        with self._reading():
            slots = self._slots_of(np.asarray(keys, np.int64))
            sums, version = self._voxel_sums(slots), self._version
        self.mark_used(slots[slots >= 0], version)
        return sums

    def _voxel_sums(self, slots: np.ndarray) -> np.ndarray:
        """:class:`Snapshot` sums of the bricks in pool ``slots`` (-1: absent)."""
        sums = wp.empty((len(slots) * _k.BRICK_VOXELS, self.channels), dtype=wp.float32,
                        device=self._device)
        if sums.shape[0]:
            slots = slots.astype(np.int32)  # held while the launch views it
            launch(_k.voxel_sums, sums.shape[0],
                   [self._on_device(slots, wp.int32), self._index, self._pool,
                    self._colors], [sums], device=self._device)
        return sums.numpy()

    def stats(self) -> StoreStats:
        """Bricks and stored voxels, bytes, lookups served from the store (hits) or not
        (misses), and the synthesis behind them: voxels added to the store, voxels the
        engine corrected per level, seconds (:class:`StoreStats`)."""
        with self._reading(), self._counts:
            bricks = int((self._keys != _EMPTY).sum())
            voxels = int(np.bitwise_count(self._valid).sum())
            payload = voxels * self._voxel_bytes + bricks * _SLOT_BYTES
            index = self._index_bytes()
            held = len(self._payload) * self._voxel_bytes + len(self._keys) * _SLOT_BYTES + index
            return {
                "bricks": bricks,
                "voxels": voxels,
                "bytes": payload + index,
                "payload_bytes": payload,
                "index_bytes": index,
                "allocated_bytes": held,
                "bytes_per_voxel": self._voxel_bytes,
                "hits": self._hits,
                "misses": self._misses,
                "voxels_added": self._added,
                "bricks_evicted": self._evicted,
                "voxels_synthesized": dict(self.synthesizer.voxels_synthesized),
                "synthesis_seconds": self._seconds,
            }

    def save(self, path: str | Path) -> bool:
        """Write the bricks to a versioned, checksummed file atomically (temporary name,
        then rename), least recently used first; a file of another kind at ``path`` is
        refused (StoreFileError), not replaced.

        A file this texture saved before, from this or another process, is merged with, not
        replaced: its voxels are the same as ours, so both renders' work stays warm. Its
        bricks count as older than ours, and the most recent that fit ``cache_bytes``, the
        memory that the file's bricks take, or that ours take once merged with the file's
        copies of them (a partly filled brick grows), whichever is largest, are written, so
        every brick of ours is. Saves to one file take turns, so none loses the bricks of
        another. A damaged file or another texture's is replaced, with a warning unless
        loading gave one for it, by a store that holds voxels; an empty store leaves it. A
        save that writes deletes the temporary files that saves killed over
        :data:`~warptex.archive.UNFINISHED_AGE` ago left beside the file.

        The file is left as it is, and False returned, where the store is empty and the file
        damaged or another's, or where it is the one this store was loaded from or last
        saved to, unchanged since, and no voxel was stored since: it holds every brick of
        ours then, and a shared file is not rewritten by every render that only reads it (so
        such a render does not make its bricks the file's most recently used). Else True.
        """
        path = written_through(Path(path))  # saves through a link take turns at its target
        check_store_path(path)
        with self._reading():
            version = self._version
            live = self._by_recency()
            ours = Bricks(self._keys[live], gathered(self._payload, self._base[live],
                                                     self._voxel_counts(live)),
                          self._valid[live])
        with taking_turns(path):
            state = file_state(path)
            if state is not None and self._synced == (state, version):
                return False
            for leftover in dead_writes(path):  # a killed saver's, perhaps gigabytes
                with contextlib.suppress(OSError):
                    leftover.unlink()
            try:
                saved = self._read(path) if path.exists() and not empty_file(path) else None
            except StoreFileError as e:
                if not len(ours.keys):  # nothing to keep: another texture's voxels stay
                    return False
                if state != self._ignored:  # reported once, when it was loaded
                    warn(f"replacing brick store file: {e}", stacklevel=2)
                saved = None
            if saved is None:
                kept = self._recent_that_fit(ours)
            else:  # a store of less room does not shrink a shared file
                mine = len(ours.keys)

                def fitting(valid: np.ndarray) -> int:
                    # Our partly filled bricks may have grown by the file's voxels: all of
                    # them are kept still, as the file is then marked as holding them.
                    budget = max(self._budget, *(
                        int(self._brick_costs(voxels_per_brick(v)).sum())
                        for v in (saved.valid, valid[len(valid) - mine:])))
                    return int(self._kept(voxels_per_brick(valid), budget).sum())

                kept = bricks_union(saved, ours, fitting)
            write_bricks(path, self.identity(), self._settings_json(), kept)
            self._synced = (file_state(path), version)
        return True

    @classmethod
    def load(cls, path: str | Path, synthesizer: Synthesizer, *,
             cache_bytes: int = DEFAULT_CACHE_BYTES, whole_bricks: bool = True) -> BrickStore:
        """A store holding the bricks saved in ``path``, the most recently used that fit
        ``cache_bytes``; an empty one, with a warning, when the file is damaged or belongs
        to another texture. Partly filled bricks load into either kind of store: with
        ``whole_bricks`` a miss in one fills the rest of it.

        Raises:
            StoreFileError: ``path`` is a folder or a file of another kind, which saving
                would destroy.
        """
        check_store_path(path)
        store = cls(synthesizer, cache_bytes=cache_bytes, whole_bricks=whole_bricks)
        state = file_state(Path(path))  # before reading: a file replaced meanwhile differs
        if empty_file(Path(path)):
            return store
        try:
            kept = store._recent_that_fit(store._read(Path(path)))
        except StoreFileError as e:
            warn(f"ignoring brick store file, starting empty: {e}", stacklevel=2)
            store._ignored = state
            return store
        with store._changing():
            store._fill(kept)
            store._synced = (state, store._version)  # the file holds every brick loaded
        return store

    # -- locking ----------------------------------------------------------------------

    @contextmanager
    def _changing(self) -> Iterator[None]:
        """The exclusive lock, for changing the bricks. Ctrl-C or SIGTERM waits for the
        change to end, so the voxels synthesized before it are kept and saved. A change cut
        short by an error may leave the bricks half made, so the store then drops every
        brick instead: their voxels can only be synthesized again, never read wrong or saved
        torn."""
        with deferred_stops(), self._lock.exclusive():
            if self._torn:  # a change cut short, and the emptying after it too
                self._empty_again()
            self._torn = True  # first: whatever is cut short after this, the flag shows it
            try:
                yield
            except BaseException:
                self._empty_again()
                raise
            self._torn = False

    def _empty_again(self) -> None:
        """Drop every brick, after a change of them was cut short."""
        self._empty()
        self._version += 1  # readers' copies (traced, scalar) see the bricks gone
        self._torn = False

    @contextmanager
    def _reading(self) -> Iterator[None]:
        """The shared lock, for reading the bricks; a store left torn (its emptying after a
        change cut short was cut short too) is emptied first."""
        if self._torn:
            with self._changing():
                pass
        with self._lock.shared():
            if self._torn:  # torn again meanwhile, by another thread's change
                raise RuntimeError("brick store: a change of its bricks was cut short; "
                                   "query again")
            yield

    # -- batches ----------------------------------------------------------------------

    def _with_voxels(self, voxels: np.ndarray, run: Callable[[], _T]) -> _T:
        """Run ``run`` while all unique ``voxels`` are stored, then evict; returns what
        ``run`` returns.

        Absent voxels are synthesized outside the lock, so lookups of stored voxels go
        on meanwhile; voxels evicted by another thread before we get the lock again are
        synthesized in the next round.
        """
        made: list[tuple[np.ndarray, np.ndarray]] = []
        while True:
            with self._changing():
                # Everything this batch synthesized goes back in, so each round leaves
                # fewer voxels to make and the loop ends whatever other threads evict.
                for v, payload in made:
                    kept = ~self._stored(v)  # not those still stored: they would be repacked
                    self._insert(v[kept], payload[kept])
                    lost = np.count_nonzero(~self._stored(v))
                    if lost:  # else the loop would synthesize them for ever
                        raise RuntimeError(f"{lost} of {len(v)} voxels inserted in the brick "
                                           "store are not stored")
                absent = voxels[~self._stored(voxels)]
                if len(absent) == 0:
                    result = run()
                    self._evict()
                    return result
            made.append((absent, self._synthesize(absent)))

    def _finish(self, kernel, points: np.ndarray, filter: str, out: np.ndarray,
                rows: np.ndarray) -> None:
        """Second half of a batch: the points whose voxels were missing, or that lie out
        of the table's reach (NaN, infinite or far), which the kernels count as missing
        rather than let their brick keys wrap onto other voxels."""
        inside = (np.abs(points) < POINT_LIMIT).all(axis=1)  # False for NaN too
        if not inside.all():
            raise ValueError(f"{int((~inside).sum())} of {len(rows)} points are NaN, "
                             f"infinite or beyond +-{POINT_LIMIT} voxels; points must lie "
                             "within it")
        voxels = self._to_store(voxels_read(points, filter),
                                most=BATCH_VOXELS if len(points) > 1 else None)
        if voxels is None:
            at = np.flatnonzero(rows)
            for half in np.array_split(np.arange(len(points)), 2):
                part = np.zeros(len(rows), bool)
                part[at[half]] = True
                self._finish(kernel, points[half], filter, out, part)
            return
        sub = np.empty((len(points), self.channels), np.float32)
        pts, res, missed, count = self._lookup_arrays(np.ascontiguousarray(points), sub)
        misses = self._with_voxels(voxels,
                                   lambda: self._launch(kernel, pts, res, missed, count))
        if misses:
            # Their colors were never written: a fault of the store, never a result.
            raise RuntimeError(f"{misses} of {len(points)} points still read voxels missing "
                               "from the brick store after synthesizing them")
        out[rows] = res.numpy()

    def _lookup_arrays(self, points: np.ndarray, out: np.ndarray) -> tuple[wp.array, ...]:
        """A lookup launch's points, colors (bound for ``out``), flags of the points that
        missed a voxel and count of them."""
        missed = wp.zeros(len(points), dtype=wp.int32, device=self._device)
        count = wp.zeros(1, dtype=wp.int32, device=self._device)
        return self._on_device(points, wp.vec3d), self._results(out), missed, count

    def _to_store(self, voxels: np.ndarray, most: int | None = None) -> np.ndarray | None:
        """The unique voxels to have stored for reading ``voxels``; None where they are more
        than ``most``, whole bricks counted before they are made."""
        if self.whole_bricks:
            keys = unique(brick_keys(voxels))
            if most is not None and len(keys) * _k.BRICK_VOXELS > most:
                return None
            return brick_voxels(keys)
        stored = unique_voxels(voxels)
        return None if most is not None and len(stored) > most else stored

    def _synthesize(self, voxels: np.ndarray) -> np.ndarray:
        """Triples (N, 3) of ``voxels`` as pixel indices, in one engine request."""
        start = time.perf_counter()
        triples = self.synthesizer.pixel_triples(voxels)
        seconds = time.perf_counter() - start
        with self._counts:
            self._seconds += seconds
            self._added += len(voxels)
        return triples.astype(self._dtype)

    def _launch(self, kernel, points: wp.array, out: wp.array, missed: wp.array,
                count: wp.array) -> int:
        """One lookup launch, split in ranges over CPU threads (Warp runs a CPU launch on
        one thread; points are independent, so ranges give the same result); returns how
        many points missed."""
        inputs = [points, self._index, self._pool, self._colors, wp.int64(next(self._tick))]
        launch_ranges(kernel, 0, len(points), inputs, [out, missed, count],
                      device=self._device)
        if self._device == "cpu":
            # Warp's CPU atomics are plain reads and writes, so threads of a split launch
            # lose counts; a GPU counts exactly and spares copying the flags back.
            return int(np.count_nonzero(missed.numpy()))
        return int(count.numpy()[0])

    # -- mutation (exclusive lock held) -----------------------------------------------

    def _stored(self, voxels: np.ndarray) -> np.ndarray:
        """Whether each of ``voxels`` (N, 3) is stored."""
        slots = self._slots_of(brick_keys(voxels))
        local = local_index(voxels, _k.BRICK)
        found = slots >= 0
        words = self._valid[slots[found], local[found] >> 5]
        out = np.zeros(len(voxels), bool)
        out[found] = (words >> (local[found] & 31).astype(np.uint32)) & 1 != 0
        return out

    def _slots_of(self, keys: np.ndarray) -> np.ndarray:
        """Pool slot of each brick key, -1 where the brick is absent."""
        live = np.flatnonzero(self._keys != _EMPTY)
        if len(live) == 0:
            return np.full(len(keys), -1, np.int64)
        order = live[np.argsort(self._keys[live])]
        pos = lookup(self._keys[order], keys)
        return np.where(pos >= 0, order[pos], -1)

    def _insert(self, voxels: np.ndarray, payload: np.ndarray) -> None:
        """Store ``voxels`` (N, 3) with their triples ``payload`` (N, 3).

        New bricks get free slots. Every brick receiving voxels is repacked: its stored
        voxels and the new ones, in local order, go to a fresh range at the end of the
        pool, and its old range is left behind until the next compaction.
        """
        if len(voxels) == 0:
            return
        keys = brick_keys(voxels)
        absent = keys[self._slots_of(keys) < 0]
        # Slots in order of first appearance: a loaded file lists bricks least recently
        # used first, and eviction breaks ties of equal stamps by slot.
        fresh = absent[np.sort(np.unique(absent, return_index=True)[1])]
        if len(fresh):
            free = np.flatnonzero(self._keys == _EMPTY)
            if len(free) < len(fresh):
                live = len(self._keys) - len(free)
                self._grow_slots(max(live + len(fresh), 2 * len(self._keys), _MIN_BRICKS))
                free = np.flatnonzero(self._keys == _EMPTY)
            self._keys[free[: len(fresh)]] = fresh
            self._valid[free[: len(fresh)]] = 0
            live = int((self._keys != _EMPTY).sum())
            if 2 * live > len(self._index.keys):
                self._rebuild_table(1 << (2 * live).bit_length())
            else:
                self._index_bricks(fresh, free[: len(fresh)])
        slots = self._slots_of(keys)
        touched = unique(slots)
        # Old and new voxels of the touched bricks, ordered by (brick, local) and without
        # repeats (a voxel synthesized twice has the same triple): the repacked ranges.
        old = self._ranges(touched)
        first, valid = packed(np.concatenate([
            np.flatnonzero(stored_bits(self._valid[touched])),
            np.searchsorted(touched, slots) * _k.BRICK_VOXELS + local_index(voxels, _k.BRICK)]),
            len(touched))
        triples = np.concatenate([self._payload[old], payload.astype(self._dtype)])[first]
        start = self._reserve(len(triples))  # may compact the pool, never moves slots
        self._garbage += len(old)
        self._valid[touched] = valid
        self._place(touched, start, triples)

    def _fill(self, bricks: Bricks) -> None:
        """Fill this empty store with ``bricks``, listed least recently used first. A
        file's triples lie brick after brick in local order, as the pool keeps them, so
        they are copied as they are; slots follow the list, so eviction breaks the tie of
        their equal stamps in its order."""
        count, voxels = len(bricks.keys), len(bricks.triples)
        if count == 0:
            return
        if count > len(self._keys):
            self._grow_slots(count)
        self._keys[:count] = bricks.keys
        self._valid[:count] = bricks.valid
        self._rebuild_table(max(len(self._index.keys), 1 << (2 * count).bit_length()))
        self._place(np.arange(count), self._reserve(voxels), bricks.triples)

    def _place(self, slots: np.ndarray, start: int, triples: np.ndarray) -> None:
        """Put ``triples``, the voxels of the bricks in ``slots`` (their bits already set)
        brick after brick in local order, at pool position ``start``; the bricks count as
        used now."""
        self._payload[start: start + len(triples)] = triples
        self._base[slots] = start + range_starts(self._voxel_counts(slots))
        self._upload_pool(start, start + len(triples))
        self._upload_slots()
        self._stamp(slots)
        self._version += 1

    def _stamp(self, slots: np.ndarray) -> None:
        """Count the bricks in ``slots`` as used now (least recently used go first)."""
        stamps = self._index.stamps.numpy()
        stamps[slots] = next(self._tick)
        self._index.stamps.assign(stamps)

    def _by_recency(self) -> np.ndarray:
        """The slots of stored bricks, least recently used first (equal stamps by slot)."""
        live = np.flatnonzero(self._keys != _EMPTY)
        return live[np.argsort(self._index.stamps.numpy()[live], kind="stable")]

    def _recent_that_fit(self, bricks: Bricks) -> Bricks:
        """The most recently used of ``bricks`` that fit the store's bound (``cache_bytes``
        within what the pool indexes)."""
        # The list ends with the most recent, so those kept are its tail: viewed, not copied.
        return most_recent(bricks, int(self._kept(voxels_per_brick(bricks.valid)).sum()))

    def _kept(self, counts: np.ndarray, budget: int | None = None) -> np.ndarray:
        """Which of the bricks holding ``counts`` voxels each, listed least recently used
        first, ``budget`` bytes (the store's bound unless given) keep: the most recently used
        that fit."""
        cost = self._brick_costs(counts)
        return np.cumsum(cost[::-1])[::-1] <= (self._budget if budget is None else budget)

    def _brick_costs(self, counts: np.ndarray) -> np.ndarray:
        """The bytes that bricks holding ``counts`` voxels each take in a store."""
        return counts * self._voxel_bytes + _SLOT_BYTES

    def _empty(self) -> None:
        """Hold no brick (pool, slots and table as a new store's)."""
        self._keys = np.full(0, _EMPTY, np.int64)  # brick key of each slot
        self._valid = np.zeros((0, _k.VALID_WORDS), np.uint32)  # stored-voxel bits per slot
        self._base = np.zeros(0, np.int64)  # pool position of each slot's first voxel
        # The pool; the device's array shows it on the CPU and is a copy of it on CUDA.
        self._payload = np.zeros((0, 3), self._dtype)
        self._used = 0  # pool voxels handed out, live or left behind by repacked bricks
        self._garbage = 0  # of those, voxels of repacked or evicted bricks
        self._index.stamps = wp.zeros(0, dtype=wp.int64, device=self._device)
        self._pool_source: np.ndarray | None = None  # the host array the device pool shows
        self._upload_slots()
        self._upload_pool(0, 0)
        self._rebuild_table(_MIN_BRICKS * 2)

    def _evict(self) -> None:
        """Drop least-recently-used bricks until the stored voxels fit ``cache_bytes``."""
        live = self._by_recency()
        counts = self._voxel_counts(live)
        gone = live[~self._kept(counts)]
        if len(gone) == 0:
            return
        self._keys[gone] = _EMPTY
        self._valid[gone] = 0
        self._garbage += int(counts[: len(gone)].sum())
        self._evicted += len(gone)
        self._version += 1
        if len(self._keys) > 2 * max(len(live) - len(gone), _MIN_BRICKS):
            self._renumber_slots()
        if 2 * self._garbage > self._used:
            self._compact()
        self._rebuild_table(len(self._index.keys))
        self._upload_slots()

    def _voxel_counts(self, slots: np.ndarray) -> np.ndarray:
        """Stored voxels of each of ``slots``."""
        return voxels_per_brick(self._valid[slots])

    def _ranges(self, slots: np.ndarray) -> np.ndarray:
        """Pool positions of the stored voxels of ``slots``, brick after brick."""
        return ranges_of(self._base[slots], self._voxel_counts(slots))

    def _reserve(self, voxels: int) -> int:
        """Pool position of ``voxels`` new consecutive voxels; compacts or grows the pool."""
        if self._used + voxels > len(self._payload) and (
                2 * self._garbage > self._used
                or (self._garbage and self._used + voxels > _MAX_POOL_VOXELS)):
            self._compact()
        needed = self._used + voxels
        if needed > len(self._payload):
            if needed > _MAX_POOL_VOXELS:
                raise MemoryError(f"brick store pool of {needed} voxels exceeds 2^31 entries")
            # Doubling, but up to the limit: a pool that fits is never refused for its growth.
            size = min(max(needed, 2 * len(self._payload), _MIN_BRICKS * 64), _MAX_POOL_VOXELS)
            payload = np.zeros((size, 3), self._dtype)
            payload[: self._used] = self._payload[: self._used]
            self._payload = payload
            self._upload_pool(0, self._used)
        start = self._used
        self._used += voxels
        return start

    def _grow_slots(self, slots: int) -> None:
        old = len(self._keys)
        stamps = wp.zeros(slots, dtype=wp.int64, device=self._device)
        if old:
            wp.copy(stamps, self._index.stamps, count=old)
        self._index.stamps = stamps
        self._keys = np.concatenate([self._keys, np.full(slots - old, _EMPTY, np.int64)])
        self._valid = np.concatenate([self._valid,
                                      np.zeros((slots - old, _k.VALID_WORDS), np.uint32)])
        self._base = np.concatenate([self._base, np.zeros(slots - old, np.int64)])

    def _renumber_slots(self) -> None:
        """Move the live bricks to the first slots, in slot order, and give back the rest
        (a large batch may have made many slots; readers such as the traced lookups
        mirror every slot)."""
        live = np.flatnonzero(self._keys != _EMPTY)
        stamps = self._index.stamps.numpy()[live]
        keys, valid, base = self._keys[live], self._valid[live], self._base[live]
        self._keys = np.zeros(0, np.int64)
        self._valid = np.zeros((0, _k.VALID_WORDS), np.uint32)
        self._base = np.zeros(0, np.int64)
        self._grow_slots(max(2 * len(live), _MIN_BRICKS))
        self._keys[: len(live)] = keys
        self._valid[: len(live)] = valid
        self._base[: len(live)] = base
        stamps = np.concatenate([stamps, np.zeros(len(self._keys) - len(live), np.int64)])
        self._index.stamps.assign(stamps)

    def _compact(self) -> None:
        """Pack the live bricks' voxels at the start of the pool, dropping what repacked
        and evicted bricks left behind; slots stay where they are."""
        live = np.flatnonzero(self._keys != _EMPTY)
        counts = self._voxel_counts(live)
        used = int(counts.sum())
        # Room to grow, but not past the limit, which _reserve checks only to grow the pool.
        payload = np.zeros((min(2 * used, max(used, _MAX_POOL_VOXELS)), 3), self._dtype)
        gathered(self._payload, self._base[live], counts, out=payload[:used])
        self._payload = payload
        self._base[live] = range_starts(counts)
        self._used, self._garbage = used, 0
        self._upload_pool(0, self._used)

    def _upload_slots(self) -> None:
        # Called once at the end of each mutation, after slots, bits and bases settle.
        # Lookups skip the stored-voxel bits while every brick is whole; a store filling
        # whole bricks may still hold partly filled ones, loaded from a file.
        live = self._keys != _EMPTY
        self._index.partial = int((self._valid[live] != np.uint32(0xFFFFFFFF)).any())
        dev = self._device
        self._index.valid = wp.array(self._valid.reshape(-1), dtype=wp.uint32, device=dev)
        self._index.base = wp.array(self._base.astype(np.int32), dtype=wp.int32, device=dev)

    def _upload_pool(self, start: int, stop: int) -> None:
        """Make the device pool show pool voxels ``start..stop`` as the host's; on the
        CPU the device pool is the host array itself, so only a new array needs a view."""
        dev = self._device
        flat = self._payload.reshape(-1)
        if dev == "cpu":
            if self._pool_source is not self._payload:
                self._pool = wp.array(flat, dtype=self._wp_dtype, device=dev, copy=False)
                self._pool_source = self._payload
            return
        if self._pool_source is not self._payload:
            self._pool = wp.zeros(len(flat), dtype=self._wp_dtype, device=dev)
            self._pool_source = self._payload
        if stop > start:
            part = wp.array(flat[3 * start: 3 * stop], dtype=self._wp_dtype, device=dev)
            wp.copy(self._pool, part, dest_offset=3 * start, count=3 * (stop - start))

    def _rebuild_table(self, capacity: int) -> None:
        dev = self._device
        self._index.keys = wp.full(capacity, _EMPTY, dtype=wp.int64, device=dev)
        self._index.slots = wp.zeros(capacity, dtype=wp.int32, device=dev)
        self._index.mask = capacity - 1
        live = np.flatnonzero(self._keys != _EMPTY)
        self._index_bricks(self._keys[live], live)

    def _index_bricks(self, keys: np.ndarray, slots: np.ndarray) -> None:
        """Enter distinct bricks ``keys``, absent from the table, at pool ``slots``."""
        if len(keys) == 0:
            return
        dev = self._device
        # One launch, never split over CPU threads: Warp's atomics are plain reads and
        # writes on the CPU, atomic only between the threads of a CUDA launch.
        launch(_k.insert_keys, len(keys),
               [wp.array(keys, dtype=wp.int64, device=dev),
                wp.array(slots.astype(np.int32), dtype=wp.int32, device=dev)],
               [self._index], device=dev)

    # -- helpers ----------------------------------------------------------------------

    @property
    def _wp_dtype(self):
        return wp.uint16 if self._dtype == np.uint16 else wp.int32

    def _index_bytes(self) -> int:
        table = len(self._index.keys) * (8 + 4)
        return table + len(self._keys) * (8 + 8)

    def _on_device(self, a: np.ndarray, dtype) -> wp.array:
        """``a`` as a Warp array; on the CPU a view, so results land in ``a`` directly."""
        return wp.array(a, dtype=dtype, device=self._device, copy=self._device != "cpu")

    def _read(self, path: Path) -> Bricks:
        return read_bricks(path, self.identity(), self._settings_json(), self._dtype,
                           self._pixels)

    def _results(self, out: np.ndarray) -> wp.array:
        """Where a launch writes colors bound for ``out``: ``out`` itself on the CPU, else
        device memory, read back after the launch (nothing to upload first)."""
        if self._device == "cpu":
            return self._on_device(out, wp.float32)
        return wp.empty(out.shape, dtype=wp.float32, device=self._device)

