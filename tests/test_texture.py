"""SolidTexture point queries: values, determinism, persistence, threads, bad input."""

from __future__ import annotations

import hashlib
import subprocess
import sys
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest
import warp as wp

from warptex.store import BrickStore
from warptex.store_files import StoreFileError

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def candidates(granite_32_file, warp_device):
    from warptex.candidates import precompute

    return precompute(granite_32_file)


@pytest.fixture(scope="module")
def reference(candidates):
    from warptex.synthesis import Synthesizer

    return Synthesizer(candidates, device="cpu")


def texture(candidates, **kw):
    from warptex.texture import SolidTexture

    return SolidTexture(candidates, device="cpu", **kw)


def trilinear(reference, points: np.ndarray) -> np.ndarray:
    """The blend of the 8 voxel centers around each point, from the engine's voxels."""
    q = points.astype(np.float64) - 0.5
    base = np.floor(q).astype(np.int64)
    t = q - base
    out = np.zeros((len(points), reference.candidates.channels))
    for d in np.indices((2, 2, 2)).reshape(3, -1).T:
        w = np.prod(np.where(d == 1, t, 1 - t), axis=1)
        out += w[:, None] * reference.voxels(base + d)
    return out


def points_near_origin(n: int, seed: int) -> np.ndarray:
    """Random points over [-10, 10)^3: negative coordinates and brick borders at -8, 0, 8."""
    return np.random.default_rng(seed).uniform(-10, 10, (n, 3))


# Voxel coordinates on both sides of brick borders, negative ones included.
BORDER = np.array([[-9, -8, -1], [-1, 0, 7], [7, 8, -8], [0, -1, 8], [8, 7, 0], [-8, -9, 15]])


def test_nearest_at_centers_equals_engine_voxels(candidates, reference):
    tex = texture(candidates)
    got = tex.query(BORDER + 0.5, filter="nearest")
    assert got.dtype == np.float32 and got.shape == (len(BORDER), tex.channels)
    np.testing.assert_array_equal(got, reference.voxels(BORDER))


def test_nearest_reads_the_voxel_containing_the_point(candidates, reference):
    tex = texture(candidates)
    pts = points_near_origin(300, 1).astype(np.float32)
    np.testing.assert_array_equal(tex.query(pts, filter="nearest"),
                                  reference.voxels(np.floor(pts).astype(np.int64)))


def test_trilinear_blends_the_8_centers_across_brick_borders(candidates, reference):
    tex = texture(candidates)
    straddling = (BORDER + 1.0).astype(np.float64)  # halfway between voxel centers
    pts = np.concatenate([straddling, straddling + 0.25, points_near_origin(200, 2)])
    np.testing.assert_allclose(tex.query(pts), trilinear(reference, pts), rtol=1e-6, atol=1e-6)
    # At a voxel center the blend is that voxel's color exactly.
    np.testing.assert_array_equal(tex.query(BORDER + 0.5), reference.voxels(BORDER))


def test_trilinear_in_partly_filled_bricks_synthesizes_the_corners_not_stored(candidates,
                                                                             reference):
    """Voxel by voxel (whole_bricks=False), one corner of a blend stored in each of the two
    bricks it straddles: the six corners not stored are synthesized, not read from pool
    positions that hold other voxels."""
    tex = texture(candidates, whole_bricks=False)
    tex.query(np.array([[7.5, 2.5, 5.5], [8.5, 3.5, 6.5]]), filter="nearest")
    pts = np.array([[8.0, 3.0, 6.0], [7.75, 3.25, 6.1]])  # corners (7..8, 2..3, 5..6)
    np.testing.assert_allclose(tex.query(pts), trilinear(reference, pts), rtol=1e-6, atol=1e-6)
    assert tex.store.stats()["voxels"] == 8


def test_the_whole_query_range_can_be_read(candidates, reference):
    """Points up to POINT_LIMIT on either side, whole bricks filled around them (the
    brick of the lowest point reaches the lowest voxel the engine takes)."""
    from warptex.texture import POINT_LIMIT

    tex = texture(candidates, whole_bricks=True)
    ends = np.array([[1.0 - POINT_LIMIT, 0.5, 0.5], [POINT_LIMIT - 1.0, 0.5, 0.5]])
    np.testing.assert_array_equal(tex.query(ends, filter="nearest"),
                                  reference.voxels(np.floor(ends).astype(np.int64)))
    assert tex.query(ends).shape == (2, tex.channels)


def test_far_slices_read_the_voxels_their_points_lie_in(candidates, reference):
    """A slice's points are not rounded to float32 on the way: at x = 4e6 + 0.9 that
    would move them into the next voxel."""
    tex = texture(candidates)
    far = tex.slice((4_000_000.9, -3.5, 2.5), (0, 1, 0), (0, 0, 1), (2, 3), filter="nearest")
    voxels = [[4_000_000, -4 + r, 2 + c] for r in range(2) for c in range(3)]
    np.testing.assert_array_equal(far.reshape(6, -1), reference.voxels(np.array(voxels)))


@pytest.mark.parametrize("filter", ["nearest", "trilinear"])
def test_batch_composition_and_order_do_not_change_colors(candidates, filter):
    pts = points_near_origin(200, 3)
    alone = texture(candidates).query(pts, filter=filter)
    others = points_near_origin(500, 4) * 1.5
    batch = np.concatenate([others, pts])
    order = np.random.default_rng(5).permutation(len(batch))
    tex = texture(candidates)
    tex.query(others[:50], filter=filter)  # some bricks already stored, some not
    shuffled = tex.query(batch[order], filter=filter)
    back = np.empty_like(shuffled)
    back[order] = shuffled
    np.testing.assert_array_equal(back[len(others):], alone)
    np.testing.assert_array_equal(texture(candidates).query(pts[::-1], filter=filter),
                                  alone[::-1])


def test_queries_of_several_batches_give_each_point_its_own_color(candidates, monkeypatch):
    """A query of more than BATCH points runs batch after batch: each point, filled ones
    among them, keeps the color a query of it alone gives."""
    from warptex import texture as texture_module

    pts = points_near_origin(150, 12)
    pts[[5, 70, 149]] = np.nan
    expected = np.concatenate([texture(candidates).query(p[None], fill=0.25) for p in pts])
    monkeypatch.setattr(texture_module, "BATCH", 64)
    np.testing.assert_array_equal(texture(candidates).query(pts, fill=0.25), expected)


def test_slabs_give_each_point_the_color_of_one_query(candidates, monkeypatch):
    """query_slabs (slice, bake) takes the points in order of x, several slabs of them:
    each point still gets its own color, in the caller's order."""
    from warptex import texture as texture_module

    monkeypatch.setattr(texture_module, "_SLAB", 64)
    pts = points_near_origin(300, 9)
    for filter in ("nearest", "trilinear"):
        expected = texture(candidates).query(pts, filter=filter)
        got = texture_module.query_slabs(texture(candidates), pts, filter)
        np.testing.assert_array_equal(got, expected)


def test_eviction_does_not_change_colors(candidates):
    pts = points_near_origin(400, 6)
    expected = texture(candidates).query(pts)
    tex = texture(candidates, cache_bytes=3 * (512 * 6 + 64))  # three bricks
    got = np.concatenate([tex.query(pts[i : i + 40]) for i in range(0, len(pts), 40)])
    again = tex.query(pts)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(again, expected)
    stats = tex.store.stats()
    assert stats["bricks"] <= 3 and stats["bricks_evicted"] > 0


def test_persistence_round_trip_starts_warm(candidates, tmp_path):
    pts = points_near_origin(300, 7)
    path = tmp_path / "granite.wtb"
    tex = texture(candidates, store=path)
    expected = {f: tex.query(pts, filter=f) for f in ("nearest", "trilinear")}
    assert tex.save() == path
    warm = texture(candidates, store=path)
    for f, colors in expected.items():
        np.testing.assert_array_equal(warm.query(pts, filter=f), colors)
    stats = warm.store.stats()
    assert stats["voxels_added"] == 0 and stats["misses"] == 0
    assert stats["voxels"] == tex.store.stats()["voxels"]
    # A missing folder is made, as the commands' -o make theirs.
    nested = tmp_path / "shots" / "a" / "granite.wtb"
    assert tex.save(nested) == nested
    np.testing.assert_array_equal(texture(candidates, store=nested).query(pts),
                                  expected["trilinear"])


def test_persistence_in_a_new_process(candidates, tmp_path):
    pts = points_near_origin(100, 8)
    path = tmp_path / "granite.wtb"
    tex = texture(candidates, store=path)
    expected = tex.query(pts)
    tex.save()
    np.save(tmp_path / "points.npy", pts)
    script = (
        "import sys, numpy as np\n"
        "from warptex.texture import SolidTexture\n"
        "from warptex.candidates import CandidateSet\n"
        f"tex = SolidTexture(CandidateSet.load(sys.argv[1]), device='cpu', store=r'{path}')\n"
        f"out = tex.query(np.load(r'{tmp_path / 'points.npy'}'))\n"
        "assert tex.store.stats()['voxels_added'] == 0\n"
        f"np.save(r'{tmp_path / 'out.npy'}', out)\n"
    )
    candidates.save(tmp_path / "cand.wtc")
    subprocess.run([sys.executable, "-c", script, str(tmp_path / "cand.wtc")], check=True,
                   cwd=REPO, timeout=120)
    np.testing.assert_array_equal(np.load(tmp_path / "out.npy"), expected)


_SAVING_AT_ONCE = """
import sys, time
from pathlib import Path

import numpy as np
import warptex.store
from warptex.candidate_set import CandidateSet
from warptex.texture import SolidTexture

candidates, store, go, k = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4])
write_bricks = warptex.store.write_bricks


def slowly(*args):  # a network disk: saves that do not take turns would overlap
    time.sleep(0.5)
    write_bricks(*args)


warptex.store.write_bricks = slowly
tex = SolidTexture(CandidateSet.load(candidates), device="cpu", store=store,
                   whole_bricks=False)
tex.query(np.array([[8.0 * k + 0.5, 0.5, 0.5]]), filter="nearest")
while not go.exists():
    time.sleep(0.01)
tex.save()
"""


def test_processes_saving_one_store_at_once_keep_each_other_s_voxels(candidates, tmp_path):
    """A render farm's jobs sharing one store file on a slow disk: saves take turns across
    processes (a lock on the folder), so each merges the file the one before wrote; with
    all released together, the file holds every process's voxel, each the engine's
    (without the lock it held one)."""
    candidates.save(tmp_path / "cand.wtc")
    store, go = tmp_path / "shared.wtb", tmp_path / "go"
    jobs = [subprocess.Popen([sys.executable, "-c", _SAVING_AT_ONCE, str(tmp_path / "cand.wtc"),
                              str(store), str(go), str(k)], cwd=REPO) for k in range(3)]
    go.touch()  # after all have started: most wait for it with their voxel synthesized
    assert [job.wait(timeout=300) for job in jobs] == [0, 0, 0]
    shared = texture(candidates, store=store, whole_bricks=False)
    voxels = np.array([[8 * k, 0, 0] for k in range(3)])
    colors = shared.query(voxels + 0.5, filter="nearest")
    assert shared.store.stats()["voxels"] == 3 and shared.store.stats()["voxels_added"] == 0
    np.testing.assert_array_equal(colors, shared.synthesizer.voxels(voxels))


def test_corrupt_or_stale_store_is_ignored_and_a_foreign_file_refused(candidates, tmp_path):
    pts = points_near_origin(50, 9)
    path = tmp_path / "granite.wtb"
    tex = texture(candidates, store=path)
    expected = tex.query(pts)
    tex.save()
    del tex  # a live texture of other settings would be refused the file
    with pytest.warns(UserWarning, match="another texture"):
        other = texture(candidates, seed=1, store=path)
    assert other.store.stats()["bricks"] == 0
    del other
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.warns(UserWarning, match="checksum"):
        damaged = texture(candidates, store=path)
    np.testing.assert_array_equal(damaged.query(pts), expected)
    path.write_bytes(b"not a store")
    with pytest.raises(StoreFileError, match="not a warptex brick store"):
        texture(candidates, store=path)
    assert path.read_bytes() == b"not a store"


def test_a_foreign_store_file_is_refused_before_the_candidates_are_computed(tmp_path,
                                                                           monkeypatch):
    """Pre-computing a large exemplar's candidates takes minutes: not spent on a texture
    whose store file would be refused after them."""
    import warptex.texture
    from warptex.texture import SolidTexture

    def computed(*args, **kwargs):
        raise AssertionError("candidates computed before the store file was checked")

    monkeypatch.setattr(warptex.texture, "precompute", computed)
    foreign = tmp_path / "photo.png"
    foreign.write_bytes(b"an image the user keeps")
    with pytest.raises(StoreFileError, match=r"photo\.png: exists and is not a warptex brick"):
        SolidTexture(tmp_path / "any.png", store=foreign)
    with pytest.raises(StoreFileError, match="is a folder, expected a brick store file"):
        SolidTexture(tmp_path / "any.png", store=tmp_path)
    assert foreign.read_bytes() == b"an image the user keeps"


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"seed": -1}, "seed must be within"), ({"jitter": 100}, "jitter must be within"),
    ({"passes": 99}, "passes must be within"), ({"cache_bytes": -5}, "cache_bytes must be at"),
    ({"whole_bricks": "no"}, "whole_bricks must be True or False"),
    ({"shifted_tiles": "no"}, "shifted_tiles must be True or False"),
    ({"device": "cdua"}, "device must be a Warp device"),
])
def test_settings_are_refused_before_the_candidates_are_computed(granite_32_file, kwargs,
                                                                 message, monkeypatch):
    """Each was refused by the engine or the store, made after minutes of pre-computation
    for a large exemplar."""
    import warptex.texture
    from warptex.texture import SolidTexture

    monkeypatch.setattr(warptex.texture, "precompute",
                        lambda *a, **k: pytest.fail("candidates computed before the check"))
    with pytest.raises(ValueError, match=message):
        SolidTexture(granite_32_file, **kwargs)


def test_an_exemplar_of_too_many_channels_is_refused_before_its_candidates(monkeypatch):
    import warptex.texture
    from warptex.exemplar import Exemplar
    from warptex.texture import SolidTexture

    monkeypatch.setattr(warptex.texture, "precompute",
                        lambda *a, **k: pytest.fail("candidates computed before the check"))
    five = np.random.default_rng(0).random((16, 16, 5), dtype=np.float32)
    with pytest.raises(ValueError, match="5 color channels; points are looked up in at most 4"):
        SolidTexture(Exemplar(five))


def test_a_store_that_could_never_be_saved_is_refused_before_any_work(candidates, tmp_path,
                                                                     monkeypatch):
    """A store named as a folder, or where it does not exist and could not be written, is
    refused when the texture is made (as the plugin's cache is), not at its first save; an
    existing one is read even from a place that cannot be written; save() names its path."""
    import warptex.texture

    with pytest.raises(StoreFileError, match=r"store names a folder, not a file: '.*/bricks/'"):
        texture(candidates, store=f"{tmp_path}/bricks/")
    existing = tmp_path / "kept.wtb"
    texture(candidates, store=existing).save()
    monkeypatch.setattr(warptex.texture, "file_problem",
                        lambda path: f"cannot write in {path.parent} (Read-only file system)")
    with pytest.raises(StoreFileError, match=r"new\.wtb: a brick store could not be saved "
                                             r"there: cannot write in .* \(Read-only"):
        texture(candidates, store=tmp_path / "new.wtb")
    assert texture(candidates, store=existing).store.stats()["bricks"] == 0
    with pytest.raises(TypeError, match=r"path must be a file name \(str or Path\), got 3"):
        texture(candidates).save(3)
    # save(path) is checked as store= is, before a file named like the folder is written.
    with pytest.raises(StoreFileError, match=r"path names a folder, not a file: '.*/stores/'"):
        texture(candidates).save(f"{tmp_path}/stores/")
    monkeypatch.undo()
    (tmp_path / "blocker").write_text("a file")
    with pytest.raises(StoreFileError, match=r"could not be saved there: .*blocker is a file"):
        texture(candidates).save(tmp_path / "blocker" / "s.wtb")
    assert not (tmp_path / "stores").exists()


def test_a_texture_says_how_its_colors_are_encoded(granite_32_file, candidates, tmp_path):
    """srgb: as the exemplar stores its colors (an 8-bit PNG: sRGB-encoded; float .npy:
    linear); unknown (None) for a CandidateSet, which does not record it."""
    from warptex.exemplar import Exemplar
    from warptex.texture import SolidTexture

    assert SolidTexture(granite_32_file, device="cpu").srgb is True
    linear = Exemplar.load(granite_32_file, srgb=False)
    assert SolidTexture(linear, device="cpu").srgb is False
    assert texture(candidates).srgb is None


def test_a_texture_of_an_exemplar_per_axis_knows_their_encoding(granite_32_file, data_dir,
                                                                  candidates, tmp_path):
    """ey and ez as precompute takes them: the same voxels as a texture of those candidates,
    with the encoding they share, which a CandidateSet does not record; exemplars encoded
    differently are refused, as a voxel's color averages theirs."""
    from PIL import Image

    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar, ExemplarError
    from warptex.texture import SolidTexture

    onyx = tmp_path / "onyx_32.png"
    Image.open(data_dir / "onyx_banded_64.png").crop((0, 0, 32, 32)).save(onyx)
    per_axis = SolidTexture(granite_32_file, ez=onyx, device="cpu")
    points = points_near_origin(50, 3)
    np.testing.assert_array_equal(
        per_axis.query(points),
        texture(precompute(granite_32_file, granite_32_file, onyx)).query(points))
    assert per_axis.srgb is True
    assert not np.array_equal(per_axis.query(points), texture(candidates).query(points))
    with pytest.raises(ExemplarError, match=r"encoded differently \(granite_32\.png sRGB-encoded, "
                                            r"onyx_32\.png linear\): convert one image$"):
        SolidTexture(granite_32_file, ey=Exemplar.load(onyx, srgb=False), device="cpu")
    with pytest.raises(TypeError, match="a CandidateSet holds those of its three axes"):
        texture(candidates, ey=onyx)


def test_the_engine_s_warnings_point_at_the_line_that_made_the_texture(granite_32_file):
    from warptex.texture import SolidTexture

    with pytest.warns(UserWarning, match="seed 3 gives the same solid as seed 0") as said:
        SolidTexture(granite_32_file, seed=3, jitter=0.0, device="cpu")
    assert [w.filename for w in said] == [__file__]


def test_a_store_file_is_refused_to_a_second_live_texture_of_other_settings(candidates,
                                                                           tmp_path):
    """Each would start empty from the other's file and discard its bricks on saving;
    textures of the same settings share a file, as their voxels are the same."""
    pts = points_near_origin(40, 4)
    path = tmp_path / "granite.wtb"
    tex = texture(candidates, store=path)
    expected = tex.query(pts)
    tex.save()
    saved = path.read_bytes()
    with pytest.raises(StoreFileError, match=r"granite\.wtb.*another texture.*seed 0 in the "
                                             r"other texture, 1 here"):
        texture(candidates, seed=1, store=tmp_path / "." / "granite.wtb")
    twin = texture(candidates, store=path)
    np.testing.assert_array_equal(twin.query(pts), expected)
    assert twin.store.stats()["voxels_added"] == 0
    elsewhere = texture(candidates, passes=1, store=tmp_path / "other.wtb")
    with pytest.raises(StoreFileError, match="correction passes 2 in the other texture, 1 here"):
        elsewhere.save(path)
    assert path.read_bytes() == saved
    del tex, twin
    elsewhere.query(pts[:1])  # voxels of its own: an empty store leaves another's file
    with pytest.warns(UserWarning, match="replacing brick store file: .*another texture") as w:
        elsewhere.save(path)
    assert path.read_bytes() != saved
    assert w[0].filename == __file__  # the line that saved, not warptex's own


def test_a_texture_whose_store_failed_to_load_leaves_its_file_to_others(candidates, tmp_path,
                                                                         monkeypatch):
    """A construction stopped while its store file loads (Ctrl-C) holds the file for no
    texture, even while its exception is kept (a REPL's ``sys.last_value``): a texture of
    other settings may take it next."""
    path = tmp_path / "granite.wtb"
    tex = texture(candidates, store=path)
    tex.query(points_near_origin(4, 1))
    tex.save()
    del tex

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(BrickStore, "load", stopped)
    with pytest.raises(KeyboardInterrupt) as kept:
        texture(candidates, store=path)
    monkeypatch.undo()
    with pytest.warns(UserWarning, match="starting empty: .*seed 0 in the file, 1 here"):
        other = texture(candidates, seed=1, store=path)
    assert other.path == path and kept.value is not None


def test_textures_built_at_once_on_threads_get_no_shared_store_file(candidates, tmp_path,
                                                                     monkeypatch):
    """Mitsuba builds a scene's plugins on several threads: of two textures of other
    settings given one store file at the same time, exactly one is refused, however long
    setting up a store takes."""
    import time

    import warptex.texture

    class SlowStore(BrickStore):
        def __init__(self, *args, **kwargs):
            time.sleep(0.3)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(warptex.texture, "BrickStore", SlowStore)
    path = tmp_path / "granite.wtb"
    made, refused = [], []

    def make(seed: int) -> None:
        try:
            made.append(texture(candidates, seed=seed, store=path))
        except StoreFileError as e:
            refused.append(e)

    threads = [threading.Thread(target=make, args=(seed,)) for seed in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(made) == 1 and len(refused) == 1


@pytest.mark.parametrize("damage", ["no valid bits", "half the triples", "wider valid bits",
                                    "valid bits as uint64"])
def test_a_store_file_whose_arrays_do_not_fit_is_ignored(candidates, tmp_path, damage):
    """Whole and checksummed, but not a store's arrays: warned about and not used."""
    from warptex import store_files
    from warptex.archive import read_archive, write_archive

    pts = points_near_origin(60, 3)
    path = tmp_path / "granite.wtb"
    tex = texture(candidates, store=path)
    expected = tex.query(pts)
    tex.save()
    arrays = read_archive(path, store_files._MAGIC, store_files.FORMAT_VERSION, "brick store",
                          StoreFileError)
    if damage == "no valid bits":
        del arrays["valid"]
    elif damage == "half the triples":
        arrays["triples"] = arrays["triples"][: len(arrays["triples"]) // 2]
    elif damage == "wider valid bits":
        arrays["valid"] = np.concatenate([arrays["valid"], arrays["valid"][:, :1]], axis=1)
    else:
        arrays["valid"] = arrays["valid"].astype(np.uint64)
    write_archive(path, store_files._MAGIC, store_files.FORMAT_VERSION, arrays)
    with pytest.warns(UserWarning, match="ignoring brick store file") as w:
        loaded = texture(candidates, store=path)
    assert w[0].filename == __file__  # the line that made the texture, not warptex's own
    assert loaded.store.stats()["voxels"] == 0
    np.testing.assert_array_equal(loaded.query(pts), expected)


def _store_lock_rule(monkeypatch, reader: str) -> None:
    """The brick store's rule, checked as it runs: it changes only under its exclusive
    lock, with no lookup running, and ``reader`` (a method that reads its pool) runs under
    its shared one at least. A race this machine's timing may not show is caught so."""
    from warptex.store import BrickStore

    def exclusive_only(name: str):
        change = getattr(BrickStore, name)

        def held(self, *args):
            assert self._lock._writing and not self._lock._readers, f"{name} not exclusive"
            return change(self, *args)

        return held

    def shared_at_least(read):
        def held(self, *args):  # a read beside a change reads a reused slot's voxels
            assert self._lock._readers or self._lock._writing, f"{reader} outside the lock"
            return read(self, *args)

        return held

    for name in ("_insert", "_evict"):
        monkeypatch.setattr(BrickStore, name, exclusive_only(name))
    monkeypatch.setattr(BrickStore, reader, shared_at_least(getattr(BrickStore, reader)))


@pytest.mark.parametrize("whole_bricks", [True, False])
def test_concurrent_queries_match_serial_ones(candidates, whole_bricks, monkeypatch):
    """Threads querying one store, with room for everything or for a few bricks only
    (evictions; with partly filled bricks also repacking and pool compaction). A race
    this machine's timing may not show is caught by its rule: the store changes only
    under its exclusive lock, with no lookup running, and looks up under its shared one."""
    _store_lock_rule(monkeypatch, "_launch")
    sets = [points_near_origin(150, 10 + i) * (1 + 0.3 * i) for i in range(4)]
    serial = [texture(candidates).query(p, filter=f) for p, f in
              zip(sets, ["trilinear", "nearest"] * 2, strict=True)]
    for cache in (256 << 20, 4 * (512 * 6 + 68)):
        tex = texture(candidates, cache_bytes=cache, whole_bricks=whole_bricks)
        results: dict[int, np.ndarray] = {}
        errors: list[BaseException] = []

        def work(i: int, tex=tex, results=results, errors=errors) -> None:
            try:
                f = "trilinear" if i % 2 == 0 else "nearest"
                for _ in range(2):
                    results[i] = tex.query(sets[i], filter=f)
            except BaseException as e:  # re-raised below, in the test's thread
                errors.append(e)

        threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert not errors, errors
        for i in range(4):
            np.testing.assert_array_equal(results[i], serial[i])


@pytest.mark.parametrize("whole_bricks", [True, False])
def test_saves_and_snapshots_beside_evicting_queries_change_no_color(candidates, reference,
                                                                    tmp_path, whole_bricks,
                                                                    monkeypatch):
    """Queries on three threads through a store of four bricks (evicting all the time),
    while a fourth thread saves it to its file, reads snapshots and prefetches: every
    color is the serial one, every snapshot holds the engine's sums (read under the
    store's lock), and the file loads the same colors."""
    from warptex.store import brick_voxels

    _store_lock_rule(monkeypatch, "_voxel_sums")

    sets = [points_near_origin(300, 20 + i) * (1 + 0.5 * i) for i in range(3)]
    serial = [texture(candidates).query(p, filter="nearest") for p in sets]
    path = tmp_path / "s.wts"
    tex = texture(candidates, store=path, cache_bytes=4 * (512 * 6 + 68),
                  whole_bricks=whole_bricks)
    channels = candidates.channels
    colors = [candidates.colors[candidates.axis_source[k]].reshape(-1, channels)
              for k in range(3)]
    results: dict[int, np.ndarray] = {}
    errors: list[BaseException] = []
    done = threading.Event()
    checked = [0, 0]  # saves, stored voxels checked

    def query(i: int) -> None:
        try:
            for _ in range(3):
                results[i] = tex.query(sets[i], filter="nearest")
        except BaseException as e:  # re-raised below, in the test's thread
            errors.append(e)

    def save_and_check() -> None:
        try:
            while not done.is_set() or not checked[1]:
                tex.save()
                snap = tex.store.snapshot()
                live = snap.keys >= 0
                sums = snap.sums.reshape(len(snap.keys), 512, channels)[live].reshape(-1, channels)
                stored = ~np.isnan(sums).any(axis=1)
                pix = reference.pixel_triples(brick_voxels(snap.keys[live])[stored])
                expected = colors[0][pix[:, 0]] + colors[1][pix[:, 1]] + colors[2][pix[:, 2]]
                np.testing.assert_array_equal(sums[stored], expected)
                tex.store.prefetch(np.floor(sets[checked[0] % 3][:5]).astype(np.int64))
                checked[0] += 1
                checked[1] += int(stored.sum())
        except BaseException as e:
            errors.append(e)

    threads = [threading.Thread(target=query, args=(i,)) for i in range(3)]
    checker = threading.Thread(target=save_and_check)
    for t in [*threads, checker]:
        t.start()
    for t in threads:
        t.join()
    done.set()
    checker.join()
    assert not errors, errors
    assert checked[1] > 0 and tex.store.stats()["bricks_evicted"] > 0
    for i in range(3):
        np.testing.assert_array_equal(results[i], serial[i])
    loaded = texture(candidates, store=path)
    for p, expected in zip(sets, serial, strict=True):
        np.testing.assert_array_equal(loaded.query(p, filter="nearest"), expected)


def test_bad_points_raise_unless_filled(candidates):
    tex = texture(candidates)
    pts = points_near_origin(10, 11)
    pts[2, 0] = np.nan
    pts[5, 1] = np.inf
    pts[6, 2] = -np.inf
    with pytest.raises(ValueError, match="3 of 10 points are NaN, infinite or masked"):
        tex.query(pts)
    filled = tex.query(pts, filter="nearest", fill=-1.0)
    assert (filled[[2, 5, 6]] == -1).all()
    good = [0, 1, 3, 4, 7, 8, 9]
    np.testing.assert_array_equal(filled[good], tex.query(pts[good], filter="nearest"))
    with pytest.raises(ValueError, match="within"):
        tex.query(np.array([[1e9, 0, 0]]))


def test_masked_points_are_missing_points(candidates):
    """np.asarray reads the values under a masked array's mask: a masked point far away
    was refused, and one in range was given the color of the value under its mask."""
    tex = texture(candidates)
    pts = points_near_origin(10, 13).astype(np.float32)
    mask = np.zeros_like(pts, bool)
    mask[3, 1] = mask[7] = True
    hidden = pts.copy()
    hidden[7] = 1e9
    points = np.ma.MaskedArray(hidden, mask)
    with pytest.raises(ValueError, match="2 of 10 points are NaN, infinite or masked"):
        tex.query(points)
    filled = tex.query(points, filter="nearest", fill=[-1.0, -2.0, -3.0])
    assert (filled[[3, 7]] == [-1.0, -2.0, -3.0]).all()
    good = [0, 1, 2, 4, 5, 6, 8, 9]
    np.testing.assert_array_equal(filled[good], tex.query(pts[good], filter="nearest"))
    unmasked = np.ma.MaskedArray(pts)
    np.testing.assert_array_equal(tex.query(unmasked), tex.query(pts))
    # In slabs too (bake and cut query so): the values under the mask were read.
    from warptex.texture import query_slabs

    with pytest.raises(ValueError, match="2 of 10 points are NaN, infinite or masked"):
        query_slabs(tex, points)


def test_points_of_either_byte_order_are_read_alike(candidates):
    """Big-endian floats, as np.fromfile reads another machine's file, were refused as
    "must be float32 or float64, got >f8"."""
    tex = texture(candidates)
    pts = points_near_origin(10, 14)
    for dtype in (">f8", ">f4", "<f4"):
        np.testing.assert_array_equal(tex.query(pts.astype(dtype)),
                                      tex.query(pts.astype(np.dtype(dtype).newbyteorder("="))))
    with pytest.raises(TypeError, match="float32 or float64, got float16"):
        tex.query(pts.astype(np.float16))


def test_a_far_point_late_in_a_query_is_refused_before_any_batch(candidates, monkeypatch):
    """The range was checked batch by batch: a far point in the last batch was refused
    after every earlier batch had been synthesized (minutes for millions of points)."""
    import warptex.texture
    from warptex.texture import POINT_LIMIT

    monkeypatch.setattr(warptex.texture, "BATCH", 8)
    tex = texture(candidates)
    pts = points_near_origin(40, 12)
    pts[-1] = [0.5, POINT_LIMIT, 0.5]
    pts[-3] = [-POINT_LIMIT - 7.0, 0.5, np.nan]  # NaN: given the fill color, not counted far
    with pytest.raises(ValueError, match=f"1 of 40 points lie at or beyond \\+-{POINT_LIMIT}"):
        tex.query(pts, fill=0.0)
    assert tex.store.stats()["voxels_added"] == 0


def test_bad_shapes_dtypes_and_empty_input(candidates):
    tex = texture(candidates)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        tex.query(np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        tex.query(np.zeros(3))
    with pytest.raises(TypeError, match="float32 or float64"):
        tex.query(np.zeros((4, 3), np.int32))
    with pytest.raises(ValueError, match="filter"):
        tex.query(np.zeros((4, 3)), filter="cubic")
    with pytest.raises(ValueError, match="fill"):
        tex.query(np.zeros((4, 3)), fill=[0.0, 1.0])
    empty = tex.query(np.zeros((0, 3), np.float32))
    assert empty.shape == (0, tex.channels) and empty.dtype == np.float32
    # Once a comparison error naming nothing ("1"), or a truthy string kept ("no").
    with pytest.raises(ValueError, match="cache_bytes must be an integer, got '1'"):
        texture(candidates, cache_bytes="1")
    with pytest.raises(ValueError, match="whole_bricks must be True or False, got 'no'"):
        texture(candidates, whole_bricks="no")
    assert texture(candidates, whole_bricks=np.bool_(False)).store.whole_bricks is False


def test_warp_arrays_are_accepted(candidates):
    tex = texture(candidates)
    pts = points_near_origin(64, 12).astype(np.float32)
    expected = tex.query(pts)
    np.testing.assert_array_equal(tex.query(wp.array(pts, dtype=wp.vec3, device="cpu")), expected)
    np.testing.assert_array_equal(tex.query(wp.array(pts, dtype=wp.float32, device="cpu")),
                                  expected)


def test_stats_report_store_and_synthesis(candidates):
    tex = texture(candidates)
    pts = np.array([[0.5, 0.5, 0.5], [1.5, 0.5, 0.5], [9.5, 0.5, 0.5]])
    tex.query(pts, filter="nearest")
    tex.query(pts, filter="nearest")
    s = tex.store.stats()
    assert s["bricks"] == 2 and s["voxels"] == s["voxels_added"] == 2 * 512
    assert (s["hits"], s["misses"]) == (3, 3)
    assert s["payload_bytes"] == 2 * (512 * 6 + 68) and s["bytes_per_voxel"] == 6
    assert s["bytes"] == s["payload_bytes"] + s["index_bytes"]
    assert s["synthesis_seconds"] > 0
    finest = max(s["voxels_synthesized"])
    assert s["voxels_synthesized"][finest] >= 2 * 512


def test_store_object_is_a_brick_store(candidates):
    assert isinstance(texture(candidates).store, BrickStore)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        texture(candidates, store=None)


def test_first_launch_of_a_kernel_may_be_split_over_threads(tmp_path, data_dir):
    """Warp loads modules lazily and not thread-safely; a fresh process whose very first
    lookup is split over threads must still work (it once raised KeyError)."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent(
        f"""
        import numpy as np
        from warptex.texture import SolidTexture
        tex = SolidTexture({str(data_dir / "granite_64.png")!r})
        tex.query(np.indices((20, 20, 20)).reshape(3, -1).T + 0.5, filter="nearest")
        pts = np.random.default_rng(0).random((50_000, 3)) * 19 + 0.5
        print(tex.query(pts).shape)
        """
    )
    env = {**__import__("os").environ, "WARPTEX_CACHE": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "(50000, 3)" in done.stdout


def test_store_files_cut_short_empty_or_with_loose_members(candidates, tmp_path):
    """A store cut short within its magic is damaged (replaced, with a warning), not
    another tool's file to refuse; an empty one (made by mktemp) is a place to save to,
    loaded empty without a warning; one whose checksum holds but whose member is no array
    (written by another tool) is damaged, not an AttributeError."""
    import io
    import zipfile

    from warptex.store_files import _MAGIC

    pts = points_near_origin(20, 3)
    path = tmp_path / "granite.wtb"
    tex = texture(candidates, store=path)
    expected = tex.query(pts)
    tex.save()
    del tex
    whole = path.read_bytes()

    path.write_bytes(whole[:5])
    with pytest.warns(UserWarning, match="not a warptex brick store"):
        cut = texture(candidates, store=path)
    np.testing.assert_array_equal(cut.query(pts), expected)
    del cut

    path.write_bytes(b"")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        empty = texture(candidates, store=path)
    assert empty.store.stats()["bricks"] == 0
    del empty

    header = len(_MAGIC) + 4 + 32
    members = zipfile.ZipFile(io.BytesIO(whole[header:]))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as out:
        for name in members.namelist():
            out.writestr(name, b"not an array" if name == "keys.npy" else members.read(name))
    payload = buf.getvalue()
    path.write_bytes(whole[:len(_MAGIC) + 4] + hashlib.sha256(payload).digest() + payload)
    with pytest.warns(UserWarning, match="keys is not an array"):
        loose = texture(candidates, store=path)
    assert loose.store.stats()["bricks"] == 0


def test_far_points_move_by_the_period_the_readme_gives():
    """README: points past the coordinate range move by whole periods of 2^22 voxels."""
    from warptex.texture import POINT_LIMIT, wrap_far

    far = np.array([POINT_LIMIT + 1.0, -(POINT_LIMIT + 1.0), 2.5 * 2.0**22 + 0.25])
    np.testing.assert_array_equal(wrap_far(far), [POINT_LIMIT + 1.0 - 2**22,
                                                  -(POINT_LIMIT + 1.0) + 2**22, 0.25 - 2**21])
    np.testing.assert_array_equal(wrap_far(far.tolist()), wrap_far(far))  # as a script writes


def test_query_slabs_shows_its_bar_under_the_name_given(capsys):
    """The bar slice and bake show while the colors are made (none where no name is
    given): a bar disabled for good passed every test."""
    from warptex.texture import query_slabs

    class Gray:
        channels = 1

        def query(self, points: np.ndarray, filter: str = "trilinear") -> np.ndarray:
            return np.full((len(points), 1), 0.5, np.float32)

    points = np.zeros((5, 3))
    np.testing.assert_array_equal(query_slabs(Gray(), points, progress="colors of wood"),
                                  np.full((5, 1), 0.5, np.float32))
    assert "colors of wood" in capsys.readouterr().err
    query_slabs(Gray(), points)
    assert capsys.readouterr().err == ""


def test_a_damaged_candidate_cache_is_said_at_the_line_that_made_the_texture(
        granite_32_file, tmp_path, monkeypatch, warp_device):
    """The texture's candidates are pre-computed inside it: their warnings, as its
    exemplars' and its engine's, point at the caller's line, not into warptex."""
    from warptex.candidate_set import resolved_params
    from warptex.candidates import cache_path
    from warptex.exemplar import Exemplar
    from warptex.texture import SolidTexture

    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path / "cache"))
    path = cache_path([Exemplar.load(granite_32_file)] * 3, resolved_params({}))
    path.parent.mkdir(parents=True)
    path.write_bytes(b"not candidates")
    with pytest.warns(UserWarning, match="ignoring damaged candidate cache") as caught:
        SolidTexture(granite_32_file)
    assert [w.filename for w in caught] == [__file__]
