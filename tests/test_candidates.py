"""3D candidate pre-computation (Dong 2008, section 4; issue 3): values, not just shapes.

The crossbar error (4.1) and the coherence test (4.2) are re-implemented here in plain
numpy, independently of the Warp kernels, and compared with what ``precompute`` stored.
Small exemplars (crops of ``tests/data/granite_64.png``) keep the file fast.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import os
import platform
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import warp as wp

import warptex.candidates as candidates
from warptex import Exemplar, ExemplarError, candidate_set, exact_pca, parallel
from warptex.archive import read_archive, write_archive
from warptex.candidate_set import FORMAT_VERSION, CandidateCacheError, CandidateSet, SourceLevel
from warptex.candidates import cache_file_name, cache_path, cached_candidate_path, precompute
from warptex.code_digest import sources_digest

GRANITE = Path(__file__).resolve().parent / "data" / "granite_64.png"


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch) -> Path:
    """Every test gets its own empty candidate cache, never the user's."""
    folder = tmp_path / "cache"
    monkeypatch.setenv("WARPTEX_CACHE", str(folder))
    return folder


def _granite() -> np.ndarray:
    return Exemplar.load(GRANITE).colors


def _crop(rows: slice, cols: slice) -> Exemplar:
    return Exemplar(_granite()[rows, cols], name="crop")


@pytest.fixture(scope="module")
def granite(warp_device) -> CandidateSet:
    """One 64x64 exemplar on all three axes: four levels, shared candidates."""
    return precompute(GRANITE, cache=False)


@pytest.fixture(scope="module")
def three(warp_device) -> tuple[CandidateSet, list[Exemplar]]:
    """Three different exemplars of different sizes, so every role has its own sizes."""
    colors = _granite()
    exemplars = [
        Exemplar(colors[:32, :32], name="x"),
        Exemplar(colors[32:56, 16:48, ::-1], name="y"),  # 24x32, channels reversed
        Exemplar(1.0 - colors[:32, 32:48], name="z"),  # 32x16, inverted
    ]
    return precompute(*exemplars, cache=False), exemplars


# -- independent numpy reference of sections 4.1 and 4.2 --------------------------------


def _strip(feat: np.ndarray, pix: np.ndarray, axis: int, half: int) -> np.ndarray:
    """The N pixels through ``pix`` along pixel coordinate ``axis``, toroidally:
    ``(..., N, F)`` int64."""
    h, w, _ = feat.shape
    u, v = np.divmod(pix, w)
    t = np.arange(-half, half + 1)
    if axis == 0:
        uu, vv = (u[..., None] + t) % h, np.broadcast_to(v[..., None], (*v.shape, len(t)))
    else:
        uu, vv = np.broadcast_to(u[..., None], (*u.shape, len(t))), (v[..., None] + t) % w
    return feat[uu, vv].astype(np.int64)


def _crossbar(feats: list[np.ndarray], pixels: list[np.ndarray], half: int) -> np.ndarray:
    """Section 4.1: the second-coordinate strip of role k against the first-coordinate
    strip of role k+1, for the pairs (0, 1), (1, 2), (2, 0), summed over channels."""
    total = np.zeros(pixels[0].shape, np.int64)
    for a in range(3):
        b = (a + 1) % 3
        d = _strip(feats[a], pixels[a], 1, half) - _strip(feats[b], pixels[b], 0, half)
        total += (d * d).sum(axis=(-2, -1))
    return total


def _incoherent(cand: np.ndarray, count: np.ndarray, sizes: list[tuple[int, int]]) -> np.ndarray:
    """Section 4.2 on final lists: (P, K) True where a valid candidate has no continuous
    coordinate among its 4-neighbours' candidates in role 1 or in role 2."""
    npix, k, _ = cand.shape
    h0, w0 = sizes[0]
    u0, v0 = np.divmod(np.arange(npix), w0)
    neighbours = [
        ((u0 + du) % h0) * w0 + (v0 + dv) % w0 for du, dv in ((-1, 0), (1, 0), (0, -1), (0, 1))
    ]
    valid = np.arange(k)[None, :] < count[:, None]
    coherent = np.ones((npix, k), bool)
    for role in (1, 2):
        h, w = sizes[role]
        cu, cv = np.divmod(cand[:, :, role - 1], w)
        found = np.zeros((npix, k), bool)
        for q in neighbours:
            du = np.abs(cu[q][:, None, :] - cu[:, :, None])
            dv = np.abs(cv[q][:, None, :] - cv[:, :, None])
            dist = np.minimum(du, h - du) + np.minimum(dv, w - dv)
            found |= ((dist == 1) & valid[q][:, None, :]).any(axis=2)
        coherent &= found
    return valid & ~coherent


def _trio(cs: CandidateSet, level: int, role: int) -> list[SourceLevel]:
    """Role k's pixels index the exemplars of axes k, k+1, k+2 (cyclic orientation)."""
    return [cs.sources[level][cs.axis_source[(role + j) % 3]] for j in range(3)]


def _role_cases(cs: CandidateSet) -> list[tuple[int, int]]:
    return [(lv, r) for lv in range(cs.num_levels) for r in range(len(cs.roles[lv]))]


def _assert_same(a: CandidateSet, b: CandidateSet) -> None:
    assert a.params == b.params and a.digests == b.digests
    assert a.axis_source == b.axis_source and a.stats == b.stats
    for ca, cb in zip(a.colors, b.colors, strict=True):
        np.testing.assert_array_equal(ca, cb)
    for la, lb in zip(a.sources, b.sources, strict=True):
        for sa, sb in zip(la, lb, strict=True):
            assert sa.shift == sb.shift and sa.margins == sb.margins
            for name in ("feat", "basis", "proj", "cand2d"):
                np.testing.assert_array_equal(getattr(sa, name), getattr(sb, name))
    for la, lb in zip(a.roles, b.roles, strict=True):
        for ra, rb in zip(la, lb, strict=True):
            for name in ("cand", "crossbar_errors", "count", "fallback"):
                np.testing.assert_array_equal(getattr(ra, name), getattr(rb, name))


# -- stored values ------------------------------------------------------------------------


def test_shared_exemplar_has_one_role_and_one_source(granite):
    assert granite.shared and granite.axis_source == (0, 0, 0)
    assert granite.num_levels == 4
    assert [lvl[0].size for lvl in granite.sources] == [(8, 8), (16, 16), (32, 32), (64, 64)]
    assert all(len(lvl) == 1 for lvl in granite.sources)
    assert all(len(lvl) == 1 for lvl in granite.roles)


@pytest.mark.parametrize("k", [1, 7, 40])
def test_nearest_rows_break_ties_by_index(k):
    # Three values in four dimensions: most distances tie, and a k-d tree's own order among
    # equal distances differs from the index order (and between SciPy builds).
    rng = np.random.default_rng(0)
    database = rng.integers(0, 3, size=(500, 4))
    queries = rng.integers(0, 3, size=(200, 4))
    assert np.array_equal(candidates.nearest_rows(database, queries, k),
                          _brute_nearest(database, queries, k))


def _brute_nearest(database: np.ndarray, queries: np.ndarray, k: int) -> np.ndarray:
    d2 = ((queries[:, None] - database[None]) ** 2).sum(axis=2)
    return np.stack([np.lexsort((np.arange(len(database)), row))[:k] for row in d2])


@pytest.mark.parametrize(("size", "k", "usable_share", "smooth"),
                         [(16, 4, 1.0, False), (16, 4, 0.6, False), (9, 30, 1.0, False),
                          (9, 30, 0.3, False), (16, 4, 1.0, True)])
def test_k_coherent_candidates_are_the_nearest_far_pixels_in_order(size, k, usable_share,
                                                                   smooth):
    """Section 4.2's 2D candidates (Tong et al. 2002) against a pixel-by-pixel reference:
    the pixel itself (or the usable one most like it), then the most similar usable pixels
    more than 2 pixels away, the lead repeated where there are too few. A level with fewer
    usable pixels than k (seams' margins at a coarse level) raised an IndexError. On a
    smooth ramp the 5x5 pixels around each are its most similar: the far ones lie past
    them."""
    rng = np.random.default_rng(size * k)
    proj = rng.integers(-2, 3, (size * size, 4)).astype(np.int16)  # ties by the hundred
    if smooth:
        u, v = np.divmod(np.arange(size * size), size)
        proj = np.stack([10 * u, 10 * v, 0 * u, 0 * v], axis=1).astype(np.int16)
    usable = rng.random(size * size) < usable_share
    usable[0] = True
    got = candidates._kcoherent(proj, size, size, k, usable)
    pool = np.flatnonzero(usable)
    for pix in range(size * size):
        d2 = ((proj[pool].astype(np.int64) - proj[pix]) ** 2).sum(axis=1)
        ranked = pool[np.lexsort((pool, d2))][: 4 * k + 25]  # ties by index
        lead = pix if usable[pix] else ranked[0]
        u, v = divmod(pix, size)
        far = [q for q in ranked if q != lead and (
            min(abs(q // size - u), size - abs(q // size - u)) > 2
            or min(abs(q % size - v), size - abs(q % size - v)) > 2)][: k - 1]
        expected = [lead, *far] + [lead] * (k - 1 - len(far))
        assert got[pix].tolist() == expected, pix


@pytest.mark.parametrize("k", [1, 5, 40, 300])
def test_nearest_rows_of_a_mostly_flat_photo_are_found_without_searching_it_all(k,
                                                                               monkeypatch):
    """Equal rows tie at every distance: each query's ties widened its search to the
    whole database (a 64 px photo, mostly flat, took 44 s and 4.4 GB to pre-compute, one
    of 128 px ran out of memory). They are searched as one row now, which stands for all
    of its members, and the result is the brute force's, ties by index, also where there
    are fewer distinct rows than k."""
    rng = np.random.default_rng(1)
    database = np.zeros((3000, 6), np.int64)  # flat, but for a few patches and dots
    database[rng.choice(3000, 200, replace=False)] = rng.integers(0, 3, (200, 6))
    queries = np.concatenate([database[rng.choice(3000, 150)], rng.integers(0, 3, (50, 6))])
    searched = []
    nearest = candidates.parallel.nearest
    monkeypatch.setattr(candidates.parallel, "nearest", lambda tree, q, **kw: (
        searched.append(kw["k"]), nearest(tree, q, **kw))[1])
    assert np.array_equal(candidates.nearest_rows(database, queries, k),
                          _brute_nearest(database, queries, k))
    assert max(searched) < 1000  # distinct rows, not every row of the database
    few = np.repeat(np.eye(3, dtype=np.int64), 50, axis=0)[rng.permutation(150)]
    assert np.array_equal(candidates.nearest_rows(few, few[:20], min(k, 150)),
                          _brute_nearest(few, few[:20], min(k, 150)))
    # In parts of a few queries and members each, as a wide search is held: the same.
    monkeypatch.setattr(candidates, "_NEAREST_ENTRIES", 50)
    monkeypatch.setattr(candidates, "_DISTANCE_TERMS", 40)
    assert np.array_equal(candidates.nearest_rows(database, queries, k),
                          _brute_nearest(database, queries, k))
    assert candidates.nearest_rows(database, queries[:0], k).shape == (0, k)


def test_coordinates_inside_their_exemplar_level(granite, three):
    for cs in (granite, three[0]):
        k3 = int(cs.params["candidates_3d"])
        for lv, r in _role_cases(cs):
            role = cs.roles[lv][r]
            own, nxt, nnx = (h * w for h, w in (s.size for s in _trio(cs, lv, r)))
            assert role.cand.shape == (own, k3, 2)
            assert role.cand[..., 0].min() >= 0 and role.cand[..., 0].max() < nxt
            assert role.cand[..., 1].min() >= 0 and role.cand[..., 1].max() < nnx
            assert role.count.min() >= 1 and role.count.max() <= k3
        for lvl in cs.sources:
            for src in lvl:
                h, w = src.size
                assert src.cand2d.min() >= 0 and src.cand2d.max() < h * w
                np.testing.assert_array_equal(src.cand2d[:, 0], np.arange(h * w))


def test_lists_sorted_by_crossbar_error_and_padded_with_the_best(granite, three):
    for cs in (granite, three[0]):
        for lv, r in _role_cases(cs):
            role = cs.roles[lv][r]
            k = role.crossbar_errors.shape[1]
            valid = np.arange(k)[None, :] < role.count[:, None]
            steps = np.diff(role.crossbar_errors, axis=1)
            assert (steps[valid[:, 1:]] >= 0).all(), f"level {lv} role {r} not ascending"
            # Slots past `count` repeat the first candidate, so readers stay in range.
            pad = ~valid
            best_cb = np.broadcast_to(role.crossbar_errors[:, :1], role.crossbar_errors.shape)
            np.testing.assert_array_equal(role.crossbar_errors[pad], best_cb[pad])
            best = np.broadcast_to(role.cand[:, :1], role.cand.shape)
            np.testing.assert_array_equal(role.cand[pad], best[pad])


def test_stored_crossbar_error_matches_numpy_reference(granite, three):
    for cs in (granite, three[0]):
        half = int(cs.params["neighborhood"]) // 2
        for lv, r in _role_cases(cs):
            role = cs.roles[lv][r]
            feats = [s.feat for s in _trio(cs, lv, r)]
            npix, k, _ = role.cand.shape
            own = np.broadcast_to(np.arange(npix)[:, None], (npix, k))
            expected = _crossbar(feats, [own, role.cand[..., 0], role.cand[..., 1]], half)
            valid = np.arange(k)[None, :] < role.count[:, None]
            np.testing.assert_array_equal(role.crossbar_errors[valid], expected[valid])


def test_crossbar_reference_sees_orientation():
    """The reference itself: a triple is scored on the strips the orientation pairs."""
    rng = np.random.default_rng(5)
    feats = [rng.integers(0, 256, size=(7, 9, 2), dtype=np.uint8) for _ in range(3)]
    p = [np.array([3]), np.array([10]), np.array([40])]
    by_hand = 0
    for a, b in ((0, 1), (1, 2), (2, 0)):
        ua, va = divmod(int(p[a][0]), 9)
        ub, vb = divmod(int(p[b][0]), 9)
        for t in range(-2, 3):
            d = feats[a][ua, (va + t) % 9].astype(int) - feats[b][(ub + t) % 7, vb]
            by_hand += int((d * d).sum())
    assert _crossbar(feats, p, 2)[0] == by_hand


def test_coherent_except_exactly_at_counted_fallback_pixels(granite, three):
    for cs in (granite, three[0]):
        for lv in range(cs.num_levels):
            for r, role in enumerate(cs.roles[lv]):
                sizes = [s.size for s in _trio(cs, lv, r)]
                bad = _incoherent(role.cand, role.count, sizes).any(axis=1)
                np.testing.assert_array_equal(bad, role.fallback, f"level {lv} role {r}")
                assert (role.count[role.fallback] == 1).all()
            total = sum(int(role.fallback.sum()) for role in cs.roles[lv])
            assert cs.stats["fallback_pixels"][lv] == total
    # Most pixels find coherent candidates.
    finest = granite.roles[-1][0]
    assert finest.fallback.mean() < 0.5


def test_coherence_holds_when_rounds_run_out(warp_device):
    """Lists cut to k3 after `coherence_rounds` are filtered on to a coherent fixpoint."""
    cs = precompute(_crop(slice(0, 32), slice(0, 32)), cache=False, coherence_rounds=1)
    for lv in range(cs.num_levels):
        role = cs.roles[lv][0]
        sizes = [cs.sources[lv][0].size] * 3
        bad = _incoherent(role.cand, role.count, sizes).any(axis=1)
        np.testing.assert_array_equal(bad, role.fallback)
    # Cut to the paper's "first 12", not fewer: lists that stay coherent keep all of them.
    assert max(int(r[0].count.max()) for r in cs.roles) == cs.params["candidates_3d"]



def test_coherence_rounds_cut_the_lists_when_they_run_out(warp_device):
    """After ``coherence_rounds`` rounds the lists are cut to their best k3 before
    filtering on; without the cut, filtering would run to its fixpoint whatever the
    setting."""
    ex = _crop(slice(0, 32), slice(0, 32))
    one, two, many = (precompute(ex, cache=False, coherence_rounds=r) for r in (1, 2, 16))

    def differ(a: CandidateSet, b: CandidateSet) -> bool:
        return any(not np.array_equal(x[0].cand, y[0].cand)
                   or not np.array_equal(x[0].count, y[0].count)
                   for x, y in zip(a.roles, b.roles, strict=True))

    assert differ(one, many) and differ(one, two)


def test_lists_are_cut_after_as_many_rounds_as_the_setting_says(monkeypatch, warp_device):
    """With ``coherence_rounds=1`` the lists that the first round filtered are cut to k3
    before the second: no two rounds in a row see longer lists. Lists filtered to their
    fixpoint before that are cut to k3 too, and keep all k3 where they are coherent."""
    ex = _crop(slice(0, 32), slice(0, 32))
    longest = []
    continued = candidates._continued
    monkeypatch.setattr(candidates, "_continued", lambda cand, count, sizes, listed: (
        longest.append(int(count[listed].max())), continued(cand, count, sizes, listed))[1])
    k3 = precompute(ex, cache=False, coherence_rounds=1).params["candidates_3d"]
    assert longest[0] > k3
    assert not any(a > k3 and b > k3 for a, b in itertools.pairwise(longest))
    longest.clear()
    plain = precompute(ex, cache=False)  # 16 rounds: the fixpoint comes first
    assert max(int(r[0].count.max()) for r in plain.roles) == k3

# -- different exemplars per axis ---------------------------------------------------------


@pytest.mark.parametrize(("sizes", "batch_rows"), [([(8, 8), (8, 8), (8, 8)], None),
                                                   ([(4, 6), (1, 7), (2, 3)], None),
                                                   ([(3, 5), (6, 1), (9, 4)], None),
                                                   ([(12, 12), (9, 40), (33, 33)], 70)])
def test_coherence_test_matches_a_numpy_reference(sizes, batch_rows, monkeypatch, warp_device):
    """The kernel's bitmaps of continued pixels against pairwise distances, on random lists
    (repeated and empty ones too) dense enough that both outcomes are common, over
    exemplars one and two pixels wide; the last case in batches of bitmap rows, split over
    the CPU threads, so that a row left marked by one pixel would wrong the next."""
    if batch_rows is not None:
        words = -(-max(h * w for h, w in sizes[1:]) // 32)
        monkeypatch.setattr(candidates, "_MARK_BYTES", 4 * words * batch_rows)
    rng = np.random.default_rng(3)
    npix, slots = sizes[0][0] * sizes[0][1], 6
    cand = np.stack([rng.integers(0, min(h * w, 60), (npix, slots)) for h, w in sizes[1:]],
                    axis=2)
    count = rng.integers(0, slots + 1, npix)
    listed = np.flatnonzero(rng.random(npix) < 0.7)
    valid = np.arange(slots)[None, :] < count[:, None]
    expected = (valid & ~_incoherent(cand, count, sizes))[listed]
    got = candidates._continued(cand, count, sizes, listed)
    assert 0 < expected.sum() < valid[listed].sum()
    np.testing.assert_array_equal(got, expected)


def test_three_different_exemplars_have_three_roles(three):
    cs, exemplars = three
    assert not cs.shared and cs.axis_source == (0, 1, 2)
    assert cs.digests == tuple(e.digest() for e in exemplars)
    assert all(len(lvl) == 3 for lvl in cs.roles)
    assert all(len(lvl) == 3 for lvl in cs.sources)
    assert [s.size for s in cs.sources[-1]] == [(32, 32), (24, 32), (32, 16)]
    for j, e in enumerate(exemplars):
        np.testing.assert_array_equal(cs.colors[j], e.colors)
    # Role k belongs to axis k.
    assert [cs.role_of_axis(k) for k in range(3)] == [0, 1, 2]


def test_two_equal_exemplars_share_a_source(warp_device):
    a = _crop(slice(0, 16), slice(0, 16))
    b = _crop(slice(16, 32), slice(16, 32))
    cs = precompute(a, b, a, cache=False)
    assert cs.axis_source == (0, 1, 0)
    assert all(len(lvl) == 2 for lvl in cs.sources)
    assert all(len(lvl) == 3 for lvl in cs.roles)
    half = int(cs.params["neighborhood"]) // 2
    for lv, r in _role_cases(cs):
        role = cs.roles[lv][r]
        npix, k, _ = role.cand.shape
        own = np.broadcast_to(np.arange(npix)[:, None], (npix, k))
        feats = [s.feat for s in _trio(cs, lv, r)]
        expected = _crossbar(feats, [own, role.cand[..., 0], role.cand[..., 1]], half)
        valid = np.arange(k)[None, :] < role.count[:, None]
        np.testing.assert_array_equal(role.crossbar_errors[valid], expected[valid])


def test_same_image_thrice_is_shared(warp_device):
    ex = _crop(slice(0, 16), slice(0, 16))
    again = Exemplar(ex.colors.copy(), name="copy")
    cs = precompute(ex, again, ex, cache=False)
    assert cs.shared and cs.axis_source == (0, 0, 0) and len(cs.sources[0]) == 1


# -- determinism and files ----------------------------------------------------------------


_SUBPROCESS = """
import sys
from warptex import Exemplar
from warptex.candidates import precompute
colors = Exemplar.load(sys.argv[1]).colors[:32, :32]
precompute(Exemplar(colors, name="crop"), cache=False).save(sys.argv[2])
"""


def test_byte_identical_files_in_one_and_across_two_processes(tmp_path, warp_device):
    ex = _crop(slice(0, 32), slice(0, 32))
    precompute(ex, cache=False).save(tmp_path / "a.wtc")
    precompute(ex, cache=False).save(tmp_path / "b.wtc")
    first = (tmp_path / "a.wtc").read_bytes()
    assert first == (tmp_path / "b.wtc").read_bytes()
    subprocess.run(
        [sys.executable, "-c", _SUBPROCESS, str(GRANITE), str(tmp_path / "c.wtc")],
        check=True,
        capture_output=True,
    )
    assert first == (tmp_path / "c.wtc").read_bytes()


# A gray noise exemplar: its neighbourhood covariance has many nearly equal eigenvalues,
# whose eigenvectors a last-bit difference turns. The script prints digests of what the
# candidates' PCA makes of it and of a 7-channel one (orthogonal iteration, not Jacobi),
# of LAPACK's eigenvectors, of a shrunk photo and its Otsu mask, and of a sliced Wasserstein
# distance (warptex.metrics), each computed under the BLAS kernels that OPENBLAS_CORETYPE
# selects.
_BLAS_SUBPROCESS = """
import hashlib
import numpy as np
from warptex import candidate_set, candidates, exemplar
rng = np.random.default_rng(7)
gray = np.repeat(rng.integers(0, 256, (16, 16, 1), dtype=np.uint8), 3, axis=2)
wide = rng.integers(0, 256, (8, 8, 7), dtype=np.uint8)
params = dict(candidate_set.DEFAULT_PARAMS)
cases = [(gray, (0, 0)), (wide, (0, 0)), (gray, (2, 2))]  # the last keeps margins
levels = [candidates._source_level(feat, params, 2, margins) for feat, margins in cases]
cov = np.cov(3 * candidates._neighborhoods(gray, 5), rowvar=False)
photo = np.random.default_rng(3).random((997, 1503, 3)).astype(np.float32)
arrays = [array for level in levels for array in (level.basis, level.proj, level.cand2d)]
arrays += [exemplar._shrunk(photo, 64, "photo"), exemplar.otsu_mask(photo)]
from warptex import metrics
ex = rng.random((16, 16, 3)).astype(np.float32)
arrays += [np.float64(metrics.sliced_wasserstein(metrics.iid_noise(ex, (8, 16, 16)), ex, 0))]
arrays += [np.linalg.eigh(cov)[1]]
for array in arrays:
    print(hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest())
"""


def _cpu_flags() -> set[str]:
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return set()
    return next((set(line.split(":", 1)[1].split()) for line in lines
                 if line.startswith("flags")), set())


@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"),
                    reason="OPENBLAS_CORETYPE names x86-64 kernels")
def test_same_candidates_whatever_blas_kernels_the_cpu_selects():
    """Machines of one render farm run other BLAS kernels (SSE3 on one, AVX-512 on
    another); the PCA basis and the exemplars must not follow them (section 6.1's
    appearance space). Each kernel set this CPU can run is tried."""
    def digests(core: str) -> list[str]:
        env = {**os.environ, "OPENBLAS_CORETYPE": core}
        run = subprocess.run([sys.executable, "-c", _BLAS_SUBPROCESS], env=env, check=True,
                             capture_output=True, text=True)
        return run.stdout.split()

    flags = _cpu_flags()
    cores = ["Prescott", *(["Sandybridge"] if "avx" in flags else []),
             *(["Haswell"] if "avx2" in flags else []),
             *(["SkylakeX"] if "avx512f" in flags else [])]
    runs = {core: digests(core) for core in cores}
    first = runs["Prescott"]
    for core, run in runs.items():
        assert run[9:11] == first[9:11], f"a shrunk exemplar or its Otsu mask differ under {core}"
        assert run[:9] == first[:9], f"the candidates' PCA differs under {core}"
        assert run[11] == first[11], f"the sliced Wasserstein distance differs under {core}"
    if len({run[12] for run in runs.values()}) == 1:
        pytest.skip(f"LAPACK gives the same eigenvectors under {', '.join(cores)} here, so "
                    "the kernels were not shown to differ")


@pytest.mark.parametrize("eigenvalues", [
    [5.0, 4.0, 3.0, 2.5, 1.0, 0.5, 0.1, 0.0, -1.0],  # odd size, a zero and a negative one
    [3.0, 3.0, 3.0, 1.0, 1.0, 0.0, 0.0, 0.0],  # repeated eigenvalues
    [0.0] * 4,
])
def test_symmetric_eigen_decomposes(eigenvalues):
    rng = np.random.default_rng(len(eigenvalues))
    basis = np.linalg.qr(rng.normal(size=(len(eigenvalues),) * 2))[0]
    matrix = basis @ np.diag(eigenvalues) @ basis.T
    matrix = (matrix + matrix.T) / 2
    values, vectors = exact_pca.symmetric_eigen(matrix)
    assert np.allclose(np.sort(values), np.sort(eigenvalues), atol=1e-12)
    assert np.allclose(vectors.T @ vectors, np.eye(len(values)), atol=1e-12)
    assert np.allclose(matrix @ vectors, vectors * values, atol=1e-12)


def test_principal_variances_of_a_low_rank_covariance_are_never_negative():
    """Neighbourhoods of a 3-channel exemplar whose 20 features mix 3 values: rotations
    leave some of the 17 null variances slightly negative (about -1e-14 on this project's
    machines), which are variances of 0."""
    rng = np.random.default_rng(0)
    vec = rng.integers(0, 255, (50, 3)).astype(np.float64) @ rng.normal(size=(3, 20))
    cov = np.cov(vec.T)
    values, _, total = exact_pca.principal_axes((cov + cov.T) / 2, 5)
    assert (values >= 0).all() and np.count_nonzero(values) >= 3
    assert total == pytest.approx(np.trace(cov))


def test_every_axis_of_a_four_channel_neighbourhood_comes_from_jacobi_rotations():
    """RGBA or RGB and a feature channel at 5 x 5 is 100 dimensions, the widest decomposed
    whole; wider ones get their leading axes only."""
    n = 4 * 5 * 5
    rng = np.random.default_rng(1)
    basis = np.linalg.qr(rng.normal(size=(n + 1, n + 1)))[0]
    for size in (n, n + 1):
        matrix = basis[:size, :size] @ np.diag(np.linspace(1, 2, size)) @ basis[:size, :size].T
        values = exact_pca.principal_axes((matrix + matrix.T) / 2, 12)[0]
        assert len(values) == (size if size == n else 12)
        expected = np.linalg.eigvalsh((matrix + matrix.T) / 2)[::-1][: len(values)]
        assert np.allclose(values, expected, rtol=1e-6)


def test_orthonormal_columns_leave_a_dependent_one_zero():
    columns = np.array([[1.0, 2.0, 0.0], [0.0, 0.0, 3.0], [0.0, 0.0, 0.0]])
    out = exact_pca._orthonormal(columns)
    assert np.array_equal(out, np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]))


@pytest.mark.parametrize("rank, decay", [(None, 0.8), (30, 0.8), (5, 0.8), (None, 0.983)])
def test_leading_eigen_finds_the_principal_axes_of_wide_neighbourhoods(rank, decay):
    """Beyond JACOBI_MAX_DIMS (multi-channel exemplars) only the leading axes are found, by
    orthogonal iteration on exact products; a matrix of low rank leaves vectors unused. A
    slowly falling spectrum takes tens of rounds to settle: one stopped at a residual of 1e-2
    was 0.4 off in its variances."""
    n = exact_pca.JACOBI_MAX_DIMS + 10
    rank = n if rank is None else rank
    rng = np.random.default_rng(rank)
    basis = np.linalg.qr(rng.normal(size=(n, n)))[0][:, :rank]
    spectrum = 100.0 * decay ** np.arange(rank)
    matrix = basis @ np.diag(spectrum) @ basis.T
    values, vectors, total = exact_pca.principal_axes((matrix + matrix.T) / 2, 12)
    found = min(12, rank)
    assert np.allclose(values[:found], spectrum[:found], rtol=1e-5, atol=1e-6)
    assert np.allclose(values[found:], 0.0, atol=1e-6 * spectrum[0])  # the rounding's noise
    assert total == pytest.approx(spectrum.sum())
    leading = vectors[:, :found]
    assert np.allclose(leading.T @ leading, np.eye(found), atol=1e-6)
    assert np.allclose(matrix @ leading, leading * values[:found], atol=1e-3)


@pytest.mark.parametrize("threads", [1, 3])
def test_same_candidates_on_any_number_of_threads(threads, monkeypatch, granite):
    """The searches split over CPU threads (warptex.parallel); each pixel's result is its
    own, so the split must not show."""
    monkeypatch.setattr(parallel, "THREADS", threads)
    _assert_same(precompute(GRANITE, cache=False), granite)


def test_coherence_retests_what_a_full_retest_would_change(monkeypatch, three):
    """Each coherence round retests only the neighbours of changed lists; retesting every
    pixel every round must give the same candidates."""
    cs, exemplars = three
    monkeypatch.setattr(candidates, "_direct_neighbours",
                        lambda marked, size: np.ones(marked.size, bool))
    _assert_same(precompute(*exemplars, cache=False), cs)


def test_save_load_round_trip(tmp_path, granite):
    granite.save(tmp_path / "g.wtc")
    loaded = CandidateSet.load(tmp_path / "g.wtc")
    _assert_same(granite, loaded)
    assert loaded.nbytes() == granite.nbytes()
    assert not list(tmp_path.glob(".*.tmp*")), "temporary file left behind"


def test_second_call_loads_the_cache(monkeypatch, private_cache, warp_device):
    ex = _crop(slice(0, 16), slice(0, 16))
    assert cached_candidate_path(ex) is None
    first = precompute(ex)
    path = cached_candidate_path(ex)
    assert path is not None and path.parent == private_cache

    def no_compute(*args, **kwargs):
        raise AssertionError("recomputed although the cache holds the candidates")

    monkeypatch.setattr(candidates, "_compute", no_compute)
    _assert_same(first, precompute(ex))
    # The key holds the content, not the name, and every parameter: candidates of other
    # parameters are computed, never served from the defaults' file.
    _assert_same(first, precompute(Exemplar(ex.colors.copy(), name="other")))
    for name, value in OTHER_PARAMS.items():
        with pytest.raises(AssertionError, match="recomputed"):
            precompute(ex, **{name: value})


def test_exemplars_beyond_the_memory_are_refused_before_any_work(monkeypatch, warp_device):
    import warptex.machine

    monkeypatch.setattr(warptex.machine, "physical_memory", lambda: 300 << 20)

    def computed(*args):
        raise RuntimeError("computed")

    monkeypatch.setattr(candidates, "_compute", computed)
    small, large = _crop(slice(0, 16), slice(0, 16)), Exemplar.load(GRANITE)  # 260, 312 MiB
    with pytest.raises(ExemplarError, match=r"granite_64\.png: 64x64 pixels; pre-computing its "
                       r"candidates needs about 312 MiB, this machine has 300 MiB; shrink it "
                       r"when loading: max_size=256 in Exemplar\.load, --exemplar-max-size 256 "
                       r'on the command line, <integer name="exemplar_max_size" value="256"/> '
                       r"in a scene"):
        precompute(large)
    with pytest.raises(ExemplarError, match=r"granite_64\.png: 64x64"):  # the largest axis
        precompute(small, large, small)
    with pytest.raises(RuntimeError, match="computed"):  # a small one fits
        precompute(small)
    # Exemplars of their own per axis take more: 256 MiB + 1024 pixels x 14, 16 or 18 KiB.
    monkeypatch.setattr(warptex.machine, "physical_memory", lambda: 273 << 20)
    crops = [_crop(slice(0, 32), slice(c, c + 32)) for c in (0, 16, 32)]
    with pytest.raises(RuntimeError, match="computed"):
        precompute(crops[0], crops[1], crops[1])
    with pytest.raises(ExemplarError, match="needs about 274 MiB, this machine has 273 MiB"):
        precompute(*crops)


def test_the_estimate_counts_feature_channels_beyond_rgb():
    """32-channel exemplars peaked 16-19 % above the estimate, which was blind to channels
    (a review's measure: 372 MiB at 64^2 and 445 MiB at 96^2)."""
    rng = np.random.default_rng(0)
    for side, peak in ((64, 372 << 20), (96, 445 << 20)):
        wide = Exemplar(rng.random((side, side, 32)).astype(np.float32))
        rgb = Exemplar(rng.random((side, side, 3)).astype(np.float32))
        assert candidates.precompute_bytes([wide]) > peak
        assert candidates.precompute_bytes([wide]) > candidates.precompute_bytes([rgb])


def test_large_exemplars_are_warned_of_when_computed_not_when_cached(monkeypatch, warp_device):
    ex = _crop(slice(0, 16), slice(0, 20))
    monkeypatch.setattr(candidates, "LARGE_PIXELS", 16 * 20 - 1)
    with pytest.warns(UserWarning, match=r"crop: 20x16 pixels, a large exemplar: pre-computing "
                      r"its candidates takes minutes .* as they are cached; to shrink it"):
        first = precompute(ex)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _assert_same(first, precompute(ex))
        monkeypatch.setattr(candidates, "LARGE_PIXELS", 16 * 20)
        precompute(ex, cache=False)


def _damage_truncate(data: bytes) -> bytes:
    return data[: len(data) // 2]


def _damage_flip(data: bytes) -> bytes:
    mid = len(data) // 2
    return data[:mid] + bytes([data[mid] ^ 0x40]) + data[mid + 1 :]


@pytest.mark.parametrize("damage", [_damage_truncate, _damage_flip])
def test_corrupt_cache_is_reported_once_and_replaced(damage, warp_device):
    ex = _crop(slice(16, 32), slice(0, 16))
    good = precompute(ex)
    path = cached_candidate_path(ex)
    good_bytes = path.read_bytes()
    path.write_bytes(damage(good_bytes))
    assert cached_candidate_path(ex) is None  # `warptex info` must not call it cached
    with pytest.warns(UserWarning, match="damaged candidate cache") as record:
        again = precompute(ex)
    assert len(record) == 1
    assert str(path) in str(record[0].message)
    _assert_same(good, again)
    assert path.read_bytes() == good_bytes
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _assert_same(good, precompute(ex))


def test_a_cache_file_of_other_exemplars_is_reported_and_replaced(warp_device):
    """A cache file copied or renamed onto another exemplar's name is whole and checksummed,
    but holds other candidates: they must not be served under this exemplar."""
    ex = _crop(slice(0, 16), slice(0, 16))
    other = _crop(slice(16, 32), slice(16, 32))
    good = precompute(ex)
    path = cached_candidate_path(ex)
    good_bytes = path.read_bytes()
    precompute(other)
    path.write_bytes(cached_candidate_path(other).read_bytes())
    assert cached_candidate_path(ex) is None
    with pytest.warns(UserWarning, match="candidates of other exemplars or parameters") as record:
        again = precompute(ex)
    assert len(record) == 1 and str(path) in str(record[0].message)
    _assert_same(good, again)
    assert path.read_bytes() == good_bytes


def test_a_cache_file_another_version_computed_is_not_served(warp_device):
    """Named as this code names its file (renamed from another version's name), but
    computed by other code: reported and computed again, and listed as another version."""
    from warptex.candidate_cache import OTHER_VERSION, cache_files

    ex = _crop(slice(8, 24), slice(0, 16))
    good = precompute(ex)
    path = cached_candidate_path(ex)
    older = CandidateSet.load(path)
    older.code = "another version's code"
    older.save(path)
    assert cached_candidate_path(ex) is None
    assert {f.path: f.status for f in cache_files()}[path] == OTHER_VERSION
    with pytest.warns(UserWarning, match="candidates another version of warptex computed"):
        again = precompute(ex)
    _assert_same(good, again)
    assert CandidateSet.load(path).code == good.code != ""


def test_a_checksummed_file_whose_arrays_do_not_fit_is_refused(tmp_path, granite):
    """Written by other means but checksummed: out-of-range candidates crashed the process
    that loaded them (the crossbar kernel read beyond its arrays), short ones loaded."""
    granite.save(tmp_path / "g.wtc")
    arrays = read_archive(tmp_path / "g.wtc", candidate_set.FILE_MAGIC, FORMAT_VERSION,
                          "candidate", CandidateCacheError)
    finest = granite.num_levels - 1
    beyond = dict(arrays)
    beyond[f"L{finest}/R0/cand"] = arrays[f"L{finest}/R0/cand"] + 60000
    short = dict(arrays)
    short[f"L{finest}/R0/cand"] = arrays[f"L{finest}/R0/cand"][:-1]
    small = dict(arrays)
    small[f"L{finest}/S0/feat"] = arrays[f"L{finest}/S0/feat"][:5, :5]
    counted = dict(arrays)
    counted[f"L{finest}/R0/count"] = arrays[f"L{finest}/R0/count"] + 200
    for name, bad in (("beyond", beyond), ("short", short), ("small", small),
                      ("counted", counted)):
        write_archive(tmp_path / f"{name}.wtc", candidate_set.FILE_MAGIC, FORMAT_VERSION, bad)
        with pytest.raises(CandidateCacheError, match="unreadable candidate data"):
            CandidateSet.load(tmp_path / f"{name}.wtc")


def _each_refused(folder: Path, arrays: dict, changes: dict) -> None:
    """Each of ``changes`` (name: arrays replaced) made to a candidate file's ``arrays``,
    written checksummed under its name, is refused on loading, the file named."""
    for name, change in changes.items():
        path = folder / f"{name}.wtc"
        write_archive(path, candidate_set.FILE_MAGIC, FORMAT_VERSION, {**arrays, **change})
        with pytest.raises(CandidateCacheError, match=f"{name}.wtc: unreadable candidate data"):
            CandidateSet.load(path)


def test_a_checksummed_file_of_three_exemplars_whose_arrays_disagree_is_refused(tmp_path,
                                                                               warp_device):
    """The kernels take the first exemplar's and the first role's candidate row widths for
    all: a narrower one elsewhere passed the checks and crashed the process that
    synthesized from it. Colors of other channels, features that are not 8-bit,
    projections beyond their 12 bits and shifts beyond an int's also passed."""
    import json

    axes = [_crop(slice(0, 16), slice(0, 16)), _crop(slice(16, 32), slice(0, 16)),
            _crop(slice(0, 16), slice(16, 32))]
    precompute(*axes, cache=False).save(tmp_path / "three.wtc")
    arrays = read_archive(tmp_path / "three.wtc", candidate_set.FILE_MAGIC, FORMAT_VERSION,
                          "candidate", CandidateCacheError)
    meta = json.loads(bytes(arrays["meta"]).decode())
    assert meta["num_sources"] == meta["num_roles"] == 3
    CandidateSet.load(tmp_path / "three.wtc")  # as written, it loads
    last = meta["num_levels"] - 1
    shifts = [list(level) for level in meta["shifts"]]
    shifts[last][2] = 40
    changes = {
        "narrow_2d": {f"L{last}/S2/cand2d": arrays[f"L{last}/S2/cand2d"][:, :1]},
        "empty_2d": {f"L{last}/S{j}/cand2d": arrays[f"L{last}/S{j}/cand2d"][:, :0]
                     for j in range(3)},
        "narrow_3d": {f"L{last}/R2/cand": arrays[f"L{last}/R2/cand"][:, :1]},
        "channels": {"colors/1": arrays["colors/1"][..., :2]},
        "features": {f"L{last}/S1/feat": arrays[f"L{last}/S1/feat"].astype(np.int16) + 300},
        "projections": {f"L{last}/S0/proj": arrays[f"L{last}/S0/proj"] * 16},
        "shift": {"meta": np.frombuffer(json.dumps({**meta, "shifts": shifts}).encode(),
                                        np.uint8)},
    }
    _each_refused(tmp_path, arrays, changes)
    # Precompute's shift rounds a negative sum down, as far as -PROJ_LIMIT - 1: still read.
    lowest = arrays[f"L{last}/S0/proj"].copy()
    lowest[0, 0] = -candidates.PROJ_LIMIT - 1
    write_archive(tmp_path / "lowest.wtc", candidate_set.FILE_MAGIC, FORMAT_VERSION,
                  {**arrays, f"L{last}/S0/proj": lowest})
    CandidateSet.load(tmp_path / "lowest.wtc")


def test_a_checksummed_file_whose_layout_is_another_is_refused_naming_it(tmp_path, granite):
    """A file of a newer warptex (a parameter this one does not know) or written by other
    means (lists too short, numbers of another type) raised a bare TypeError or IndexError
    that named no file."""
    import json

    granite.save(tmp_path / "g.wtc")
    arrays = read_archive(tmp_path / "g.wtc", candidate_set.FILE_MAGIC, FORMAT_VERSION,
                          "candidate", CandidateCacheError)
    meta = json.loads(bytes(arrays["meta"]).decode())
    changes = {"newer": {"params": {**meta["params"], "a_later_setting": 1}},
               "no_levels": {"num_levels": 0}, "shifts": {"shifts": meta["shifts"][:1]},
               "axes": {"axis_source": [0.0, 0.0, 0.0]}}
    for name, change in changes.items():
        path = tmp_path / f"{name}.wtc"
        changed = {**arrays, "meta": np.frombuffer(json.dumps({**meta, **change}).encode(),
                                                   np.uint8)}
        write_archive(path, candidate_set.FILE_MAGIC, FORMAT_VERSION, changed)
        with pytest.raises(CandidateCacheError, match=f"{name}.wtc: unreadable candidate data"):
            CandidateSet.load(path)


def test_a_checksummed_file_of_numbers_that_narrow_into_range_is_refused(tmp_path, granite):
    """Arrays were narrowed to int32 before their bounds were checked: a candidate of 2^32
    read as 0, a count of 2^32 + 1 as 1; a float shift was truncated, NaN colors and too
    few packed fallback flags (padded with zeros) loaded."""
    import json

    granite.save(tmp_path / "g.wtc")
    arrays = read_archive(tmp_path / "g.wtc", candidate_set.FILE_MAGIC, FORMAT_VERSION,
                          "candidate", CandidateCacheError)
    meta = json.loads(bytes(arrays["meta"]).decode())
    last = granite.num_levels - 1

    def wrapped(name, at=0):
        a = arrays[name].astype(np.int64)
        a.flat[at] += 2**32
        return a

    shifts = [list(level) for level in meta["shifts"]]
    shifts[last][0] = float(shifts[last][0]) + 0.5
    colors = arrays["colors/0"].copy()
    colors[0, 0, 0] = np.nan
    changes = {
        "cand": {f"L{last}/R0/cand": wrapped(f"L{last}/R0/cand")},
        "cand2d": {f"L{last}/S0/cand2d": wrapped(f"L{last}/S0/cand2d")},
        "count": {f"L{last}/R0/count": wrapped(f"L{last}/R0/count")},
        "basis": {f"L{last}/S0/basis": wrapped(f"L{last}/S0/basis")},
        "fallback": {f"L{last}/R0/fallback": arrays[f"L{last}/R0/fallback"][:-1]},
        "nan": {"colors/0": colors},
        "wide_colors": {"colors/0": arrays["colors/0"].astype(np.float64)},
        "shift": {"meta": np.frombuffer(json.dumps({**meta, "shifts": shifts}).encode(),
                                        np.uint8)},
    }
    _each_refused(tmp_path, arrays, changes)


def test_a_checksummed_file_one_past_each_bound_of_its_layout_is_refused(tmp_path, three):
    """Each layout check at its edge, in a file of three exemplars of different sizes: a
    2D candidate one past the pixels (a synthesis from it ended the process), colors smaller
    than the finest level (an IndexError traceback), a role's candidate one past the pixels
    of the exemplar it indexes, arrays one row or column short, no dimensions, a negative
    shift or margin, a count one past the row, a projection one past its range, one role for
    three exemplars, a source of fewer feature channels, fractional candidates. Mutants that
    dropped or loosened each check passed every test."""
    import json

    cs, _ = three
    cs.save(tmp_path / "three.wtc")
    arrays = read_archive(tmp_path / "three.wtc", candidate_set.FILE_MAGIC, FORMAT_VERSION,
                          "candidate", CandidateCacheError)
    CandidateSet.load(tmp_path / "three.wtc")  # as written, it loads
    meta = json.loads(bytes(arrays["meta"]).decode())
    last = meta["num_levels"] - 1
    sizes = [s.size for s in cs.sources[last]]
    assert len(set(sizes)) == 3  # each role's others differ in size

    def changed(name: str, at: tuple, value: int) -> np.ndarray:
        a = arrays[name].copy()  # of its own type: only the bound under test is crossed
        a[at] = value
        assert a[at] == value
        return a

    def with_meta(**change) -> dict:
        return {"meta": np.frombuffer(json.dumps({**meta, **change}).encode(), np.uint8)}

    shifts = [list(level) for level in meta["shifts"]]
    shifts[last][0] = -1
    wide_shifts = [list(level) for level in meta["shifts"]]
    wide_shifts[last][0] = 32  # a shift of an int32 by 32 bits is undefined in the kernels
    margins = [[list(m) for m in level] for level in meta["margins"]]
    margins[last][0] = [-1, 0]
    pixels = [h * w for h, w in sizes]
    # Role 0's triples index the exemplars of axes 1 and 2, in that order.
    role0 = f"L{last}/R0/cand"
    basis, proj = arrays[f"L{last}/S0/basis"], arrays[f"L{last}/S0/proj"]
    _each_refused(tmp_path, arrays, {
        "cand2d_at_pixels": {f"L{last}/S0/cand2d": changed(f"L{last}/S0/cand2d", (0, 0),
                                                           pixels[0])},
        "cand2d_far": {f"L{last}/S0/cand2d": changed(f"L{last}/S0/cand2d", (0, 0),
                                                     pixels[0] + 5000)},
        "small_colors": {"colors/0": arrays["colors/0"][:8, :8]},
        "first_of_triple": {role0: changed(role0, (0, 0, 0), pixels[1])},
        "second_of_triple": {role0: changed(role0, (0, 0, 1), pixels[2])},
        "basis_columns": {f"L{last}/S0/basis": basis[:, :-3]},
        "proj_rows": {f"L{last}/S0/proj": proj[:-1]},
        "no_dims": {f"L{last}/S0/basis": basis[:0], f"L{last}/S0/proj": proj[:, :0]},
        "negative_shift": with_meta(shifts=shifts),
        "shift_of_32": with_meta(shifts=wide_shifts),
        "triples_of_three": {role0: np.concatenate([arrays[role0], arrays[role0][..., :1]],
                                                   axis=2)},
        "negative_margin": with_meta(margins=margins),
        "count_past_row": {f"L{last}/R0/count": changed(
            f"L{last}/R0/count", (0,), arrays[role0].shape[1] + 1)},
        "proj_past_range": {f"L{last}/S0/proj": changed(f"L{last}/S0/proj", (0, 0),
                                                        candidates.PROJ_LIMIT + 1)},
        "one_role": with_meta(num_roles=1),
        "fewer_features": {f"L{last}/S1/feat": arrays[f"L{last}/S1/feat"][..., :2],
                           f"L{last}/S1/basis": arrays[f"L{last}/S1/basis"][:, :-25]},
        "fractional": {role0: arrays[role0] + 0.5},
    })
    # The largest of each in range still loads: the checks are one past, not at, the bound.
    top = {role0: changed(role0, (0, 0, 0), pixels[1] - 1)}
    top[role0][0, 0, 1] = pixels[2] - 1
    write_archive(tmp_path / "top.wtc", candidate_set.FILE_MAGIC, FORMAT_VERSION,
                  {**arrays, **top})
    CandidateSet.load(tmp_path / "top.wtc")


def test_a_candidate_record_with_names_of_another_type_is_refused(tmp_path, granite):
    """Cache listings read the names as they come, so a hand-made record of other names
    must not reach them: its check, dropped, passed every test."""
    import json

    granite.save(tmp_path / "g.wtc")
    arrays = read_archive(tmp_path / "g.wtc", candidate_set.FILE_MAGIC, FORMAT_VERSION,
                          "candidate", CandidateCacheError)
    meta = json.loads(bytes(arrays["meta"]).decode())
    for names in (3, {"x": 1}, [1, 2, 3]):
        path = tmp_path / "names.wtc"
        record = np.frombuffer(json.dumps({**meta, "names": names}).encode(), np.uint8)
        write_archive(path, candidate_set.FILE_MAGIC, FORMAT_VERSION, {**arrays, "meta": record})
        with pytest.raises(CandidateCacheError, match=r"names\.wtc: unreadable candidate data"):
            candidate_set.read_cache_meta(path)


def test_a_file_whose_basis_reaches_past_127_is_refused(tmp_path, granite):
    """A basis coefficient of -128 (int8 holds it) makes the projections' float32 sums
    depend on their order of adding, so a CPU and a GPU could differ."""
    granite.save(tmp_path / "g.wtc")
    arrays = read_archive(tmp_path / "g.wtc", candidate_set.FILE_MAGIC, FORMAT_VERSION,
                          "candidate", CandidateCacheError)
    name = next(k for k in arrays if k.endswith("/basis"))
    basis = arrays[name].copy()
    basis.flat[0] = -128
    write_archive(tmp_path / "wide.wtc", candidate_set.FILE_MAGIC, FORMAT_VERSION,
                  {**arrays, name: basis})
    with pytest.raises(CandidateCacheError, match=r"wide\.wtc: unreadable candidate data"):
        CandidateSet.load(tmp_path / "wide.wtc")


def test_content_digest_is_kept_through_a_file_and_sees_one_coefficient(tmp_path, granite):
    granite.save(tmp_path / "g.wtc")
    assert CandidateSet.load(tmp_path / "g.wtc").content_digest == granite.content_digest
    # Equal sets are those of the same parameters too (their caches are other files).
    assert CandidateSet.load(tmp_path / "g.wtc") == granite
    assert dataclasses.replace(granite, params={**granite.params, "keep": 50}) != granite
    # Another LAPACK may round one PCA coefficient otherwise, under the same cache key.
    loaded = CandidateSet.load(tmp_path / "g.wtc")
    loaded.sources[1][0].basis[0, 0] += 1
    assert loaded.content_digest != granite.content_digest


def _changed(value):
    """``value`` with one entry (or the value itself) changed."""
    if isinstance(value, tuple):
        return (value[0] + 1, *value[1:])
    if not isinstance(value, np.ndarray):
        return value + 1
    changed = value.copy()
    flat = changed.reshape(-1)
    flat[len(flat) // 2] = not flat[len(flat) // 2] if changed.dtype == bool else flat[0] + 1
    return changed


@pytest.mark.parametrize("field", ["feat", "basis", "shift", "proj", "cand2d", "margins",
                                   "cand", "count", "fallback", "colors"])
def test_content_digest_sees_every_field_synthesis_reads(granite, field):
    """A digest leaving one out (the candidate counts, the margins) would let a brick store
    of other candidates pass for this one's under the same exemplars and parameters."""
    level = granite.num_levels - 1
    sources = [list(lvl) for lvl in granite.sources]
    roles = [list(lvl) for lvl in granite.roles]
    colors = list(granite.colors)
    if field == "colors":
        colors[0] = _changed(colors[0])
    elif field in ("cand", "count", "fallback"):
        role = roles[level][0]
        roles[level][0] = dataclasses.replace(role, **{field: _changed(getattr(role, field))})
    else:
        source = sources[level][0]
        sources[level][0] = dataclasses.replace(source,
                                                **{field: _changed(getattr(source, field))})
    other = dataclasses.replace(granite, sources=sources, roles=roles, colors=colors)
    assert other.content_digest != granite.content_digest
    assert dataclasses.replace(granite).content_digest == granite.content_digest


def _valid_header(payload: bytes, version: int = FORMAT_VERSION) -> bytes:
    return b"WARPTEXC" + version.to_bytes(4, "little") + hashlib.sha256(payload).digest()


def test_load_rejects_bad_magic_version_checksum_and_data(tmp_path, granite):
    granite.save(tmp_path / "g.wtc")
    data = (tmp_path / "g.wtc").read_bytes()
    cases = {
        "magic": (b"NOTWARPT" + data[8:], "not a warptex candidate file"),
        "version": (
            _valid_header(data[44:], FORMAT_VERSION + 1) + data[44:],
            f"version {FORMAT_VERSION + 1}, expected {FORMAT_VERSION}",
        ),
        "empty": (b"", "not a warptex candidate file"),
        "checksum": (_damage_flip(data), "checksum mismatch"),
        "payload": (_valid_header(b"garbage") + b"garbage", "unreadable candidate data"),
    }
    # Whole and checksummed, but not the arrays a candidate set is made of.
    write_archive(tmp_path / "arrays.wtc", candidate_set.FILE_MAGIC, FORMAT_VERSION,
                  {"x": np.zeros(1)})
    cases["arrays"] = ((tmp_path / "arrays.wtc").read_bytes(), "unreadable candidate data")
    for name, (content, message) in cases.items():
        (tmp_path / f"{name}.wtc").write_bytes(content)
        with pytest.raises(CandidateCacheError, match=message):
            CandidateSet.load(tmp_path / f"{name}.wtc")
    with pytest.raises(CandidateCacheError, match="cannot read"):
        CandidateSet.load(tmp_path / "missing.wtc")


# A valid value other than the default for every candidate parameter.
OTHER_PARAMS = {"neighborhood": 3, "strips": 33, "keep": 50, "candidates_3d": 8,
                "candidates_2d": 3, "candidates_2d_finest": 1, "variance": 0.9, "min_dims": 6,
                "max_dims": 10, "coherence_rounds": 8, "tileable": True}


def test_cache_file_name_depends_on_content_parameters_and_code(warp_device, monkeypatch):
    a = _crop(slice(0, 16), slice(0, 16))
    b = _crop(slice(0, 16), slice(16, 32))
    params = candidate_set.resolved_params({})
    assert cache_path([a, a, a], params) == cache_path([a, a, a], dict(params))
    assert cache_path([a, a, a], params) != cache_path([b, b, b], params)
    assert cache_path([a, b, a], params) != cache_path([a, a, b], params)
    assert set(OTHER_PARAMS) == set(candidate_set.DEFAULT_PARAMS)
    assert params.keys() == candidate_set.CandidateParams.__annotations__.keys()  # as typed
    for name, value in OTHER_PARAMS.items():  # files of two parameter sets never collide
        other = candidate_set.resolved_params({name: value})
        assert other != params
        assert cache_path([a, a, a], params) != cache_path([a, a, a], other), name
    before = cache_path([a, a, a], params)
    uncached_code_digest = candidates._code_digest.__wrapped__
    monkeypatch.setattr(candidates, "_code_digest", lambda: "other code")
    assert cache_path([a, a, a], params) != before
    # Sources that are not files (a zip or frozen application) key by the version instead.
    from_sources = uncached_code_digest()
    monkeypatch.setattr(candidates, "_deciding_sources", lambda: [Path("/no/such/module.py")])
    by_version = uncached_code_digest()
    assert len(by_version) == 64 and by_version != from_sources
    monkeypatch.setattr(candidates, "_deciding_sources", lambda: None)
    assert uncached_code_digest() == by_version
    # Another Warp compiles the kernels otherwise, another NumPy or SciPy may round
    # otherwise: their files are keyed otherwise.
    import scipy

    monkeypatch.setattr(candidates, "_deciding_sources", lambda: None)
    for module, name in ((wp.config, "version"), (np, "__version__"), (scipy, "__version__")):
        with monkeypatch.context() as patch:
            patch.setattr(module, name, getattr(module, name) + ".other")
            assert uncached_code_digest() != by_version, module
    monkeypatch.undo()
    assert uncached_code_digest() == from_sources


def test_cache_key_reads_the_code_that_decides_candidates(tmp_path):
    root = Path(candidates.__file__).resolve().parents[1]
    assert sorted(p.resolve().relative_to(root).as_posix()
                  for p in candidates._deciding_sources()) == [
        "kernels/candidates.py", "kernels/common.py", "warptex/candidate_set.py",
        "warptex/candidates.py",
        "warptex/exact_pca.py", "warptex/exemplar.py", "warptex/parallel.py",
        "warptex/warp_runtime.py"]
    files = [tmp_path / "a.py", tmp_path / "b.py"]
    for f in files:
        f.write_text("x = 1\n")
    first = sources_digest(files, "12 127")
    files[1].write_text("x = 2\n")
    assert sources_digest(files, "12 127") != first
    assert sources_digest(files, "12 127") != sources_digest(files, "8 127")


def test_cache_key_reads_the_constants_that_decide_candidates(monkeypatch):
    """The PCA's dimensions, the projections' range and the bases' range each change the
    candidates; the bases' range was left out of the key."""
    from warptex.candidates import _code_digest

    current = _code_digest.__wrapped__()
    for name in ("MAX_DIMS", "PROJ_LIMIT", "BASIS_LIMIT"):
        with monkeypatch.context() as patch:
            patch.setattr(candidates, name, getattr(candidates, name) - 1)
            assert _code_digest.__wrapped__() != current, name
    assert _code_digest.__wrapped__() == current


def test_unknown_or_bad_parameters_are_rejected():
    ex = _crop(slice(0, 16), slice(0, 16))
    with pytest.raises(TypeError, match="unknown candidate parameter"):
        precompute(ex, cache=False, strip=3)
    with pytest.raises(ValueError, match="neighborhood must be odd"):
        precompute(ex, cache=False, neighborhood=4)
    with pytest.raises(ValueError, match=r"candidates_3d must be within \[1, 255\]"):
        precompute(ex, cache=False, candidates_3d=300)  # its counts are stored as bytes
    with pytest.raises(ValueError, match=r"candidates_2d_finest must be within \[1, 64\]"):
        precompute(ex, cache=False, candidates_2d_finest=0)
    # Each of these crashed a kernel (keep 0), ran for hours (strips 100000), failed with a
    # message naming no parameter, or was kept and cached as given.
    bad = [({"keep": 0}, ValueError, r"keep must be within \[1, 65535\], got 0"),
           ({"strips": 100000}, ValueError, r"strips must be within \[1, 256\]"),
           ({"strips": -1}, ValueError, "strips must be within"),
           ({"max_dims": 0}, ValueError, "max_dims must be within"),
           ({"neighborhood": 11}, ValueError, r"neighborhood must be within \[3, 9\]"),
           ({"neighborhood": 5.5}, TypeError, "neighborhood must be an integer, got 5.5"),
           ({"neighborhood": "5"}, TypeError, "neighborhood must be an integer"),
           ({"keep": True}, TypeError, "keep must be an integer"),
           ({"coherence_rounds": -1}, ValueError, "coherence_rounds must be within"),
           ({"min_dims": 12, "max_dims": 8}, ValueError, r"min_dims \(12\) must not exceed"),
           ({"variance": 2.0}, ValueError, r"variance .* must be within \(0, 1\]"),
           ({"variance": float("nan")}, ValueError, "variance"),
           ({"variance": "0.9"}, TypeError, "variance must be a number"),
           ({"variance": 0}, ValueError, r"variance .* must be within \(0, 1\]"),
           ({"variance": True}, TypeError, "variance must be a number"),
           ({"coherence_rounds": 0}, ValueError, "coherence_rounds must be within"),
           ({"tileable": "yes"}, ValueError, 'tileable must be "auto", True or False'),
           ({"tileable": 1}, TypeError, "tileable must be"),
           ({"tileable": None}, TypeError, "tileable must be")]
    for params, error, message in bad:
        with pytest.raises(error, match=message):
            precompute(ex, cache=False, **params)
    with pytest.raises(ValueError, match="cache must be True or False, got 'no'"):
        precompute(ex, cache="no")
    with pytest.raises(ValueError, match="progress must be True or False"):
        precompute(ex, cache=False, progress="x")
    # A NumPy integer is an integer, and keys the cache as the plain one does.
    resolved = candidate_set.resolved_params({"neighborhood": np.int64(5)})
    assert resolved == candidate_set.DEFAULT_PARAMS and type(resolved["neighborhood"]) is int
    assert candidate_set.resolved_params({"tileable": np.bool_(False)})["tileable"] is False
    # The bounds themselves are taken: the whole variance, a dimension count fixed by
    # min_dims == max_dims; an integer variance is the float one (one cache name).
    fixed = candidate_set.resolved_params({"variance": 1, "min_dims": 8, "max_dims": 8})
    assert fixed["variance"] == 1.0 and type(fixed["variance"]) is float
    as_float = candidate_set.resolved_params({"variance": 1.0, "min_dims": 8, "max_dims": 8})
    assert cache_file_name(["d"], fixed) == cache_file_name(["d"], as_float)


def _squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a, b = a.astype(np.int64), b.astype(np.int64)
    return (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2 * a @ b.T


def _nearest(d2: np.ndarray, k: int) -> np.ndarray:
    """Per row, the k columns of least distance, equally near ones by index."""
    cols = np.broadcast_to(np.arange(d2.shape[1]), d2.shape)
    return np.lexsort((cols, d2), axis=-1)[:, :k]


def test_features_of_all_exemplars_are_quantized_over_one_range(granite_32, warp_device):
    colors = granite_32.colors
    images = [colors, 1.0 - colors, 0.5 * colors[:, :24]]
    cs = precompute(*[Exemplar(np.ascontiguousarray(c, np.float32), name=str(i))
                      for i, c in enumerate(images)], cache=False)
    # One range for all three colour channels too: distances are the L2 norm on colour
    # differences (Dong 2008, section 5.2), not each channel's over its own range.
    flat = np.concatenate([c.reshape(-1, 3) for c in images]).astype(np.float64)
    lo, hi = flat.min(), flat.max()
    for j, image in enumerate(images):
        expected = np.rint((image.astype(np.float32).astype(np.float64) - lo) / (hi - lo) * 255)
        np.testing.assert_array_equal(cs.sources[-1][j].feat, expected.astype(np.uint8))


def test_a_constant_channel_quantizes_without_warnings(warp_device):
    """A colour channel of one value (a flat blue) keeps that value on the colours' range; a
    feature channel of nothing has no range of its own to quantize over: it becomes 0, with
    no division by zero on the way."""
    colors = np.array(_granite()[:32, :32])
    colors[..., 2] = 0.5
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cs = precompute(Exemplar(colors, name="flat blue",
                                 feature_distance=np.zeros(colors.shape[:2], np.float32)),
                        cache=False)
    lo, hi = colors.min(), colors.max()
    blue = np.rint((np.float64(np.float32(0.5)) - lo) / (hi - lo) * 255)
    for lv, level in enumerate(cs.sources):
        assert (level[0].feat[..., 2] == blue).all(), lv
        assert not level[0].feat[..., 3].any(), lv
        assert level[0].feat[..., :2].std() > 0, lv


def test_a_flat_exemplar_keeps_the_fewest_dimensions_and_gives_its_color(warp_device):
    """No variance to keep: min_dims at every level (the fraction of none is taken as all
    of it), and the texture is the one color."""
    from warptex.texture import SolidTexture

    with pytest.warns(UserWarning, match="flat: image is constant"):
        flat = Exemplar(np.full((16, 16, 3), 0.5, np.float32), name="flat")
    cs = precompute(flat, cache=False)
    assert {level[0].basis.shape[0] for level in cs.sources} == {cs.params["min_dims"]}
    points = np.random.default_rng(0).uniform(-30, 30, (50, 3))
    assert (SolidTexture(cs).query(points) == np.float32(0.5)).all()


def test_pca_keeps_the_fewest_dimensions_that_hold_the_variance(granite_32, warp_device):
    cs = precompute(granite_32, cache=False, variance=0.7, min_dims=1, max_dims=12)
    dims = []
    for level in cs.sources:
        feat = level[0].feat.astype(np.float64)
        vec = np.concatenate([np.roll(feat, (-a, -b), axis=(0, 1)).reshape(-1, 3)
                              for a in range(-2, 3) for b in range(-2, 3)], axis=1)
        s = np.linalg.svd(vec - vec.mean(0), compute_uv=False) ** 2
        frac = np.cumsum(s) / s.sum()
        want = min(int(np.argmax(frac >= 0.7)) + 1, 12)
        assert level[0].basis.shape[0] == want
        dims.append(want)
    assert min(dims) < 12  # the variance, not the cap, decided somewhere
    floor = min(dims) + 1  # min_dims raises the levels that need fewer
    raised = precompute(granite_32, cache=False, variance=0.7, min_dims=floor, max_dims=12)
    assert [level[0].basis.shape[0] for level in raised.sources] == [max(d, floor)
                                                                     for d in dims]


def test_pca_basis_is_orthonormal_axes_on_one_common_scale(granite_32, warp_device):
    """The quantized basis is the principal axes, each of unit length, times one scale
    (127 over the largest coefficient): distances in appearance space weigh every kept
    component alike, as distances between the neighbourhoods themselves do."""
    cs = precompute(granite_32, cache=False)
    for lv, level in enumerate(cs.sources):
        basis = level[0].basis.astype(np.float64)
        assert np.abs(basis).max() == 127
        gram = basis @ basis.T
        scale = np.sqrt(np.diagonal(gram))
        # Rounding each coefficient moves a norm by well under 5 %.
        np.testing.assert_allclose(scale, scale.mean(), rtol=0.05, err_msg=f"level {lv}")
        off = gram / np.outer(scale, scale) - np.eye(len(gram))
        assert np.abs(off).max() < 0.05, lv


def test_pca_axes_point_to_their_largest_coefficient(granite_32, warp_device):
    """An eigensolver leaves each axis's sign free; the basis fixes it (its largest
    coefficient positive), so that the stored projections, and the files and digests
    that hold them, do not turn with the solver."""
    cs = precompute(granite_32, cache=False)
    for lv, level in enumerate(cs.sources):
        basis = level[0].basis
        assert (basis.max(axis=1) >= -basis.min(axis=1)).all(), lv


def test_projections_are_of_three_times_the_neighbourhood_in_basis_order(warp_device):
    """Synthesis projects a voxel's N x N neighbourhoods, sums of three exemplar colours,
    entry (a, b) then channel, a along the first pixel coordinate: the stored basis must
    take that layout, and the stored projections be those of 3 * feat under it. A 24x32
    crop, so that its neighbourhoods are not symmetric in a and b."""
    cs = precompute(_crop(slice(8, 32), slice(0, 32)), cache=False)
    half = int(cs.params["neighborhood"]) // 2
    for lv, level in enumerate(cs.sources):
        src = level[0]
        feat = src.feat.astype(np.int64)
        h, w, _ = feat.shape
        u, v = np.divmod(np.arange(h * w), w)
        vec = np.concatenate([feat[(u + a) % h, (v + b) % w]
                              for a in range(-half, half + 1) for b in range(-half, half + 1)],
                             axis=1)
        expected = (3 * vec) @ src.basis.astype(np.int64).T >> src.shift
        np.testing.assert_array_equal(src.proj, expected, f"level {lv}")
        # The least shift that fits them in range: they use its upper half, no bit lost.
        assert src.shift > 0 and np.abs(src.proj).max() > candidates.PROJ_LIMIT // 2, lv


def test_2d_candidates_are_the_nearest_neighbourhoods_more_than_2_pixels_away(granite_32,
                                                                               warp_device):
    cs = precompute(granite_32, cache=False)
    for level in cs.sources:
        src = level[0]
        h, w = src.size
        k = src.cand2d.shape[1]
        u, v = np.divmod(np.arange(h * w), w)
        du = np.abs(u[:, None] - u[None, :])
        dv = np.abs(v[:, None] - v[None, :])
        far = (np.minimum(du, h - du) > 2) | (np.minimum(dv, w - dv) > 2)
        d2 = np.where(far, _squared_distances(src.proj, src.proj), np.iinfo(np.int64).max)
        np.testing.assert_array_equal(src.cand2d[:, 0], np.arange(h * w))
        np.testing.assert_array_equal(src.cand2d[:, 1:], _nearest(d2, k - 1))


def _nearest_strips(feat: np.ndarray, strips: int, half: int):
    """Each pixel of ``feat``, the ``strips`` pixels whose first-coordinate strip is
    nearest its second-coordinate strip (pair 0-1), and the reverse (pair 2-0)."""
    pixels = np.arange(feat.shape[0] * feat.shape[1])
    first, second = (_strip(feat, pixels, axis, half).reshape(len(pixels), -1)
                     for axis in (0, 1))
    return (pixels, _nearest(_squared_distances(second, first), strips),
            _nearest(_squared_distances(first, second), strips))


def test_triples_come_from_the_nearest_crossbar_strips(granite_32, warp_device):
    """Section 4.1: q among the S strips nearest p's second-coordinate strip (pair 0-1),
    r among the S strips nearest p's first-coordinate strip (pair 2-0)."""
    strips = 4
    cs = precompute(granite_32, cache=False, strips=strips, keep=16)
    half = int(cs.params["neighborhood"]) // 2
    for lv, level in enumerate(cs.sources):
        _, near1, near2 = _nearest_strips(level[0].feat, strips, half)
        cand = cs.roles[lv][0].cand
        assert (cand[:, :, 0, None] == near1[:, None, :]).any(axis=2).all(), lv
        assert (cand[:, :, 1, None] == near2[:, None, :]).any(axis=2).all(), lv


def test_triples_are_among_the_keep_lowest_crossbar_errors(granite_32, warp_device):
    """Section 4.1: of the S^2 triples of a pixel only the ``keep`` of least crossbar
    error go on to the coherence test, so no stored triple scores worse than the keep-th
    best of them."""
    strips, keep = 4, 3
    cs = precompute(granite_32, cache=False, strips=strips, keep=keep)
    half = int(cs.params["neighborhood"]) // 2
    for lv, level in enumerate(cs.sources):
        feat = level[0].feat
        pixels, near1, near2 = _nearest_strips(feat, strips, half)
        triples = [np.broadcast_to(pixels[:, None, None], (len(pixels), strips, strips)),
                   np.broadcast_to(near1[:, :, None], (len(pixels), strips, strips)),
                   np.broadcast_to(near2[:, None, :], (len(pixels), strips, strips))]
        errors = np.sort(_crossbar([feat] * 3, triples, half).reshape(len(pixels), -1), axis=1)
        role = cs.roles[lv][0]
        valid = np.arange(role.crossbar_errors.shape[1])[None, :] < role.count[:, None]
        worst = np.where(valid, role.crossbar_errors, -1).max(axis=1)
        assert (worst <= errors[:, keep - 1]).all(), lv


def test_crossbar_triples_of_equal_error_keep_the_order_of_their_pair_rank(warp_device):
    """Section 4.1's sorted lists, to the triple where errors tie (integer strips tie
    often): the triple of q = near1[i] and r = near2[j] ranks i * S + j among equals, so
    the lists and every voxel after them are the same on every machine."""
    from kernels import candidates as kc
    from warptex.candidate_set import role_strips
    from warptex.warp_runtime import launch

    rng = np.random.default_rng(5)
    pixels, strips, keep = 9, 4, 7
    own_first, own_second, next_first, next_second, nnext_first, nnext_second = (
        rng.integers(0, 2, (pixels, 3)) for _ in range(6))
    near1, near2 = (np.stack([rng.permutation(pixels)[:strips] for _ in range(pixels)])
                    for _ in range(2))
    outputs = [wp.zeros((pixels, keep), dtype=t) for t in (wp.int64, wp.int32, wp.int32,
                                                           wp.int32)]
    keys, cand1, cand2, errors = outputs
    keys.fill_(np.iinfo(np.int64).max)
    count = wp.zeros(pixels, dtype=wp.int32)
    launch(kc.best_crossbar_triples, pixels,
           [0, role_strips([own_first, own_second, next_first, next_second, nnext_first,
                            nnext_second]),
            wp.array(near1, dtype=wp.int32), wp.array(near2, dtype=wp.int32),
            wp.empty((pixels, strips), dtype=wp.int32)], [*outputs, count])

    def distance(a, b):
        return ((a - b) ** 2).sum(axis=-1)

    ties = 0
    for p in range(pixels):
        q, r = near1[p][:, None], near2[p][None, :]
        error = (distance(own_second[p], next_first[q]) + distance(next_second[q], nnext_first[r])
                 + distance(nnext_second[r], own_first[p]))  # (S, S): rank i * S + j
        order = np.argsort(error.ravel(), kind="stable")[:keep]
        ties += len(order) - len(np.unique(error.ravel()[order]))
        assert cand1.numpy()[p].tolist() == near1[p][order // strips].tolist(), p
        assert cand2.numpy()[p].tolist() == near2[p][order % strips].tolist(), p
        assert errors.numpy()[p].tolist() == error.ravel()[order].tolist(), p
    assert count.numpy().tolist() == [keep] * pixels
    assert ties > pixels  # what the rule decides


def _ramp(rows: int, cols: int) -> Exemplar:
    """A noisy ramp from left to right: its left and right edges form a seam, its top and
    bottom edges do not."""
    rng = np.random.default_rng(2)
    ramp = np.linspace(0.0, 1.0, cols)[None, :, None] + 0.05 * rng.random((rows, cols, 3))
    return Exemplar(ramp.astype(np.float32), name="ramp")


def test_candidates_keep_away_from_the_edges_of_a_photo_that_does_not_tile(
        tmp_path, monkeypatch, warp_device):
    """Exemplars are tori to the paper (section 4), so a photo whose opposite edges differ
    would show its seam at every period. Its candidates keep N // 2 pixels from those
    edges instead, at every level with room for N pixels inside (no N x N neighbourhood of
    a candidate crosses the seam), silently; ``tileable=True`` keeps the paper's tori and
    ``tileable=False`` keeps away from every edge."""
    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path))
    ramp = _ramp(24, 32)
    assert ramp.seams() == (False, True) and ramp.seam_contrast()[0] > 10
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cs = precompute(ramp)
    sizes = [(6, 8), (12, 16), (24, 32)]
    assert [s[0].size for s in cs.sources] == sizes
    assert [s[0].margins for s in cs.sources] == [(0, 0), (0, 2), (0, 2)]
    for level in range(cs.num_levels):
        usable = cs.sources[level][0].usable()
        assert usable[cs.sources[level][0].cand2d].all()
        assert usable[cs.roles[level][0].cand].all()
    _assert_same(cs, CandidateSet.load(candidates.cache_path([ramp] * 3, cs.params)))

    torus = precompute(ramp, cache=False, tileable=True)
    assert all(s[0].margins == (0, 0) for s in torus.sources)
    margin = ~cs.sources[-1][0].usable()
    assert margin[torus.sources[-1][0].cand2d].any()
    assert torus.content_digest != cs.content_digest
    never = precompute(ramp, cache=False, tileable=False)
    assert [s[0].margins for s in never.sources] == [(0, 0), (2, 2), (2, 2)]

    granite = Exemplar.load(GRANITE)
    assert max(granite.seam_contrast()) < 1.1 and granite.seam_problem() is None
    assert granite.seams() == (False, False)


def test_candidates_blur_their_pyramid_as_tileable_says(tmp_path, monkeypatch, warp_device):
    """The seams the margins keep away from are those the pyramid reflects at."""
    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path))
    asked = []
    pyramid = Exemplar.pyramid

    def recorded(self, min_size=8, seams=None):
        asked.append(seams)
        return pyramid(self, min_size, seams)

    monkeypatch.setattr(Exemplar, "pyramid", recorded)
    ramp = _ramp(24, 32)
    for tileable, seams in (("auto", (False, True)), (True, (False, False)),
                            (False, (True, True))):
        asked.clear()
        precompute(ramp, cache=False, tileable=tileable)
        assert asked == [seams]


def test_the_pyramid_does_not_blur_across_a_seam():
    """A coarser level's blur wraps around the edges that tile but reflects at a seam, so
    no coarse pixel mixes the two ends of a ramp: each level rises from left to right, as
    the photo does. Wrapped as a torus, the first column takes in the last one's bright
    values."""
    ramp = _ramp(24, 32)
    for level in ramp.pyramid(min_size=2)[:-1]:
        assert (np.diff(level.colors.mean(axis=(0, 2))) > 0).all()
    torus = ramp.pyramid(min_size=2, seams=(False, False))[-2].colors.mean(axis=(0, 2))
    assert torus[0] > torus[1]
    granite = Exemplar.load(GRANITE)
    for level, wrapped in zip(granite.pyramid(), granite.pyramid(seams=(False, False)),
                              strict=True):
        assert np.array_equal(level.colors, wrapped.colors)


def test_pyramids_of_exemplars_of_different_sizes_align_at_the_finest_level(warp_device):
    """A 32x32 exemplar has three levels, a 16x16 one two: the 32x32 one's coarsest is
    left out, and the finest level is each exemplar itself."""
    big, small = _crop(slice(0, 32), slice(0, 32)), _crop(slice(32, 48), slice(32, 48))
    cs = precompute(big, small, small, cache=False)
    assert cs.num_levels == 2
    assert [[s.size for s in lvl] for lvl in cs.sources] == [[(16, 16), (8, 8)],
                                                           [(32, 32), (16, 16)]]
    np.testing.assert_array_equal(cs.colors[0], big.colors)
    np.testing.assert_array_equal(cs.colors[1], small.colors)


def test_the_finest_level_keeps_its_own_number_of_2d_candidates(warp_device):
    cs = precompute(_crop(slice(0, 32), slice(0, 32)), cache=False, candidates_2d=3,
                    candidates_2d_finest=1)
    assert [lvl[0].cand2d.shape[1] for lvl in cs.sources] == [3, 3, 1]


def test_a_z_exemplar_left_out_is_the_y_exemplar(warp_device):
    a, b = _crop(slice(0, 16), slice(0, 16)), _crop(slice(16, 32), slice(16, 32))
    assert precompute(a, b, cache=False).axis_source == (0, 1, 1)
    assert precompute(a, cache=False).axis_source == (0, 0, 0)


def test_a_cache_file_of_other_parameters_is_reported_and_replaced(warp_device):
    """Copied onto the name of other parameters' candidates, a whole file of the same
    exemplar is not served under them."""
    ex = _crop(slice(0, 16), slice(0, 16))
    precompute(ex)
    params = candidate_set.resolved_params({"neighborhood": 3})
    wanted = cache_path([ex] * 3, params)
    wanted.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(cache_path([ex] * 3, candidate_set.resolved_params({})), wanted)
    with pytest.warns(UserWarning, match="candidates of other exemplars or parameters"):
        cs = precompute(ex, neighborhood=3)
    assert cs.params["neighborhood"] == 3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert precompute(ex, neighborhood=3).params["neighborhood"] == 3


def test_margins_keep_candidates_off_each_seamed_edge_on_both_sides(warp_device):
    """A ramp's left and right edges form a seam, its top and bottom do not: no candidate
    lies in the 2 columns at either side, and every row may hold one (margins (0, 2),
    told apart: rows and columns, near and far side)."""
    rng = np.random.default_rng(2)
    ramp = Exemplar((np.linspace(0.0, 1.0, 32)[None, :, None]
                     + 0.05 * rng.random((24, 32, 3))).astype(np.float32), name="ramp")
    cs = precompute(ramp, cache=False)
    for lvl, roles in zip(cs.sources[1:], cs.roles[1:], strict=True):
        src = lvl[0]
        h, w = src.size
        assert src.margins == (0, 2)
        expected = np.zeros((h, w), bool)
        expected[:, 2:w - 2] = True
        np.testing.assert_array_equal(src.usable(), expected.reshape(-1))
        for held in (src.cand2d, roles[0].cand):
            rows, cols = np.divmod(held, w)
            assert cols.min() == 2 and cols.max() == w - 3
            assert rows.min() == 0 and rows.max() == h - 1


def test_pca_of_a_photo_that_does_not_tile_is_of_the_neighbourhoods_inside_its_margins(
        warp_device):
    """Candidates never lie in the margins, whose neighbourhoods wrap across the seam, so
    the appearance space is that of the neighbourhoods inside them: each axis of the basis
    lies in the span of the leading principal axes of those (numpy's eigensolver), within
    its quantization."""
    cs = precompute(_ramp(24, 32), cache=False)
    assert cs.sources[-1][0].margins == (0, 2)
    for lv, level in enumerate(cs.sources):
        src = level[0]
        feat = src.feat.astype(np.int64)
        h, w, _ = feat.shape
        u, v = np.divmod(np.flatnonzero(src.usable()), w)
        vec = 3 * np.concatenate([feat[(u + a) % h, (v + b) % w]
                                  for a in range(-2, 3) for b in range(-2, 3)], axis=1)
        axes = np.linalg.eigh(np.cov(vec.astype(np.float64), rowvar=False))[1]
        leading = axes[:, ::-1][:, :src.basis.shape[0]]
        basis = src.basis / np.linalg.norm(src.basis, axis=1, keepdims=True)
        outside = np.linalg.norm(basis - basis @ leading @ leading.T, axis=1)
        assert outside.max() < 0.05, (lv, outside)


def test_each_role_keeps_to_the_margins_of_its_own_exemplars(warp_device):
    """With a different exemplar on each axis, each coordinate of a triple keeps to the
    margins of the exemplar it indexes: granite, which tiles, a ramp with a seam between
    its left and right edges and a smaller ramp turned (a seam between top and bottom)."""
    turned = Exemplar(np.ascontiguousarray(_ramp(24, 32).colors.transpose(1, 0, 2)),
                      name="turned")
    cs = precompute(Exemplar.load(GRANITE), _ramp(48, 64), turned, cache=False)
    assert [s.margins for s in cs.sources[-1]] == [(0, 0), (0, 2), (2, 0)]
    for lv, r in _role_cases(cs):
        trio = _trio(cs, lv, r)
        cand = cs.roles[lv][r].cand
        for k in (0, 1):
            assert trio[k + 1].usable()[cand[..., k]].all(), (lv, r, k)


def test_the_bar_moves_after_each_half_of_a_role_level(monkeypatch, warp_device):
    """A role's crossbar search and coherence test are about half its time each (24 s at a
    256 px finest level, where the bar stood still): the bar moves after each."""
    updates: list[float] = []

    class Bar:
        def __init__(self, *args, **kwargs) -> None:
            pass

        def update(self, n: float) -> None:
            updates.append(n)

        def close(self) -> None:
            pass

    monkeypatch.setattr(candidates, "tqdm", Bar)
    exemplar = Exemplar.load(GRANITE)
    precompute(exemplar, cache=False, progress=True)
    finest = exemplar.shape[0] * exemplar.shape[1]
    assert updates[-3:] == [finest, finest / 2, finest / 2]  # its source, then the halves


@pytest.mark.parametrize(("xdg", "expected"), [
    (None, "{home}/.cache/warptex"), ("", "{home}/.cache/warptex"),
    ("/srv/cache", "/srv/cache/warptex"), ("relcache", "{home}/.cache/warptex"),
])
def test_the_cache_folder_follows_xdg_cache_home_when_absolute(monkeypatch, tmp_path, xdg,
                                                                expected):
    """A relative XDG_CACHE_HOME put the cache in whatever folder a command ran from."""
    from warptex.candidates import cache_dir

    monkeypatch.delenv("WARPTEX_CACHE", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    if xdg is None:
        monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    else:
        monkeypatch.setenv("XDG_CACHE_HOME", xdg)
    assert cache_dir() == Path(expected.format(home=tmp_path))


def test_the_cached_file_looked_up_is_that_of_the_setting_tileable(warp_device, tmp_path,
                                                                  monkeypatch):
    """`warptex info` says whether candidates are cached for the tileable asked: the file
    of tileable=True is not the file of "auto"."""
    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path))
    ex = _crop(slice(0, 16), slice(0, 16))
    precompute(ex, tileable=True)
    assert cached_candidate_path(ex, True) is not None
    assert cached_candidate_path(ex, "auto") is None
