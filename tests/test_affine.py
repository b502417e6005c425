"""Affine maps in one fixed order of float64 operations (warptex.affine): the plugin's
world-to-texture and object frames and the meshes' voxel space go through them, not
through LAPACK or a BLAS, whose kernels differ from CPU to CPU in the last bits."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from warptex.affine import affine_inverse, apply_affine
from warptex.surface import to_voxel_space


def _affine(rng: np.random.Generator) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rng.normal(size=(3, 3)) * rng.uniform(0.01, 100.0)
    m[:3, 3] = rng.normal(size=3) * 1e3
    return m


def test_the_inverse_of_affine_maps_and_none_for_singular_ones():
    rng = np.random.default_rng(0)
    for _ in range(50):
        m = _affine(rng)
        inverse = affine_inverse(m)
        np.testing.assert_allclose(inverse, np.linalg.inv(m), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(m @ inverse, np.eye(4), atol=1e-9)
        assert inverse.dtype == np.float64 and inverse[3].tolist() == [0.0, 0.0, 0.0, 1.0]
    assert affine_inverse(np.diag([1.0, 0.0, 1.0, 1.0])) is None
    assert affine_inverse(np.diag([0.0, 0.0, 0.0, 1.0])) is None
    # Determinants beyond float64 (1e-600, 1e600, 1e-320 subnormal); the inverses are not.
    for scales in ([1e-200] * 3, [1e200] * 3, [1.0, 1e-160, 1e-160], [1e200, 1e200, 1e-200]):
        np.testing.assert_array_equal(affine_inverse(np.diag([*scales, 1.0])),
                                      np.diag([1 / v for v in scales] + [1.0]))
    assert affine_inverse(np.diag([1e-310, 1.0, 1.0, 1.0])) is None  # 1e310: beyond it


def test_maps_with_a_zero_where_a_pivot_would_be_are_inverted_exactly():
    """A quarter turn and an axis swap: their first column's leading entry is 0, which
    elimination without row exchanges cannot divide by (a rotated object lost its frame);
    and a tiny leading entry beside a unit one, where the largest pivot keeps the inverse
    exact."""
    turn = np.array([[0.0, -1.0, 0.0, 5.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 0.0],
                     [0.0, 0.0, 0.0, 1.0]])
    swap = np.array([[0.0, 0.0, 2.0, 1.0], [0.0, 4.0, 0.0, 0.0], [8.0, 0.0, 0.0, -3.0],
                     [0.0, 0.0, 0.0, 1.0]])
    for m in (turn, swap):
        np.testing.assert_array_equal(affine_inverse(m), np.linalg.inv(m))
    small = np.array([[1e-12, 1.0, 0.0, 1.0], [1.0, 1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 0.0],
                      [0.0, 0.0, 0.0, 1.0]])
    np.testing.assert_allclose(small @ affine_inverse(small), np.eye(4), atol=1e-15)


def test_a_scale_s_inverse_is_its_correctly_rounded_reciprocal():
    """Cofactors over a determinant made 1/0.33 an ulp off (as for 1,666 of 3,000 random
    scales), so a point on a face of the block of matter mapped to 0.9999999999999999,
    into the voxel layer below the one LAPACK's inverse gave."""
    rng = np.random.default_rng(4)
    for _ in range(500):
        scales = rng.uniform(0.01, 10.0, 3).astype(np.float32).astype(np.float64)
        shift = rng.normal(size=3).astype(np.float32).astype(np.float64) * 10
        m = np.diag([*scales, 1.0])
        m[:3, 3] = shift
        inverse = affine_inverse(m)
        np.testing.assert_array_equal(np.diag(inverse)[:3], 1.0 / scales)
        np.testing.assert_array_equal(inverse[:3, 3], -((1.0 / scales) * shift))
    m = np.diag([np.float32(0.33)] * 3 + [1.0])
    corner = np.array(apply_affine(affine_inverse(m), *[np.float64(np.float32(0.33))] * 3))
    np.testing.assert_array_equal(corner, [1.0, 1.0, 1.0])


def test_the_inverse_takes_no_lapack_call(monkeypatch):
    """The plugin's inverses were np.linalg.inv's, whose last bits depend on the CPU's
    OpenBLAS kernels (SkylakeX and Haswell inverted 36 of 44 transforms otherwise, and
    colours of far points differed by an ulp)."""
    def refused(*args, **kwargs):
        raise AssertionError("LAPACK called")

    m = _affine(np.random.default_rng(1))
    expected = affine_inverse(m)
    for name in ("inv", "solve", "lstsq", "pinv"):
        monkeypatch.setattr(np.linalg, name, refused)
    np.testing.assert_array_equal(affine_inverse(m), expected)


@pytest.mark.parametrize("seed", [2, 3])
def test_points_are_mapped_in_one_order_of_operations(seed):
    """Term by term, left to right, each product and sum rounded: as Python floats, NumPy
    arrays and the plugin's Dr.Jit arrays compute it, so a point maps alike everywhere."""
    rng = np.random.default_rng(seed)
    m = _affine(rng)
    points = rng.normal(size=(200, 3)) * 1e4
    mapped = np.stack(apply_affine(m, *points.T), axis=1)
    rows = m.tolist()
    by_hand = [[r[0] * x + r[1] * y + r[2] * z + r[3] for r in rows[:3]]
               for x, y, z in points.tolist()]
    np.testing.assert_array_equal(mapped, np.array(by_hand))
    mesh = trimesh.Trimesh(points, [[0, 1, 2]], process=False)
    np.testing.assert_array_equal(to_voxel_space(mesh, m), mapped)
