"""The synthesis engine (Dong 2008, section 5): determinism is the contract."""

from __future__ import annotations

import dataclasses
import itertools
import subprocess
import sys
import textwrap
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from itertools import pairwise

import numpy as np
import pytest

from kernels import synthesis as _k
from warptex import metrics, synthesis
from warptex.candidate_set import CandidateSet
from warptex.candidates import precompute
from warptex.dependencies import (
    apron_blocks,
    correction_steps,
    default_apron_blocks,
    dependency_chain,
    dependency_mask,
    dependency_radius,
)
from warptex.exemplar import Exemplar
from warptex.keysets import pack, unique
from warptex.synthesis import COORD_LIMIT, Synthesizer


@pytest.fixture(scope="module")
def candidates(granite_32, tmp_path_factory, warp_device) -> CandidateSet:
    return precompute(granite_32, cache=False)


@pytest.fixture(scope="module")
def wide_candidates(granite_32x48, warp_device) -> CandidateSet:
    """Candidates of a 32x48 exemplar: a square one would hide a height read for a width."""
    return precompute(granite_32x48, cache=False)


@pytest.fixture(scope="module")
def mixed_candidates(granite_32x48, warp_device) -> CandidateSet:
    """Candidates of three exemplars of three sizes, 32x48, 32x32 and 48x32 along x, y and
    z: each axis' coordinates wrap at its own exemplar's size."""
    granite = granite_32x48.colors
    return precompute(granite_32x48, Exemplar(np.ascontiguousarray(granite[:, 16:]), name="y"),
                      Exemplar(np.ascontiguousarray(granite.swapaxes(0, 1)), name="z"),
                      cache=False)


def _sizes(candidates: CandidateSet, level: int) -> np.ndarray:
    """(3, 2): the (height, width) of the exemplar of each axis at ``level``."""
    return np.array([candidates.sources[level][candidates.axis_source[k]].size
                     for k in range(3)])


def _random_voxels(rng: np.random.Generator, n: int, lo: int = -40, hi: int = 40) -> np.ndarray:
    return rng.integers(lo, hi, size=(n, 3))


@pytest.mark.parametrize("passes", [1, 2, 3])
def test_voxel_independent_of_what_else_is_requested(candidates, passes):
    """Also at 1 and 3 passes, whose dependency radii (2 and 6 voxels) are no whole number of
    blocks: an apron rounded down passed at the default 2 passes' 4."""
    rng = np.random.default_rng(1)
    probe = np.array([[3, 5, 7], [-9, 0, 4], [0, -1, -13], [17, 22, -6]])
    alone = np.concatenate([Synthesizer(candidates, seed=5, passes=passes).voxels(p[None])
                            for p in probe])
    small_box = Synthesizer(candidates, seed=5, passes=passes).box((-16, -16, -16),
                                                                   (40, 40, 40))
    in_box = small_box[probe[:, 0] + 16, probe[:, 1] + 16, probe[:, 2] + 16]
    scattered = np.concatenate([probe, _random_voxels(rng, 300)])
    perm = rng.permutation(len(scattered))
    shuffled = Synthesizer(candidates, seed=5, passes=passes).voxels(scattered[perm])
    in_scattered = np.empty_like(shuffled)
    in_scattered[perm] = shuffled
    assert np.array_equal(alone, in_box)
    assert np.array_equal(alone, in_scattered[: len(probe)])


@pytest.mark.parametrize("subpasses", [1, 8])
def test_batch_size_and_order_do_not_matter(candidates, subpasses):
    """Also with 8 interleaved sub-passes, whose dependencies chain from sub-pass to
    sub-pass (fewer voxels, closer together: each reaches 19 voxels further a level)."""
    rng = np.random.default_rng(2)
    count, step = (200, 37) if subpasses == 1 else (24, 7)
    pts = _random_voxels(rng, count) if subpasses == 1 else _random_voxels(rng, count, -24, 24)
    whole = Synthesizer(candidates, seed=9, subpasses=subpasses).voxels(pts)
    syn = Synthesizer(candidates, seed=9, subpasses=subpasses)
    pieces = [syn.voxels(pts[i : i + step]) for i in range(0, len(pts), step)]
    assert np.array_equal(whole, np.concatenate(pieces))
    reverse = Synthesizer(candidates, seed=9, subpasses=subpasses).voxels(pts[::-1])[::-1]
    assert np.array_equal(whole, reverse)


@pytest.mark.parametrize("kind", ["neighbourhood 3", "neighbourhood 3, 1 pass",
                                  "neighbourhood 9", "feature distance"])
def test_other_settings_keep_each_voxel_independent_in_any_parts(granite_32, kind,
                                                                 monkeypatch):
    """N = 9 reads a whole block away, the farthest the dependency spread of section 5.2
    supports, N = 3 the nearest, and a feature-distance channel (section 6) widens every
    neighbourhood's vector: each voxel alone, among others shuffled, and in parts of one
    block each, over block edges, far voxels and both ends of the range."""
    if kind == "feature distance":
        rows, columns = np.mgrid[:32, :32]
        distance = (0.5 + 0.5 * np.sin(columns / 5.0) * np.cos(rows / 7.0)).astype(np.float32)
        cs = precompute(Exemplar(granite_32.colors, name="features", feature_distance=distance),
                        cache=False)
    else:
        cs = precompute(granite_32, cache=False, neighborhood=int(kind.split()[1][0]))
    passes = 1 if kind.endswith("1 pass") else 2  # radius 1: an apron of one block
    rng = np.random.default_rng(4)
    edges = rng.integers(-3, 3, (12, 3)) * 4 + rng.choice([-1, 0, 3], (12, 3))
    ends = np.array([[-COORD_LIMIT, 0, COORD_LIMIT - 1], [COORD_LIMIT - 2, -COORD_LIMIT + 1, 5]])
    pts = np.concatenate([_random_voxels(rng, 12), edges, ends,
                          _random_voxels(rng, 4, -10**6, 10**6)])

    def triples(voxels: np.ndarray) -> np.ndarray:
        return Synthesizer(cs, seed=3, passes=passes).pixel_triples(voxels)

    alone = np.concatenate([triples(p[None]) for p in pts])
    perm = rng.permutation(np.concatenate([np.arange(len(pts)), [0, 5, 13]]))
    assert np.array_equal(triples(pts[perm]), alone[perm])
    monkeypatch.setattr(synthesis, "work_voxel_cap", lambda *args: 1)
    assert np.array_equal(triples(pts[perm]), alone[perm])


def test_a_gpu_or_a_process_too_small_for_the_largest_part_gets_smaller_ones(monkeypatch):
    """A part of MAX_WORK_VOXELS takes about 4.7 GB: a 4 GB GPU failed half-way through
    a large box (Warp's "Failed to allocate"), and so did 3,000 scattered points queried
    through a brick store (whose batches no request check sees) on a 2 GiB machine."""
    import warptex.machine
    monkeypatch.setattr(synthesis, "_device_memory", lambda device: 4 << 30)
    rgb = synthesis.work_bytes_per_voxel(3)
    assert synthesis.work_voxel_cap("cuda:0") == (4 << 30) // (2 * rgb)
    assert synthesis.work_voxel_cap("cuda:0") < synthesis.MAX_WORK_VOXELS
    # More feature channels, more memory a work voxel: smaller parts (they took 76% of the
    # GPU at 34 channels, not half).
    assert synthesis.work_voxel_cap("cuda:0", 34) == (4 << 30) // (2 * (rgb + 6 * 31))
    assert synthesis.work_bytes_per_voxel(1) == rgb  # gray: no fewer than RGB's
    monkeypatch.setattr(synthesis, "_device_memory", lambda device: 80 << 30)
    assert synthesis.work_voxel_cap("cuda") == synthesis.MAX_WORK_VOXELS
    for memory, cap in ((80 << 30, synthesis.MAX_WORK_VOXELS), (2 << 30, (2 << 30) // (2 * rgb)),
                        (None, synthesis.MAX_WORK_VOXELS)):  # None: unknown
        monkeypatch.setattr(warptex.machine, "physical_memory", lambda memory=memory: memory)
        synthesis._host_memory.cache_clear()
        assert synthesis.work_voxel_cap("cpu") == cap


def test_requests_beyond_one_call_are_split_into_parts_with_the_same_result(candidates,
                                                                           monkeypatch):
    rng = np.random.default_rng(3)
    pts = np.concatenate([np.indices((12, 10, 9)).reshape(3, -1).T - 5, _random_voxels(rng, 60)])
    whole = Synthesizer(candidates, seed=2)
    expected = whole.triples(pts)
    monkeypatch.setattr(synthesis, "MAX_WORK_VOXELS", 40 * 64)
    parted = Synthesizer(candidates, seed=2)
    parts = parted._parts(unique(pack(pts >> 2)))
    assert len(parts) > 4
    assert max(len(work) for _, work in parts) * 64 <= synthesis.MAX_WORK_VOXELS
    assert np.array_equal(parted.triples(pts), expected)
    # Aprons overlap between parts, so parts cost more finest voxels than one call.
    assert parted.voxels_synthesized[parted.finest] > whole.voxels_synthesized[whole.finest]


def test_triples_identical_and_colors_are_their_average(candidates):
    pts = np.array([[0, 0, 0], [-1, -1, -1], [31, 2, -40], [100, -100, 7]])
    syn = Synthesizer(candidates, seed=0)
    tri = syn.triples(pts)
    again = Synthesizer(candidates, seed=0).triples(pts[::-1])[::-1]
    assert np.array_equal(tri, again)
    assert tri.shape == (4, 3, 2)
    h, w = candidates.colors[0].shape[:2]
    assert (tri[..., 0] >= 0).all() and (tri[..., 0] < h).all()
    assert (tri[..., 1] >= 0).all() and (tri[..., 1] < w).all()
    col = candidates.colors[0]
    expected = (col[tri[:, 0, 0], tri[:, 0, 1]] + col[tri[:, 1, 0], tri[:, 1, 1]])
    expected = (expected + col[tri[:, 2, 0], tri[:, 2, 1]]) / np.float32(3)
    assert np.array_equal(syn.voxels(pts), expected.astype(np.float32))


def test_coarse_cache_never_changes_a_result(candidates, monkeypatch):
    """The warm engine's second request reads coarse voxels the first one cached (asserted:
    without hits this would compare two cold engines)."""
    rng = np.random.default_rng(3)
    first, second = _random_voxels(rng, 150), _random_voxels(rng, 150, -60, 20)
    warm = Synthesizer(candidates, seed=4)
    warm.voxels(first)
    hits = []
    find = synthesis._LevelCache.find

    def counted(self, keys, flat):
        rows = find(self, keys, flat)
        hits.append(int(np.count_nonzero(rows >= 0)))
        return rows

    monkeypatch.setattr(synthesis._LevelCache, "find", counted)
    warmed = warm.voxels(second)
    assert sum(hits) > 0
    cold = Synthesizer(candidates, seed=4, coarse_cache_bytes=0)
    assert np.array_equal(warmed, cold.voxels(second))


def test_a_full_coarse_cache_starts_over_without_changing_results(candidates):
    small = Synthesizer(candidates, seed=4, coarse_cache_bytes=1000 * 64 * 12)
    cold = Synthesizer(candidates, seed=4, coarse_cache_bytes=0)
    rng = np.random.default_rng(3)
    held = []
    for _ in range(6):
        voxels = _random_voxels(rng, 60, -60, 60)
        assert np.array_equal(small.voxels(voxels), cold.voxels(voxels))
        held.append(sum(len(c.keys) for c in small._cache.values()))
    assert any(b < a for a, b in pairwise(held))  # the cache filled up and started over
    # A request of more blocks than the cache holds keeps none of them: the bound holds.
    tiny = Synthesizer(candidates, seed=4, coarse_cache_bytes=4 * 64 * 12)
    assert np.array_equal(tiny.box((0, 0, 0), (24, 24, 24)), cold.box((0, 0, 0), (24, 24, 24)))
    assert all(c.triples.nbytes <= c.max_bytes for c in tiny._cache.values())


class _StoppedInTheCache:
    """numpy, but Ctrl-C where the coarse cache joins its blocks' bits (a uint64
    concatenation), or where it sets the bits of voxels whose triples it has written
    (``np.bitwise_or``, which only that step uses)."""

    def __init__(self, where: str) -> None:
        self.stop = where  # not .where: np.where is looked up here too

    def __getattr__(self, name: str):
        if self.stop == "before the bits" and name == "bitwise_or":
            raise KeyboardInterrupt
        return getattr(np, name)

    def concatenate(self, arrays, *args, **kwargs):
        if self.stop == "joining blocks" and arrays[0].dtype == np.uint64:
            raise KeyboardInterrupt
        return np.concatenate(arrays, *args, **kwargs)


@pytest.mark.parametrize("where", ["joining blocks", "before the bits"])
def test_a_request_stopped_while_caching_leaves_no_wrong_coarse_voxel(candidates, monkeypatch,
                                                                     where):
    """Ctrl-C while a request enters coarse blocks in the cache, as it joins their bits or
    once it has written their voxels' triples and not yet the bits that mark them cached:
    later requests still get what an engine without a cache gives (the blocks change in
    one step, and triples without their bits are never read)."""
    rng = np.random.default_rng(6)
    first, second = _random_voxels(rng, 150), _random_voxels(rng, 150, -60, 20)
    engine = Synthesizer(candidates, seed=4)
    engine.voxels(first)
    with monkeypatch.context() as patch:
        patch.setattr(synthesis, "np", _StoppedInTheCache(where))
        with pytest.raises(KeyboardInterrupt):
            engine.voxels(second)
    both = np.concatenate([first, second])
    cold = Synthesizer(candidates, seed=4, coarse_cache_bytes=0)
    assert np.array_equal(engine.voxels(both), cold.voxels(both))


class _OwnedLock:
    """A lock that says which thread holds it (``threading.Lock.locked`` says only that one
    does, which another thread's holding would satisfy)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.owner: int | None = None

    def __enter__(self) -> _OwnedLock:
        self._lock.acquire()
        self.owner = threading.get_ident()
        return self

    def __exit__(self, *exc) -> None:
        self.owner = None
        self._lock.release()


@pytest.mark.parametrize("cache_blocks", [1500, None])
def test_threads_sharing_one_engine_get_what_serial_requests_get(candidates, monkeypatch,
                                                                 cache_blocks):
    """Also with a coarse cache small enough to be filled and cleared while the threads
    race (1500 blocks of 64 voxels, 12 bytes a voxel): every use of it is under the
    engine's lock, checked as it happens, since a race need not show in the results (200
    blocks, fewer than one request adds, left the cache unused)."""
    rng = np.random.default_rng(8)
    requests = [_random_voxels(rng, 60 if cache_blocks else 100, -80, 80)
                for _ in range(24 if cache_blocks else 12)]
    serial = Synthesizer(candidates, seed=5, coarse_cache_bytes=0)
    expected = [serial.voxels(r) for r in requests]
    cache = {} if cache_blocks is None else {"coarse_cache_bytes": cache_blocks * 64 * 12}
    racing: list[Synthesizer] = []  # the engine the threads share, while they race
    seen = {"clear": 0, "hits": 0}

    def under_lock(name: str):
        use = getattr(synthesis._LevelCache, name)

        def checked(self, *args):
            if racing:
                assert racing[0]._lock.owner == threading.get_ident(), (
                    f"coarse cache {name} without the lock")
                seen["clear"] += name == "clear"
            found = use(self, *args)
            if racing and name == "find":
                seen["hits"] += int(np.count_nonzero(found >= 0))
            return found
        return checked

    for name in ("find", "insert", "clear"):
        monkeypatch.setattr(synthesis._LevelCache, name, under_lock(name))
    for _ in range(2):
        shared = Synthesizer(candidates, seed=5, **cache)
        shared._lock = _OwnedLock()
        racing.append(shared)
        with ThreadPoolExecutor(8 if cache_blocks else 4) as pool:
            got = list(pool.map(shared.voxels, requests))
        racing.clear()
        for g, e in zip(got, expected, strict=True):
            assert np.array_equal(g, e)
    assert seen["hits"] > 0
    if cache_blocks is not None:
        assert seen["clear"] > 0


@pytest.mark.parametrize(("threads", "halo_chunk"), [(2, 256), (3, 1), (8, 3)])
def test_results_do_not_depend_on_how_launches_are_split(candidates, monkeypatch, threads,
                                                         halo_chunk):
    """A machine of another number of cores splits each launch otherwise, and halos are
    gathered in chunks: neither may change a voxel (here the split is set, whatever this
    machine's cores)."""
    from warptex import parallel

    box = np.indices((24, 20, 22)).reshape(3, -1).T - 10
    points = np.concatenate([box, _random_voxels(np.random.default_rng(1), 200)])
    monkeypatch.setattr(parallel, "THREADS", 1)
    one = Synthesizer(candidates, seed=3).triples(points)
    monkeypatch.setattr(parallel, "THREADS", threads)
    monkeypatch.setitem(synthesis._HALO_CHUNK, "cpu", halo_chunk)
    assert np.array_equal(Synthesizer(candidates, seed=3).triples(points), one)


def test_bit_identical_across_processes(candidates, tmp_path):
    pts = np.array([[1, 2, 3], [-20, 7, 11], [5, -5, 5]])
    path = tmp_path / "cands.wtc"
    candidates.save(path)
    out = tmp_path / "out.npy"
    script = textwrap.dedent(
        f"""
        import numpy as np
        from warptex.candidate_set import CandidateSet
        from warptex.synthesis import Synthesizer
        syn = Synthesizer(CandidateSet.load({str(path)!r}), seed=11, device="cpu")
        np.save({str(out)!r}, syn.voxels(np.array({pts.tolist()!r})))
        """
    )
    subprocess.run([sys.executable, "-c", script], check=True)
    here = Synthesizer(CandidateSet.load(path), seed=11).voxels(pts)
    assert np.array_equal(np.load(out), here)


@pytest.mark.parametrize("which", ["candidates", "wide_candidates", "mixed_candidates"])
def test_initialization_tiles_the_candidate_slab(request, which):
    """Section 4.3 and 5.1: without jitter or correction a voxel holds the x exemplar's
    pixel under it and that pixel's first 3D candidate, its two other coordinates moved
    along the slab's depth (x): the column of the y exemplar, the row of the z one, each
    wrapped at its own exemplar's size."""
    candidates = request.getfixturevalue(which)
    syn = Synthesizer(candidates, jitter=0.0, passes=0, levels=0)
    n = int(candidates.params["neighborhood"])
    h, w = _sizes(candidates, syn.finest)[0]
    vox = np.indices((n, h, w)).reshape(3, -1).T + np.array([-2 * n, 3 * h, -w])
    np.testing.assert_array_equal(syn.triples(vox), _slab_tiling(candidates, syn.finest, vox))


def test_seeds_differ_and_jitter_zero_tiles_the_slab(candidates):
    box_a = Synthesizer(candidates, seed=1).box((0, 0, 0), (16, 16, 16))
    box_b = Synthesizer(candidates, seed=2).box((0, 0, 0), (16, 16, 16))
    assert not np.array_equal(box_a, box_b)
    # Without jitter the start level is a tiling of the slab, and every later step is
    # translation invariant, so the result repeats with the slab's period scaled up.
    with pytest.warns(UserWarning, match=r"seed 1 gives the same solid as seed 0: .* and a "
                      r"jitter of 0\.001 is taken as 0 \(at most 1/512\), with no tiles shifted"):
        syn = Synthesizer(candidates, seed=1, jitter=0.001)
    scale = 2 ** (syn.finest - syn.start)
    n = int(candidates.params["neighborhood"])
    h, w = candidates.sources[syn.start][0].size
    period = np.array([n * scale, h * scale, w * scale])
    pts = _random_voxels(np.random.default_rng(4), 100)
    assert np.array_equal(syn.voxels(pts), syn.voxels(pts + period))
    assert np.array_equal(syn.voxels(pts), Synthesizer(candidates, jitter=0.0).voxels(pts))
    with warnings.catch_warnings():  # the seed acts, or is 0: no warning
        warnings.simplefilter("error")
        Synthesizer(candidates, jitter=0.0)
        Synthesizer(candidates, seed=1, jitter=1 / 256)
        Synthesizer(candidates, seed=1, jitter=0.0, shifted_tiles=True)
    jittered = Synthesizer(candidates, seed=1, jitter=1.0)
    assert not np.array_equal(jittered.voxels(pts), jittered.voxels(pts + period))


def test_shifted_tiles_end_the_period_and_stay_deterministic(candidates):
    """Each tile of the slab shifted by its own hashed offset: without jitter the texture
    no longer repeats with the slab's period, and a voxel is still the same whatever is
    requested with it and in whatever order."""
    syn = Synthesizer(candidates, seed=1, jitter=0.0, shifted_tiles=True)
    scale = 2 ** (syn.finest - syn.start)
    n = int(candidates.params["neighborhood"])
    h, w = candidates.sources[syn.start][0].size
    pts = _random_voxels(np.random.default_rng(4), 100)
    for period in ([0, h * scale, 0], [0, 0, w * scale], [n * scale, 0, 0]):
        repeats = np.all(syn.voxels(pts) == syn.voxels(pts + period), axis=1)
        assert repeats.mean() < 0.2, period
    alone = np.concatenate([Synthesizer(candidates, seed=1, jitter=0.0, shifted_tiles=True)
                            .voxels(p[None]) for p in pts[:4]])
    shuffled = Synthesizer(candidates, seed=1, jitter=0.0, shifted_tiles=True).voxels(pts[::-1])
    np.testing.assert_array_equal(alone, syn.voxels(pts[:4]))
    np.testing.assert_array_equal(shuffled[::-1], syn.voxels(pts))
    with pytest.raises(ValueError, match="shifted_tiles must be True or False"):
        Synthesizer(candidates, shifted_tiles=1)


def test_seeds_shift_the_tiles_differently_without_jitter(candidates):
    """With shifted tiles and no jitter the seed alone decides each tile's offset: two seeds
    give two textures, else a user's seed would change nothing."""
    pts = _random_voxels(np.random.default_rng(5), 100, lo=-200, hi=200)
    one, two = (Synthesizer(candidates, seed=seed, jitter=0.0, shifted_tiles=True, passes=0,
                            levels=0).triples(pts) for seed in (1, 2))
    assert np.all(one != two, axis=(1, 2)).mean() > 0.5


def test_jitter_moves_the_voxel_the_slab_is_read_at_along_every_axis(wide_candidates):
    """Section 5.1, "Jitter": the start level is the slab's tiling read at each voxel moved
    by a small random warp: a triple is the tiling's at some position (the x exemplar's
    pixel and its first 3D candidate moved along the slab's depth), and for some voxels the
    warp moves that position off the voxel's own along each axis: the pixel off its (y, z),
    by a few pixels, the depth off its x's."""
    syn = Synthesizer(wide_candidates, seed=3, jitter=1.0, passes=0, levels=0)
    n = int(wide_candidates.params["neighborhood"])
    h, w = wide_candidates.sources[syn.start][0].size
    vox = _random_voxels(np.random.default_rng(6), 2000, lo=-300, hi=300)
    got = syn.triples(vox)

    def tiled_at(depth):
        # The tiling at the voxel of the read pixel whose x puts it at ``depth`` in its slab.
        at = np.c_[np.broadcast_to(depth + n // 2, len(got)), got[:, 0]]
        return (_slab_tiling(wide_candidates, syn.start, at) == got).all(axis=(1, 2))

    assert np.any([tiled_at(depth) for depth in range(-(n // 2), n // 2 + 1)], axis=0).all()
    assert not tiled_at(vox[:, 0] % n - n // 2).all()  # x moves too
    for axis, size in ((1, h), (2, w)):
        moved = (got[:, 0, axis - 1] - vox[:, axis] + size // 2) % size - size // 2
        assert 0.1 < np.mean(moved != 0) < 0.6 and np.abs(moved).max() <= 12, axis


def test_jitter_lattice_floors_negative_coordinates(warp_device):
    """The jitter's lattice cells (``bump_sum``) need floor division at negative voxels;
    Warp's integer ``//`` truncated there before NVIDIA/warp#1918, so ``floor_div`` stands in."""
    import warp as wp

    from kernels.common import floor_div

    @wp.kernel
    def divide(x: wp.array(dtype=int), n: int, out: wp.array(dtype=int)):
        i = wp.tid()
        out[i] = floor_div(x[i], n)

    x = np.arange(-40, 41, dtype=np.int32)
    out = wp.zeros(len(x), dtype=int, device=warp_device)
    for n in (1, 6, 16):
        wp.launch(divide, dim=len(x), inputs=[wp.array(x, device=warp_device), n, out],
                  device=warp_device)
        assert np.array_equal(out.numpy(), x // n)


def _hash_u32(x: np.ndarray) -> np.ndarray:
    """lowbias32 on uint32 arrays, as ``kernels.common.hash_u32``: NumPy's uint32 products
    wrap as CUDA's and the CPU's do."""
    x = x ^ (x >> np.uint32(16))
    x = x * np.uint32(0x7FEB352D)
    x = x ^ (x >> np.uint32(15))
    x = x * np.uint32(0x846CA68B)
    return x ^ (x >> np.uint32(16))


def _hash_cell(cells: np.ndarray, seed: int, salt: int) -> np.ndarray:
    h = _hash_u32(np.uint32(seed) ^ np.full(len(cells), 0x9E3779B9, np.uint32))
    for axis in range(3):
        h = _hash_u32(h ^ cells[:, axis].astype(np.uint32))  # two's complement, as Warp
    return _hash_u32(h ^ np.uint32(salt))


def _bump_sum(pos: np.ndarray, seed: int, jitter: int, octave: int, cell: int, rmin: int,
              rrange: int, amin: int, arange: int) -> np.ndarray:
    """Section 5.1's random warp, one octave, written from ``bump_sum``'s description: a
    bump (1 - r^2/R^2)^3 of random centre, radius, amplitude and direction per lattice
    cell of ``cell`` voxels, summed over the 27 cells around each voxel, in 1/256 voxel."""
    total = np.zeros(pos.shape, np.int64)
    for offset in itertools.product((-1, 0, 1), repeat=3):
        cells = pos // cell + offset  # floor division: cells extend to negative voxels
        h, h1, h2 = (_hash_cell(cells, seed, octave + salt).astype(np.int64)
                     for salt in (0, 16, 32))
        span = cell * 256
        centre = cells * span + np.c_[h % span, (h >> 8) % span, (h >> 16) % span]
        radius = rmin * 256 + h1 % (rrange * 256 + 1)
        r2 = ((pos * 256 - centre) ** 2).sum(axis=1)
        t = 65536 - r2 * 65536 // (radius * radius)
        weight = (((t * t) >> 16) * t) >> 16
        amplitude = ((amin * 256 + (h1 >> 12) % (arange * 256 + 1)) * jitter) >> 8
        direction = np.c_[h2 % 513, (h2 >> 10) % 513, (h2 >> 20) % 513] - 256
        bump = (amplitude[:, None] * direction * weight[:, None]) >> 24
        total += np.where((r2 < radius * radius)[:, None], bump, 0)
    return total


def test_jitter_warp_matches_a_reference_written_from_its_description(warp_device):
    """``warp_offset`` (section 5.1, "Jitter") against a NumPy rewrite of its two octaves of
    bumps, exactly, at voxels of both signs far from the origin, for several seeds and
    strengths: a changed hash, lattice, radius, profile or rounding shows here, where the
    jitter tests above see only that voxels move."""
    import warp as wp

    @wp.kernel
    def offsets(pos: wp.array(dtype=wp.vec3i), seed: int, jitter: int,
                out: wp.array(dtype=wp.vec3i)):
        i = wp.tid()
        out[i] = _k.warp_offset(pos[i], seed, jitter)

    rng = np.random.default_rng(12)
    corners = np.array(list(itertools.product((-COORD_LIMIT, COORD_LIMIT - 1), repeat=3)))
    pos = np.concatenate([_random_voxels(rng, 3000), corners,  # int32 is tightest there
                          _random_voxels(rng, 1000, -COORD_LIMIT, COORD_LIMIT)])
    out = wp.zeros(len(pos), dtype=wp.vec3i, device=warp_device)
    moved = []
    for seed, jitter in ((0, 256), (3, 256), (2**31 - 1, 2048), (7, 0)):
        wp.launch(offsets, dim=len(pos), device=warp_device,
                  inputs=[wp.array(pos, dtype=wp.vec3i, device=warp_device), seed, jitter, out])
        fine = (_bump_sum(pos, seed, jitter, 0, 16, 6, 8, 2, 4)
                + _bump_sum(pos, seed, jitter, 1, 6, 2, 3, 1, 2))
        assert np.array_equal(out.numpy(), (fine + 128) >> 8), (seed, jitter)
        moved.append(np.mean(np.any(out.numpy() != 0, axis=1)))
    assert moved[0] > 0.3 and moved[2] > moved[0] and moved[3] == 0.0


def test_the_ends_of_the_coordinate_range_are_synthesized_right(candidates):
    """Without jitter the texture repeats with the slab's period, so the last voxels of the
    coordinate range equal their repeats near the origin: their work regions (8 sub-passes,
    an apron of 5 blocks) stay within the packed block keys."""
    syn = Synthesizer(candidates, jitter=0.0, subpasses=8)
    n = int(candidates.params["neighborhood"])
    scale = 2 ** (syn.finest - syn.start)
    # x: the slab's tiles (even at every level: sub-pass parity); y and z: the exemplar's.
    height, width = candidates.sources[syn.start][candidates.axis_source[0]].size
    period = np.array([2 * n * scale, height * scale, width * scale])
    ends = (-COORD_LIMIT, 1 - COORD_LIMIT, COORD_LIMIT - 2, COORD_LIMIT - 1, 0)
    far = np.array(list(itertools.product(ends, repeat=3)))  # each axis' key field
    near = far - (far // period) * period
    np.testing.assert_array_equal(syn.voxels(far), syn.voxels(near))


def test_subpasses_are_deterministic_too(candidates):
    pts = np.array([[2, 3, 4], [-7, 8, -9]])
    alone = Synthesizer(candidates, seed=3, subpasses=8).voxels(pts[:1])
    box = Synthesizer(candidates, seed=3, subpasses=8).box((-10, 0, -12), (16, 12, 20))
    assert np.array_equal(alone[0], box[12, 3, 16])
    assert np.array_equal(
        Synthesizer(candidates, seed=3, subpasses=8).voxels(pts)[1], box[3, 8, 3]
    )


def test_dependency_masks():
    assert correction_steps(2, 1) == [-1, -1]
    assert correction_steps(1, 8) == list(range(8))
    # One correction reads the three N x N planes through a voxel: radius N//2 a pass.
    assert dependency_radius(2, 1, 1) == 2
    assert dependency_radius(2, 2, 1) == 4
    assert dependency_radius(2, 0, 1) == 0
    # Interleaved sub-passes chain within a pass, so they reach much farther.
    assert dependency_radius(2, 2, 8) > dependency_radius(2, 2, 1)
    chain = dependency_chain(2, 2, 1, 3)
    # The finest level needs the 3-neighbourhood of the 3-neighbourhood of one voxel.
    plane = 5 * 5 * 3 - 3 * 5 + 1
    assert plane < chain[0] < 9**3
    assert chain == [473, 1749, 2815]  # BENCHMARKS.md; the paper reports 6778 in all
    # The apron is the radius in whole blocks, rounded up: one voxel past a multiple of
    # the block (N = 3 at 1 or 5 passes, N = 7 at 3) needs one block more.
    for half, passes, subpasses in itertools.product(range(1, 5), range(7), (1, 8)):
        radius = dependency_radius(half, passes, subpasses)
        blocks = apron_blocks(half, passes, subpasses)
        assert (blocks - 1) * _k.BLOCK < radius <= blocks * _k.BLOCK or radius == blocks == 0
    assert [default_apron_blocks(p) for p in range(5)] == [apron_blocks(2, p, 1)
                                                          for p in range(5)] == [0, 1, 1, 2, 2]


@pytest.mark.parametrize("spread", [1, 50])
def test_neighbor_table_finds_every_present_neighbour(spread):
    """Compact block sets (a dense grid over their bounding box) and sparse ones (searched)
    give each block's 27 neighbours' slots, -1 where absent."""
    rng = np.random.default_rng(spread)
    blocks = np.unique(rng.integers(-4, 4, (600, 3)) * spread + rng.integers(-1, 2, (600, 3)),
                       axis=0)
    cells = np.prod(blocks.max(axis=0) - blocks.min(axis=0) + 3) / len(blocks)
    assert (cells <= synthesis._DENSE_CELLS_PER_BLOCK) == (spread == 1)  # one of each way
    keys = pack(blocks)
    order = np.argsort(keys)
    keys, blocks = keys[order], blocks[order]
    slot = {tuple(b): i for i, b in enumerate(blocks.tolist())}
    offsets = np.indices((3, 3, 3)).reshape(3, -1).T - 1
    expected = [[slot.get(tuple(b + d), -1) for d in offsets] for b in blocks]
    np.testing.assert_array_equal(synthesis._neighbor_table(keys, blocks), expected)


def _mask_radius(half: int, passes: int, subpasses: int) -> int:
    """The dependency radius measured on :func:`dependency_mask` grids, one voxel of each
    parity class dilated through every step."""
    steps = correction_steps(passes, subpasses)
    reach = len(steps) * half
    n = 2 * reach + 3
    worst = 0
    for parity in range(8):
        desired = np.zeros((n, n, n), bool)
        c = reach + np.array([parity & 1, (parity >> 1) & 1, (parity >> 2) & 1])
        desired[tuple(c)] = True
        hit = np.argwhere(dependency_mask(desired, half, steps))
        worst = max(worst, int(np.abs(hit - c).max()))
    return worst


@pytest.mark.parametrize("half,passes,subpasses",
                         [(2, 2, 1), (3, 1, 1), (2, 0, 8), (1, 3, 8), (2, 1, 8), (2, 2, 8),
                          (3, 1, 8), (4, 2, 1)])
def test_dependency_radius_is_the_masks_extent(half, passes, subpasses):
    """dependency_radius follows parity classes instead of dilating grids: it must
    reach exactly as far as the masks do, sub-passes' chains included."""
    assert dependency_radius(half, passes, subpasses) == _mask_radius(half, passes, subpasses)


def _corrected(desired: np.ndarray, steps: list[int]) -> np.ndarray:
    """Voxels corrected by some step: the ones each step's mask holds in its class
    (grid indices of the same parity as the voxel coordinates)."""
    idx = np.indices(desired.shape)
    parity = (idx[0] & 1) + 2 * (idx[1] & 1) + 4 * (idx[2] & 1)
    corrected = np.zeros_like(desired)
    for k, step in enumerate(steps):
        need = dependency_mask(desired, 2, steps[k + 1 :])
        corrected |= need if step < 0 else need & (parity == step)
    return corrected


def _inside(mask: np.ndarray) -> bool:
    """Whether ``mask`` stays off its grid's faces (grown no farther than the grid)."""
    return not any(np.take(mask, i, axis=a).any() for a in range(3) for i in (0, -1))


@pytest.mark.parametrize(("subpasses", "extent"), [(1, 1), (8, 1), (1, 13), (8, 13)])
def test_levels_correct_exactly_the_dependency_mask(candidates, subpasses, extent):
    """Section 5.2 voxel-exact: a requested voxel, or a box of ``extent``^3 off the blocks'
    grid (whose inner blocks the engine does not spread the mask from), makes the finest
    level correct only the voxels of its dependency mask, and the next level only those
    its parents need, not whole padded blocks."""
    syn = Synthesizer(candidates, seed=2, subpasses=subpasses)
    steps = correction_steps(syn.passes, subpasses)
    # Grids just large enough for the masks, which must not reach their faces.
    room = dependency_radius(2, syn.passes, subpasses) + extent + 2
    half = room + room % 2
    n = 2 * half + 1
    origin = 100 - half  # even, so grid parity is voxel parity
    desired = np.zeros((n, n, n), bool)
    corner = np.array([half + 1, half - extent // 2, half + 1])  # odd, even, odd: parity 5
    desired[tuple(slice(c, c + extent) for c in corner)] = True
    corrected = _corrected(desired, steps)
    syn.triples(np.argwhere(desired) + origin)
    assert syn.voxels_synthesized[syn.finest] == int(corrected.sum())
    if subpasses == 1 and extent == 1:
        assert int(corrected.sum()) == 5 * 5 * 3 - 3 * 5 + 1  # one 3-neighbourhood
    # The parents of every voxel the finest level reads, on an even-aligned coarse grid.
    mask = dependency_mask(desired, 2, steps)
    assert _inside(mask)
    parents = np.unique((np.argwhere(mask) + origin) >> 1, axis=0)
    base = (parents.min(axis=0) - room) & ~1
    coarse = np.zeros(tuple(parents.max(axis=0) - base + room + 1), bool)
    coarse[tuple((parents - base).T)] = True
    assert _inside(dependency_mask(coarse, 2, steps))
    assert syn.voxels_synthesized[syn.finest - 1] == int(_corrected(coarse, steps).sum())


def test_a_block_is_enclosed_only_when_all_27_blocks_around_are_present_and_full():
    """The mask is not spread from an enclosed block's voxels (section 5.2's masks, fewer
    writes): a correction reads up to one block away, along edges too, so one partial
    edge-diagonal block or one absent block around it must keep its voxels spreading.
    Boxes, whose masks stay convex, never leave just such a block out."""
    blocks = np.indices((3, 3, 3)).reshape(3, -1).T - 1
    order = np.argsort(pack(blocks))
    keys, blocks = pack(blocks)[order], blocks[order]
    centre = int(np.flatnonzero((blocks == 0).all(axis=1))[0])
    table = synthesis._neighbor_table(keys, blocks)
    need = np.ones(len(keys) * 64, np.uint8)
    assert synthesis._enclosed(need, table)[centre]
    edge = int(np.flatnonzero((blocks == (1, 1, 0)).all(axis=1))[0])
    need[edge * 64] = 0
    assert not synthesis._enclosed(need, table)[centre]
    # A corner block missing: the table says -1 there, whatever the last block holds.
    kept = ~(blocks == (1, 1, 1)).all(axis=1)
    table = synthesis._neighbor_table(keys[kept], blocks[kept])
    centre = int(np.flatnonzero((blocks[kept] == 0).all(axis=1))[0])
    assert not synthesis._enclosed(np.ones(kept.sum() * 64, np.uint8), table)[centre]


def test_box_layout_matches_voxels(candidates):
    syn = Synthesizer(candidates, seed=6)
    box = syn.box((-3, 4, 10), (5, 6, 7))
    assert box.shape == (5, 6, 7, 3)
    pts = np.array([[-3, 4, 10], [1, 9, 16], [0, 5, 12]])
    assert np.array_equal(box[[0, 4, 3], [0, 5, 1], [0, 6, 2]], syn.voxels(pts))


def test_a_non_square_exemplar_keeps_rows_and_columns_apart(granite_32x48, warp_device):
    wide = precompute(granite_32x48, cache=False)
    syn = Synthesizer(wide, seed=2)
    box = syn.box((-6, -6, -6), (12, 12, 12))
    pts = np.array([[3, 5, -2], [-6, 0, 4], [5, -6, 5]])
    alone = np.concatenate([Synthesizer(wide, seed=2).voxels(p[None]) for p in pts])
    assert np.array_equal(alone, box[pts[:, 0] + 6, pts[:, 1] + 6, pts[:, 2] + 6])
    grid = np.stack(np.meshgrid(*[np.arange(-6, 6)] * 3, indexing="ij"), -1).reshape(-1, 3)
    tri = syn.triples(grid)
    assert (tri[..., 0] >= 0).all() and (tri[..., 0] < 32).all()
    assert (tri[..., 1] >= 0).all() and (tri[..., 1] < 48).all()
    assert (tri[..., 1] >= 32).any()  # columns beyond the height are reached
    col = wide.colors[0]
    expected = (col[tri[:, 0, 0], tri[:, 0, 1]] + col[tri[:, 1, 0], tri[:, 1, 1]])
    expected = (expected + col[tri[:, 2, 0], tri[:, 2, 1]]) / np.float32(3)
    assert np.array_equal(box.reshape(-1, 3), expected.astype(np.float32))


def test_bad_requests_are_clear(candidates):
    syn = Synthesizer(candidates)
    with pytest.raises(ValueError, match="integer"):
        syn.voxels(np.zeros((3, 3), np.float32))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        syn.voxels(np.zeros((3, 2), np.int64))
    with pytest.raises(ValueError, match="within"):
        syn.voxels(np.array([[COORD_LIMIT, 0, 0]]))
    # Python ints past int64 became objects or floats, and the error spoke of their type.
    for far in ([[2**64, 0, 0]], [[2**63, 0, 0]], [(0, -(2**70), 1)]):
        with pytest.raises(ValueError, match=r"must lie within \["):
            syn.voxels(far)
    with pytest.raises(ValueError, match="integer array, got float64"):
        syn.voxels([[0.5, 0, 0]])
    # NumPy makes a bool among ints 0 or 1, a voxel nobody named; ragged rows failed in
    # NumPy's words, which name no argument.
    for flagged in ([[True, 1, 2]], [(np.True_, 0, 5)]):
        with pytest.raises(ValueError, match="must be integers, got booleans among them"):
            syn.voxels(flagged)
    with pytest.raises(ValueError, match=r"voxel coordinates must be an \(N, 3\) integer "
                                         r"array, got rows of other lengths"):
        syn.voxels([[1, 2, 3], [4, 5]])
    assert syn.voxels(np.zeros((0, 3), np.int64)).shape == (0, 3)
    # Beyond int64, and an empty box too long to be an array: the range names both.
    for origin, shape in (((10**20, 0, 0), (1, 1, 1)), ((0, 0, 0), (0, 10**30, 10**30)),
                          ((COORD_LIMIT - 1, 0, 0), (2, 1, 1)),
                          ((-COORD_LIMIT - 1, 0, 0), (1, 1, 1))):
        with pytest.raises(ValueError, match=rf"a box at origin .* of shape .* leaves the voxel "
                                             rf"coordinates' range \[-{COORD_LIMIT}, "):
            syn.box(origin, shape)
    assert syn.box((COORD_LIMIT - 1, -COORD_LIMIT, 0), (1, 1, 0)).shape == (1, 1, 0, 3)
    with pytest.raises(ValueError, match="subpasses"):
        Synthesizer(candidates, subpasses=4)
    with pytest.raises(ValueError, match="jitter"):
        Synthesizer(candidates, jitter=-1.0)
    for passes in (-1, 9):
        with pytest.raises(ValueError, match=r"passes must be within \[0, 8\]"):
            Synthesizer(candidates, passes=passes)
    with pytest.raises(ValueError, match="levels must be at least 0, got -1"):
        Synthesizer(candidates, levels=-1)
    # Once truncated (2.5), or a raw comparison error (None), or kept (-1).
    for name, value in (("levels", 2.5), ("levels", None), ("coarse_cache_bytes", "1")):
        with pytest.raises(ValueError, match=f"{name} must be an integer"):
            Synthesizer(candidates, **{name: value})
    with pytest.raises(ValueError, match="coarse_cache_bytes must be at least 0"):
        Synthesizer(candidates, coarse_cache_bytes=-1)
    for seed in (-1, 2**31):  # once kept to their low 31 bits: aliases of other seeds
        with pytest.raises(ValueError, match=r"seed must be within \[0, 2147483647\]"):
            Synthesizer(candidates, seed=seed)
    wide = dataclasses.replace(candidates, params={**candidates.params, "neighborhood": 11})
    with pytest.raises(ValueError, match="neighbourhoods of more than 9 voxels"):
        Synthesizer(wide)


def test_candidates_no_synthesis_could_use_are_refused_before_they_are_computed(monkeypatch):
    import warptex.candidates

    def computed(*args):
        raise AssertionError("pre-computed candidates the engine refuses")

    monkeypatch.setattr(warptex.candidates, "_compute", computed)
    many = Exemplar(np.random.default_rng(0).random((16, 16, 35), np.float32), name="wide")
    with pytest.raises(ValueError, match=r"^wide: 35 feature channels are too many .* \(at most "
                                         r"34\)"):
        precompute(many, cache=False)
    with pytest.raises(ValueError, match=r"35 feature channels .* \(at most 19\)"):
        precompute(many, cache=False, neighborhood=9)
    # The most it names is taken: 34 channels reach the pre-computation.
    most = Exemplar(np.random.default_rng(0).random((16, 16, 34), np.float32), name="most")
    with pytest.raises(AssertionError, match="pre-computed candidates the engine refuses"):
        precompute(most, cache=False)


def test_candidate_counts_reach_the_search(granite_32, candidates):
    """Synthesis searches every 2D and 3D candidate the set keeps, but the paper's 4 3D
    candidates at the finest level (section 5.1); more candidates give another texture."""
    more = precompute(granite_32, cache=False, candidates_2d=6, candidates_3d=16)
    syn = Synthesizer(more, seed=3)
    assert [syn._tables[lv].k2 for lv in (syn.start, syn.finest)] == [6, 2]
    assert [syn._tables[lv].k3 for lv in (syn.start, syn.finest)] == [16, 4]
    box = syn.box((-5, 3, 7), (8, 8, 8))
    assert not np.array_equal(box, Synthesizer(candidates, seed=3).box((-5, 3, 7), (8, 8, 8)))


@pytest.fixture(scope="module")
def three_granites(data_dir, warp_device) -> CandidateSet:
    """Candidates of three different 32x32 granite crops, one per axis, taken as photos
    that do not tile: their candidates keep margins."""
    base = Exemplar.load(data_dir / "granite_64.png").colors
    exs = [Exemplar(np.ascontiguousarray(base[i * 16 : i * 16 + 32, :32])) for i in range(3)]
    return precompute(*exs, cache=False, tileable=False)


def test_three_different_exemplars(three_granites):
    cs = three_granites
    assert len(cs.roles[0]) == 3
    syn = Synthesizer(cs, seed=2)
    box = syn.box((0, 0, 0), (8, 8, 8))
    assert np.isfinite(box).all()
    assert np.array_equal(box[3, 4, 5], Synthesizer(cs, seed=2).voxels(np.array([[3, 4, 5]]))[0])


@pytest.fixture(scope="module")
def granite(data_dir, warp_device) -> tuple[Exemplar, CandidateSet]:
    ex = Exemplar.load(data_dir / "granite_64.png")
    return ex, precompute(ex, cache=False)


def test_quality_beats_noise_and_extrusion(granite):
    """Section 6.3: slices look like the exemplar along all three axes."""
    ex, cs = granite
    vol = Synthesizer(cs, seed=3).box((0, 0, 0), (48, 48, 48))
    colors = ex.colors
    ours = [metrics.neighborhood_energy(vol, colors, a) for a in range(3)]
    noise = metrics.iid_noise(colors, vol.shape[:3])
    worst_noise = min(metrics.neighborhood_energy(noise, colors, a) for a in range(3))
    stacked = metrics.extrusion(colors[:48, :48], 48, axis=2)
    worst_stacked = metrics.worst_axis_energy(stacked, colors)
    assert max(ours) < 0.6 * worst_noise
    assert max(ours) < worst_stacked


def in_plane_coherence(triples: np.ndarray, heights: list[int], widths: list[int]) -> float:
    """Share of neighbouring voxel pairs, within the planes of each axis k, whose exemplar
    k pixels are neighbours too (the pair continues one exemplar patch)."""
    shares = []
    for k in range(3):
        pix = triples[..., k, :]
        for axis, step in (((k + 1) % 3, (1, 0)), ((k + 2) % 3, (0, 1))):
            diff = np.diff(pix, axis=axis)
            rows = (diff[..., 0] - step[0]) % heights[k] == 0
            cols = (diff[..., 1] - step[1]) % widths[k] == 0
            shares.append(np.mean(rows & cols))
    return float(np.mean(shares))


def test_shifted_neighbour_triples_continue_exemplar_patches(granite):
    """Each voxel may take an in-plane neighbour's triple, shifted: neighbouring voxels
    then continue one exemplar patch in a good share of pairs (about 5% without)."""
    _, cs = granite
    size = 24
    grid = np.indices((size,) * 3).reshape(3, -1).T
    shape = cs.sources[-1][0].size
    triples = Synthesizer(cs, seed=3).triples(grid).reshape(size, size, size, 3, 2)
    assert in_plane_coherence(triples, [shape[0]] * 3, [shape[1]] * 3) > 0.09


@pytest.fixture(scope="module")
def ramp(warp_device) -> Exemplar:
    """A noisy ramp from left to right: its left and right edges form a seam."""
    rng = np.random.default_rng(4)
    ramp = np.linspace(0.0, 1.0, 32)[None, :, None] + 0.1 * rng.random((32, 32, 3))
    return Exemplar(ramp.astype(np.float32), name="ramp")


@pytest.mark.parametrize("along", ["columns", "rows"])
def test_a_photo_that_does_not_tile_never_has_its_seam_continued(ramp, along):
    """A ramp's left and right edges differ (and, turned, its top and bottom). As a torus
    (``tileable=True``, the paper's exemplars) the texture continues patches across that
    seam into the pixels next to it; by default no voxel takes the N // 2 columns (rows)
    at either edge, so no patch crosses the seam: shifted neighbour triples stop at the
    margins, as candidates do."""
    exemplar = ramp if along == "columns" else Exemplar(
        np.ascontiguousarray(ramp.colors.transpose(1, 0, 2)), name="turned ramp")
    grid = np.indices((20, 20, 20)).reshape(3, -1).T - 10
    index = 1 if along == "columns" else 0
    pixels = {tileable: Synthesizer(precompute(exemplar, cache=False, tileable=tileable),
                                    seed=1).triples(grid)[:, :, index]
              for tileable in ("auto", True)}
    half = 2  # of the default 5 x 5 neighbourhoods
    in_margin = {k: (c < half) | (c >= 32 - half) for k, c in pixels.items()}
    assert in_margin[True].mean() > 0.02
    assert not in_margin["auto"].any()


@pytest.mark.skipif(
    "not __import__('warp').get_cuda_device_count()", reason="no CUDA device: CPU-only machine"
)
@pytest.mark.parametrize("subpasses", [1, 8])
def test_cpu_and_cuda_agree_bit_for_bit(candidates, subpasses):
    rng = np.random.default_rng(7)
    n = 500 if subpasses == 1 else 50  # 8 sub-passes take about 50x the time per voxel
    far = rng.integers(COORD_LIMIT - 50, COORD_LIMIT, (n // 10, 3))
    pts = np.concatenate([_random_voxels(rng, n), far * rng.choice([-1, 1], far.shape)])
    kw = {"seed": 8, "subpasses": subpasses}
    cpu, cuda = (Synthesizer(candidates, device=d, **kw) for d in ("cpu", "cuda"))
    assert np.array_equal(cpu.voxels(pts), cuda.voxels(pts))
    if subpasses == 1:  # over 8192 blocks: the GPU gathers halos in several chunks
        assert np.array_equal(cpu.box((-40, 0, 0), (96, 96, 96)),
                              cuda.box((-40, 0, 0), (96, 96, 96)))


@pytest.mark.skipif(
    "not __import__('warp').get_cuda_device_count()", reason="no CUDA device: CPU-only machine"
)
@pytest.mark.parametrize("shifted_tiles", [False, True])
def test_cpu_and_cuda_agree_where_candidates_keep_margins(ramp, shifted_tiles):
    """The margins' test in the correction kernel (exemplars that do not tile), with and
    without shifted tiles."""
    candidates = precompute(ramp, cache=False)
    assert candidates.sources[-1][0].margins == (0, 2)
    pts = _random_voxels(np.random.default_rng(9), 400)
    cpu, cuda = (Synthesizer(candidates, device=d, seed=2, shifted_tiles=shifted_tiles)
                 for d in ("cpu", "cuda"))
    assert np.array_equal(cpu.triples(pts), cuda.triples(pts))


def test_more_passes_change_the_texture_and_stay_deterministic(candidates):
    from warptex.texture import SolidTexture

    pts = np.array([[3, -4, 5], [11, 0, -7]])
    three = Synthesizer(candidates, seed=2, passes=3)
    box = three.box((0, -8, -10), (16, 12, 20))
    assert np.array_equal(Synthesizer(candidates, seed=2, passes=3).voxels(pts[:1])[0],
                          box[3, 4, 15])
    assert np.array_equal(three.voxels(pts[1:])[0], box[11, 8, 3])
    assert not np.array_equal(Synthesizer(candidates, seed=2).box((0, -8, -10), (16, 12, 20)),
                              box)
    tex = SolidTexture(candidates, seed=2, passes=3)
    assert np.array_equal(tex.query(pts + 0.5, filter="nearest"), three.voxels(pts))


def test_a_box_larger_than_the_memory_is_refused_before_any_work(candidates, monkeypatch):
    """As the commands do: a box whose request would not fit is one clear error, where
    NumPy's MemoryError (or the system's out-of-memory killer) came half-way."""
    import warptex.machine
    from warptex.texture import SolidTexture

    syn = Synthesizer(candidates)
    monkeypatch.setattr(warptex.machine, "physical_memory", lambda: 1 << 30)
    with pytest.raises(ValueError, match=r"a box of shape \(1024, 1024, 400\) needs about "
                       r"\d+ GiB, this machine has 1 GiB; synthesize it in parts"):
        syn.box((0, 0, 0), (1024, 1024, 400))
    assert syn.box((0, 0, 0), (2, 2, 2)).shape == (2, 2, 2, 3)
    tex = SolidTexture(candidates, device="cpu")
    with pytest.raises(ValueError, match=r"a slice of shape \(40000, 40000\) needs about"):
        tex.slice((0, 0, 0), (1, 0, 0), (0, 1, 0), (40000, 40000))
    # Pixels far apart each bring the whole bricks of their corners: 32 x 32 of them read
    # 4M voxels at once, which the slice's estimate counted as 1024.
    monkeypatch.setattr(warptex.machine, "physical_memory", lambda: 64 << 20)
    with pytest.raises(ValueError, match=r"a slice of shape \(32, 32\) needs about 40\d MiB"):
        tex.slice((0.5, 0.5, 0.5), (64, 0, 0), (0, 64, 0), (32, 32))
    near = SolidTexture(candidates, device="cpu", whole_bricks=False)
    assert near.slice((0.5, 0.5, 0.5), (64, 0, 0), (0, 64, 0), (32, 32), "nearest").shape == (
        32, 32, 3)


def test_every_setting_keeps_its_work_within_the_keys_margin():
    """Requests stay _KEY_MARGIN blocks inside the keys' range so that a work region grown by
    its apron (and a block of halo) never wraps around: the largest apron of any setting the
    engine takes (neighbourhoods up to 2 * BLOCK + 1, MAX_PASSES passes, 1 or 8 sub-passes)
    fits, so no setting needs refusing for it."""
    from warptex.settings import MAX_PASSES

    largest = max(apron_blocks(half, passes, subpasses) for half in range(synthesis.BLOCK + 1)
                  for passes in range(MAX_PASSES + 1) for subpasses in (1, 8))
    assert largest + 2 <= synthesis._KEY_MARGIN


def test_a_boxs_memory_counts_the_apron_of_its_passes(candidates, monkeypatch):
    """A box's estimate took the apron of the default passes, whatever the engine's: with 8
    passes of 8 sub-passes a box that voxels() refused ran."""
    import warptex.machine
    from warptex.synthesis import box_bytes

    # Parts as large as a GPU of memory to spare takes: on the CPU the engine's parts are
    # kept to half the memory, one block's work at least (the next tests).
    monkeypatch.setattr(synthesis, "work_voxel_cap", lambda *args: synthesis.MAX_WORK_VOXELS)
    syn = Synthesizer(candidates, passes=8, subpasses=8)
    shape = (64, 64, 64)
    colors = 4 * candidates.channels * 64**3
    memory = (box_bytes(shape) + box_bytes(shape, syn._apron)) // 2 + colors
    assert box_bytes(shape) + colors < memory < box_bytes(shape, syn._apron) + colors
    monkeypatch.setattr(warptex.machine, "physical_memory", lambda: memory)
    monkeypatch.setattr(syn, "_pixel_triples", lambda voxels: pytest.fail("the box ran"))
    with pytest.raises(ValueError, match=r"a box of shape \(64, 64, 64\) needs about"):
        syn.box((0, 0, 0), shape)


def test_voxels_and_triples_beyond_the_memory_are_refused_before_any_work(candidates,
                                                                          monkeypatch):
    """The README says so of voxels() as of box(); only box() checked, so scattered points
    ran, each with its block and apron."""
    import warptex.machine
    from warptex.synthesis import (
        BLOCK,
        DILATED_KEY_BYTES,
        REQUEST_BYTES_PER_VOXEL,
        request_bytes,
        work_bytes_per_voxel,
    )

    monkeypatch.setattr(synthesis, "work_voxel_cap", lambda *args: synthesis.MAX_WORK_VOXELS)
    syn = Synthesizer(candidates)
    points = np.random.default_rng(5).integers(-1000, 1000, (4096, 3))
    monkeypatch.setattr(warptex.machine, "physical_memory", lambda: request_bytes(points) - 1)
    for ask in (syn.voxels, syn.triples):
        with pytest.raises(ValueError, match=r"a request of 4096 voxels needs about \d+ [GM]iB, "
                           r"this machine has \d+ [GM]iB; synthesize them in parts"):
            ask(points)
    assert sum(syn.voxels_synthesized.values()) == 0
    # Close together, as many voxels take far less: one block and its apron.
    near = np.argwhere(np.ones((16, 16, 16), bool))[:4096]
    assert request_bytes(near) < request_bytes(points) / 20
    # More passes read farther: a wider apron around each block.
    assert request_bytes(points[:8], apron_blocks=2) > request_bytes(points[:8])
    assert syn.voxels(near).shape == (4096, 3)
    # Each of two far voxels: its arrays, its block's 27 dilated keys, its block and apron.
    far = np.array([[-COORD_LIMIT] * 3, [COORD_LIMIT - 1] * 3])  # a box of 2^69 voxels
    assert request_bytes(far) == 2 * (REQUEST_BYTES_PER_VOXEL + 27 * DILATED_KEY_BYTES
                                      + (3 * BLOCK) ** 3 * work_bytes_per_voxel())
    # Scattered voxels' dilated keys (measured 744-997 bytes a voxel in all, the engine's
    # work apart) are counted; a box's blocks hold many voxels each, so its keys count for
    # little.
    scattered = np.random.default_rng(6).integers(-COORD_LIMIT, COORD_LIMIT, (100_000, 3))
    work = synthesis.MAX_WORK_VOXELS * work_bytes_per_voxel()
    assert request_bytes(scattered) - work >= 997 * len(scattered)
    box = np.argwhere(np.ones((64, 64, 64), bool))
    assert request_bytes(box) - len(box) * REQUEST_BYTES_PER_VOXEL < 2 * 80**3 * 280
    # Exemplars of more feature channels take more memory a work voxel.
    assert request_bytes(points, channels=34) > request_bytes(points)


def test_requests_are_estimated_in_the_parts_the_engine_works_in(candidates, monkeypatch):
    """voxels(), triples() and box() counted a request's work as MAX_WORK_VOXELS whatever
    the parts the engine keeps to where memory is small (work_voxel_cap): on a 120 MiB
    machine they refused what the engine does in parts."""
    import warptex.machine
    from warptex.synthesis import box_bytes, request_bytes, work_voxel_cap

    points = np.random.default_rng(5).integers(-1000, 1000, (512, 3))
    shape = (64, 64, 64)
    reference = Synthesizer(candidates)
    expected = reference.voxels(points), reference.triples(points)
    box = reference.box((0, 0, 0), shape)
    memory = 120 << 20
    monkeypatch.setattr(warptex.machine, "physical_memory", lambda: memory)
    synthesis._host_memory.cache_clear()
    cap = work_voxel_cap("cpu")
    assert request_bytes(points) > memory > request_bytes(points, work_cap=cap) + (1 << 20)
    colors = 4 * candidates.channels * 64**3
    assert box_bytes(shape) + colors > memory > box_bytes(shape, work_cap=cap) + colors
    syn = Synthesizer(candidates)
    np.testing.assert_array_equal(syn.voxels(points), expected[0])
    np.testing.assert_array_equal(syn.triples(points), expected[1])
    np.testing.assert_array_equal(syn.box((0, 0, 0), shape), box)


def test_a_part_is_estimated_at_one_block_at_least(candidates, monkeypatch):
    """The engine splits no part below one block, whose work with 8 passes of 8 sub-passes
    (an apron of 17 blocks) is 2.7M voxels: estimated at a 512 MiB machine's cap instead, one
    voxel was accepted, and grew the process by 1.6 GB."""
    import warptex.machine
    from warptex.synthesis import BLOCK, request_bytes, work_bytes_per_voxel

    syn = Synthesizer(candidates, passes=8, subpasses=8)
    block = (BLOCK + 2 * syn._apron * BLOCK) ** 3
    one = np.zeros((1, 3), np.int64)
    assert request_bytes(one, syn._apron, work_cap=1) >= block * work_bytes_per_voxel()
    memory = 512 << 20
    assert block * work_bytes_per_voxel() > memory
    monkeypatch.setattr(warptex.machine, "physical_memory", lambda: memory)
    synthesis._host_memory.cache_clear()
    monkeypatch.setattr(syn, "_pixel_triples", lambda voxels: pytest.fail("it ran"))
    with pytest.raises(ValueError, match=r"a request of 1 voxels needs about"):
        syn.voxels(one)
    with pytest.raises(ValueError, match=r"a box of shape \(1, 1, 1\) needs about"):
        syn.box((0, 0, 0), (1, 1, 1))


def test_more_correction_steps_count_more_memory_a_work_voxel(candidates, monkeypatch):
    """Each correction step lists the voxels it corrects: a work voxel took 603 bytes at 8
    passes of 8 sub-passes, where 280 were counted, so one voxel's block, estimated at 688
    MiB, grew the process by 1.6 GB (BENCHMARKS.md, "Memory of a request")."""
    import warptex.machine
    from warptex.synthesis import request_bytes, work_bytes_per_voxel

    assert work_bytes_per_voxel(3, 8) >= 325 and work_bytes_per_voxel(3, 32) >= 405
    assert work_bytes_per_voxel(3, 64) >= 603 and work_bytes_per_voxel(3, 1) == 280
    deep = Synthesizer(candidates, passes=8, subpasses=8)
    one = np.zeros((1, 3), np.int64)
    counted = request_bytes(one, deep._apron, steps=64)
    memory = (request_bytes(one, deep._apron) + counted) // 2  # between 2 steps' and 64's
    monkeypatch.setattr(warptex.machine, "physical_memory", lambda: memory)
    synthesis._host_memory.cache_clear()
    monkeypatch.setattr(deep, "_pixel_triples", lambda voxels: pytest.fail("it ran"))
    with pytest.raises(ValueError, match=r"a request of 1 voxels needs about"):
        deep.voxels(one)


def _slab_tiling(candidates: CandidateSet, level: int, vox: np.ndarray) -> np.ndarray:
    """Triples (N, 3, 2) of the start level without jitter or correction: the x exemplar's
    pixel under each voxel and that pixel's first 3D candidate, its two other coordinates
    moved along the slab's depth (x): the column of the y exemplar, the row of the z one,
    each wrapped at its own exemplar's size."""
    n = int(candidates.params["neighborhood"])
    (h, w), (_, wy), (hz, wz) = _sizes(candidates, level)
    own = (vox[:, 1] % h) * w + vox[:, 2] % w
    first = candidates.roles[level][0].cand[own, 0, :]  # pixels of the y and z exemplars
    depth = vox[:, 0] % n - n // 2
    return np.stack([np.stack([vox[:, 1] % h, vox[:, 2] % w], 1),
                     np.stack([first[:, 0] // wy, (first[:, 0] % wy + depth) % wy], 1),
                     np.stack([(first[:, 1] // wz + depth) % hz, first[:, 1] % wz], 1)], 1)


@pytest.mark.parametrize("which", ["candidates", "wide_candidates", "mixed_candidates"])
def test_upsampling_inherits_twice_the_parents_coordinates_plus_the_childs_offset(request,
                                                                                  which):
    """Section 5.1, "Upsampling": child v of parent v >> 1 holds, in exemplar k, twice the
    parent's pixel plus v's offset within its parent along the axes (k+1, k+2) that
    exemplar spans, wrapped at its child level's size. Without correction the finest level
    is exactly the start level's tiling, upsampled."""
    candidates = request.getfixturevalue(which)
    syn = Synthesizer(candidates, jitter=0.0, passes=0, levels=1)
    assert syn.start == syn.finest - 1
    vox = np.indices((6, 6, 6)).reshape(3, -1).T + np.array([-3, 17, -40])
    parent = _slab_tiling(candidates, syn.start, vox >> 1)
    offset = np.stack([np.stack([vox[:, (k + 1) % 3] & 1, vox[:, (k + 2) % 3] & 1], 1)
                       for k in range(3)], 1)
    expected = (2 * parent + offset) % _sizes(candidates, syn.finest)
    np.testing.assert_array_equal(syn.triples(vox), expected)


def test_correction_brings_a_banded_exemplars_slices_closer_to_it(data_dir, warp_device):
    """Section 5.1: correction passes replace each triple by its best candidate over all
    three planes, so a corrected texture's slices match the exemplar better than the
    start level's tiling, merely upsampled. Banded onyx, unlike granite, tells them apart
    clearly (0.12 against 0.16); picking worse candidates, skipping a pass or never
    offering 3D candidates brings the corrected one back to 0.16 or more."""
    ex = Exemplar.load(data_dir / "onyx_banded_64.png")
    cs = precompute(ex, cache=False)
    energy = {passes: [metrics.neighborhood_energy(
        Synthesizer(cs, seed=3, passes=passes).box((0, 0, 0), (32, 32, 32)), ex.colors, a)
        for a in range(3)] for passes in (0, 2)}
    assert max(energy[2]) < 0.85 * min(energy[0])


def _plane_offset(k: int, a: int, b: int) -> np.ndarray:
    """Volume offset of pixel offset (a, b) in the plane of axis k, whose exemplar spans
    volume axes (k+1, k+2) as its rows and columns (kernels' ``plane_offset``)."""
    d = np.zeros(3, int)
    d[(k + 1) % 3], d[(k + 2) % 3] = a, b
    return d


def _plane_projection(feat_at, basis: np.ndarray, shift: int, half: int, k: int) -> np.ndarray:
    """NumPy reference of section 5.1's appearance vector of one plane: the N x N
    neighbourhood of the plane of axis k (volume axes (k+1, k+2) as the exemplar's rows and
    columns), in (a, b, channel) order, times the PCA basis, shifted and clamped as the
    kernels store it. ``feat_at(d)`` gives the features at volume offset ``d``."""
    rows = []
    for a in range(-half, half + 1):
        for b in range(-half, half + 1):
            rows.append(feat_at(_plane_offset(k, a, b)))
    acc = basis.astype(np.int64) @ np.concatenate(rows).astype(np.int64)
    return np.clip(acc >> shift, -_k.PROJ_LIMIT, _k.PROJ_LIMIT)


def test_the_reference_projection_of_a_slice_is_its_exemplar_pixels(candidates):
    """The reference below reads plane k as the candidates read exemplar k: a volume
    extruded along axis k from (three times) exemplar k projects to the exemplar's own
    pixels' projections."""
    source = candidates.sources[-1][candidates.axis_source[0]]
    h, w = source.size
    half = int(candidates.params["neighborhood"]) // 2
    feat = 3 * source.feat.astype(np.int64)
    for k in range(3):
        for u, v in [(0, 0), (5, 17), (h - 1, 3), (20, w - 1)]:
            pos = _plane_offset(k, u, v)

            def feat_at(d, pos=pos, k=k):
                p = pos + d
                return feat[p[(k + 1) % 3] % h, p[(k + 2) % 3] % w]

            expected = source.proj[u * w + v]
            got = _plane_projection(feat_at, source.basis, source.shift, half, k)
            np.testing.assert_array_equal(got[: len(expected)], expected)


@dataclasses.dataclass
class _Step:
    """What one correction step read and wrote, copied (on the CPU, ``numpy()`` shares
    memory that later steps overwrite)."""

    level: int
    listed: np.ndarray  # flat work voxels the step corrected
    nbr: np.ndarray  # the work blocks' neighbour table
    before: np.ndarray  # (voxels, 3) triples the step read
    after: np.ndarray  # (voxels, 3) triples it wrote
    qproj: np.ndarray  # (voxels, 3, MAX_DIMS) its projections of the listed voxels

    def neighbor(self, i: int, d: np.ndarray) -> int:
        """Flat index of the voxel at offset ``d`` from voxel ``i``, -1 if absent."""
        block, own = divmod(int(i), 64)
        p = synthesis._LOCAL[own] + d
        b = (p >> 2) + 1
        slot = self.nbr[block, b[0] * 9 + b[1] * 3 + b[2]]
        q = p & 3
        return -1 if slot < 0 else int(slot) * 64 + int(q[0] * 16 + q[1] * 4 + q[2])

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return rng.choice(self.listed, size=min(n, len(self.listed)), replace=False)


def _correction_steps_of(cs: CandidateSet, monkeypatch) -> tuple[Synthesizer, list[_Step]]:
    syn = Synthesizer(cs, seed=4)
    steps: list[_Step] = []
    original = Synthesizer._correct_step

    def spy(self, listed, voxels, nbr, src, feats, t, qproj, dst):
        original(self, listed, voxels, nbr, src, feats, t, qproj, dst)
        level = next(lv for lv, tables in self._tables.items() if tables is t)
        steps.append(_Step(level, listed.copy(), nbr.numpy().copy(), src.numpy().copy(),
                           dst.numpy().copy(),
                           qproj.numpy().reshape(-1, 3, _k.MAX_DIMS).copy()))

    monkeypatch.setattr(Synthesizer, "_correct_step", spy)
    syn.voxels(np.array([[3, -2, 7], [30, 31, 29]]))
    assert {step.level for step in steps} == set(range(syn.start, syn.finest + 1))
    return syn, steps


@pytest.mark.parametrize("exemplars", ["candidates", "three_granites"])
def test_corrections_project_each_plane_as_the_reference_does(exemplars, request, monkeypatch):
    """Every voxel a correction step lists gets, in each of its three planes, exactly the
    reference's projection of its current neighbourhood (features: the sum of its triple's
    three exemplar features; absent neighbours read as the voxel itself). A plane read
    along swapped axes, or (with three exemplars) with another plane's basis, differs."""
    cs = request.getfixturevalue(exemplars)
    _, steps = _correction_steps_of(cs, monkeypatch)
    rng = np.random.default_rng(0)
    half = int(cs.params["neighborhood"]) // 2
    for step in steps:
        sources = [cs.sources[step.level][cs.axis_source[k]] for k in range(3)]
        flat_feat = [s.feat.reshape(-1, s.feat.shape[2]).astype(np.int64) for s in sources]
        for i in step.sample(20, rng):

            def feat_at(d, i=i, step=step, flat_feat=flat_feat):
                j = step.neighbor(i, d)
                tri = step.before[i if j < 0 else j]
                return sum(flat_feat[k][tri[k]] for k in range(3))

            for k in range(3):
                s = sources[k]
                expected = _plane_projection(feat_at, s.basis, s.shift, half, k)
                np.testing.assert_array_equal(step.qproj[i, k, : len(expected)], expected,
                                              err_msg=f"level {step.level}, voxel {i}, plane {k}")


def _wrapped_step(pix: int, du: int, dv: int, size: tuple[int, int]) -> int:
    u, v = divmod(pix, size[1])
    return (u + du) % size[0] * size[1] + (v + dv) % size[1]


def _reference_correction(cs: CandidateSet, step: _Step, i: int, finest: bool) -> np.ndarray:
    """NumPy reference of section 5.1's correction of voxel ``i``: the triple of least
    3-plane distance among the 3D candidates of each plane's best k-coherent 2D
    candidate and the in-plane neighbours' triples shifted to continue here (those
    clear of the exemplars' margins); the first of equals wins, in the kernel's order."""
    sources = [cs.sources[step.level][cs.axis_source[k]] for k in range(3)]
    roles = [cs.roles[step.level][cs.role_of_axis(k)] for k in range(3)]
    q = step.qproj[i].astype(np.int64)

    def distance(k: int, pix: int) -> int:
        e = sources[k].proj[pix].astype(np.int64) - q[k, : sources[k].proj.shape[1]]
        return int(e @ e)

    own_triple = step.before[i]
    best, best_d = own_triple, None
    for k in range(3):
        own, own_d = None, None
        for da in (-1, 0, 1):
            for db in (-1, 0, 1):
                j = step.neighbor(i, _plane_offset(k, da, db))
                pix = int((step.before[j] if j >= 0 else own_triple)[k])
                p = _wrapped_step(pix, -da, -db, sources[k].size)
                for cand in sources[k].cand2d[p]:
                    dist = distance(k, int(cand))
                    if own is None or dist < own_d:
                        own, own_d = int(cand), dist
        k1, k2 = (k + 1) % 3, (k + 2) % 3
        keep = roles[k].cand.shape[1] if not finest else min(roles[k].cand.shape[1], 4)
        for c in range(min(keep, int(roles[k].count[own]))):
            p1, p2 = (int(x) for x in roles[k].cand[own, c])
            dist = own_d + distance(k1, p1) + distance(k2, p2)
            if best_d is None or dist < best_d:
                best, best_d = np.array([0, 0, 0]), dist
                best[k], best[k1], best[k2] = own, p1, p2
    for k in range(3):
        for a, b in [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)]:
            d = _plane_offset(k, a, b)
            # A face neighbour lies in two planes; the kernel offers it once.
            if (a, b) == (0, 0) or (k == 1 and b == 0) or (k == 2 and 0 in (a, b)):
                continue
            j = step.neighbor(i, d)
            if j < 0:
                continue
            shifted = [_wrapped_step(int(step.before[j][m]), -d[(m + 1) % 3], -d[(m + 2) % 3],
                                     sources[m].size) for m in range(3)]
            clear = all(
                s.margins[0] <= p // s.size[1] < s.size[0] - s.margins[0]
                and s.margins[1] <= p % s.size[1] < s.size[1] - s.margins[1]
                for p, s in zip(shifted, sources, strict=True))
            if clear:
                dist = sum(distance(m, shifted[m]) for m in range(3))
                if best_d is None or dist < best_d:
                    best, best_d = np.array(shifted), dist
    return np.asarray(best)


@pytest.mark.parametrize("exemplars", ["candidates", "three_granites"])
def test_corrections_pick_the_reference_triple(exemplars, request, monkeypatch):
    """Each voxel a correction step lists takes exactly the triple the NumPy reference of
    section 5.1 picks from the step's own projections: 3D candidates put in the wrong
    exemplars, a plane's distance taken in another plane, the finest level's four 3D
    candidates or the shifted neighbours' margins each make them differ."""
    cs = request.getfixturevalue(exemplars)
    syn, steps = _correction_steps_of(cs, monkeypatch)
    rng = np.random.default_rng(1)
    changed = 0
    for step in steps:
        for i in step.sample(40, rng):
            expected = _reference_correction(cs, step, i, step.level == syn.finest)
            np.testing.assert_array_equal(step.after[i], expected,
                                          err_msg=f"level {step.level}, voxel {i}")
            changed += not np.array_equal(step.after[i], step.before[i])
    assert changed > 40  # corrections that keep every triple would test nothing


# The engine's triples of voxels across the origin, per exemplar and setting, at
# ENGINE_VERSION 4: what the engine makes, which no other test pins (a changed start level,
# jitter scale, sub-pass order or tie rule stays deterministic and passes them all). The
# kernels compute in integers and the candidates are the same on every CPU, so these are
# the same on every machine and device. A change that alters them must say so: raise
# ENGINE_VERSION and write the new digests here.
_GOLDEN = {
    ("granite_32", ()): "795ef8f7a454118b",
    ("granite_32", (("subpasses", 8),)): "3cd70528e9c33aff",
    ("granite_32", (("shifted_tiles", True), ("jitter", 1.5), ("seed", 7))): "e7aa76994676850d",
    ("granite_64", ()): "d00e20092ab7d0a5",  # four levels: the start is three above
}


@pytest.mark.parametrize(("exemplar", "settings"), list(_GOLDEN))
def test_the_engine_makes_the_triples_of_its_version(candidates, data_dir, exemplar,
                                                     settings):
    import hashlib

    assert synthesis.ENGINE_VERSION == 4
    if exemplar == "granite_64":
        candidates = precompute(Exemplar.load(data_dir / "granite_64.png"), cache=False)
    voxels = np.concatenate([
        np.random.default_rng(0).integers(-40, 40, (48, 3)),
        np.stack(np.meshgrid(*[np.arange(-2, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)])
    triples = Synthesizer(candidates, **dict(settings)).pixel_triples(voxels)
    digest = hashlib.sha256(np.ascontiguousarray(triples, np.int32).tobytes()).hexdigest()
    assert digest[:16] == _GOLDEN[exemplar, settings]


def test_a_request_counts_its_results_beside_its_work(candidates, monkeypatch):
    """voxels() and triples() ask the machine for the request's work and the arrays they
    make: C float32 colors a voxel, or its triples and the int64 rows, columns and their
    stack on the way (136 bytes)."""
    syn = Synthesizer(candidates)
    ijk = _random_voxels(np.random.default_rng(3), 64)
    asked = []
    monkeypatch.setattr(synthesis, "memory_problem", lambda need: asked.append(need))
    syn.voxels(ijk)
    syn.triples(ijk)
    work = synthesis.request_bytes(ijk, syn._apron, syn._features, syn._work_cap(),
                                   syn._steps)
    assert asked == [work + 64 * 4 * 3, work + 64 * 136]


def test_the_coarse_cache_keeps_every_voxel_a_block_was_given(candidates):
    """A second request whose coarse voxels share blocks with the first's adds to them:
    asking the first again synthesizes nothing above the finest level."""
    syn = Synthesizer(candidates)
    first, second = np.array([[0, 0, 0]]), np.array([[3, 1, 0]])
    syn.voxels(first)
    syn.voxels(second)
    before = dict(syn.voxels_synthesized)
    syn.voxels(first)
    coarse = [lv for lv in before if lv < syn.finest]
    assert coarse and all(syn.voxels_synthesized[lv] == before[lv] for lv in coarse)
