"""The plugins in spectral and monochrome Mitsuba variants: Mitsuba's own upsampling of the
texture's colors, in eval, in the medium, in traced and wavefront renders, against RGB
renders of the same scene, and ``warptex render --variant``."""

from __future__ import annotations

import json
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import warp as wp

import mitsuba_plugin
import warptex
from mitsuba_plugin import spectrum

REPO = Path(__file__).resolve().parent.parent
SPECTRAL = "llvm_ad_spectral"
CUDA = "cuda_ad_spectral"


def use(variant: str) -> None:
    if variant.startswith("llvm_") and warptex.best_mitsuba_variant() != "llvm_ad_rgb":
        pytest.skip(f"{variant} needs libLLVM >= 16 (see warptex/llvm.py)")
    if variant.startswith("cuda_") and not wp.get_cuda_device_count():
        pytest.skip(f"{variant} needs a CUDA device")
    mi.set_variant(variant)
    mitsuba_plugin.register()


def load(path, **props):
    return mi.load_dict({"type": "lazy_solid", "exemplar": str(path), "scale": 8.0} | props)


def fetched(colors: np.ndarray) -> np.ndarray:
    """Mitsuba's own coefficients of each color, one scalar lookup at a time."""
    return np.array([list(mi.srgb_model_fetch(mi.ScalarColor3f(*c))) for c in colors])


@pytest.mark.parametrize("variant", [SPECTRAL, CUDA])
def test_coefficients_are_mitsubas_own_to_the_bit(variant):
    """On the CPU to the bit; CUDA's float32 division is approximate, so there within the
    tolerance that a texture's check on loading allows."""
    use(variant)
    rng = np.random.default_rng(5)
    colors = rng.uniform(-0.2, 1.2, (3000, 3))
    grays = np.concatenate([[0.0, 1.0, 1e-7, 1 - 1e-7], rng.uniform(0, 1, 60)])
    colors[:64] = grays[:, None]
    colors[64:128, 1] = colors[64:128, 0]  # two largest components equal: the tie rule
    colors[128:192, 2] = colors[128:192, 1]
    colors = colors.astype(np.float32)
    ours = np.array(spectrum.srgb_coefficients(mi.Color3f(colors.T))).T
    if variant == CUDA:
        np.testing.assert_allclose(ours, fetched(colors), rtol=1e-4, atol=1e-6)
    else:
        np.testing.assert_array_equal(ours, fetched(colors))


def _interactions(points: np.ndarray, wavelengths: np.ndarray, kind=None):
    """Interactions at ``points`` seeing ``wavelengths`` (N, 4), for a JIT variant."""
    it = dr.zeros(kind or mi.SurfaceInteraction3f, len(points))
    it.p = mi.Point3f(points.T)
    if mi.is_spectral:
        it.wavelengths = type(it.wavelengths)(wavelengths.T)
    return it


def _points_and_wavelengths(n: int = 6) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(2)
    return (rng.uniform(-1, 1, (n, 3)).astype(np.float32),
            rng.uniform(360, 830, (n, 4)).astype(np.float32))


@pytest.mark.parametrize("variant", ["scalar_spectral", SPECTRAL, "llvm_ad_spectral_polarized",
                                     CUDA])
def test_eval_is_the_upsampled_color_at_each_point(granite_32_file, srgb_decoded, variant):
    use(variant)
    tex = load(granite_32_file, seed=3, raw=True)  # the stored colors, to the bit
    points, wavelengths = _points_and_wavelengths()
    rgb = tex.solid.query(points * 8.0)[:, :3]
    coefficients = fetched(rgb)
    if dr.is_jit_v(mi.Float):
        si = _interactions(points, wavelengths)
        got = np.array(tex.eval(si)).T
        expected = np.array(mi.srgb_model_eval(mi.Vector3f(coefficients.T),
                                               si.wavelengths)).T
        np.testing.assert_array_equal(np.array(tex.eval_3(si)).T, rgb)
        np.testing.assert_allclose(np.array(tex.eval_1(si)),
                                   np.array(mi.luminance(mi.Color3f(rgb.T))), rtol=1e-6)
    else:
        si = mi.SurfaceInteraction3f()
        got, expected = [], []
        for p, w, c in zip(points, wavelengths, coefficients, strict=True):
            si.p, si.wavelengths = mi.Point3f(*p), type(si.wavelengths)(*w)
            got.append(list(tex.eval(si)))
            expected.append(list(mi.srgb_model_eval(mi.ScalarVector3f(*c), si.wavelengths)))
    # CUDA's coefficients are Mitsuba's within the tolerance of its check (see above).
    tolerance = 1e-4 if variant == CUDA else 1e-6
    np.testing.assert_allclose(got, expected, rtol=tolerance, atol=tolerance / 10)
    assert np.min(got) > 0.0 and np.max(got) < 1.0
    assert tex.max() == 1.0 > tex.largest  # spectra may exceed the largest channel, not 1
    if dr.is_jit_v(mi.Float):  # by default the decoded colors are upsampled
        decoded = load(granite_32_file, seed=3)
        np.testing.assert_allclose(np.array(decoded.eval_3(si)).T, srgb_decoded(rgb),
                                   rtol=1e-5)
        linear = fetched(srgb_decoded(rgb).astype(np.float32))
        np.testing.assert_allclose(np.array(decoded.eval(si)).T, np.array(
            mi.srgb_model_eval(mi.Vector3f(linear.T), si.wavelengths)).T, rtol=1e-4)


def test_monochrome_variants_see_luminance(granite_32_file, srgb_decoded):
    """Of the linear colors, as Mitsuba's bitmap: the exemplar's sRGB decoded first."""

    use("llvm_ad_mono")
    tex = load(granite_32_file)
    points, _ = _points_and_wavelengths()
    si = dr.zeros(mi.SurfaceInteraction3f, len(points))
    si.p = mi.Point3f(points.T)
    rgb = srgb_decoded(tex.solid.query(points * 8.0)[:, :3])
    luminance = np.array(mi.luminance(mi.Color3f(rgb.T)))
    np.testing.assert_allclose(np.array(tex.eval(si))[0], luminance, rtol=1e-5)
    # The mean is the luminance of the mean voxel color, estimated from the exemplar's
    # pixels (a voxel averages three before they are decoded); voxels synthesized agree.
    voxels = np.random.default_rng(5).uniform(-40, 40, (20000, 3))
    seen = srgb_decoded(tex.solid.query(voxels, filter="nearest")[:, :3]).mean(axis=0)
    expected = np.array(mi.luminance(mi.Color3f(*map(float, seen))))
    np.testing.assert_allclose(np.array(tex.mean()), expected, rtol=0.05)


def test_the_medium_albedo_is_upsampled_like_the_texture(granite_32_file):
    use(SPECTRAL)
    from mitsuba_plugin.volume import LazySolidVolume

    tex = load(granite_32_file)
    points, wavelengths = _points_and_wavelengths()
    albedo = LazySolidVolume(tex).eval(_interactions(points, wavelengths,
                                                     mi.MediumInteraction3f))
    surface = tex.eval(_interactions(points, wavelengths))
    np.testing.assert_array_equal(np.array(albedo), np.array(surface))


def test_a_lazy_sigma_t_is_upsampled_unbounded_as_mitsubas_gridvolume(tmp_path):
    """Extinctions above 1 keep their size in a spectral variant (the reflectance model
    clipped them to 1: a medium 5x thinner than in RGB), as Mitsuba's gridvolume of the same
    values gives them, below the medium's majorant."""
    use(SPECTRAL)
    extinctions = np.random.default_rng(0).uniform(2.0, 8.0, (32, 32, 3)).astype(np.float32)
    np.save(tmp_path / "sigma_t.npy", extinctions)
    sigma_t = load(tmp_path / "sigma_t.npy", raw=True)
    medium = mi.load_dict({"type": "lazy_solid_medium", "albedo": sigma_t,
                           "sigma_t": sigma_t})
    points, wavelengths = _points_and_wavelengths()
    it = _interactions(points, wavelengths, mi.MediumInteraction3f)
    got = np.array(medium.get_scattering_coefficients(it)[2])
    rgb = sigma_t.solid.query(points * 8.0)[:, :3]
    for i, color in enumerate(rgb):
        grid = mi.load_dict({"type": "gridvolume", "filter_type": "nearest",
                             "grid": mi.VolumeGrid(np.full((1, 1, 1, 3), color, np.float32))})
        at = _interactions(np.full((1, 3), 0.5, np.float32), wavelengths[i:i + 1],
                           mi.MediumInteraction3f)
        np.testing.assert_allclose(got[:, i], np.array(grid.eval(at)).ravel(), rtol=1e-5)
    assert got.max() > 2.0  # clipped, none passed 1
    assert (got <= np.array(medium.get_majorant(it))).all()


def test_a_mitsuba_that_upsamples_otherwise_is_refused(granite_32_file, monkeypatch):
    """Another Mitsuba release's lookup would show colors Mitsuba itself would not give:
    the texture is refused when it loads, naming the color that differs."""
    use(SPECTRAL)
    exact = spectrum.srgb_coefficients
    monkeypatch.setattr(spectrum, "srgb_coefficients", lambda rgb: exact(rgb) * 1.01)
    spectrum._check_upsampling.cache_clear()
    try:
        with pytest.raises(RuntimeError, match=r"upsamples RGB to spectra otherwise than "
                           r"warptex: for color \[.*Mitsuba gives coefficients"):
            load(granite_32_file)
    finally:
        spectrum._check_upsampling.cache_clear()


def test_a_table_that_is_not_mitsubas_whole_table_is_refused(tmp_path):
    """Read as Mitsuba reads it: a SPEC header, a resolution of at least 2 and every
    coefficient it promises (more bytes after them are ignored)."""
    mi.set_variant("scalar_spectral")
    mitsubas = str(mi.file_resolver().resolve(spectrum._TABLE))
    table = Path(mitsubas).read_bytes()
    res, scale, data = spectrum._table(mitsubas)
    assert res >= 2 and len(scale) == res and len(data) == 9 * res**3
    (tmp_path / "longer").write_bytes(table + b"more")
    assert spectrum._table(str(tmp_path / "longer"))[0] == res
    whole = 8 + 4 * (res + 9 * res**3)
    for name, content in (("truncated", table[:whole - 4]), ("other", b"CEPS" + table[4:]),
                          ("one", b"SPEC" + np.uint32(1).tobytes() + table[8:]),
                          ("header", table[:6])):
        (tmp_path / name).write_bytes(content)
        with pytest.raises(RuntimeError, match="not Mitsuba's spectral upsampling table"):
            spectrum._table(str(tmp_path / name))


@pytest.mark.parametrize("emissive", [False, True], ids=["reflectance", "radiance"])
def test_spectral_renders_are_traced_and_match_the_rgb_render(emissive, plane_scene):
    """A spectral render reads stored voxels in its traced program as the wavefront one
    does, and comes out in the colors of the RGB render of the same scene: a reflectance
    as it is, a radiance wrapped in ``d65`` as Mitsuba does with its own bitmaps."""
    wood = REPO / "scenes" / "textures" / "wood_rosewood_64.png"
    # raw: the upsampling is compared, on colors as light as the stored ones (decoded, the
    # rosewood's near-black blue strays by about 3 %; the eval tests cover the decoding).
    tex = {"type": "lazy_solid", "exemplar": str(wood), "scale": 8.0, "raw": True}
    if emissive:
        tex = {"type": "d65", "texture": tex}
    means = {}
    for variant in ("llvm_ad_rgb", SPECTRAL):
        use(variant)
        before = set(mitsuba_plugin.textures())  # the objects: a freed one's id may be reused
        scene = plane_scene(tex, emissive, size=16, spp=16)
        (texture,) = [t for t in mitsuba_plugin.textures() if t not in before]
        image = np.array(mitsuba_plugin.render(scene, spp=16))[..., :3]
        means[variant] = image.reshape(-1, 3).mean(axis=0)
    assert texture.traced_stats()["renders"] >= 2  # missed, synthesized, rendered again
    with mitsuba_plugin.wavefront():
        wavefront = np.array(mi.render(scene, spp=16, seed=0))[..., :3]
    np.testing.assert_allclose(image, wavefront, rtol=1e-5, atol=1e-6)
    red, _, blue = means["llvm_ad_rgb"]
    assert red > 2 * blue  # rosewood: a gray or blue-tinted spectral image would fail below
    np.testing.assert_allclose(means[SPECTRAL], means["llvm_ad_rgb"], rtol=0.03)


@pytest.mark.parametrize("variant", mi.variants())
def test_every_variant_registers_once_and_evaluates(granite_32_file, variant):
    """RGB, spectral and monochrome, polarized or not: a texture loads and gives values in
    (0, 1); registering again for the same variant keeps the plugin classes."""
    use(variant)
    registered = mitsuba_plugin.texture.LazySolidTexture
    mitsuba_plugin.register()
    assert mitsuba_plugin.texture.LazySolidTexture is registered
    tex = load(granite_32_file)
    points, wavelengths = _points_and_wavelengths(1)
    if dr.is_jit_v(mi.Float):
        value = np.array(tex.eval(_interactions(points, wavelengths)))
    else:
        si = mi.SurfaceInteraction3f()
        si.p = mi.Point3f(*points[0])
        if mi.is_spectral:
            si.wavelengths = type(si.wavelengths)(*wavelengths[0])
        value = np.array(list(tex.eval(si)))
    assert value.size in (1, 3, 4) and np.all((value > 0.0) & (value < 1.0))


def test_use_variant_says_what_a_variant_lacks_here(monkeypatch):
    mi.set_variant("scalar_rgb")
    with pytest.raises(ValueError, match="unknown Mitsuba variant 'llvm_rgb'; this Mitsuba"):
        mitsuba_plugin.use_variant("llvm_rgb")
    if not wp.get_cuda_device_count():
        with pytest.raises(ValueError, match="cuda_ad_spectral needs a CUDA GPU and its driver"):
            mitsuba_plugin.use_variant("cuda_ad_spectral")
        assert mi.variant() == "scalar_rgb"
    with monkeypatch.context() as mp:
        mp.setattr(mitsuba_plugin, "configure_drjit", lambda: None)
        with pytest.raises(ValueError, match="llvm_ad_mono needs libLLVM >= 16"):
            mitsuba_plugin.use_variant("llvm_ad_mono")
    assert mitsuba_plugin.use_variant("scalar_spectral") == mi.variant() == "scalar_spectral"


def test_render_command_takes_a_variant(tmp_path, capsys):
    from warptex.cli import main

    out = tmp_path / "bunny.exr"
    assert main(["render", str(REPO / "scenes" / "bunny_wood.xml"), "-o", str(out),
                 "--spp", "1", "--res", "8x8", "--variant", "scalar_spectral"]) == 0
    assert json.loads((tmp_path / "bunny.exr.json").read_text())["variant"] == "scalar_spectral"
    printed = capsys.readouterr().out
    assert "scalar_spectral" in printed and "from brick copies" in printed
    assert np.array(mi.Bitmap(str(out))).mean() > 0.05
