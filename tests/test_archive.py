"""Versioned, checksummed archives of arrays (`warptex.archive`): the layout the candidate
cache and brick store files share, and what reading and writing one holds in memory."""

from __future__ import annotations

import hashlib
import io
import tracemalloc

import numpy as np
import pytest

from warptex.archive import (
    _DIGEST_BYTES,
    _VERSION_BYTES,
    ArchiveError,
    read_archive,
    write_archive,
)

MAGIC = b"WTXTEST\0"


def arrays(megabytes: int = 1) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    return {"name": np.array("granite"), "keys": rng.integers(0, 2**40, 1000),
            "triples": rng.integers(0, 4096, ((megabytes << 20) // 12, 3), dtype=np.int32)}


def assert_same(found: dict[str, np.ndarray], expected: dict[str, np.ndarray]) -> None:
    assert found.keys() == expected.keys()
    for key, value in expected.items():
        assert found[key].dtype == value.dtype and np.array_equal(found[key], value), key


def test_an_archive_is_a_header_then_a_plain_npz_it_hashes(tmp_path):
    """Files stay readable across versions: the payload is an ``.npz`` NumPy reads on its
    own, under the magic, the version and its SHA-256, as it always was."""
    expected = arrays()
    write_archive(tmp_path / "a.wta", MAGIC, 3, expected)
    data = (tmp_path / "a.wta").read_bytes()
    start = len(MAGIC) + _VERSION_BYTES
    payload = data[start + _DIGEST_BYTES:]
    assert data[:len(MAGIC)] == MAGIC and int.from_bytes(data[len(MAGIC):start], "little") == 3
    assert data[start:start + _DIGEST_BYTES] == hashlib.sha256(payload).digest()
    with np.load(io.BytesIO(payload), allow_pickle=False) as z:
        assert_same(dict(z), expected)
    # As earlier versions wrote it: the payload made whole in memory by np.savez.
    earlier = io.BytesIO()
    np.savez(earlier, **expected)
    payload = earlier.getvalue()
    (tmp_path / "b.wta").write_bytes(data[:start] + hashlib.sha256(payload).digest() + payload)
    assert_same(read_archive(tmp_path / "b.wta", MAGIC, 3, "test"), expected)
    assert_same(read_archive(tmp_path / "a.wta", MAGIC, 3, "test"), expected)
    with pytest.raises(ArchiveError, match=r"a\.wta: test file version 3, expected 4"):
        read_archive(tmp_path / "a.wta", MAGIC, 4, "test")


def test_reading_or_writing_an_archive_holds_no_copy_of_the_file(tmp_path):
    """A brick store file takes up to the store's memory: its bytes, held whole beside the
    arrays (once to hash, once sliced, once read), made loading one take four times its
    size, and saving three."""
    expected = arrays(megabytes=64)
    size = sum(a.nbytes for a in expected.values())
    tracemalloc.start()
    try:
        write_archive(tmp_path / "a.wta", MAGIC, 1, expected)
        written = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        found = read_archive(tmp_path / "a.wta", MAGIC, 1, "test")
        read = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert_same(found, expected)
    assert written < size / 2, f"writing {size} bytes of arrays held {written}"
    assert read < size * 1.5, f"reading {size} bytes of arrays held {read}"
