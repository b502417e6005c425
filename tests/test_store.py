"""BrickStore: hash table, color decoding, LRU eviction and the store file."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import os
import re
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from kernels.lookup import BRICK_VOXELS
from warptex.archive import _TOKEN_BYTES, UNFINISHED_AGE, _temporary_name
from warptex.store import (
    BrickStore,
    StoreStats,
    brick_keys,
    brick_voxels,
    unique_voxels,
    voxels_read,
)
from warptex.store_files import StoreFileError, store_settings

SLOT_BYTES = 68  # a brick's stored-voxel bits and pool base
BRICK_BYTES = 512 * 6 + SLOT_BYTES  # uint16 triples


@pytest.fixture(scope="module")
def candidates(granite_32_file, warp_device):
    from warptex.candidates import precompute

    return precompute(granite_32_file)


def synthesizer(candidates, **kw):
    from warptex.synthesis import Synthesizer

    return Synthesizer(candidates, device="cpu", **kw)


def sample(store: BrickStore, points, filter="nearest") -> np.ndarray:
    pts = np.asarray(points, np.float64)
    out = np.empty((len(pts), store.channels), np.float32)
    store.sample(pts, filter, out)
    return out


def brick_center(b) -> list[float]:
    return [8 * c + 4.5 for c in b]


def test_unique_voxels_are_the_distinct_rows():
    rng = np.random.default_rng(2)
    v = rng.integers(-20, 20, (5000, 3))
    got = unique_voxels(v)
    assert len(got) == len(np.unique(v, axis=0))
    assert {tuple(r) for r in got} == {tuple(r) for r in v}


def test_voxels_read_by_each_filter():
    def as_set(voxels):
        return {tuple(int(c) for c in v) for v in voxels}

    at_border = np.array([[8.0, 4.0, -3.0]])
    assert as_set(voxels_read(at_border, "nearest")) == {(8, 4, -3)}
    assert as_set(voxels_read(at_border, "trilinear")) == {
        (x, y, z) for x in (7, 8) for y in (3, 4) for z in (-4, -3)}
    assert brick_keys(np.array([[-1, -8, -9]])) == brick_keys(np.array([[-8, -1, -16]]))


def test_hash_table_finds_many_bricks_and_decodes_like_the_engine(candidates):
    """Bricks inserted straight into the table (no synthesis): every lookup must find
    its own brick through probing and table growth, and decode the engine's colors."""
    syn = synthesizer(candidates)
    store = BrickStore(syn)
    rng = np.random.default_rng(0)
    coords = np.unique(rng.integers(-40, 40, (700, 3)), axis=0)
    keys = brick_keys(coords * 8)
    pixels = rng.integers(0, 32 * 32, (len(keys) * 512, 3))
    with store._lock.exclusive():
        store._insert(brick_voxels(keys), pixels.astype(np.uint16))
    local = rng.integers(0, 8, (len(keys), 3))
    pts = coords * 8 + local + 0.5
    slot_of = {k: i for i, k in enumerate(keys)}
    idx = np.array([slot_of[k] * 512 + x * 64 + y * 8 + z
                    for k, (x, y, z) in zip(keys, local, strict=True)])
    np.testing.assert_array_equal(sample(store, pts), syn.colors_of(pixels[idx]))
    stats = store.stats()
    assert stats["bricks"] == len(keys) and stats["misses"] == 0
    assert stats["voxels"] == len(keys) * 512 and stats["voxels_added"] == 0
    assert stats["index_bytes"] <= 0.1 * stats["payload_bytes"]
    assert stats.keys() == StoreStats.__annotations__.keys()  # as documented, no more
    check_table(store, keys, np.arange(len(keys)))


@pytest.mark.parametrize("whole_bricks", [True, False])
def test_a_non_square_exemplar_decodes_like_the_engine(granite_32x48, warp_device,
                                                       whole_bricks):
    """Stored pixels are decoded with the exemplar's width."""
    from warptex.candidates import precompute

    wide = precompute(granite_32x48, cache=False)
    syn = synthesizer(wide, seed=1)
    voxels = np.random.default_rng(0).integers(-20, 20, (50, 3))
    store = BrickStore(syn, whole_bricks=whole_bricks)
    np.testing.assert_array_equal(sample(store, voxels + 0.5), syn.voxels(voxels))


def home(keys: np.ndarray, mask: int) -> np.ndarray:
    """``kernels.lookup.home`` in NumPy: the first probe of each key."""
    h = keys.astype(np.uint64)
    with np.errstate(over="ignore"):
        h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    h ^= h >> np.uint64(31)
    return (h.view(np.int64) & mask).astype(np.int64)


def check_table(store: BrickStore, keys: np.ndarray, slots: np.ndarray) -> None:
    """The hash table holds exactly ``keys``, each once with its slot and reachable by
    linear probing: no free entry between a key's first probe and where it lies."""
    table = store._index.keys.numpy()
    where = np.flatnonzero(table != -1)
    assert sorted(table[where]) == sorted(keys)
    at = {int(k): int(i) for i, k in zip(where, table[where], strict=True)}
    entry = np.array([at[int(k)] for k in keys])
    np.testing.assert_array_equal(store._index.slots.numpy()[entry], slots)
    free = table == -1
    for first, lies in zip(home(np.asarray(keys), len(table) - 1), entry, strict=True):
        between = np.arange(first, lies if lies >= first else lies + len(table)) % len(table)
        assert not free[between].any()


@pytest.mark.parametrize("filter", ["nearest", "trilinear"])
def test_least_recently_used_brick_is_evicted(candidates, filter):
    """Hits of either lookup count as uses (at a brick's centre both read that brick only)."""
    store = BrickStore(synthesizer(candidates), cache_bytes=2 * BRICK_BYTES)
    a, b, c = brick_center((0, 0, 0)), brick_center((1, 0, 0)), brick_center((0, 1, 0))
    for p in (a, b, a, c):  # b is now the least recently used
        sample(store, [p], filter)
    assert store.stats()["misses"] == 3
    sample(store, [a], filter)
    sample(store, [c], filter)
    assert store.stats()["misses"] == 3
    sample(store, [b], filter)
    s = store.stats()
    assert s["misses"] == 4 and s["bricks"] == 2 and s["bricks_evicted"] == 2
    live = np.flatnonzero(store._keys != -1)
    check_table(store, store._keys[live], live)


def test_bricks_kept_through_slot_renumbering_read_their_own_voxels(candidates):
    """A batch of many bricks evicted down to a few renumbers the slots that remain (the
    table shrinks); each kept brick still reads its own voxels, without a miss."""
    syn = synthesizer(candidates)
    store = BrickStore(syn, cache_bytes=10 * BRICK_BYTES)
    store.prefetch(np.array([[8 * i, 0, 0] for i in range(300)]))
    assert store.stats()["bricks"] == 10 and len(store._keys) < 300
    kept = np.array([[8 * i + 3, 2, 5] for i in range(290, 300)])
    np.testing.assert_array_equal(sample(store, kept + 0.5), syn.voxels(kept))
    assert store.stats()["misses"] == 0


@pytest.mark.parametrize("whole_bricks", [True, False])
def test_exemplars_over_65536_pixels_store_int32_triples_that_decode_alike(
        candidates, tmp_path: Path, monkeypatch, whole_bricks):
    """The wide voxel format (exemplars over 65536 pixels, whose pixel indices do not fit
    16 bits) decodes like the engine, also after a save and load; the limit is lowered
    here, as such an exemplar takes half a minute to pre-compute. The color sums that the
    plugin's traced and scalar lookups mirror are those of the compact format."""
    syn = synthesizer(candidates)
    voxels = np.random.default_rng(4).integers(-20, 20, (60, 3))
    compact = BrickStore(syn, whole_bricks=whole_bricks)
    sample(compact, voxels + 0.5)
    monkeypatch.setattr("warptex.store._COMPACT_PIXELS", 0)
    store = BrickStore(syn, whole_bricks=whole_bricks)
    assert store.stats()["bytes_per_voxel"] == 12
    np.testing.assert_array_equal(sample(store, voxels + 0.5), syn.voxels(voxels))
    np.testing.assert_array_equal(store.snapshot().sums, compact.snapshot().sums)
    store.save(tmp_path / "wide.wtb")
    loaded = BrickStore.load(tmp_path / "wide.wtb", syn, whole_bricks=whole_bricks)
    np.testing.assert_array_equal(sample(loaded, voxels + 0.5), syn.voxels(voxels))
    assert loaded.stats()["misses"] == 0


@pytest.mark.parametrize("kernel", ["sample_nearest", "sample_trilinear"])
def test_cpu_lookups_count_misses_by_their_flags(candidates, kernel):
    """Warp's CPU atomics are plain reads and writes, so the shared counter of a launch
    split over threads can lose counts (a quarter of them, in some runs on 2 cores): on the
    CPU the flags are counted instead, whatever the counter holds."""
    import warp as wp

    from kernels import lookup

    store = BrickStore(synthesizer(candidates))
    sample(store, [brick_center((0, 0, 0))])
    points = np.random.default_rng(0).uniform(-40, 40, (100_000, 3))
    missed = wp.zeros(len(points), dtype=wp.int32, device="cpu")
    count = wp.full(1, 12345, dtype=wp.int32, device="cpu")
    misses = store._launch(getattr(lookup, kernel), wp.array(points, dtype=wp.vec3d, device="cpu"),
                           wp.empty((len(points), store.channels), dtype=wp.float32, device="cpu"),
                           missed, count)
    assert misses == missed.numpy().sum() > 0.99 * len(points)


@pytest.mark.parametrize("filter", ["nearest", "trilinear"])
@pytest.mark.parametrize("threads", [2, 3])
def test_lookups_split_over_threads_give_the_colors_of_one_launch(candidates, monkeypatch,
                                                                  filter, threads):
    """A lookup launch of many points is split over CPU threads (as many as the machine
    has cores; set here): every part must read its own points."""
    from warptex import parallel

    points = np.random.default_rng(0).uniform(-20, 20, (3 * parallel.MIN_SPLIT, 3))
    monkeypatch.setattr(parallel, "THREADS", 1)
    store = BrickStore(synthesizer(candidates))
    one = sample(store, points, filter)
    monkeypatch.setattr(parallel, "THREADS", threads)
    assert np.array_equal(sample(store, points, filter), one)  # all hits: one launch
    assert np.array_equal(sample(BrickStore(synthesizer(candidates)), points, filter), one)
    if filter == "nearest":
        voxels = np.floor(points).astype(np.int64)
        assert np.array_equal(one, synthesizer(candidates).voxels(voxels))


@pytest.mark.parametrize("whole_bricks", [True, False])
@pytest.mark.parametrize("filter", ["nearest", "trilinear"])
def test_a_batch_needing_too_many_voxels_is_finished_in_parts(candidates, monkeypatch,
                                                             whole_bricks, filter):
    """Points far apart each bring a whole brick: a batch of 2^20 of them would synthesize
    2^29 voxels at once (a 128 x 128 slice 8 voxels a pixel needed 5.6 GB). Batches are
    finished in halves until each synthesizes at most BATCH_VOXELS, with the same colors."""
    import warptex.store

    points = np.random.default_rng(2).uniform(-400, 400, (300, 3))
    expected = sample(BrickStore(synthesizer(candidates), whole_bricks=whole_bricks), points,
                      filter)
    budget = 8 * 512 if whole_bricks else 256  # a point's trilinear corners fit
    monkeypatch.setattr(warptex.store, "BATCH_VOXELS", budget)
    store = BrickStore(synthesizer(candidates), whole_bricks=whole_bricks)
    made = []
    synthesize = store._synthesize
    monkeypatch.setattr(store, "_synthesize", lambda voxels: (
        made.append(len(voxels)), synthesize(voxels))[1])
    assert np.array_equal(sample(store, points[::-1], filter), expected[::-1])
    assert len(made) > 1 and max(made) <= budget


def test_points_left_unstored_raise_rather_than_read_garbage(candidates, monkeypatch):
    store = BrickStore(synthesizer(candidates))
    monkeypatch.setattr(store, "_to_store", lambda voxels, most=None: voxels[:0])
    with pytest.raises(RuntimeError, match="2 of 2 points still read voxels missing"):
        sample(store, [brick_center((0, 0, 0)), brick_center((3, 0, 0))])


def test_voxels_an_insertion_leaves_unstored_raise_rather_than_synthesize_for_ever(
        candidates, monkeypatch):
    """A store that keeps losing what it inserts (a fault of the store) is reported
    after the first round, never synthesized again and again."""
    store = BrickStore(synthesizer(candidates))
    rounds = []
    synthesize = store._synthesize

    def counted(voxels):
        rounds.append(len(voxels))
        assert len(rounds) <= 2, "the batch synthesizes the same voxels round after round"
        return synthesize(voxels)

    monkeypatch.setattr(store, "_synthesize", counted)
    monkeypatch.setattr(store, "_insert", lambda voxels, payload: None)
    with pytest.raises(RuntimeError, match=r"(\d+) of \1 voxels inserted in the brick store "
                                           "are not stored"):
        sample(store, [brick_center((0, 0, 0))])
    assert len(rounds) == 1


def _cut_short(store: BrickStore, monkeypatch, step: str, after: bool) -> None:
    """Stop the store's next call of ``step`` with an exception raised there (a
    KeyboardInterrupt, which no signal handler defers), before the step or right ``after``
    it."""
    original = getattr(store, step)

    def stopped(*args, **kwargs):
        if after:
            original(*args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(store, step, stopped)


@pytest.mark.parametrize(("step", "after"), [
    ("_index_bricks", True), ("_reserve", True), ("_upload_pool", True),
    ("_upload_slots", False), ("_evict", False)])
def test_a_change_cut_short_drops_the_bricks_rather_than_read_or_save_them_torn(
        candidates, tmp_path: Path, monkeypatch, step, after):
    """An error anywhere in an insertion may leave the bricks half changed (keys entered,
    bits set, voxels not yet placed or uploaded): the store then holds no brick, so every
    later lookup and the file it saves give the engine's colors."""
    syn = synthesizer(candidates)
    store = BrickStore(syn)
    before = np.array([[8 * i + 1, 2, 3] for i in range(4)])
    sample(store, before + 0.5)
    version = store.version
    new = np.array([[8 * i + 1, 2, 3] for i in range(4, 7)])
    with monkeypatch.context() as patch:
        _cut_short(store, patch, step, after)
        with pytest.raises(KeyboardInterrupt):
            sample(store, new + 0.5)
    assert store.stats()["bricks"] == 0 and store.version != version
    both = np.concatenate([before, new])
    np.testing.assert_array_equal(sample(store, both + 0.5), syn.voxels(both))
    store.save(tmp_path / "s.wtb")
    loaded = BrickStore.load(tmp_path / "s.wtb", syn)
    np.testing.assert_array_equal(sample(loaded, both + 0.5), syn.voxels(both))
    assert loaded.stats()["misses"] == 0


@pytest.mark.parametrize("step", ["_insert", "_upload_slots", "_evict"])
def test_ctrl_c_during_a_change_keeps_its_voxels_and_they_are_saved(
        candidates, tmp_path: Path, monkeypatch, step):
    """A Ctrl-C that comes while the bricks change waits for the change to end: the voxels
    synthesized before it stay stored and saved_when_stopped saves them (before, the store
    dropped every brick and then said it held the voxels synthesized before stopping)."""
    import signal

    from warptex.store_files import saved_when_stopped

    syn = synthesizer(candidates)
    store = BrickStore(syn)
    before = np.array([[8 * i + 1, 2, 3] for i in range(4)])
    sample(store, before + 0.5)
    new = np.array([[8 * i + 1, 2, 3] for i in range(4, 7)])
    original = getattr(store, step)

    def signalled(*args, **kwargs):
        signal.raise_signal(signal.SIGINT)  # as a user's Ctrl-C would, mid-change
        return original(*args, **kwargs)

    path = tmp_path / "s.wtb"

    def save():
        store.save(path)
        return [path]

    with monkeypatch.context() as patch:
        patch.setattr(store, step, signalled)
        with pytest.raises(KeyboardInterrupt), saved_when_stopped(save):
            sample(store, new + 0.5)
    assert store.stats()["bricks"] == len(before) + len(new)
    loaded = BrickStore.load(path, syn)
    both = np.concatenate([before, new])
    np.testing.assert_array_equal(sample(loaded, both + 0.5), syn.voxels(both))
    assert loaded.stats()["misses"] == 0


def test_a_store_whose_emptying_was_cut_short_too_is_emptied_when_next_used(
        candidates, tmp_path: Path, monkeypatch):
    """A second error during the emptying that follows a change cut short leaves the store
    torn; its next lookup or save empties it first."""
    syn = synthesizer(candidates)
    voxels = np.array([[8 * i + 5, 0, 7] for i in range(3)])
    for use in ("sample", "save"):
        store = BrickStore(syn)
        sample(store, voxels[:1] + 0.5)
        with monkeypatch.context() as patch:
            _cut_short(store, patch, "_upload_slots", after=False)
            _cut_short(store, patch, "_empty", after=False)
            with pytest.raises(KeyboardInterrupt):
                sample(store, voxels + 0.5)
        if use == "save":
            store.save(tmp_path / "s.wtb")
            store = BrickStore.load(tmp_path / "s.wtb", syn)
            assert store.stats()["bricks"] == 0
        np.testing.assert_array_equal(sample(store, voxels + 0.5), syn.voxels(voxels))


def test_a_mutation_stopped_while_waiting_does_not_hold_back_lookups(monkeypatch):
    """Ctrl-C while a change waits for lookups to end: later lookups and changes go on
    (before, the waiting change went on counting and held back every lookup for ever)."""
    from warptex.store import _SharedLock

    def stopped(predicate):
        raise KeyboardInterrupt

    lock = _SharedLock()
    with lock.shared():
        with monkeypatch.context() as patch:
            patch.setattr(lock._cond, "wait_for", stopped)
            with pytest.raises(KeyboardInterrupt), lock.exclusive():
                pass
        assert lock._waiting == 0  # else the next shared() would wait for ever
    with lock.shared(), lock.shared():
        pass
    # A change that got the lock wakes the waiting lookups once, as it ends, not as it starts
    # too (they would only find it writing and wait again).
    notify_all = lock._cond.notify_all
    woken = []
    monkeypatch.setattr(lock._cond, "notify_all", lambda: woken.append(1) or notify_all())
    with lock.exclusive():
        assert woken == []
    assert woken == [1]


def test_a_waiting_mutation_holds_back_new_lookups_and_a_stopped_one_no_writer(monkeypatch):
    """A change waiting for a lookup keeps later lookups out until it has run (a steady
    stream of queries would starve it); a change stopped while another holds the lock
    leaves that one writing."""
    import threading

    from warptex.store import _SharedLock

    lock, order = _SharedLock(), []

    def change() -> None:
        with lock.exclusive():
            order.append("change")

    def lookup() -> None:
        with lock.shared():
            order.append("lookup")

    with lock.shared():
        writer = threading.Thread(target=change)
        writer.start()
        for _ in range(10**6):  # until the change waits (bounded: a regression fails)
            with lock._cond:
                if lock._waiting:
                    break
        else:
            pytest.fail("the change never waited")
        reader = threading.Thread(target=lookup)
        reader.start()
        reader.join(0.2)
        assert reader.is_alive() and order == []  # held back behind the waiting change
    writer.join()
    reader.join()
    assert order == ["change", "lookup"]

    def stopped(predicate):
        raise KeyboardInterrupt

    with lock.exclusive():
        with monkeypatch.context() as patch:
            patch.setattr(lock._cond, "wait_for", stopped)
            with pytest.raises(KeyboardInterrupt), lock.exclusive():
                pass
        assert lock._writing  # still this block's, not cleared by the stopped one
    assert not lock._writing


def test_a_lookup_finding_the_store_torn_as_it_reads_asks_again(candidates):
    """Another thread's change cut short between this lookup's check and its lock: the
    lookup reads no half-changed bricks, it says to query again."""
    from contextlib import contextmanager

    store = BrickStore(synthesizer(candidates))
    sample(store, [brick_center((0, 0, 0))])
    shared = store._lock.shared

    @contextmanager
    def torn_meanwhile():
        with shared():
            store._torn = True
            yield

    store._lock.shared = torn_meanwhile
    with pytest.raises(RuntimeError, match="a change of its bricks was cut short; query again"):
        store.snapshot()


@pytest.mark.parametrize("mode", ["shared", "exclusive"])
def test_a_stop_as_the_lock_is_taken_leaves_no_reader_or_writer_counted(mode):
    """Ctrl-C as the lock's condition is released, before the block (a signal comes
    between any two steps): the lookup or change went on counting, and every later change
    or lookup waited for it for ever."""
    import threading

    from warptex.store import _SharedLock

    class StoppedOnRelease(threading.Condition):
        armed = False

        def __exit__(self, *exc):
            super().__exit__(*exc)
            if self.armed:
                self.armed = False
                raise KeyboardInterrupt

    lock = _SharedLock()
    lock._cond = StoppedOnRelease()
    lock._cond.armed = True
    with pytest.raises(KeyboardInterrupt), getattr(lock, mode)():
        pytest.fail("the block ran")
    assert (lock._readers, lock._writing, lock._waiting) == (0, False, 0)
    with lock.exclusive():
        pass
    with lock.shared():
        pass


def test_stores_are_saved_when_a_block_is_stopped(tmp_path: Path, capsys):
    """saved_when_stopped: Ctrl-C or SIGTERM in the block saves, says where, and stops as
    asked; a save that fails says why and stops all the same; no stop, no save."""
    from warptex.store_files import saved_when_stopped

    saves = []
    with saved_when_stopped(lambda: saves.append(1) or [tmp_path / "a.wtb"]):
        pass
    assert saves == []
    with pytest.raises(KeyboardInterrupt), saved_when_stopped(lambda: [tmp_path / "a.wtb"]):
        raise KeyboardInterrupt
    assert (f"brick store {tmp_path / 'a.wtb'} holds the voxels synthesized before stopping"
            in capsys.readouterr().err)

    def full_disk():
        raise OSError(28, "No space left on device", str(tmp_path / "a.wtb"))

    with pytest.raises(KeyboardInterrupt), saved_when_stopped(full_disk):
        raise KeyboardInterrupt
    assert (f"brick store not saved: {tmp_path / 'a.wtb'}: cannot write (No space left on "
            "device)") in capsys.readouterr().err
    # A texture's own save returns its one path; one without a store raises ValueError,
    # which the interrupt, not the save's error, goes on after.
    with pytest.raises(KeyboardInterrupt), saved_when_stopped(lambda: tmp_path / "b.wtb"):
        raise KeyboardInterrupt
    assert f"brick store {tmp_path / 'b.wtb'} holds the voxels" in capsys.readouterr().err

    def no_store():
        raise ValueError("no store path: give one")

    with pytest.raises(KeyboardInterrupt), saved_when_stopped(no_store):
        raise KeyboardInterrupt
    assert "warptex: brick store not saved: no store path: give one" in capsys.readouterr().err
    # A path as a string is one path, not one per character; another error is named.
    with pytest.raises(KeyboardInterrupt), saved_when_stopped(lambda: str(tmp_path / "c")):
        raise KeyboardInterrupt
    assert capsys.readouterr().err.count("holds the voxels") == 1
    with pytest.raises(KeyboardInterrupt), saved_when_stopped(lambda: None.save()):
        raise KeyboardInterrupt
    assert ("warptex: brick store not saved: AttributeError: 'NoneType' object has no "
            "attribute 'save'") in capsys.readouterr().err


def test_the_pool_grows_up_to_its_limit_and_refuses_only_what_exceeds_it(candidates,
                                                                         monkeypatch):
    """The pool doubles as it grows, but up to the limit of its int32 indices: voxels that
    fit under it are stored (before, a doubling past the limit was refused though they fit).
    A store keeps what the limit leaves room for, whatever its cache_bytes, evicting as any
    store does (a full one refused every miss after); a batch that does not fit is refused
    with the voxels it needs."""
    import warptex.store as store_module

    monkeypatch.setattr(store_module, "_MAX_POOL_VOXELS", 6000)
    monkeypatch.setattr(store_module, "BATCH_VOXELS", 512)  # room kept: 4976 voxels
    syn = synthesizer(candidates)
    with pytest.warns(UserWarning, match=r"cache_bytes 268435456 is more than a brick store's "
                                         r"pool can index: the store keeps at most 29856 bytes"):
        store = BrickStore(syn)  # whole bricks of 512 voxels, a first pool of 4096
    bricks = np.array([brick_center((i, 0, 0)) for i in range(40)])
    for batch in (bricks[:8], bricks[8:9], *bricks[9:, None]):
        np.testing.assert_array_equal(sample(store, batch),
                                      syn.voxels(np.floor(batch).astype(int)))
        if len(store._payload) > 4096:
            assert len(store._payload) == 6000  # not 8192
    assert store.stats()["bricks"] == 9 and store.stats()["bricks_evicted"] == 31
    with pytest.raises(MemoryError, match="brick store pool of 11264 voxels exceeds"):  # 9 + 13
        store.prefetch(np.floor(bricks[:13]).astype(int))


def test_a_store_keeps_a_brick_from_its_brick_bytes_on(candidates):
    """brick_bytes, what the plugin warns a smaller cache_bytes against, is what one whole
    brick takes of the budget."""
    syn = synthesizer(candidates)
    point = np.array([brick_center((0, 0, 0))])
    for budget, bricks in ((BRICK_BYTES - 1, 0), (BRICK_BYTES, 1)):
        store = BrickStore(syn, cache_bytes=budget)
        assert store.brick_bytes == BRICK_BYTES
        sample(store, point)
        assert store.stats()["bricks"] == bricks


def test_zero_cache_still_answers(candidates):
    syn = synthesizer(candidates)
    store = BrickStore(syn, cache_bytes=0)
    pts = np.array([brick_center((0, 0, 0)), brick_center((-1, 0, 2))])
    np.testing.assert_array_equal(sample(store, pts), syn.voxels(np.floor(pts).astype(int)))
    assert store.stats()["bricks"] == 0


def test_sample_refuses_an_out_it_could_not_write_into(candidates):
    """``sample`` writes colors into ``out``: one of another dtype, shape or layout, which
    Warp would quietly copy and the colors be lost with the copy, is refused."""
    store = BrickStore(synthesizer(candidates))
    pts = np.array([[0.5, 0.5, 0.5], [9.5, 1.5, 2.5]])
    for out in (np.empty((2, 3), np.float64), np.empty((3, 2), np.float32).T,
                np.empty((2, 4), np.float32), [[0.0] * 3] * 2):
        with pytest.raises(ValueError, match=r"out must be a C-contiguous float32 array of "
                                             r"shape \(2, 3\)"):
            store.sample(pts, "nearest", out)
    np.testing.assert_array_equal(sample(store, pts), store.synthesizer.voxels(
        np.floor(pts).astype(int)))


def test_voxels_another_thread_evicted_mid_batch_are_made_again_and_each_stored_once(
        candidates, monkeypatch):
    """Voxels stored when a batch began but evicted while it synthesized the absent ones are
    made in a second round; that round puts back only what is no longer stored, so the
    first round's voxels are not repacked again (pool space left behind)."""
    store = BrickStore(synthesizer(candidates), whole_bricks=False)
    stored_first = np.array([[1, 2, 3], [9, 9, 9], [-4, 0, 17]])
    absent = np.array([[30, 1, 2], [-20, 5, 5]])
    store.prefetch(stored_first)
    synthesize, insert = store._synthesize, store._insert
    made, inserted = [], []

    def evicted_meanwhile(voxels):
        triples = synthesize(voxels)
        if not made:  # as another thread's eviction would, while this batch synthesizes
            with store._changing():
                store._empty()
        made.append(len(voxels))
        return triples

    def counted(voxels, payload):
        inserted.append(len(voxels))
        insert(voxels, payload)

    monkeypatch.setattr(store, "_synthesize", evicted_meanwhile)
    monkeypatch.setattr(store, "_insert", counted)
    both = np.concatenate([stored_first, absent])
    store.prefetch(both)
    assert made == [len(absent), len(stored_first)]
    assert [n for n in inserted if n] == [len(absent), len(stored_first)]
    assert store._stored(both).all()
    np.testing.assert_array_equal(sample(store, both + 0.5), store.synthesizer.voxels(both))


def test_a_save_deletes_the_temporary_files_of_saves_killed_long_ago(candidates, tmp_path):
    """A killed save leaves its half-written temporary file, as large as the store; the
    next save to that file deletes those older than UNFINISHED_AGE, not a young one (a
    writer's on a folder that cannot be locked) nor another file's."""
    path = tmp_path / "s.wtb"
    old = time.time() - 2 * UNFINISHED_AGE
    dead, young = (tmp_path / _temporary_name(path, tag)
                   for tag in (f"12.{'0a' * _TOKEN_BYTES}", f"7.{'b9' * _TOKEN_BYTES}"))
    other = tmp_path / _temporary_name(tmp_path / "t.wtb", f"12.{'0a' * _TOKEN_BYTES}")
    for leftover in (dead, young, other):
        leftover.write_bytes(b"part")
        if leftover is not young:
            os.utime(leftover, (old, old))
    store = BrickStore(synthesizer(candidates))
    sample(store, [brick_center((0, 0, 0))])
    assert store.save(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [path.name, young.name, other.name])


def test_save_load_keeps_the_most_recent_bricks_that_fit(candidates, tmp_path: Path):
    syn = synthesizer(candidates)
    store = BrickStore(syn)
    centers = [brick_center((i, 0, 0)) for i in range(3)]
    for p in centers:
        sample(store, [p])
    path = tmp_path / "s.wtb"
    store.save(path)
    assert not list(tmp_path.glob(".*.tmp*"))
    small = BrickStore.load(path, syn, cache_bytes=2 * BRICK_BYTES)
    assert small.stats()["bricks"] == 2
    np.testing.assert_array_equal(sample(small, centers[1:]), sample(store, centers[1:]))
    assert small.stats()["misses"] == 0
    full = BrickStore.load(path, syn)
    assert full.stats()["bricks"] == 3
    voxels = np.floor(centers).astype(int)
    np.testing.assert_array_equal(sample(full, centers), syn.voxels(voxels))
    assert full.stats()["misses"] == 0  # read from the file, not synthesized again


@pytest.mark.parametrize("filter, voxels", [("nearest", 1), ("trilinear", 8)])
def test_only_the_voxels_read_are_synthesized_and_stored(candidates, tmp_path: Path,
                                                         filter, voxels):
    """Bricks fill voxel by voxel: a query stores what its filter reads, no more, and a
    voxel missing from a partly filled brick (also after a reload) is synthesized."""
    syn = synthesizer(candidates)
    store = BrickStore(syn, whole_bricks=False)
    p = np.array([[3.25, 2.75, 5.5]])
    first = sample(store, p, filter)
    s = store.stats()
    assert (s["bricks"], s["voxels"], s["voxels_added"], s["misses"]) == (1, voxels, voxels, 1)
    assert sample(store, p, filter).tobytes() == first.tobytes()
    assert store.stats()["misses"] == 1
    path = tmp_path / "partial.wtb"
    store.save(path)
    loaded = BrickStore.load(path, syn, whole_bricks=False)
    assert loaded.stats()["voxels"] == voxels
    np.testing.assert_array_equal(sample(loaded, p, filter), first)
    other = np.array([[6.5, 0.5, 1.5]])  # same brick, not stored
    np.testing.assert_array_equal(sample(loaded, other, "nearest"),
                                  syn.voxels(np.array([[6, 0, 1]])))
    assert loaded.stats()["voxels"] == voxels + 1 and loaded.stats()["bricks"] == 1
    # A store filling whole bricks (a renderer's) reads the partly filled brick too, and a
    # miss in it fills the rest of the brick.
    whole = BrickStore.load(path, syn)
    assert whole.stats()["voxels"] == voxels
    np.testing.assert_array_equal(sample(whole, p, filter), first)
    assert whole.stats()["misses"] == 0
    np.testing.assert_array_equal(sample(whole, other, "nearest"),
                                  syn.voxels(np.array([[6, 0, 1]])))
    assert whole.stats()["voxels"] == 512 and whole.stats()["voxels_added"] == 512 - voxels
    np.testing.assert_array_equal(sample(whole, p, filter), first)


def test_a_partly_filled_brick_beside_whole_ones_reads_only_its_own_voxels(candidates):
    """One whole brick and one lacking a single voxel, so that every word of its stored
    bits holds some: the lookups must read the bits wherever any brick is partly filled,
    not only where all are, nor only where a word is empty."""
    syn = synthesizer(candidates)
    store = BrickStore(syn, whole_bricks=False)
    gap = np.array([[12, 5, 3]])
    bricks = brick_voxels(brick_keys(np.array([[0, 0, 0], [8, 0, 0]])))
    store.prefetch(bricks[(bricks != gap).any(axis=1)])
    # In the whole brick, in the other after the gap, and the gap.
    voxels = np.array([[3, 6, 1], [15, 7, 7], *gap])
    np.testing.assert_array_equal(sample(store, voxels + 0.5), syn.voxels(voxels))
    s = store.stats()
    assert (s["misses"], s["voxels"]) == (1, 2 * 512)


def test_identity_covers_seed_jitter_and_engine_parameters(candidates, tmp_path: Path,
                                                          monkeypatch):
    ids = {BrickStore(synthesizer(candidates, **kw)).identity() for kw in
           ({}, {"seed": 1}, {"jitter": 0.5}, {"passes": 1}, {"levels": 1}, {"subpasses": 8},
            {"shifted_tiles": True})}
    assert len(ids) == 7
    # Candidates made with other parameters make another texture from the same exemplars.
    other_params = dataclasses.replace(candidates, params={**candidates.params, "keep": 7})
    assert BrickStore(synthesizer(other_params)).identity() not in ids
    with monkeypatch.context() as m:
        m.setattr("warptex.store_files.ENGINE_VERSION", -1)
        assert BrickStore(synthesizer(candidates)).identity() not in ids
    store = BrickStore(synthesizer(candidates))
    sample(store, [brick_center((0, 0, 0))])
    path = tmp_path / "s.wtb"
    store.save(path)
    with pytest.warns(UserWarning, match=r"another texture \(jitter 1.0 in the file, 0.5 here\)"):
        assert BrickStore.load(path, synthesizer(candidates, jitter=0.5)).stats()["bricks"] == 0
    both = r"\(correction passes 2 in the file, 3 here, seed 0 in the file, 4 here\)"
    with pytest.warns(UserWarning, match=both):
        BrickStore.load(path, synthesizer(candidates, passes=3, seed=4))
    with pytest.warns(UserWarning, match=r"another texture \(shifted tiles False in the file, "
                                         r"True here\)"):
        BrickStore.load(path, synthesizer(candidates, shifted_tiles=True))
    # Files written before tile shifts were kept, and as a later warptex might write one,
    # with a setting this one does not know.
    kept = store_settings
    for name, written_with, said in (
            ("older", lambda s: {k: v for k, v in kept(s).items() if k != "shifted_tiles"},
             r"shifted tiles \(not recorded in the file\)"),
            ("newer", lambda s: {**kept(s), "grain": 3}, r"grain \(in the file, not kept here\)")):
        with monkeypatch.context() as m:
            m.setattr("warptex.store.store_settings", written_with)
            other_store = BrickStore(synthesizer(candidates))
            sample(other_store, [brick_center((0, 0, 0))])
            other_store.save(tmp_path / f"{name}.wtb")
        with pytest.warns(UserWarning, match=rf"another texture \({said}\)"):
            BrickStore.load(tmp_path / f"{name}.wtb", synthesizer(candidates))
    with pytest.warns(UserWarning, match=r"another texture \(sub-passes 1 in the file, 8 here\)"):
        assert BrickStore.load(path, synthesizer(candidates, subpasses=8)).stats()["bricks"] == 0
    with pytest.warns(UserWarning, match=r"another texture \(candidate parameters\)"):
        BrickStore.load(path, synthesizer(other_params))
    with monkeypatch.context() as m:
        m.setattr("warptex.store_files.ENGINE_VERSION", -1)
        with pytest.warns(UserWarning, match=r"\(engine version \d+ in the file, -1 here\)"):
            BrickStore.load(path, synthesizer(candidates))
    with monkeypatch.context() as m:
        m.setattr(candidates, "digests", tuple("other" for _ in candidates.digests))
        with pytest.warns(UserWarning, match=r"another texture \(exemplars\)"):
            BrickStore.load(path, synthesizer(candidates))
    # Candidates recomputed under the same exemplars and parameters, one PCA coefficient
    # rounded otherwise (another LAPACK): every voxel may differ, so the file is refused.
    rounded = dataclasses.replace(candidates, sources=[
        [dataclasses.replace(s, basis=s.basis.copy()) for s in level]
        for level in candidates.sources])
    rounded.sources[-1][0].basis[0, 0] += 1
    with pytest.warns(UserWarning, match=r"another texture \(pre-computed candidates\)"):
        assert BrickStore.load(path, synthesizer(rounded)).stats()["bricks"] == 0
    data = bytearray(path.read_bytes())
    data[8] += 1  # format version
    path.write_bytes(bytes(data))
    with pytest.warns(UserWarning, match=r"brick store file version \d+, expected \d+"):
        assert BrickStore.load(path, synthesizer(candidates)).stats()["bricks"] == 0
    path.write_bytes(path.read_bytes()[:60])
    with pytest.warns(UserWarning, match="ignoring brick store file"):
        BrickStore.load(path, synthesizer(candidates))
    with pytest.warns(UserWarning, match="cannot read"):
        BrickStore.load(tmp_path / "missing.wtb", synthesizer(candidates))


def test_a_file_of_another_kind_is_refused_and_kept(candidates, tmp_path: Path):
    notes = tmp_path / "notes.txt"
    notes.write_text("not bricks")
    for path, words in ((notes, "not a warptex brick store file"),
                        (tmp_path, "is a folder, expected a brick store file")):
        with pytest.raises(StoreFileError, match=words):
            BrickStore.load(path, synthesizer(candidates))
        with pytest.raises(StoreFileError, match=words):
            BrickStore(synthesizer(candidates)).save(path)
    assert notes.read_text() == "not bricks"
    empty = tmp_path / "made_by_mktemp"
    empty.touch()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a place to save to, nothing replaced or ignored
        assert BrickStore.load(empty, synthesizer(candidates)).stats()["bricks"] == 0
        BrickStore(synthesizer(candidates)).save(empty)
    assert empty.stat().st_size > 0


def test_mark_used_refuses_slots_the_snapshot_does_not_have(candidates):
    """A negative slot, which NumPy wraps, stamped another brick as just used."""
    store = BrickStore(synthesizer(candidates))
    sample(store, [brick_center((0, 0, 0))])
    snap = store.snapshot()
    for slots in ([-1], [len(snap.keys)]):
        with pytest.raises(IndexError, match=r"slots must be those of the snapshot, 0 to "):
            store.mark_used(np.array(slots), store.version)
    store.mark_used(np.flatnonzero(snap.keys >= 0), store.version)


def test_an_eviction_alone_makes_snapshots_stale_and_their_marks_are_ignored(candidates):
    """A store made smaller, then asked for what it holds, evicts without inserting: its
    version changes all the same (readers of a snapshot look again), and a stale snapshot's
    marks of use stamp nothing, though its slots still hold bricks."""
    store = BrickStore(synthesizer(candidates))
    bricks = [(0, 0, 0), (1, 0, 0), (2, 0, 0)]
    for b in bricks:
        sample(store, [brick_center(b)])
    snap, version = store.snapshot(), store.version
    evicted = store.stats()["bricks_evicted"]
    store.cache_bytes = 2 * BRICK_BYTES
    store.prefetch(np.array([[16, 0, 0]]))  # brick (2, 0, 0), stored: nothing inserted
    assert store.stats()["bricks_evicted"] == evicted + 1 and store.version != version
    # The oldest left, brick (1, 0, 0), marked through the stale snapshot: ignored, so it
    # is the one the next brick evicts.
    store.mark_used(np.flatnonzero(snap.keys == brick_keys(np.array([[8, 0, 0]]))[0]), version)
    store.prefetch(np.array([[24, 0, 0]]))
    now = store.snapshot()
    assert set(now.keys[now.keys >= 0]) == set(brick_keys(np.array([[16, 0, 0], [24, 0, 0]])))


def test_bricks_read_through_brick_sums_count_as_used(candidates):
    """The scalar plugin's copies read bricks through brick_sums: those count for
    least-recently-used eviction like a lookup's."""
    store = BrickStore(synthesizer(candidates))
    for b in [(0, 0, 0), (1, 0, 0), (2, 0, 0)]:
        sample(store, [brick_center(b)])
    store.brick_sums(brick_keys(np.array([[0, 0, 0]])))  # the oldest becomes the newest
    store.cache_bytes = 2 * BRICK_BYTES
    store.prefetch(np.array([[0, 40, 0]]))
    snap = store.snapshot()
    assert set(snap.keys[snap.keys >= 0]) == set(brick_keys(np.array([[0, 0, 0], [0, 40, 0]])))


def test_a_loaded_store_evicts_in_the_saved_recency_order(candidates, tmp_path: Path):
    syn = synthesizer(candidates)
    store = BrickStore(syn)
    recent_last = [(2, 0, 0), (0, 0, 0), (1, 0, 0)]  # key order differs from recency
    for b in recent_last:
        sample(store, [brick_center(b)])
    path = tmp_path / "s.wtb"
    store.save(path)
    loaded = BrickStore.load(path, syn)
    loaded.cache_bytes = 2 * BRICK_BYTES
    loaded.prefetch(np.array([[0, 40, 0]]))  # a fourth brick: the two oldest go
    snap = loaded.snapshot()
    kept = set(snap.keys[snap.keys >= 0])
    assert kept == set(brick_keys(np.array([[8, 0, 0], [0, 40, 0]])))


def test_partly_filled_bricks_cost_only_their_voxels(candidates, tmp_path: Path):
    """Voxels arriving in many small batches, in random order, across a few bricks: each
    batch repacks its bricks, evictions compact the pool, and every stored voxel keeps
    reading exactly the engine's color, also after a save and load."""
    syn = synthesizer(candidates)
    store = BrickStore(syn, whole_bricks=False)
    rng = np.random.default_rng(5)
    voxels = unique_voxels(rng.integers(-6, 14, (900, 3)))
    voxels = voxels[rng.permutation(len(voxels))]
    expected = syn.voxels(voxels)
    for batch in np.array_split(np.arange(len(voxels)), 12):
        store.prefetch(voxels[batch])
    s = store.stats()
    assert s["voxels"] == len(voxels) == s["voxels_added"]
    assert s["payload_bytes"] == len(voxels) * 6 + s["bricks"] * (16 * 4 + 4)
    assert s["payload_bytes"] < 0.5 * s["bricks"] * BRICK_BYTES  # bricks are far from full
    np.testing.assert_array_equal(sample(store, voxels + 0.5), expected)
    assert store.stats()["misses"] == 0
    snap = store.snapshot()
    assert np.isfinite(snap.sums[:, 0]).sum() == len(voxels)
    # Bricks asked for by key, in any order, absent ones all NaN: the snapshot's rows.
    live = np.flatnonzero(snap.keys >= 0)[::-1]
    absent = brick_keys(np.array([[400, 0, 0]]))
    asked = store.brick_sums(np.concatenate([snap.keys[live], absent])).reshape(
        len(live) + 1, BRICK_VOXELS, -1)
    np.testing.assert_array_equal(asked[:-1],
                                  snap.sums.reshape(-1, BRICK_VOXELS, asked.shape[2])[live])
    assert np.isnan(asked[-1]).all()

    path = tmp_path / "packed.wtb"
    store.save(path)
    assert path.stat().st_size < s["payload_bytes"] + 64 * 1024
    loaded = BrickStore.load(path, syn, whole_bricks=False)
    np.testing.assert_array_equal(sample(loaded, voxels + 0.5), expected)
    assert loaded.stats()["misses"] == 0

    # A budget of about half: the least recently used bricks go, the pool is compacted,
    # and what stays (or comes back) still reads the engine's colors.
    loaded.cache_bytes = s["payload_bytes"] // 2
    loaded.prefetch(voxels[:1])
    kept = loaded.stats()
    assert 0 < kept["payload_bytes"] <= loaded.cache_bytes and kept["bricks_evicted"] > 0
    np.testing.assert_array_equal(sample(loaded, voxels[::-1] + 0.5), expected[::-1])


def test_saves_to_one_file_merge_rather_than_replace(candidates, tmp_path: Path):
    """Two stores of one texture (two renders of other objects) save to one file: it keeps
    the voxels of both, a brick both filled in part holding the voxels of either, and the
    later save's bricks count as the more recent. A file of another texture is replaced."""
    syn = synthesizer(candidates)
    path = tmp_path / "shared.wtb"
    first, second = BrickStore(syn, whole_bricks=False), BrickStore(syn, whole_bricks=False)
    first.prefetch(np.array([[0, 0, 0], [1, 2, 3], [20, 0, 0]]))
    second.prefetch(np.array([[1, 2, 3], [4, 4, 4], [-9, 0, 0]]))
    first.save(path)
    second.save(path)
    voxels = np.array([[0, 0, 0], [1, 2, 3], [20, 0, 0], [4, 4, 4], [-9, 0, 0]])
    loaded = BrickStore.load(path, syn, whole_bricks=False)
    assert (loaded.stats()["voxels"], loaded.stats()["bricks"]) == (5, 3)
    np.testing.assert_array_equal(sample(loaded, voxels + 0.5), syn.voxels(voxels))
    assert loaded.stats()["misses"] == 0
    # The brick at the origin, in both, and the one at -9, the second's alone, are the most
    # recent: a store of two bricks' room keeps them.
    two = 2 * SLOT_BYTES + 4 * 6  # their four voxels
    small = BrickStore.load(path, syn, whole_bricks=False, cache_bytes=two)
    snap = small.snapshot()
    assert set(snap.keys[snap.keys >= 0]) == set(brick_keys(voxels[[0, 4]]))
    # Their own voxels, read from the file past the partial brick left out of the room.
    kept = voxels[[0, 1, 3, 4]]
    np.testing.assert_array_equal(sample(small, kept + 0.5), syn.voxels(kept))
    assert small.stats()["misses"] == 0
    # Saving again changes nothing; a store of another seed replaces the file.
    second.save(path)
    assert BrickStore.load(path, syn).stats()["voxels"] == 5
    other = BrickStore(synthesizer(candidates, seed=3), whole_bricks=False)
    other.prefetch(np.array([[0, 0, 0]]))
    with pytest.warns(UserWarning, match=r"replacing brick store file: .*another texture \(seed"):
        other.save(path)
    with pytest.warns(UserWarning, match="another texture"):
        BrickStore.load(path, syn)
    assert BrickStore.load(path, synthesizer(candidates, seed=3)).stats()["voxels"] == 1


def test_a_store_file_that_cannot_be_used_is_reported_once(candidates, tmp_path: Path):
    """Loading reports a damaged or another texture's file, and saving replaces it without
    saying so again (a stale store after an upgrade was reported twice in one render);
    a file that changed since loading is reported anew."""
    import warnings

    path = tmp_path / "s.wtb"
    syn = synthesizer(candidates)
    other = BrickStore(synthesizer(candidates, seed=3), whole_bricks=False)
    other.prefetch(np.array([[0, 0, 0]]))
    other.save(path)
    with pytest.warns(UserWarning, match="ignoring brick store file.*another texture") as said:
        store = BrickStore.load(path, syn, whole_bricks=False)
    assert len(said) == 1
    store.prefetch(np.array([[1, 0, 0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert store.save(path)
    assert BrickStore.load(path, syn).stats()["voxels"] == 1
    with pytest.warns(UserWarning, match="ignoring brick store file"):
        again = BrickStore.load(path, synthesizer(candidates, seed=3), whole_bricks=False)
    path.write_bytes(path.read_bytes()[:100])  # damaged since it was loaded
    again.prefetch(np.array([[2, 0, 0]]))
    with pytest.warns(UserWarning, match="replacing brick store file"):
        again.save(path)


def test_an_empty_store_leaves_another_texture_s_file_as_it_was(candidates, tmp_path: Path,
                                                                 capsys):
    """A render that synthesized nothing for a texture whose file was another's (ignored
    on loading), or one stopped before any synthesis, replaced that file with an empty
    store: the other texture's voxels were lost for none of this one's. A stop's save is
    no longer made without voxels, whatever file is there, and says so (a job's log said
    nothing of its store)."""
    from warptex.store_files import saved_if_any

    path = tmp_path / "s.wtb"
    other = BrickStore(synthesizer(candidates, seed=3), whole_bricks=False)
    other.prefetch(np.array([[0, 0, 0]]))
    other.save(path)
    before = path.read_bytes()
    with pytest.warns(UserWarning, match="ignoring brick store file.*another texture"):
        empty = BrickStore.load(path, synthesizer(candidates), whole_bricks=False)
    assert saved_if_any(empty, path, lambda: empty.save(path) and path) == []
    assert capsys.readouterr().err == (f"warptex: brick store {path} left as it was: no "
                                       "voxel was synthesized yet\n")
    assert not empty.save(path)
    assert path.read_bytes() == before
    empty.prefetch(np.array([[1, 0, 0]]))  # with voxels of its own, it replaces the file
    assert saved_if_any(empty, path, lambda: empty.save(path) and path) == [path]
    assert saved_if_any(empty, None, lambda: pytest.fail("no file to save to")) == []
    assert BrickStore.load(path, synthesizer(candidates)).stats()["voxels"] == 1


def test_a_store_saved_through_a_symbolic_link_merges_into_its_target(candidates,
                                                                    tmp_path: Path):
    """Saving through a link writes the file it points to, in turns with saves to that
    file, rather than replacing the link with a file of its own."""
    syn = synthesizer(candidates)
    target = tmp_path / "stores" / "shared.wtb"
    first, second = BrickStore(syn, whole_bricks=False), BrickStore(syn, whole_bricks=False)
    first.prefetch(np.array([[0, 0, 0]]))
    first.save(target)
    link = tmp_path / "link.wtb"
    link.symlink_to(target)
    second.prefetch(np.array([[40, 0, 0]]))
    second.save(link)
    assert link.is_symlink()
    assert BrickStore.load(target, syn, whole_bricks=False).stats()["voxels"] == 2


def test_prefetch_refuses_voxels_the_engine_refuses(candidates):
    """Before a brick key could wrap them onto other voxels: nothing is stored."""
    from warptex.synthesis import COORD_LIMIT

    store = BrickStore(synthesizer(candidates))
    for voxels, problem in (([[3, 5, 2**24 + 8]], "must lie within"),
                            ([[-COORD_LIMIT - 1, 0, 0]], "must lie within"),
                            ([[-0.5, 0.7, 9.9]], "integer array"),
                            ([[np.nan, 0, 0]], "integer array"),
                            ([1, 2, 3], "integer array")):
        with pytest.raises(ValueError, match=problem):
            store.prefetch(np.array(voxels))
    assert store.stats()["voxels"] == 0
    store.prefetch(np.zeros((0, 3), np.int64))
    assert store.stats()["voxels"] == 0


@pytest.mark.parametrize("filter", ["nearest", "trilinear"])
def test_sample_refuses_points_whose_brick_keys_would_wrap_onto_stored_voxels(candidates,
                                                                             filter):
    """2^24 voxels out along z, a brick key's z field overflows into y: the point would
    read voxel (0, 8, 0), stored, without a miss. NaN and infinite points are refused too,
    and nothing is synthesized for any of them."""
    from warptex.store import POINT_LIMIT

    store = BrickStore(synthesizer(candidates))
    near = sample(store, [[0.5, 8.5, 0.5]], filter)
    stored = store.stats()["voxels"]
    for point in ([0.5, 8.5, 2.0**24 + 0.5], [0.5, 8.5, POINT_LIMIT], [np.nan, 8.5, 0.5],
                  [0.5, -np.inf, 0.5]):
        with pytest.raises(ValueError, match=f"1 of 2 points are NaN, infinite or beyond "
                                             f"\\+-{POINT_LIMIT} voxels"):
            sample(store, [[0.5, 8.5, 0.5], point], filter)
    assert store.stats()["voxels"] == stored
    np.testing.assert_array_equal(sample(store, [[0.5, 8.5, 0.5]], filter), near)


def test_a_store_that_stored_nothing_since_leaves_its_file_as_it_is(candidates,
                                                                      tmp_path: Path):
    """Saving to the file a store was loaded from, or last saved to, rewrites it only when
    the store stored voxels since or another save replaced the file meanwhile."""
    syn = synthesizer(candidates)
    path = tmp_path / "shared.wtb"
    first = BrickStore(syn)
    sample(first, [brick_center((0, 0, 0))])
    assert first.save(path)

    def state() -> tuple:
        st = path.stat()
        return st.st_ino, st.st_mtime_ns, path.read_bytes()

    as_saved = state()
    assert not first.save(path) and state() == as_saved
    reader = BrickStore.load(path, syn)
    sample(reader, [brick_center((0, 0, 0))])  # a hit: nothing synthesized
    assert reader.stats()["voxels_added"] == 0
    assert not reader.save(path) and state() == as_saved
    sample(reader, [brick_center((1, 0, 0))])  # stored since loading: the file is rewritten
    assert reader.save(path) and state() != as_saved
    assert reader.save(tmp_path / "elsewhere.wtb")  # another file is written
    # The first stored nothing since its save, but another save replaced the file: merged.
    assert first.save(path)
    assert BrickStore.load(path, syn).stats()["bricks"] == 2


def test_a_merged_save_keeps_what_fits_the_cache_or_the_file(candidates, tmp_path: Path):
    """A store of little room does not shrink a shared file: the most recent bricks that
    fit the file's size are kept (the oldest goes); a store of more room keeps them all."""
    syn = synthesizer(candidates)
    path = tmp_path / "s.wtb"
    old = BrickStore(syn)
    for b in range(3):
        sample(old, [brick_center((b, 0, 0))])
    old.save(path)
    small = BrickStore(syn, cache_bytes=BRICK_BYTES)
    sample(small, [brick_center((0, 5, 0))])
    small.save(path)
    snap = BrickStore.load(path, syn).snapshot()
    assert set(snap.keys[snap.keys >= 0]) == set(
        brick_keys(np.array([[8, 0, 0], [16, 0, 0], [0, 40, 0]])))
    large = BrickStore(syn)
    sample(large, [brick_center((0, 6, 0))])
    large.save(path)
    assert BrickStore.load(path, syn).stats()["bricks"] == 4


def test_a_merged_save_keeps_every_brick_of_ours_though_merging_grew_them(candidates,
                                                                        tmp_path: Path):
    """Two stores filling halves of the same bricks: merged, each brick holds both halves
    and costs more than either store's room or the file's. Some of the second store's
    bricks were left out, yet the file was marked as holding them all, so its next save
    wrote nothing and a store loaded from it synthesized them again."""
    syn = synthesizer(candidates)
    path = tmp_path / "halves.wtb"
    grid = np.stack(np.meshgrid(np.arange(32), np.arange(8), np.arange(8), indexing="ij"),
                    axis=-1).reshape(-1, 3)
    even, odd = grid[grid[:, 2] % 2 == 0], grid[grid[:, 2] % 2 == 1]
    room = 4 * (SLOT_BYTES + 256 * 6)  # four bricks of 256 voxels: either half, not both
    first = BrickStore(syn, whole_bricks=False, cache_bytes=room)
    first.prefetch(even)
    first.save(path)
    second = BrickStore(syn, whole_bricks=False, cache_bytes=room)
    second.prefetch(odd)
    assert second.save(path)
    assert not second.save(path)  # the file holds every brick of the second's
    loaded = BrickStore.load(path, syn, whole_bricks=False, cache_bytes=1 << 30)
    np.testing.assert_array_equal(sample(loaded, odd + 0.5), syn.voxels(odd))
    assert loaded.stats()["misses"] == 0


def test_a_merge_pairs_each_brick_with_its_own_copy_whatever_the_recency_order(
        candidates, tmp_path: Path):
    """The saving store lists its bricks by recency, not by key: a brick of the file is
    merged with the saving store's copy of that same brick (found through the key order),
    never with the brick that sits at its place in the key order."""
    syn = synthesizer(candidates)
    path = tmp_path / "s.wtb"
    first = BrickStore(syn, whole_bricks=False)
    first.prefetch(np.array([[0, 0, 0], [21, 0, 0]]))
    first.save(path)
    second = BrickStore(syn, whole_bricks=False)
    second.prefetch(np.array([[20, 0, 0]]))  # the later key used first
    second.prefetch(np.array([[1, 2, 3]]))
    second.save(path)
    voxels = np.array([[0, 0, 0], [21, 0, 0], [20, 0, 0], [1, 2, 3]])
    loaded = BrickStore.load(path, syn, whole_bricks=False)
    assert (loaded.stats()["voxels"], loaded.stats()["bricks"]) == (4, 2)
    np.testing.assert_array_equal(sample(loaded, voxels + 0.5), syn.voxels(voxels))
    assert loaded.stats()["misses"] == 0


@pytest.mark.parametrize("gather", [1, 3, 2048])
def test_a_merge_of_random_lists_holds_each_brick_once_with_the_voxels_of_either(
        monkeypatch, gather):
    """Against a brute-force merge: the older list's own bricks first, then the newer's,
    each in its list's order, a brick in both holding the voxels of either in local order;
    gathered and merged a few bricks at a time as one (a merge of partly filled bricks, two
    bakes' stores, held ten times the file at once)."""
    import warptex.bricks as bricks_module
    from kernels.lookup import VALID_WORDS

    monkeypatch.setattr(bricks_module, "_GATHER_BRICKS", gather)
    rng = np.random.default_rng(gather)

    def triple(key: int, local: int) -> list[int]:  # as voxels are: one value per place
        return [key % 97, local, (key * 7 + local) % 1000]

    def bricks(keys: np.ndarray) -> tuple[bricks_module.Bricks, dict[int, set[int]]]:
        held = {int(k): set(np.flatnonzero(rng.random(512) < rng.choice([0.01, 0.3, 1.0])))
                or {0} for k in keys}
        bits = np.zeros((len(keys), 512), bool)
        for n, k in enumerate(keys):
            bits[n, sorted(held[int(k)])] = True
        valid = np.packbits(bits, axis=1, bitorder="little").view(np.uint32)
        triples = [triple(int(k), c) for k in keys for c in sorted(held[int(k)])]
        assert valid.shape == (len(keys), VALID_WORDS)
        return bricks_module.Bricks(keys, np.array(triples, np.uint16).reshape(-1, 3), valid), held

    grown = 0  # bricks whose older copy holds voxels the newer lacks: merged voxel by voxel
    for _ in range(5):
        pool = rng.permutation(40)[:rng.integers(1, 40)].astype(np.int64)
        older, old_held = bricks(rng.permutation(pool)[:rng.integers(0, len(pool) + 1)])
        newer, new_held = bricks(rng.permutation(pool)[:rng.integers(1, len(pool) + 1)])
        merged = bricks_module.bricks_union(older, newer)
        keys = [k for k in older.keys if k not in new_held] + list(newer.keys)
        assert list(merged.keys) == keys
        expected = [triple(int(k), c) for k in keys
                    for c in sorted(old_held.get(int(k), set()) | new_held.get(int(k), set()))]
        np.testing.assert_array_equal(merged.triples, np.array(expected).reshape(-1, 3))
        counts = [len(old_held.get(int(k), set()) | new_held.get(int(k), set())) for k in keys]
        np.testing.assert_array_equal(np.bitwise_count(merged.valid).sum(axis=1), counts)
        grown += sum(bool(old_held[k] - new_held[k]) for k in old_held.keys() & new_held.keys())
        # Only the most recent bricks a budget keeps are gathered (a save of a large union
        # held all of it first): the same as the whole union's tail.
        seen = []
        for count in (0, int(rng.integers(0, len(keys) + 1)), len(keys)):
            tail = bricks_module.bricks_union(older, newer,
                                       lambda valid, n=count, seen=seen: seen.append(valid) or n)
            first, voxels = len(keys) - count, sum(counts[len(keys) - count:])
            np.testing.assert_array_equal(tail.keys, merged.keys[first:])
            np.testing.assert_array_equal(tail.valid, merged.valid[first:])
            np.testing.assert_array_equal(tail.triples,
                                          merged.triples[len(merged.triples) - voxels:])
        for valid in seen:
            np.testing.assert_array_equal(valid, merged.valid)
    assert grown > 0


def test_concurrent_saves_to_one_file_lose_nothing(candidates, tmp_path: Path):
    """Saves take turns on the file's folder, so each merge reads the file the previous
    one wrote (threads here; processes lock the same way)."""
    import threading

    syn = synthesizer(candidates)
    path = tmp_path / "s.wtb"
    stores = []
    for i in range(4):
        store = BrickStore(syn, whole_bricks=False)
        store.prefetch(np.array([[8 * i, 0, 0]]))
        stores.append(store)
    barrier = threading.Barrier(len(stores))

    def save(store: BrickStore) -> None:
        barrier.wait()
        store.save(path)

    threads = [threading.Thread(target=save, args=(s,)) for s in stores]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert BrickStore.load(path, syn).stats()["voxels"] == len(stores)


@pytest.mark.parametrize("refused", ["open", "flock"])
def test_saves_that_cannot_take_turns_say_so_once_a_folder(candidates, tmp_path, monkeypatch,
                                                          refused):
    """A folder that cannot be locked (some network file systems) let concurrent saves
    each keep only their own voxels without a word; said once a folder now, and the save
    still goes on."""
    import errno

    from warptex import store_files

    def no_locks(*args):
        raise OSError(errno.ENOLCK, "No locks available")

    if refused == "open":
        opening = os.open
        monkeypatch.setattr(store_files.os, "open", lambda path, *rest: no_locks()
                            if Path(path) == tmp_path else opening(path, *rest))
    else:
        monkeypatch.setattr(store_files.fcntl, "flock", no_locks)
    monkeypatch.setattr(store_files, "_UNLOCKED", set())
    store = BrickStore(synthesizer(candidates), whole_bricks=False)
    store.prefetch(np.array([[0, 0, 0]]))
    with pytest.warns(UserWarning, match=rf"^{re.escape(str(tmp_path))}: brick stores saved "
                                         r"here do not take turns, as the folder cannot be "
                                         r"locked \(No locks available\)"):
        assert store.save(tmp_path / "a.wtb")
    store.prefetch(np.array([[8, 0, 0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert store.save(tmp_path / "b.wtb")
    assert BrickStore.load(tmp_path / "b.wtb", store.synthesizer).stats()["voxels"] == 2


def test_identity_follows_the_engine_code_and_the_jitter_the_engine_takes(candidates, tmp_path,
                                                                         monkeypatch):
    """Stores of another engine's code are never reused, even at the same ENGINE_VERSION;
    jitters that the engine rounds alike (to 1/256) share stores."""
    same = {BrickStore(synthesizer(candidates, jitter=j)).identity() for j in (1.0, 1.0000001)}
    assert len(same) == 1
    assert BrickStore(synthesizer(candidates, jitter=1.01)).identity() not in same
    # Jitters about the engine's steps of 1/256: one identity, one texture.
    voxels = np.random.default_rng(0).integers(-20, 20, (100, 3))
    by_identity: dict[str, np.ndarray] = {}
    for j in (0.999, 1.0, 1.0000001, 1.001, 129.4 / 256, 129.6 / 256, 129.5 / 256):
        syn = synthesizer(candidates, jitter=j)
        got = syn.voxels(voxels)
        np.testing.assert_array_equal(by_identity.setdefault(BrickStore(syn).identity(), got),
                                      got, err_msg=f"jitter {j}")
    assert len(by_identity) > 1
    store = BrickStore(synthesizer(candidates))
    sample(store, [brick_center((0, 0, 0))])
    path = tmp_path / "s.wtb"
    store.save(path)
    monkeypatch.setattr("warptex.store_files._engine_code", lambda: "another engine")
    with pytest.warns(UserWarning, match=r"another texture \(engine code\)"):
        assert BrickStore.load(path, synthesizer(candidates)).stats()["bricks"] == 0


def test_engine_code_digest_reads_every_module_the_engine_runs(monkeypatch):
    """The kernel modules the engine imports, and its own, are all digested: a change to
    any of them (a building block in kernels/common.py, say) retires the stores it wrote."""
    import ast

    import warptex.store_files

    read = []
    real = warptex.store_files.module_sources

    def recorded(modules):
        read.extend(modules)
        return real(read)

    monkeypatch.setattr(warptex.store_files, "module_sources", recorded)
    warptex.store_files._engine_code.__wrapped__()
    digested = {m.__name__ for m in read}
    assert {"warptex.synthesis", "warptex.dependencies", "kernels.synthesis", "warptex.keysets",
            "warptex.parallel", "warptex.warp_runtime"} <= digested
    for module in read:
        tree = ast.parse(Path(module.__file__).read_text())
        imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)} | {
            a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        kernels = {m for m in imported if m and m.split(".")[0] == "kernels"} - {"kernels"}
        assert kernels <= digested, f"{module.__name__} imports {kernels - digested}"


def test_code_without_source_files_is_keyed_by_warptex_s_version(monkeypatch):
    """A frozen application's modules have no files: the caches' code digest is then the
    constants and warptex's version, all or nothing (a part of the code left out would
    serve caches of code that differs there)."""
    import sys
    import types

    from warptex import code_digest

    frozen = types.ModuleType("frozen")
    assert code_digest.module_sources([sys.modules["warptex.store"], frozen]) is None
    before = code_digest.code_digest(None, "constants")
    monkeypatch.setattr(code_digest, "_package_version", lambda: "0.0.0-other")
    assert code_digest.code_digest(None, "constants") != before


def test_the_installed_code_digest_reads_the_plugin_too(monkeypatch):
    """What a report names beside the version covers all three packages."""
    from warptex import code_digest

    read = []
    monkeypatch.setattr(code_digest, "_digest", lambda files, constants: read.extend(files) or "")
    code_digest.installed_code_digest()
    assert {p.parent.name for p in read} >= {"warptex", "kernels", "mitsuba_plugin"}


def test_a_negative_triple_in_a_file_of_wide_triples_is_refused(candidates, tmp_path,
                                                                 monkeypatch):
    """Exemplars of more than 65536 pixels are stored as int32 triples, which can hold a
    negative pixel: the lookup kernels would read before the exemplar's colors. The check,
    dropped, passed every test (uint16 triples cannot be negative)."""
    from warptex.archive import read_archive, write_archive
    from warptex.store_files import _MAGIC, FORMAT_VERSION

    monkeypatch.setattr("warptex.store._COMPACT_PIXELS", 0)
    syn = synthesizer(candidates)
    store = BrickStore(syn)
    sample(store, [brick_center((0, 0, 0))])
    path = tmp_path / "wide.wtb"
    store.save(path)
    arrays = read_archive(path, _MAGIC, FORMAT_VERSION, "brick store", StoreFileError)
    assert arrays["triples"].dtype == np.int32
    arrays["triples"][0, 1] = -1
    write_archive(path, _MAGIC, FORMAT_VERSION, arrays)
    with pytest.warns(UserWarning, match="voxel triples outside the exemplars"):
        assert BrickStore.load(path, syn).stats()["bricks"] == 0


def test_a_file_of_another_texture_without_its_settings_is_refused_in_general_words(
        candidates, tmp_path):
    """Files written before the settings were kept (or with settings of another shape)
    cannot say which setting differs: the warning names what could."""
    from warptex.archive import read_archive, write_archive
    from warptex.store_files import _MAGIC, FORMAT_VERSION

    store = BrickStore(synthesizer(candidates))
    sample(store, [brick_center((0, 0, 0))])
    path = tmp_path / "s.wtb"
    store.save(path)
    good = read_archive(path, _MAGIC, FORMAT_VERSION, "brick store", StoreFileError)
    unkept = {name: array for name, array in good.items() if name != "settings"}
    for arrays in (unkept, dict(good, settings=np.array("[1, 2]")),
                   dict(good, settings=np.array("{not json"))):
        write_archive(path, _MAGIC, FORMAT_VERSION, arrays)
        with pytest.warns(UserWarning, match=r"written for another texture \(other exemplars, "
                                             r"seed, jitter or synthesis parameters\)"):
            assert BrickStore.load(path, synthesizer(candidates, seed=3)).stats()["bricks"] == 0


def test_a_file_of_triples_or_bricks_the_kernels_cannot_read_is_refused(candidates, tmp_path):
    """A file that passes its checksum but was written by other means: triples beyond the
    exemplars or repeated bricks would send the lookup kernels out of bounds."""
    from warptex.archive import read_archive, write_archive
    from warptex.keysets import pack
    from warptex.store_files import _MAGIC, FORMAT_VERSION
    from warptex.synthesis import COORD_LIMIT

    syn = synthesizer(candidates)
    store = BrickStore(syn)
    sample(store, [brick_center((0, 0, 0)), brick_center((1, 0, 0))])
    path = tmp_path / "s.wtb"
    store.save(path)
    good = read_archive(path, _MAGIC, FORMAT_VERSION, "brick store", StoreFileError)
    beyond = dict(good, triples=good["triples"].copy())
    beyond["triples"][5, 2] = 32 * 32  # granite_32 has 1024 pixels
    repeated = dict(good, keys=np.repeat(good["keys"], 2), valid=np.repeat(good["valid"], 2, 0),
                    triples=np.concatenate([good["triples"]] * 2))
    float_keys = dict(good, keys=good["keys"].astype(np.float64))
    # One past each other check (each, dropped or loosened, passed every test; the first
    # three then failed in a traceback): keys of another shape, a brick's bits missing (its
    # voxels too), bits of a float type, triples of another type, a brick past the range.
    last = int(np.bitwise_count(good["valid"][-1]).sum())
    # Bricks of voxels just past the coordinates' range [-COORD_LIMIT, COORD_LIMIT), at
    # either end; the bricks of its first and last voxels are read (below).
    beyond_range = [[COORD_LIMIT // 8, 0, 0], [0, (-COORD_LIMIT - 1) // 8, 0]]
    fars = []
    for brick in beyond_range:
        far = good["keys"].copy()
        far[0] = pack(np.array([brick]))[0]
        fars.append((dict(good, keys=far), "bricks beyond the texture range"))
    cases = ((beyond, "outside the exemplars"), (repeated, "repeated bricks"),
             (float_keys, "brick keys of unexpected type"),
             (dict(good, keys=good["keys"][:, None]), "brick keys of unexpected type or shape"),
             (dict(good, valid=good["valid"][:-1], triples=good["triples"][:-last]),
              "stored-voxel bits of unexpected type or shape"),
             (dict(good, valid=good["valid"].view(np.float32)), "stored-voxel bits"),
             (dict(good, triples=good["triples"].astype(np.int64)), "voxel triples of unexpected"),
             *fars)
    for arrays, problem in cases:
        write_archive(path, _MAGIC, FORMAT_VERSION, arrays)
        with pytest.warns(UserWarning, match=problem):
            assert BrickStore.load(path, syn).stats()["bricks"] == 0
    edges = pack(np.array([[-COORD_LIMIT // 8, 0, 0], [0, 0, (COORD_LIMIT - 1) // 8]]))
    write_archive(path, _MAGIC, FORMAT_VERSION, dict(good, keys=edges))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert BrickStore.load(path, syn).stats()["bricks"] == 2
    # Checksummed, but no archive NumPy reads: refused in the same words as damage.
    from warptex.archive import _VERSION_BYTES

    magic_and_version = path.read_bytes()[:len(_MAGIC) + _VERSION_BYTES]
    single = io.BytesIO()
    np.save(single, good["keys"])  # one array's .npy, which NumPy loads as that array
    for payload in (b"PK\x03\x04" + bytes(60), b"", single.getvalue()):
        path.write_bytes(magic_and_version + hashlib.sha256(payload).digest() + payload)
        with pytest.warns(UserWarning, match="unreadable brick store data"):
            assert BrickStore.load(path, syn).stats()["bricks"] == 0
    # Bits stored column-major are the same bits.
    write_archive(path, _MAGIC, FORMAT_VERSION, dict(good, valid=np.asfortranarray(good["valid"])))
    assert BrickStore.load(path, syn).stats()["bricks"] == 2


def test_stats_count_hits_misses_and_bytes_as_documented(candidates):
    """One point of a cold store misses, the same point again hits; bytes are the payload's
    and the index's (StoreStats)."""
    store = BrickStore(synthesizer(candidates))
    sample(store, [brick_center((0, 0, 0))])
    first = store.stats()
    assert (first["hits"], first["misses"]) == (0, 1)
    sample(store, [brick_center((0, 0, 0))])
    again = store.stats()
    assert (again["hits"], again["misses"]) == (1, 1)
    assert again["bytes"] == again["payload_bytes"] + again["index_bytes"] > 0



def test_a_partial_brick_grown_voxel_by_voxel_does_not_grow_the_pool(candidates):
    """Each voxel added to a partly stored brick repacks the brick; the ranges left behind
    are garbage the pool compacts. Left uncounted, 300 voxels of one brick grew the pool
    with the sum of the brick's sizes."""
    store = BrickStore(synthesizer(candidates), whole_bricks=False)
    sample(store, [[0.5, 0.5, 0.5]])
    start = store.stats()["allocated_bytes"]
    for k in range(1, 300):
        sample(store, [[k % 8 + 0.5, k // 8 % 8 + 0.5, k // 64 + 0.5]])
    stats = store.stats()
    assert stats["voxels"] == 300 and stats["bricks"] == 1
    assert stats["allocated_bytes"] < 2 * start
