"""Scalar variants' lookups (mitsuba_plugin.scalar): the store's colors to the bit, cold
and warm, with either filter, from partly filled bricks and through a mirror that starts
over, with warm points served without the store."""

from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

import mitsuba_plugin
from kernels.lookup import BRICK_VOXELS
from mitsuba_plugin.scalar import ScalarLookup

RGB_BRICK_BYTES = BRICK_VOXELS * 3 * 4


def sample_points(rng: np.random.Generator, n: int, low: float, high: float) -> np.ndarray:
    """Random points, a quarter of them on voxel faces and centers, where rounding bites."""
    points = rng.uniform(low, high, (n, 3))
    points[: n // 8] = np.round(points[: n // 8])
    points[n // 8 : n // 4] = np.round(points[n // 8 : n // 4]) + 0.5
    return points


@pytest.mark.parametrize("filter", ["trilinear", "nearest"])
def test_eval_is_the_store_to_the_bit_cold_and_warm(granite_32_file, filter):
    mi.set_variant("scalar_rgb")
    mitsuba_plugin.register()
    # raw: the stored colors, undecoded (tests/test_plugin.py decodes in scalar_rgb too).
    tex = mi.load_dict({"type": "lazy_solid", "exemplar": str(granite_32_file),
                        "scale": 8.0, "filter": filter, "raw": True})
    world = sample_points(np.random.default_rng(4), 300, -3.0, 3.0) / 8.0
    si = mi.SurfaceInteraction3f()

    def evaluated() -> np.ndarray:
        out = []
        for p in world:
            si.p = mi.Point3f(*p)
            out.append(list(tex.eval(si)))
        return np.array(out, np.float32)

    with mitsuba_plugin.traced_renders(None):  # nothing to trace in scalar variants
        cold = evaluated()  # bricks synthesized as points reach them
    before, counted = tex.solid.store.stats(), tex.scalar_stats()
    warm = evaluated()
    after = tex.solid.store.stats()
    assert (after["hits"], after["misses"]) == (before["hits"], before["misses"])
    assert tex.scalar_stats() == {"hits": counted["hits"] + len(world),
                                  "misses": counted["misses"]}
    assert counted["misses"] > 0
    # The points as the plugin maps them: float32 scene points, scaled in float64.
    expected = tex.solid.query(world.astype(np.float32).astype(np.float64) * 8.0,
                               filter=filter)
    np.testing.assert_array_equal(cold, expected)
    np.testing.assert_array_equal(warm, expected)


@pytest.mark.parametrize("filter", ["trilinear", "nearest"])
# Starts over at every brick, after ten of the RGB bricks, or keeps all.
@pytest.mark.parametrize("max_bytes", [1, 10 * RGB_BRICK_BYTES, 1 << 20])
def test_partly_stored_bricks_are_misses_until_the_store_fills_them(granite_32_file,
                                                                    warp_device, filter,
                                                                    max_bytes):
    """A miss forgets every brick the point reads, so once the store has filled them the
    next lookup finds the point, however many bricks the copies keep; the copies never
    take more than ``max_bytes`` (or one brick), counted in float32 colors."""
    from warptex.texture import SolidTexture

    tex = SolidTexture(granite_32_file, whole_bricks=False, device=warp_device)
    tex.query(np.array([[3.5, 3.5, 3.5]]), filter="nearest")  # one voxel of its brick
    lookup = ScalarLookup(tex.store, filter, max_bytes=max_bytes)
    points = sample_points(np.random.default_rng(6), 200, -12.0, 12.0)
    got = []
    for p in points:
        color = lookup.color(tuple(p))
        if color is None:
            lookup.forget(tuple(p))
            tex.query(p[None], filter=filter)
            color = lookup.color(tuple(p))
            assert color is not None, p
        got.append(color)
        assert len(lookup._bricks) * RGB_BRICK_BYTES <= max(max_bytes, RGB_BRICK_BYTES)
    assert lookup.color(tuple(points[0])) is not None  # stored by now
    assert ScalarLookup(tex.store, filter, 1 << 20).color((40.0, 40.0, 40.0)) is None
    np.testing.assert_array_equal(np.array(got, np.float64).astype(np.float32),
                                  tex.query(points, filter=filter))


def test_gray_exemplars_and_points_out_of_range(granite_32_file, srgb_decoded, tmp_path):
    """A one-channel exemplar gives gray RGB as the store's query does; the brick copies
    hold no point beyond the texture's range (packed brick keys would wrap there), and
    eval moves such a point by whole periods (wrap_far) instead."""
    from PIL import Image

    from warptex.texture import FAR_PERIOD, POINT_LIMIT

    gray = tmp_path / "gray.png"
    Image.open(granite_32_file).convert("L").save(gray)
    mi.set_variant("scalar_rgb")
    mitsuba_plugin.register()
    tex = mi.load_dict({"type": "lazy_solid", "exemplar": str(gray), "scale": 1.0})
    si = mi.SurfaceInteraction3f()
    si.p = mi.Point3f(3.25, -7.5, 12.0)
    expected = srgb_decoded(tex.solid.query(np.array([[3.25, -7.5, 12.0]]))[0, 0])
    cold, warm = (list(tex.eval(si)) for _ in range(2))  # then from the copies
    assert cold == warm == [pytest.approx(expected, rel=1e-6)] * 3
    assert cold[0] == cold[1] == cold[2]
    lookup = tex._scalar
    assert lookup.color((3.5, 3.5, 2.0**24 + 3.5)) is None
    assert lookup.color((float("nan"), 0.0, 0.0)) is None
    si.p = mi.Point3f(3.5, 3.5, POINT_LIMIT + 8.0)
    far = list(tex.eval(si))
    si.p = mi.Point3f(3.5, 3.5, POINT_LIMIT + 8.0 - FAR_PERIOD)
    assert far == list(tex.eval(si))
