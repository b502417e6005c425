"""Traced lookups (mitsuba_plugin.traced): the same colors as SolidTexture.query to the
bit, misses logged and synthesized, and renders that do not depend on the mode or on what
the brick store held before."""

from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

import mitsuba_plugin
import warptex
from warptex.store import brick_keys, voxels_read

LLVM = "llvm_ad_rgb"


@pytest.fixture(autouse=True)
def llvm_variant():
    if warptex.best_mitsuba_variant() != LLVM:
        pytest.skip("llvm_ad_rgb needs libLLVM >= 16 (see warptex/llvm.py)")
    mi.set_variant(LLVM)
    mitsuba_plugin.register()


@pytest.fixture()
def texture(granite_32_file, warp_device):
    from warptex.texture import SolidTexture

    return SolidTexture(granite_32_file, device=warp_device)


def sample_points(rng: np.random.Generator, n: int, low: float, high: float) -> np.ndarray:
    """Random points, a quarter of them on voxel faces and centers, where rounding bites."""
    points = rng.uniform(low, high, (n, 3))
    points[: n // 8] = np.round(points[: n // 8])
    points[n // 8 : n // 4] = np.round(points[n // 8 : n // 4]) + 0.5
    return points


def traced_colors(lookup, points: np.ndarray) -> np.ndarray:
    rgb = lookup.colors(tuple(mi.Float64(points[:, k]) for k in range(3)), mi.Bool(True))
    return np.stack([rgb[k].numpy() for k in range(3)], axis=1)


@pytest.mark.parametrize("filter", ["nearest", "trilinear"])
def test_traced_colors_are_bit_identical_to_query(texture, filter):
    from mitsuba_plugin.traced import TracedLookup

    # Of other extents on each axis: in a cube of bricks, swapped page strides read alike.
    points = sample_points(np.random.default_rng(3), 4000, -12.0, 12.0) * [1.0, 0.35, 1.7]
    expected = texture.query(points, filter=filter)[:, :3]
    lookup = TracedLookup(texture.store, filter, fallback=(0.5, 0.5, 0.5))
    assert lookup.refresh()
    np.testing.assert_array_equal(traced_colors(lookup, points), expected)
    assert len(lookup.take_misses()) == 0


@pytest.mark.parametrize("filter", ["nearest", "trilinear"])
@pytest.mark.parametrize("side", [1.0, -1.0])
@pytest.mark.parametrize("offset", [0.0, 4_190_000.0])  # near POINT_LIMIT: 2^22 voxels
def test_misses_show_the_fallback_and_log_every_brick_they_read(texture, filter, side, offset):
    from mitsuba_plugin.traced import TracedLookup

    texture.query(np.full((1, 3), side * offset), filter=filter)  # bricks near the others
    lookup = TracedLookup(texture.store, filter, fallback=(0.25, 0.5, 0.75))
    assert lookup.refresh()
    far = side * (sample_points(np.random.default_rng(4), 500, 40.0, 90.0) + offset)
    np.testing.assert_array_equal(traced_colors(lookup, far),
                                  np.tile([0.25, 0.5, 0.75], (len(far), 1)).astype(np.float32))
    # Bricks whose log slots collide are logged by a later read (the hash changes).
    missed = lookup.take_misses()
    for _ in range(3):
        traced_colors(lookup, far)
        missed = np.concatenate([missed, lookup.take_misses()])
    assert set(brick_keys(voxels_read(far, filter))) <= set(brick_keys(missed))
    assert len(lookup.take_misses()) == 0  # taking clears the log
    texture.store.prefetch(missed)
    assert lookup.refresh()
    np.testing.assert_array_equal(traced_colors(lookup, far),
                                  texture.query(far, filter=filter)[:, :3])


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("side", [1, -1])
def test_a_point_just_past_the_stored_bricks_is_a_miss(texture, axis, side):
    """The brick next to the stored ones lies outside their table of pages: no page of it
    is read (one past the end read another brick's slot, or memory beyond the table)."""
    from mitsuba_plugin.traced import TracedLookup

    texture.query(np.array([[3.5, 3.5, 3.5], [11.5, 11.5, 11.5]]), filter="nearest")
    lookup = TracedLookup(texture.store, "nearest", fallback=(0.25, 0.5, 0.75))
    assert lookup.refresh()
    point = np.array([[3.5, 3.5, 3.5]]) if side < 0 else np.array([[11.5, 11.5, 11.5]])
    point[0, axis] += side * 8.0
    np.testing.assert_array_equal(traced_colors(lookup, point),
                                  np.array([[0.25, 0.5, 0.75]], np.float32))
    assert set(brick_keys(lookup.take_misses())) == set(brick_keys(point.astype(int)))


def test_the_miss_log_spreads_bricks_over_all_of_its_slots(texture):
    """Slots were the hash's bits 16 to 31: 65,536 of the log's 2^20, so a large cold
    render lost most of its missed bricks to collisions, took more traced rounds and fell
    back to the slower wavefront mode."""
    from mitsuba_plugin.traced import LOG_CAPACITY, TracedLookup

    lookup = TracedLookup(texture.store, "nearest", fallback=(0.5, 0.5, 0.5))
    bricks = np.random.default_rng(1).choice(200**3, 200_000, replace=False)
    voxels = np.stack(np.unravel_index(bricks, (200, 200, 200)), axis=1) * 8 - 800
    lookup._log([mi.Int32(voxels[:, k]) for k in range(3)], mi.Bool(True))
    slots = np.flatnonzero(lookup._log_voxels.numpy())
    # 200,000 bricks hashed into 2^20 slots fill about 181,000 of them.
    assert len(slots) > 170_000 and slots.max() >= LOG_CAPACITY - 1000


def test_bricks_lost_to_a_collision_in_the_miss_log_are_logged_the_next_render(texture):
    """Each render hashes the log's slots anew: bricks that one render's collisions lost
    are found by the next, so a cold render's misses are all filled in a few rounds."""
    from mitsuba_plugin.traced import TracedLookup

    lookup = TracedLookup(texture.store, "nearest", fallback=(0.5, 0.5, 0.5))
    bricks = np.random.default_rng(3).choice(200**3, 200_000, replace=False)
    voxels = np.stack(np.unravel_index(bricks, (200, 200, 200)), axis=1) * 8 - 800
    seen = []
    for _ in range(2):
        lookup._log([mi.Int32(voxels[:, k]) for k in range(3)], mi.Bool(True))
        seen.append(set(brick_keys(lookup.take_misses())))
    assert len(seen[0]) < 190_000  # collisions lost some
    assert len(seen[0] | seen[1]) > len(seen[0]) + 10_000


def test_evicted_bricks_miss_instead_of_reading_a_reused_slot(texture):
    from mitsuba_plugin.traced import TracedLookup

    store = texture.store
    a = sample_points(np.random.default_rng(6), 100, 0.5, 7.5)  # brick (0, 0, 0)
    texture.query(a, filter="nearest")
    store.cache_bytes = store.stats()["payload_bytes"]  # room for one brick
    lookup = TracedLookup(store, "nearest", (0.25, 0.5, 0.75))
    assert lookup.refresh()
    texture.query(a + 16.0, filter="nearest")  # brick (2, 2, 2) evicts (0, 0, 0)
    assert lookup.refresh()
    np.testing.assert_array_equal(traced_colors(lookup, a),
                                  np.tile([0.25, 0.5, 0.75], (len(a), 1)).astype(np.float32))
    assert set(brick_keys(lookup.take_misses())) == set(brick_keys(np.zeros((1, 3), int)))
    np.testing.assert_array_equal(traced_colors(lookup, a + 16.0),
                                  texture.query(a + 16.0, filter="nearest")[:, :3])


def test_a_refresh_stopped_half_way_is_done_again_when_next_asked(texture, monkeypatch):
    """Ctrl-C while the lookup mirrors a changed store (its brick table made, the colour
    sums not yet): the next refresh mirrors it again, so no table meets the wrong sums."""
    import drjit

    from mitsuba_plugin import traced
    from mitsuba_plugin.traced import TracedLookup

    class Stopped:
        def __getattr__(self, name: str):
            return getattr(drjit, name)

        @staticmethod
        def zeros(*args, **kwargs):
            raise KeyboardInterrupt

    points = sample_points(np.random.default_rng(9), 400, -20.0, 20.0)
    texture.query(points[:40], filter="nearest")
    lookup = TracedLookup(texture.store, "nearest", (0.25, 0.5, 0.75))
    assert lookup.refresh()
    expected = texture.query(points, filter="nearest")[:, :3]  # more bricks: a new version
    with monkeypatch.context() as patch:
        patch.setattr(traced, "dr", Stopped())
        with pytest.raises(KeyboardInterrupt):
            lookup.refresh()
    assert lookup.refresh()
    np.testing.assert_array_equal(traced_colors(lookup, points), expected)


def test_scattered_bricks_beyond_the_page_budget_are_not_traced(texture, monkeypatch):
    from mitsuba_plugin.traced import TracedLookup

    texture.query(np.array([[0.0, 0.0, 0.0], [100.0, 100.0, 100.0]]), filter="nearest")
    assert TracedLookup(texture.store, "nearest", (0, 0, 0), max_pages=12**3 - 1).refresh() is False
    assert TracedLookup(texture.store, "nearest", (0, 0, 0), max_pages=13**3).refresh() is True
    # Nor a store of more slots than 32-bit positions reach in the mirror's sums.
    slots = len(texture.store.snapshot().keys)
    monkeypatch.setattr("mitsuba_plugin.traced._MAX_SUMS", slots * 512 * 3)
    assert TracedLookup(texture.store, "nearest", (0, 0, 0), max_pages=13**3).refresh() is False


def lit_plane(path, space: str = "world", filter: str = "trilinear", integrator: str = "path",
              extra: dict | None = None, **props):
    """A floor and a wall of one lazy_solid texture under an environment (and the objects
    ``extra``), and that texture: paths bounce between them, so later bounces read bricks
    the first did not."""
    before = set(mitsuba_plugin.textures())  # the objects: a freed one's id may be reused
    tex = {"type": "ref", "id": "tex"}
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "tex": {"type": "lazy_solid", "exemplar": str(path), "scale": 6.0, "space": space,
                "filter": filter} | props,
        "integrator": {"type": integrator, "max_depth": 4},
        "sensor": {"type": "perspective", "fov": 50,
                   "to_world": T().look_at(origin=[0, -3, 4], target=[0, 0, 0], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 24, "height": 24},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "plane": {"type": "rectangle", "to_world": T().scale([2, 2, 1]),
                  "bsdf": {"type": "diffuse", "reflectance": tex}},
        "wall": {"type": "rectangle",
                 "to_world": T().translate([0, 1.5, 1]).rotate([1, 0, 0], 90).scale([2, 1, 1]),
                 "bsdf": {"type": "diffuse", "reflectance": tex}},
        "light": {"type": "constant"},
    } | (extra or {}))
    (texture,) = [t for t in mitsuba_plugin.textures() if t not in before]
    return scene, texture


@pytest.mark.parametrize("filter", ["trilinear", "nearest"])
def test_renders_agree_cold_warm_and_in_wavefront_mode(granite_32_file, filter):
    """Determinism at the renderer: a cold store (traced renders that miss, synthesis,
    render again), a warm one (one traced render) and wavefront mode give one image, with
    either filter (a traced program that ignored it would not). The wavefront image is
    another texture's, its store empty, so it does not read the voxels the traced renders
    stored: those must be what lookups alone synthesize."""
    scene, texture = lit_plane(granite_32_file, filter=filter)
    cold = np.array(mitsuba_plugin.render(scene, spp=4))
    first = texture.traced_stats()
    assert first["renders_with_misses"] >= 1
    assert first["renders"] == first["renders_with_misses"] + 1
    warm = np.array(mitsuba_plugin.render(scene, spp=4))
    assert texture.traced_stats() == {"renders": first["renders"] + 1,
                                      "renders_with_misses": first["renders_with_misses"]}
    apart, other = lit_plane(granite_32_file, filter=filter)
    assert other is not texture and other.solid.store.stats()["bricks"] == 0
    with mitsuba_plugin.wavefront():
        wavefront = np.array(mi.render(apart, spp=4, seed=0))
    assert other.solid.store.stats()["voxels_added"] > 0
    assert warm.mean() > 0.05
    # Mitsuba adds samples into the film with atomics, in an order that varies from run
    # to run, so even a texture-free scene differs in the last bits between renders; a
    # wrong voxel would be off by a visible amount (the lookups are compared bit for bit
    # above).
    np.testing.assert_allclose(cold, warm, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(warm, wavefront, rtol=1e-5, atol=1e-6)


def test_object_space_bumps_render_as_in_wavefront_mode(granite_32_file):
    """bumpmap's slopes in object space take each hit's object frame in the traced program
    as in wavefront mode (a scaled sphere, whose frame sizes the steps)."""
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "perspective", "fov": 40, "near_clip": 0.001,
                   "to_world": T().look_at(origin=[0, 0, 0.2], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 24, "height": 24},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "ball": {"type": "sphere", "radius": 0.05, "bsdf": {
            "type": "bumpmap", "bsdf": {"type": "diffuse"},
            "arg0": {"type": "lazy_solid", "exemplar": str(granite_32_file),
                     "space": "object", "scale": 16.0}}},
        "light": {"type": "directional", "direction": [0.3, -0.2, -1], "irradiance": 3.0},
    })
    traced = np.array(mitsuba_plugin.render(scene, spp=4))
    with mitsuba_plugin.wavefront():
        wavefront = np.array(mi.render(scene, spp=4, seed=0))
    assert traced.mean() > 0.02
    np.testing.assert_allclose(traced, wavefront, rtol=1e-5, atol=1e-6)


def test_a_block_placed_beyond_the_texture_range_renders_as_in_wavefront_mode(granite_32_file):
    """Shading points a million scene units out (6 million voxels, beyond POINT_LIMIT) are
    moved by whole periods (wrap_far) in the traced program as in wavefront mode: a render,
    not an error."""
    far = mi.ScalarTransform4f().translate([-1e6, 0, 0])
    scene, texture = lit_plane(granite_32_file, to_world=far)
    traced = np.array(mitsuba_plugin.render(scene, spp=4))
    assert texture.traced_stats()["renders"] >= 1
    with mitsuba_plugin.wavefront():
        wavefront = np.array(mi.render(scene, spp=4, seed=0))
    assert traced.mean() > 0.05
    np.testing.assert_allclose(traced, wavefront, rtol=1e-5, atol=1e-6)


def test_non_finite_points_are_black_in_traced_lookups_as_in_wavefront_ones(granite_32_file):
    """A NaN or infinite shading point is black in a traced program too; the traced
    lookup's masked-off lanes show the stand-in color of a miss, which a traced eval
    that did not blacken them gave such points (no render test has one)."""
    import drjit as dr

    scene, texture = lit_plane(granite_32_file)
    mitsuba_plugin.render(scene, spp=1)  # stores the plane's voxels
    si = dr.zeros(mi.SurfaceInteraction3f, 4)
    si.p = mi.Point3f([0.1, np.nan, 0.0, 0.3], [0.2, 0.0, np.inf, -0.4], [0.0, 0.0, 0.0, 0.0])
    wavefront = np.array(texture.eval(si))
    with mitsuba_plugin.traced_renders(scene):
        # A condition Dr.Jit cannot see through, so the eval is traced (SymbolicScope).
        traced = dr.if_stmt(args=(si,), cond=dr.opaque(mi.Bool, True, 4), true_fn=texture.eval,
                            false_fn=lambda si: dr.zeros(mi.Color3f, 4), mode="symbolic")
        traced = np.array(traced)
    assert (wavefront[:, [0, 3]] > 0).all()
    np.testing.assert_array_equal(wavefront[:, 1:3], 0.0)
    np.testing.assert_array_equal(traced, wavefront)
    # Lanes masked off by ``active`` are black too, as colors_at says, not the stand-in.
    active = mi.Bool([True, True, True, False])
    wavefront = np.array(texture.eval(si, active))
    with mitsuba_plugin.traced_renders(scene):
        traced = np.array(dr.if_stmt(args=(si, active), cond=dr.opaque(mi.Bool, True, 4),
                                     true_fn=texture.eval,
                                     false_fn=lambda si, active: dr.zeros(mi.Color3f, 4),
                                     mode="symbolic"))
    np.testing.assert_array_equal(wavefront[:, 3], 0.0)
    np.testing.assert_array_equal(traced, wavefront)


def test_object_space_is_traced_and_agrees_with_wavefront_mode(granite_32_file):
    """Object-space frames (instances, shapes with to_world) found per lane in the traced
    program give the image that wavefront mode gives."""
    before = set(mitsuba_plugin.textures())  # the objects: a freed one's id may be reused
    T = mi.ScalarTransform4f
    tex = {"type": "lazy_solid", "exemplar": str(granite_32_file), "scale": 8.0,
           "space": "object"}
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "orthographic",
                   "to_world": T().look_at(origin=[0, 0, 6], target=[0, 0, 0], up=[0, 1, 0])
                   .scale([3, 3, 1]),
                   "film": {"type": "hdrfilm", "width": 24, "height": 24},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "tex": tex,
        "group": {"type": "shapegroup",
                  "s": {"type": "sphere", "bsdf": {"type": "diffuse",
                                                   "reflectance": {"type": "ref", "id": "tex"}}}},
        "a": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
              "to_world": T().translate([1.5, 0, 0]).rotate([0, 0, 1], 30)},
        "b": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
              "to_world": T().translate([-1.5, 1, 0])},
        "c": {"type": "sphere", "to_world": T().translate([0, -1.5, 0]).scale(0.8),
              "bsdf": {"type": "diffuse", "reflectance": {"type": "ref", "id": "tex"}}},
        "light": {"type": "constant"},
    })
    (texture,) = [t for t in mitsuba_plugin.textures() if t not in before]
    traced = np.array(mitsuba_plugin.render(scene, spp=4))
    assert texture.traced_stats()["renders"] >= 2
    with mitsuba_plugin.wavefront():
        wavefront = np.array(mi.render(scene, spp=4, seed=0))
    assert traced.std() > 0.02
    np.testing.assert_allclose(traced, wavefront, rtol=1e-5, atol=1e-6)


def test_a_shape_without_a_frame_stops_no_traced_render(granite_32_file):
    """A sphere of radius 0 has a to_world that cannot be inverted: taking the frames of a
    scene's shapes for an object-space texture (its own, or a live one of another scene)
    raised LinAlgError, where wavefront mode rendered."""
    other = lit_plane(granite_32_file, space="object")  # alive, of another scene
    point = {"point": {"type": "sphere", "center": [0, 0, -3], "radius": 0.0}}
    for space in ("world", "object"):
        scene, texture = lit_plane(granite_32_file, space=space, extra=point)
        traced = np.array(mitsuba_plugin.render(scene, spp=4))
        assert texture.traced_stats()["renders"] >= 1
        with mitsuba_plugin.wavefront():
            wavefront = np.array(mi.render(scene, spp=4, seed=0))
        np.testing.assert_allclose(traced, wavefront, rtol=1e-5, atol=1e-6)
    del other


def test_an_untraceable_texture_of_another_scene_leaves_this_one_traced(granite_32_file):
    """Dr.Jit traces every texture of the variant into a render's program: one of another
    scene whose bricks lie too far apart to be traced sent every batch of this scene to
    wavefront mode, and made this scene's traced_renders raise."""
    _, far = lit_plane(granite_32_file)
    far.solid.query(np.array([[0.0, 0.0, 0.0], [3e6, 3e6, 3e6]]))
    assert not far.begin_tracing(mi.load_dict({"type": "scene"}))
    far.end_tracing()
    scene, texture = lit_plane(granite_32_file)
    image = np.array(mitsuba_plugin.render(scene, spp=4))
    assert texture.traced_stats()["renders"] >= 1
    with mitsuba_plugin.traced_renders(scene):
        again = np.array(mi.render(scene, spp=4, seed=0))
    np.testing.assert_allclose(again, image, rtol=1e-5, atol=1e-6)


def test_a_texture_too_scattered_to_trace_renders_its_scene_in_wavefront_mode(granite_32_file):
    """Bricks too far apart for the page table (a query far out): render() takes wavefront
    mode, without a word and with the same image, where traced_renders() raises."""
    scene, texture = lit_plane(granite_32_file)
    texture.solid.query(np.array([[0.0, 0.0, 0.0], [3e6, 3e6, 3e6]]))
    image = np.array(mitsuba_plugin.render(scene, spp=4))
    assert texture.traced_stats()["renders"] == 0 and image.mean() > 0.05
    with mitsuba_plugin.wavefront():
        wavefront = np.array(mi.render(scene, spp=4, seed=0))
    np.testing.assert_allclose(image, wavefront, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("channels", [1, 2])
def test_a_gray_exemplar_renders_gray_traced_as_in_wavefront_mode(granite_32_file, tmp_path,
                                                                  channels):
    """A gray exemplar keeps one channel, and one of two channels (a .npy's) shows its
    first as gray: traced lookups give it to R, G and B, as wavefront mode does."""
    from PIL import Image

    gray = np.asarray(Image.open(granite_32_file).convert("L"), np.float32) / 255
    path = tmp_path / "granite_gray.npy"
    np.save(path, np.stack([gray, 1 - gray][:channels], axis=2))
    scene, texture = lit_plane(path)
    assert texture.solid.channels == channels
    traced = np.array(mitsuba_plugin.render(scene, spp=4))
    assert texture.traced_stats()["renders"] >= 1 and traced.mean() > 0.05
    np.testing.assert_allclose(traced[..., 1], traced[..., 0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(traced[..., 2], traced[..., 0], rtol=1e-5, atol=1e-6)
    with mitsuba_plugin.wavefront():
        wavefront = np.array(mi.render(scene, spp=4, seed=0))
    np.testing.assert_allclose(traced, wavefront, rtol=1e-5, atol=1e-6)


def test_out_of_rounds_a_pass_is_rendered_in_wavefront_mode(granite_32_file, monkeypatch):
    scene, texture = lit_plane(granite_32_file)
    monkeypatch.setattr(mitsuba_plugin, "TRACED_ROUNDS", 1)
    fallback = np.array(mitsuba_plugin.render(scene, spp=4))  # the one traced try misses
    assert texture.traced_stats() == {"renders": 1, "renders_with_misses": 1}
    assert texture.solid.store.stats()["hits"] > 0  # wavefront lookups served the image
    monkeypatch.setattr(mitsuba_plugin, "TRACED_ROUNDS", 6)
    np.testing.assert_allclose(fallback, np.array(mitsuba_plugin.render(scene, spp=4)),
                               rtol=1e-5, atol=1e-6)


def test_only_the_rendering_thread_reads_traced_colors(granite_32_file):
    """While one thread's render traces a texture, a plain symbolic render elsewhere
    still raises instead of showing stand-in colors."""
    import threading

    scene, texture = lit_plane(granite_32_file)
    errors = []

    def plain_render():
        try:
            mi.render(scene, spp=1)
        except RuntimeError as e:
            errors.append(e)

    assert texture.begin_tracing(scene)
    try:
        other = threading.Thread(target=plain_render)
        other.start()
        other.join()
    finally:
        texture.end_tracing()
    assert len(errors) == 1


def assert_plain_render_refused(scene: mi.Scene) -> None:
    """A plain symbolic render of ``scene`` raises the texture's error."""
    with pytest.raises(RuntimeError) as raised:
        mi.render(scene, spp=1)
    # Mitsuba wraps the texture's error; the texture's own message is the cause.
    causes = [raised.value]
    while causes[-1].__cause__ is not None:
        causes.append(causes[-1].__cause__)
    assert any("lazy_solid: render with mitsuba_plugin.render" in str(e) for e in causes)


def test_a_plain_symbolic_render_raises_instead_of_showing_missing_voxels(granite_32_file):
    assert_plain_render_refused(lit_plane(granite_32_file)[0])


def test_traced_reads_count_for_least_recently_used_eviction(texture):
    """Bricks read by traced lookups are kept over bricks stored later but not read."""
    from mitsuba_plugin.traced import TracedLookup

    near = sample_points(np.random.default_rng(5), 200, 0.5, 7.5)  # brick (0, 0, 0)
    texture.query(near, filter="nearest")
    texture.query(np.array([[40.0, 40.0, 40.0]]), filter="nearest")  # stored later
    lookup = TracedLookup(texture.store, "nearest", (0, 0, 0))
    assert lookup.refresh()
    traced_colors(lookup, near)
    lookup.take_misses()
    store = texture.store
    store.cache_bytes = 2 * store.stats()["payload_bytes"] // store.stats()["bricks"]
    store.prefetch(np.array([[-40, -40, -40]]))  # a third brick: one must go
    kept = brick_keys(np.array([[0, 0, 0], [-40, -40, -40]]))
    snap = store.snapshot()
    assert sorted(snap.keys[snap.keys >= 0]) == sorted(kept)


def test_trilinear_reads_count_for_both_bricks_they_read(texture):
    """A trilinear point on a brick's last voxel reads the next brick too; the render
    that reads it keeps both over a brick stored later but not read."""
    from mitsuba_plugin.traced import TracedLookup

    rng = np.random.default_rng(8)
    across = np.column_stack([rng.uniform(7.6, 7.9, 50), rng.uniform(1, 6, (50, 2))])
    expected = texture.query(across, filter="trilinear")  # bricks (0, 0, 0) and (1, 0, 0)
    texture.query(np.array([[40.0, 40.0, 40.0]]), filter="nearest")  # stored later
    lookup = TracedLookup(texture.store, "trilinear", (0, 0, 0))
    assert lookup.refresh()
    np.testing.assert_array_equal(traced_colors(lookup, across), expected)
    lookup.take_misses()
    store = texture.store
    store.cache_bytes = 3 * store.stats()["payload_bytes"] // store.stats()["bricks"]
    store.prefetch(np.array([[-40, -40, -40]]))  # a fourth brick: one must go
    kept = brick_keys(np.array([[0, 0, 0], [8, 0, 0], [-40, -40, -40]]))
    snap = store.snapshot()
    assert sorted(snap.keys[snap.keys >= 0]) == sorted(kept)


def test_voxels_missing_from_a_partly_filled_brick_are_misses(granite_32_file, warp_device):
    from mitsuba_plugin.traced import TracedLookup
    from warptex.texture import SolidTexture

    texture = SolidTexture(granite_32_file, device=warp_device, whole_bricks=False)
    stored = np.array([[2.5, 3.5, 4.5]])
    texture.query(stored, filter="nearest")
    lookup = TracedLookup(texture.store, "nearest", (0.25, 0.5, 0.75))
    assert lookup.refresh()
    np.testing.assert_array_equal(traced_colors(lookup, stored),
                                  texture.query(stored, filter="nearest")[:, :3])
    assert len(lookup.take_misses()) == 0
    neighbour = stored + 1.0  # same brick, not stored
    np.testing.assert_array_equal(traced_colors(lookup, neighbour),
                                  np.array([[0.25, 0.5, 0.75]], np.float32))
    assert len(lookup.take_misses()) == 512  # the whole brick is asked for


def test_cuda_variants_are_not_traced(granite_32_file, monkeypatch):
    """On CUDA, Dr.Jit's float32 division is approximate and the GPU compiler may fuse its
    multiply-adds, so traced colors would not be bit-identical to the Warp lookups:
    textures there render in wavefront mode."""
    import drjit as dr

    scene, texture = lit_plane(granite_32_file)
    assert texture.begin_tracing(scene) is True
    monkeypatch.setattr(dr, "backend_v", lambda _: dr.JitBackend.CUDA)
    assert texture.begin_tracing(scene) is False


def test_traced_blocks_serve_your_own_differentiable_renders(granite_32_file):
    """mitsuba_plugin.traced_renders: a prb render's loss and gradient with respect to the sky
    equal the path integrator's in wavefront mode (where Warp serves every lookup); a
    cold block synthesizes what it missed and raises MissedVoxels, then runs clean."""
    import drjit as dr

    scene, _ = lit_plane(granite_32_file)
    params = mi.traverse(scene)
    key = "light.radiance.value"

    def loss_and_gradient(integrator=None) -> tuple[float, np.ndarray]:
        dr.enable_grad(params[key])
        params.update()
        image = mi.render(scene, params, spp=4, seed=0, integrator=integrator)
        loss = dr.mean(image, axis=None)
        dr.backward(loss)
        grad = np.array(dr.grad(params[key]))
        dr.disable_grad(params[key])
        return float(np.ravel(loss)[0]), grad

    prb = mi.load_dict({"type": "prb", "max_depth": 4})
    with (pytest.raises(mitsuba_plugin.MissedVoxels, match="run the block again"),
          mitsuba_plugin.traced_renders(scene)):
        loss_and_gradient(prb)
    for _ in range(mitsuba_plugin.TRACED_ROUNDS):  # later bounces reach further bricks
        try:
            with mitsuba_plugin.traced_renders(scene):
                traced = loss_and_gradient(prb)
            break
        except mitsuba_plugin.MissedVoxels:
            continue
    else:
        pytest.fail(f"still missing voxels after {mitsuba_plugin.TRACED_ROUNDS} blocks")
    with mitsuba_plugin.wavefront():
        reference = loss_and_gradient(mi.load_dict({"type": "path", "max_depth": 4}))
    assert traced[0] > 0.05 and (traced[1] > 0).all()
    np.testing.assert_allclose(traced[0], reference[0], rtol=1e-4)
    np.testing.assert_allclose(traced[1], reference[1], rtol=1e-3)


def test_the_readme_optimization_loop_runs_as_written(granite_32_file, monkeypatch):
    """README's loop of differentiable renders: steps whose new seeds miss voxels run again
    with cleared gradients, so the sky it optimizes takes the same steps as when every
    voxel was stored beforehand."""
    import re
    from pathlib import Path

    import drjit as dr

    readme = (Path(__file__).parents[1] / "README.md").read_text()
    (loop,) = [block for block in re.findall(r"```python\n(.*?)```", readme, re.S)
               if "traced_renders" in block]
    loop = loop.replace("range(100)", "range(3)")
    scene, _ = lit_plane(granite_32_file, integrator="prb", scale=60.0)
    params = mi.traverse(scene)
    key = "light.radiance.value"
    kind = type(params[key])
    start = kind(params[key])
    missed = []
    original = mitsuba_plugin.MissedVoxels

    class Counted(original):
        def __init__(self, *args):
            missed.append(args)
            super().__init__(*args)

    monkeypatch.setattr(mitsuba_plugin, "MissedVoxels", Counted)

    def run() -> np.ndarray:
        params[key] = kind(start)
        params.update()
        opt = mi.ad.SGD(lr=0.5)  # steps proportional to the gradients, unlike Adam's
        opt[key] = params[key]
        params.update(opt)
        exec(loop, {"mi": mi, "dr": dr, "mitsuba_plugin": mitsuba_plugin, "scene": scene,
                    "params": params, "opt": opt,
                    "loss": lambda image: dr.mean(dr.square(image - 0.3), axis=None)})
        return np.array(params[key])

    cold = run()
    assert missed, "the seeds after the first read no voxel the first render had not stored"
    missed.clear()
    warm = run()
    assert not missed
    assert not np.allclose(warm, np.array(start))
    np.testing.assert_allclose(cold, warm, rtol=1e-5)


def test_traced_blocks_end_their_tracing_and_do_not_nest(granite_32_file, monkeypatch):
    scene, texture = lit_plane(granite_32_file)
    # The block's own error comes through, not a MissedVoxels.
    with pytest.raises(KeyError, match="raised in the block"), \
            mitsuba_plugin.traced_renders(scene):
        raise KeyError("raised in the block")
    assert_plain_render_refused(scene)  # outside the block, symbolic evals raise again
    with pytest.raises(RuntimeError, match=r"cannot run inside a traced_renders\(\) block"), \
            mitsuba_plugin.traced_renders(scene):
        mitsuba_plugin.render(scene, spp=1)
    monkeypatch.setattr(type(texture), "begin_tracing", lambda self, scene, own=True: False)
    with pytest.raises(RuntimeError, match="cannot be traced"), \
            mitsuba_plugin.traced_renders(scene):
        pass

    def failing(self, scene, own=True):
        raise MemoryError("while mirroring the store")

    # A texture failing to start tracing leaves nothing traced and nothing locked.
    monkeypatch.setattr(type(texture), "begin_tracing", failing)
    with pytest.raises(MemoryError), mitsuba_plugin.traced_renders(scene):
        pass
    monkeypatch.undo()
    assert_plain_render_refused(scene)
    assert mitsuba_plugin.render(scene, spp=1).shape[0] > 0


@pytest.mark.parametrize("variant", ["scalar_rgb", LLVM])
def test_light_tracing_reads_an_object_space_light_in_its_shape_s_frame(granite_32_file,
                                                                        variant):
    """Mitsuba's area lights emit ptracer's rays from points that carry no shape: an
    object-space texture as a light's radiance was read there in world space. Read in its
    shape's frame, it is the world-space texture placed by the shape's own to_world."""
    mi.set_variant(variant)
    mitsuba_plugin.register()
    T = mi.ScalarTransform4f
    place = T().translate([5.0, 0.0, 0.0])

    def image(**placing) -> np.ndarray:
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "ptracer", "max_depth": 2},
            "sensor": {"type": "perspective", "fov": 20,
                       "to_world": T().look_at(origin=[5, 0, 5], target=[5, 0, 0],
                                               up=[0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 8, "height": 8,
                                "rfilter": {"type": "box"}}},
            "rect": {"type": "rectangle", "to_world": place,
                     "emitter": {"type": "area", "radiance": {
                         "type": "lazy_solid", "exemplar": str(granite_32_file), "scale": 4.0,
                         "filter": "nearest", **placing}}}})
        return scene, np.array(mitsuba_plugin.render(scene, spp=16))

    scene, in_object_space = image(space="object")
    # A plain render reads them in world space, also after mitsuba_plugin.render, which
    # sets the frame for its own renders only (later plain renders took it too).
    with mitsuba_plugin.wavefront():
        plain = np.array(mi.render(scene, spp=16))
    np.testing.assert_allclose(in_object_space, image(to_world=place)[1], rtol=1e-5,
                               atol=1e-6)
    in_world_space = image()[1]
    assert not np.allclose(in_object_space, in_world_space, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(plain, in_world_space, rtol=1e-5, atol=1e-6)
    # A render that ends while another goes on (a preview) leaves the other its frame.
    steady = np.array(mitsuba_plugin.render(scene, spp=16, batches=2))

    def preview(done: int, total: int) -> None:
        if done == 1:
            mitsuba_plugin.render(scene, spp=1)

    overlapped = np.array(mitsuba_plugin.render(scene, spp=16, batches=2, progress=preview))
    np.testing.assert_allclose(overlapped, steady, rtol=1e-5, atol=1e-6)
