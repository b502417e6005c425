"""The Python API refuses wrong arguments with one error naming the argument, instead of
an error from deep inside NumPy, pathlib or Warp, or a silently truncated value."""

from __future__ import annotations

import errno
import os
import re
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

import warptex
from warptex import metrics
from warptex.archive import (
    _TOKEN_BYTES,
    UNFINISHED_AGE,
    _temporary_name,
    dead_writes,
    file_problem,
    is_temporary,
    write_atomically,
    write_together,
)
from warptex.candidate_set import CandidateCacheError, CandidateSet
from warptex.candidates import precompute
from warptex.settings import MAX_JITTER, MAX_PASSES, MAX_SEED, SettingError, check_settings
from warptex.volume_files import write_image, write_volume


@pytest.fixture(scope="module")
def candidates(granite_32):
    return precompute(granite_32, cache=False)


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"seed": 1.5}, "seed"), ({"seed": None}, "seed"), ({"passes": "2"}, "passes"),
    ({"passes": True}, "passes"), ({"jitter": "1"}, "jitter"),
])
def test_settings_of_the_wrong_type_are_named(kwargs, name):
    """A TypeError too, as the other arguments' wrong types are (a script's ``except
    TypeError`` missed these), and still a SettingError (a ValueError) as before."""
    with pytest.raises(SettingError, match=f"^{name} must be an? ") as refused:
        check_settings(**kwargs)
    assert isinstance(refused.value, TypeError) and isinstance(refused.value, ValueError)


def test_settings_of_the_wrong_type_are_type_errors_everywhere(granite_32, granite_32_file,
                                                                warp_device):
    """The Python API review's cases: cache_bytes=1e8 (a common way to write 100 MB), a
    float seed, a string flag, a float exemplar size: each a TypeError naming the setting;
    a value out of range is no TypeError."""
    from warptex.exemplar import Exemplar
    from warptex.texture import SolidTexture

    for call, name in ((lambda: SolidTexture(granite_32, cache_bytes=1e8), "cache_bytes"),
                       (lambda: SolidTexture(granite_32, seed=1.5), "seed"),
                       (lambda: SolidTexture(granite_32, shifted_tiles="no"), "shifted_tiles"),
                       (lambda: Exemplar.load(granite_32_file, max_size=32.0), "max_size")):
        with pytest.raises(TypeError, match=f"^{name} must be"):
            call()
    with pytest.raises(SettingError, match=r"^seed must be within") as refused:
        SolidTexture(granite_32, seed=-1)
    assert not isinstance(refused.value, TypeError)


def test_sources_of_the_wrong_kind_are_named(candidates, warp_device):
    from warptex.synthesis import Synthesizer

    with pytest.raises(TypeError, match=r"warptex\.Exemplar\(array\)"):
        precompute(np.zeros((32, 32, 3), np.float32))
    with pytest.raises(TypeError, match="candidates must be a CandidateSet"):
        Synthesizer("granite.png")
    for seed in (1.5, "3", None):
        with pytest.raises(SettingError, match="seed must be an integer"):
            Synthesizer(candidates, seed=seed)
    synth = Synthesizer(candidates)
    for origin, shape in (((0.5, 0, 0), (2, 2, 2)), ((0, 0, 0), (2.7, 2, 2)), ((0, 0), (2, 2, 2))):
        with pytest.raises(ValueError, match="must be three ints"):
            synth.box(origin, shape)
    assert synth.box(np.array([1, 2, 3]), (1, 1, 2)).shape == (1, 1, 2, 3)
    with pytest.raises(ValueError, match="device must be a Warp device such as 'cpu'"):
        Synthesizer(candidates, device="foo")
    for subpasses in (True, 2):  # True would pass for 1
        with pytest.raises(ValueError, match="subpasses must be 1 or 8"):
            Synthesizer(candidates, subpasses=subpasses)
    for call in (CandidateSet.load, candidates.save):
        with pytest.raises(TypeError, match=r"path must be a file name \(str or Path\), got 3"):
            call(3)


def test_kopf_refuses_a_callback_it_cannot_call_before_any_work(granite_32, monkeypatch):
    from warptex.baselines import kopf

    monkeypatch.setattr(kopf, "_axis_exemplars", lambda *a, **k: pytest.fail("work started"))
    with pytest.raises(TypeError, match="on_iteration must be a function or None, got 5"):
        kopf.synthesize(granite_32, size=16, on_iteration=5, progress=False)


def test_texture_arguments_of_the_wrong_kind_are_named(candidates, warp_device):
    from warptex.texture import SolidTexture

    with pytest.raises(TypeError, match="store must be a file name"):
        SolidTexture(candidates, store=123)
    tex = SolidTexture(candidates)
    with pytest.raises(ValueError, match="fill must be one finite value or 3 of them, got 'red'"):
        tex.query(np.array([[np.nan, 0.0, 0.0]]), fill="red")
    # np.float32 reads both as numbers, the bool as 1; NaN and infinity are no colours,
    # and one value in a list is a list of the wrong length.
    for fill in (True, "0.25", np.array([True, False, True]), np.nan, -np.inf,
                 [0.0, np.nan, 1.0], [0.5], [[0.5], [0.5, 0.5]]):  # the last ragged
        with pytest.raises(ValueError, match="fill must be one finite value or 3 of them"):
            tex.query(np.array([[np.nan, 0.0, 0.0]]), fill=fill)
    with pytest.raises(ValueError, match=r"no store path: pass one here or as "
                                         r"SolidTexture\(store=\.\.\.\)"):
        tex.save()
    with pytest.raises(ValueError, match=r"shape must be three non-negative ints, got "
                                         r"\(2, -1, 2\)"):
        tex.synthesizer.box((0, 0, 0), (2, -1, 2))
    np.testing.assert_array_equal(tex.query(np.array([[np.nan, 0.0, 0.0]]), fill=np.int64(1)),
                                  [[1.0, 1.0, 1.0]])
    for subpasses in (8.0, True, 2):
        with pytest.raises(ValueError, match="subpasses must be 1 or 8"):
            warptex.Synthesizer(candidates, subpasses=subpasses)


def test_mesh_arguments_are_checked_before_the_kernels_read_through_them(warp_device):
    """A short ``uv`` was read past its end by the kernels: a different bake each call."""
    import trimesh

    from warptex.bake import bake_uv_texture, texel_points, vertex_colors
    from warptex.cut import cut
    from warptex.surface import block_transform, shell

    mesh = trimesh.creation.icosphere(subdivisions=1)
    m = block_transform(mesh, 16)
    uv = np.random.default_rng(0).uniform(0, 1, (len(mesh.vertices), 2))
    for bad, why in ((uv[:10], r"one \(u, v\) row per mesh vertex, \(42, 2\), got shape \(10, 2\)"),
                     (uv[:, :1], "got shape"), (np.where(uv > 0.5, np.nan, uv), "NaN"),
                     ("uv", "array of numbers")):
        with pytest.raises(ValueError, match=why):
            texel_points(mesh, bad, m, (8, 8))
    # A vertex no face holds is never read: its UV may be anything.
    unused = trimesh.Trimesh(np.vstack([mesh.vertices, [[9.0, 9.0, 9.0]]]), mesh.faces,
                             process=False)
    loose = np.vstack([uv, [[np.nan, np.nan]]])
    np.testing.assert_array_equal(texel_points(unused, loose, m, (8, 8))[1],
                                  texel_points(mesh, uv, m, (8, 8))[1])
    for size in (0, 8.0, True):
        with pytest.raises(SettingError, match=r"^size must be"):
            bake_uv_texture(None, mesh, uv, m, size=size)
    broken = trimesh.Trimesh(mesh.vertices, np.where(mesh.faces == 5, -1, mesh.faces),
                             process=False)
    for call in (lambda: texel_points(broken, uv, m, (8, 8)), lambda: shell(broken, 16)):
        with pytest.raises(ValueError, match=r"faces index vertices outside \[0, 42\)"):
            call()
    for transform, why in ((m[:3], "4x4 matrix, got shape"), (np.full((4, 4), np.nan), "NaN")):
        with pytest.raises(ValueError, match=f"transform .*{why}"):
            shell(mesh, transform=transform)
    # A list is a matrix too: its translation was indexed as the list, a TypeError.
    np.testing.assert_array_equal(vertex_colors(_Positions(), mesh, m.tolist()),
                                  vertex_colors(_Positions(), mesh, m))
    for resolution in (0, 16.0):
        with pytest.raises(SettingError, match=r"^resolution must be"):
            block_transform(mesh, resolution)
    for origin, normal, name in (((0, 0), (0, 0, 1), "origin"), ((0, 0, 0), (0, 1), "normal"),
                                 ((0, 0, np.inf), (0, 0, 1), "origin")):
        with pytest.raises(ValueError, match=f"plane's {name} must be three finite numbers"):
            cut(mesh, origin, normal)
    for origin, normal, name in (("abc", (0, 0, 1), "origin"),
                                 ((0, 0, 0), [[0], [0, 1]], "normal")):
        with pytest.raises(ValueError, match=f"plane's {name} must be three numbers, got"):
            cut(mesh, origin, normal)
    with pytest.raises(ValueError, match="transform must be a 4x4 matrix of numbers, got str"):
        shell(mesh, transform="identity")
    # Not NumPy's divide warning and "the plane does not cut the mesh".
    with pytest.raises(ValueError, match="non-zero normal"):
        cut(mesh, (0, 0, 0), (0, 0, 0))
    # What trimesh.load gives of a .glb, a Scene, and a file name are named, where they
    # failed deep inside ("'Scene' object has no attribute 'vertices'").
    from warptex.bake import unwrapped
    from warptex.mesh_files import export

    for not_a_mesh, hint in ((trimesh.Scene([mesh]), r"Scene \(.*force='mesh'"),
                             ("bunny.ply", r"str \(warptex.mesh_files.load_mesh reads one")):
        for call in (lambda x: block_transform(x, 16), lambda x: shell(x, 16),
                     lambda x: vertex_colors(_Positions(), x, m),
                     lambda x: texel_points(x, uv, m, (8, 8)),
                     lambda x: cut(x, (0, 0, 0), (0, 0, 1)), unwrapped,
                     lambda x: export(x, "never.ply", colors=np.zeros((42, 3)))):
            with pytest.raises(TypeError, match=f"^mesh must be a trimesh.Trimesh, got {hint}"):
                call(not_a_mesh)
    assert not Path("never.ply").exists()


def test_meshes_are_read_by_the_library_as_the_commands_read_them(tmp_path):
    from warptex.mesh_files import MeshFileError, load_mesh

    for path, problem in ((tmp_path / "missing.ply", "mesh file not found"),
                          (tmp_path, "is a folder, expected a mesh file")):
        with pytest.raises(MeshFileError, match=problem):
            load_mesh(path)
    with pytest.raises(ValueError, match="uv must be 'none', 'auto' or 'mesh'"):
        load_mesh(tmp_path / "missing.ply", uv="yes")
    with pytest.raises(ValueError, match="weld must be True or False, got 'no'"):  # welded
        load_mesh(tmp_path / "missing.ply", weld="no")
    import trimesh

    far = trimesh.creation.box()
    far.apply_translation((1e9, 0, 0))
    far.export(tmp_path / "far.obj")
    assert len(load_mesh(tmp_path / "far.obj", outputs=["out.obj"]).faces) == 12
    with pytest.raises(MeshFileError, match=r"out\.glb: \.ply and \.glb files hold vertices as"):
        load_mesh(tmp_path / "far.obj", outputs=["out.obj", "out.glb"])


def test_meshes_loaded_at_once_weld_each_at_its_own_tolerance(tmp_path, monkeypatch):
    """trimesh welds at a global tolerance, which each load sets for its mesh: two threads
    loading at once welded one mesh at the other's, and left the global changed."""
    import threading

    import trimesh

    from warptex import mesh_files

    small, large = trimesh.creation.box(extents=(1e-6,) * 3), trimesh.creation.box()
    small.export(tmp_path / "small.ply")
    large.export(tmp_path / "large.ply")
    load, seen, original = trimesh.load, {}, trimesh.tol.merge

    def slow_load(path, **kwargs):
        if kwargs.get("process", True):  # the welding load: hold it while the other starts
            seen[Path(path).name] = trimesh.tol.merge
            time.sleep(0.2)
            assert trimesh.tol.merge == seen[Path(path).name]
        return load(path, **kwargs)

    monkeypatch.setattr(trimesh, "load", slow_load)
    errors = []

    def read(name):
        try:
            mesh_files.load_mesh(tmp_path / name)
        except BaseException as error:  # re-raised below, in the test's thread
            errors.append(error)

    threads = [threading.Thread(target=read, args=(n,)) for n in ("small.ply", "large.ply")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    assert seen["small.ply"] < seen["large.ply"] and trimesh.tol.merge == original


class _Positions:
    """A texture whose color at a point is the point."""

    channels = 3

    def query(self, points: np.ndarray, filter: str = "trilinear") -> np.ndarray:
        return np.asarray(points, np.float32)


def test_a_store_file_named_by_a_loop_of_links_is_refused(candidates, warp_device, tmp_path):
    """It was a RuntimeError ("Symlink loop") from deep inside, and save's the same."""
    from warptex.store_files import StoreFileError
    from warptex.texture import SolidTexture

    (tmp_path / "loop.wts").symlink_to("loop.wts")
    problem = "a brick store could not be saved there: cannot look up"
    with pytest.raises(StoreFileError, match=problem):
        SolidTexture(candidates, store=tmp_path / "loop.wts")
    with pytest.raises(StoreFileError, match=problem):
        SolidTexture(candidates).save(tmp_path / "loop.wts")


def test_a_relative_store_path_stays_where_it_was_given(candidates, warp_device, tmp_path,
                                                       monkeypatch):
    from warptex.texture import SolidTexture

    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path)
    tex = SolidTexture(candidates, store="rel.wts")
    tex.query(np.zeros((1, 3)))
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert tex.save() == tmp_path / "rel.wts"
    assert (tmp_path / "rel.wts").is_file() and not (tmp_path / "elsewhere" / "rel.wts").exists()


def test_slice_arguments_are_checked(candidates, warp_device):
    from warptex.texture import SolidTexture

    tex = SolidTexture(candidates)
    for shape in (8, (8, 8, 3), (8.0, 8.0), (-1, 8), (True, 8)):
        with pytest.raises(ValueError, match="shape must be two positive ints"):
            tex.slice((0, 0, 0), (1, 0, 0), (0, 1, 0), shape)
    for origin in ((0, 0), "000", (0, np.nan, 0), (1 + 2j, 0, 0)):
        with pytest.raises(ValueError, match="origin must be three finite real numbers"):
            tex.slice(origin, (1, 0, 0), (0, 1, 0), (2, 2))
    # Finite vectors whose pixels overflow (1e308 * 2), or only reach past the range,
    # opposite infinities making NaN of one corner: the plane is named, not query's fill=.
    for u, v, shape in (((1e308, 0, 0), (0, 1e308, 0), (3, 3)),
                        ((1e308, 0, 0), (-1e308, 0, 0), (3, 3)),
                        ((0, 0, 1), (0, 1, 0), (2, 5_000_000))):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(ValueError, match=r"the plane reaches beyond the texture's "
                                                 r"coordinate range .*: check origin, u, v and "):
                tex.slice((0, 0, 0), u, v, shape)
    # Zero or parallel vectors make a line of a plane: said at the caller's line, as the
    # command says it; a plane is taken without a word.
    for u, v in (((0, 0, 0), (0, 1, 0)), ((1, 0, 0), (-2, 0, 0))):
        with pytest.warns(UserWarning, match="u and v are zero or parallel") as caught:
            assert tex.slice((0, 0, 0), u, v, (2, 2)).shape == (2, 2, 3)
        assert [w.filename for w in caught] == [__file__]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tex.slice((0, 0, 0), (1, 0, 0), (0, 0, -1), (2, 2))
    # NumPy integers: their product wrapped around, and the slice met NumPy's MemoryError.
    for shape in ((np.int64(2**32),) * 2, np.array([2**32, 2**32])):
        with pytest.raises(ValueError, match="take it in parts"):
            tex.slice((0, 0, 0), (1, 0, 0), (0, 1, 0), shape)
    for shape in ((0, 5), (5, 0)):
        with pytest.raises(ValueError, match="shape must be two positive ints"):
            tex.slice((0, 0, 0), (1, 0, 0), (0, 1, 0), shape)
    # A plane whose last pixel lies just inside the range is taken, a row or column of one
    # pixel included.
    from warptex.texture import POINT_LIMIT

    edge = POINT_LIMIT - 0.5
    for origin, u, v in (((edge, 0, 0), (0, 1, 0), (0, 0, 1)),
                         ((0, 0, edge - 3), (0, 1, 0), (0, 0, 1))):
        assert tex.slice(origin, u, v, (1, 4 if origin[2] else 1)).shape[:2] == (
            1, 4 if origin[2] else 1)
    # One pixel exactly at the limit, which queries refuse, is the plane's to name.
    for origin, u, v, shape in (((POINT_LIMIT, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1)),
                                ((0, 0, POINT_LIMIT - 3), (0, 1, 0), (0, 0, 1), (1, 4))):
        with pytest.raises(ValueError, match="the plane reaches beyond"):
            tex.slice(origin, u, v, shape)


def test_a_slice_counts_the_memory_of_its_points_and_the_voxels_they_read(candidates,
                                                                           warp_device,
                                                                           monkeypatch):
    """What a slice asks of the machine before any work: 40 bytes a point (its float64
    points, their grid while made) and its colors, and one batch of the voxels its points
    read: eight a point trilinear, one nearest, a whole brick each where bricks are whole."""
    from kernels.lookup import BRICK_VOXELS
    from warptex import texture as texture_module
    from warptex.store import BATCH_VOXELS
    from warptex.synthesis import REQUEST_BYTES_PER_VOXEL
    from warptex.texture import SolidTexture

    asked = []
    monkeypatch.setattr(texture_module, "memory_problem", lambda need: asked.append(need))
    for whole, filter in ((False, "nearest"), (False, "trilinear"), (True, "nearest")):
        asked.clear()
        SolidTexture(candidates, whole_bricks=whole).slice((0, 0, 0), (1, 0, 0), (0, 1, 0),
                                                            (4, 4), filter=filter)
        per_point = (8 if filter == "trilinear" else 1) * (BRICK_VOXELS if whole else 1)
        assert asked[0] == (16 * (40 + 4 * 3)
                            + min(16 * per_point, BATCH_VOXELS) * REQUEST_BYTES_PER_VOXEL)


def test_a_slices_filter_is_checked_before_its_points_are_made(candidates, warp_device,
                                                              monkeypatch):
    """A filter the texture has not was refused by its query, once the plane's points had
    taken seconds and gigabytes to make (6000 x 6000: 7.7 s)."""
    import warptex.texture
    from warptex.texture import SolidTexture

    def not_now(*args):
        raise AssertionError("the plane's points were made")

    monkeypatch.setattr(warptex.texture, "plane_points", not_now)
    with pytest.raises(ValueError, match="filter must be one of"):
        SolidTexture(candidates).slice((0, 0, 0), (1, 0, 0), (0, 1, 0), (4, 4), filter="linear")


def test_colors_are_reencoded_only_by_flags():
    """``srgb=None``, a texture's "not recorded", decoded one way and encoded the other."""
    from warptex.srgb import reencoded

    values = np.full((2, 3), 0.5, np.float32)
    np.testing.assert_array_equal(reencoded(values, srgb=True, to_srgb=True), values)
    for srgb, to_srgb, name in ((None, False, "srgb"), ("no", True, "srgb"), (True, 1, "to_srgb")):
        with pytest.raises(SettingError, match=f"^{name} must be True or False"):
            reencoded(values, srgb=srgb, to_srgb=to_srgb)


def test_a_surface_device_that_warp_lacks_is_named(warp_device):
    """shell and texel_points took their device as engines do not: Warp's own error named
    no argument."""
    import trimesh

    from warptex.bake import texel_points
    from warptex.surface import block_transform, shell

    cube = trimesh.creation.box()
    transform = block_transform(cube, 8)
    for run in (lambda: shell(cube, 8, transform, device="gpu"),
                lambda: texel_points(cube, cube.vertices[:, :2], transform, (4, 4),
                                     device="gpu")):
        with pytest.raises(ValueError, match=r"^device must be a Warp device such as 'cpu' or "
                                             r"'cuda:0', got 'gpu'"):
            run()


def test_colors_of_pixel_triples_refuses_what_is_no_triple(candidates, warp_device):
    """colors_of failed in NumPy's take, naming no argument, and on a list of triples."""
    from warptex.synthesis import Synthesizer

    syn = Synthesizer(candidates)
    triples = syn.pixel_triples(np.array([[0, 0, 0], [5, -3, 9]]))
    np.testing.assert_array_equal(syn.colors_of(triples),
                                  syn.voxels(np.array([[0, 0, 0], [5, -3, 9]])))
    np.testing.assert_array_equal(syn.colors_of(triples.tolist()), syn.colors_of(triples))
    for bad in (triples[:, :2], triples.astype(float), triples[0]):
        with pytest.raises(ValueError, match=r"pixels must be an \(N, 3\) integer array"):
            syn.colors_of(bad)
    for bad in ([[0, 0, 32 * 32]], [[-1, 0, 0]]):
        with pytest.raises(ValueError, match="pixels must index each axis' exemplar, from 0"):
            syn.colors_of(np.array(bad))


def test_colors_to_reencode_are_floats():
    """8-bit colors taken for values in [0, 1] came out 10^5 times too bright; one number
    for a color failed on its missing channels; a negative value warned of its unused
    power."""
    import warnings

    from warptex.srgb import linear_to_srgb, reencoded, srgb_to_linear

    for convert in (srgb_to_linear, linear_to_srgb,
                    lambda v: reencoded(v, srgb=True, to_srgb=False)):
        with pytest.raises(TypeError, match=r"^colors must be floats in \[0, 1\] \(8-bit ones "
                                            r"divided by 255\), got uint8$"):
            convert(np.full((2, 3), 128, np.uint8))
    with pytest.raises(ValueError, match=r"an array of colors, channels last \(\.\.\., C\)"):
        reencoded(0.5, srgb=True, to_srgb=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(srgb_to_linear([-0.5, 0.5]),
                                      np.array([-0.5 / 12.92, 0.21404114], np.float32))


def test_exemplar_features_are_asked_for_in_one_way(granite_32_file, tmp_path):
    """True stood for "auto" but was dropped beside a mask; 1 passed for True."""
    from warptex.exemplar import Exemplar

    mask = tmp_path / "mask.npy"
    np.save(mask, (np.arange(32 * 32).reshape(32, 32) % 7 == 0).astype(np.float32))
    for distance in ("auto", True, np.True_):
        with pytest.raises(ValueError, match="give either feature_mask or feature_distance"):
            Exemplar.load(granite_32_file, feature_mask=mask, feature_distance=distance)
    for distance in (1, 0.0, "yes", None):
        with pytest.raises(ValueError, match="feature_distance must be False, True or 'auto'"):
            Exemplar.load(granite_32_file, feature_distance=distance)
    with pytest.raises(TypeError, match="feature_mask must be a file name"):
        Exemplar.load(granite_32_file, feature_mask=5)
    automatic = Exemplar.load(granite_32_file, feature_distance=True)
    np.testing.assert_array_equal(
        automatic.features, Exemplar.load(granite_32_file, feature_distance="auto").features)
    assert automatic.features.shape[2] == 4
    assert Exemplar.load(granite_32_file, feature_mask=mask).features_from == "mask.npy"


def test_candidates_are_saved_where_nothing_else_is_lost(candidates, tmp_path):
    """``save("dir/")`` wrote a file named ``dir``, and a save over a photo destroyed it."""
    photo = tmp_path / "granite.png"
    photo.write_bytes(b"\x89PNG\r\n\x1a\n not candidates")
    (tmp_path / "folder").mkdir()
    for path, problem in ((f"{tmp_path}/cands/", "names a folder, not a file"),
                          (photo, "exists and is not a warptex candidate file"),
                          (tmp_path / "folder", "is a folder")):
        with pytest.raises(CandidateCacheError, match=problem):
            candidates.save(path)
    assert photo.read_bytes().endswith(b"not candidates")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder", "granite.png"]
    candidates.save(tmp_path / "c.wtc")
    candidates.save(tmp_path / "c.wtc")  # its own file, written again
    loaded = CandidateSet.load(tmp_path / "c.wtc")
    assert loaded == candidates and loaded is not candidates
    assert loaded != precompute(warptex.Exemplar(candidates.colors[0][::-1].copy()), cache=False)
    # The fields' arrays made thousands of lines of it.
    assert repr(loaded).count("\n") == 0 and "levels" in repr(loaded)


def test_metrics_name_what_does_not_fit(granite_32):
    volume = np.zeros((16, 16, 16, 3), np.float32)
    colors = granite_32.colors
    for call in (metrics.neighborhood_energy, metrics.sliced_wasserstein,
                 metrics.histogram_distance):
        with pytest.raises(ValueError, match="volume has 1 channels, exemplar 3"):
            call(volume[..., :1], colors, 0)
        with pytest.raises(ValueError, match="axis must be 0, 1 or 2"):
            call(volume, colors, 3)
        with pytest.raises(TypeError, match="exemplar must hold float colors"):
            call(volume, (colors * 255).astype(np.uint8), 0)
    with pytest.raises(ValueError, match="too small for 5 x 5 patches"):
        metrics.neighborhood_energy(volume[:, :4], colors, 0)
    # An Exemplar is taken for its colors.
    assert metrics.histogram_distance(volume, granite_32, 0) == pytest.approx(
        metrics.histogram_distance(volume, colors, 0))
    with pytest.raises(ValueError, match="too small for the repetition score"):
        metrics.repetition_score(colors[:16, :16])
    assert 0.0 <= metrics.repetition_score(np.tile(colors[..., 0], (2, 2))) <= 1.0


def test_reference_volumes_and_patches_name_the_argument_at_fault(granite_32):
    """The helpers comparisons are built from refuse what NumPy would take otherwise (a
    2-int shape, a fractional depth) or fail on deep inside."""
    colors = granite_32.colors
    for shape in ((4, 4), (4, 4, -1), (4, 4, 2.0), 4):
        with pytest.raises(ValueError, match="shape must be"):
            metrics.iid_noise(colors, shape)
    assert metrics.iid_noise(granite_32, (2, 3, 4)).shape == (2, 3, 4, 3)
    for seed, problem in ((1.5, "an integer"), (True, "an integer"), (-1, "at least 0")):
        with pytest.raises(SettingError, match=f"^seed must be {problem}"):
            metrics.iid_noise(colors, (2, 2, 2), seed=seed)
    for depth, problem in ((1.5, "depth must be an integer"), (0, "depth must be at least 1")):
        with pytest.raises(ValueError, match=problem):
            metrics.extrusion(colors, depth)
    with pytest.raises(ValueError, match=r"exemplar must be an \(H, W, C\) image"):
        metrics.extrusion(colors[..., 0], 2)
    with pytest.raises(ValueError, match=r"image must be an \(H, W, C\) image"):
        metrics.patches(colors[..., 0], 5)
    with pytest.raises(ValueError, match="size \\(of the patches\\) must be at least 1"):
        metrics.patches(colors, 0)
    with pytest.raises(ValueError, match=r"volume must be an \(X, Y, Z, C\) array"):
        metrics.axis_slices([[1.0]], 0)


def test_files_refuse_what_their_formats_cannot_hold(tmp_path):
    with pytest.raises(ValueError, match=r"volume must be a \(X, Y, Z, C\) array"):
        write_volume(tmp_path / "v.exr", np.zeros((4, 4, 4), np.float32), srgb=False)
    with pytest.raises(TypeError, match="volume must hold float colors, got uint8"):
        write_volume(tmp_path / "v.npy", np.zeros((4, 4, 4, 3), np.uint8), srgb=False)
    with pytest.raises(ValueError, match=r"image must be a \(H, W, C\) array"):
        write_image(tmp_path / "i.exr", [[0.0, 1.0]], srgb=False)
    with pytest.raises(ValueError, match=r"must end in \.npy or \.exr"):
        write_image(tmp_path / "i.png", np.zeros((2, 2, 3), np.float32), srgb=False)
    assert not any(tmp_path.iterdir())


def test_files_reach_the_disk_before_they_replace_the_old_ones(tmp_path, monkeypatch):
    """Renamed unsynced, a file can be found empty under its name after a power cut, the
    old one gone: each is synced before the renames, and their folders after."""
    events = []
    sync, replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("sync", os.readlink(f"/proc/self/fd/{fd}")))
        sync(fd)

    def renamed(source, target):
        events.append(("rename", str(target)))
        replace(source, target)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", renamed)
    first, second = tmp_path / "a" / "image.png", tmp_path / "image.png.json"
    write_together([(first, lambda tmp: tmp.write_bytes(b"png")),
                    (second, lambda tmp: tmp.write_bytes(b"{}"))])
    kinds = [kind for kind, _ in events]
    assert kinds[:2] == ["sync", "sync"] and kinds[2:4] == ["rename", "rename"]
    assert [is_temporary(Path(synced).name, target.stem, target.suffix)
            for (_, synced), target in zip(events[:2], (first, second), strict=True)] == [True] * 2
    assert {name for kind, name in events[4:] if kind == "sync"} == {str(tmp_path),
                                                                      str(tmp_path / "a")}
    assert first.read_bytes() == b"png" and second.read_bytes() == b"{}"


def test_a_failed_write_names_the_file_asked_for(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    target = blocker / "out.npy"
    with pytest.raises(OSError) as caught:
        write_atomically(target, lambda tmp: tmp.write_bytes(b"x"))
    assert caught.value.filename == str(target)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_any_name_that_fits_is_written_and_a_longer_one_is_refused_before_the_work(tmp_path):
    """The temporary name is longer than the name asked for: its stem is cut, so a name
    of 255 bytes is written (it failed after the work); a longer one is refused by the
    check that runs before the work."""
    for name in ("s" * 251 + ".png", "é" * 125 + "s.png", "s" * 200 + "." + "x" * 54):
        target = tmp_path / name
        assert len(os.fsencode(target.name)) == 255 and file_problem(target) is None
        write_atomically(target, lambda tmp: tmp.write_bytes(b"x"))
        assert target.read_bytes() == b"x"
        target.unlink()
    assert not any(tmp_path.iterdir())
    for folder in (tmp_path, tmp_path / "not yet made"):
        assert "file name too long" in file_problem(folder / ("s" * 256 + ".png"))
        # A suffix too long for any temporary name, and a name no file system takes.
        assert "suffix too long" in file_problem(folder / ("a." + "x" * 253))
        assert "cannot be encoded" in file_problem(folder / "a\ud800.png")


def test_writers_never_share_a_temporary_name(tmp_path):
    """Writers in two containers sharing a folder may have the same pid and thread id:
    the temporary names are random, so each write has its own, even from one thread."""
    names = []
    for _ in range(2):
        write_atomically(tmp_path / "a.npy", lambda tmp: names.append(tmp.name)
                         or tmp.write_bytes(b"x"))
    assert len(set(names)) == 2 and all(n.startswith(".a.") for n in names)


def test_temporary_names_are_told_alike_by_the_cache_listing_and_dead_writes(tmp_path):
    # Earlier versions tagged temporary files with a pid and a thread id: still theirs.
    target = tmp_path / "wtc_1.wtc"
    old = time.time() - 2 * UNFINISHED_AGE
    for tag in (f"12.{'0a' * _TOKEN_BYTES}", "4242.140213"):
        name = _temporary_name(target, tag)
        assert is_temporary(name, "wtc_", ".wtc") and not is_temporary(name, "wtb_", ".wtc")
        (tmp_path / name).write_bytes(b"part")
        os.utime(tmp_path / name, (old, old))
    assert len(dead_writes(target)) == 2
    for name in (".wtc_1.tmp.wtc", ".wtc_1.12.tmp.wtc", ".wtc_1.x.3.tmp.wtc", "wtc_1.1.2.tmp.wtc",
                 ".wtc_1.1.2.tmp.wtb"):
        assert not is_temporary(name, "wtc_", ".wtc"), name


def test_dead_writes_are_a_file_s_own_temporary_files_left_over_an_hour(tmp_path):
    target = tmp_path / "s.store"
    old = time.time() - 2 * UNFINISHED_AGE
    tags = [f"12.{'0a' * _TOKEN_BYTES}", f"7.{'b9' * _TOKEN_BYTES}"]
    dead, young = (tmp_path / _temporary_name(target, tag) for tag in tags)
    others = [tmp_path / _temporary_name(tmp_path / name, tags[0])
              for name in ("s.x.store", "s.wtb", "t.store")]
    for path in (dead, young, *others):
        path.write_bytes(b"part")
        if path is not young:
            os.utime(path, (old, old))
    assert dead_writes(target) == [dead]
    odd = tmp_path / "a\nb.store"  # any character a name may hold
    odd_dead = tmp_path / _temporary_name(odd, tags[0])
    odd_dead.write_bytes(b"part")
    os.utime(odd_dead, (old, old))
    assert dead_writes(odd) == [odd_dead]
    long = tmp_path / ("s" * 251 + ".png")  # its temporary files' stems are cut
    cut = tmp_path / _temporary_name(long, tags[0])
    cut.write_bytes(b"part")
    os.utime(cut, (old, old))
    assert dead_writes(long) == [cut] and dead_writes(tmp_path / "missing" / "s.store") == []


def test_a_write_through_a_symbolic_link_replaces_its_target_and_keeps_the_link(tmp_path):
    """As ``open`` writes through a link: a file shared through links stays shared."""
    target = tmp_path / "real" / "out.bin"
    target.parent.mkdir()
    target.write_bytes(b"old")
    link = tmp_path / "link.bin"
    link.symlink_to(target)
    write_atomically(link, lambda tmp: tmp.write_bytes(b"new"))
    assert link.is_symlink() and target.read_bytes() == b"new"
    assert sorted(p.name for p in target.parent.iterdir()) == ["out.bin"]
    dangling = tmp_path / "dangling.bin"
    dangling.symlink_to(tmp_path / "real" / "made.bin")
    write_atomically(dangling, lambda tmp: tmp.write_bytes(b"made"))
    assert dangling.is_symlink() and (tmp_path / "real" / "made.bin").read_bytes() == b"made"
    # The temporary file is named as asked: writers take the format from its suffix.
    suffixes = []
    other = tmp_path / "image.png"
    other.symlink_to(target)
    write_atomically(other, lambda tmp: suffixes.append(tmp.suffix) or tmp.write_bytes(b"png"))
    assert suffixes == [".png"] and target.read_bytes() == b"png"
    with pytest.raises(ValueError, match="are one file"):
        write_together([(target, lambda tmp: tmp.write_bytes(b"a")),
                        (link, lambda tmp: tmp.write_bytes(b"b"))])
    assert target.read_bytes() == b"png"


def test_a_failed_write_leaves_no_folder_it_made(tmp_path):
    """Folders made for the files are removed again when the write fails (compare's -o
    DIR on a full disk), not those that were there, nor one another writer filled."""
    def full(tmp):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp))

    with pytest.raises(OSError, match="No space"):
        write_together([(tmp_path / "new" / "deeper" / "a.png", lambda tmp: tmp.write_bytes(b"a")),
                        (tmp_path / "new" / "b.json", full)])
    assert not any(tmp_path.iterdir())

    def crowded(tmp):
        (tmp_path / "new" / "theirs.txt").write_text("another writer's")
        full(tmp)

    with pytest.raises(OSError, match="No space"):
        write_atomically(tmp_path / "new" / "deeper" / "c.npy", crowded)
    assert [p.name for p in tmp_path.rglob("*")] == ["new", "theirs.txt"]


def test_a_library_writer_failing_for_another_reason_names_the_file_asked_for(tmp_path):
    """A writer's RuntimeError without a system reason keeps its words, the temporary
    file's name in them replaced by the file asked for."""
    target = tmp_path / "out.exr"

    def odd(tmp):
        raise RuntimeError(f'cannot encode "{tmp}": unsupported channel layout')

    with pytest.raises(OSError) as caught:
        write_atomically(target, odd)
    assert caught.value.errno == errno.EIO and caught.value.filename == str(target)
    assert caught.value.strerror == f'cannot encode "{target}": unsupported channel layout'
    assert not any(tmp_path.iterdir())


def test_files_written_together_are_all_left_as_they_were_when_one_fails(tmp_path):
    """write_together: the second file's write fails (a full disk), so the first, written
    already, is not put in place either; the error names the file that failed."""
    first, second = tmp_path / "image.png", tmp_path / "image.png.json"
    first.write_bytes(b"old image")
    second.write_text("old figures")

    def full(tmp):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp))

    with pytest.raises(OSError) as caught:
        write_together([(first, lambda tmp: tmp.write_bytes(b"new image")), (second, full)])
    assert caught.value.filename == str(second) and caught.value.errno == errno.ENOSPC
    assert (first.read_bytes(), second.read_text()) == (b"old image", "old figures")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["image.png", "image.png.json"]
    write_together([(first, lambda tmp: tmp.write_bytes(b"new image")),
                    (second, lambda tmp: tmp.write_text("new figures"))])
    assert (first.read_bytes(), second.read_text()) == (b"new image", "new figures")


def test_a_folder_in_the_place_of_a_later_file_written_together_replaces_none(tmp_path):
    """Refused before any rename: the first file is not replaced beside a second that
    cannot be, and no temporary file is left."""
    first, second = tmp_path / "image.png", tmp_path / "image.png.json"
    first.write_bytes(b"old image")
    second.mkdir()
    with pytest.raises(IsADirectoryError) as caught:
        write_together([(first, lambda tmp: tmp.write_bytes(b"new image")),
                        (second, lambda tmp: tmp.write_text("new figures"))])
    assert caught.value.filename == str(second)
    assert first.read_bytes() == b"old image" and not any(second.iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["image.png", "image.png.json"]


def test_a_folder_that_takes_no_file_is_found_by_a_trial_write(tmp_path, monkeypatch):
    """Permission bits do not tell (root, read-only mounts): a trial file does."""
    import tempfile

    from warptex.archive import folder_problem

    assert folder_problem(tmp_path / "new" / "deeper") is None

    def refused(*args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(tempfile, "TemporaryFile", refused)
    assert folder_problem(tmp_path / "new" / "deeper") == (
        f"cannot write in {tmp_path} ({os.strerror(errno.EROFS)})")


def test_a_ctrl_c_between_the_renames_of_files_written_together_comes_after_the_last(
        tmp_path, monkeypatch):
    """A stop right after the first rename left a new image beside old figures (a
    comparison's new sheet beside its old tables)."""
    import signal

    import warptex.archive

    first, second = tmp_path / "image.png", tmp_path / "image.png.json"
    first.write_bytes(b"old image")
    second.write_text("old figures")
    replace = os.replace
    renamed = []

    def replace_then_stop(source, target):
        replace(source, target)
        renamed.append(Path(target).name)
        if len(renamed) == 1:
            signal.raise_signal(signal.SIGINT)

    synced = []
    folder_synced = warptex.archive._synced
    monkeypatch.setattr(warptex.archive.os, "replace", replace_then_stop)
    monkeypatch.setattr(warptex.archive, "_synced", lambda path, mode: (
        synced.append(Path(path)), folder_synced(path, mode)))
    with pytest.raises(KeyboardInterrupt):
        write_together([(first, lambda tmp: tmp.write_bytes(b"new image")),
                        (second, lambda tmp: tmp.write_text("new figures"))])
    assert renamed == ["image.png", "image.png.json"]
    assert synced[-1] == tmp_path  # the folder too, so the renames outlast a power cut
    assert (first.read_bytes(), second.read_text()) == (b"new image", "new figures")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["image.png", "image.png.json"]


def test_the_ends_of_every_range_are_accepted_and_one_step_beyond_refused():
    for jitter, passes, seed in ((0.0, 0, 0), (MAX_JITTER, MAX_PASSES, MAX_SEED)):
        check_settings(jitter=jitter, passes=passes, seed=seed)
    for kw, name in (({"jitter": MAX_JITTER + 1e-9}, "jitter"), ({"jitter": -1e-9}, "jitter"),
                     ({"passes": MAX_PASSES + 1}, "passes"), ({"passes": -1}, "passes"),
                     ({"seed": MAX_SEED + 1}, "seed"), ({"seed": -1}, "seed")):
        with pytest.raises(SettingError) as err:
            check_settings(**kw)
        assert err.value.name == name


def test_the_modules_the_readme_names_are_reached_from_a_plain_import():
    """`import warptex` alone, in a fresh interpreter: every `warptex.MODULE.NAME` the README
    writes works as written (`warptex.mesh_files.load_mesh` did not)."""
    readme = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    names = sorted(set(re.findall(r"\bwarptex\.([a-z_]+\.[A-Za-z_]+)", readme)))
    assert "volume_files.write_volume" in names
    names.append("baselines.kopf")
    code = "import warptex\n" + "".join(f"warptex.{n}\n" for n in names)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    with pytest.raises(AttributeError, match="no attribute 'volumes'"):
        warptex.volumes  # noqa: B018
    # Completion offers the API, not the helpers the package imports.
    assert set(dir(warptex)) == set(warptex.__all__) | set(warptex._SUBMODULES)
    assert "sys" in vars(warptex) and "sys" not in dir(warptex)


def _import_warptex(folder: Path, first: str = "") -> subprocess.CompletedProcess:
    """``import warptex`` in a fresh interpreter working in ``folder``, after ``first``."""
    return subprocess.run([sys.executable, "-c", first + "import warptex"], cwd=folder,
                          capture_output=True, text=True, timeout=120)


def _kernels_package(folder: Path, common: str) -> None:
    """A package ``kernels`` in ``folder`` whose ``common`` module is ``common``."""
    (folder / "kernels").mkdir()
    (folder / "kernels" / "__init__.py").write_text("")
    (folder / "kernels" / "common.py").write_text(common)


def test_another_kernels_package_is_named_as_the_cause(tmp_path):
    """warptex's kernels are the top-level package ``kernels``: a folder of that name in the
    working folder (or PyPI's package installed over it) hid it, and imports failed later
    with "No module named 'kernels.candidates'"."""
    _kernels_package(tmp_path, "HUB = 'another package'\n")
    run = _import_warptex(tmp_path)
    assert run.returncode != 0
    assert (f"the one Python found, {tmp_path / 'kernels' / '__init__.py'}, is another "
            f"({tmp_path / 'kernels' / 'common.py'} is not warptex's)" in run.stderr)
    # One without common.py: an editable install's import hook gave warptex's to it, which
    # passed, and imports failed later on the modules it hides.
    (tmp_path / "kernels" / "common.py").unlink()
    (tmp_path / "kernels" / "synthesis.py").write_text("HUB = 'another package'\n")
    run = _import_warptex(tmp_path)
    assert run.returncode != 0 and "is another (" in run.stderr, run.stderr
    (tmp_path / "kernels" / "synthesis.py").unlink()
    (tmp_path / "kernels" / "__init__.py").unlink()
    # One of links to warptex's own files (a strict editable install's) hides nothing.
    import kernels

    for mine in Path(kernels.__file__).parent.glob("*.py"):
        (tmp_path / "kernels" / mine.name).symlink_to(mine)
    run = _import_warptex(tmp_path)
    assert run.returncode == 0, run.stderr
    for link in (tmp_path / "kernels").glob("*.py"):
        link.unlink()
    # A folder named kernels without __init__.py (a cache) hides nothing.
    run = _import_warptex(tmp_path)
    assert run.returncode == 0, run.stderr


def test_a_python_without_warp_is_named_not_another_kernels_package(tmp_path):
    """The system's python3 where the checkout's .venv was meant: warptex's own kernels fail
    to import Warp, which is the cause to name; another kernels package that fails on a
    module of its own is still another package."""
    run = _import_warptex(tmp_path, "import sys\nsys.modules['warp'] = None\n")
    assert run.returncode != 0
    assert (f"ImportError: warptex needs the module 'warp', which this Python "
            f"({sys.executable}) does not have: run warptex in the environment" in run.stderr)
    assert "is another" not in run.stderr
    _kernels_package(tmp_path, "import some_module_of_its_own\n")
    run = _import_warptex(tmp_path)
    assert run.returncode != 0
    assert "is another (No module named 'some_module_of_its_own')" in run.stderr, run.stderr


def test_an_engine_or_texture_is_not_pickled_but_named(data_dir, warp_device):
    """pickle failed inside ctypes, naming no warptex object (a ProcessPoolExecutor's
    submit of texture.query, say); the engine's CandidateSet pickles, and a texture made
    from it in another process gives the same voxels."""
    import copy
    import pickle

    from warptex.candidates import precompute
    from warptex.store import BrickStore
    from warptex.synthesis import Synthesizer
    from warptex.texture import SolidTexture

    texture = SolidTexture(precompute(data_dir / "granite_64.png"))
    for thing, what in ((texture, "a SolidTexture"), (texture.synthesizer, "a Synthesizer"),
                        (texture.store, "a Synthesizer")):
        with pytest.raises(TypeError, match=f"^{what} holds Warp arrays of this process"):
            pickle.dumps(thing)
        with pytest.raises(TypeError, match=f"^{what} holds Warp arrays"):
            copy.deepcopy(thing)
    candidates = pickle.loads(pickle.dumps(texture.synthesizer.candidates))
    points = np.random.default_rng(4).uniform(-40, 40, (200, 3))
    np.testing.assert_array_equal(SolidTexture(candidates).query(points), texture.query(points))
    with pytest.raises(TypeError, match=r"a SolidTexture's is its \.synthesizer\), got "
                                        r"SolidTexture"):
        BrickStore(texture)
    assert isinstance(texture.store, BrickStore) and isinstance(texture.synthesizer, Synthesizer)
