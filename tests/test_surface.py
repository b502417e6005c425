"""Surface shells (Dong 2008, section 6.2): only the voxels a surface passes through."""

import numpy as np
import pytest
import trimesh

from warptex.surface import (
    MAX_SHELL,
    block_transform,
    checked_shell_size,
    shell,
    shell_size,
    to_voxel_space,
)


@pytest.mark.parametrize("resolution", [24, 48])
def test_sphere_shell_grows_with_area_and_hugs_the_surface(resolution, warp_device):
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    voxels = shell(sphere, resolution)
    radius = resolution / 2 * (1 - 1e-3 / resolution)
    # A closed surface crossing unit voxels touches about 1.5 voxels per unit of area.
    ratio = len(voxels) / (4 * np.pi * radius**2)
    assert 1.3 < ratio < 1.7
    centres = voxels + 0.5 - resolution / 2
    # The mesh is inscribed in the sphere: allow its chord error on top of the voxel.
    chord = 1 - np.cos(np.pi / (5 * 2**4))
    off = np.abs(np.linalg.norm(centres, axis=1) - radius)
    assert off.max() <= np.sqrt(3) / 2 + chord * radius
    assert len(np.unique(voxels, axis=0)) == len(voxels)


@pytest.mark.parametrize("first", [0, 1, 2])
@pytest.mark.parametrize("offset", [(0, 0, 0), (-10, -20, -30), (-1, 0, -2), (100000, -3, 7)])
def test_a_single_triangle_touches_exactly_the_voxels_it_crosses(offset, first, warp_device):
    """Moved by whole voxels too: floor (not truncation) finds the voxels of negative
    points, and the rows come sorted below zero and far out. The corners start at each
    ``first`` in turn, so that the hypotenuse, whose edge axes alone keep out the voxels
    beyond it, is each of the triangle's edges once."""
    corners = [[0.5, 0.5, 0.5], [3.5, 0.5, 0.5], [0.5, 2.5, 0.5]]
    tri = trimesh.Trimesh(vertices=corners, faces=[np.roll([0, 1, 2], -first)], process=False)
    m = np.eye(4)
    m[:3, 3] = offset
    voxels = shell(tri, transform=m)
    expected = {(x, y, 0) for x in range(4) for y in range(3) if x / 3 + y / 2 <= 1 + 1e-9}
    # The hypotenuse from (3.5, 0.5) to (0.5, 2.5) also crosses voxels (1, 2) and (2, 1).
    expected |= {(1, 2, 0), (2, 1, 0)}
    moved = {tuple(int(a) + b for a, b in zip(v, offset, strict=True)) for v in expected}
    assert set(map(tuple, voxels.tolist())) == moved
    assert np.array_equal(voxels, np.array(sorted(moved), np.int32))


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_a_triangle_barely_entering_a_voxel_touches_it(axis, warp_device):
    corners = np.roll([[0.5, 0.5, 0.5], [1.0005, 0.5, 0.5], [0.5, 0.9, 0.5]], axis, axis=1)
    tri = trimesh.Trimesh(vertices=corners, faces=[[0, 1, 2]], process=False)
    expected = {tuple(np.roll([0, 0, 0], axis)), tuple(np.roll([1, 0, 0], axis))}
    assert set(map(tuple, shell(tri, transform=np.eye(4)).tolist())) == expected


def test_to_voxel_space_applies_the_transform_to_column_vectors():
    """A rotation, a shear and a shift, against the 4x4 matrix applied to homogeneous
    column vectors: the linear part is not symmetric, so its transpose would place the
    mesh elsewhere in the texture."""
    box = trimesh.creation.box(extents=[2.0, 1.0, 0.5])
    m = np.array([[0.0, -3.0, 0.5, 10.0], [2.0, 0.0, 0.0, -4.0], [0.0, 1.0, 4.0, 7.5],
                  [0.0, 0.0, 0.0, 1.0]])
    homogeneous = np.c_[box.vertices, np.ones(len(box.vertices))]
    np.testing.assert_allclose(to_voxel_space(box, m), (m @ homogeneous.T).T[:, :3])


def test_block_transform_fits_the_bounding_box():
    box = trimesh.creation.box(extents=[2.0, 1.0, 0.5])
    m = block_transform(box, 64)
    corners = box.bounds @ m[:3, :3].T + m[:3, 3]
    assert corners.min() >= 0 and corners.max() < 64
    assert np.isclose(np.ptp(corners[:, 0]), 64, atol=0.01)


def test_block_transform_centres_the_bounding_box():
    """The mesh's box in the middle of the block, wherever the mesh lies: a mesh moved to a
    corner showed other voxels (nothing else checked where in the block it went)."""
    box = trimesh.creation.box(extents=[2.0, 1.0, 0.5])
    box.apply_translation([5.0, -3.0, 7.0])
    m = block_transform(box, 64)
    corners = box.bounds @ m[:3, :3].T + m[:3, 3]
    np.testing.assert_allclose(corners.mean(axis=0), [32.0, 32.0, 32.0], atol=1e-9)


def test_faces_naming_one_past_the_last_vertex_are_refused(warp_device):
    """The first index past the vertices, not only ones far out: a raw IndexError from the
    shell, or xatlas's own error, otherwise."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    mesh = trimesh.Trimesh(v, np.array([[0, 1, 3]]), process=False)
    with pytest.raises(ValueError, match="outside"):
        shell(mesh, 8, transform=np.eye(4))


def test_long_slivers_are_halved_and_touch_the_same_voxels(monkeypatch, warp_device):
    """A thin rod along the block's diagonal (CAD exports have such slivers): the kernel
    tested every voxel of each triangle's bounding box, the whole block, 75 s at 512^3.
    Halved until their boxes fit them, its triangles touch the same voxels; a sphere's
    even triangles are left as they are."""
    import warptex.surface as surface

    rod = trimesh.creation.cylinder(radius=0.01, height=1.0, sections=16)
    rod.apply_transform(trimesh.geometry.align_vectors([0, 0, 1], [1, 1, 1]))
    vertices = to_voxel_space(rod, block_transform(rod, 96))
    halved_vertices, halved_faces = surface._slivers_halved(vertices, np.asarray(rod.faces))
    assert len(halved_faces) > 10 * len(rod.faces)
    assert not surface._box_waste(halved_vertices[halved_faces]).any()
    halving = surface._slivers_halved
    searched = []

    def spy(vertices, faces):
        searched.append(len(halving(vertices, faces)[1]))
        return halving(vertices, faces)

    monkeypatch.setattr(surface, "_slivers_halved", spy)
    voxels = shell(rod, 96, device=warp_device)
    assert searched == [len(halved_faces)]  # what the kernel searched: the halves
    monkeypatch.setattr(surface, "_BOX_WASTE", float("inf"))  # every triangle as it is
    np.testing.assert_array_equal(voxels, shell(rod, 96, device=warp_device))
    assert searched[-1] == len(rod.faces)
    sphere = trimesh.creation.icosphere(subdivisions=3)
    even = to_voxel_space(sphere, block_transform(sphere, 256))
    assert surface._slivers_halved(even, np.asarray(sphere.faces))[0] is even


def test_a_transform_beyond_the_texture_s_range_is_refused_in_words(warp_device):
    """Points past int32 were floored to undefined voxels (a triangle at 3e9 voxels touched
    none on this CPU; a GPU saturates), and a transform of 1e200 failed in NumPy."""
    from warptex.synthesis import COORD_LIMIT

    tri = trimesh.Trimesh(vertices=[[0.5, 0.5, 0.5], [3.5, 0.5, 0.5], [0.5, 2.5, 0.5]],
                          faces=[[0, 1, 2]], process=False)
    shifted = np.eye(4)
    shifted[0, 3] = 3e9
    for m in (shifted, np.diag([1e200, 1.0, 1.0, 1.0])):
        with pytest.raises(ValueError, match=rf"beyond the texture's \+-{COORD_LIMIT}"):
            shell(tri, transform=m)
    near_end = np.eye(4)
    near_end[0, 3] = COORD_LIMIT - 3.6  # float32 rounds the far corner onto the range's end
    with pytest.raises(ValueError, match="beyond the texture's"):
        shell(tri, transform=near_end)
    m = np.eye(4)
    m[0, 3] = COORD_LIMIT - 8  # the last voxels within the range are still found (float32
    voxels = shell(tri, transform=m)  # rounds the corners there: some of 11, not all)
    assert len(voxels) and (voxels[:, 0] >= COORD_LIMIT - 8).all()


def test_shell_rows_of_a_box_wider_than_int64_s_numbering_stay_apart():
    """Rows are numbered within their bounding box: one 2.2e6 voxels on each side wrapped
    int64, and the rows came back as other voxels."""
    from warptex.surface import _unique_rows

    rows = np.array([[0, 0, 2200000], [2200000, 0, 0], [0, 2200000, 0], [0, 0, 0],
                     [0, 0, 0]], np.int32)
    assert np.array_equal(_unique_rows(rows), np.unique(rows, axis=0))


def test_the_shell_size_estimate_is_near_the_shell(warp_device):
    """shell_size, which the commands' refusals and memory checks go by, is within a few
    per cent of the voxels shell finds (the surface's area projected on the axis planes)."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    m = block_transform(sphere, 64)
    found = len(shell(sphere, transform=m))
    assert abs(shell_size(sphere, m) - found) < 0.02 * found


def test_a_shell_beyond_what_a_shell_may_hold_is_refused_before_the_work():
    """Up to 2^28 voxels: a sphere at 9600^3 passes through about 4e8, refused in words;
    at 4096^3 through 7e7, taken."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    assert MAX_SHELL == 1 << 28
    with pytest.raises(ValueError, match=r"about 4.*e\+08 voxels, more than the 268435456 a "
                                         r"shell may hold"):
        checked_shell_size(sphere, block_transform(sphere, 9600))
    assert checked_shell_size(sphere, block_transform(sphere, 4096)) < MAX_SHELL


def test_vertices_no_face_uses_decide_nothing_of_the_shell(warp_device):
    """An unused vertex far out, as exporters leave them, neither widens the shell nor
    takes it past the texture's range; a used NaN vertex is refused in words."""
    sphere = trimesh.creation.icosphere(subdivisions=2)
    m = block_transform(sphere, 24)
    stray = trimesh.Trimesh(np.vstack([sphere.vertices, [[1e12, 0.0, 0.0]]]), sphere.faces,
                            process=False)
    np.testing.assert_array_equal(shell(stray, transform=m), shell(sphere, transform=m))
    broken = trimesh.Trimesh(sphere.vertices.copy(), sphere.faces, process=False)
    broken.vertices[broken.faces[0, 0]] = np.nan
    with pytest.raises(ValueError, match=r"reaches nan voxels .*: check transform"):
        shell(broken, transform=m)


def test_meshes_and_transforms_that_fit_no_block_are_refused_in_words(warp_device):
    point = trimesh.Trimesh(np.ones((3, 3)), [[0, 1, 2]], process=False)
    with pytest.raises(ValueError, match="the mesh has an empty bounding box"):
        block_transform(point, 16)
    # Vertices without faces have no bounds in trimesh (a TypeError unpacking None); given
    # a transform, their shell is empty.
    faceless = trimesh.Trimesh(np.eye(3), np.zeros((0, 3), np.int64), process=False)
    for call in (lambda: block_transform(faceless, 16), lambda: shell(faceless, 16)):
        with pytest.raises(ValueError, match="the mesh has no faces: no bounding box to fit"):
            call()
    assert shell(faceless, transform=np.eye(4)).shape == (0, 3)
    for bad in (np.eye(4)[:, :3], np.eye(4)[:3], np.eye(3)):
        with pytest.raises(ValueError, match="transform must be a 4x4 matrix"):
            to_voxel_space(point, bad)
