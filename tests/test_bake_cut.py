"""Baking onto meshes and planar cuts (Dong 2008, sections 6.2 and 6.4)."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from warptex.bake import bake_uv_texture, texel_points, vertex_colors
from warptex.cut import cap_faces, cut
from warptex.mesh_files import export, exported_files
from warptex.surface import block_transform, shell, to_voxel_space
from warptex.texture import SolidTexture, plane_points
from warptex.warp_runtime import KernelCacheError


@pytest.fixture(scope="module")
def texture(granite_32, warp_device) -> SolidTexture:
    from warptex.candidates import precompute

    return SolidTexture(precompute(granite_32, cache=False), seed=2)


@pytest.fixture(scope="module")
def sphere() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=3, radius=1.0)


def test_vertex_colors_are_point_queries(texture, sphere):
    m = block_transform(sphere, 24)
    colors = vertex_colors(texture, sphere, m)
    assert np.array_equal(colors, texture.query(to_voxel_space(sphere, m)))


def test_baked_texel_equals_query_at_its_surface_point(texture, sphere):
    # Off the origin and of radius 2: its normals are not its positions.
    mesh = sphere.copy().apply_scale(2.0).apply_translation([5.0, -1.0, 0.5]).unwrap()
    m = block_transform(mesh, 24)
    image, covered = bake_uv_texture(texture, mesh, mesh.visual.uv, m, size=64)
    points, mask = texel_points(mesh, mesh.visual.uv, m, (64, 64))
    assert np.array_equal(covered.reshape(-1), mask)
    assert 0.3 < covered.mean() < 1.0
    flat = image.reshape(-1, image.shape[2])
    assert np.array_equal(flat[mask], texture.query(points[mask]))
    # Independently: the point of a covered texel lies in its triangle, on the surface.
    radius = np.linalg.norm(points[mask] - 12.0, axis=1)  # the block's centre
    scale = m[0, 0] * 2.0
    assert np.all(radius <= scale + 1e-3) and np.all(radius >= scale * 0.98)


def test_far_from_the_origin_baking_shows_the_colors_of_the_same_points(texture, sphere):
    """Surface points stay float64 on the way to the texture, as queries and slices do:
    1.5 million voxels out, float32 would move them by up to 1/16 of a voxel."""
    mesh = sphere.unwrap()
    near = block_transform(mesh, 24)
    far = near.copy()
    far[:3, 3] += 1.5e6
    exact = np.asarray(mesh.vertices, np.float64) @ far[:3, :3].T + far[:3, 3]
    assert np.array_equal(vertex_colors(texture, mesh, far), texture.query(exact))
    points, mask = texel_points(mesh, mesh.visual.uv, far, (32, 32))
    points_near, mask_near = texel_points(mesh, mesh.visual.uv, near, (32, 32))
    assert np.array_equal(mask, mask_near) and mask.any()
    assert np.allclose(points[mask] - 1.5e6, points_near[mask], rtol=0.0, atol=1e-6)


def test_planar_slice_matches_the_volume(texture):
    box = texture.synthesizer.box((2, -3, 5), (6, 7, 1))[:, :, 0]
    pts = plane_points(np.array([2.5, -2.5, 5.5]), np.array([1, 0, 0]), np.array([0, 1, 0]),
                       (6, 7))
    got = texture.query(pts, filter="nearest").reshape(6, 7, -1)
    assert np.array_equal(got, box)
    sliced = texture.slice((2.5, -2.5, 5.5), (1, 0, 0), (0, 1, 0), (6, 7), filter="nearest")
    assert np.array_equal(sliced, box)
    tilted = texture.slice((0.0, 0.0, 0.0), (0.6, 0.8, 0.0), (0.0, 0.6, 0.8), (5, 4))
    expected = texture.query(np.array([r * np.array([0.6, 0.8, 0]) + c * np.array([0, 0.6, 0.8])
                                       for r in range(5) for c in range(4)]))
    assert np.allclose(tilted.reshape(-1, tilted.shape[2]), expected, atol=1e-6)


def test_cut_caps_continue_the_outer_surface(texture, sphere):
    origin, normal = np.array([0.1, 0.0, 0.0]), np.array([1.0, 0.3, 0.0])
    top, bottom = cut(sphere, origin, normal)
    m = block_transform(sphere, 24)
    for half in (top, bottom):
        assert half.is_watertight
        cap = cap_faces(half, origin, normal)
        assert 0 < cap.sum() < len(half.faces)
        cap_vertices = np.unique(half.faces[cap])
        outline = np.intersect1d(cap_vertices, half.faces[~cap])
        # The cap meets the outer surface vertex for vertex (watertight: no gap, no seam),
        # and has vertices of its own inside, no further apart than twice the median of the
        # sphere's edges that cross the plane, so vertex colours carry the texture across it.
        assert len(cap_vertices) > 2 * len(outline) > 0
        corners = half.vertices[half.faces[cap]]
        sides = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)
        above = (sphere.vertices - origin) @ normal > 0
        crossing = above[sphere.edges_unique[:, 0]] != above[sphere.edges_unique[:, 1]]
        assert sides.max() <= 2 * np.median(sphere.edges_unique_length[crossing]) + 1e-12
        assert np.allclose((half.vertices[cap_vertices] - origin) @ normal, 0.0, atol=1e-9)
        colors = vertex_colors(texture, half, m)
        expected = texture.query(to_voxel_space(half, m))
        assert np.array_equal(colors[cap_vertices], expected[cap_vertices])
    with pytest.raises(ValueError, match="does not cut"):
        cut(sphere, np.array([5.0, 0, 0]), normal)


@pytest.mark.parametrize(("origin", "normal"), [
    ((0.0, 0.0, 0.0), (0.0, 2.0, 1.0)),  # trimesh's cap starts with a zero-area triangle
    ((0.1, 0.2, 0.3), (2.0, -1.0, 2.0)),
    ((0.0, 0.0, 0.0), (1.0, 1.0, 0.3)),  # outline vertices on straight runs of the outline
])
def test_refined_caps_face_outwards_and_keep_every_outline_vertex(origin, normal):
    box = trimesh.creation.box()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no cap left unrefined
        halves = cut(box, np.array(origin), np.array(normal))
    n = np.asarray(normal) / np.linalg.norm(normal)
    for half, facing in zip(halves, (-n, n), strict=True):
        assert half.is_watertight and half.is_winding_consistent
        cap = cap_faces(half, np.array(origin), n)
        assert np.allclose(half.face_normals[cap] @ facing, 1.0)
    assert np.isclose(halves[0].volume + halves[1].volume, box.volume)


@pytest.mark.parametrize(("origin", "normal"), [
    ((0.06, -0.18, -0.1), (0.4, -0.2, -0.9)),
    ((0.04, 0.02, -0.07), (-0.3, 0.5, -0.9)),
    ((-0.09, 0.0, -0.15), (-0.2, 0.1, 0.4)),
])
def test_a_cut_across_flat_quads_keeps_each_outline_vertex(origin, normal):
    """Where the plane crosses a flat quad's diagonal, three outline vertices are collinear
    and trimesh's cap skips the middle one: the refined cap had a crack (a T-junction,
    whose vertex colour the cap did not show) beside it."""
    ring = trimesh.creation.annulus(0.5, 1.0, 1.0)
    for half in cut(ring, np.array(origin), np.array(normal)):
        assert half.is_watertight and half.is_winding_consistent


def test_cutting_an_open_mesh_where_it_has_no_inside():
    tube = trimesh.creation.cylinder(0.5, 1.0)
    tube.update_faces(np.abs(tube.face_normals[:, 2]) < 0.5)  # no end discs
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        halves = cut(tube, np.zeros(3), np.array([1.0, 0.0, 0.0]))
    assert all(len(half.faces) > 0 for half in halves)


def test_halves_whose_caps_differ_or_are_missing_are_warned_of():
    """README promises one colour on either half at a point of the cut face. A plane along
    one of the mesh's faces (the inner face of an L) gave the halves caps of other
    triangles, and boxes glued face to face (a wall inside) no cap at all, unsaid."""
    import shapely

    ell = trimesh.creation.extrude_polygon(
        shapely.Polygon([(0, 0), (2, 0), (2, 1), (1, 1), (1, 2), (0, 2)]), 1.0)
    with pytest.warns(UserWarning, match=r"the two halves' caps differ \(\d+ of \d+ and \d+ "
                      "triangles shared"):
        cut(ell, np.array([0.0, 1.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    glued = trimesh.util.concatenate([
        trimesh.creation.box(bounds=[[-1, -0.5, -0.5], [0, 0.5, 0.5]]),
        trimesh.creation.box(bounds=[[0, -0.5, -0.5], [1, 0.5, 0.5]])])
    glued.merge_vertices()
    with pytest.warns(UserWarning, match="the cut left both halves of a closed mesh open"):
        cut(glued, np.array([0.3, 0.0, 0.1]), np.array([0.0, 0.0, 1.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # across the wall, each box's section is a cap
        cut(glued, np.array([0.3, 0.0, 0.1]), np.array([0.0, 1.0, 0.0]))


def test_a_cap_that_cannot_be_refined_is_trimesh_s_own_and_said_so(sphere, monkeypatch):
    """Where the cap's triangulation does not come out as its outline (shapely giving no
    triangles here), each half keeps trimesh's cap, closed, with a warning: colours then
    interpolate the outline's, and the halves still meet."""
    import shapely

    origin, normal = np.array([0.1, 0.0, 0.0]), np.array([1.0, 0.3, 0.2])
    refined = cut(sphere, origin, normal)
    monkeypatch.setattr(shapely, "constrained_delaunay_triangles",
                        lambda region: shapely.GeometryCollection())
    with pytest.warns(UserWarning) as caught:
        halves = cut(sphere, origin, normal)
    # Each half's cap, and that trimesh triangulated the two caps each its own way.
    assert [str(w.message)[:50] for w in caught] == [
        "a cut's cap could not be refined; its colors inter"] * 2 + [
        "the two halves' caps differ (1 of 93 and 93 triang"]
    assert "a cap left unrefined" in str(caught[2].message)
    assert all(w.filename == __file__ for w in caught)
    for half, finer in zip(halves, refined, strict=True):
        assert half.is_watertight and len(half.faces) < len(finer.faces)
        assert half.volume == pytest.approx(finer.volume, rel=1e-9)


def test_a_cap_whose_region_misses_a_loop_of_the_section_is_not_refined(monkeypatch):
    """Two spheres cut at once: where the region triangulated holds one of the two loops
    (shapely giving one polygon here), refining would leave the other's cap out, a hole;
    each half keeps trimesh's caps instead, closed, and says so."""
    import shapely

    first = trimesh.creation.icosphere(subdivisions=3)
    second = first.copy()
    second.apply_translation([3.0, 0.0, 0.0])
    pair = trimesh.util.concatenate([first, second])
    build_area = shapely.build_area
    monkeypatch.setattr(shapely, "build_area", lambda lines: shapely.get_parts(
        build_area(lines))[0])
    with pytest.warns(UserWarning) as caught:
        halves = cut(pair, np.array([0.0, 0.1, 0.0]), np.array([0.0, 1.0, 0.2]))
    said = [str(w.message) for w in caught]
    assert len(said) == 3 and said[2].startswith("the two halves' caps differ (")
    assert all(s.startswith("a cut's cap could not be refined") for s in said[:2])
    assert all(half.is_watertight for half in halves)


def test_a_cap_across_an_open_mesh_s_opening_is_refined():
    """trimesh closes the section of a tube open at the top across its opening, with cap
    edges that no face of the tube holds: the refined cap keeps them."""
    tube = trimesh.creation.cylinder(0.5, 1.0)
    tube.update_faces(tube.face_normals[:, 2] < 0.5)
    origin, normal = np.array([0.0, 0.0, 0.3]), np.array([1.0, 0.0, 1.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no cap left unrefined
        halves = cut(tube, origin, normal)
    caps = [half.area_faces[cap_faces(half, origin, normal)].sum() for half in halves]
    assert caps[0] > 0.5 and np.isclose(caps[0], caps[1])


def test_triangles_of_zero_area_are_left_out_of_a_cut():
    """A box with a sliver on the plane and one across it cuts as the box does; a mesh of
    slivers alone is refused (its cap failed with an IndexError)."""
    box = trimesh.creation.box()
    corners = [[0.0, -0.5, -0.5], [0.0, 0.0, 0.0], [0.0, 0.5, 0.5], [-0.4, -0.1, -0.1],
               [0.4, 0.1, 0.1]]
    n = len(box.vertices)
    slivers = trimesh.Trimesh(np.vstack([box.vertices, corners]),
                              np.vstack([box.faces, [[n, n + 1, n + 2], [n + 3, n + 1, n + 4]]]),
                              process=False)
    origin, normal = np.zeros(3), np.array([1.0, 0.0, 0.0])
    for with_slivers, plain in zip(cut(slivers, origin, normal), cut(box, origin, normal),
                                   strict=True):
        assert with_slivers.is_watertight
        np.testing.assert_array_equal(with_slivers.faces, plain.faces)
        np.testing.assert_array_equal(with_slivers.vertices, plain.vertices)
    line = trimesh.Trimesh(corners[:3], [[0, 1, 2]], process=False)
    with pytest.raises(ValueError, match="every triangle of the mesh has zero area"):
        cut(line, origin, np.array([0.0, 1.0, 0.0]))


def test_a_normal_of_any_finite_length_cuts_as_its_direction():
    """Its length alone overflowed beyond 1e154 (NumPy warnings, then a cap left coarse)."""
    box = trimesh.creation.box()
    origin = np.full(3, 0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        expected = cut(box, origin, np.array([1.0, 1.0, 0.0]))
        for scale in (1e308, 1e-300):
            for half, same in zip(cut(box, origin, np.array([scale, scale, 0.0])), expected,
                                  strict=True):
                np.testing.assert_array_equal(half.vertices, same.vertices)
                np.testing.assert_array_equal(half.faces, same.faces)
    with pytest.raises(ValueError, match="normal must be three finite numbers"):
        cut(box, origin, np.array([np.inf, 0.0, 0.0]))


def test_a_cut_through_separate_parts_caps_each():
    """Two boxes cut together: the cap has two outlines, which trimesh nests with rtree."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    other = box.copy()
    other.apply_translation((0.0, 2.0, 0.0))
    pair = trimesh.util.concatenate([box, other])
    origin, normal = np.zeros(3), np.array([1.0, 0.0, 0.0])
    for half in cut(pair, origin, normal):
        assert half.is_watertight
        assert len(half.split(only_watertight=True)) == 2
        assert np.isclose(half.volume, 1.0)
        cap = cap_faces(half, origin, normal)
        assert np.isclose(half.area_faces[cap].sum(), 2.0)


def test_cut_halves_agree_where_they_meet(granite_32_file, sphere, tmp_path, warp_device,
                                           capsys):
    """Off the mesh's centre, each half has its own bounding box; both must be textured
    in the block of the whole mesh, so the outline they share has one colour."""
    from warptex.cli import main

    mesh = tmp_path / "sphere.ply"
    sphere.export(mesh)
    assert main(["cut", str(mesh), "--exemplar", str(granite_32_file), "--resolution", "24",
                 "--origin", "0.3", "0", "0", "-o", str(tmp_path / "c.ply")]) == 0
    assert "cutting: 100%" in capsys.readouterr().err  # seconds on a large mesh: a bar
    a = trimesh.load(tmp_path / "c.ply", process=False)
    b = trimesh.load(tmp_path / "c_b.ply", process=False)
    in_b = {v.tobytes(): i for i, v in enumerate(np.round(b.vertices, 6))}
    shared = [(i, in_b[v.tobytes()]) for i, v in enumerate(np.round(a.vertices, 6))
              if v.tobytes() in in_b]
    assert len(shared) > 10
    ia, ib = np.array(shared).T
    np.testing.assert_array_equal(a.visual.vertex_colors[ia], b.visual.vertex_colors[ib])


def test_export_formats(texture, sphere, tmp_path):
    m = block_transform(sphere, 24)
    written = export(sphere, tmp_path / "s.ply", colors=vertex_colors(texture, sphere, m))
    loaded = trimesh.load(written[0])
    assert len(loaded.vertices) == len(sphere.vertices)
    mesh = sphere.unwrap()
    image, _ = bake_uv_texture(texture, mesh, mesh.visual.uv, m, size=32)
    files = export(mesh, tmp_path / "t.obj", image=image, uv=mesh.visual.uv)
    # What the command line checks against its inputs before baking.
    assert sorted(files) == sorted(exported_files(tmp_path / "t.obj", uv_texture=True))
    assert written == exported_files(tmp_path / "s.ply", uv_texture=False)
    glb_files = export(mesh, tmp_path / "t.glb", image=image, uv=mesh.visual.uv)
    assert glb_files == exported_files(tmp_path / "t.glb", uv_texture=True)
    glb = trimesh.load(glb_files[0], force="mesh")
    assert glb.visual.uv.shape == mesh.visual.uv.shape
    with pytest.raises(ValueError, match=r"\.glb or \.obj"):
        export(mesh, tmp_path / "t.ply", image=image, uv=mesh.visual.uv)
    assert not list(tmp_path.glob(".t.ply*"))


def test_an_obj_named_with_spaces_is_refused_and_nothing_written(tmp_path):
    """``mtllib my mesh.mtl`` would name two files to the readers of the .obj."""
    mesh, uv = _square()
    with pytest.raises(ValueError, match="choose a name without spaces"):
        export(mesh, tmp_path / "my mesh.obj", image=np.full((8, 8, 3), 0.5, np.float32), uv=uv)
    assert not any(tmp_path.iterdir())


def test_an_obj_never_arrives_before_its_texture(tmp_path, disk_full_at):
    """Where the .obj's texture cannot be written (a folder of its name), none of its files
    is: the error names the texture, and no temporary is left. A texture whose write fails
    later leaves no .obj that would show another texture."""
    mesh, uv = _square()
    image = np.full((8, 8, 3), 0.5, np.float32)
    (tmp_path / "t.png").mkdir()
    with pytest.raises(IsADirectoryError) as error:
        export(mesh, tmp_path / "t.obj", image=image, uv=uv)
    assert error.value.filename == str(tmp_path / "t.png")
    assert [p.name for p in tmp_path.iterdir()] == ["t.png"]

    disk_full_at(tmp_path / "u.png")
    with pytest.raises(OSError, match="No space"):
        export(mesh, tmp_path / "u.obj", image=image, uv=uv)
    assert not (tmp_path / "u.obj").exists()


def glb_vertex_colors(path: Path) -> np.ndarray:
    """RGB vertex colors (COLOR_0) of a one-mesh .glb: trimesh keeps them beside a material
    as a vertex attribute of the scene's geometry (force="mesh" would drop them)."""
    (geometry,) = trimesh.load(path, process=False).geometry.values()
    return geometry.visual.vertex_attributes["color"][:, :3]


def _gltf_json(path: Path) -> dict:
    import json
    import struct

    data = path.read_bytes()
    (length,) = struct.unpack("<I", data[12:16])
    return json.loads(data[20:20 + length])


def test_exported_materials_are_white_and_matte(tmp_path):
    """The colors show as baked: not tinted by trimesh's default 0.4 gray in .mtl files, not
    metallic as glTF's default material is."""
    mesh, uv = _square()
    image = np.full((8, 8, 3), 0.5, np.float32)
    for name, colors in (("t.glb", None), ("v.glb", np.full((4, 3), 0.5, np.float32))):
        export(mesh, tmp_path / name, colors=colors, image=None if colors is not None else image,
               uv=uv)
        (material,) = _gltf_json(tmp_path / name)["materials"]
        pbr = material["pbrMetallicRoughness"]
        assert pbr["metallicFactor"] == 0.0 and pbr.get("baseColorFactor", [1] * 4) == [1] * 4
    export(mesh, tmp_path / "t.obj", image=image, uv=uv)
    mtl = (tmp_path / "t.mtl").read_text()
    assert "Kd 1.00000000 1.00000000 1.00000000" in mtl and "Ks 0.00000000" in mtl
    assert "Ka 1.00000000 1.00000000 1.00000000" in mtl


@pytest.mark.parametrize(("colors", "image", "error", "message"), [
    (np.full((4, 3), 128, np.uint8), None, TypeError, r"colors must hold floats in \[0, 1\]"),
    (np.full((4, 3), np.nan), None, ValueError, "colors holds NaN or infinite values"),
    (np.full(4, 0.5), None, ValueError, r"colors must be a \(V, C\) array, channels last, "
                                        r"got shape \(4,\)"),
    ([[0.5, 0.5, 0.5]] * 4, None, None, None),  # a list of float rows is colors too
    (None, np.full((8, 8, 3), 200, np.uint8), TypeError, "image must hold floats"),
    (None, np.full((8, 8), 0.5), ValueError, r"image must be a \(H, W, C\) array"),
])
def test_exported_colors_are_floats_of_their_shape(tmp_path, colors, image, error, message):
    """8-bit colors came out white and NaN black, without a word; a row of gray values
    failed deep inside trimesh."""
    mesh, uv = _square()
    path = tmp_path / ("t.ply" if image is None else "t.glb")
    if error is None:
        assert export(mesh, path, colors=colors, image=image, uv=uv) == [path]
        return
    with pytest.raises(error, match=message):
        export(mesh, path, colors=colors, image=image, uv=uv)
    assert list(tmp_path.iterdir()) == []


def test_cli_slice_writes_each_format_in_its_own_encoding(tmp_path, data_dir, warp_device,
                                                         srgb_decoded):
    """An 8-bit exemplar's slice: .npy as synthesized, .exr decoded to linear, .png as the
    values are; a float (linear) exemplar's .png is encoded to sRGB; --raw writes stored
    values everywhere."""
    from PIL import Image

    from warptex.cli import main
    from warptex.srgb import linear_to_srgb

    def sliced(exemplar: Path, name: str, *extra: str) -> np.ndarray:
        out = tmp_path / name
        assert main(["slice", str(exemplar), "--shape", "8", "12", *extra, "-o", str(out)]) == 0
        if out.suffix == ".png":
            return np.asarray(Image.open(out))
        if out.suffix == ".npy":
            return np.load(out)
        import OpenEXR

        with OpenEXR.File(str(out)) as file:
            return file.channels()["RGB"].pixels

    png = data_dir / "granite_64.png"
    stored = sliced(png, "s.npy")
    np.testing.assert_allclose(sliced(png, "s.exr"), srgb_decoded(stored), rtol=1e-5)
    np.testing.assert_array_equal(sliced(png, "raw.exr", "--raw"), stored)
    np.testing.assert_array_equal(sliced(png, "s.png"), np.round(stored * 255))
    floats = tmp_path / "granite.npy"
    np.save(floats, np.asarray(Image.open(png), np.float32) / 255)
    assert np.array_equal(sliced(floats, "f.npy"), stored)  # the same values, synthesized alike
    np.testing.assert_array_equal(sliced(floats, "f.png"), np.round(linear_to_srgb(stored) * 255))
    np.testing.assert_array_equal(sliced(floats, "raw.png", "--raw"), np.round(stored * 255))
    np.testing.assert_array_equal(sliced(floats, "f.exr"), stored)


def test_cli_slice_bake_and_cut(tmp_path, data_dir, sphere, warp_device, capsys, srgb_decoded):
    from warptex.cli import main

    exemplar = str(data_dir / "granite_64.png")
    mesh_path = tmp_path / "sphere.ply"
    sphere.export(mesh_path)
    assert main(["slice", exemplar, "--shape", "8", "12", "-o", str(tmp_path / "s.npy")]) == 0
    assert np.load(tmp_path / "s.npy").shape == (8, 12, 3)
    assert main(["bake", str(mesh_path), "--exemplar", exemplar, "--resolution", "24",
                 "-o", str(tmp_path / "b.ply")]) == 0
    assert len(trimesh.load(tmp_path / "b.ply").vertices) == len(sphere.vertices)
    report = capsys.readouterr().out
    # glTF vertex colors are linear: the PNG's colors decoded, unless --raw.
    ply = trimesh.load(tmp_path / "b.ply", process=False).visual.vertex_colors[:, :3] / 255
    linear = srgb_decoded(ply)
    assert np.abs(linear - ply).max() > 20 / 255
    for extra, expected in (([], linear), (["--raw"], ply)):
        assert main(["bake", str(mesh_path), "--exemplar", exemplar, "--resolution", "24",
                     *extra, "-o", str(tmp_path / "b.glb")]) == 0
        # Float colors in the .glb; the .ply's are rounded to 8 bits.
        got = glb_vertex_colors(tmp_path / "b.glb")
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, expected, atol=0.51 / 255 if extra else 0.008)
    capsys.readouterr()
    shell_voxels = int(re.search(r"surface shell: (\d+) voxels", report).group(1))
    made, corrected = (int(n) for n in re.search(
        r"voxels synthesized: (\d+) .* corrected (\d+)", report).groups())
    assert shell_voxels <= made < corrected  # the shell, then what the vertices read
    # With a store file a second bake synthesizes nothing, and the store warms a texture
    # that fills whole bricks, as the renderer's does.
    store = tmp_path / "bunny.wtb"
    for expected, said in ((made, f"b.ply, {store}\n"), (0, f"{store} unchanged")):
        assert main(["bake", str(mesh_path), "--exemplar", exemplar, "--resolution", "24",
                     "--store", str(store), "-o", str(tmp_path / "b.ply")]) == 0
        report = capsys.readouterr().out
        assert f"voxels synthesized: {expected} (" in report and said in report
    warm = SolidTexture(exemplar, store=store)
    warm.query(shell(sphere, 24, block_transform(sphere, 24)) + 0.5, filter="nearest")
    assert warm.store.stats()["misses"] == 0
    assert main(["cut", str(mesh_path), "--exemplar", exemplar, "--resolution", "24",
                 "-o", str(tmp_path / "c.ply")]) == 0
    assert (tmp_path / "c.ply").exists() and (tmp_path / "c_b.ply").exists()
    # A plane beside the mesh: the mesh named, nothing written.
    capsys.readouterr()
    assert main(["cut", str(mesh_path), "--exemplar", exemplar, "--resolution", "24",
                 "--origin", "100", "0", "0", "-o", str(tmp_path / "d.ply")]) == 2
    assert f"{mesh_path}: the plane does not cut the mesh" in capsys.readouterr().err
    assert not list(tmp_path.glob("d*.ply"))
    assert main(["bake", str(tmp_path / "missing.ply"), "--exemplar", exemplar,
                 "-o", str(tmp_path / "x.ply")]) == 2


@pytest.mark.parametrize("command", ["bake", "cut"])
@pytest.mark.parametrize(("stop", "code", "cause"), [
    (KeyboardInterrupt, 130, "stopping"),
    # A kernel cache that took the synthesis kernels but not a later module's build.
    (lambda: KernelCacheError("/cache: cannot build kernels"), 1, "the kernel cache failed")])
def test_a_stopped_bake_or_cut_saves_its_store(tmp_path, data_dir, sphere, warp_device,
                                               capsys, monkeypatch, command, stop, code,
                                               cause):
    """Ctrl-C, or a failing kernel cache, while the mesh's colours are made (a cut's second
    half): the --store file keeps what was synthesized (the cache's failure lost it), no
    mesh is written, not even a cut's first half, and the next run synthesizes less."""
    import warptex.cli
    from warptex.cli import main

    mesh_path = tmp_path / "sphere.ply"
    sphere.export(mesh_path)
    store = tmp_path / "s.wtb"
    argv = [command, str(mesh_path), "--exemplar", str(data_dir / "granite_64.png"),
            "--resolution", "24", "--store", str(store), "-o", str(tmp_path / "m.ply")]
    assert main([*argv[:-4], "-o", str(tmp_path / "cold.ply")]) == 0
    cold = int(re.search(r"voxels synthesized: (\d+) \(", capsys.readouterr().out).group(1))
    baked = warptex.cli.meshes._baked
    made = []

    def stopped_on_the_last(tex, mesh, *args):
        if command == "bake" or made:
            raise stop()
        made.append(baked(tex, mesh, *args))
        return made[-1]

    before = set(tmp_path.iterdir())
    with monkeypatch.context() as patch:
        patch.setattr(warptex.cli.meshes, "_baked", stopped_on_the_last)
        assert main(argv) == code
    assert (f"brick store {store} holds the voxels synthesized before {cause}"
            in capsys.readouterr().err)
    assert set(tmp_path.iterdir()) == before | {store}
    assert main(argv) == 0
    warm = int(re.search(r"voxels synthesized: (\d+) \(", capsys.readouterr().out).group(1))
    assert warm < cold


def test_a_bake_stopped_before_any_synthesis_writes_no_empty_store(tmp_path, data_dir,
                                                                    sphere, warp_device,
                                                                    capsys, monkeypatch):
    """A Ctrl-C before the first voxel: no --store file is made (an empty one was, and the
    stop said it held the voxels synthesized before stopping); the log says why."""
    import warptex.cli
    from warptex.cli import main

    def stopped(*args):
        raise KeyboardInterrupt

    mesh_path = tmp_path / "sphere.ply"
    sphere.export(mesh_path)
    store = tmp_path / "s.wtb"
    monkeypatch.setattr(warptex.cli.meshes, "_synthesize_shell", stopped)
    assert main(["bake", str(mesh_path), "--exemplar", str(data_dir / "granite_64.png"),
                 "--resolution", "24", "--store", str(store),
                 "-o", str(tmp_path / "m.ply")]) == 130
    err = capsys.readouterr().err
    assert f"warptex: brick store {store} left as it was: no voxel was synthesized yet\n" in err
    assert "holds the voxels" not in err and sorted(tmp_path.iterdir()) == [mesh_path]


def _square(z=0.0):
    """The unit square in z = ``z`` as two triangles, its UVs its (x, y)."""
    v = np.array([[0, 0, z], [1, 0, z], [1, 1, z], [0, 1, z]], float)
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False), v[:, :2].copy()


def _texel_centres(w, h):
    x, y = np.meshgrid(np.arange(w), np.arange(h))  # row-major: texel y * w + x
    return np.stack([(x + 0.5) / w, 1 - (y + 0.5) / h], -1).reshape(-1, 2)


@pytest.mark.parametrize("size", [(8, 8), (5, 7)])
def test_texel_points_of_a_flat_square_are_its_texel_centres(size, warp_device):
    """UV = (x, y) and the identity transform: every texel is covered (its left column, its
    centres on the diagonal both triangles share, included) and shows the point (u, v, 0)."""
    mesh, uv = _square()
    # a scaled, shifted transform: points are uv * 3 + (10, -4, 2)
    m = np.diag([3.0, 3.0, 3.0, 1.0])
    m[:3, 3] = [10, -4, 2]
    points, covered = texel_points(mesh, uv, m, size)
    assert covered.all()
    expected = np.c_[_texel_centres(*size) * 3 + [10, -4], np.full(size[0] * size[1], 2.0)]
    np.testing.assert_allclose(points, expected, atol=1e-5)


@pytest.mark.parametrize("size", [(16, 16), (16, 20), (20, 16)])
def test_a_skewed_triangle_interpolates_with_the_right_corner_weights(size, warp_device):
    """Positions not an affine copy of the UVs with symmetric roles: swapping the weights
    of corners b and c moves the points. The texels covered are those whose centres lie
    in the UV triangle, also where width and height differ (no centre of those lies on its
    hypotenuse)."""
    v = np.array([[0, 0, 0], [4, 0, 1], [0, 2, 3]], float)
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    mesh = trimesh.Trimesh(v, [[0, 1, 2]], process=False)
    points, covered = texel_points(mesh, uv, np.eye(4), size)
    centres = _texel_centres(*size)
    if size[0] != size[1]:
        np.testing.assert_array_equal(covered, centres.sum(axis=1) < 1)
    c = centres[covered]
    assert 0.4 < covered.mean() < 0.6
    expected = c[:, :1] * (v[1] - v[0]) + c[:, 1:] * (v[2] - v[0])
    np.testing.assert_allclose(points[covered], expected, atol=1e-5)


@pytest.mark.parametrize("first", [0, 1, 2])
def test_texel_centres_on_a_triangle_s_edge_are_covered(first, warp_device):
    """Half the square alone, its corners in each order so that the diagonal is each of its
    edges once: the texel centres on the diagonal are its (no other triangle claims them)."""
    mesh, uv = _square()
    half = trimesh.Trimesh(mesh.vertices, [np.roll([0, 2, 3], -first)], process=False)
    points, covered = texel_points(half, uv, np.eye(4), (8, 8))
    centres = _texel_centres(8, 8)
    np.testing.assert_array_equal(covered, centres[:, 0] <= centres[:, 1])
    np.testing.assert_allclose(points[covered], np.c_[centres[covered], np.zeros(covered.sum())],
                               atol=1e-6)


@pytest.mark.parametrize("reach", [10.0, 1e6, 1e10])
def test_a_triangle_whose_uvs_reach_far_claims_the_texels_it_covers(reach, warp_device):
    """UVs beyond int32 once scaled by the texture's width (an exporter's garbage vertex):
    the float-to-int conversion of its bounds is undefined, and such a triangle, covering
    the whole texture, claimed no texel."""
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], process=False)
    uv = np.float32([[-reach, -reach], [reach, -reach], [0, reach]])
    assert texel_points(flat, uv, np.eye(4), (8, 8))[1].all()


def test_overlapping_triangles_resolve_to_the_lowest_numbered(warp_device):
    """Two charts on the same UVs: the texels show triangle 0's surface everywhere."""
    low, uv = _square(0.0)
    high, _ = _square(5.0)
    mesh = trimesh.Trimesh(np.r_[low.vertices, high.vertices],
                           [[4, 5, 6], [0, 1, 2], [4, 6, 7], [0, 2, 3]], process=False)
    points, covered = texel_points(mesh, np.r_[uv, uv], np.eye(4), (8, 8))
    # texels under the lower-right triangle (faces 0 and 1 overlap): face 0, z = 5;
    # under the upper-left one (faces 2 and 3): face 2, z = 5
    assert covered.all() and np.all(points[:, 2] == 5.0)


class _Constant:
    """A texture of one colour everywhere."""

    def query(self, points, filter="trilinear"):
        return np.tile(np.float32([0.25, 0.5, 0.75]), (len(points), 1))


def test_uncovered_texels_take_a_covered_color(warp_device):
    """A triangle covering half the texture: the other half is filled, not left black,
    so filtering does not bleed black into the seams."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    mesh = trimesh.Trimesh(v, [[0, 1, 2]], process=False)
    image, mask = bake_uv_texture(_Constant(), mesh, v[:, :2], np.eye(4), size=16)
    assert 0.3 < mask.mean() < 0.7
    np.testing.assert_array_equal(image, np.broadcast_to([0.25, 0.5, 0.75], image.shape))


def test_uv_layouts_that_bake_wrong_colors_are_told(texture, sphere):
    """A mesh's own UVs: xatlas' layout bakes each point its own texel; two triangles over
    one UV triangle (mirrored UVs) share it, and UVs past [0, 1] (tiled) leave parts
    unbaked."""
    from warptex.bake import uv_layout_problems

    unwrapped = sphere.unwrap()
    m = block_transform(unwrapped, 24)
    _, covered = bake_uv_texture(texture, unwrapped, unwrapped.visual.uv, m, size=128)
    assert uv_layout_problems(unwrapped.visual.uv, unwrapped.faces, covered) == []
    rounded = unwrapped.visual.uv.copy()  # an exporter's float32 rounding at the edges
    rounded[rounded.argmin(axis=0), [0, 1]] = -1e-7
    rounded[rounded.argmax(axis=0), [0, 1]] = 1.0000001
    assert uv_layout_problems(rounded, unwrapped.faces, covered) == []
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3]])
    mirrored = np.array([[0.1, 0.1], [0.9, 0.1], [0.1, 0.9], [0.1, 0.9]])
    mesh = trimesh.Trimesh(v, faces, process=False)
    _, covered = bake_uv_texture(_Constant(), mesh, mirrored, np.eye(4), size=64)
    # The third triangle's UVs run along a line: collapsed, they show no texel.
    collapsed, overlap = uv_layout_problems(mirrored, faces, covered)
    assert collapsed.startswith("the UVs of 1 of 3 triangles have no area (collapsed")
    share, said = overlap.split("% ", 1)  # two of the three triangles alike: about half
    assert 45 <= int(share) <= 55 and said.startswith("of the UV area lies over other")
    tiled = mirrored * np.array([3.0, 1.0])
    _, covered = bake_uv_texture(_Constant(), mesh, tiled, np.eye(4), size=64)
    collapsed, outside = uv_layout_problems(tiled, faces, covered)  # and no overlap
    assert outside == (
        "the UVs of 2 of 3 triangles reach outside [0, 1] (tiled UVs), where no texel holds "
        "their colors")
    # Unmapped faces exported at one UV: all collapsed, but not a degenerate face, which
    # has no surface to show.
    flat = np.zeros((4, 2))
    _, covered = bake_uv_texture(_Constant(), mesh, flat, np.eye(4), size=64)
    assert uv_layout_problems(flat, faces, covered, mesh.area_faces)[0].startswith(
        "the UVs of 3 of 3 triangles have no area")
    assert uv_layout_problems(flat, faces, covered, np.array([1.0, 1e-17, 1.0]))[0].startswith(
        "the UVs of 2 of 3 triangles have no area")  # a collinear face's rounding is none
    # Seven triangles of their own, two over one UV triangle: a seventh of the UV area
    # overlaps, told as such (not as the six sevenths shown), above the 5% let pass.
    corners = np.array([[0.0, 0.0], [0.2, 0.0], [0.0, 0.2]])
    offsets = [(0.05 + 0.3 * (i % 3), 0.05 + 0.3 * (i // 3)) for i in range(6)]
    uv7 = np.concatenate([corners + offset for offset in [*offsets, offsets[0]]])
    faces7 = np.arange(21).reshape(7, 3)
    seven = trimesh.Trimesh(np.concatenate([v[:3] + k for k in range(7)]), faces7,
                            process=False)
    _, covered = bake_uv_texture(_Constant(), seven, uv7, np.eye(4), size=128)
    (overlap,) = uv_layout_problems(uv7, faces7, covered)
    assert 11 <= int(overlap.split("% ", 1)[0]) <= 17


def test_uvs_a_little_past_one_are_told_as_tiled():
    """UVs up to 1.5, exactly 2 or down to -0.5 leave surface uncoloured as surely as 2.7
    does; only those at 2.7 and 1.0000001 (rounding, not tiling) were tried."""
    from warptex.bake import uv_layout_problems

    faces = np.array([[0, 1, 2]])
    # A thousandth past is a texel of a 1024 texture: told too, where 1.0000001 is not.
    for low, top in ((0.0, 1.5), (0.0, 2.0), (-0.5, 1.0), (0.0, 1.001), (-0.001, 1.0)):
        uv = np.array([[low, 0.0], [top, 0.0], [0.0, 1.0]])
        problems = uv_layout_problems(uv, faces, np.ones(64 * 64, bool))
        assert any("reach outside [0, 1]" in p for p in problems), (low, top, problems)
    # A sliver of UV area 1e-14 shows no texel of any texture: collapsed, as zero is.
    sliver = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 2e-14]])
    assert uv_layout_problems(sliver, faces, np.ones(64 * 64, bool))[0].startswith(
        "the UVs of 1 of 1 triangles have no area")


class _FilterRecorder(_Constant):
    """A texture of one colour that notes the filter of each query."""

    def __init__(self):
        self.filters = []

    def query(self, points, filter="trilinear"):
        self.filters.append(filter)
        return super().query(points, filter)


def test_a_uv_texture_is_baked_with_the_filter_asked_for(warp_device):
    """bake_uv_texture(filter="nearest") from the Python API gave trilinear colours had
    the argument not reached the queries (the command never passes it)."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    mesh = trimesh.Trimesh(v, np.array([[0, 1, 2]]), process=False)
    recorder = _FilterRecorder()
    bake_uv_texture(recorder, mesh, v[:, :2], np.eye(4), size=8, filter="nearest")
    assert recorder.filters and set(recorder.filters) == {"nearest"}


def test_vertex_colors_use_the_filter_asked_for(texture):
    sphere = trimesh.creation.icosphere(subdivisions=2)
    m = block_transform(sphere, 24)
    points = to_voxel_space(sphere, m)
    nearest = vertex_colors(texture, sphere, m, filter="nearest")
    np.testing.assert_array_equal(nearest, texture.query(points, filter="nearest"))
    assert not np.array_equal(nearest, vertex_colors(texture, sphere, m))


def test_exported_vertex_colors_are_rounded_clipped_and_opaque(tmp_path):
    mesh, _ = _square()
    colors = np.array([[0.5, 0.0, 1.0], [1.5, -0.2, 0.2], [0.999, 0.001, 0.502],
                       [0.25, 0.75, 0.1]], np.float32)
    written = export(mesh, tmp_path / "q.ply", colors=colors)
    got = trimesh.load(written[0], process=False).visual.vertex_colors
    np.testing.assert_array_equal(got[:, :3], [[128, 0, 255], [255, 0, 51], [255, 0, 128],
                                               [64, 191, 26]])
    assert np.all(got[:, 3] == 255)


def test_exported_colors_are_in_the_encoding_each_format_assumes(tmp_path, srgb_decoded):
    """PLY vertex colors and PNG textures sRGB, glTF vertex colors linear (glTF 2.0): an
    sRGB exemplar's colors are decoded for .glb only, a linear exemplar's encoded for the
    others; srgb=None writes them as they are."""
    from PIL import Image

    from warptex.srgb import linear_to_srgb, srgb_to_linear

    mesh, uv = _square()
    colors = np.array([[0.5, 0.0, 1.0], [0.2, 0.75, 0.04], [0.9, 0.3, 0.6],
                       [0.25, 0.1, 0.4]], np.float32)

    def vertex_rgb(name: str, srgb: bool | None) -> np.ndarray:
        written = export(mesh, tmp_path / name, colors=colors, srgb=srgb)[0]
        if written.suffix == ".glb":
            return glb_vertex_colors(written)
        return trimesh.load(written, process=False).visual.vertex_colors[:, :3]

    def rgb8(values: np.ndarray) -> np.ndarray:
        return np.floor(np.asarray(values) * 255 + 0.5)

    for srgb in (True, None):
        np.testing.assert_array_equal(vertex_rgb("s.ply", srgb), rgb8(colors))
    # glTF's COLOR_0 is float: 8 linear bits would band the darks.
    np.testing.assert_array_equal(vertex_rgb("s.glb", True), srgb_to_linear(colors))
    np.testing.assert_allclose(vertex_rgb("s.glb", True), srgb_decoded(colors), atol=1e-7)
    np.testing.assert_array_equal(vertex_rgb("s.glb", None), colors)
    np.testing.assert_array_equal(vertex_rgb("l.ply", False), rgb8(linear_to_srgb(colors)))
    np.testing.assert_array_equal(vertex_rgb("l.glb", False), colors)
    # Dark sRGB steps stay apart, where 8 linear bits would keep 2 of these 4.
    dark = np.array([0.0, 0.01, 0.02, 0.03], np.float32)[:, None].repeat(3, axis=1)
    export(mesh, tmp_path / "d.glb", colors=dark, srgb=True)
    assert len(np.unique(glb_vertex_colors(tmp_path / "d.glb")[:, 0])) == 4
    image = np.tile(colors[:2, None, :], (1, 16, 1)).reshape(2, 16, 3).repeat(8, axis=0)
    for srgb, expected in ((True, image), (False, linear_to_srgb(image))):
        files = export(mesh, tmp_path / f"t{srgb}.obj", image=image, uv=uv, srgb=srgb)
        png = next(f for f in files if f.suffix == ".png")
        np.testing.assert_array_equal(np.asarray(Image.open(png))[..., :3], rgb8(expected))
        # A .glb's texture is a PNG too, sRGB as glTF's baseColorTexture is.
        (glb,) = export(mesh, tmp_path / f"t{srgb}.glb", image=image, uv=uv, srgb=srgb)
        embedded = trimesh.load(glb, force="mesh").visual.material.baseColorTexture
        np.testing.assert_array_equal(np.asarray(embedded)[..., :3], rgb8(expected))
    # The linear colors go in as COLOR_0 alone, not also under the name trimesh was given.
    (primitive,) = _gltf_json(tmp_path / "s.glb")["meshes"][0]["primitives"]
    assert "COLOR_0" in primitive["attributes"]
    assert not any("linear" in name for name in primitive["attributes"])


def test_cli_slice_shows_the_z_exemplar_as_its_photo_is_oriented(tmp_path, data_dir,
                                                                 warp_device):
    """The default slice is the plane z = 0.5 with rows along x and columns along y: the
    z exemplar's own rows and columns (each exemplar spans the next two axes, cyclically),
    so patches of the photo appear upright in it. The z-slices of `warptex volume -o
    out.exr` (x across, as image tools show volumes) are its transpose."""
    from warptex.candidates import precompute
    from warptex.cli import main
    from warptex.synthesis import Synthesizer
    from warptex.volume_files import exr_sheet

    exemplar = data_dir / "granite_64.png"
    assert main(["slice", str(exemplar), "--shape", "8", "12", "--filter", "nearest",
                 "-o", str(tmp_path / "s.npy")]) == 0
    assert main(["volume", str(exemplar), "--size", "12", "-o", str(tmp_path / "v.npy")]) == 0
    volume = np.load(tmp_path / "v.npy")
    np.testing.assert_array_equal(np.load(tmp_path / "s.npy"), volume[:8, :12, 0])
    np.testing.assert_array_equal(exr_sheet(volume)[:12, :8], volume[:8, :12, 0].swapaxes(0, 1))
    # Along a row of the slice (y), continued patches step the z exemplar's column.
    grid = np.stack(np.meshgrid(np.arange(32), np.arange(32), [0], indexing="ij"), -1)
    pixel = Synthesizer(precompute(exemplar)).triples(grid.reshape(-1, 3))[:, 2].reshape(
        32, 32, 2)
    step = pixel[:, 1:] - pixel[:, :-1]
    along_columns = np.all(step == (0, 1), axis=-1).sum()
    along_rows = np.all(step == (1, 0), axis=-1).sum()
    assert along_columns > 4 * along_rows


@pytest.mark.parametrize(("exemplar", "dropped"), [("rgba.png", "1 channel of 4"),
                                                  ("yca.exr", "2 channels of 3")])
def test_bake_writes_colors_only_and_says_what_it_drops(tmp_path, data_dir, sphere,
                                                        warp_device, capsys, exemplar,
                                                        dropped):
    """Mesh files hold RGB: an alpha kept with --alpha keep is synthesized (it takes part in
    the matching) but not written, which the command says before its work. Of gray, a data
    channel and a kept alpha (an EXR's Y, C1, A) the mesh gets the gray (the three were
    written as RGB, without a word)."""
    import trimesh
    from PIL import Image

    from warptex.cli import main
    from warptex.volume_files import write_image

    granite = np.asarray(Image.open(data_dir / "granite_64.png"))[:32, :32, :3]
    if exemplar == "rgba.png":
        alpha = np.arange(32 * 32, dtype=np.uint8).reshape(32, 32)
        Image.fromarray(np.dstack([granite, alpha])).save(tmp_path / exemplar)
    else:
        write_image(tmp_path / exemplar, granite.astype(np.float32) / 255, srgb=False,
                    alpha=True)
    mesh_path = tmp_path / "sphere.ply"
    sphere.export(mesh_path)
    assert main(["bake", str(mesh_path), "--exemplar", str(tmp_path / exemplar),
                 "--alpha", "keep", "--resolution", "16", "-o", str(tmp_path / "b.ply")]) == 0
    assert (f"warptex: warning: mesh files hold RGB colors: {dropped} (an alpha kept by "
            "--alpha keep) synthesized but not written") in capsys.readouterr().err
    colors = trimesh.load(tmp_path / "b.ply", process=False).visual.vertex_colors
    assert np.ptp(colors[:, 0]) > 0
    gray = (colors[:, 0] == colors[:, 1]).all() and (colors[:, 1] == colors[:, 2]).all()
    assert gray == (exemplar == "yca.exr")


def test_bake_names_finding_the_shell_before_that_long_call(tmp_path, granite_32_file,
                                                            sphere, warp_device, capsys,
                                                            monkeypatch):
    """Finding a shell takes seconds at the default 1024^3 and moves no bar: the surface
    shell's bar is shown, naming that step, before it starts."""
    import warptex.surface
    from warptex.cli import main

    shown = []
    found = warptex.surface.shell

    def shell_seen(*args, **kwargs):
        shown.append(capsys.readouterr().err)
        return found(*args, **kwargs)

    monkeypatch.setattr(warptex.surface, "shell", shell_seen)
    mesh_path = tmp_path / "sphere.ply"
    sphere.export(mesh_path)
    assert main(["bake", str(mesh_path), "--exemplar", str(granite_32_file),
                 "--resolution", "16", "-o", str(tmp_path / "b.ply")]) == 0
    assert len(shown) == 1
    assert "surface shell" in shown[0] and "finding the voxels" in shown[0]


def test_the_shell_bar_ticks_while_its_voxels_are_synthesized(tmp_path, granite_32_file,
                                                              sphere, warp_device,
                                                              monkeypatch):
    """A shell of up to 2^20 voxels (512^3 blocks) is one engine request of minutes: its
    bar stood at 0 % with a stopped clock, and a log got no line meanwhile."""
    import threading

    from warptex.cli import main
    from warptex.texture import SolidTexture

    ticking = []
    query = SolidTexture.query

    def seen(self, points, filter="trilinear"):
        ticking.append(any(t.name == "warptex-bar" for t in threading.enumerate()))
        return query(self, points, filter=filter)

    monkeypatch.setattr(SolidTexture, "query", seen)
    mesh_path = tmp_path / "sphere.ply"
    sphere.export(mesh_path)
    assert main(["bake", str(mesh_path), "--exemplar", str(granite_32_file),
                 "--resolution", "16", "-o", str(tmp_path / "b.ply")]) == 0
    assert ticking[0]  # the shell's one request


def test_the_uv_bar_ticks_while_the_mesh_is_unwrapped(texture, sphere, capsys, monkeypatch):
    """xatlas takes 21 s for the bunny in a child process; its bar's clock is redrawn
    meanwhile rather than standing at the step's start."""
    import argparse

    import warptex.parallel
    from warptex.cli.meshes import _baked

    monkeypatch.setattr(warptex.parallel, "WAIT_SECONDS", 0.02)
    args = argparse.Namespace(uv="auto", texture_size=8, mesh=Path("sphere.ply"))
    capsys.readouterr()
    _baked(texture, sphere, block_transform(sphere, 16), args, "b.glb")
    err = capsys.readouterr().err
    # A child's start-up alone takes over half a second: many redraws at 0.02 s.
    assert err.count("unwrapping (xatlas)") > 5


def test_bake_keeps_vertices_of_their_own_normals_and_cut_welds_them(tmp_path, data_dir,
                                                                    warp_device, capsys):
    """A flat-shaded mesh, each face with its own vertices and normals: bake keeps a vertex
    per normal, as trimesh loads it (processing without the normals welded it); cut welds
    them to a closed surface, caps and all. A NaN vertex of a face is refused, not left out
    with its faces; an unused vertex far away is dropped, not synthesized (its point lay
    beyond the texture's range)."""
    from warptex.cli import main

    box = trimesh.creation.box()
    flat = trimesh.Trimesh(box.vertices[box.faces].reshape(-1, 3),
                           np.arange(3 * len(box.faces)).reshape(-1, 3), process=False)
    mesh_path = tmp_path / "flat.ply"
    flat.export(mesh_path, vertex_normal=True)
    exemplar = str(data_dir / "granite_64.png")
    assert main(["bake", str(mesh_path), "--exemplar", exemplar, "--resolution", "16",
                 "-o", str(tmp_path / "b.ply")]) == 0
    baked = trimesh.load(tmp_path / "b.ply", process=False)
    assert len(baked.vertices) == 24  # each corner once per side: not welded to 8
    assert main(["cut", str(mesh_path), "--exemplar", exemplar, "--resolution", "16",
                 "--normal", "1", "0", "0", "-o", str(tmp_path / "c.ply")]) == 0
    for half in ("c.ply", "c_b.ply"):
        assert trimesh.load(tmp_path / half).is_watertight
    from warptex.mesh_files import load_mesh

    assert len(load_mesh(mesh_path, weld=True).vertices) == 8  # whatever the normals say
    broken = flat.copy()
    broken.vertices[5] = np.nan
    broken.export(tmp_path / "nan.ply")
    capsys.readouterr()
    assert main(["bake", str(tmp_path / "nan.ply"), "--exemplar", exemplar, "--resolution",
                 "16", "-o", str(tmp_path / "n.ply")]) == 2
    assert "nan.ply: vertex coordinates hold NaN or infinite values" in capsys.readouterr().err
    assert not (tmp_path / "n.ply").exists()
    stray = trimesh.Trimesh(np.vstack([box.vertices, [[1e7, 0.0, 0.0], [np.nan] * 3]]),
                            box.faces, process=False)
    stray.export(tmp_path / "stray.ply")
    assert main(["bake", str(tmp_path / "stray.ply"), "--exemplar", exemplar, "--resolution",
                 "16", "-o", str(tmp_path / "s.ply")]) == 0
    assert len(trimesh.load(tmp_path / "s.ply", process=False).vertices) == len(box.vertices)


def test_unused_vertices_decide_neither_refusal_nor_welding(tmp_path):
    """Only the faces' vertices are checked and measured: an unused vertex at 1e14 set the
    weld tolerance to 0.1 units (a unit sphere of 642 vertices kept 26), an unused NaN one
    let a sphere of radius 1e-8 weld at trimesh's 1e-8 (26 kept), one at 1e30 refused the
    mesh. A negative face index, which NumPy wraps to the last vertex, is refused."""
    from warptex.mesh_files import MeshFileError, load_mesh

    for name, radius, stray in (("far", 1.0, 1e14), ("farther", 1.0, 1e30),
                                ("nan", 1e-8, np.nan)):
        sphere = trimesh.creation.icosphere(subdivisions=3)
        sphere.apply_scale(radius)
        trimesh.Trimesh(np.vstack([sphere.vertices, [[stray, 0.0, 0.0]]]), sphere.faces,
                        process=False).export(tmp_path / f"{name}.ply")
        assert len(load_mesh(tmp_path / f"{name}.ply").vertices) == 642, name
    (tmp_path / "negative.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 -1\n")
    with pytest.raises(MeshFileError, match=r"negative\.ply: a face refers to vertex -1"):
        load_mesh(tmp_path / "negative.ply")
    # A .glb keeps an unused vertex (trimesh does not drop it there): its NaN UV is no
    # face's, so the mesh's own UVs are usable.
    from trimesh.visual import TextureVisuals

    box = trimesh.creation.box()
    uv = np.vstack([np.random.default_rng(1).random((8, 2)), [[np.nan, np.nan]]])
    trimesh.Trimesh(np.vstack([box.vertices, [[5.0, 5.0, 5.0]]]), box.faces,
                    visual=TextureVisuals(uv=uv), process=False).export(tmp_path / "u.glb")
    assert np.isfinite(load_mesh(tmp_path / "u.glb", uv="mesh").visual.uv[box.faces]).all()


def test_a_reader_s_missing_library_is_said_so_not_called_damage(tmp_path, monkeypatch):
    """trimesh reads .dae through pycollada and .3mf through lxml: a sound file was called
    "damaged, or not what its name says" where the library was not installed."""
    from warptex.mesh_files import MeshFileError, load_mesh

    (tmp_path / "part.3mf").write_bytes(b"a sound file, as far as this test goes")

    def without_lxml(*args, **kwargs):
        raise ModuleNotFoundError("No module named 'lxml'")

    monkeypatch.setattr(trimesh, "load", without_lxml)
    with pytest.raises(MeshFileError, match=r"part\.3mf: reading this format needs a library "
                                            r"that is not installed \(No module named 'lxml'\)"):
        load_mesh(tmp_path / "part.3mf")


def test_a_mesh_far_smaller_than_a_unit_bakes_and_cuts_as_at_unit_size(tmp_path, data_dir,
                                                                        warp_device):
    """Coincident vertices were welded to 8 decimals whatever the mesh's size: a sphere
    2e-8 units across kept 26 of its 642 vertices. The block scales any
    mesh to its voxels, so the tiny one now gets the same colors, and its cut halves are
    as closed."""
    from warptex.cli import main
    from warptex.mesh_files import weld_tolerance

    exemplar = str(data_dir / "granite_64.png")
    baked, halves = {}, {}
    for scale in (1.0, 1e-8):  # a radius
        sphere = trimesh.creation.icosphere(subdivisions=3)
        sphere.apply_scale(scale)
        sphere.export(tmp_path / f"s{scale}.ply")
        for command in ("bake", "cut"):
            assert main([command, str(tmp_path / f"s{scale}.ply"), "--exemplar", exemplar,
                         "--resolution", "16", "--uv", "none", "-o",
                         str(tmp_path / f"{command}{scale}.ply")]) == 0
        baked[scale] = trimesh.load(tmp_path / f"bake{scale}.ply", process=False)
        halves[scale] = []
        for name in (f"cut{scale}.ply", f"cut{scale}_b.ply"):
            half = trimesh.load(tmp_path / name, process=False)
            digits = trimesh.util.decimal_to_digits(weld_tolerance(half.vertices))
            half.merge_vertices(digits_vertex=digits)
            halves[scale].append((len(half.vertices), half.is_watertight))
    assert len(baked[1e-8].vertices) == 642
    np.testing.assert_array_equal(baked[1e-8].visual.vertex_colors, baked[1.0].visual.vertex_colors)
    assert halves[1e-8] == halves[1.0] and all(closed for _, closed in halves[1.0])


def test_a_mesh_of_huge_coordinates_keeps_its_vertices(tmp_path, data_dir, warp_device):
    """Welding rounds coordinates to integers of the tolerance: from 1e11 units on they
    overflowed int64, and a sphere of radius 1e12 kept 31 of its 642 vertices."""
    from warptex.cli import main
    from warptex.mesh_files import weld_tolerance

    sphere = trimesh.creation.icosphere(subdivisions=3)
    sphere.apply_scale(1e12)
    sphere.export(tmp_path / "huge.ply")
    arguments = ["--exemplar", str(data_dir / "granite_64.png"), "--resolution", "16",
                 "--uv", "none"]
    assert main(["bake", str(tmp_path / "huge.ply"), *arguments, "-o",
                 str(tmp_path / "bake.ply")]) == 0
    assert len(trimesh.load(tmp_path / "bake.ply", process=False).vertices) == 642
    assert main(["cut", str(tmp_path / "huge.ply"), *arguments, "-o",
                 str(tmp_path / "cut.ply")]) == 0
    for name in ("cut.ply", "cut_b.ply"):
        half = trimesh.load(tmp_path / name, process=False)
        half.merge_vertices(digits_vertex=trimesh.util.decimal_to_digits(
            weld_tolerance(half.vertices)))
        assert half.is_watertight
    # Beyond 1e15 float64 vertices are an eighth of a unit apart: refused, not welded wrong.
    sphere.apply_scale(1e4)
    sphere.export(tmp_path / "beyond.ply")
    assert main(["bake", str(tmp_path / "beyond.ply"), *arguments, "-o",
                 str(tmp_path / "beyond_baked.ply")]) == 2


def test_a_ply_or_glb_that_float32_would_flatten_is_refused_before_the_work(
        tmp_path, data_dir, warp_device, capsys):
    """A 10 cm sphere at map coordinates (5e5, 4.4e6): .ply and .glb hold vertices as
    float32, a unit apart there, and the sphere came out flat; .obj keeps it."""
    from warptex.cli import main

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    sphere.apply_translation([5e5, 4.4e6, 100.0])
    (tmp_path / "far.obj").write_text(trimesh.exchange.obj.export_obj(sphere, digits=10))
    arguments = [str(tmp_path / "far.obj"), "--exemplar", str(data_dir / "granite_64.png"),
                 "--resolution", "16"]
    for command, output in (("bake", "far.ply"), ("bake", "far.glb"), ("cut", "cut.ply")):
        assert main([command, *arguments, "--uv", "none", "-o", str(tmp_path / output)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(
            f"warptex: error: {tmp_path / output}: .ply and .glb files hold vertices as float32")
        # The way out it names is one the command takes: .obj alone was refused as a file of
        # no vertex colors.
        assert err.endswith(": write .obj with a UV texture (--uv auto: .obj holds no vertex "
                            "colors), or move the mesh nearer the origin\n")
    # A part of a few units a few thousand units out (millimetres, an assembly) moves by a
    # fraction of a micrometre: written.
    part = trimesh.creation.icosphere(subdivisions=2)
    part.apply_translation([5000.0, 0.0, 0.0])
    (tmp_path / "part.obj").write_text(trimesh.exchange.obj.export_obj(part, digits=10))
    assert main(["bake", str(tmp_path / "part.obj"), *arguments[1:], "--uv", "none", "-o",
                 str(tmp_path / "part.ply")]) == 0
    assert main(["bake", *arguments, "--uv", "auto", "-o", str(tmp_path / "far_baked.obj")]) == 0
    kept = trimesh.load(tmp_path / "far_baked.obj", force="mesh")
    np.testing.assert_allclose(kept.extents, sphere.extents, rtol=1e-6)


def test_bake_refuses_nan_uvs_of_the_mesh(tmp_path, data_dir, warp_device, capsys):
    """A triangle with a NaN UV claimed no texel: its surface showed its neighbours'
    colours, with a NumPy warning about a cast, and the file got the NaN UVs."""
    from warptex.cli import main

    mesh_path = tmp_path / "nan_uv.obj"
    mesh_path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvt 0 0\nvt 1 0\nvt nan 1\n"
                         "f 1/1 2/2 3/3\nf 1/1 2/2 4/3\n")
    assert main(["bake", str(mesh_path), "--exemplar", str(data_dir / "granite_64.png"),
                 "--resolution", "16", "--uv", "mesh", "--texture-size", "32",
                 "-o", str(tmp_path / "b.glb")]) == 2
    assert "nan_uv.obj: UV coordinates hold NaN or infinite values" in capsys.readouterr().err
    assert not (tmp_path / "b.glb").exists()


def test_bake_with_the_mesh_s_own_uvs_warns_of_a_mirrored_layout(tmp_path, data_dir, sphere,
                                                                warp_device, capsys):
    from warptex.cli import main

    mesh = sphere.copy()
    uv = mesh.vertices[:, :2] * 0.45 + 0.5  # front and back share one disc
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv)
    mesh.export(tmp_path / "mirrored.obj")
    assert main(["bake", str(tmp_path / "mirrored.obj"), "--exemplar",
                 str(data_dir / "granite_64.png"), "--resolution", "16", "--uv", "mesh",
                 "--texture-size", "64", "-o", str(tmp_path / "m.glb")]) == 0
    err = capsys.readouterr().err
    assert "mirrored.obj: " in err and "of the UV area lies over other triangles'" in err
    assert "--uv auto makes UVs of its own" in err


def _cap_triangles(half: trimesh.Trimesh, normal: np.ndarray) -> set:
    """A half's cap triangles (faces parallel to the cut plane) as sets of their corners'
    coordinate bytes: the same set on both halves when their caps are the same triangles."""
    corners = half.vertices[half.faces]
    # Not trimesh's face_normals, zero for the triangles of a mesh of micrometres.
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    flat = np.abs(normals @ normal) > (1 - 1e-9) * np.linalg.norm(normals, axis=1)
    return {frozenset(map(bytes, triangle)) for triangle in corners[flat]}


@pytest.mark.parametrize(("mesh", "origin", "normal"), [
    (trimesh.creation.icosphere(2), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0)),
    (trimesh.creation.capsule(), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0)),
    # 1e-8 from the equator's vertices, which trimesh's slicing takes to lie in the plane.
    (trimesh.creation.icosphere(2), (0.0, 0.0, 1e-8), (0.0, 0.0, 1.0)),
    (trimesh.creation.icosphere(3).apply_scale(1e-6), (2e-8, -1e-8, 3e-8), (0.3, -1.0, 0.6)),
    # 5 cm at map coordinates: sliced near the origin, or rounding beats the tolerances.
    (trimesh.creation.icosphere(3).apply_scale(0.05).apply_translation([5e5, 4.4e6, 100.0]),
     (5e5 + 0.01, 4.4e6, 100.0), (1.0, 0.2, 0.3)),
])
def test_both_halves_of_a_cut_close_with_the_same_cap(mesh, origin, normal):
    """Vertex colours interpolate over the cap's triangles, so where the halves' caps are
    triangulated apart, the same cap point shows two colours (27/255 apart on the sphere).
    The second half's frame was mirrored, its section's points an ulp off the first's, and
    a plane that nearly grazed vertices, or a mesh of micrometres against trimesh's absolute
    tolerance, left halves open."""
    normal = np.asarray(normal) / np.linalg.norm(normal)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every cap refined
        first, second = cut(mesh, np.asarray(origin), normal)
    caps = _cap_triangles(first, normal)
    assert len(caps) > 20 and caps == _cap_triangles(second, normal)
    assert first.is_watertight and second.is_watertight
    np.testing.assert_allclose(first.volume + second.volume, mesh.volume, rtol=1e-9)



@pytest.mark.parametrize(("radius", "offset"), [(0.7, (0.3, -0.2, 0.11)),
                                                 (3e-3, (1e3 + 0.1, 0.0, 0.0))])
def test_the_halves_keep_the_mesh_s_own_vertices_bit_for_bit(radius, offset):
    """A cut works at unit size near the origin and brings the halves back exactly (a
    power-of-two scale, a centre whose differences are exact): every vertex of a half off
    the cut plane is one of the mesh's, to the bit, near the origin or far from it for its
    size."""
    mesh = trimesh.creation.icosphere(2, radius=radius).apply_translation(offset)
    original = {v.tobytes() for v in mesh.vertices}
    origin = mesh.vertices.mean(axis=0) + 0.01 * mesh.scale
    normal = np.array([1.0, 0.3, 0.2])
    for half in cut(mesh, origin, normal):
        off = np.abs((half.vertices - origin) @ (normal / np.linalg.norm(normal)))
        kept = half.vertices[off > 1e-6 * mesh.scale]
        assert len(kept) > 20 and all(v.tobytes() in original for v in kept)


@pytest.mark.parametrize("size", [1e8, 1e-9])
def test_cap_faces_are_found_on_halves_of_any_size(size):
    """cap_faces measures its tolerance in the half's own size, as the cut does."""
    box = trimesh.creation.box(extents=(size,) * 3).apply_translation((0.3 * size, 0.1 * size,
                                                                        0.0))
    origin, normal = np.array([0.31 * size, 0.1 * size, 0.0]), np.array([1.0, 0.37, 0.11])
    for half in cut(box, origin, normal):
        assert cap_faces(half, origin, normal).sum() >= 4


def _flat_grid(size: float) -> trimesh.Trimesh:
    """A square of 8 x 8 quads in the plane z = 0, ``size`` across: a decal, a terrain tile."""
    u, v = np.meshgrid(np.arange(9.0), np.arange(9.0), indexing="ij")
    vertices = np.c_[u.ravel(), v.ravel(), np.zeros(81)] * size / 8
    corner = (np.arange(8)[:, None] * 9 + np.arange(8)[None, :]).ravel()
    faces = np.r_[np.c_[corner, corner + 9, corner + 1], np.c_[corner + 1, corner + 9,
                                                                corner + 10]]
    return trimesh.Trimesh(vertices, faces, process=False)


@pytest.mark.parametrize("size", [1.0, 1e-9])
def test_flat_meshes_unwrap_weld_and_export_at_their_own_size(size, tmp_path):
    """A flat mesh's size is its longest side, not its thickness of none: it unwraps to
    finite UVs of some area, welds only coincident vertices and keeps its shape in .obj."""
    from warptex.bake import unwrapped
    from warptex.mesh_files import _obj_digits, weld_tolerance

    grid = _flat_grid(size)
    uv = np.asarray(unwrapped(grid).visual.uv)
    assert np.isfinite(uv).all() and np.ptp(uv, axis=0).min() > 0.1
    assert weld_tolerance(grid.vertices) <= 1e-6 * size
    assert _obj_digits(grid.vertices) >= 8 - np.floor(np.log10(size))
    export(grid, tmp_path / "grid.obj", image=np.full((8, 8, 3), 0.5, np.float32),
           uv=grid.vertices[:, :2] / size)
    kept = trimesh.load(tmp_path / "grid.obj", force="mesh", process=False)
    np.testing.assert_allclose(kept.extents[:2], [size, size], rtol=1e-7)


def test_output_suffixes_in_capitals_are_the_same_formats(tmp_path):
    """-o X.OBJ writes its .mtl and .png too; -o X.PLY holds float32 vertices too; and a
    format without vertex colors is refused them whatever its case."""
    from warptex.mesh_files import MeshFileError, load_mesh

    assert exported_files(tmp_path / "a.OBJ", uv_texture=True) == [
        tmp_path / "a.OBJ", tmp_path / "a.mtl", tmp_path / "a.png"]
    far = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    far.apply_translation([5e5, 4.4e6, 100.0])
    (tmp_path / "far.obj").write_text(trimesh.exchange.obj.export_obj(far, digits=10))
    with pytest.raises(MeshFileError, match="hold vertices as float32"):
        load_mesh(tmp_path / "far.obj", outputs=[tmp_path / "out.PLY"])
    mesh, _ = _square()
    for name in ("x.obj", "x.OBJ"):
        with pytest.raises(ValueError, match=r"vertex colors need a \.ply or \.glb file"):
            export(mesh, tmp_path / name, colors=np.full((4, 3), 0.5, np.float32))


def test_uvs_a_face_reads_must_be_finite(warp_device):
    """An infinite UV would make its triangle claim no texel, without a word; NaN too."""
    mesh, uv = _square()
    for bad in (np.inf, -np.inf, np.nan):
        broken = uv.copy()
        broken[2, 0] = bad
        with pytest.raises(ValueError, match="uv holds NaN or infinite coordinates"):
            texel_points(mesh, broken, np.eye(4), (8, 8))


def test_a_file_of_points_only_is_said_to_hold_no_triangles(tmp_path):
    from warptex.mesh_files import MeshFileError, load_mesh

    trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(tmp_path / "p.ply")
    with pytest.raises(MeshFileError, match=r"p\.ply: no triangles found"):
        load_mesh(tmp_path / "p.ply")


def test_input_files_named_with_spaces_or_escapes_are_found(tmp_path):
    """An OBJ's one library named with a space (as trimesh reads it) and a .gltf's
    percent-escaped buffer are files an output must not replace."""
    from warptex.mesh_files import referenced_files

    (tmp_path / "my lib.mtl").write_text("newmtl m\nmap_Kd wood grain.png\n"
                                         "map_bump -bm 0.5 bumps.png\n")
    (tmp_path / "a.obj").write_text("mtllib my lib.mtl\nv 0 0 0\n")
    for texture in ("wood grain.png", "bumps.png"):
        (tmp_path / texture).write_bytes(b"")
    # A texture statement's file: its whole rest where it has no options, else its last word.
    assert {tmp_path / "my lib.mtl", tmp_path / "wood grain.png",
            tmp_path / "bumps.png"} <= set(referenced_files(tmp_path / "a.obj"))
    # Several libraries on one line, as OBJ has it.
    (tmp_path / "b.obj").write_text("mtllib other.mtl third.mtl\nv 0 0 0\n")
    (tmp_path / "other.mtl").write_text("newmtl n\n")
    (tmp_path / "third.mtl").write_text("newmtl t\nmap_Kd bumps.png\n")
    assert set(referenced_files(tmp_path / "b.obj")) == {
        tmp_path / "other.mtl", tmp_path / "third.mtl", tmp_path / "bumps.png"}
    (tmp_path / "my buf.bin").write_bytes(b"")
    (tmp_path / "a.gltf").write_text('{"buffers": [{"uri": "my%20buf.bin"}]}')
    assert referenced_files(tmp_path / "a.gltf") == [tmp_path / "my buf.bin"]


def test_a_plane_through_vertices_up_to_rounding_is_not_moved():
    """A cylinder's axis vertices lie 6e-17 off the plane x = 0 (cos(pi / 2) rounds): the
    slicing and the cap take them as in it, so moving the plane off them would only leave
    slivers 1e-7 wide beside them."""
    cylinder = trimesh.creation.cylinder(1.0, 2.0, sections=32)
    for half in cut(cylinder, np.zeros(3), np.array([1.0, 0.0, 0.0])):
        edges = half.vertices[half.edges_unique]
        assert np.linalg.norm(edges[:, 0] - edges[:, 1], axis=1).min() > 0.1
        assert half.is_watertight


def test_cap_ties_are_broken_by_position_not_numbering():
    """The halves number a cap's vertices apart: the edges' ranks and the segments handed to
    the triangulation must not depend on it (square caps are all ties)."""
    from warptex.cut import _in_order, _rank_edges

    rng = np.random.default_rng(3)
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0]], float)
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [0, 4], [1, 4], [2, 4], [3, 4]])
    ranks = _rank_edges(vertices, edges)[0]
    assert len(set(ranks)) == len(edges)  # equal lengths, still one order
    order = rng.permutation(len(vertices))  # vertex i becomes number order[i]
    renumbered = np.empty_like(vertices)
    renumbered[order] = vertices
    listed = rng.permutation(len(edges))  # and the edges listed in another order
    flipped = order[edges][listed][:, ::-1]
    np.testing.assert_array_equal(_rank_edges(renumbered, flipped)[0], ranks[listed])
    segments = vertices[edges][:, :, :2]
    shuffled = segments[rng.permutation(len(segments))][:, ::-1]
    np.testing.assert_array_equal(_in_order(shuffled), _in_order(segments))


def test_meshes_far_out_or_tiny_unwrap_as_at_unit_size():
    """xatlas works in float32: a sphere at map coordinates got faces of no UV area (a
    scrambled texture, exit 0), one of 2 mm NaN UVs (a traceback after the synthesis).
    Unwrapped at unit size, each gets the UVs of the sphere at the origin, its own
    vertices kept."""
    from warptex.bake import unwrapped

    sphere = trimesh.creation.icosphere(subdivisions=3)
    reference = unwrapped(sphere)
    for scale, offset in ((10.0, [4.5e5, 5.4e6, 120.0]), (1e-3, [0.0, 0.0, 0.0])):
        placed = trimesh.Trimesh(sphere.vertices * scale + offset, sphere.faces, process=False)
        mesh = unwrapped(placed)
        np.testing.assert_array_equal(mesh.faces, reference.faces)
        np.testing.assert_allclose(mesh.visual.uv, reference.visual.uv, atol=1e-5)
        corners = mesh.visual.uv[mesh.faces]
        edges = corners[:, 1:] - corners[:, :1]
        area = edges[:, 0, 0] * edges[:, 1, 1] - edges[:, 0, 1] * edges[:, 1, 0]
        assert (np.abs(area) > 1e-9).all()
        np.testing.assert_array_equal(mesh.vertices, placed.vertices[_vertex_map(mesh, placed)])


def _vertex_map(split: trimesh.Trimesh, whole: trimesh.Trimesh) -> np.ndarray:
    """For each vertex of ``split`` (an unwrapped ``whole``), the vertex of ``whole`` that
    its faces put in its place."""
    vmap = np.zeros(len(split.vertices), int)
    vmap[split.faces.ravel()] = whole.faces.ravel()
    return vmap


def test_outputs_keep_what_the_input_mesh_reads_and_what_they_are_given(tmp_path, data_dir,
                                                                         capsys):
    """An .obj's material library was replaced by an output of its name (the input then
    showed the baked texture); colors or UVs of another length were written gray or not at
    all; a mesh 2e-9 across came out of an .obj as one point."""
    from warptex.cli import main
    from warptex.mesh_files import export, referenced_files

    folder = tmp_path / "in"
    folder.mkdir()
    sphere = trimesh.creation.icosphere(subdivisions=1)
    uv = (sphere.vertices[:, :2] + 1) / 2
    export(sphere, folder / "ball.obj", image=np.full((8, 8, 3), 0.5, np.float32), uv=uv)
    (folder / "ball.obj").rename(folder / "input.obj")
    assert referenced_files(folder / "input.obj") == [folder / "ball.mtl", folder / "ball.png"]
    # Statements split by tabs, as OBJ allows and trimesh reads them; a .gltf's files; and
    # files of no sense to look for in, which loading the mesh then refuses.
    text = (folder / "input.obj").read_text()
    mtl = (folder / "ball.mtl").read_text()
    (folder / "tabbed.mtl").write_text(mtl.replace("map_Kd ", "map_Kd\t-s 1 1 1 "))
    (folder / "tabbed.obj").write_text(text.replace("mtllib ball.mtl", "mtllib\ttabbed.mtl"))
    assert referenced_files(folder / "tabbed.obj") == [folder / "tabbed.mtl",
                                                       folder / "ball.png"]
    (folder / "buffers.bin").write_bytes(b"")
    (folder / "a.gltf").write_text('{"buffers": [{"uri": "buffers.bin"}, {"uri": "data:,"}], '
                                   '"images": [{"uri": "missing.png"}]}')
    assert referenced_files(folder / "a.gltf") == [folder / "buffers.bin"]
    for broken in ('{"buffers": 5}', '{"images": null}', "[1]", "not json"):
        (folder / "b.gltf").write_text(broken)
        assert referenced_files(folder / "b.gltf") == []
    before = (folder / "ball.mtl").read_bytes()
    assert main(["bake", str(folder / "input.obj"), "--exemplar", str(data_dir / "granite_64.png"),
                 "--resolution", "16", "--uv", "mesh", "--texture-size", "8",
                 "-o", str(folder / "ball.obj")]) == 2
    assert capsys.readouterr().err == (f"warptex: error: {folder / 'ball.mtl'}: "
                                       f"{folder / 'input.obj'} reads this file; choose another "
                                       "output name\n")
    assert (folder / "ball.mtl").read_bytes() == before
    for name, given in (("colors", {"colors": np.zeros((10, 3), np.float32)}),
                        ("uv", {"uv": uv[:10], "image": np.zeros((8, 8, 3), np.float32)})):
        for suffix in (".ply", ".glb") if name == "colors" else (".glb", ".obj"):
            with pytest.raises(ValueError, match=f"{name} holds 10 rows, one per vertex of the "
                               f"mesh's {len(sphere.vertices)}"):
                export(sphere, tmp_path / f"bad{suffix}", **given)
    tiny = trimesh.Trimesh(sphere.vertices * 1e-9, sphere.faces, process=False)
    export(tiny, tmp_path / "tiny.obj", image=np.zeros((8, 8, 3), np.float32), uv=uv)
    read = trimesh.load(tmp_path / "tiny.obj", force="mesh", process=False)
    np.testing.assert_allclose(read.vertices, tiny.vertices, rtol=1e-6, atol=1e-18)


def test_float32_outputs_are_refused_past_a_hundredth_of_the_median_edge(tmp_path):
    """Near the limit, both ways: a unit sphere of 0.3-unit edges 3e4 units out moves by
    0.6 % of an edge in float32 and is written; 6e4 units out, by 1.3 %, it is refused."""
    from warptex.mesh_files import MeshFileError, load_mesh

    sphere = trimesh.creation.icosphere(subdivisions=2)
    for offset, refused in ((3e4, False), (6e4, True)):
        placed = sphere.copy()
        placed.apply_translation([offset + 0.1234567, 1.37 * offset + 0.7654321, 0.3333333])
        path = tmp_path / f"at_{offset:.0f}.obj"
        path.write_text(trimesh.exchange.obj.export_obj(placed, digits=10))
        if refused:
            with pytest.raises(MeshFileError, match=r"by up to .*, 0\.013 of its median edge"):
                load_mesh(path, outputs=[tmp_path / "out.ply"])
        else:
            assert len(load_mesh(path, outputs=[tmp_path / "out.glb"]).faces) == 320


def test_a_ply_whose_small_faces_float32_would_bend_is_refused(tmp_path, data_dir, capsys):
    """A 40 m sphere of 5 cm faces at map coordinates moves by a small part of its size in
    float32 (0.6 %), which the check let through, but by a large part of its edges: faces
    collapsed and turned. The median edge is the measure now."""
    from warptex.cli import main

    statue = trimesh.creation.icosphere(subdivisions=7, radius=20.0)
    statue.apply_translation([4.5e5, 5.4e6, 120.0])
    (tmp_path / "statue.obj").write_text(trimesh.exchange.obj.export_obj(statue, digits=10))
    assert main(["bake", str(tmp_path / "statue.obj"), "--exemplar",
                 str(data_dir / "granite_64.png"), "--resolution", "16",
                 "-o", str(tmp_path / "statue.ply")]) == 2
    assert "of its median edge" in capsys.readouterr().err
