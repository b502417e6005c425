"""The lazy_solid Mitsuba plugin: properties, errors, eval against SolidTexture, object
space, Mitsuba's vectorization check."""

from __future__ import annotations

import re
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import warp as wp

import mitsuba_plugin
import warptex

LLVM = "llvm_ad_rgb"
CUDA = "cuda_ad_rgb"


def use(variant: str) -> None:
    if variant == LLVM and variant != warptex.best_mitsuba_variant():
        pytest.skip("llvm_ad_rgb needs libLLVM >= 16 (see warptex/llvm.py)")
    if variant == CUDA and (CUDA not in mi.variants() or not wp.get_cuda_device_count()):
        pytest.skip("cuda_ad_rgb needs a CUDA device")
    mi.set_variant(variant)
    mitsuba_plugin.register()


def load(exemplar_path, **props):
    return mi.load_dict({"type": "lazy_solid", "exemplar": str(exemplar_path)} | props)


def interaction(points: np.ndarray) -> mi.SurfaceInteraction3f:
    si = dr.zeros(mi.SurfaceInteraction3f, len(points))
    si.p = mi.Point3f(points.T.astype(np.float32))
    return si


def eval_at(tex: mi.Texture, points: np.ndarray) -> np.ndarray:
    """``tex.eval`` at ``points`` (N, 3) as (N, 3): one call in the JIT variants, a call per
    point in the scalar ones."""
    if dr.is_jit_v(mi.Float):
        return np.array(tex.eval(interaction(points))).T
    si = mi.SurfaceInteraction3f()
    got = []
    for p in points:
        si.p = mi.Point3f(*p)
        got.append(np.array(tex.eval(si)))
    return np.array(got)


@pytest.mark.parametrize(("props", "name"), [
    ({"space": "foo"}, "space"),
    ({"filter": "cubic"}, "filter"),
    ({"scale": -2.0}, "scale"),
    # Zero voxels per unit gives every point one voxel's color, infinitely many black.
    ({"scale": 0}, 'scale" must be a positive number, got 0.0'),
    ({"scale": float("inf")}, 'scale" must be a positive number, got inf'),
    ({"seed": "one"}, "seed"),
    ({"seed": -1}, "seed"),
    ({"cache_bytes": -1}, "cache_bytes"),
    ({"jitter": 80.0}, "jitter"),
    ({"passes": -1}, "passes"),
    ({"passes": 2.5}, "passes"),
    ({"passes": 9}, "passes"),
    # Python's bools are numbers: jitter=True would have been a jitter of 1.
    ({"jitter": True}, 'jitter" must be a <float ...>, got True'),
    ({"scale": False}, 'scale" must be a <float ...>, got False'),
    ({"raw": 1}, 'raw" must be a <boolean ...>, got 1'),
    ({"shifted_tiles": "yes"}, "shifted_tiles\" must be a <boolean ...>, got 'yes'"),
    ({"tileable": "maybe"}, 'tileable" must be "auto" or "yes" or "no", got "maybe"'),
    ({"tileable": True}, 'tileable" must be a <string ...>, got True'),
    ({"exemplar_max_size": 15}, 'exemplar_max_size" must be at least 16 pixels, got 15'),
    ({"exemplar_max_size": 32.0}, 'exemplar_max_size" must be an <integer ...>, got 32.0'),
    ({"exemplar_max_size": "32"}, "exemplar_max_size\" must be an <integer ...>, got '32'"),
    ({"exemplar": "no/such/file.png"}, 'exemplar" names a file that does not exist'),
    ({"exemplar_y": "missing.png"}, 'exemplar_y" names a file that does not exist'),
    ({"exemplar": "/"}, 'exemplar" names a folder, not a file'),
    ({"exemplar": "/dev/null"},
     'exemplar" names no regular file .a pipe or a device.: "/dev/null"'),
    ({"exemplar": 5, "exemplar_x": "a.png", "exemplar_y": "a.png", "exemplar_z": "a.png"},
     'exemplar" must be a <string ...>'),
    ({"exemplar_x": "a.png"}, 'exemplar" and "exemplar_x" name the same axis'),  # x ignored it
    ({"to_world": "identity"}, "to_world\" must be a <transform ...>, got 'identity'"),
    ({"feature_distance": "auto"}, "feature_distance\" must be a <boolean ...>, got 'auto'"),
    ({"feature_mask": "no/such/mask.png"}, 'feature_mask" names a file that does not exist'),
    ({"feature_mask": "mask.png", "feature_distance": True},
     'feature_mask" and "feature_distance" exclude each other'),
])
def test_property_errors_name_the_property(granite_32_file, props, name):
    use("scalar_rgb")
    with pytest.raises(RuntimeError, match=f'lazy_solid: property "{name}'):
        load(granite_32_file, **props)


@pytest.mark.parametrize("props", [{"seed": True}, {"passes": True}, {"cache_bytes": False}])
def test_a_boolean_is_no_integer_property(granite_32_file, props):
    """Python's bools are ints: cache_bytes=False failed deep in the store with a message
    that named no property, inside Mitsuba's traceback."""
    use("scalar_rgb")
    name = next(iter(props))
    with pytest.raises(RuntimeError, match=f'lazy_solid: property "{name}" must be an <integer'):
        load(granite_32_file, **props)


def test_a_broken_or_looping_link_is_named_as_such_not_as_a_missing_file(granite_32_file,
                                                                           tmp_path):
    use("scalar_rgb")
    (tmp_path / "gone.png").symlink_to(tmp_path / "deleted.png")
    (tmp_path / "loop.png").symlink_to(tmp_path / "loop.png")
    (tmp_path / "f.png").write_bytes(b"")  # a file where a folder would be: no such file
    expected = {"gone.png": 'names a broken symbolic link: "gone.png"',
                "loop.png": f'cannot look up "loop.png" .{tmp_path / "loop.png"}: Too many levels '
                            "of symbolic links.",
                "f.png/y.png": 'names a file that does not exist: "f.png/y.png" .looked for in '}
    for name, message in expected.items():
        (tmp_path / "scene.xml").write_text(
            f'<scene version="3.0.0"><texture type="lazy_solid" id="t">'
            f'<string name="exemplar" value="{name}"/></texture></scene>')
        with pytest.raises(RuntimeError, match=f'property "exemplar" {message}'):
            mi.load_file(str(tmp_path / "scene.xml"))


_PARALLEL_WARNINGS = """
import sys, warnings
import warptex, mitsuba as mi, mitsuba_plugin

mi.set_variant("scalar_rgb")
mitsuba_plugin.register()
textures = "".join(f'<texture type="lazy_solid" id="t{i}"><string name="exemplar" '
                   f'value="{name}"/></texture>' for i, name in enumerate(sys.argv[1:]))
with warnings.catch_warnings(record=True) as said:
    warnings.simplefilter("always")
    mi.load_string(f'<scene version="3.0.0">{textures}</scene>')
print("\\n".join(sorted(str(w.message) for w in said)))
"""


def test_each_texture_s_exemplar_warning_comes_once_when_mitsuba_loads_them_in_parallel(
        tmp_path):
    """Mitsuba builds a scene's textures on several threads, and warnings' hooks are the
    process's: captures that overlapped lost warnings or gave them twice the plugin's
    prefix (and could leave a dead capture swallowing every later warning). In a process
    of its own, as `warptex render` loads scenes."""
    import os
    import subprocess
    import sys

    from PIL import Image

    names = [tmp_path / f"flat_{i}.png" for i in range(6)]
    for i, name in enumerate(names):
        Image.fromarray(np.full((32, 32, 3), 100 + i, np.uint8)).save(name)
    kernels = os.path.abspath(os.environ.get("WARP_CACHE_PATH", ".cache/warp"))
    run = subprocess.run([sys.executable, "-c", _PARALLEL_WARNINGS, *map(str, names)],
                         capture_output=True, text=True, timeout=300,
                         env=os.environ | {"WARP_CACHE_PATH": kernels,
                                           "WARPTEX_CACHE": str(tmp_path / "cache")})
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.splitlines() == [
        f"lazy_solid: {name}: image is constant; nothing to synthesize" for name in names]


def test_register_before_any_variant_says_to_set_one():
    """In a process of its own: this one has its variant set."""
    import subprocess
    import sys

    code = ("import mitsuba_plugin\ntry:\n    mitsuba_plugin.register()\n"
            "except RuntimeError as error:\n    print(error)\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout == ("mitsuba_plugin.register: set a Mitsuba variant first "
                          "(mitsuba_plugin.set_best_variant())\n")


def test_a_pillow_warning_made_an_error_is_the_exemplar_property_s(tmp_path, monkeypatch):
    from PIL import Image

    path = tmp_path / "photo.bmp"
    Image.fromarray(np.full((16, 16, 3), 90, np.uint8)).save(path)
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 200)  # 256 pixels: Pillow warns
    use("scalar_rgb")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(RuntimeError, match=r'lazy_solid: property "exemplar" cannot be '
                                               r"used: .*photo\.bmp: Image size"):
            load(path)


def test_a_misspelled_exemplar_is_named_beside_the_missing_one(granite_32_file):
    use("scalar_rgb")
    with pytest.raises(RuntimeError, match=r'property "exemplar" is required .*\("exemplr" is no '
                                           r"property of lazy_solid\)"):
        mi.load_dict({"type": "lazy_solid", "exemplr": str(granite_32_file)})
    # Mitsuba's bitmap names its image "filename": a texture moved over from one.
    with pytest.raises(RuntimeError, match=r'"exemplar" is required \(or "exemplar_x"\) '
                                           r'\("filename" is no property of lazy_solid\)$'):
        mi.load_dict({"type": "lazy_solid", "filename": str(granite_32_file)})
    with pytest.raises(RuntimeError, match=r'"exemplar" is required \(or "exemplar_x"\)$'):
        # the properties it reads are no typos
        mi.load_dict({"type": "lazy_solid", "exemplar_y": str(granite_32_file),
                      "exemplar_z": str(granite_32_file), "exemplar_max_size": 32})


def test_a_property_the_plugin_does_not_read_is_named_with_its_likely_one(granite_32_file):
    use("scalar_rgb")
    with pytest.raises(RuntimeError, match='lazy_solid: property "sede" is no property of '
                                           'lazy_solid; did you mean "seed"'):
        load(granite_32_file, sede=3)
    with pytest.raises(RuntimeError, match='property "colour" is no property of lazy_solid'):
        load(granite_32_file, colour=3)


def test_candidates_progress_blocks_nest():
    assert mitsuba_plugin.candidates_bar() is None
    with mitsuba_plugin.candidates_progress():
        with mitsuba_plugin.candidates_progress():
            assert mitsuba_plugin.candidates_bar() is True
        assert mitsuba_plugin.candidates_bar() is True
    assert mitsuba_plugin.candidates_bar() is None


def test_a_to_world_that_collapses_the_block_is_the_property_named(granite_32_file):
    use("scalar_rgb")
    with pytest.raises(RuntimeError, match='lazy_solid: property "to_world" must be invertible'):
        load(granite_32_file, to_world=mi.ScalarTransform4f().scale([1, 0, 1]))
    with pytest.raises(RuntimeError, match='lazy_solid: property "to_world" must be finite'):
        load(granite_32_file, to_world=mi.ScalarTransform4f().scale([1, float("nan"), 1]))
    # Finite as the scene gives it (in float64), but not in float32, as the texture keeps it:
    # that was called NaN or infinite, after NumPy's warning of an overflow.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(RuntimeError, match='lazy_solid: property "to_world" is beyond '
                                               "float32's range"):
            load(granite_32_file, to_world=mi.ScalarTransform4d().scale(3.5e38))
    # Kept as an affine transform, a projective one acted as a scale of 2.
    with pytest.raises(RuntimeError, match='lazy_solid: property "to_world" must be affine: '
                       "its last row is 0 0 0 2, not 0 0 0 1"):
        load(granite_32_file, to_world=mi.ScalarTransform4f(np.diag([2.0, 2.0, 2.0, 2.0])))
    with pytest.raises(RuntimeError, match="must be affine: its last row is 0 0 0 0"):
        load(granite_32_file, to_world=mi.ScalarTransform4f(np.diag([1.0, 1.0, 1.0, 0.0])))
    # Each finite and invertible, together beyond float64: every point would be black.
    with pytest.raises(RuntimeError, match='lazy_solid: property "scale" 1e\\+300 times the '
                       "inverse of to_world is beyond float64's range"):
        load(granite_32_file, scale=1e300, to_world=mi.ScalarTransform4f().scale(1e-10))


def test_an_axis_exemplar_unlike_the_others_is_the_property_named(granite_32_file, tmp_path):
    from PIL import Image

    use("scalar_rgb")
    gray = tmp_path / "gray.png"
    Image.open(granite_32_file).convert("L").save(gray)
    with pytest.raises(RuntimeError, match=r'property "exemplar_y" cannot be used: .*channels'):
        load(granite_32_file, exemplar_y=str(gray))
    # A file that cannot be read is blamed on the property naming it, even beside others.
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not an image")
    with pytest.raises(RuntimeError, match=r'property "exemplar" cannot be used: .*broken'):
        load(broken, exemplar_z=str(granite_32_file))


def test_an_exemplar_of_more_channels_than_lookups_take_is_refused_before_precomputing(
        tmp_path, monkeypatch):
    from warptex import candidates

    use("scalar_rgb")
    five = tmp_path / "five.npy"
    np.save(five, np.random.default_rng(0).random((32, 32, 5)).astype(np.float32))
    monkeypatch.setattr(candidates, "_compute", lambda *args: pytest.fail("pre-computed"))
    with pytest.raises(RuntimeError, match=r'property "exemplar" cannot be used: 5 color '
                                           r"channels; points are looked up in at most 4"):
        load(five)


def test_passes_shifted_tiles_and_tileable_reach_the_synthesis(granite_32_file):
    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar
    from warptex.synthesis import Synthesizer

    use("scalar_rgb")
    tex = load(granite_32_file, passes=1, seed=2)
    assert tex.solid.synthesizer.passes == 1 and "passes=1" in tex.to_string()
    ijk = np.array([[3, 5, 7], [-4, 0, 9]])
    cs = precompute(Exemplar.load(granite_32_file))
    one = Synthesizer(cs, seed=2, passes=1).voxels(ijk)
    np.testing.assert_array_equal(tex.solid.query(ijk + 0.5, filter="nearest"), one)
    assert not np.array_equal(one, Synthesizer(cs, seed=2).voxels(ijk))
    jittered = load(granite_32_file, jitter=8.0, seed=2)
    strong = Synthesizer(cs, seed=2, jitter=8.0).voxels(ijk)
    np.testing.assert_array_equal(jittered.solid.query(ijk + 0.5, filter="nearest"), strong)
    assert not np.array_equal(strong, Synthesizer(cs, seed=2).voxels(ijk))
    shifted = load(granite_32_file, shifted_tiles=True, seed=2)
    assert "shifted_tiles=True" in shifted.to_string()
    np.testing.assert_array_equal(shifted.solid.query(ijk + 0.5, filter="nearest"),
                                  Synthesizer(cs, seed=2, shifted_tiles=True).voxels(ijk))
    never = load(granite_32_file, tileable="no", seed=2)
    assert "tileable=no" in never.to_string() and "tileable=auto" in shifted.to_string()
    edges = precompute(Exemplar.load(granite_32_file), tileable=False)
    np.testing.assert_array_equal(never.solid.query(ijk + 0.5, filter="nearest"),
                                  Synthesizer(edges, seed=2).voxels(ijk))
    assert not np.array_equal(Synthesizer(edges, seed=2).voxels(ijk),
                              Synthesizer(cs, seed=2).voxels(ijk))


def test_feature_distance_and_feature_mask_reach_the_candidates(granite_32_file, tmp_path):
    """The feature-distance channel (Lefebvre & Hoppe 2006), automatic or from a mask, is
    the one Exemplar.load adds: the same candidates, so the same voxels as the CLI's
    --feature-distance/--feature-mask; a mask marks one exemplar, and its errors name it."""
    from PIL import Image

    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar
    from warptex.synthesis import Synthesizer

    use("scalar_rgb")
    ijk = np.array([[3, 5, 7], [-4, 0, 9], [30, 2, -11]])
    auto = load(granite_32_file, feature_distance=True)
    with_distance = Exemplar.load(granite_32_file, feature_distance="auto")
    assert auto.solid.synthesizer.candidates.digests == (with_distance.digest(),) * 3
    assert with_distance.digest() != Exemplar.load(granite_32_file).digest()
    np.testing.assert_array_equal(auto.solid.query(ijk + 0.5, filter="nearest"),
                                  Synthesizer(precompute(with_distance)).voxels(ijk))
    assert "feature_distance=True" in auto.to_string()
    assert "feature" not in load(granite_32_file).to_string()

    gray = np.asarray(Image.open(granite_32_file).convert("L"))
    mask = tmp_path / "mask.png"
    Image.fromarray(((gray > np.median(gray)) * 255).astype(np.uint8)).save(mask)
    masked = load(granite_32_file, feature_mask=str(mask))
    marked = Exemplar.load(granite_32_file, feature_mask=mask)
    assert masked.solid.synthesizer.candidates.digests == (marked.digest(),) * 3
    assert f'feature_mask="{mask}"' in masked.to_string()
    # As read from the scene: the mask's distance is no automatic one.
    assert masked.properties()["feature_mask"] == str(mask)
    assert masked.properties()["feature_distance"] is False
    assert auto.properties()["feature_distance"] is True

    with pytest.raises(RuntimeError, match=r'property "feature_mask" marks the pixels of one '
                                           r'"exemplar"; with "exemplar_x", \.\.\. use'):
        load(granite_32_file, exemplar_y=str(granite_32_file), feature_mask=str(mask))
    small = tmp_path / "small.png"
    Image.fromarray(np.zeros((16, 16), np.uint8)).save(small)
    with pytest.raises(RuntimeError, match=r'property "feature_mask" cannot be used: .*small.png: '
                                           r"feature mask is 16x16 pixels"):
        load(granite_32_file, feature_mask=str(small))
    # An exemplar's own error is the exemplar's, though the mask's name begins its name.
    (tmp_path / "rock").write_bytes(mask.read_bytes())
    (tmp_path / "rock_32.png").write_text("no image")
    with pytest.raises(RuntimeError, match=r'property "exemplar" cannot be used: .*rock_32.png'):
        load(tmp_path / "rock_32.png", feature_mask=str(tmp_path / "rock"))


def test_to_string_tells_textures_of_other_settings_apart(granite_32_file, tmp_path):
    """`warptex render` records the string: textures that show other colors differ in it,
    per-axis exemplars by axis, placed blocks by their transform."""
    from PIL import Image

    use("scalar_rgb")
    other = tmp_path / "turned.png"
    Image.open(granite_32_file).transpose(Image.Transpose.ROTATE_90).save(other)
    on_y = load(granite_32_file, exemplar_y=str(other)).to_string()
    on_z = load(granite_32_file, exemplar_z=str(other)).to_string()
    assert on_y != on_z
    assert f'x="{granite_32_file}", y="{granite_32_file}", z="{other}"' in on_z
    plain = load(granite_32_file).to_string()
    assert f'exemplars=["{granite_32_file}"]' in plain and "to_world" not in plain
    assert "scale=64.0," in plain  # the default, README's
    finer = load(granite_32_file, scale=8.0)
    assert "scale=8.0," in finer.to_string() and finer.properties()["scale"] == 8.0
    assert f"cache_bytes={256 << 20}]" in plain
    moved = load(granite_32_file, to_world=mi.ScalarTransform4f().translate([1, 2, 3]))
    assert "to_world=[[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 2.0]," in moved.to_string()
    assert "cache_bytes=1048576]" in load(granite_32_file, cache_bytes=1 << 20).to_string()


def test_a_cache_too_small_for_one_brick_is_warned_of(granite_32_file):
    """A store of cache_bytes 0 keeps nothing: every render synthesized its voxels again and
    the traced renders repeated, said nowhere but in the statistics."""
    use("scalar_rgb")
    brick = load(granite_32_file).solid.store.brick_bytes
    for small in (0, brick - 1):
        with pytest.warns(UserWarning, match=rf'lazy_solid: property "cache_bytes": {small} '
                                             rf"bytes keep no brick of voxels \(one takes "
                                             rf"{brick}\)"):
            load(granite_32_file, cache_bytes=small)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load(granite_32_file, cache_bytes=brick)


def test_per_axis_exemplars_default_as_precompute_and_the_commands_take_them(
        granite_32_file, tmp_path):
    """x's defaults to ``exemplar``, y's to x's, z's to y's (``--ey`` alone gives z too):
    a scene and ``precompute`` given the same images make the same candidates, so the same
    solid."""
    from PIL import Image

    from warptex.candidates import precompute

    use("scalar_rgb")
    other = tmp_path / "turned.png"
    Image.open(granite_32_file).transpose(Image.Transpose.ROTATE_90).save(other)
    for props, axes in (({"exemplar_y": str(other)}, (granite_32_file, other)),
                        ({"exemplar": None, "exemplar_x": str(other)}, (other,)),
                        ({"exemplar_z": str(other)}, (granite_32_file, granite_32_file, other))):
        texture = mi.load_dict({k: v for k, v in ({"type": "lazy_solid",
                                                   "exemplar": str(granite_32_file)}
                                                  | props).items() if v is not None})
        expected = precompute(*axes)
        got = texture.solid.synthesizer.candidates
        assert (got.axis_source, got.content_digest) == (expected.axis_source,
                                                         expected.content_digest)
    assert load(granite_32_file, exemplar_y=str(other)).exemplars == [granite_32_file, other,
                                                                     other]


def test_exemplar_max_size_shrinks_the_exemplars(granite_32_file):
    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar
    from warptex.synthesis import Synthesizer

    use("scalar_rgb")
    tex = load(granite_32_file, exemplar_max_size=16, seed=3)
    assert "], exemplar_max_size=16, seed=3," in tex.to_string()
    assert "exemplar_max_size" not in load(granite_32_file).to_string()
    shrunk = Exemplar.load(granite_32_file, max_size=16)
    assert tex.solid.synthesizer.candidates.digests == (shrunk.digest(),) * 3
    ijk = np.array([[3, 5, 7], [-4, 0, 9]])
    np.testing.assert_array_equal(tex.solid.query(ijk + 0.5, filter="nearest"),
                                  Synthesizer(precompute(shrunk), seed=3).voxels(ijk))


def test_an_exemplar_too_large_for_the_memory_is_refused_with_the_scene_line(
        granite_32_file, tmp_path, monkeypatch):
    import warptex.machine

    use("scalar_rgb")
    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path / "cache"))  # nothing cached
    monkeypatch.setattr(warptex.machine, "physical_memory", lambda: 260 << 20)
    with pytest.raises(RuntimeError, match=r'lazy_solid: property "exemplar" cannot be used: '
                       r'.*granite_32\.png: 32x32 pixels; pre-computing its candidates needs '
                       r'about 270 MiB, this machine has 260 MiB; .*<integer '
                       r'name="exemplar_max_size" value="256"/> in a scene'):
        load(granite_32_file)
    assert load(granite_32_file, exemplar_max_size=16) is not None  # 259.5 MiB


def test_a_cache_that_is_no_brick_store_is_refused_and_kept(granite_32_file, tmp_path):
    use("scalar_rgb")
    notes = tmp_path / "notes.txt"
    notes.write_text("not bricks")
    with pytest.raises(RuntimeError, match=r'lazy_solid: property "cache".*notes\.txt'):
        load(granite_32_file, cache=str(notes))
    assert notes.read_text() == "not bricks"


def test_a_cache_that_could_never_be_saved_is_refused_at_loading(granite_32_file, tmp_path):
    """A store file yet to be made under a file (or anywhere not writable) would only fail
    the save after a render; one that exists is read, wherever it is."""
    use("scalar_rgb")
    notes = tmp_path / "notes.txt"
    notes.write_text("not a folder")
    with pytest.raises(RuntimeError, match=r'lazy_solid: property "cache" cannot be saved to '
                       r'.*notes\.txt/bricks\.wtb: cannot write, .*notes\.txt is a file'):
        load(granite_32_file, cache=str(notes / "bricks.wtb"))
    assert notes.read_text() == "not a folder"
    assert load(granite_32_file, cache=str(tmp_path / "new" / "bricks.wtb")) is not None


def test_a_cache_of_another_live_texture_of_other_settings_is_refused(granite_32_file,
                                                                      tmp_path):
    use("scalar_rgb")
    cache = str(tmp_path / "granite.wtb")
    first = load(granite_32_file, cache=cache)
    with pytest.raises(RuntimeError, match=r'lazy_solid: property "cache".*granite\.wtb.*'
                                           r"seed 0 in the other texture, 3 here"):
        load(granite_32_file, cache=cache, seed=3)
    assert load(granite_32_file, cache=cache) is not None
    assert first is not None


def test_a_relative_cache_is_always_beside_the_scene(granite_32_file, tmp_path, monkeypatch):
    """A store file to write is never another scene's that the working folder happens to
    hold; ``~`` is the home folder; a folder's name is refused, whether it exists or not."""
    use("scalar_rgb")
    (tmp_path / "sub").mkdir()
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "c.wtb").write_text("another scene's store")
    monkeypatch.chdir(tmp_path / "other")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))

    def loaded(cache: str):
        scene = tmp_path / "sub" / "scene.xml"
        scene.write_text(
            '<scene version="3.0.0"><shape type="rectangle"><bsdf type="diffuse">'
            '<texture type="lazy_solid" name="reflectance">'
            f'<string name="exemplar" value="{granite_32_file}"/>'
            f'<string name="cache" value="{cache}"/></texture></bsdf></shape></scene>')
        before = set(mitsuba_plugin.textures())  # the objects: a freed one's id may be reused
        loaded.scene = mi.load_file(str(scene))  # kept alive with its texture
        (texture,) = [t for t in mitsuba_plugin.textures() if t not in before]
        return texture.cache

    assert loaded("c.wtb") == tmp_path / "sub" / "c.wtb"
    assert (tmp_path / "other" / "c.wtb").read_text() == "another scene's store"
    assert loaded("~/stores/c.wtb") == tmp_path / "home" / "stores" / "c.wtb"
    for folder in ("stores/", "."):
        with pytest.raises(RuntimeError, match=f'property "cache" names a folder, not a file: '
                                               f'"{re.escape(folder)}"'):
            loaded(folder)
    with pytest.raises(RuntimeError, match=r'property "cache".*is a folder, expected a brick'):
        loaded(str(tmp_path / "other"))


@pytest.fixture
def file_resolver_kept():
    """Mitsuba's file resolver (one for the process) as it was after the test, the plugin
    told of it again."""
    resolver = mi.file_resolver()
    folders = [str(resolver[i]) for i in range(len(resolver))]
    yield resolver
    resolver.clear()
    for folder in folders:
        resolver.append(folder)
    mitsuba_plugin.register()


def test_a_relative_cache_of_a_dict_is_in_the_working_folder_of_the_moment(
        granite_32_file, tmp_path, monkeypatch, file_resolver_kept):
    """mi.load_dict's names are the working folder's, as its exemplar's are: the file
    resolver's first folder is the one Mitsuba started in, which a notebook may have left;
    a scene parsed in that folder still keeps its store beside it."""
    use("scalar_rgb")
    started = tmp_path / "started"
    started.mkdir()
    file_resolver_kept.prepend(str(started))  # as if Mitsuba had started there
    mitsuba_plugin.register()
    (tmp_path / "now").mkdir()
    monkeypatch.chdir(tmp_path / "now")
    assert load(granite_32_file, cache="c.wtb").cache == tmp_path / "now" / "c.wtb"
    file_resolver_kept.append(str(tmp_path / "assets"))  # a script's folder of bitmaps
    assert load(granite_32_file, cache="c.wtb").cache == tmp_path / "now" / "c.wtb"
    scene = started / "scene.xml"
    scene.write_text(
        '<scene version="3.0.0"><shape type="rectangle"><bsdf type="diffuse">'
        '<texture type="lazy_solid" name="reflectance">'
        f'<string name="exemplar" value="{granite_32_file}"/>'
        '<string name="cache" value="c.wtb"/></texture></bsdf></shape></scene>')
    before = set(mitsuba_plugin.textures())
    kept = mi.load_file(str(scene))
    (texture,) = [t for t in mitsuba_plugin.textures() if t not in before]
    assert texture.cache == started / "c.wtb" and kept is not None
    # The folder the parse puts first, listed there already, is said once.
    missing = started / "missing.xml"
    missing.write_text(scene.read_text().replace(str(granite_32_file), "none.png"))
    once = re.escape(str(started))
    with pytest.raises(RuntimeError, match=rf'"none\.png" \(looked for in {once}, (?!{once})'):
        mi.load_file(str(missing))


def test_a_dropped_alpha_channel_is_said_in_the_plugin_s_words(granite_32_file, tmp_path):
    """The plugin has no alpha property: its warning does not send the author to one."""
    from PIL import Image

    from warptex.exemplar import AlphaDropped

    use("scalar_rgb")
    rgba = tmp_path / "rgba.png"
    half_transparent = Image.open(granite_32_file).convert("RGBA")
    half_transparent.putalpha(128)
    half_transparent.save(rgba)
    with pytest.warns(AlphaDropped) as said:
        load(rgba)
    (warning,) = [w for w in said if issubclass(w.category, AlphaDropped)]
    assert str(warning.message) == (f"lazy_solid: {rgba}: alpha channel dropped (lazy_solid "
                                    "gives colors only)")
    assert warning.filename == __file__  # the line that loads the scene, not the plugin's


def test_save_caches_writes_the_stores_of_textures_with_a_cache(granite_32_file, tmp_path):
    """What a script calls after rendering, as `warptex render` does: the next process
    starts from the voxels synthesized here."""
    use("scalar_rgb")
    cache = tmp_path / "granite.wtb"
    tex = load(granite_32_file, cache=str(cache), seed=5)
    without = load(granite_32_file, seed=5)
    points = np.array([[1.5, 2.5, 3.5], [20.0, 7.25, 9.5]])
    colors = eval_at(tex, points)
    assert cache in mitsuba_plugin.save_caches()  # with those of any other live texture
    del tex
    again = load(granite_32_file, cache=str(cache), seed=5)
    stored = again.solid.store.stats()["voxels"]
    assert stored > 0
    np.testing.assert_array_equal(eval_at(again, points), colors)
    assert again.solid.store.stats()["voxels"] == stored  # nothing synthesized anew
    np.testing.assert_array_equal(eval_at(without, points), colors)


@pytest.mark.parametrize("variant", ["scalar_rgb", LLVM, CUDA])
@pytest.mark.parametrize(("filter", "raw"), [("trilinear", False), ("nearest", False),
                                             ("trilinear", True)])
def test_eval_is_the_solid_texture_at_scaled_points(granite_32_file, srgb_decoded, variant,
                                                    filter, raw):
    """Decoded from the PNG's sRGB to linear, as Mitsuba's bitmap does, unless raw."""
    use(variant)
    to_world = mi.ScalarTransform4f().translate([0.5, -1.0, 2.0])
    tex = load(granite_32_file, scale=8.0, filter=filter, seed=3, to_world=to_world, raw=raw)
    points = np.random.default_rng(1).uniform(-1, 1, (6, 3)).astype(np.float32)
    stored = tex.solid.query((points - [0.5, -1.0, 2.0]) * 8.0, filter=filter)
    expected = stored if raw else srgb_decoded(stored)
    np.testing.assert_allclose(eval_at(tex, points), expected, atol=1e-5)
    assert tex.is_spatially_varying()
    assert tex.mean()[0] > 0.0 if variant != "scalar_rgb" else tex.mean() > 0.0
    assert tex.max() <= 1.0
    assert "seed=3" in tex.to_string() and f"raw={raw}" in tex.to_string()


@pytest.mark.parametrize("filter", ["trilinear", "nearest"])
def test_every_variant_gives_a_point_the_same_bits(granite_32_file, filter):
    """Raw or decoded to linear, the scalar and the LLVM variants give each point the color
    that ``srgb_to_linear`` makes of the stored values, bit for bit (float32 powers of
    NumPy, Dr.Jit and Python differ by up to 7 ulp there; the decoding is done in float64)."""
    from warptex.srgb import srgb_to_linear

    points = np.random.default_rng(5).uniform(-1, 1, (400, 3)).astype(np.float32)
    got = {}
    for variant in ("scalar_rgb", LLVM):
        use(variant)
        for raw in (True, False):
            tex = load(granite_32_file, scale=8.0, filter=filter, seed=3, raw=raw)
            got[variant, raw] = eval_at(tex, points).astype(np.float32)
    stored = got[LLVM, True]
    np.testing.assert_array_equal(got["scalar_rgb", True], stored)
    np.testing.assert_array_equal(got[LLVM, False], srgb_to_linear(stored))
    np.testing.assert_array_equal(got["scalar_rgb", False], srgb_to_linear(stored))
    assert (got[LLVM, False] != stored).mean() > 0.9


@pytest.mark.parametrize("variant", ["scalar_rgb", LLVM])
def test_colors_render_as_mitsubas_bitmap_of_the_exemplar(tmp_path, variant):
    """One photo as a lazy_solid and as Mitsuba's bitmap: the same colors reach a render
    (an exemplar of nearly one gray, so every voxel's color is close to the texels')."""
    from PIL import Image

    use(variant)
    gray = np.random.default_rng(5).integers(100, 104, (16, 16, 3)).astype(np.uint8)
    Image.fromarray(gray).save(tmp_path / "gray.png")
    solid = load(tmp_path / "gray.png", scale=4.0)
    bitmap = mi.load_dict({"type": "bitmap", "filename": str(tmp_path / "gray.png")})
    points = np.random.default_rng(6).uniform(-2, 2, (32, 3)).astype(np.float32)
    texel = float(np.ravel(bitmap.mean())[0])
    np.testing.assert_allclose(eval_at(solid, points).mean(axis=0), texel, rtol=0.02)
    np.testing.assert_allclose(np.ravel(solid.mean())[0], texel, rtol=1e-3)
    raw = load(tmp_path / "gray.png", scale=4.0, raw=True)
    assert np.ravel(raw.mean())[0] == pytest.approx(gray.mean() / 255, rel=1e-3)


def test_float_exemplars_are_linear_already(granite_32_file, tmp_path):
    from PIL import Image

    use(LLVM)
    path = tmp_path / "granite.npy"
    np.save(path, np.asarray(Image.open(granite_32_file), np.float32) / 255)
    tex = load(path, scale=8.0)
    points = np.random.default_rng(7).uniform(-1, 1, (6, 3)).astype(np.float32)
    np.testing.assert_allclose(np.array(tex.eval(interaction(points))).T,
                               tex.solid.query(points * 8.0), atol=1e-5)
    # Averaging a linear color with encoded ones means nothing: refused unless raw.
    with pytest.raises(RuntimeError, match=r'property "exemplar_y" cannot be used: the '
                       r"exemplars' colors are encoded differently \(granite\.npy linear, "
                       r"granite_32\.png sRGB-encoded\)"):
        load(path, exemplar_y=str(granite_32_file))
    assert "raw=True" in load(path, exemplar_y=str(granite_32_file), raw=True).to_string()


@pytest.mark.parametrize("variant", ["scalar_rgb", LLVM])
def test_inactive_lanes_are_zero_and_not_synthesized(granite_32_file, variant):
    use(variant)
    tex = load(granite_32_file, scale=8.0)
    far = np.array([[0.1, 0.1, 0.1], [500.0, 500.0, 500.0]], np.float32)
    if dr.is_jit_v(mi.Float):
        colors = np.array(tex.eval(interaction(far), mi.Bool([True, False]))).T
    else:
        si = mi.SurfaceInteraction3f()
        colors = []
        for p, active in zip(far, (True, False), strict=True):
            si.p = mi.Point3f(*map(float, p))
            colors.append(np.array(tex.eval(si, active)))
        colors = np.array(colors)
    assert (colors[1] == 0).all() and (colors[0] > 0).all()
    assert tex.solid.store.stats()["misses"] == 1


def test_wrap_far_is_exact_and_alike_in_numpy_drjit_and_python():
    use(LLVM)
    from mitsuba_plugin.texture import _choice_of
    from warptex.texture import FAR_PERIOD, POINT_LIMIT, wrap_far

    rng = np.random.default_rng(5)
    c = np.concatenate([rng.uniform(-POINT_LIMIT + 1, POINT_LIMIT - 1, 50),
                        rng.uniform(-1, 1, 50) * 10.0 ** rng.integers(6, 300, 50),
                        [POINT_LIMIT, -POINT_LIMIT, 1.5 * FAR_PERIOD, 2.5 * FAR_PERIOD]])
    wrapped = wrap_far(c)
    inside = np.abs(c) < POINT_LIMIT
    np.testing.assert_array_equal(wrapped[inside], c[inside])
    assert (np.abs(wrapped[~inside]) <= FAR_PERIOD / 2).all()
    # Whole periods away, exactly: the float64 remainder rounds nothing.
    np.testing.assert_array_equal(np.fmod(c - wrapped, FAR_PERIOD), 0.0)
    np.testing.assert_array_equal(np.array(wrap_far(mi.Float64(c), dr.select, dr.round)),
                                  wrapped)
    assert [wrap_far(float(v), _choice_of, round) for v in c] == wrapped.tolist()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(wrap_far(np.array([np.inf, -np.inf, np.nan]))).all()


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("variant", ["scalar_rgb", LLVM])
def test_points_beyond_the_range_wrap_and_non_finite_ones_are_black(granite_32_file, variant):
    """Mitsuba's textures never raise: a point past the texture's coordinate range gets the
    color whole periods away (wrap_far), a NaN or infinite one black."""
    from warptex.texture import FAR_PERIOD

    use(variant)
    tex = load(granite_32_file, scale=1.0)
    # Exact in float32, whose steps are halves between 2^22 and 2^23.
    near = np.array([[3.5, -7.5, 12.0], [-100.5, 40.5, 0.5]], np.float32)
    shift = np.array([[FAR_PERIOD, 0, 0], [0, -FAR_PERIOD, FAR_PERIOD]], np.float32)
    # 1.75 periods out: wrapped by the nearest whole number of periods (2), not 1.
    beyond = np.array([[-0.25 * FAR_PERIOD + 3.5, 0.5, 0.5]], np.float32)
    two_periods = np.array([[2 * FAR_PERIOD, 0, 0]], np.float32)
    odd = np.array([[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf]], np.float32)
    colors = eval_at(tex, np.concatenate([near, near + shift, beyond,
                                          beyond + two_periods, odd]))
    assert (colors[:2] > 0).all()
    np.testing.assert_array_equal(colors[2:4], colors[:2])
    np.testing.assert_array_equal(colors[5], colors[4])
    np.testing.assert_array_equal(colors[6:], 0.0)


def test_traverse_updates_to_world(granite_32_file):
    use(LLVM)
    tex = load(granite_32_file, scale=8.0)
    params = mi.traverse(tex)
    before = np.array(tex.eval(interaction(np.array([[0.2, 0.3, 0.4]], np.float32))))
    params["to_world"] = mi.AffineTransform4f().translate([0.2, 0.3, 0.4])
    params.update()
    after = np.array(tex.eval(interaction(np.array([[0.4, 0.6, 0.8]], np.float32))))
    np.testing.assert_allclose(after, before, atol=1e-6)
    # An update is checked as the scene's property is (a bare LinAlgError, or NaN colours).
    # A refused one leaves the matrix that eval goes on using, which properties() reports.
    placed = tex.properties()["to_world"]
    projective = mi.AffineTransform4f(np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                                [0, 0, 0.5, 1]], np.float32))
    for matrix, problem in ((mi.AffineTransform4f().scale([1, 0, 1]), "invertible"),
                            (mi.AffineTransform4f().scale([1, float("nan"), 1]), "finite"),
                            (projective, "affine: its last row is 0 0 0.5 1")):
        params["to_world"] = matrix
        with pytest.raises(ValueError, match=f'lazy_solid: property "to_world" must be {problem}'):
            params.update()
        assert tex.properties()["to_world"] == placed
        again = np.array(tex.eval(interaction(np.array([[0.4, 0.6, 0.8]], np.float32))))
        np.testing.assert_array_equal(again, after)


@pytest.mark.parametrize("variant", ["scalar_rgb", LLVM])
def test_object_space_follows_instances(granite_32_file, variant):
    """Two instances of one sphere, moved apart: the same local point has one color."""
    use(variant)
    T = mi.ScalarTransform4f
    tex = {"type": "lazy_solid", "exemplar": str(granite_32_file), "scale": 8.0, "space": "object"}
    scene = mi.load_dict({
        "type": "scene",
        "group": {"type": "shapegroup",
                  "s": {"type": "sphere", "bsdf": {"type": "diffuse", "reflectance": tex}}},
        "a": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
              "to_world": T().translate([3, 0, 0])},
        "b": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
              "to_world": T().translate([-3, 2, 0])},
    })
    if variant == LLVM:
        rays = mi.Ray3f(mi.Point3f([3.2, -2.8], [0.3, 2.3], [-5, -5]), mi.Vector3f(0, 0, 1))
        with mitsuba_plugin.wavefront():  # the BSDF call reaches the texture
            si = scene.ray_intersect(rays)
            colors = np.array(si.bsdf().eval_diffuse_reflectance(si)).T
    else:
        colors = []
        for x, y in ((3.2, 0.3), (-2.8, 2.3)):
            si = scene.ray_intersect(mi.Ray3f(mi.Point3f(x, y, -5), mi.Vector3f(0, 0, 1)))
            colors.append(list(si.bsdf().eval_diffuse_reflectance(si)))
        colors = np.array(colors)
    assert colors[0].max() > 0
    np.testing.assert_allclose(colors[0], colors[1], atol=1e-6)


def _texture_points(to_world: mi.ScalarTransform4f, points: np.ndarray) -> np.ndarray:
    """World ``points`` (N, 3) taken into a frame by the inverse of its float32 matrix (as
    Mitsuba stores a transform), in float64, then scaled by 8 voxels per unit."""
    matrix = np.array(to_world.matrix, np.float32).astype(np.float64).reshape(4, 4)
    local = np.linalg.inv(matrix) @ np.c_[points, np.ones(len(points))].T
    return 8.0 * local[:3].T


@pytest.mark.parametrize("variant", ["scalar_rgb", LLVM])
def test_rotated_frames_place_points_by_their_inverse_matrix(granite_32_file, variant):
    """A to_world and object frames (a shape's, an instance's) that rotate and scale
    unevenly: a point's color is the solid's at scale * to_world^-1 * p. Every frame
    tested before only moved, so one whose rotation was transposed (the block of matter,
    or the texture on a rotated object, turned the other way) failed no test."""
    use(variant)
    T = mi.ScalarTransform4f
    turned = T().translate([0.5, -1.0, 2.0]).rotate([1, 2, 3], 40).scale([1.0, 2.0, 0.5])
    tex = load(granite_32_file, scale=8.0, raw=True, to_world=turned)
    points = np.random.default_rng(8).uniform(-1, 1, (8, 3)).astype(np.float32)
    np.testing.assert_allclose(eval_at(tex, points), tex.solid.query(
        _texture_points(turned, points.astype(np.float64))), atol=1e-5)

    sphere_frame = T().translate([1.5, 0, 0]).rotate([0, 0, 1], 50).scale([0.8, 1.2, 1.0])
    instance_frame = T().translate([-1.5, 0.5, 0]).rotate([1, 1, 0], 70)
    obj = {"type": "lazy_solid", "exemplar": str(granite_32_file), "scale": 8.0,
           "space": "object", "raw": True}
    before = set(mitsuba_plugin.textures())
    scene = mi.load_dict({
        "type": "scene", "tex": obj,
        "sphere": {"type": "sphere", "to_world": sphere_frame,
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "ref", "id": "tex"}}},
        "group": {"type": "shapegroup", "s": {"type": "sphere", "bsdf": {
            "type": "diffuse", "reflectance": {"type": "ref", "id": "tex"}}}},
        "instance": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                     "to_world": instance_frame},
    })
    (solid,) = [t.solid for t in mitsuba_plugin.textures() if t not in before]
    starts = np.array([[1.6, 0.2, -5], [1.3, -0.3, -5], [-1.4, 0.7, -5], [-1.7, 0.3, -5]])
    if dr.is_jit_v(mi.Float):
        rays = mi.Ray3f(mi.Point3f(starts.T.astype(np.float32)), mi.Vector3f(0, 0, 1))
        with mitsuba_plugin.wavefront():  # the BSDF call reaches the texture
            si = scene.ray_intersect(rays)
            colors = np.array(si.bsdf().eval_diffuse_reflectance(si)).T
        hits, distances = np.array(si.p, np.float64).T, np.array(si.t)
    else:
        colors, hits, distances = [], [], []
        for start in starts:
            si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*start), mi.Vector3f(0, 0, 1)))
            colors.append(list(si.bsdf().eval_diffuse_reflectance(si)))
            hits.append(list(si.p))
            distances.append(si.t)
        colors, hits = np.array(colors), np.array(hits, np.float64)
    assert np.isfinite(distances).all()  # every ray hit its object
    expected = np.concatenate([solid.query(_texture_points(sphere_frame, hits[:2])),
                               solid.query(_texture_points(instance_frame, hits[2:]))])
    np.testing.assert_allclose(colors, expected[:, :3], atol=1e-5)


def test_mean_is_the_same_on_every_load(granite_32_file):
    """mean() is estimated from sampled voxels: from the same samples on every load, or a
    scene's mean (which Mitsuba reads) would change from one load to the next."""
    use("scalar_rgb")
    assert len({float(load(granite_32_file).mean()) for _ in range(3)}) == 1


def test_mean_weighs_the_axes_alike_and_max_bounds_every_voxel(granite_32_file, tmp_path):
    """A voxel averages one pixel of each axis' exemplar: mean() weighed the exemplars by
    their pixel counts (a large bright one beside small dark ones: 4.9x the mean of
    eval). max() bounds every voxel's channels, also after sRGB decoding."""
    from PIL import Image

    from warptex.srgb import srgb_to_linear

    use("scalar_rgb")
    pixels = np.asarray(Image.open(granite_32_file).convert("RGB"), np.float32) / 255
    dark = tmp_path / "dark.png"
    Image.fromarray(np.round(pixels[:16, :16] * 0.3 * 255).astype(np.uint8)).save(dark)
    darks = np.asarray(Image.open(dark), np.float32) / 255
    raw = load(granite_32_file, raw=True, exemplar_y=str(dark))
    expected = (pixels.mean() + 2 * darks.mean()) / 3  # z takes y's exemplar
    assert float(raw.mean()) == pytest.approx(float(expected), rel=1e-5)
    voxels = np.random.default_rng(2).integers(-20, 20, (2000, 3))
    for texture, decode in ((raw, False), (load(granite_32_file, exemplar_y=str(dark)), True)):
        colors = texture.solid.synthesizer.voxels(voxels)[:, :3]
        colors = srgb_to_linear(colors) if decode else colors
        assert colors.max() <= texture.max() < 1.0


def test_mean_and_max_decode_each_voxel_of_a_two_tone_exemplar(tmp_path):
    """Half black, half gray (128) pixels: a voxel averages 0 to 3 gray ones of its three
    axes (binomial, 1:3:3:1), each average decoded from sRGB, so mean() is the mean of those
    four decoded values; decoding the mean voxel instead gave 0.73 of it (1 to 2 percent
    on the granite), and max() the undecoded gray 2.3 times too large; neither failed a
    test before."""
    from PIL import Image

    from warptex.srgb import srgb_to_linear

    use("scalar_rgb")
    gray = 128 / 255
    board = (np.indices((16, 16)).sum(axis=0) % 2) * 128
    Image.fromarray(np.repeat(board[..., None], 3, axis=2).astype(np.uint8)).save(
        tmp_path / "board.png")
    tex = load(tmp_path / "board.png")
    levels = srgb_to_linear(np.array([1, 2, 3], np.float32) * np.float32(gray) / np.float32(3))
    expected = (3 * levels[0] + 3 * levels[1] + levels[2]) / 8
    assert float(tex.mean()) == pytest.approx(float(expected), rel=0.02)
    assert tex.max() == pytest.approx(float(levels[2]), rel=1e-6)


def _scalar_interaction(point: np.ndarray) -> mi.SurfaceInteraction3f:
    si = mi.SurfaceInteraction3f()
    si.p = mi.Point3f(*map(float, point))
    return si


@pytest.mark.parametrize("vectorized", [LLVM, CUDA])
def test_eval_1_gives_a_point_the_same_bits_in_scalar_and_vectorized_variants(
        granite_32_file, vectorized):
    """Mitsuba's own luminance differs by a float32 ulp between its scalar and LLVM builds
    (it did at 39 of 300 points), which bumpmap slopes and blendbsdf weights then read. On
    CUDA, Dr.Jit's float64 arithmetic may be fused into FMAs, which LLVM's is not."""
    use(vectorized)  # skipped before any work where the variant is not here
    points = np.random.default_rng(6).uniform(-2, 2, (300, 3)).astype(np.float32)
    values = {}
    for variant in ("scalar_rgb", vectorized):
        use(variant)
        tex = load(granite_32_file, scale=16.0)
        if variant == "scalar_rgb":
            # As Python floats, which a scalar variant's mi.Float is: float32 values too.
            values[variant] = np.array([tex.eval_1(_scalar_interaction(p)) for p in points])
        else:
            values[variant] = np.array(tex.eval_1(interaction(points)), np.float64)
    np.testing.assert_array_equal(values["scalar_rgb"], values[vectorized])


@pytest.mark.parametrize("vectorized", [LLVM, CUDA])
def test_eval_1_grad_gives_the_same_bits_in_scalar_and_vectorized_variants(
        granite_32_file, vectorized):
    """bumpmap's slopes: the scalar build's dr.norm is an ulp off the LLVM build's at some
    lengths (the slopes of 21 of 552 points of a render differed), and a scalar eval_1
    that was not rounded to float32 moved nearly all of them."""
    use(vectorized)
    rng = np.random.default_rng(8)
    points = rng.uniform(-2, 2, (200, 3)).astype(np.float32)
    tangents = rng.normal(0, 3, (200, 6)).astype(np.float32)
    slopes = {}
    for variant in ("scalar_rgb", vectorized):
        use(variant)
        tex = load(granite_32_file, scale=16.0)
        if variant == "scalar_rgb":
            got = []
            for p, t in zip(points, tangents, strict=True):
                si = _scalar_interaction(p)
                si.dp_du = mi.Vector3f(*map(float, t[:3]))
                si.dp_dv = mi.Vector3f(*map(float, t[3:]))
                got.append(list(tex.eval_1_grad(si)))
            slopes[variant] = np.array(got, np.float32)
        else:
            si = interaction(points)
            si.dp_du, si.dp_dv = mi.Vector3f(tangents[:, :3].T), mi.Vector3f(tangents[:, 3:].T)
            slopes[variant] = np.array(tex.eval_1_grad(si), np.float32).T
    assert np.count_nonzero(slopes[vectorized]) > 300
    np.testing.assert_array_equal(slopes["scalar_rgb"], slopes[vectorized])


def test_check_vectorization(granite_32_file):
    """Mitsuba's helper: scalar_rgb evaluations, one at a time, equal llvm_ad_rgb's."""
    from mitsuba.python.test.util import check_vectorization

    use(LLVM)
    use("scalar_rgb")

    def kernel(p: mi.Point3f) -> mi.Color3f:
        mitsuba_plugin.register()
        tex = load(granite_32_file, scale=16.0)
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.p = p
        return tex.eval(si)

    check_vectorization(kernel, width=12, modes=["llvm_ad"])


def test_eval_copies_points_where_numpy_cannot_view_them(granite_32_file, srgb_decoded,
                                                         monkeypatch):
    """NumPy views only host memory: in the CUDA variants eval copies the points. Faked
    here by reporting the LLVM variant's arrays as CUDA ones."""
    use(LLVM)
    tex = load(granite_32_file, scale=8.0, seed=3)
    points = np.random.default_rng(4).uniform(-1, 1, (6, 3)).astype(np.float32)
    monkeypatch.setattr(dr, "backend_v", lambda _: dr.JitBackend.CUDA)
    np.testing.assert_allclose(np.array(tex.eval(interaction(points))).T,
                               srgb_decoded(tex.solid.query(points * 8.0)), atol=1e-5)


def _emitting_rectangle(granite_32_file, integrator: str) -> mi.Scene:
    T = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": 3},
        "sensor": {"type": "perspective",
                   "to_world": T().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16}},
        "rectangle": {"type": "rectangle", "emitter": {
            "type": "area", "radiance": {"type": "lazy_solid", "exemplar": str(granite_32_file),
                                         "scale": 8.0}}}})


@pytest.mark.parametrize("variant", [LLVM, "llvm_ad_spectral"])
def test_an_emitter_traced_from_the_light_shows_what_the_camera_sees(granite_32_file, variant):
    """Light tracing samples the emitter's wavelengths (sample_spectrum): its image of a
    textured area light agrees with the path tracer's, which only evaluates the texture."""
    use(LLVM)
    if variant not in mi.variants():
        pytest.skip(f"this Mitsuba lacks {variant}")
    mi.set_variant(variant)
    mitsuba_plugin.register()
    path, light = (np.array(mitsuba_plugin.render(_emitting_rectangle(granite_32_file, i),
                                                  spp=64))
                   for i in ("path", "ptracer"))
    assert path.mean() > 0.02
    np.testing.assert_allclose(light.mean(), path.mean(), rtol=0.02)


@pytest.mark.parametrize("lights", [1, 2])
def test_the_points_of_no_shape_are_in_the_frame_of_the_one_light_alone(granite_32_file,
                                                                          srgb_decoded, lights):
    """While a render emits light tracing's rays, a point of no shape is read in the frame
    of the one shape whose light an object-space texture colours; a texture lighting two
    shapes has no one frame, and reads it in world space (README)."""
    use("scalar_rgb")
    T = mi.ScalarTransform4f
    scene = {"type": "scene", "tex": {"type": "lazy_solid", "exemplar": str(granite_32_file),
                                      "scale": 4.0, "space": "object", "filter": "nearest"}}
    for n, x in enumerate((5.0, -5.0)[:lights]):
        scene[f"rect{n}"] = {"type": "rectangle", "to_world": T().translate([x, 0.0, 0.0]),
                             "emitter": {"type": "area", "radiance": {"type": "ref",
                                                                      "id": "tex"}}}
    scene = mi.load_dict(scene)
    (tex,) = mitsuba_plugin.textures(scene)
    si = mi.SurfaceInteraction3f()  # of no shape, as an area light's emitted points
    si.p = mi.Point3f(5.1, 0.2, 0.0)
    in_world = np.array(tex.eval(si))
    with tex.emitting_in(scene):
        emitted = np.array(tex.eval(si))
    if lights == 1:  # the rectangle's frame: the world point 5 units along x from it
        stored = tex.solid.query(np.array([[0.1, 0.2, 0.0]]) * 4.0, filter="nearest")
        np.testing.assert_allclose(emitted, srgb_decoded(stored)[0], rtol=1e-6)
        assert not np.allclose(emitted, in_world)
    else:
        np.testing.assert_array_equal(emitted, in_world)


@pytest.mark.parametrize("variant", ["scalar_rgb", LLVM])
def test_eval_1_grad_is_the_slope_along_the_surface(granite_32_file, variant):
    """bumpmap reads eval_1_grad: forward differences half a voxel long, in (u, v) units, so
    a parametrization twice as fast doubles the slope; a degenerate one has none."""
    use(variant)
    tex = load(granite_32_file, scale=8.0)

    def grad(dp_du, dp_dv) -> np.ndarray:
        si = dr.zeros(mi.SurfaceInteraction3f) if dr.is_jit_v(mi.Float) \
            else mi.SurfaceInteraction3f()
        si.p = mi.Point3f(0.3, 0.7, 0.2)
        si.dp_du, si.dp_dv = mi.Vector3f(*dp_du), mi.Vector3f(*dp_dv)
        return np.ravel(np.array(tex.eval_1_grad(si)))

    base = grad((1, 0, 0), (0, 0, 0))
    assert base[0] != 0 and base[1] == 0
    np.testing.assert_allclose(grad((2, 0, 0), (0, 1, 0))[0], 2 * base[0], rtol=1e-4)
    si = mi.SurfaceInteraction3f() if not dr.is_jit_v(mi.Float) else dr.zeros(
        mi.SurfaceInteraction3f)
    si.p = mi.Point3f(0.3, 0.7, 0.2)
    here = float(np.ravel(np.array(tex.eval_1(si)))[0])
    si.p = mi.Point3f(0.3 + 0.5 / 8.0, 0.7, 0.2)
    ahead = float(np.ravel(np.array(tex.eval_1(si)))[0])
    np.testing.assert_allclose(base[0], (ahead - here) / (0.5 / 8.0), rtol=1e-3)
    # A to_world that makes voxels 4 times larger makes the steps 4 times longer: half a
    # voxel still (they were half of a voxel of scale alone, an eighth of one here). From
    # x = 1.3 voxels, half a voxel crosses the centre at 1.5 into the next trilinear cell.
    larger = load(granite_32_file, scale=8.0, to_world=mi.ScalarTransform4f().scale(4.0))
    si.p = mi.Point3f(0.65 + 2.0 / 8.0, 0.7, 0.2)
    ahead = float(np.ravel(np.array(larger.eval_1(si)))[0])
    si.p = mi.Point3f(0.65, 0.7, 0.2)
    here = float(np.ravel(np.array(larger.eval_1(si)))[0])
    si.dp_du, si.dp_dv = mi.Vector3f(1, 0, 0), mi.Vector3f(0, 0, 0)
    slope = float(np.ravel(np.array(larger.eval_1_grad(si)))[0])
    assert ahead != here
    np.testing.assert_allclose(slope, (ahead - here) / (2.0 / 8.0), rtol=1e-3)


@pytest.mark.parametrize("variant", ["scalar_rgb", LLVM])
def test_object_space_bumps_do_not_change_with_the_shapes_size(granite_32_file, variant):
    """In object space the texture scales with the shape, and so must eval_1_grad's steps:
    they were sized without the shape's to_world, so a sphere of radius 0.05 stepped over
    ten of its voxels where one of radius 1 stepped over half of one (4.4 % of a bump image
    changed with the scene's scale)."""
    use(variant)
    rays = np.array([[0.1, 0.2, 5.0], [-0.3, 0.05, 5.0], [0.4, -0.4, 5.0]])
    found = {}
    for radius in (1.0, 0.05):
        before = set(mitsuba_plugin.live_textures)
        scene = mi.load_dict({"type": "scene", "ball": {
            "type": "sphere", "radius": radius, "bsdf": {"type": "diffuse", "reflectance": {
                "type": "lazy_solid", "exemplar": str(granite_32_file), "space": "object",
                "scale": 16.0}}}})
        (tex,) = [t for t in mitsuba_plugin.live_textures if t not in before]
        grads = []
        with mitsuba_plugin.wavefront():
            for o in rays * radius:
                ray = mi.Ray3f(mi.Point3f(*map(float, o)), mi.Vector3f(0, 0, -1))
                si = scene.ray_intersect(ray)
                grads.append(np.ravel(np.array(tex.eval_1_grad(si))))
        found[radius] = np.array(grads)
    assert np.abs(found[1.0]).max() > 0
    np.testing.assert_allclose(found[0.05], found[1.0], rtol=1e-3, atol=1e-4)


def test_a_store_file_ignored_is_said_of_the_cache_property(granite_32_file, tmp_path):
    """The brick store's warning named neither the plugin nor its property, and Python
    pointed at warptex's own line."""
    use("scalar_rgb")
    store = tmp_path / "bricks.wtb"
    load(granite_32_file, cache=str(store)).save()
    store.write_bytes(store.read_bytes()[:60])  # truncated
    with pytest.warns(UserWarning, match=r'^lazy_solid: property "cache": ignoring brick '
                                         r"store file, starting empty: .*bricks\.wtb") as said:
        load(granite_32_file, cache=str(store))
    assert all(w.filename == __file__ for w in said)


@pytest.mark.parametrize("variant", ["scalar_rgb", LLVM])
def test_the_recorded_to_world_is_the_one_rendered(granite_32_file, variant):
    """properties() rounded to_world to 6 decimals: a block scaled by 4e-7 was recorded as a
    zero matrix, and a rotation only nearly. Each entry now reads back as the value held."""
    use(variant)
    rotation = mi.ScalarTransform4f().rotate([0.3, 0.5, 0.8], 30.0).scale(4e-7)
    tex = load(granite_32_file, to_world=rotation)
    recorded = np.array(tex.properties()["to_world"], np.float32)
    np.testing.assert_array_equal(recorded, np.array(rotation.matrix, np.float32).reshape(4, 4))
    assert recorded[0, 0] != 0.0


@pytest.mark.parametrize("variant", ["scalar_rgb", LLVM])
def test_an_object_frame_is_read_without_traversing_what_the_shape_holds(granite_32_file,
                                                                          variant, monkeypatch):
    """Object space read a shape's to_world through mi.traverse, which walks its BSDF and
    textures too, this plugin's among them: at every shading point of a scalar render (4-5x
    the time of world space). The shape's own parameters give the same matrix."""
    use(variant)
    from mitsuba_plugin import texture as module  # of the variant set

    tex = {"type": "lazy_solid", "exemplar": str(granite_32_file), "space": "object"}
    transform = mi.ScalarTransform4f().translate([1.0, 2.0, 3.0]).rotate([0, 1, 1], 40).scale(2.0)
    sphere = mi.load_dict({"type": "sphere", "to_world": transform,
                           "bsdf": {"type": "diffuse", "reflectance": tex}})
    expected = np.linalg.inv(module._affine_matrix(mi.traverse(sphere)["to_world"]))
    cube = mi.load_dict({"type": "cube", "bsdf": {"type": "diffuse", "reflectance": tex}})
    framed = "to_world" in mi.traverse(cube)  # a mesh holds its frame in its vertices
    traversed = []
    monkeypatch.setattr(module.LazySolidTexture, "traverse",
                        lambda self, callback: traversed.append(self))
    np.testing.assert_allclose(module._to_object_matrix(sphere), expected, rtol=1e-12)
    assert (module._to_object_matrix(cube) is not None) == framed
    assert traversed == []


def test_a_variant_set_on_one_core_leaves_the_exr_writer_a_worker(monkeypatch):
    """Dr.Jit sizes its pool to the cores: on one, Mitsuba's EXR writer waited for ever for
    a worker (`warptex render -o out.exr` hung past SIGTERM, and so did the tests)."""
    import drjit as dr

    import mitsuba_plugin

    asked = []
    monkeypatch.setattr(dr, "thread_count", lambda: 1)
    monkeypatch.setattr(dr, "set_thread_count", asked.append)
    mitsuba_plugin.use_variant("scalar_rgb")
    mitsuba_plugin.set_best_variant()
    mi.set_variant("scalar_rgb")  # a script's own way, then the plugin registered
    mitsuba_plugin.register()
    assert asked == [2, 2, 2]
