"""Packed coordinate keys, and sorted key sets: the same answers as numpy's unique, empty
arrays included."""

import numpy as np

from warptex.keysets import distinct_sorted, lookup, lookup_runs, pack, run_starts, unique, unpack
from warptex.surface import _unique_rows


def test_unique_matches_numpy():
    rng = np.random.default_rng(1)
    # The last holds runs of repeats, as a box's block keys do, split and met again.
    for a in (rng.integers(-(1 << 40), 1 << 40, 5000), rng.integers(0, 7, 300),
              np.zeros(0, np.int64), np.array([5]), np.repeat(rng.integers(0, 9, 200), 4)):
        np.testing.assert_array_equal(unique(a), np.unique(a))
        np.testing.assert_array_equal(distinct_sorted(np.sort(a)), np.unique(a))


def test_run_starts_finds_the_first_of_each_run():
    assert run_starts(np.array([3, 3, 1, 1, 1, 3, 7])).tolist() == [0, 2, 5, 6]
    assert run_starts(np.array([4])).tolist() == [0]
    assert run_starts(np.zeros(0, np.int32)).tolist() == []


def test_unique_rows_sorted_like_numpy():
    rng = np.random.default_rng(2)
    v = rng.integers(-30, 30, (4000, 3)).astype(np.int32)
    got = _unique_rows(v)
    np.testing.assert_array_equal(got, np.unique(v, axis=0))
    assert got.dtype == np.int32 and _unique_rows(v[:0]).shape == (0, 3)


def test_packed_keys_round_trip_and_keep_the_order_of_coordinates():
    rng = np.random.default_rng(3)
    limit = (1 << 20) - 1
    c = np.concatenate([rng.integers(-limit, limit, (3000, 3)),
                        [[-limit, -limit, -limit], [limit, limit, limit], [-1, 0, 1]]])
    keys = pack(c)
    np.testing.assert_array_equal(unpack(keys), c)
    np.testing.assert_array_equal(np.argsort(keys, kind="stable"),
                                  np.lexsort((c[:, 2], c[:, 1], c[:, 0])))


def test_lookup_finds_each_present_key_and_only_those():
    rng = np.random.default_rng(3)
    keys = np.unique(rng.integers(-50, 50, 40))
    query = rng.integers(-60, 60, 500)
    where = {int(k): i for i, k in enumerate(keys)}
    expected = [where.get(int(q), -1) for q in query]
    assert lookup(keys, query).tolist() == expected
    assert lookup(keys[:0], query).tolist() == [-1] * len(query)


def test_lookup_of_runs_is_lookup():
    rng = np.random.default_rng(4)
    keys = np.unique(rng.integers(-50, 50, 40))
    runs = np.repeat(rng.integers(-60, 60, 300), rng.integers(1, 6, 300))
    for query in (runs, rng.integers(-60, 60, 500), runs[:1], runs[:0]):
        np.testing.assert_array_equal(lookup_runs(keys, query), lookup(keys, query))
    assert lookup_runs(keys, runs).dtype == lookup(keys, runs).dtype


def test_a_cell_s_voxels_are_numbered_x_slowest_in_both_directions():
    """The order the kernels number a block's or brick's voxels in: the offsets' index is
    the local index, and negative voxels sit in their cell as positive ones do."""
    from warptex.keysets import cell_offsets, local_index

    for size in (2, 4, 8):
        offsets = cell_offsets(size)
        np.testing.assert_array_equal(local_index(offsets, size), np.arange(size**3))
        np.testing.assert_array_equal(local_index(offsets - 3 * size, size), np.arange(size**3))
    assert cell_offsets(2)[1].tolist() == [0, 0, 1] and cell_offsets(2)[4].tolist() == [1, 0, 0]
    assert local_index(np.array([[-1, 0, 1], [5, -6, 7]]), 4).tolist() == [49, 27]
