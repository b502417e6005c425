"""Rendering with lazy_solid: exemplar colors in pixels, the same color from two cameras,
agreement with Mitsuba's own gridvolume texture, and the bundled scene."""

from __future__ import annotations

import errno
import json
import os
import re
from datetime import datetime
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mitsuba_plugin
import warptex

REPO = Path(__file__).resolve().parent.parent
LLVM = "llvm_ad_rgb"
SCALE = 4.0  # voxels per unit: the 8x8 film over [-1, 1]^2 puts one voxel in each pixel


@pytest.fixture(scope="module")
def synthesizer(granite_32_file, warp_device):
    """The engine with the plugin's default seed and jitter, for expected colors."""
    from warptex.texture import SolidTexture

    return SolidTexture(granite_32_file, device=warp_device).synthesizer


def use(variant: str) -> None:
    if variant == LLVM and variant != warptex.best_mitsuba_variant():
        pytest.skip("llvm_ad_rgb needs libLLVM >= 16 (see warptex/llvm.py)")
    mi.set_variant(variant)
    mitsuba_plugin.register()


def lazy(path, filter: str = "nearest") -> dict:
    return {"type": "lazy_solid", "exemplar": str(path), "scale": SCALE,
            "filter": filter}


def rgb(image) -> np.ndarray:
    return np.array(image)[..., :3]


def pixel_voxels(size: int = 8) -> np.ndarray:
    """Voxel (x, y, z) seen at each pixel of a ``plane_scene`` (conftest): image rows go
    down in y."""
    x = np.arange(size) - size // 2
    y = size // 2 - 1 - np.arange(size)
    grid = np.stack(np.meshgrid(x, y, indexing="xy"), -1)
    return np.concatenate([grid, np.zeros((size, size, 1), int)], -1)


@pytest.mark.parametrize("variant", ["scalar_rgb", LLVM])
def test_pixels_carry_the_synthesized_voxels(granite_32_file, synthesizer, srgb_decoded,
                                              variant, plane_scene):
    use(variant)
    image = rgb(mitsuba_plugin.render(plane_scene(lazy(granite_32_file), emissive=True)))
    voxels = pixel_voxels().reshape(-1, 3)
    expected = srgb_decoded(synthesizer.voxels(voxels).reshape(8, 8, -1)[..., :3])
    np.testing.assert_allclose(image, expected, atol=1e-5)
    # granite: warm colors, red > green > blue on average, linear (sRGB 0.4-0.6: 0.13-0.32)
    mean = image.reshape(-1, 3).mean(0)
    assert 0.08 < mean[2] < mean[1] < mean[0] < 0.5
    assert image.std() > 0.01


def test_two_cameras_agree_at_shared_points(granite_32_file, plane_scene):
    use(LLVM)
    left = rgb(mitsuba_plugin.render(plane_scene(lazy(granite_32_file, "trilinear"), True, x=0.0,
                                                 size=16, spp=16)))
    right = rgb(mitsuba_plugin.render(plane_scene(lazy(granite_32_file, "trilinear"), True, x=0.5,
                                                  size=16, spp=16), seed=7))
    # 0.5 units = 4 pixels of 0.125: the right camera's column c is the left's c + 4.
    np.testing.assert_allclose(right[:, :-4], left[:, 4:], atol=0.02)
    assert np.abs(right[:, :-4] - left[:, 4:]).mean() < 0.004


def gridvolume(synthesizer, decoded, origin=(-6, -6, -2), shape=(12, 12, 4)) -> dict:
    """Mitsuba's ``volume`` texture over a ``gridvolume`` of the same synthesized voxels,
    ``decoded`` to linear as the plugin decodes them (a grid holds linear values)."""
    box = decoded(synthesizer.box(origin, shape)[..., :3])
    data = mi.TensorXf(np.ascontiguousarray(box.transpose(2, 1, 0, 3)))  # z, y, x, C
    place = mi.ScalarTransform4f().scale(1 / SCALE).translate(list(origin)).scale(list(shape))
    return {"type": "volume", "volume": {"type": "gridvolume", "data": data,
                                         "to_world": place, "filter_type": "trilinear"}}


def test_matches_gridvolume_texture_of_the_same_voxels(granite_32_file, synthesizer,
                                                       srgb_decoded, plane_scene):
    """Same scene, same seed, Mitsuba's grid texture instead: equal within MC noise."""
    use(LLVM)
    ours = plane_scene(lazy(granite_32_file, "trilinear"), emissive=False, size=16, spp=16)
    theirs = plane_scene(gridvolume(synthesizer, srgb_decoded), emissive=False, size=16, spp=16)
    a = rgb(mitsuba_plugin.render(ours))
    b = rgb(mitsuba_plugin.render(theirs))
    assert a.mean() > 0.1 and np.abs(a - b).mean() < 0.01
    np.testing.assert_allclose(a.mean((0, 1)), b.mean((0, 1)), atol=0.01)


def test_bundled_bunny_scene_renders():
    """scenes/bunny_wood.xml, the README's scene, at a tiny size."""
    use(warptex.best_mitsuba_variant())
    scene = mi.load_file(str(REPO / "scenes" / "bunny_wood.xml"), width=16, height=16, spp=2)
    calls = []
    image = rgb(mitsuba_plugin.render(scene, batches=2,
                                      progress=lambda *done: calls.append(done)))
    assert np.isfinite(image).all() and image.mean() > 0.05
    assert calls == [(0, 2), (1, 2), (2, 2)]  # a bar shows before the first batch ends


def test_bundled_medium_scene_renders_its_wood_albedo():
    """scenes/wood_medium.xml: lazy_solid_medium scatters with the texture's colours (the
    rosewood is red), also after the plugins were registered for another variant, and
    names its property when the albedo is not a lazy_solid."""
    for variant in (warptex.best_mitsuba_variant(), "scalar_rgb", warptex.best_mitsuba_variant()):
        use(variant)  # the plugin modules are reloaded for each new variant
    scene = mi.load_file(str(REPO / "scenes" / "wood_medium.xml"), width=32, height=32, spp=4)
    image = rgb(mitsuba_plugin.render(scene))
    assert np.isfinite(image).all()
    # Inside the cube, away from its edges, where the sky shows more than the dark wood.
    red, _, blue = image[14:18, 14:18].reshape(-1, 3).mean(axis=0)
    assert red > 1.5 * blue
    red, _, blue = image[:5].reshape(-1, 3).mean(axis=0)  # the grey floor behind
    assert red < 1.2 * blue
    with pytest.raises(RuntimeError, match='lazy_solid_medium: property "albedo" must be'):
        mi.load_dict({"type": "lazy_solid_medium", "albedo": {"type": "checkerboard"}})
    wood = REPO / "scenes" / "textures" / "wood_rosewood_64.png"
    albedo = {"type": "lazy_solid", "exemplar": str(wood)}
    for name, value in (("sigma_t", -1.0), ("sigma_t", float("inf")), ("sigma_t", -2),
                        ("scale", "dense"), ("scale", -1.0)):
        with pytest.raises(RuntimeError, match=f'lazy_solid_medium: property "{name}" must'):
            mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo, name: value})
    with pytest.raises(RuntimeError, match='lazy_solid_medium: property "phase" must be given '
                       "once, got 2"):
        mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo,
                      "front": {"type": "hg"}, "back": {"type": "isotropic"}})
    with pytest.raises(RuntimeError, match='lazy_solid_medium: property "phase" must be a '
                       r"nested phase function \(<phase \.\.\.>\), got 'hg'"):
        mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo, "phase": "hg"})
    with pytest.raises(RuntimeError, match='lazy_solid_medium: property "bsdf" must be a '
                       "nested phase function"):
        mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo, "bsdf": {"type": "diffuse"}})
    for typo, value, meant in (("sigmat", 2.0, "sigma_t"), ("albedoo", albedo, "albedo")):
        with pytest.raises(RuntimeError, match=f'lazy_solid_medium: property "{typo}" is no '
                           f'property of lazy_solid_medium; did you mean "{meant}"'):
            mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo, typo: value})
    with pytest.raises(RuntimeError, match='lazy_solid_medium: property "sigma_t" must be a '
                       r"<float \.\.\.>, a colour or a nested volume, got 'six'"):
        mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo, "sigma_t": "six"})
    for name in ("albedo", "sigma_t"):
        with pytest.raises(RuntimeError, match=f'lazy_solid_medium: property "{name}" is a '
                           'lazy_solid of space="object", which a medium cannot follow'):
            mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo,
                          name: dict(albedo, space="object")})
    with pytest.raises(RuntimeError, match='lazy_solid_medium: property "sigma_t" is a '
                       "Checkerboard texture, which Mitsuba's media read at one point only"):
        mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo,
                      "sigma_t": {"type": "checkerboard"}})
    with pytest.raises(RuntimeError, match='lazy_solid_medium: property "scale" must be a '
                       r"<float \.\.\.>, got a nested "):
        mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo,
                      "scale": {"type": "constvolume", "value": 2.0}})
    quiet = mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo,
                          "sigma_t": {"type": "constvolume", "value": 2.0},
                          "sample_emitters": False})
    coloured = mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo,
                             "sigma_t": {"type": "rgb", "value": [0.5, 0.4, 0.3]}})
    assert "sigma_t" in str(coloured)  # an <rgb> sigma_t, as Mitsuba's heterogeneous takes
    for value, shown in (([1.0, 2.0, 3.0], "1, 2, 3"), ([float("nan"), 1.0, 1.0], "nan, 1, 1")):
        with pytest.raises(RuntimeError, match=r'lazy_solid_medium: property "sigma_t" must be a '
                           rf"colour of channels within \[0, 1\].*got {shown}"):
            mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo,
                          "sigma_t": {"type": "rgb", "value": value}})
    assert not quiet.use_emitter_sampling()
    assert mi.load_dict({"type": "lazy_solid_medium", "albedo": albedo}).use_emitter_sampling()


def _medium_cube_scene(medium: dict, spp: int = 2, depth: int = 8) -> mi.Scene:
    """The cube [-1, 1]^3 filled with ``medium``, seen from +z under a white sky."""
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "volpath", "max_depth": depth},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0],
                                                              up=[0, 1, 0]),
                   "sampler": {"type": "independent", "sample_count": spp},
                   "film": {"type": "hdrfilm", "width": 8, "height": 8,
                            "rfilter": {"type": "box"}}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}},
        "cube": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium}})


@pytest.mark.filterwarnings("ignore:lazy_solid.*image is constant")
def test_the_medium_fills_its_shape_as_a_homogeneous_one(tmp_path):
    """Mitsuba's heterogeneous medium exists only within its sigma_t volume's box, the unit
    cube [0, 1]^3 unless placed: lazy_solid_medium filled an eighth of a cube [-1, 1]^3
    (and of the bundled scene's block). Of one colour everywhere, it now renders as
    Mitsuba's homogeneous medium of that colour, the same samples giving the same pixels.
    (The box is Mitsuba's C++ in every variant; the scalar ones render this slowly.)"""
    from PIL import Image

    use(LLVM)
    flat = tmp_path / "flat.png"
    Image.fromarray(np.full((32, 32, 3), (200, 120, 60), np.uint8)).save(flat)
    albedo = mi.ScalarColor3f(warptex.srgb.srgb_to_linear(
        np.array([200, 120, 60], np.float32) / 255))
    lazy_texture = {"type": "lazy_solid", "exemplar": str(flat)}
    homogeneous = rgb(mitsuba_plugin.render(_medium_cube_scene(
        {"type": "homogeneous", "albedo": {"type": "rgb", "value": albedo}, "sigma_t": 2.0})))
    for sigma_t, scale in ((2.0, 1.0), ({"type": "rgb", "value": [0.5, 0.5, 0.5]}, 4.0)):
        lazy_medium = {"type": "lazy_solid_medium", "albedo": lazy_texture, "sigma_t": sigma_t,
                       "scale": scale}
        np.testing.assert_allclose(rgb(mitsuba_plugin.render(_medium_cube_scene(lazy_medium))),
                                   homogeneous, rtol=1e-5, atol=1e-6)


def test_the_medium_is_there_far_from_the_origin_as_a_homogeneous_one_is():
    """Its volumes spanned +-1e7 units: a ray starting further out found no medium."""
    use("scalar_rgb")
    wood = REPO / "scenes" / "textures" / "wood_rosewood_64.png"
    lazy = mi.load_dict({"type": "lazy_solid_medium", "sigma_t": 1.0,
                         "albedo": {"type": "lazy_solid", "exemplar": str(wood)}})
    homogeneous = mi.load_dict({"type": "homogeneous", "albedo": 0.5, "sigma_t": 1.0})
    for x in (0.0, 1.01e7, -3e8, 1e11):
        ray = mi.Ray3f(mi.Point3f(x, 0.0, 0.0), mi.Vector3f(1.0, 0.0, 0.0))
        ray.maxt = 100.0
        found = [medium.sample_interaction(ray, 0.5, 0, True) for medium in (lazy, homogeneous)]
        assert [(bool(m.is_valid()), float(m.t)) for m in found] == [(True, found[1].t)] * 2


def test_a_lazy_solid_sigma_t_of_negative_values_is_refused(tmp_path):
    use("scalar_rgb")
    values = np.random.default_rng(0).uniform(-0.7, 3.0, (32, 32, 3)).astype(np.float32)
    np.save(tmp_path / "signed.npy", values)
    wood = REPO / "scenes" / "textures" / "wood_rosewood_64.png"
    with pytest.raises(RuntimeError, match='lazy_solid_medium: property "sigma_t" is a lazy_solid '
                       r"whose exemplar holds negative values \(down to -0\.6"):
        mi.load_dict({"type": "lazy_solid_medium",
                      "albedo": {"type": "lazy_solid", "exemplar": str(wood)},
                      "sigma_t": {"type": "lazy_solid", "exemplar": str(tmp_path / "signed.npy")}})


def test_zero_extinction_and_scale_are_taken_as_mitsubas_media_take_them(tmp_path):
    """A vacuum is a medium too: sigma_t and scale of 0, and a lazy_solid sigma_t whose
    exemplar holds zeros (clear gaps in smoke), load; just below zero does not."""
    use("scalar_rgb")
    values = np.random.default_rng(0).uniform(0.5, 3.0, (32, 32, 3)).astype(np.float32)
    values[:4] = 0.0
    np.save(tmp_path / "gaps.npy", values)
    wood = REPO / "scenes" / "textures" / "wood_rosewood_64.png"
    albedo = {"type": "lazy_solid", "exemplar": str(wood)}
    for sigma_t, scale in ((0.0, 1.0), (2.0, 0.0),
                           ({"type": "lazy_solid", "exemplar": str(tmp_path / "gaps.npy")}, 1.0)):
        medium = mi.load_dict({"type": "lazy_solid_medium", "albedo": dict(albedo),
                               "sigma_t": sigma_t, "scale": scale})
        assert not medium.is_homogeneous()  # loaded, its albedo varying
    for name, value in (("sigma_t", -1e-9), ("scale", -1e-9)):
        with pytest.raises(RuntimeError, match=f'lazy_solid_medium: property "{name}" must be '
                                               "finite and not negative, got -1e-09"):
            mi.load_dict({"type": "lazy_solid_medium", "albedo": dict(albedo), name: value})


def test_a_lazy_solid_sigma_t_varies_with_the_point_as_the_texture_does():
    """Mitsuba's texture-to-volume conversion reads a texture at p = 0 only: a lazy_solid
    sigma_t was the texture's colour at the origin everywhere."""
    use("scalar_rgb")
    wood = REPO / "scenes" / "textures" / "wood_rosewood_64.png"
    texture = {"type": "lazy_solid", "exemplar": str(wood), "filter": "nearest"}
    medium = mi.load_dict({"type": "lazy_solid_medium", "albedo": dict(texture),
                           "sigma_t": dict(texture)})
    reference = mi.load_dict(texture)
    seen = []
    for p in ((0.0, 0.0, 0.0), (0.3, 0.1, 0.2), (0.7, -0.4, 0.5)):
        mei = mi.MediumInteraction3f()
        mei.p, mei.medium = mi.Point3f(*p), medium
        _, _, sigma_t = medium.get_scattering_coefficients(mei)
        it = mi.SurfaceInteraction3f()
        it.p = mi.Point3f(*p)
        np.testing.assert_allclose(np.ravel(sigma_t), np.ravel(reference.eval(it)), rtol=1e-6)
        seen.append(tuple(np.ravel(sigma_t)))
    assert len(set(seen)) == 3


def test_medium_takes_a_nested_phase_function_and_an_integer_sigma_t():
    """Like Mitsuba's own media: a phase function nested in the scene (isotropic without),
    and <integer name="sigma_t" .../> as well as a float."""
    use("scalar_rgb")
    wood = REPO / "scenes" / "textures" / "wood_rosewood_64.png"
    xml = ('<scene version="3.0.0"><medium type="lazy_solid_medium" id="m">'
           f'<texture type="lazy_solid" name="albedo"><string name="exemplar" value="{wood}"/>'
           '</texture><integer name="sigma_t" value="6"/>{phase}</medium>'
           '<shape type="sphere"><ref name="interior" id="m"/></shape></scene>')
    for phase, expected in (('<phase type="hg"><float name="g" value="0.7"/></phase>', "g = 0.7"),
                            ("", "IsotropicPhaseFunction")):
        scene = mi.load_string(xml.replace("{phase}", phase))
        (shape,) = scene.shapes()
        medium = shape.interior_medium()
        assert expected in str(medium.phase_function())
        assert "UniformSpectrum[value=6.000000]" in str(medium)


def test_render_refuses_arguments_mitsuba_would_fail_on_deep_inside():
    """mitsuba_plugin.render, textures and save_caches: one error naming the argument, not
    a ZeroDivisionError or Dr.Jit's words."""
    use("scalar_rgb")
    scene = mi.load_file(str(REPO / "scenes" / "bunny_wood.xml"), width=4, height=4)
    for kwargs, error, words in (
            ({"spp": 0}, ValueError, "spp must be positive, got 0"),
            ({"spp": 2**32}, ValueError, "spp must be at most 4294967295 (Mitsuba counts"),
            ({"spp": 2.5}, TypeError, "spp must be an integer, got 2.5"),
            ({"batches": 0}, ValueError, "batches must be positive, got 0"),
            ({"seed": -1}, ValueError, "seed must be 0 to 4294967295 for 1 batch, got -1"),
            ({"spp": 4, "batches": 4, "seed": 2**30}, ValueError,
             "seed must be 0 to 1073741823 for 4 batches, got 1073741824")):
        with pytest.raises(error, match=re.escape(words)):
            mitsuba_plugin.render(scene, **kwargs)
    for call in (mitsuba_plugin.render, mitsuba_plugin.textures, mitsuba_plugin.save_caches):
        with pytest.raises(TypeError, match="scene must be a loaded Mitsuba scene"):
            call("scenes/bunny_wood.xml")
    (texture,) = mitsuba_plugin.textures(scene)  # a part of a scene is no scene to render
    with pytest.raises(TypeError, match="scene must be a loaded Mitsuba scene"):
        mitsuba_plugin.render(texture)
    assert mitsuba_plugin.render(scene, spp=2, batches=2, seed=2**31 - 1).shape == (4, 4, 3)
    other = warptex.best_mitsuba_variant()
    if other != "scalar_rgb":  # a scene of the variant set before: its variant is the fault
        use(other)
        with pytest.raises(TypeError, match="scene was loaded under another Mitsuba variant "
                           f"than the current one, {other}: load it again"):
            mitsuba_plugin.render(scene)


def test_render_keeps_the_samplers_count_and_its_stratification(tmp_path, capsys):
    """Batches set the scene's sampler to their share of the samples: the next render that
    took the scene's count rendered fewer. A stratified sampler rounded each batch's share
    up (2 to 4): eight batches took 32 samples where 16 were asked, stratified batch by
    batch; it now renders one batch, and a count it would round is refused."""
    from warptex.cli import main

    use("scalar_rgb")
    scene = mi.load_file(str(REPO / "scenes" / "bunny_wood.xml"), width=4, height=4, spp=12)
    sampler = mitsuba_plugin.first_sensor(scene).sampler()
    calls = []
    mitsuba_plugin.render(scene, batches=4, progress=lambda *done: calls.append(done))
    assert calls[-1] == (4, 4) and sampler.sample_count() == 12
    xml = (REPO / "scenes" / "bunny_wood.xml").read_text()
    stratified = tmp_path / "stratified.xml"
    assert 'type="independent"' in xml
    stratified.write_text(xml.replace('type="independent"', 'type="stratified"')
                          .replace('value="meshes/', f'value="{REPO}/scenes/meshes/')
                          .replace('value="textures/', f'value="{REPO}/scenes/textures/'))
    scene = mi.load_file(str(stratified), width=4, height=4, spp=16)
    calls.clear()
    mitsuba_plugin.render(scene, batches=8, progress=lambda *done: calls.append(done))
    assert calls == [(0, 1), (1, 1)]
    with pytest.raises(ValueError, match="10 samples per pixel: the scene's StratifiedSampler "
                                         "takes 16 when asked for 10; ask for 16"):
        mitsuba_plugin.render(scene, spp=10)
    out = tmp_path / "s.exr"
    assert main(["render", str(stratified), "-o", str(out), "--res", "4x4", "--spp", "4"]) == 0
    assert json.loads(out.with_name("s.exr.json").read_text())["spp"] == 4
    assert "rendering: batch 1/1\n" in capsys.readouterr().err
    assert main(["render", str(stratified), "-o", str(out), "--res", "4x4", "--spp", "5"]) == 2
    assert "5 samples per pixel: the scene's StratifiedSampler takes 9" in capsys.readouterr().err
    # Without --spp, the scene's own count, as rendered, is what the report records.
    assert main(["render", str(stratified), "-o", str(out), "--res", "4x4"]) == 0
    assert json.loads(out.with_name("s.exr.json").read_text())["spp"] == 16


def test_the_size_check_counts_the_largest_batch_a_render_makes():
    """`warptex render` refuses, before loading, a film whose largest batch Dr.Jit could
    not hold: the share it counts is the largest the render takes."""
    from mitsuba_plugin.command import _samples_per_batch
    from warptex.settings import RENDER_BATCHES

    use("scalar_rgb")
    sampler = mi.load_dict({"type": "independent"})
    for total in (*range(1, 3 * RENDER_BATCHES), 1000, 4097):
        shares = mitsuba_plugin._batch_shares(sampler, total, RENDER_BATCHES)
        assert _samples_per_batch(total) == max(shares), total


def test_batches_are_renders_of_their_shares_with_their_own_seeds_weighted_by_share():
    """render(spp=3, batches=2, seed=5) is Mitsuba's render of 2 samples with seed 10 and of
    1 sample with seed 11, weighted 2:1, as render's documentation says: batches sharing
    a seed (their noise averages to nothing), shares that drop the remainder, batches
    weighted alike or batches of no samples passed the tests before."""
    use("scalar_rgb")
    scene = mi.load_file(str(REPO / "scenes" / "bunny_wood.xml"), width=4, height=4)
    image = rgb(mitsuba_plugin.render(scene, spp=3, batches=2, seed=5))
    # Every voxel is stored now, and a scalar variant's mi.render works on any scene.
    two, one = (rgb(mi.render(scene, spp=spp, seed=seed)) for spp, seed in ((2, 10), (1, 11)))
    assert np.abs(two - one).max() > 0.01  # the seeds and counts make visible noise
    np.testing.assert_allclose(image, (2 * two + one) / 3, rtol=1e-5, atol=1e-6)
    # More batches than samples per pixel: as many batches as samples, here one (seed 11).
    np.testing.assert_allclose(rgb(mitsuba_plugin.render(scene, spp=1, batches=3, seed=11)),
                               one, rtol=1e-5, atol=1e-6)


def test_render_refuses_what_it_could_not_write_or_would_overwrite_once_loaded(
        granite_32_file, tmp_path, capsys, monkeypatch):
    """Checked on the loaded scene, before rendering: a film of arbitrary outputs (an aov
    integrator) written to a .png failed after the render as a write error; an exemplar
    that the scene's text does not show (found by Mitsuba's file resolver) is no output."""
    import shutil

    import mitsuba_plugin.command
    from warptex.cli import main

    exemplar = tmp_path / "granite.png"
    shutil.copy(granite_32_file, exemplar)
    aov = ('<integrator type="aov"><string name="aovs" value="dd.y:depth"/>'
           '<integrator type="path"/></integrator>')
    scene = tmp_path / "scene.xml"
    scene.write_text(
        f'<scene version="3.0.0">{aov}<sensor type="perspective"><film type="hdrfilm">'
        '<integer name="width" value="4"/><integer name="height" value="4"/></film></sensor>'
        '<shape type="sphere"><bsdf type="diffuse"><texture type="lazy_solid" '
        f'name="reflectance"><string name="exemplar" value="{exemplar}"/></texture></bsdf>'
        '</shape></scene>')
    assert main(["render", str(scene), "-o", str(tmp_path / "r.png"), "--spp", "1"]) == 2
    assert "r.png: the film holds arbitrary outputs (" in capsys.readouterr().err
    assert main(["render", str(scene), "-o", str(tmp_path / "r.exr"), "--spp", "1"]) == 0
    before = exemplar.read_bytes()
    monkeypatch.setattr(mitsuba_plugin.command, "scene_files", lambda *a: [])
    scene.write_text(scene.read_text().replace(aov, '<integrator type="path"/>'))
    assert main(["render", str(scene), "-o", str(exemplar), "--spp", "1"]) == 2
    assert (f"{exemplar}: would overwrite {exemplar}, which a lazy_solid texture reads"
            in capsys.readouterr().err)
    assert exemplar.read_bytes() == before
    from PIL import Image  # the feature mask it reads as well

    mask = tmp_path / "mask.png"
    Image.fromarray(np.where(np.arange(32)[:, None] < 16, 255, 0).astype(np.uint8)
                    .repeat(32, axis=1)).save(mask)
    before = mask.read_bytes()
    scene.write_text(scene.read_text().replace(
        "</texture>", f'<string name="feature_mask" value="{mask}"/></texture>'))
    assert main(["render", str(scene), "-o", str(mask), "--spp", "1"]) == 2
    assert (f"{mask}: would overwrite {mask}, which a lazy_solid texture reads"
            in capsys.readouterr().err)
    assert mask.read_bytes() == before


def test_mitsubas_warnings_go_to_stderr_uncoloured(tmp_path, capfd, monkeypatch):
    """Mitsuba's logger writes to stdout, coloured even in a log: `warptex render` relays a
    render's Mitsuba lines (a monochrome film's, here) to stderr, plain, and leaves Mitsuba's
    logger as it was, and no file of it behind."""
    import tempfile

    from warptex.cli import main

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "temporary"))
    (tmp_path / "temporary").mkdir()
    use("llvm_ad_mono")
    logger = mi.logger()
    appenders = [logger.appender(i) for i in range(logger.appender_count())]
    out = tmp_path / "mono.png"
    assert main(["render", str(REPO / "scenes" / "bunny_wood.xml"), "-o", str(out),
                 "--spp", "1", "--res", "8x8", "--variant", "llvm_ad_mono"]) == 0
    stdout, stderr = capfd.readouterr()
    assert stdout.startswith(f"written: {out} ") and "Monochrome" not in stdout, stdout
    assert re.search(r"^\S+ \S+ WARN  \[HDRFilm\] Monochrome mode enabled", stderr, re.M)
    assert "\x1b[" not in stderr
    assert [logger.appender(i) for i in range(logger.appender_count())] == appenders
    assert list((tmp_path / "temporary").glob("warptex-mitsuba-log-*")) == []
    # A line Mitsuba logs while rendering, not loading, as well.
    rendering = mitsuba_plugin.render

    def logged(*args, **kwargs):
        mi.Log(mi.LogLevel.Warn, "while rendering")
        return rendering(*args, **kwargs)

    monkeypatch.setattr(mitsuba_plugin, "render", logged)
    assert main(["render", str(REPO / "scenes" / "bunny_wood.xml"), "-o", str(out),
                 "--spp", "1", "--res", "8x8", "--variant", "llvm_ad_mono"]) == 0
    stdout, stderr = capfd.readouterr()
    assert "while rendering" in stderr and "while rendering" not in stdout


def test_render_command_writes_image_and_statistics(tmp_path, capsys):
    """`warptex render`: the image and its statistics land whole, no temporary left; the
    suffix's case does not matter, though Mitsuba's writer is particular about it."""
    from mitsuba_plugin.command import RenderReport, TextureReport
    from warptex.cli import main

    out = tmp_path / "bunny.PNG"
    assert main(["render", str(REPO / "scenes" / "bunny_wood.xml"), "-o", str(out),
                 "--spp", "1", "--res", "16x16"]) == 0
    assert list(mi.Bitmap(str(out)).size()) == [16, 16]
    report = json.loads((tmp_path / "bunny.PNG.json").read_text())
    assert report["spp"] == 1 and report["format"] == 2
    assert report["parameters"] == {"width": 16, "height": 16}  # --res sets them
    assert datetime.strptime(report["date"], "%Y-%m-%dT%H:%M:%SZ")  # ISO 8601, UTC
    assert report["versions"]["mitsuba"] == mi.__version__
    assert set(report["versions"]) == {"warptex", "warptex_code", "mitsuba", "drjit", "warp",
                                       "numpy", "scipy", "python", "os"}
    (texture,) = report["textures"]
    # As documented, no more: what the render's statistics hold is what the API's types say.
    assert report.keys() == RenderReport.__annotations__.keys()
    assert texture.keys() == TextureReport.__annotations__.keys() - {"not_saved"}
    props = texture["properties"]  # the scene's lazy_solid, as a mapping
    assert [Path(e).name for e in props["exemplars"]] == ["wood_rosewood_64.png"] * 3
    assert f"seed={props['seed']}," in texture["texture"]
    assert f"passes={props['passes']}," in texture["texture"]
    assert len(props["to_world"]) == 4 and props["space"] in ("world", "object")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bunny.PNG", "bunny.PNG.json"]
    # Captured, stderr is no terminal: progress comes as lines, no carriage returns.
    assert "rendering: batch 0/1\nrendering: batch 1/1\n" in capsys.readouterr().err


def test_a_stop_while_the_render_is_written_comes_after_it_is_written_and_said(
        tmp_path, capsys, monkeypatch):
    """Ctrl-C while the image was written lost the render, or, right after the rename,
    left it in place while the command said only that it had stopped."""
    import signal

    import mitsuba_plugin.command
    from warptex import archive
    from warptex.cli import main

    write = archive.write_together

    def stopped_half_way(writes):
        signal.raise_signal(signal.SIGINT)
        write(writes)

    monkeypatch.setattr(mitsuba_plugin.command, "write_together", stopped_half_way)
    out = tmp_path / "b.png"
    assert main(["render", str(REPO / "scenes" / "bunny_wood.xml"), "-o", str(out),
                 "--spp", "1", "--res", "8x8"]) == 130
    assert list(mi.Bitmap(str(out)).size()) == [8, 8]
    captured = capsys.readouterr()
    assert f"written: {out} (8x8" in captured.out
    assert captured.err.endswith("\nwarptex: interrupted\n")


def test_render_progress_in_a_log_is_its_first_and_last_line(tmp_path, capsys, monkeypatch):
    """In a log, a render's batches are lines as a bar's redraws are: the first, at most
    one every _LOG_SECONDS (made longer than any render here), and the last."""
    from warptex import cli

    monkeypatch.setattr(cli.console, "_LOG_SECONDS", 1e9)
    assert cli.main(["render", str(REPO / "scenes" / "bunny_wood.xml"), "-o",
                     str(tmp_path / "b.png"), "--spp", "4", "--res", "8x8"]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "rendering" in line]
    assert lines == ["rendering: batch 0/4", "rendering: batch 4/4"]


def test_render_command_takes_scene_parameters_and_a_sampler_seed(tmp_path):
    """-D sets the scene's parameters (here its film's size), --sampler-seed the samples'
    seed (another image of the same scene); the report records both."""
    from warptex.cli import main

    scene = str(REPO / "scenes" / "bunny_wood.xml")
    images = {}
    for seed in (0, 5):
        out = tmp_path / f"seed{seed}.exr"
        assert main(["render", scene, "-D", "width=12", "-D", "height=8", "--spp", "2",
                     "--sampler-seed", str(seed), "-o", str(out)]) == 0
        images[seed] = np.array(mi.Bitmap(str(out)))
        report = json.loads(out.with_name(out.name + ".json").read_text())
        assert report["size"] == [12, 8] and report["sampler_seed"] == seed
        assert report["parameters"] == {"width": "12", "height": "8"}
    assert np.abs(images[0] - images[5]).max() > 1e-3  # other samples, not rounding


def test_render_command_shows_the_candidates_a_scene_precomputes(tmp_path, capsys,
                                                                 monkeypatch):
    """A scene whose exemplar is new to the candidate cache loads for seconds to minutes:
    `warptex render` shows the candidates' bar, also in a log."""
    from warptex.cli import main

    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path / "cache"))
    assert main(["render", str(REPO / "scenes" / "bunny_wood.xml"), "-o",
                 str(tmp_path / "b.png"), "--spp", "1", "--res", "8x8"]) == 0
    err = capsys.readouterr().err
    assert re.search(r"candidates: 100%", err)
    assert main(["render", str(REPO / "scenes" / "bunny_wood.xml"), "-o",
                 str(tmp_path / "b.png"), "--spp", "1", "--res", "8x8"]) == 0
    assert "candidates:" not in capsys.readouterr().err  # cached now: nothing to show


def _scene_with_cache(tmp_path: Path, cache: str) -> Path:
    """The bunny scene copied with its texture's brick store in ``cache``."""
    import shutil

    scenes = tmp_path / "scenes"
    shutil.copytree(REPO / "scenes", scenes)
    scene = scenes / "bunny_wood.xml"
    text = scene.read_text()
    seed = '<integer name="seed" value="1"/>'
    assert seed in text
    scene.write_text(text.replace(seed, f'{seed}<string name="cache" value="{cache}"/>'))
    return scene


def test_a_scenes_textures_are_found_in_its_media_and_nested_bsdfs(granite_32_file):
    """``mitsuba_plugin.textures(scene)``: a medium's albedo and a texture inside a
    two-sided BSDF, each once, and no texture of another scene."""
    use("scalar_rgb")
    medium = {"type": "lazy_solid_medium", "albedo": lazy(granite_32_file), "sigma_t": 2.0}
    shared = mi.load_dict(lazy(granite_32_file) | {"seed": 4})
    scene = mi.load_dict({"type": "scene", "a": {
        "type": "sphere", "interior": medium,
        "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": shared}}},
        "b": {"type": "cube", "bsdf": {"type": "diffuse", "reflectance": shared}}})
    other = mi.load_dict(lazy(granite_32_file))
    found = mitsuba_plugin.textures(scene)
    assert len(found) == 2 and shared in found and other not in found
    assert other in mitsuba_plugin.textures()


def test_render_command_reports_checks_and_saves_only_its_scenes_textures(tmp_path,
                                                                         granite_32_file):
    """A ``lazy_solid`` of another scene still alive in the process (a Python session's
    earlier scene) is not the rendered scene's: `warptex render` neither lists it in the
    statistics nor writes its brick store."""
    from warptex.cli import main

    use(warptex.best_mitsuba_variant())
    other_store = tmp_path / "other.wtb"
    other = mi.load_dict({"type": "scene", "shape": {
        "type": "sphere", "bsdf": {"type": "diffuse", "reflectance": lazy(granite_32_file) | {
            "cache": str(other_store)}}}})
    scene = _scene_with_cache(tmp_path, "bricks/bunny.wtb")
    out = tmp_path / "bunny.exr"
    assert main(["render", str(scene), "-o", str(out), "--spp", "1", "--res", "8x8"]) == 0
    (texture,) = json.loads((tmp_path / "bunny.exr.json").read_text())["textures"]
    assert texture["saved_to"] == str(scene.parent / "bricks" / "bunny.wtb")
    assert not other_store.exists()
    # Its own scene finds it, and saves it where it says.
    assert [Path(t.save()) for t in mitsuba_plugin.textures(other)] == [other_store]


def test_render_command_saves_the_store_and_starts_warm_from_it(tmp_path, capsys):
    """The plugin's ``cache``: `warptex render` saves the brick store, and the next render
    of the scene reads every voxel from it, to the same image, leaving the file as it was
    and saying so."""
    from warptex.cli import main

    scene = _scene_with_cache(tmp_path, "bricks/bunny.wtb")
    reports, images, printed = [], [], []
    for run in range(2):
        out = tmp_path / f"run{run}.exr"
        assert main(["render", str(scene), "-o", str(out), "--spp", "1", "--res", "16x16"]) == 0
        printed.append(capsys.readouterr().out)
        reports.append(json.loads((tmp_path / f"run{run}.exr.json").read_text())["textures"])
        images.append(rgb(mi.Bitmap(str(out))))
        mitsuba_plugin.live_textures.clear()  # as a new process would start
    store = scene.parent / "bricks" / "bunny.wtb"
    assert [r[0]["saved_to"] for r in reports] == [str(store)] * 2
    assert [r[0]["store_file"] for r in reports] == ["written", "unchanged"]
    assert f", saved to {store}" in printed[0]
    assert f", {store} unchanged (it held them all)" in printed[1] and "saved to" not in printed[1]
    cold, warm = (r[0]["store"] for r in reports)
    assert cold["voxels_added"] == cold["voxels"] > 0
    assert warm["voxels_added"] == 0 and warm["voxels"] == cold["voxels"]
    assert sum(warm["voxels_synthesized"].values()) == 0
    assert reports[1][0]["traced"]["renders_with_misses"] == 0
    # Mitsuba's film adds samples with atomics, so pixels agree to float rounding only.
    np.testing.assert_allclose(images[1], images[0], rtol=1e-5, atol=1e-6)



def test_a_render_stopped_before_its_first_batch_writes_no_empty_store(tmp_path, capsys,
                                                                       monkeypatch):
    """A Ctrl-C before anything was synthesized: no cache file is made (an empty one was,
    said to hold the voxels synthesized before stopping), and the log says why."""
    import mitsuba_plugin.command
    from warptex.cli import main

    def stopped(done: int, total: int) -> None:
        raise KeyboardInterrupt

    scene = _scene_with_cache(tmp_path, "bricks/bunny.wtb")
    monkeypatch.setattr(mitsuba_plugin.command, "_progress", stopped)
    assert main(["render", str(scene), "--res", "16x16", "--spp", "2",
                 "-o", str(tmp_path / "stopped.exr")]) == 130
    store = scene.parent / "bricks" / "bunny.wtb"
    err = capsys.readouterr().err
    assert f"warptex: brick store {store} left as it was: no voxel was synthesized yet\n" in err
    assert "holds the voxels" not in err and not store.exists()

@pytest.mark.parametrize("stop", ["Ctrl-C", "Ctrl-C in mi.render", "SIGTERM",
                                  "SIGTERM in mi.render", "read-only"])
def test_a_stopped_render_saves_its_store_for_the_next_to_start_from(tmp_path, capsys,
                                                                      monkeypatch, stop):
    """Ctrl-C or SIGTERM after a render's first batch: the voxels synthesized so far are
    saved before the command stops, so a render of those samples synthesizes nothing;
    with --read-only-stores the file is not written. Dr.Jit wraps a Ctrl-C that comes
    within mi.render (its custom operation) in a RuntimeError: that ended in a traceback,
    exit status 1 and nothing saved."""
    import mitsuba_plugin.command
    import mitsuba_plugin.traced
    from warptex.cli import main
    from warptex.cli.console import SigtermInterrupt

    scene = _scene_with_cache(tmp_path, "bricks/bunny.wtb")
    store = scene.parent / "bricks" / "bunny.wtb"
    argv = ["render", str(scene), "--res", "16x16"]
    signal = SigtermInterrupt if stop.startswith("SIGTERM") else KeyboardInterrupt
    in_render = stop.endswith("in mi.render")
    batches = []
    colors = mitsuba_plugin.traced.TracedLookup.colors

    def progress(done: int, total: int) -> None:
        if done:
            batches.append(done)
        if done == 1 and not in_render:
            raise signal

    def interrupted(self, *args, **kwargs):
        if batches:  # the second batch's render, as Python handles the signal within it
            raise signal
        return colors(self, *args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(mitsuba_plugin.command, "_progress", progress)
        patch.setattr(mitsuba_plugin.traced.TracedLookup, "colors", interrupted)
        extra = ["--read-only-stores"] if stop == "read-only" else []
        code = main([*argv, "--spp", "2", *extra, "-o", str(tmp_path / "stopped.exr")])
    assert code == (143 if stop.startswith("SIGTERM") else 130)
    assert not (tmp_path / "stopped.exr").exists()
    err = capsys.readouterr().err
    if stop == "read-only":
        assert not store.exists() and "brick store" not in err
        return
    assert f"brick store {store} holds the voxels synthesized before stopping" in err
    mitsuba_plugin.live_textures.clear()  # as a new process would start
    # The first of two batches is the render of one sample with the sampler's seed 0.
    assert main([*argv, "--spp", "1", "-o", str(tmp_path / "next.exr")]) == 0
    (report,) = json.loads((tmp_path / "next.exr.json").read_text())["textures"]
    assert report["store"]["voxels"] > 0 and report["store"]["voxels_added"] == 0


@pytest.mark.parametrize("failure", ["Mitsuba's", "the kernel cache's"])
def test_a_render_that_fails_half_way_saves_its_store_first(tmp_path, capsys, monkeypatch,
                                                            failure):
    """A RuntimeError from Mitsuba or Dr.Jit after a batch: the voxels synthesized so far
    are saved before the error is reported (they were lost); one of Warp's kernel cache,
    which Dr.Jit wraps, is the machine's failure (exit 1, the cache named), not the
    scene's."""
    import mitsuba_plugin
    from warptex.cli import main
    from warptex.warp_runtime import KernelCacheError

    render_batch = mitsuba_plugin._render_batch
    batches = []

    def failing(scene, spp, seed):
        batches.append(spp)
        if len(batches) == 2:
            if failure == "Mitsuba's":
                raise RuntimeError("[Integrator] drjit.while_loop(): out of registers")
            try:
                raise KernelCacheError("Warp cannot build the kernels of kernels.lookup in "
                                       "/cache (Read-only file system); set WARP_CACHE_PATH "
                                       "to another folder")
            except KernelCacheError as error:
                raise RuntimeError("drjit.custom(): error in the operation (see above)") from error
        return render_batch(scene, spp, seed)

    scene = _scene_with_cache(tmp_path, "bricks/bunny.wtb")
    store = scene.parent / "bricks" / "bunny.wtb"
    monkeypatch.setattr(mitsuba_plugin, "_render_batch", failing)
    code = main(["render", str(scene), "--res", "16x16", "--spp", "2",
                 "-o", str(tmp_path / "failed.exr")])
    err = capsys.readouterr().err
    assert f"brick store {store} holds the voxels synthesized before the render failed" in err
    assert store.exists() and not (tmp_path / "failed.exr").exists()
    if failure == "Mitsuba's":
        assert code == 2 and err.rstrip().endswith(
            "Mitsuba cannot render the scene: drjit.while_loop(): out of registers")
    else:
        assert code == 1 and err.rstrip().endswith(
            "warptex: error: Warp cannot build the kernels of kernels.lookup in /cache "
            "(Read-only file system); set WARP_CACHE_PATH to another folder")
    # Stores only to be read are left as they were, though the first batch (of other
    # samples) synthesized voxels they lack.
    before = store.read_bytes()
    batches.clear()
    assert main(["render", str(scene), "--res", "16x16", "--spp", "2", "--sampler-seed", "7",
                 "--read-only-stores", "-o", str(tmp_path / "failed.exr")]) == code
    assert "holds the voxels" not in capsys.readouterr().err
    assert store.read_bytes() == before


def test_a_render_stopped_while_saving_its_store_leaves_image_and_statistics_as_they_were(
        tmp_path, capsys, monkeypatch):
    """The stores are written before the image: Ctrl-C during that longest write leaves the
    last render's image beside its own statistics, not a new image beside old figures."""
    import warptex.store
    from warptex.cli import main

    scene = _scene_with_cache(tmp_path, "bricks/bunny.wtb")
    out = tmp_path / "img.exr"
    argv = ["render", str(scene), "--res", "16x16", "-o", str(out)]
    assert main([*argv, "--spp", "2"]) == 0
    before = out.read_bytes(), (tmp_path / "img.exr.json").read_bytes()
    mitsuba_plugin.live_textures.clear()

    def stopped(self, path):
        raise KeyboardInterrupt

    monkeypatch.setattr(warptex.store.BrickStore, "save", stopped)
    assert main([*argv, "--spp", "1"]) == 130
    assert (out.read_bytes(), (tmp_path / "img.exr.json").read_bytes()) == before


def test_a_store_that_cannot_be_written_does_not_cost_the_image(tmp_path, capsys, disk_full_at):
    """A full disk when the brick store is saved: the image and its statistics are written
    all the same, the statistics say why the store was not, and the command ends with 1,
    naming the store, which is left as it was."""
    from warptex.cli import main

    scene = _scene_with_cache(tmp_path, "bricks/bunny.wtb")
    store = scene.parent / "bricks" / "bunny.wtb"
    argv = ["render", str(scene), "--spp", "1"]
    assert main([*argv, "--res", "8x8", "-o", str(tmp_path / "small.exr")]) == 0
    mitsuba_plugin.live_textures.clear()
    before = store.read_bytes()
    disk_full_at(store)
    capsys.readouterr()
    out = tmp_path / "img.exr"
    assert main([*argv, "--res", "16x16", "-o", str(out)]) == 1
    message = f"{store}: cannot write (No space left on device)"
    assert capsys.readouterr().err.endswith(f"warptex: error: {message}\n")
    (entry,) = json.loads((tmp_path / "img.exr.json").read_text())["textures"]
    assert entry["not_saved"] == message and entry["saved_to"] is None
    assert rgb(mi.Bitmap(str(out))).shape == (16, 16, 3)
    assert store.read_bytes() == before


def test_statistics_that_cannot_be_written_leave_image_and_statistics_as_they_were(
        tmp_path, capsys, monkeypatch):
    """A full disk while the statistics are written: the new image is not put in place
    either, so the last render's image stays beside its own statistics; the error names
    the statistics file."""
    from warptex.cli import main

    scene = _scene_with_cache(tmp_path, "bricks/bunny.wtb")
    out = tmp_path / "img.exr"
    statistics = tmp_path / "img.exr.json"
    argv = ["render", str(scene), "--res", "16x16", "-o", str(out)]
    assert main([*argv, "--spp", "2"]) == 0
    before = out.read_bytes(), statistics.read_bytes()
    mitsuba_plugin.live_textures.clear()
    write_text = Path.write_text

    def full_for_statistics(self, *args, **kwargs):
        if self.name.startswith(f".{statistics.stem}.") and self.suffix == ".json":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
        return write_text(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full_for_statistics)
    capsys.readouterr()
    assert main([*argv, "--spp", "1"]) == 1
    assert capsys.readouterr().err.endswith(
        f"warptex: error: {statistics}: cannot write (No space left on device)\n")
    assert (out.read_bytes(), statistics.read_bytes()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["img.exr", "img.exr.json", "scenes"]


def test_a_store_file_replaced_during_the_render_is_not_overwritten(tmp_path, capsys,
                                                                    monkeypatch):
    """A file of another kind put where the brick store is saved while the scene renders:
    it is left as it is, the image and statistics are written, and the statistics and the
    exit status say why the store was not saved."""
    import mitsuba_plugin.command
    from warptex.cli import main

    scene = _scene_with_cache(tmp_path, "bricks/bunny.wtb")
    store = scene.parent / "bricks" / "bunny.wtb"

    def progress(done: int, total: int) -> None:
        store.parent.mkdir(exist_ok=True)
        store.write_text("someone's notes")

    monkeypatch.setattr(mitsuba_plugin.command, "_progress", progress)
    out = tmp_path / "img.exr"
    assert main(["render", str(scene), "--spp", "1", "--res", "16x16", "-o", str(out)]) == 1
    message = (f"{store}: exists and is not a warptex brick store file; it would be "
               "overwritten, choose another store path")
    assert capsys.readouterr().err.endswith(f"warptex: error: {message}\n")
    (entry,) = json.loads((tmp_path / "img.exr.json").read_text())["textures"]
    assert entry["not_saved"] == message and entry["saved_to"] is None
    assert rgb(mi.Bitmap(str(out))).shape == (16, 16, 3)
    assert store.read_text() == "someone's notes"


def test_render_command_reads_a_store_it_may_not_write(tmp_path, monkeypatch):
    """--read-only-stores: a store in a place that cannot be written (a shared one) is read
    and left as it was, where without it the render is refused."""
    import mitsuba_plugin.command
    from warptex.cli import main

    scene = _scene_with_cache(tmp_path, "bricks/bunny.wtb")
    argv = ["render", str(scene), "--spp", "1", "--res", "16x16"]
    assert main([*argv, "-o", str(tmp_path / "first.exr")]) == 0
    mitsuba_plugin.live_textures.clear()  # as a new process would start
    store = scene.parent / "bricks" / "bunny.wtb"
    before = store.read_bytes()
    monkeypatch.setattr(mitsuba_plugin.command, "file_problem",
                        lambda path: f"cannot write in {path.parent} (Read-only file system)"
                        if path == store else None)
    assert main([*argv, "-o", str(tmp_path / "refused.exr")]) == 2
    mitsuba_plugin.live_textures.clear()
    assert main([*argv, "--read-only-stores", "-o", str(tmp_path / "read.exr")]) == 0
    (report,) = json.loads((tmp_path / "read.exr.json").read_text())["textures"]
    assert report["saved_to"] is None and report["store"]["voxels_added"] == 0
    assert store.read_bytes() == before


def test_render_command_reads_no_store_where_a_read_only_place_has_none_yet(tmp_path, capsys,
                                                                            monkeypatch):
    """--read-only-stores with a ``cache`` not made yet in a place that cannot be written
    (a shared folder not filled yet): rendered without a store, where without the flag
    the scene is refused as its store could not be saved."""
    import mitsuba_plugin.command
    import mitsuba_plugin.texture
    from warptex.cli import main

    scene = _scene_with_cache(tmp_path, "shared/bunny.wtb")
    missing = scene.parent / "shared" / "bunny.wtb"

    def read_only(path):
        return f"cannot write in {path.parent} (Read-only file system)" if path == missing else None

    monkeypatch.setattr(mitsuba_plugin.command, "file_problem", read_only)
    monkeypatch.setattr(mitsuba_plugin.texture, "file_problem", read_only)
    argv = ["render", str(scene), "--spp", "1", "--res", "16x16"]
    assert main([*argv, "-o", str(tmp_path / "refused.exr")]) == 2
    assert 'property "cache" cannot be saved to' in capsys.readouterr().err
    mitsuba_plugin.live_textures.clear()
    assert main([*argv, "--read-only-stores", "-o", str(tmp_path / "read.exr")]) == 0
    (report,) = json.loads((tmp_path / "read.exr.json").read_text())["textures"]
    assert report["saved_to"] is None and report["store"]["voxels_added"] > 0
    assert report["properties"]["cache"] == str(missing)
    assert not missing.parent.exists()
    with mitsuba_plugin.stores_read_only():  # as loaded from Python: save() writes nothing
        loaded = mi.load_file(str(scene), width=16, height=16)
    (texture,) = mitsuba_plugin.textures(loaded)
    texture.solid.query(np.zeros((1, 3)))
    assert mitsuba_plugin.save_caches(loaded) == [] and not missing.parent.exists()


@pytest.mark.parametrize("case", ["the output", "its statistics", "read-only"])
def test_render_command_refuses_a_store_it_could_not_save_before_rendering(
        tmp_path, capsys, monkeypatch, case):
    """A ``cache`` that this render writes as its image or statistics, or that cannot be
    written, is refused before the render's work, which would be lost otherwise."""
    import mitsuba_plugin.command
    from warptex.cli import main

    out = tmp_path / "out" / "bunny.png"
    cache = {"the output": out, "its statistics": out.with_name("bunny.png.json"),
             "read-only": tmp_path / "stores" / "bunny.wtb"}[case]
    scene = _scene_with_cache(tmp_path, str(cache))
    if case == "read-only":  # root writes anywhere: the folder's answer is stood in for
        monkeypatch.setattr(mitsuba_plugin.command, "file_problem",
                            lambda path: f"cannot write in {path.parent} (Read-only file system)"
                            if path == cache else None)
    rendered = []
    monkeypatch.setattr(mitsuba_plugin, "render", lambda *a, **k: rendered.append(a))
    assert main(["render", str(scene), "-o", str(out), "--spp", "1", "--res", "16x16"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"warptex: error: {scene}: lazy_solid: property \"cache\"")
    assert ("which this render writes" in err if case != "read-only"
            else "Read-only file system" in err)
    assert rendered == [] and not out.exists() and not cache.exists()


def test_bundled_cut_sphere_scene_renders():
    """scenes/cut_sphere.xml: object-space texture on instanced halves, at a tiny size."""
    use(warptex.best_mitsuba_variant())
    before = set(mitsuba_plugin.textures())
    scene = mi.load_file(str(REPO / "scenes" / "cut_sphere.xml"), width=16, height=16, spp=2)
    image = rgb(mitsuba_plugin.render(scene))
    assert np.isfinite(image).all() and image.mean() > 0.05
    assert any(t.space == "object" and t.solid.store.stats()["voxels"] > 0
               for t in mitsuba_plugin.textures() if t not in before)


@pytest.mark.parametrize("case", ["-D spp=0", "-D width=0", "no integrator"])
def test_render_command_refuses_a_scene_mitsuba_could_not_render(tmp_path, capsys, case):
    """A scene that loads but that Mitsuba fails to render, with an error from deep inside
    it (no integrator, an empty film, no samples): one line naming what to give."""
    from warptex.cli import main

    scene = REPO / "scenes" / "bunny_wood.xml"
    extra = case.split() if case.startswith("-D") else []
    if case == "no integrator":
        scene = _scene_with_cache(tmp_path, "bricks/bunny.wtb")
        scene.write_text(re.sub(r"<integrator.*?</integrator>", "", scene.read_text(),
                                flags=re.DOTALL))
    out = tmp_path / "img.png"
    assert main(["render", str(scene), "-o", str(out), *extra]) == 2
    err = capsys.readouterr().err.splitlines()[-1]
    assert err.startswith(f"warptex: error: {scene}: ")
    assert {"-D spp=0": "the sampler takes no samples per pixel (its sample_count is 0)",
            "-D width=0": "the film is 0x256 pixels: give --res",
            "no integrator": "the scene has no <integrator>"}[case] in err
    assert not out.exists() and not out.with_name("img.png.json").exists()
    if case == "-D spp=0":  # --spp would replace the scene's count: -D would do nothing
        assert main(["render", str(scene), "-o", str(out), *extra, "--spp", "1",
                     "--res", "8x8"]) == 2
        assert "give it with -D or --spp, not both" in capsys.readouterr().err


@pytest.mark.parametrize(("folder", "stop"), [("plain", "Ctrl-C"),
                                               ("KeyboardInterrupt", "Ctrl-C"),
                                               ("plain", "SIGTERM")])
def test_render_command_interrupted_while_loading(tmp_path, capsys, monkeypatch, folder, stop):
    """Ctrl-C while a texture pre-computes its candidates is an interruption, not a scene
    error, though Mitsuba wraps what a plugin raises; a path that happens to hold the word
    does not make an error one. SIGTERM there was "cannot load the scene" and exit 2."""
    import os
    import shutil
    import signal

    from warptex.cli import main

    mitsuba_plugin.set_best_variant()
    mitsuba_plugin.register()  # as render does, before the plugin module is patched
    scenes = tmp_path / folder
    shutil.copytree(REPO / "scenes", scenes)

    def interrupted(*args, **kwargs):
        if stop == "SIGTERM":  # the command's handler raises it in this frame
            os.kill(os.getpid(), signal.SIGTERM)
        raise KeyboardInterrupt

    out = tmp_path / "out"
    argv = ["render", str(scenes / "bunny_wood.xml"), "-o", str(out / "b.png"), "--spp",
            "1", "--res", "16x16"]
    with monkeypatch.context() as patch:
        patch.setattr(mitsuba_plugin.texture, "precompute", interrupted)
        assert main(argv) == (143 if stop == "SIGTERM" else 130)
    said = "terminated" if stop == "SIGTERM" else "interrupted"
    assert capsys.readouterr().err.endswith(f"warptex: {said}\n")
    (scenes / "textures" / "wood_rosewood_64.png").write_bytes(b"broken")
    assert main(argv) == 2
    assert "cannot be used" in capsys.readouterr().err
    assert not out.exists()


def test_medium_scatters_with_the_texture_at_each_point(granite_32_file, srgb_decoded):
    """sigma_s = albedo(p) * sigma_t * scale, the albedo being the nested texture's colour
    at the medium point, channel for channel."""
    use(LLVM)
    before = set(mitsuba_plugin.textures())  # the objects: a freed one's id may be reused
    medium = mi.load_dict({"type": "lazy_solid_medium", "sigma_t": 3.0, "scale": 2.0,
                           "albedo": {"type": "lazy_solid", "exemplar": str(granite_32_file),
                                      "scale": 8.0}})
    (texture,) = [t for t in mitsuba_plugin.textures() if t not in before]
    points = np.random.default_rng(0).uniform(-1, 1, (5, 3)).astype(np.float32)
    mei = dr.zeros(mi.MediumInteraction3f, len(points))
    mei.p = mi.Point3f(*points.T)
    sigma_s, _, sigma_t = medium.get_scattering_coefficients(mei)
    albedo = np.array(sigma_s).T / 6.0
    np.testing.assert_allclose(np.array(sigma_t).T, 6.0, rtol=1e-6)
    expected = srgb_decoded(texture.solid.query(points * 8.0))
    np.testing.assert_allclose(albedo, expected, rtol=1e-5, atol=1e-6)
    # The volume the medium wraps its texture in, as RGB and as one value.
    from mitsuba_plugin.spectrum import luminance
    from mitsuba_plugin.volume import LazySolidVolume

    volume = LazySolidVolume(texture)
    assert volume.channel_count() == 3
    np.testing.assert_allclose(np.array(volume.eval_3(mei)).T, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.array(volume.eval_1(mei)),
                               np.array(luminance(mi.Color3f(*expected.T))), rtol=1e-5,
                               atol=1e-6)


def test_render_command_messages_say_what_is_so(tmp_path, capsys, monkeypatch):
    """A scene Mitsuba cannot render (ptracer through an orthographic camera) gave a
    traceback and exit 1, as for a file that could not be written; -D of a parameter the
    scene declares but never reads was asked whether it meant itself; a store file of
    another kind, only to be read, was said to be overwritten; a scene given by a bare
    file name listed "" among the folders an exemplar was looked for in."""
    from warptex.cli import main

    scene = _scene_with_cache(tmp_path, "notes.wtb")
    (scene.parent / "notes.wtb").write_text("someone's notes")
    text = scene.read_text()
    argv = ["render", str(scene), "--spp", "1", "--res", "8x8", "-o", str(tmp_path / "o.exr")]
    assert main([*argv, "--read-only-stores"]) == 2
    err = capsys.readouterr().err
    assert "exists and is not a warptex brick store file" in err and "overwritten" not in err
    assert main(argv) == 2
    assert "it would be overwritten" in capsys.readouterr().err
    mitsuba_plugin.live_textures.clear()

    plain = scene.with_name("plain.xml")
    plain.write_text(text.replace('<string name="cache" value="notes.wtb"/>', "")
                     .replace('<default name="spp"', '<default name="unread" value="1"/>'
                              '<default name="spp"'))
    assert main([*argv[:1], str(plain), *argv[2:], "-D", "unread=2"]) == 2
    err = capsys.readouterr().err
    assert "does not use: unread (declared by a <default>, but no value reads $unread)" in err
    assert "did you mean" not in err
    # Several unused: the list, no hint to any one of them.
    assert main([*argv[:1], str(plain), *argv[2:], "-D", "unread=2", "-D", "other=3"]) == 2
    assert capsys.readouterr().err.strip().endswith("does not use: other, unread")
    # Arguments refused before any loading: a --res without its x, a -D without its =.
    assert main([*argv[:1], str(plain), "--res", "8", "-o", str(tmp_path / "o.exr")]) == 2
    assert "--res must look like 256x256, got '8'" in capsys.readouterr().err
    for given in ("unread", "1x=2"):
        with pytest.raises(SystemExit) as stopped:
            main([*argv[:1], str(plain), *argv[2:], "-D", given])
        assert stopped.value.code == 2
        assert f"{given!r}: expected NAME=VALUE" in capsys.readouterr().err
    # A scene that includes itself: Mitsuba's refusal, in one line where it wraps its
    # error once per inclusion; warptex's own reading of the scene's files stops at the loop.
    looped = scene.with_name("looped.xml")
    looped.write_text(text.replace('<string name="cache" value="notes.wtb"/>', "")
                      .replace("</scene>", '<include filename="looped.xml"/></scene>'))
    assert main([*argv[:1], str(looped), *argv[2:]]) == 2
    err = capsys.readouterr().err
    assert re.fullmatch(rf"warptex: error: {re.escape(str(looped))}: cannot load the scene: "
                        rf"Error while loading {re.escape(str(looped))} \(line \d+, col \d+\): "
                        r"while processing <include>: Exceeded maximum include recursion "
                        r"depth of \d+\n", err)

    ortho = scene.with_name("ortho.xml")
    integrator = re.search(r'<integrator type="\w+"', text).group(0)
    sensor = re.search(r'<sensor type="\w+"', text).group(0)
    ortho.write_text(re.sub(r'<float name="fov"[^>]*/>', "", text)
                     .replace('<string name="cache" value="notes.wtb"/>', "")
                     .replace(integrator, '<integrator type="ptracer"')
                     .replace(sensor, '<sensor type="orthographic"'))
    assert main([*argv[:1], str(ortho), *argv[2:]]) == 2
    err = capsys.readouterr().err
    assert err.strip().endswith(f"{ortho}: Mitsuba cannot render the scene: "
                                "Endpoint::sample_direction(): not implemented!")
    assert "Traceback" not in err

    missing = scene.with_name("missing.xml")
    missing.write_text(text.replace("wood_rosewood_64.png", "nowhere.png"))
    monkeypatch.chdir(scene.parent)
    assert main(["render", missing.name, "--spp", "1", "--res", "8x8", "-o", "o.exr"]) == 2
    assert '"textures/nowhere.png" (looked for in ., ' in capsys.readouterr().err


@pytest.mark.parametrize("medium", ["homogeneous", "heterogeneous"])
def test_a_texture_in_a_medium_of_mitsubas_own_is_refused(granite_32_file, medium):
    """Mitsuba's media hold a texture as a constant volume, read at p = 0 only: the medium
    rendered one color without a word. Refused, naming lazy_solid_medium; in it, rendered."""
    use("scalar_rgb")
    texture = lazy(granite_32_file)
    own = _medium_cube_scene({"type": medium, "albedo": texture, "sigma_t": 2.0})
    with pytest.raises(ValueError, match="a lazy_solid texture is the constant volume "
                       r"\S*albedo of a medium of Mitsuba's own.*use a lazy_solid_medium"):
        mitsuba_plugin.render(own, spp=1)
    ours = _medium_cube_scene({"type": "lazy_solid_medium", "albedo": texture, "sigma_t": 2.0})
    assert rgb(mitsuba_plugin.render(ours, spp=1)).std() > 0
