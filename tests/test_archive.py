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
    archive_version,
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


def test_a_file_cut_inside_its_header_or_of_another_magic_is_no_archive(tmp_path):
    """Not an archive at all (the cache lists it damaged), not one of version 0 or 3: the
    magic alone, the magic and a version, a header one byte short; a magic differing in its
    last byte only; a payload changed after its checksum; a newer version."""
    write_archive(tmp_path / "a.wta", MAGIC, 3, arrays(1))
    data = (tmp_path / "a.wta").read_bytes()
    header = len(MAGIC) + _VERSION_BYTES + _DIGEST_BYTES
    cut = tmp_path / "cut.wta"
    for length in (len(MAGIC), len(MAGIC) + _VERSION_BYTES, header - 1):
        cut.write_bytes(data[:length])
        assert archive_version(cut, MAGIC) is None, length
        with pytest.raises(ArchiveError, match=r"cut\.wta: not a warptex test file"):
            read_archive(cut, MAGIC, 3, "test")
    other = tmp_path / "other.wta"
    other.write_bytes(MAGIC[:-1] + b"X" + data[len(MAGIC):])
    assert archive_version(other, MAGIC) is None
    with pytest.raises(ArchiveError, match="not a warptex test file"):
        read_archive(other, MAGIC, 3, "test")
    flipped = bytearray(data)
    flipped[-100] ^= 1
    (tmp_path / "flipped.wta").write_bytes(bytes(flipped))
    with pytest.raises(ArchiveError, match="checksum mismatch"):
        read_archive(tmp_path / "flipped.wta", MAGIC, 3, "test")
    assert archive_version(tmp_path / "a.wta", MAGIC) == 3
    with pytest.raises(ArchiveError, match="test file version 3, expected 2"):
        read_archive(tmp_path / "a.wta", MAGIC, 2, "test")
