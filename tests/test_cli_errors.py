"""The command line checks what it can before any work: one clear line naming the option
or file at fault, exit code 2, and nothing written or overwritten."""

from __future__ import annotations

import contextlib
import errno
import os
import signal
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from warptex.cli import main


@pytest.fixture(scope="module")
def files(granite_32_file, tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("inputs")
    mesh = folder / "sphere.ply"
    trimesh.creation.icosphere(subdivisions=1).export(mesh)
    other_linear = folder / "other_linear.npy"  # float: linear colors, the PNG's are sRGB
    np.save(other_linear, _rotated(granite_32_file).astype(np.float32) / 255)
    flat = folder / "flat.ply"  # one triangle whose corners lie on a line
    trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False).export(flat)
    notes = folder / "notes.txt"
    notes.write_text("not bricks")
    broken_mesh = folder / "broken.ply"
    broken_mesh.write_text("not a mesh")
    scene = folder / "scene.xml"
    scene.write_text("this is not XML")
    other = folder / "other_y.npy"
    np.save(other, _rotated(granite_32_file))
    bad_property = folder / "bad_property.xml"
    bad_property.write_text(
        '<scene version="3.0.0"><bsdf type="diffuse"><texture type="lazy_solid" '
        f'name="reflectance"><string name="exemplar" value="{granite_32_file}"/>'
        '<string name="filter" value="cubic"/></texture></bsdf></scene>')
    missing_exemplar = folder / "missing_exemplar.xml"
    missing_exemplar.write_text(
        '<scene version="3.0.0"><bsdf type="diffuse"><texture type="lazy_solid" '
        'name="reflectance"><string name="exemplar" value="textures/nope.png"/></texture>'
        '</bsdf></scene>')
    including = folder / "including.xml"
    including.write_text('<scene version="3.0.0">\n<include filename="bad_property.xml"/>\n'
                         '</scene>')
    no_sensor = folder / "no_sensor.xml"
    no_sensor.write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    declaring = folder / "declaring.xml"  # declares spp, which nothing uses
    declaring.write_text('<scene version="3.0.0"><default name="spp" value="4"/>'
                         '<shape type="sphere"/></scene>')
    gray = folder / "gray.npy"
    np.save(gray, _rotated(granite_32_file)[..., :1])
    five = folder / "five.npy"  # more channels than points are looked up in
    np.save(five, np.random.default_rng(0).random((32, 32, 5)).astype(np.float32))
    return {"exemplar": granite_32_file, "mesh": mesh, "notes": notes, "scene": scene,
            "other": other, "bad_property": bad_property, "including": including,
            "gray": gray, "no_sensor": no_sensor, "declaring": declaring, "flat": flat,
            "other_linear": other_linear, "broken_mesh": broken_mesh, "five": five,
            "missing_exemplar": missing_exemplar, "folder": folder}


def _rotated(path: Path) -> np.ndarray:
    """The PNG's 8-bit pixels turned, so they are sRGB-encoded as the PNG's are."""
    return np.rot90(np.asarray(Image.open(path).convert("RGB"))).copy()


CASES = [
    (["volume", "{exemplar}", "--size", "100000", "-o", "{out}/v.npy"], "--size 100000"),
    (["volume", "{exemplar}", "--passes", "-1", "-o", "{out}/v.npy"], "--passes must be"),
    (["slice", "{exemplar}", "--seed", "4294967296", "-o", "{out}/s.png"],
     "--seed must be within [0, 2147483647], got 4294967296"),
    (["compare", "{exemplar}", "--seed", "-1", "-o", "{out}/cmp"], "--seed must be within"),
    (["volume", "{exemplar}", "-o", "{notes}/v.npy"], "is a file, not a folder"),
    (["volume", "{exemplar}", "-o", "{out}/v.txt"], "must end in .npy, .exr or .vol"),
    (["volume", "{exemplar}", "-o", "{out}"], "{out}: is a folder, expected a file name"),
    (["precompute", "{exemplar}", "-o", "{out}/c.npz"], "a candidate file must end in .wtc"),
    (["slice", "{exemplar}", "--origin", "nan", "0", "0", "-o", "{out}/s.png"], "--origin"),
    (["slice", "{exemplar}", "-o", "{out}/s.jpg"], "must end in .png, .exr or .npy"),
    (["slice", "{exemplar}", "-o", "{out}/.png"], "the image needs a name before .png"),
    (["volume", "{exemplar}", "--ey", "{other_linear}", "--size", "8", "-o", "{out}/v.vol"],
     "keep the values as stored (--raw)"),
    (["slice", "{exemplar}", "--jitter", "65", "-o", "{out}/s.png"],
     "--jitter must be within [0, 64], got 65.0"),
    (["slice", "{exemplar}", "--passes", "-2", "-o", "{out}/s.png"], "--passes must be"),
    (["slice", "{exemplar}", "--exemplar-max-size", "8", "-o", "{out}/s.png"],
     "--exemplar-max-size must be at least 16 pixels, got 8"),
    (["bake", "{out}/missing.ply", "--exemplar", "{exemplar}", "--exemplar-max-size", "8",
      "-o", "{out}/b.ply"], "--exemplar-max-size must be at least 16 pixels, got 8"),
    (["compare", "{exemplar}", "--exemplar-max-size", "0", "-o", "{out}/cmp"],
     "--exemplar-max-size must be at least 16 pixels, got 0"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "--jitter", "-1", "-o", "{out}/b.ply"],
     "--jitter must be within"),
    (["compare", "{exemplar}", "--passes", "-1", "-o", "{out}/cmp"], "--passes must be"),
    (["volume", "{exemplar}", "--passes", "9", "-o", "{out}/v.npy"],
     "--passes must be within [0, 8], got 9"),
    (["volume", "{exemplar}", "--method", "kopf", "--passes", "3", "-o", "{out}/v.npy"],
     "--passes: for lazy synthesis only, not --method kopf"),
    # The default given, as a script may: still no setting Kopf takes.
    (["volume", "{exemplar}", "--method", "kopf", "--jitter", "1", "--passes", "2",
      "--shifted-tiles", "-o", "{out}/v.npy"],
     "--passes, --jitter, --shifted-tiles: for lazy synthesis only, not --method kopf"),
    (["cut", "{mesh}", "--exemplar", "{exemplar}", "--passes", "-1", "-o", "{out}/c.ply"],
     "--passes must be"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "--resolution", "0", "-o", "{out}/b.ply"],
     "--resolution must be at least 1"),
    (["cut", "{mesh}", "--exemplar", "{exemplar}", "--resolution", "2097025",
      "-o", "{out}/c.ply"], "--resolution must be at most 2097024, got 2097025"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "--texture-size", "0", "--uv", "auto",
      "-o", "{out}/b.glb"], "--texture-size must be at least 1"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "--uv", "auto", "-o", "{out}/my b.obj"],
     "my b.obj: an .obj names its .mtl and texture after itself on lines that readers split"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "-o", "{out}/b.obj"],
     "vertex colors (--uv none) must end in .ply or .glb"),
    (["bake", "{exemplar}", "--exemplar", "{exemplar}", "-o", "{out}/b.ply"],
     "{exemplar}: not a mesh format warptex reads (.ply, .obj, .glb, .gltf, .stl, .off"),
    (["bake", "{broken_mesh}", "--exemplar", "{exemplar}", "-o", "{out}/b.ply"],
     "{broken_mesh}: cannot read the mesh: damaged"),
    (["bake", "{out}/missing.ply", "--exemplar", "{exemplar}", "-o", "{out}/b.ply"],
     "{out}/missing.ply: mesh file not found"),
    (["bake", "{flat}", "--exemplar", "{exemplar}", "-o", "{out}/b.ply"],
     "{flat}: every triangle has zero area"),
    (["cut", "{flat}", "--exemplar", "{exemplar}", "-o", "{out}/c.ply"],
     "{flat}: every triangle has zero area"),
    (["render", "{out}/missing.xml", "-o", "{out}/r.png"],
     "{out}/missing.xml: scene file not found"),
    (["render", "{no_sensor}", "-D", "spp=2", "-D", "spp=3", "-o", "{out}/r.png"],
     "-D spp is given more than once (2, 3): give it once"),
    (["render", "{no_sensor}", "-o", "{notes}/r.png"],
     "{notes}/r.png: cannot write, {notes} is a file, not a folder"),
    (["precompute", "{exemplar}", "--no-cache", "-o", "{notes}/c.wtc"],
     "{notes}/c.wtc: cannot write, {notes} is a file, not a folder"),
    (["compare", "{notes}", "-o", "{out}/cmp"], "{notes}: not an image"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "--uv", "mesh", "-o", "{out}/b.glb"],
     "has no UVs"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "--resolution", "8", "--store", "{notes}",
      "-o", "{out}/b.ply"], "not a warptex brick store file"),
    (["cut", "{mesh}", "--exemplar", "{exemplar}", "--normal", "nan", "1", "0",
      "-o", "{out}/c.ply"], "--normal"),
    (["cut", "{mesh}", "--exemplar", "{exemplar}", "--normal", "0", "0", "0",
      "-o", "{out}/c.ply"], "--normal must not be 0 0 0"),
    (["slice", "{exemplar}", "--shape", "1000000", "1000000", "-o", "{out}/s.png"],
     "--shape 1000000 1000000: a slice of 1000000 x 1000000 pixels needs about"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "--uv", "auto", "--texture-size",
      "50000", "-o", "{out}/b.glb"], "--texture-size must be at most 46340"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "--uv", "auto", "--texture-size",
      "40000", "-o", "{out}/b.glb"], "--texture-size 40000: a 40000^2 UV texture needs about"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "--resolution", "2000000",
      "-o", "{out}/b.ply"], "--resolution 2000000: the surface passes through about"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "--resolution", "30000",
      "-o", "{out}/b.ply"], "--resolution 30000: the surface passes through about"),
    (["compare", "{exemplar}", "--size", "0", "-o", "{out}/cmp"], "--size must be at least 8"),
    (["render", "{no_sensor}", "-o", "{out}/r.png"], "has no sensor (camera)"),
    (["render", "{no_sensor}", "--res", "16x16", "-o", "{out}/r.png"],
     "--res sets the parameters $width and $height, which this scene does not declare"),
    (["render", "{no_sensor}", "-D", "shade=1", "-o", "{out}/r.png"],
     "-D sets parameters this scene does not use: shade"),
    (["render", "{declaring}", "-D", "sp=1", "-o", "{out}/r.png"],
     '-D sets parameters this scene does not use: sp; did you mean "spp"?'),
    (["render", "{no_sensor}", "--res", "16x16", "-D", "width=8", "-o", "{out}/r.png"],
     "give them with -D or --res, not both"),
    (["render", "{declaring}", "--spp", "2", "-D", "spp=3", "-o", "{out}/r.png"],
     "give it with -D or --spp, not both"),
    (["render", "{no_sensor}", "-D", "optimize=false", "-o", "{out}/r.png"],
     "-D optimize: Mitsuba's load_file takes optimize as an argument of its own"),
    (["render", "{no_sensor}", "--sampler-seed", "-1", "-o", "{out}/r.png"],
     "--sampler-seed must be 0 to 536870911, got -1"),
    # The largest seed passes its check: the scene is what is refused.
    (["render", "{no_sensor}", "--sampler-seed", "536870911", "-o", "{out}/r.png"],
     "has no sensor (camera)"),
    (["render", "{no_sensor}", "--res", "16x0", "-o", "{out}/r.png"],
     "--res must be positive, got '16x0'"),
    (["render", "{no_sensor}", "--spp", "0", "-o", "{out}/r.png"],
     "--spp must be 1 to 4294967295 (Mitsuba counts samples per pixel in 32 bits), got 0"),
    (["render", "{no_sensor}", "--res", "100000x100000", "-o", "{out}/r.png"],
     "100000x100000 pixels at 1 samples per pixel in a batch exceed"),
    (["render", "{no_sensor}", "--res", "16384x16384", "--spp", "512", "-o", "{out}/r.png"],
     "16384x16384 pixels at 64 samples per pixel in a batch exceed"),
    (["cut", "{mesh}", "--exemplar", "{exemplar}", "-o", "{out}/c"], "must end in .ply or .glb"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "--store", "{out}/b.ply",
      "-o", "{out}/b.ply"], "--store names an output file"),
    (["slice", "{exemplar}", "--origin", "5e6", "0", "0", "-o", "{out}/s.png"],
     "coordinate range"),
    (["compare", "{exemplar}", "--size", "4", "-o", "{out}/cmp"], "--size must be at least 8"),
    # Kopf's checks come before the work for its mean-shift variant alone too.
    (["compare", "{exemplar}", "--methods", "kopf-meanshift", "--size", "12", "-o",
      "{out}/cmp"], "--size must be a positive multiple of 8 for Kopf's method"),
    (["slice", "{exemplar}", "--shape", "16", "0", "-o", "{out}/s.png"],
     "--shape must be positive, got 16 0"),
    (["cut", "{mesh}", "--exemplar", "{exemplar}", "--normal", "inf", "1", "0",
      "-o", "{out}/c.ply"], "--normal must be finite numbers, got inf 1.0 0.0"),
    (["slice", "{exemplar}", "--origin", "-inf", "0", "0", "-o", "{out}/s.png"],
     "--origin must be finite numbers, got -inf 0.0 0.0"),
    (["compare", "{exemplar}", "--ey", "{out}/missing.png", "-o", "{out}/cmp"],
     "{out}/missing.png"),
    (["compare", "{exemplar}", "--ez", "{gray}", "-o", "{out}/cmp"],
     "same number of feature channels"),
    (["compare", "{exemplar}", "--ey", "{other_linear}", "-o", "{out}/cmp"],
     "encoded differently"),
    (["compare", "{exemplar}", "--jitter", "65", "-o", "{out}/cmp"],
     "--jitter must be within [0, 64], got 65.0"),
    (["compare", "{exemplar}", "--size", "12", "--methods", "lazy,kopf", "-o", "{out}/cmp"],
     "--size must be a positive multiple of 8 for Kopf's method"),
    (["volume", "{exemplar}", "--method", "kopf", "--size", "12", "-o", "{out}/v.npy"],
     "--size must be a positive multiple of 8 for Kopf's method"),
    (["volume", "{exemplar}", "--size", "99999999999999", "-o", "{out}/v.npy"],
     "--size 99999999999999: a 99999999999999^3 volume needs about"),
    (["compare", "{exemplar}", "--size", "99999999999999", "--methods", "noise",
      "-o", "{out}/cmp"], "--size 99999999999999: a 99999999999999^3 volume needs about"),
    (["compare", "{exemplar}", "--size", "5000", "--methods", "noise", "-o", "{out}/cmp"],
     "--size 5000: a 5000^3 volume needs about"),
    (["bake", "{out}", "--exemplar", "{exemplar}", "-o", "{out}/b.ply"],
     "{out}: is a folder, expected a mesh file"),
    (["render", "{out}", "-o", "{out}/r.png"], "{out}: is a folder, expected a scene file"),
    (["compare", "{exemplar}", "--methods", " ", "-o", "{out}/cmp"],
     "--methods: no method given"),
    # Not blamed on --size, whose check is Kopf's ("kopf-ms" names a docs column).
    (["compare", "{exemplar}", "--size", "12", "--methods", "lazy,kopf-ms", "-o", "{out}/cmp"],
     "--methods: unknown method(s) kopf-ms; choose from"),
    (["compare", "{exemplar}", "--methods", "noise,extrude,noise", "-o", "{out}/cmp"],
     "method(s) given more than once: noise"),
    (["compare", "{exemplar}", "-o", "{notes}"],
     "{notes}: cannot write, {notes} is a file, not a folder"),
    (["compare", "{exemplar}", "-o", "{out}/" + "a" * 300],
     "a" * 300 + ": cannot look up {out}/" + "a" * 300 + " (File name too long)"),
    (["precompute", "{exemplar}", "--ey", "{gray}"],
     "same number of feature channels; found x {exemplar} 3, y {gray} 1, z {gray} 1"),
    (["volume", "{exemplar}", "--ez", "{gray}", "-o", "{out}/v.npy"],
     "same number of feature channels"),
    (["render", "{scene}", "-o", "{out}/r.jpg"], "must end in .exr or .png"),
    (["render", "{scene}", "--variant", "rgb", "-o", "{out}/r.png"],
     "--variant rgb: unknown Mitsuba variant 'rgb'; this Mitsuba has scalar_rgb"),
    (["render", "{scene}", "-o", "{out}/r.png"], "cannot load the scene"),
    (["render", "{bad_property}", "-o", "{out}/r.png"],
     'load the scene: line 1, col 46: lazy_solid: property "filter" must be "trilinear"'),
    (["slice", "{five}", "-o", "{out}/s.npy"],
     "{five}: 5 color channels; points are looked up in at most 4 (gray, RGB or RGBA)"),
    (["bake", "{mesh}", "--exemplar", "{five}", "-o", "{out}/b.ply"],
     "{five}: 5 color channels"),
    (["bake", "{mesh}", "--exemplar", "{exemplar}", "--texture-size", "64", "-o", "{out}/b.ply"],
     "--texture-size applies to a UV texture (--uv auto or mesh)"),
    # cut has no --uv mesh: a cut's caps have no UVs of the mesh's
    (["cut", "{mesh}", "--exemplar", "{exemplar}", "--texture-size", "64", "-o", "{out}/c.ply"],
     "--texture-size applies to a UV texture (--uv auto), not to vertex colors"),
    (["render", "{missing_exemplar}", "-o", "{out}/r.png"],  # the scene's folder first
     'property "exemplar" names a file that does not exist: "textures/nope.png" (looked for '
     "in {folder}, "),
    (["render", "{including}", "-o", "{out}/r.png"],
     '{including}: cannot load the scene: {bad_property} (line 1, col 46): lazy_solid: '
     'property "filter"'),
]


@pytest.mark.parametrize(("argv", "message"), CASES, ids=[f"{c[0][0]}: {c[1]}"
                                                          for c in CASES])
def test_bad_input_is_one_clear_error_and_writes_nothing(files, tmp_path, capsys, argv,
                                                          message):
    out = tmp_path / "out"
    out.mkdir()
    names = {k: str(v) for k, v in files.items()} | {"out": str(out)}
    code = main([a.format(**names) for a in argv])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("warptex: error: ") and message.format(**names) in err
    assert "Traceback" not in err
    assert not any(out.iterdir())
    assert files["notes"].read_text() == "not bricks"


REPO = Path(__file__).resolve().parent.parent
MESH = ["--exemplar", "{exemplar}", "--resolution", "8", "--passes", "0"]
# A command's arguments, its outputs under {out}, and the one of them whose write fails.
WRITE_FAILURES = [
    (["volume", "{exemplar}", "--size", "8", "--passes", "0", "-o", "{out}/v.npy"], "v.npy"),
    (["slice", "{exemplar}", "--shape", "4", "4", "--passes", "0", "-o", "{out}/s.png"],
     "s.png"),
    (["slice", "{exemplar}", "--shape", "4", "4", "--passes", "0", "-o", "{out}/s.exr"],
     "s.exr"),
    (["precompute", "{exemplar}", "-o", "{out}/c.wtc"], "c.wtc"),
    (["bake", "{mesh}", *MESH, "-o", "{out}/b.ply"], "b.ply"),
    (["bake", "{mesh}", *MESH, "--store", "{out}/b.wtb", "-o", "{out}/b.ply"], "b.wtb"),
    (["cut", "{mesh}", *MESH, "-o", "{out}/c.ply"], "c.ply"),
    (["compare", "{exemplar}", "--size", "8", "--methods", "noise", "-o", "{out}/cmp"],
     "cmp/table.md"),
    (["compare", "{exemplar}", "--size", "8", "--methods", "noise", "-o", "{out}/cmp"],
     "cmp/table.json"),
    (["render", str(REPO / "scenes" / "bunny_wood.xml"), "--spp", "1", "--res", "8x8",
      "-o", "{out}/r.png"], "r.png"),
]


@pytest.mark.parametrize(("argv", "failing"), WRITE_FAILURES,
                         ids=[f"{c[0][0]}: {c[1]}" for c in WRITE_FAILURES])
def test_an_output_that_cannot_be_written_is_one_clear_error(files, tmp_path, capsys,
                                                             disk_full_at, argv, failing):
    """A full disk at the end of the work: the file is named, the old one kept, and no
    temporary is left behind (every output is written under another name, then renamed)."""
    out = tmp_path / "out"
    target = out / failing
    target.parent.mkdir(parents=True)
    names = {k: str(v) for k, v in files.items()} | {"out": str(out)}
    argv = [a.format(**names) for a in argv]
    if target.suffix == ".wtb":  # a store path must hold a brick store: made by a first run
        # of another resolution, since a store that stores nothing new leaves its file alone
        coarser = [("4" if a == "8" and b == "--resolution" else a)
                   for b, a in zip(["", *argv], argv, strict=False)]
        assert main(coarser) == 0
    else:  # a candidate file cut short: -o refuses to overwrite a file of another kind
        target.write_bytes(b"WARPTEXC" if target.suffix == ".wtc" else b"old")
    before = target.read_bytes()
    disk_full_at(target)
    capsys.readouterr()
    assert main(argv) == 1  # not 2, which says the input was refused
    said, err = capsys.readouterr()
    assert err.endswith(f"warptex: error: {target}: cannot write (No space left on device)\n")
    if target.suffix == ".wtb":  # the mesh is written before the store, and kept
        assert said.endswith(f"written: {out / 'b.ply'}; not {target}\n")
        assert (out / "b.ply").is_file()
    assert "Traceback" not in err
    assert target.read_bytes() == before
    assert not [p for p in out.rglob(".*")]  # no temporary left


# Outputs that OpenEXR or Mitsuba's bitmap writer writes: they raise RuntimeError, not
# OSError, where the disk is full.
LIBRARY_WRITE_FAILURES = [
    (["volume", "{exemplar}", "--size", "8", "--passes", "0", "-o", "{out}/v.exr"], "v.exr"),
    (["slice", "{exemplar}", "--shape", "4", "4", "--passes", "0", "-o", "{out}/s.exr"],
     "s.exr"),
    (["render", str(REPO / "scenes" / "bunny_wood.xml"), "--spp", "1", "--res", "8x8",
      "-o", "{out}/r.exr"], "r.exr"),
]


@pytest.mark.parametrize(("argv", "failing"), LIBRARY_WRITE_FAILURES,
                         ids=[c[1] for c in LIBRARY_WRITE_FAILURES])
def test_an_image_library_that_cannot_write_is_one_clear_error(files, tmp_path, capsys,
                                                               monkeypatch, argv, failing):
    """OpenEXR and Mitsuba say a full disk in a RuntimeError naming the temporary file:
    reported as any failed write, naming the output, which keeps its old contents."""
    import mitsuba as mi

    import warptex.volume_files

    def full(path, *args, **kwargs):  # as OpenEXR's File.write and Mitsuba's say it
        raise RuntimeError(f'Failed to write pixel data to image file "{path}". No space '
                           "left on device.")

    # Images and volumes write through it.
    monkeypatch.setattr(warptex.volume_files, "_write_exr_planes", full)
    monkeypatch.setattr(mi.util, "write_bitmap", full)
    out = tmp_path / "out"
    out.mkdir()
    target = out / failing
    target.write_bytes(b"old")
    names = {k: str(v) for k, v in files.items()} | {"out": str(out)}
    capsys.readouterr()
    assert main([a.format(**names) for a in argv]) == 1
    err = capsys.readouterr().err
    assert err.endswith(f"warptex: error: {target}: cannot write (No space left on device)\n")
    assert "Traceback" not in err
    assert target.read_bytes() == b"old"
    assert not [p for p in out.rglob(".*")]


@pytest.mark.parametrize("command", ["volume", "slice", "precompute", "render", "bake"])
@pytest.mark.parametrize("ending", ["/", "/.", "/.."])
def test_an_output_name_of_a_folder_is_refused(files, tmp_path, capsys, command, ending):
    """-o out.npy/ names a folder: refused, not written as the file out.npy."""
    given = f"{tmp_path / 'out.npy'}{ending}"
    inputs = {"render": [str(files["scene"])],
              "bake": [str(files["mesh"]), "--exemplar", str(files["exemplar"])]}
    with pytest.raises(SystemExit) as exit_code:
        main([command, *inputs.get(command, [str(files["exemplar"])]), "-o", given])
    assert exit_code.value.code == 2
    assert f"'{given}' names a folder, not a file" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(("extra", "said"), [
    (["--seeds", "3"], "unrecognized arguments: --seeds 3; did you mean --seed?"),
    (["--store", "s.wtb"], "unrecognized arguments: --store s.wtb; --store is an option of "
     "bake, cut (see"),
    (["--normal", "-1e3", "0", "0"], "unrecognized arguments: --normal -1e3 0 0; --normal is "
     "an option of cut (see"),
    (["stray"], "unrecognized arguments: stray (see"),
    (["--size", "x"], "argument --size: invalid int value: 'x'"),
])
def test_a_command_line_mistake_is_one_line_from_the_command(files, tmp_path, capsys, extra,
                                                             said):
    """An option the command does not take was refused by the top-level parser, with its
    usage (warptex [-h] [--version] COMMAND ...), as if the command did not matter; any
    usage error printed a block of usage lines before it."""
    out = tmp_path / "v.npy"
    with pytest.raises(SystemExit) as stop:
        main(["volume", str(files["exemplar"]), *extra, "-o", str(out)])
    err = capsys.readouterr().err
    assert stop.value.code == 2
    assert err.startswith("warptex volume: error: ") and said in err
    assert err.endswith("(see 'warptex volume --help')\n") and err.count("\n") == 1
    assert not out.exists()


def test_an_empty_output_folder_of_compare_is_refused(files, tmp_path, capsys, monkeypatch):
    """compare -o "" named the working folder (Path("") is "."), where it wrote its files."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_code:
        main(["compare", str(files["exemplar"]), "--size", "16", "--methods", "noise",
              "-o", ""])
    assert exit_code.value.code == 2
    assert "argument -o/--output: empty folder name" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_an_obj_is_refused_before_any_work_where_its_texture_cannot_be_written(files,
                                                                               tmp_path,
                                                                               capsys):
    out = tmp_path / "out"
    (out / "t.png").mkdir(parents=True)
    assert main(["bake", str(files["mesh"]), "--exemplar", str(files["exemplar"]),
                 "--resolution", "8", "--uv", "auto", "-o", str(out / "t.obj")]) == 2
    err = capsys.readouterr().err
    assert (f"warptex: error: {out / 't.png'} (written with {out / 't.obj'}): is a folder, "
            "expected a file name") in err
    assert "surface shell" not in err  # no work done
    assert [p.name for p in out.iterdir()] == ["t.png"]


def test_render_refuses_statistics_it_could_not_write_before_rendering(files, tmp_path,
                                                                       capsys):
    out = tmp_path / "out"
    (out / "r.png.json").mkdir(parents=True)
    assert main(["render", str(REPO / "scenes" / "bunny_wood.xml"), "--spp", "1", "--res",
                 "8x8", "-o", str(out / "r.png")]) == 2
    err = capsys.readouterr().err
    assert (f"warptex: error: {out / 'r.png.json'} (the statistics written with "
            f"{out / 'r.png'}): is a folder, expected a file name") in err
    assert "rendering" not in err
    assert [p.name for p in out.iterdir()] == ["r.png.json"]


def test_a_warning_that_names_warptex_is_not_prefixed_twice(capsys):
    """Warnings worded for Python's users ("warptex: Mitsuba falls back to scalar_rgb")
    show once prefixed in a command's output, as any other."""
    from warptex.cli.console import show_warning

    show_warning(UserWarning("warptex: falls back to scalar_rgb"), UserWarning, "f.py", 1)
    show_warning(UserWarning("image is constant"), UserWarning, "f.py", 1)
    assert capsys.readouterr().err == ("warptex: warning: falls back to scalar_rgb\n"
                                       "warptex: warning: image is constant\n")


def test_python_m_warptex_is_the_command():
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "warptex", "--version"], capture_output=True,
                         text=True, check=False)
    assert run.returncode == 0 and run.stdout.startswith("warptex ")


def test_cut_checks_both_halves_before_writing_either(files, tmp_path, capsys):
    out = tmp_path / "out"
    (out / "c_b.ply").mkdir(parents=True)
    assert main(["cut", str(files["mesh"]), "--exemplar", str(files["exemplar"]),
                 "--resolution", "8", "-o", str(out / "c.ply")]) == 2
    assert f"{out / 'c_b.ply'}: is a folder, expected a file name" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["c_b.ply"]


def test_a_cut_whose_second_half_cannot_be_written_writes_neither(files, tmp_path, capsys,
                                                                  monkeypatch):
    """The disk fills while the second half is written: the first half's new file is not
    put beside the second's old one, and both keep their old contents."""
    out = tmp_path / "out"
    out.mkdir()
    for name in ("c.ply", "c_b.ply"):
        (out / name).write_bytes(b"old")
    write_bytes = Path.write_bytes

    def full_at_second_half(self, data):
        if self.name.startswith(".c_b."):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
        return write_bytes(self, data)

    monkeypatch.setattr(Path, "write_bytes", full_at_second_half)
    assert main(["cut", str(files["mesh"]), "--exemplar", str(files["exemplar"]),
                 "--resolution", "8", "--passes", "0", "-o", str(out / "c.ply")]) == 1
    err = capsys.readouterr().err
    assert err.endswith(f"{out / 'c_b.ply'}: cannot write (No space left on device)\n")
    assert sorted(p.name for p in out.iterdir()) == ["c.ply", "c_b.ply"]
    assert (out / "c.ply").read_bytes() == (out / "c_b.ply").read_bytes() == b"old"


def test_an_unwritable_cache_folder(files, tmp_path, capsys, monkeypatch):
    """`precompute`, whose job is the cache, refuses a cache folder it cannot make before
    any work; other commands warn that the candidates are not cached and carry on."""
    monkeypatch.setenv("WARPTEX_CACHE", str(files["notes"]))
    assert main(["precompute", str(files["exemplar"])]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"warptex: error: {files['notes']}: cannot make the cache folder")
    assert "WARPTEX_CACHE" in err
    out = tmp_path / "v.npy"
    assert main(["volume", str(files["exemplar"]), "--size", "8", "-o", str(out)]) == 0
    assert (f"warptex: warning: candidates not cached: {files['notes']}: cannot write, "
            f"{files['notes'].absolute()} is a file, not a folder; WARPTEX_CACHE sets"
            in capsys.readouterr().err)
    assert np.load(out).shape == (8, 8, 8, 3)
    assert files["notes"].read_text() == "not bricks"


@pytest.mark.parametrize("value", ["gpu", "cuda"])
def test_an_unusable_device_is_a_clear_error(files, tmp_path, capsys, monkeypatch, value):
    import warp as wp

    from warptex.warp_runtime import init_warp

    init_warp()
    if value == "cuda" and wp.get_cuda_device_count() > 0:
        pytest.skip("this machine has a GPU")
    monkeypatch.setenv("WARPTEX_DEVICE", value)
    assert main(["slice", str(files["exemplar"]), "-o", str(tmp_path / "s.png")]) == 2
    assert capsys.readouterr().err.startswith("warptex: error: WARPTEX_DEVICE=")
    assert not (tmp_path / "s.png").exists()
    # Describing an exemplar or the cache uses no device.
    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path / "cache"))
    assert main(["info", str(files["exemplar"])]) == 0
    assert main(["cache"]) == 0


@pytest.mark.parametrize("command", ["volume", "render"])
def test_a_kernel_cache_warp_cannot_make_is_a_clear_error(files, tmp_path, command):
    """WARP_CACHE_PATH naming a file: Warp's start-up fails making its folder, which the
    command reports as one line naming it, not a traceback. A process of its own, as Warp
    starts once a process."""
    import subprocess
    import sys

    out = tmp_path / ("v.npy" if command == "volume" else "r.png")
    source = files["exemplar"] if command == "volume" else files["scene"]
    env = {**os.environ, "WARP_CACHE_PATH": str(files["notes"])}
    run = subprocess.run([sys.executable, "-m", "warptex", command, str(source), "-o", str(out)],
                         capture_output=True, text=True, env=env, timeout=120)
    assert run.returncode == 2
    assert run.stderr.startswith(f"warptex: error: {files['notes']}")
    assert "WARP_CACHE_PATH sets its folder" in run.stderr
    assert "Traceback" not in run.stderr and len(run.stderr.splitlines()) == 1
    assert not out.exists() and files["notes"].read_text() == "not bricks"


@pytest.mark.parametrize("failure", ["cannot build", "cannot load"])
def test_a_kernel_cache_that_fails_a_build_is_one_line_and_exit_1(files, tmp_path, capsys,
                                                                  monkeypatch, failure):
    """A kernel cache folder that exists but cannot take a new build (read-only, another
    user's, a full disk) or load one: the machine's failure mid-work, as a full disk is for
    an output, not a traceback."""
    import warp as wp

    import warptex.warp_runtime

    def failing_launch(kernel, *args, **kwargs):
        if failure == "cannot build":
            raise OSError(errno.EROFS, "Read-only file system",
                          f"{tmp_path}/wp_{kernel.module.name}_1234567_p1_t2")
        raise Exception(f"Failed to load CPU module '{kernel.module.name}' (device='cpu')")

    monkeypatch.setattr(wp, "launch", failing_launch)
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    monkeypatch.setattr(warptex.warp_runtime, "_REBUILT", set())
    monkeypatch.setattr(warptex.warp_runtime, "_drop_builds", lambda module: [])
    out = tmp_path / "v.npy"
    assert main(["volume", str(files["exemplar"]), "--size", "4", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    (line,) = [line for line in err.splitlines() if line.startswith("warptex: error: ")]
    assert line.startswith("warptex: error: Warp cannot "), err
    assert str(tmp_path) in line and "set WARP_CACHE_PATH to another folder" in line
    assert "Traceback" not in err and not out.exists()


def test_a_shell_s_check_counts_its_making_and_a_batch_s_synthesis(files, tmp_path, capsys,
                                                                   monkeypatch):
    """Making a shell peaked at 108-119 bytes a voxel where 64 were counted, and one batch
    of its synthesis (about 2 KB a voxel) was not counted at all: on a 4 GiB machine a
    4096^3 bunny passed the check and failed after two minutes in a traceback."""
    import warptex.machine
    import warptex.surface

    monkeypatch.setattr(warptex.surface, "checked_shell_size", lambda mesh, transform: 10**7)
    monkeypatch.setattr(warptex.machine, "physical_memory", lambda: 2 << 30)
    out = tmp_path / "b.ply"
    assert main(["bake", str(files["mesh"]), "--exemplar", str(files["exemplar"]),
                 "--resolution", "64", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert ("--resolution 64: the surface passes through about 1e+07 voxels, which needs "
            "about 3 GiB") in err, err
    assert not out.exists()


@pytest.mark.parametrize("failure", [
    MemoryError("Unable to allocate 192. MiB for an array"),  # NumPy's
    RuntimeError("Failed to allocate 104857600 bytes on device 'cpu'"),  # Warp's
])
def test_an_allocation_that_fails_mid_work_is_one_line_and_exit_1(files, tmp_path, capsys,
                                                                 monkeypatch, failure):
    """Under a limit the checks did not see (ulimit -v), or past their estimate, an
    allocation failed anywhere with a traceback, at times after minutes of work."""
    from warptex.synthesis import Synthesizer

    def failing(*args, **kwargs):
        raise failure

    monkeypatch.setattr(Synthesizer, "box", failing)
    out = tmp_path / "v.npy"
    assert main(["volume", str(files["exemplar"]), "--size", "4", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    (line,) = [line for line in err.splitlines() if line.startswith("warptex: error: ")]
    assert line.startswith(f"warptex: error: out of memory ({failure}): "), err
    assert "Traceback" not in err and not out.exists()
    monkeypatch.setattr(Synthesizer, "box",
                        lambda *args, **kwargs: (_ for _ in ()).throw(RuntimeError("other")))
    with pytest.raises(RuntimeError, match="other"):  # any other error is not one
        main(["volume", str(files["exemplar"]), "--size", "4", "-o", str(out)])


@pytest.mark.parametrize("exemplar", ["missing.png", "{five}"])
def test_cut_refuses_a_bad_exemplar_before_cutting(files, tmp_path, capsys, monkeypatch,
                                                   exemplar):
    """Cutting a large mesh takes a while: an exemplar that cannot be read, or not looked
    up in, is refused before it, as bad input is before any work."""
    import warptex.cut

    def never(*args, **kwargs):
        raise AssertionError("cut before the exemplar was checked")

    monkeypatch.setattr(warptex.cut, "cut", never)
    path = exemplar.format(five=files["five"])
    assert main(["cut", str(files["mesh"]), "--exemplar", path, "-o",
                 str(tmp_path / "c.ply")]) == 2
    assert capsys.readouterr().err.startswith(f"warptex: error: {path}: ")
    assert not any(tmp_path.iterdir())


def test_a_second_half_named_by_a_link_to_the_first_is_refused_before_the_cut(
        files, tmp_path, capsys, monkeypatch):
    """Both halves would be one file: refused up front in one line, where it was a
    ValueError's traceback from the writer after the work."""
    import warptex.cut

    def never(*args, **kwargs):
        raise AssertionError("cut before its outputs were checked")

    monkeypatch.setattr(warptex.cut, "cut", never)
    (tmp_path / "c.ply").touch()
    (tmp_path / "c_b.ply").symlink_to(tmp_path / "c.ply")
    assert main(["cut", str(files["mesh"]), "--exemplar", str(files["exemplar"]), "-o",
                 str(tmp_path / "c.ply")]) == 2
    assert capsys.readouterr().err == (
        f"warptex: error: {tmp_path / 'c.ply'} and {tmp_path / 'c_b.ply'} are one file "
        "(through a link); each file of a cut is written once: choose another output name\n")


def test_outputs_behind_links_that_lead_nowhere_are_refused_before_the_work(
        files, tmp_path, capsys, monkeypatch):
    """A loop of links as a file or folder name was a RuntimeError's traceback (bake's and
    cut's --store); a folder that is a link to a missing target (an unmounted disk) was
    found only after the work, as "cannot write (File exists)"."""
    import warptex.surface

    def never(*args, **kwargs):
        raise AssertionError("shell synthesized before its outputs were checked")

    monkeypatch.setattr(warptex.surface, "shell", never)
    (tmp_path / "loop.wts").symlink_to("loop.wts")
    (tmp_path / "out").symlink_to(tmp_path / "unmounted" / "out")
    (tmp_path / "notes.txt").write_text("a file")
    (tmp_path / "to_below_a_file.npy").symlink_to(tmp_path / "notes.txt" / "v.npy")
    mesh = ["bake", str(files["mesh"]), "--exemplar", str(files["exemplar"]), "--resolution",
            "16"]
    for args, problem in (
            ([*mesh, "-o", str(tmp_path / "a.ply"), "--store", str(tmp_path / "loop.wts")],
             f"{tmp_path / 'loop.wts'}: cannot look up (Too many levels of symbolic links)"),
            ([*mesh, "-o", str(tmp_path / "out" / "a.ply")],
             f"{tmp_path / 'out' / 'a.ply'}: cannot write there: {tmp_path / 'out'} is a "
             f"symbolic link to {tmp_path / 'unmounted' / 'out'}, which leads nowhere"),
            (["volume", str(files["exemplar"]), "--size", "8", "-o",
              str(tmp_path / "out" / "v.npy")],
             f"{tmp_path / 'out' / 'v.npy'}: cannot write there: {tmp_path / 'out'} is"),
            # A link written through to a file that no folder can hold (below a file).
            (["volume", str(files["exemplar"]), "--size", "8", "-o",
              str(tmp_path / "to_below_a_file.npy")],
             f"{tmp_path / 'to_below_a_file.npy'}: cannot write, {tmp_path / 'notes.txt'} is "
             "a file, not a folder")):
        assert main(args) == 2
        assert capsys.readouterr().err.startswith(f"warptex: error: {problem}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["loop.wts", "notes.txt", "out",
                                                          "to_below_a_file.npy"]
    (tmp_path / "loop.ply").symlink_to("loop.ply")  # an input: not "not found" either
    assert main(["bake", str(tmp_path / "loop.ply"), "--exemplar", str(files["exemplar"]),
                 "-o", str(tmp_path / "a.ply")]) == 2
    assert capsys.readouterr().err == (f"warptex: error: {tmp_path / 'loop.ply'}: cannot look "
                                       "up mesh file (Too many levels of symbolic links)\n")


def test_texture_settings_reach_volume_and_slice(files, tmp_path):
    """--ey gives the y (and so z) axis its own exemplar, and --passes the engine its
    passes, in volume and slice alike."""
    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar
    from warptex.synthesis import Synthesizer

    ex, ey = Exemplar.load(files["exemplar"]), Exemplar.load(files["other"])
    expected = Synthesizer(precompute(ex, ey, ey), passes=1).box((0, 0, 0), (8, 8, 8))
    for other in (Synthesizer(precompute(ex), passes=1), Synthesizer(precompute(ex, ey, ey))):
        assert not np.array_equal(expected, other.box((0, 0, 0), (8, 8, 8)))
    volume = tmp_path / "v.npy"
    assert main(["volume", str(files["exemplar"]), "--ey", str(files["other"]), "--size", "8",
                 "--passes", "1", "-o", str(volume)]) == 0
    np.testing.assert_array_equal(np.load(volume), expected)
    plane = tmp_path / "s.npy"
    assert main(["slice", str(files["exemplar"]), "--ey", str(files["other"]), "--filter",
                 "nearest", "--shape", "8", "8", "--origin", "0.5", "0.5", "2.5",
                 "--passes", "1", "-o", str(plane)]) == 0
    np.testing.assert_array_equal(np.load(plane), expected[:, :, 2])


def test_exemplar_loading_options_reach_slice_as_volume(files, tmp_path):
    """--feature-distance changes the exemplar's features and so the voxels; slice (like
    bake and cut) takes it as volume does, and then gives volume's voxels."""
    volume, plain, plane = tmp_path / "v.npy", tmp_path / "p.npy", tmp_path / "s.npy"
    args = ["--size", "8", "--passes", "1"]
    assert main(["volume", str(files["exemplar"]), "--feature-distance", *args,
                 "-o", str(volume)]) == 0
    assert main(["volume", str(files["exemplar"]), *args, "-o", str(plain)]) == 0
    assert not np.array_equal(np.load(volume), np.load(plain))
    assert main(["slice", str(files["exemplar"]), "--feature-distance", "--filter", "nearest",
                 "--shape", "8", "8", "--origin", "0.5", "0.5", "2.5", "--passes", "1",
                 "-o", str(plane)]) == 0
    np.testing.assert_array_equal(np.load(plane), np.load(volume)[:, :, 2])


def test_a_reader_gone_early_ends_the_command_quietly(files):
    """`warptex info ... | head -1`: output nobody reads is no error worth a traceback."""
    import subprocess
    import sys

    proc = subprocess.Popen(
        [sys.executable, "-c", "import sys; from warptex.cli import main; sys.exit(main())",
         "info", str(files["exemplar"])], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # before anything is written: every write fails
    err = proc.communicate()[1].decode()
    assert proc.returncode == 141 and err == ""


@pytest.mark.parametrize("argv", [["--help"], ["volume", "--help"], ["--version"]])
def test_help_that_cannot_be_written_is_an_error(argv):
    """argparse drops its failures to write: help sent to a full disk exited 0, as if
    shown. A reader gone early ends quietly, as a command's output does."""
    import subprocess
    import sys

    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    command = [sys.executable, "-c", "import sys; from warptex.cli import main; sys.exit(main())",
               *argv]
    with open("/dev/full", "w") as full:
        run = subprocess.run(command, stdout=full, stderr=subprocess.PIPE, text=True,
                             timeout=300)
    prog = " ".join(["warptex", *argv[:-1]])
    assert run.returncode == 1
    assert run.stderr == f"{prog}: error: standard output: No space left on device\n"
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    assert proc.communicate()[1].decode() == "" and proc.returncode == 141


@pytest.mark.parametrize("closed", ["2>&-", ">&-"])
def test_a_command_runs_with_a_standard_stream_closed(files, tmp_path, closed):
    """Python has a stream closed when it started as None: the progress bars failed on a
    closed stderr, the last flush on a closed stdout, each with exit code 1 and no word."""
    import subprocess
    import sys

    out = tmp_path / "v.npy"
    command = [sys.executable, "-m", "warptex", "volume", str(files["exemplar"]), "--size", "4",
               "-o", str(out)]
    run = subprocess.run(["sh", "-c", f'exec "$@" {closed}', "sh", *command],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert np.load(out).shape == (4, 4, 4, 3)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full")
@pytest.mark.parametrize("buffered", [True, False])
def test_standard_output_that_cannot_be_written_is_one_line_and_exit_1(files, buffered):
    """`warptex info ... >/dev/full`: the output lost is the command's failure, as a file
    that cannot be written is, whether it fails as it is printed or as it is flushed."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    if not buffered:
        env["PYTHONUNBUFFERED"] = "1"
    with open("/dev/full", "w") as full:
        run = subprocess.run([sys.executable, "-m", "warptex", "info", str(files["exemplar"])],
                             stdout=full, stderr=subprocess.PIPE, text=True, env=env,
                             timeout=300)
    assert (run.returncode, run.stderr) == (
        1, "warptex: error: standard output: No space left on device\n")


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full")
def test_standard_output_that_fails_after_an_output_says_it_was_written(files, tmp_path):
    """The line that says a volume was written is the one that fails: the error says so."""
    import subprocess
    import sys

    out = tmp_path / "v.npy"
    with open("/dev/full", "w") as full:
        run = subprocess.run([sys.executable, "-m", "warptex", "volume", str(files["exemplar"]),
                              "--size", "4", "-o", str(out)], stdout=full,
                             stderr=subprocess.PIPE, text=True, timeout=300)
    assert run.returncode == 1 and run.stderr.endswith(
        f"warptex: error: standard output: No space left on device (after writing {out})\n")
    assert np.load(out).shape == (4, 4, 4, 3)


def test_negative_numbers_in_any_notation_are_values(files, tmp_path, capsys):
    """argparse reads "-1e3" (or "-32x32") as an unknown option; warptex takes it as the
    value, only where an option of numbers expects one (a file may be called -5), so that
    the option's own check says what is wrong with it."""
    from warptex.cli.parsing import _negative_values

    assert _negative_values(["precompute", "-5"]) == ["precompute", "-5"]
    assert _negative_values(["x", "--normal", "-1e3", "0", "-2E-1", "-4e1"]) == [
        "x", "--normal", " -1e3", "0", " -2E-1", "-4e1"]
    assert _negative_values(["x", "--res", "-32x32", "--filter", "-3", "-o", "-5.png"]) == [
        "x", "--res=-32x32", "--filter", "-3", "-o", "-5.png"]
    with pytest.raises(SystemExit):
        main(["volume", str(files["exemplar"]), "--size", "-1e3", "-o", str(tmp_path / "v.npy")])
    assert "--size: invalid int value: '-1e3'" in capsys.readouterr().err
    assert main(["render", str(files["scene"]), "--res", "-32x32", "-o",
                 str(tmp_path / "r.png")]) == 2
    assert "--res must be positive, got '-32x32'" in capsys.readouterr().err
    a, b = tmp_path / "a.npy", tmp_path / "b.npy"
    common = ["slice", str(files["exemplar"]), "--shape", "2", "2", "--passes", "0"]
    assert main([*common, "--origin", "-1e3", "-2.5E1", "0", "-o", str(a)]) == 0
    assert main([*common, "--origin", "-1000", "-25", "0", "-o", str(b)]) == 0
    assert np.array_equal(np.load(a), np.load(b))


def test_slice_warns_of_what_a_png_cannot_show(files, tmp_path, capsys):
    out = tmp_path / "s.png"
    assert main(["slice", str(files["exemplar"]), "--alpha", "keep", "--shape", "4", "4",
                 "--u", "0", "0", "0", "--passes", "0", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "--u and --v are zero or parallel" in err
    assert "PNG" not in err  # RGB in [0, 1]: nothing lost
    assert main(["slice", str(files["gray"]), "--shape", "4", "4", "--passes", "0",
                 "-o", str(out)]) == 0
    assert "PNG" not in capsys.readouterr().err  # gray is shown whole
    rgba = tmp_path / "rgba.npy"
    color = _rotated(files["exemplar"])
    np.save(rgba, np.concatenate([color, color[..., :1]], axis=2))
    assert main(["slice", str(rgba), "--alpha", "keep", "--shape", "4", "4", "--passes", "0",
                 "-o", str(out)]) == 0
    assert "the PNG keeps 8-bit RGB: 1 channel of 4 dropped" in capsys.readouterr().err
    # Data below 0 (linear, centred) is clipped too, and said so.
    signed = tmp_path / "signed.npy"
    np.save(signed, color.astype(np.float32) / 255 - 0.5)
    assert main(["slice", str(signed), "--shape", "4", "4", "--passes", "0",
                 "-o", str(out)]) == 0
    assert "values outside [0, 1] are clipped" in capsys.readouterr().err
    # A file's alpha, kept, is the PNG's alpha, as stored; a .npy's fourth channel is data.
    png = tmp_path / "rgba.png"
    Image.fromarray(np.concatenate([color, color[..., 1:2]], axis=2)).save(png)
    for name in ("slice.png", "slice.npy"):
        assert main(["slice", str(png), "--alpha", "keep", "--shape", "4", "4", "--passes",
                     "0", "-o", str(tmp_path / name)]) == 0
    assert "PNG" not in capsys.readouterr().err
    with Image.open(tmp_path / "slice.png") as written:
        assert written.mode == "RGBA"
        opacity = np.asarray(written)[..., 3]
    expected = np.load(tmp_path / "slice.npy")[..., 3]
    assert np.array_equal(opacity, (np.clip(expected, 0, 1) * 255 + 0.5).astype(np.uint8))
    assert len(np.unique(opacity)) > 1  # not a constant alpha that any writer might add


def test_a_slice_of_gray_data_and_alpha_keeps_its_alpha_as_stored(files, tmp_path, capsys):
    """Gray, a data channel and a kept alpha (an EXR's Y, C1, A): the PNG shows the gray and
    the alpha as stored (the alpha was sRGB-encoded as a third color), and says the data
    channel is dropped."""
    from warptex.volume_files import write_image

    exr = tmp_path / "yca.exr"
    color = _rotated(files["exemplar"]).astype(np.float32) / 255
    write_image(exr, color, srgb=False, alpha=True)  # R as gray, G as data, B as alpha
    common = ["slice", str(exr), "--alpha", "keep", "--shape", "4", "4", "--passes", "0"]
    assert main([*common, "-o", str(tmp_path / "s.npy")]) == 0
    assert main([*common, "-o", str(tmp_path / "s.png")]) == 0
    err = capsys.readouterr().err
    assert "the PNG keeps 8-bit RGBA: 1 channel of 3 dropped" in err
    assert "mesh files" not in err  # bake's and cut's warning, not a slice's
    synthesized = np.load(tmp_path / "s.npy")
    with Image.open(tmp_path / "s.png") as written:
        assert written.mode == "RGBA"
        shown = np.asarray(written)
    np.testing.assert_array_equal(shown[..., 3], np.round(synthesized[..., 2] * 255))
    assert (shown[..., 0] == shown[..., 1]).all() and (shown[..., 1] == shown[..., 2]).all()


def test_a_stop_right_after_the_outputs_rename_names_it(files, tmp_path, capsys,
                                                        monkeypatch):
    """A stop after the new volume replaced the old, before the command said so, left it
    in place unmentioned: the stop's line names it. One during the write keeps the old."""
    import signal

    import warptex.cli

    write = warptex.cli.volumes.write_volume
    out = tmp_path / "v.npy"
    for stop_first in (False, True):

        def stopped(*args, stop_first=stop_first, **kwargs):
            if stop_first:
                signal.raise_signal(signal.SIGINT)
            write(*args, **kwargs)
            signal.raise_signal(signal.SIGINT)

        monkeypatch.setattr(warptex.cli.volumes, "write_volume", stopped)
        np.save(out, np.zeros(1))
        assert main(["volume", str(files["exemplar"]), "--size", "8", "-o", str(out)]) == 130
        captured = capsys.readouterr()
        assert "written:" not in captured.out
        if stop_first:
            assert np.load(out).shape == (1,)
            assert captured.err.endswith("\nwarptex: interrupted\n")
        else:
            assert np.load(out).shape == (8, 8, 8, 3)
            assert captured.err.endswith(f"\nwarptex: interrupted after writing {out}\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.npy"]


def test_an_interrupt_is_one_line_and_exit_130(files, capsys, monkeypatch):
    import warptex.cli

    def interrupted() -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(warptex.cli, "_check_device", interrupted)
    assert main(["slice", str(files["exemplar"]), "-o", "never.png"]) == 130
    assert capsys.readouterr().err == "\nwarptex: interrupted\n"


def test_sigterm_is_an_interrupt_that_leaves_no_partial_file(files, tmp_path, capsys,
                                                              monkeypatch):
    """A scheduler's SIGTERM in the middle of writing the output: exit 143 with one line, no
    output file and no temporary one; the process's own SIGTERM handling is restored."""
    before = signal.getsignal(signal.SIGTERM)

    def write_then_terminated(file, header) -> None:
        file.write(b"\x93NUMPY, the first bytes of it")
        os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(np.lib.format, "write_array_header_1_0", write_then_terminated)
    out = tmp_path / "out"
    out.mkdir()
    assert main(["volume", str(files["exemplar"]), "--size", "8", "--passes", "0",
                 "-o", str(out / "v.npy")]) == 143
    assert capsys.readouterr().err.endswith("\nwarptex: terminated\n")
    assert list(out.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is before


_STOP_IN_IMPORT = """
import os, signal, sys

name, module, called_in, *argv = sys.argv[1:]
armed, fired = [False], [False]


class Arm:
    def find_spec(self, spec_name, path=None, target=None):
        armed[0] = armed[0] or spec_name == module


def profile(frame, event, arg):
    if armed[0] and not fired[0] and event == "call" and (
            frame.f_code.co_filename.endswith(called_in)):
        fired[0] = True
        os.kill(os.getpid(), getattr(signal, name))


from warptex.cli import main

sys.meta_path.insert(0, Arm())
sys.setprofile(profile)
code = main(argv)
sys.setprofile(None)
print("fired" if fired[0] else "never fired", file=sys.stderr)
sys.exit(code)
"""


@pytest.mark.parametrize(("stop", "module", "called_in", "command"), [
    # trimesh's optional imports catch every exception: the bake ran to its end, exit 0.
    ("SIGTERM", "networkx", "", "bake"),
    ("SIGINT", "networkx", "", "cut"),
    # Dr.Jit's start of a variant turned it into an ImportError: a scalar render, exit 0.
    ("SIGTERM", "mitsuba.llvm_ad_rgb", "typing.py", "render"),
    ("SIGINT", "mitsuba.llvm_ad_rgb", "typing.py", "render"),
])
def test_a_stop_while_a_library_is_imported_stops_the_command(tmp_path, data_dir, stop,
                                                              module, called_in, command):
    """Ctrl-C or SIGTERM while a command imports a library that would lose it: the command
    stops with 130 or 143, as at any other time, and writes nothing."""
    import subprocess
    import sys

    import warptex

    if command == "render" and warptex.best_mitsuba_variant() != "llvm_ad_rgb":
        pytest.skip("llvm_ad_rgb needs libLLVM >= 16 (see warptex/llvm.py)")
    root = Path(__file__).resolve().parent.parent
    arguments = {
        "bake": [str(root / "scenes" / "meshes" / "bunny.ply"), "--exemplar",
                 str(data_dir / "granite_64.png"), "--resolution", "16", "-o", "out.ply"],
        "render": [str(root / "scenes" / "bunny_wood.xml"), "--res", "16x16", "--spp", "1",
                   "-o", "out.png"]}
    arguments["cut"] = arguments["bake"]
    work = tmp_path / "work"
    work.mkdir()
    (work / "stop.py").write_text(_STOP_IN_IMPORT)
    kernels = os.path.abspath(os.environ.get("WARP_CACHE_PATH", root / ".cache" / "warp"))
    run = subprocess.run([sys.executable, "stop.py", stop, module, called_in, command,
                          *arguments[command]], cwd=work, capture_output=True, text=True,
                         env=os.environ | {"WARPTEX_CACHE": str(tmp_path / "cache"),
                                           "WARP_CACHE_PATH": kernels}, timeout=600)
    assert run.stderr.endswith("fired\n") and not run.stderr.endswith("never fired\n")
    assert run.returncode == (143 if stop == "SIGTERM" else 130), run.stderr[-2000:]
    said = "terminated" if stop == "SIGTERM" else "interrupted"
    assert f"\nwarptex: {said}\n" in run.stderr
    assert sorted(p.name for p in work.iterdir()) == ["stop.py"]


def test_a_command_that_builds_the_kernels_says_so_once(tmp_path, monkeypatch, capsys,
                                                       data_dir, warp_device):
    """Whatever the modules it builds and the threads it launches on: one line, naming
    the kernel cache."""
    from warptex import warp_runtime

    absent = tmp_path / "kernels"
    monkeypatch.setattr(warp_runtime, "build_folder", lambda name, cpu: absent / name)
    monkeypatch.setattr(warp_runtime, "_LAUNCHED", set())  # as in a fresh process
    out = tmp_path / "s.npy"
    assert main(["slice", str(data_dir / "granite_64.png"), "--shape", "8", "12", "-o",
                 str(out)]) == 0
    err = capsys.readouterr().err
    assert err.count("warptex: Warp is building the kernels") == 1, err
    assert f"building the kernels into {absent} (once for this version" in err
    assert out.exists()


def test_a_refused_input_on_a_fresh_kernel_cache_is_one_line(tmp_path, monkeypatch, capsys,
                                                             data_dir, warp_device):
    """The kernels are built at the first launch, and said to be then: a command refused
    before any launch says its error alone (it said that the kernels were being built)."""
    import warp as wp

    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path / "kernels"))
    out = tmp_path / "v.npy"
    assert main(["volume", str(data_dir / "granite_64.png"), "--size", "100000", "-o",
                 str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("warptex: error: --size 100000") and err.count("\n") == 1, err
    assert not out.exists()


# A command's arguments and the input file that one of its outputs would overwrite; the
# inputs are copies in {work}, whatever their role: wood.png the exemplar, ball.ply the mesh.
OVERWRITES = [
    (["volume", "{work}/wood.npy", "--size", "8", "-o", "{work}/wood.npy"], "wood.npy"),
    (["slice", "{work}/wood.png", "--ey", "{work}/y.png", "-o", "{work}/y.png"], "y.png"),
    (["slice", "{work}/wood.png", "--feature-mask", "{work}/sheet.png", "-o",
      "{work}/sheet.png"], "sheet.png"),
    (["bake", "{work}/ball.ply", "--exemplar", "{work}/wood.png", "-o", "{work}/ball.ply"],
     "ball.ply"),
    # An .obj comes with its texture, named after it: wood.obj writes wood.png.
    (["bake", "{work}/ball.ply", "--exemplar", "{work}/wood.png", "--uv", "auto",
      "-o", "{work}/wood.obj"], "wood.png"),
    (["cut", "{work}/ball.ply", "--exemplar", "{work}/half_b.png", "--uv", "auto",
      "-o", "{work}/half.obj"], "half_b.png"),
    (["compare", "{work}/sheet.png", "--methods", "noise", "-o", "{work}"], "sheet.png"),
    (["render", "{work}/scene.xml", "-o", "{work}/wood.png"], "wood.png"),
    # The statistics go to OUTPUT.json, here the scene itself.
    (["render", "{work}/shot.png.json", "-o", "{work}/shot.png"], "shot.png.json"),
    # Exemplars named through a parameter, an included file and the home folder.
    (["render", "{work}/param.xml", "-D", "tex=half_b.png", "-o", "{work}/half_b.png"],
     "half_b.png"),
    (["render", "{work}/outer.xml", "-o", "{work}/sheet.png"], "sheet.png"),
    (["render", "{work}/home.xml", "-o", "{work}/y.png"], "y.png"),
    # A bitmap named in an included file through a default of the scene including it.
    (["render", "{work}/outer2.xml", "-o", "{work}/half_b.png"], "half_b.png"),
]


@pytest.mark.parametrize(("argv", "victim"), OVERWRITES,
                         ids=[f"{c[0][0]}: {c[1]}" for c in OVERWRITES])
def test_no_output_overwrites_an_input(files, tmp_path, capsys, monkeypatch, argv, victim):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.setenv("HOME", str(work))
    image = files["exemplar"].read_bytes()
    for name in ("wood.png", "y.png", "half_b.png", "sheet.png"):
        (work / name).write_bytes(image)
    np.save(work / "wood.npy", np.load(files["other"]))
    (work / "ball.ply").write_bytes(files["mesh"].read_bytes())
    scene = ('<scene version="3.0.0">{default}<shape type="sphere"><bsdf type="diffuse">'
             '<texture type="lazy_solid" name="reflectance"><string name="exemplar" '
             'value="{exemplar}"/></texture></bsdf></shape></scene>')
    for name, default, exemplar in (
            ("scene.xml", "", "wood.png"), ("shot.png.json", "", "wood.png"),
            ("param.xml", '<default name="tex" value="wood.png"/>', "$tex"),
            ("inner.xml", "", "sheet.png"), ("home.xml", "", "~/y.png")):
        (work / name).write_text(scene.format(default=default, exemplar=exemplar))
    (work / "outer.xml").write_text('<scene version="3.0.0"><include filename="inner.xml"/>'
                                    "</scene>")
    (work / "outer2.xml").write_text('<scene version="3.0.0"><default name="img" '
                                     'value="half_b.png"/><include filename="inner2.xml"/>'
                                     "</scene>")
    (work / "inner2.xml").write_text(
        '<scene version="3.0.0"><shape type="sphere"><bsdf type="diffuse"><texture '
        'type="bitmap" name="reflectance"><string name="filename" value="$img"/></texture>'
        "</bsdf></shape></scene>")
    # Files only: Dr.Jit makes its folder in the home folder when it first loads.
    before = {p.name: p.read_bytes() for p in work.iterdir() if p.is_file()}
    code = main([a.format(work=work) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"would overwrite {work / victim}" in err or \
        f"would overwrite the input {work / victim}" in err
    assert {p.name: p.read_bytes() for p in work.iterdir() if p.is_file()} == before


def test_cuts_second_half_over_its_input_names_the_output_it_comes_from(files, tmp_path,
                                                                       capsys):
    """-o half.ply writes half_b.ply too: where that is the mesh cut, the refusal says which
    -o it comes with, as for an .obj's texture."""
    mesh = tmp_path / "half_b.ply"
    mesh.write_bytes(files["mesh"].read_bytes())
    out = tmp_path / "half.ply"
    assert main(["cut", str(mesh), "--exemplar", str(files["exemplar"]), "-o", str(out)]) == 2
    assert (f"warptex: error: {mesh} (written with {out}): would overwrite the input {mesh}"
            in capsys.readouterr().err)
    assert sorted(tmp_path.iterdir()) == [mesh]


@pytest.mark.parametrize("command", ["slice", "volume"])
def test_an_output_that_is_a_folder_is_named_so_whatever_its_name(files, tmp_path, capsys,
                                                                  command):
    """A folder given as output, with no suffix or a right one: the same error, that it is
    a folder, not one about its suffix."""
    for folder in (tmp_path / "renders", tmp_path / "volume.npy"):
        folder.mkdir()
        assert main([command, str(files["exemplar"]), "-o", str(folder)]) == 2
        err = capsys.readouterr().err
        assert err.endswith(f"warptex: error: {folder}: is a folder, expected a file name\n")
        assert not any(folder.iterdir())


def test_every_command_s_help_ends_with_examples_that_parse(capsys):
    """Each command's --help shows examples, one per line, and each is a command line that
    the parser takes, naming files that the checkout has: help that does not go stale."""
    import shlex

    from warptex.cli import parsing

    repo = Path(__file__).resolve().parent.parent
    parser = parsing.build_parser()
    for name in parsing.SUBCOMMANDS:
        with pytest.raises(SystemExit):
            main([name, "--help"])
        text = capsys.readouterr().out
        examples = parsing._EXAMPLES[name]
        assert text.rstrip().endswith("\n".join(f"  {e}" for e in examples))
        if name == "cache":  # an epilog of its own comes first, wrapped as argparse does
            assert "Deleted candidates are computed again when next needed" in text
        for example in examples:
            argv = shlex.split(example)[1:]
            args = parser.parse_args(argv)
            assert args.command == name
            for value in argv:
                if value.startswith("scenes/"):
                    assert (repo / value).is_file(), value


def test_the_help_examples_write_no_file_of_another(capsys):
    """Run one after another, as a new user does, no example replaces what another wrote:
    an .obj's texture is named after it, a cut's second half gets _b, a render's
    statistics go beside it (and `make demo` is the render example)."""
    import shlex

    from warptex.cli import parsing
    from warptex.compare import REPORT_FILES
    from warptex.mesh_files import exported_files

    parser = parsing.build_parser()
    written: dict[Path, str] = {}
    for name in parsing.SUBCOMMANDS:
        for example in parsing._EXAMPLES[name]:
            args = parser.parse_args(shlex.split(example)[1:])
            output = getattr(args, "output", None)
            if output is None:
                continue
            if name == "compare":
                files = [Path(output) / f for f in REPORT_FILES]
            elif name in ("bake", "cut"):
                halves = [output] + ([output.with_stem(output.stem + "_b")]
                                     if name == "cut" else [])
                files = [f for h in halves for f in exported_files(h, uv_texture=args.uv
                                                                    != "none")]
            else:
                files = [output] + ([Path(f"{output}.json")] if name == "render" else [])
            for f in files:
                assert f not in written, f"{example} replaces {f}, written by {written[f]}"
                written[f] = example


def test_too_many_channels_for_lazy_synthesis_are_refused_before_pre_computing(
        tmp_path, capsys, monkeypatch):
    """40 channels: the engine's exact projections take at most 34 of 5-voxel rows; the
    candidates were pre-computed first, minutes for a large exemplar, then refused."""
    import warptex.candidates
    from warptex.cli import main

    path = tmp_path / "stack.npy"
    np.save(path, np.random.default_rng(0).random((16, 16, 40), np.float32))

    def never(*args, **kwargs):
        raise AssertionError("pre-computed")

    monkeypatch.setattr(warptex.candidates, "_compute", never)
    assert main(["volume", str(path), "--size", "8", "-o", str(tmp_path / "v.npy")]) == 2
    assert (f"{path}: 40 feature channels are too many for exact projections with 5-voxel "
            "neighbourhoods (at most 34)") in capsys.readouterr().err
    assert main(["compare", str(path), "--size", "8", "--methods", "noise,lazy",
                 "-o", str(tmp_path / "cmp")]) == 2
    assert f"{path}: 40 feature channels are too many" in capsys.readouterr().err
    assert not (tmp_path / "cmp").exists()
    # Nor does precompute make candidates that no synthesis could use.
    assert main(["precompute", str(path), "-o", str(tmp_path / "c.wtc")]) == 2
    assert f"{path}: 40 feature channels are too many" in capsys.readouterr().err
    assert not (tmp_path / "c.wtc").exists()


@pytest.mark.parametrize(("channels", "methods", "said"), [
    (9, "noise,kopf", "9 matching channels; Kopf's method handles at most 8"),
    (5, "noise,lazy", "5 color channels; points are looked up in at most 4"),
])
def test_compare_refuses_channels_a_later_method_cannot_take_before_any_method_runs(
        tmp_path, capsys, monkeypatch, channels, methods, said):
    """Kopf's windows take at most 8 channels and the lazy cube's lookups 4: the methods
    before it ran to the end (lazy's candidates for minutes), then the comparison failed
    with no report (a traceback for the lazy cube)."""
    from warptex import compare
    from warptex.cli import main
    from warptex.compare import measure

    path = tmp_path / "stack.npy"
    np.save(path, np.random.default_rng(0).random((32, 32, channels), np.float32))

    def never(*args, **kwargs):
        raise AssertionError("a method ran")

    monkeypatch.setattr(measure, "in_child_process", never)
    assert main(["compare", str(path), "--size", "16", "--methods", methods,
                 "-o", str(tmp_path / "cmp")]) == 2
    assert f"warptex: error: {path}: {said}" in capsys.readouterr().err
    assert not (tmp_path / "cmp").exists()
    with pytest.raises(ValueError, match=said):
        compare.compare(compare.Setup(path, 16), methods.split(","), progress=False)


def test_a_volume_file_s_write_copies_are_counted_before_the_work(files, tmp_path, capsys,
                                                                  monkeypatch):
    """A .exr holds three copies of the volume while it is written (WRITE_COPIES), a .npy
    none: at 1024^3, where the volume's slabs take less than those copies, memory for the
    volume and its slabs but not for the copies refuses the .exr before any work."""
    from warptex import candidates, machine
    from warptex.cli.common import volume_bytes
    from warptex.volume_files import WRITE_COPIES

    def work(*args, **kwargs):
        raise AssertionError("the work began")

    monkeypatch.setattr(candidates, "precompute", work)
    need = (1 + WRITE_COPIES[".exr"]) * volume_bytes(1024, 3)
    monkeypatch.setattr(machine, "physical_memory", lambda: need - 1)
    assert main(["volume", str(files["exemplar"]), "--size", "1024",
                 "-o", str(tmp_path / "v.exr")]) == 2
    assert "--size 1024: a 1024^3 volume needs about" in capsys.readouterr().err
    with pytest.raises(AssertionError, match="the work began"):  # a .npy fits
        main(["volume", str(files["exemplar"]), "--size", "1024", "-o", str(tmp_path / "v.npy")])


def test_a_kopf_search_beyond_the_memory_is_refused_naming_the_exemplar(
        files, tmp_path, capsys, monkeypatch):
    """The search's windows take kilobytes per exemplar pixel whatever the volume's size:
    a 512 px photo took 1.1 GB for a 16^3 volume, which the memory check did not count."""
    from warptex import machine
    from warptex.baselines import kopf
    from warptex.cli import main
    from warptex.exemplar import as_exemplar

    exemplar = files["exemplar"]
    search = kopf.search_bytes([as_exemplar(exemplar)] * 3)
    small = 2 * 4 * 3 * 8**3 + kopf.working_bytes(8)  # an 8^3 volume and its work
    monkeypatch.setattr(machine, "physical_memory", lambda: search + small - 1)
    monkeypatch.setattr(kopf, "synthesize", lambda *a, **k: pytest.fail("ran"))
    out = tmp_path / "v.npy"
    assert main(["volume", str(exemplar), "--method", "kopf", "--size", "8",
                 "-o", str(out)]) == 2
    err = capsys.readouterr().err
    said = f"{exemplar}: Kopf's search over its windows (with the 8^3 volume) needs about"
    assert f"warptex: error: {said}" in err
    assert "shrink the exemplar with --exemplar-max-size" in err and not out.exists()
    assert main(["compare", str(exemplar), "--methods", "kopf", "--size", "8",
                 "-o", str(tmp_path / "cmp")]) == 2
    assert said in capsys.readouterr().err
    # Where the volume takes more than the search, a smaller --size is the advice.
    large = 2 * 4 * 3 * 64**3 + kopf.working_bytes(64)
    monkeypatch.setattr(machine, "physical_memory", lambda: search + large - 1)
    assert main(["volume", str(exemplar), "--method", "kopf", "--size", "64",
                 "-o", str(out)]) == 2
    assert "warptex: error: --size 64: a 64^3 volume needs about" in capsys.readouterr().err


@pytest.fixture
def pipes(tmp_path):
    """Named pipes, each named like an input file, and a watchdog that opens any one read
    meanwhile for writing and closes it: a reader that waits for a writer gets an empty
    file, and the test fails on the wrong error instead of hanging."""
    import threading

    names = {k: tmp_path / f"pipe.{k}" for k in ("png", "npy", "ply", "xml")}
    for path in names.values():
        os.mkfifo(path)
    done = threading.Event()

    def release() -> None:
        while not done.wait(0.05):
            for path in names.values():
                with contextlib.suppress(OSError):  # no reader waiting: as it should be
                    os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))

    watchdog = threading.Thread(target=release, daemon=True)
    watchdog.start()
    yield names
    done.set()
    watchdog.join()


def test_a_named_pipe_given_as_an_input_file_is_refused_without_reading_it(
        pipes, files, tmp_path, capsys):
    """``info`` on a pipe named like an image waited for a writer for ever; ``bake`` and
    ``render`` called theirs "not found"."""
    from warptex.exemplar import Exemplar

    exemplar = str(files["exemplar"])
    for argv, said in [
        (["info", str(pipes["png"])], f"{pipes['png']}: is not a regular file"),
        (["info", str(pipes["npy"])], f"{pipes['npy']}: is not a regular file"),
        (["slice", exemplar, "--feature-mask", str(pipes["png"]), "-o",
          str(tmp_path / "s.png")], f"{pipes['png']}: is not a regular file"),
        (["bake", str(pipes["ply"]), "--exemplar", exemplar, "-o", str(tmp_path / "b.ply")],
         f"{pipes['ply']}: is not a regular file (a pipe or a device), expected a mesh file"),
        (["render", str(pipes["xml"]), "-o", str(tmp_path / "r.png")],
         f"{pipes['xml']}: is not a regular file (a pipe or a device), expected a scene"),
    ]:
        assert main(argv) == 2, argv
        assert said in capsys.readouterr().err, argv
    with pytest.raises(ValueError, match="is not a regular file"):
        Exemplar.load(pipes["png"])


def test_an_empty_file_name_is_refused_as_such(tmp_path, capsys):
    """Path("") names the working folder, which the error named instead ('.: is a
    directory')."""
    from warptex.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["volume", "", "-o", str(tmp_path / "v.npy")])
    assert stop.value.code == 2
    assert "argument EXEMPLAR: empty file name" in capsys.readouterr().err


def test_a_scene_naming_a_home_folder_of_no_user_is_refused_as_mitsuba_refuses_it(
        tmp_path, capsys):
    """Looking for the files a scene names expanded ~nosuchuser and stopped the render with
    a traceback (RuntimeError: Could not determine home directory)."""
    scene = tmp_path / "s.xml"
    scene.write_text('<scene version="3.0.0"><shape type="sphere"><bsdf type="diffuse">'
                     '<texture type="bitmap" name="reflectance"><string name="filename" '
                     f'value="~nosuchuser{"x" * 300}/y.png"/></texture></bsdf></shape></scene>')
    assert main(["render", str(scene), "-o", str(tmp_path / "r.exr"),
                 "--variant", "scalar_rgb"]) == 2
    assert "cannot load the scene" in capsys.readouterr().err



def test_render_help_gives_the_sampler_seed_range_it_checks(capsys):
    """The range --sampler-seed's help gives is the one its error names (above)."""
    with pytest.raises(SystemExit):
        main(["render", "--help"])
    assert "0 to 536870911;" in " ".join(capsys.readouterr().out.split())


_COMMAND_STOPPED = """
import os, signal, sys

when, exemplar = sys.argv[1:]
sys.argv[1:] = ["info", exemplar]


class StopWhileWarpLoads:
    def find_spec(self, name, path=None, target=None):
        if name == "warp":
            os.kill(os.getpid(), signal.SIGINT)


class StopCaughtByAnImport:
    # As NumPy's C extension turns what stops it into an ImportError, which an optional
    # import then catches.
    def find_spec(self, name, path=None, target=None):
        if name == "warp":
            try:
                os.kill(os.getpid(), signal.SIGINT)
                for _ in range(1000):  # the handler runs at the loop's next turn
                    pass
            except BaseException:
                pass


if when == "starting":
    sys.meta_path.insert(0, StopWhileWarpLoads())
elif when == "caught":
    sys.meta_path.insert(0, StopCaughtByAnImport())
from warptex.cli import main

code = main()
if when == "ended":
    os.kill(os.getpid(), signal.SIGINT)  # as Python shuts down, its work done: ignored
sys.exit(code)
"""


@pytest.mark.parametrize("when", ["starting", "caught", "ended"])
def test_ctrl_c_before_the_command_runs_or_after_it_ended_says_one_line(tmp_path, data_dir,
                                                                        when):
    """Ctrl-C while the command's libraries loaded (its first second) printed a traceback
    of the import under way, or, where the import caught what it became, said
    "interrupted" and ran the command all the same (or blamed a foreign `kernels`
    package); one as Python shut down after the work (a few tenths of a second) made a
    finished command exit 130 without a word."""
    import subprocess
    import sys

    (tmp_path / "warptex").write_text(_COMMAND_STOPPED)  # named as the command's script
    run = subprocess.run([sys.executable, "warptex", when, str(data_dir / "granite_64.png")],
                         cwd=tmp_path, capture_output=True, text=True, timeout=300,
                         env=os.environ | {"WARPTEX_CACHE": str(tmp_path / "cache")})
    assert "Traceback" not in run.stderr, run.stderr
    if when != "ended":
        assert (run.returncode, run.stderr) == (130, "\nwarptex: interrupted\n")
        assert run.stdout == ""
    else:
        assert run.returncode == 0 and "granite_64.png" in run.stdout


def test_only_the_command_s_own_process_stops_quietly(monkeypatch):
    """Library users' and other programs' Ctrl-C stays Python's KeyboardInterrupt."""
    import sys

    from warptex.stops import is_the_command

    for orig_argv, expected in (
            (["python", "/venv/bin/warptex", "info"], True),
            (["python", "-X", "importtime", "/venv/bin/warptex", "info"], True),
            (["python", "-m", "warptex", "info"], True),
            (["python", "-m", "pytest", "-m", "warptex"], False),
            (["python", "render.py", "-m", "warptex"], False),
            # a process the command starts is given its arguments, not its command line
            (["python", "-c", "from multiprocessing.spawn import spawn_main; spawn_main()",
              "--multiprocessing-fork"], False)):
        monkeypatch.setattr(sys, "orig_argv", orig_argv)
        monkeypatch.setattr(sys, "argv", ["/venv/bin/warptex", "info"])
        assert is_the_command() == expected, orig_argv


def test_a_stream_closed_from_the_start_is_passed_over_at_the_end(monkeypatch):
    """It flushed sys.stdout and sys.stderr, None where closed (`2>&-`)."""
    import sys

    import warptex.stops

    handlers = {}
    monkeypatch.setattr(warptex.stops, "is_the_command", lambda: True)
    monkeypatch.setattr(signal, "signal", lambda number, handler: handlers.update({
        number: handler}))
    monkeypatch.setattr(sys, "stderr", None)
    warptex.stops.stops_ignored_after_the_work()
    assert set(handlers) == {signal.SIGINT, signal.SIGTERM}


def test_the_command_run_on_another_thread_leaves_the_signals_to_the_main_one(
        monkeypatch, errors_on_a_thread):
    """The end of the command's work (``stops_ignored_after_the_work``, as ``main()``
    called from a pipeline's worker thread reaches it): signals are the main thread's to
    set, and setting them from there raised ValueError."""
    import warptex.stops

    monkeypatch.setattr(warptex.stops, "is_the_command", lambda: True)
    assert errors_on_a_thread(warptex.stops.stops_ignored_after_the_work) == []


def test_a_ctrl_c_handler_of_the_caller_s_own_is_kept_while_starting(monkeypatch):
    import warptex.stops

    def own(signum, frame):
        pass

    monkeypatch.setattr(warptex.stops, "is_the_command", lambda: True)
    previous = signal.signal(signal.SIGINT, own)
    try:
        warptex.stops.quiet_while_starting()
        assert signal.getsignal(signal.SIGINT) is own
    finally:
        signal.signal(signal.SIGINT, previous)


_SIGNALLED_AS_PYTHON_ENDS = '''
import os, signal, sys, time
import warptex.stops as stops
stops.is_the_command = lambda: True
class Late:
    def __del__(self):  # as Python tears the command's libraries down, after its handlers
        os.kill(os.getpid(), signal.{signal})
        time.sleep(0.2)
keep = Late()
stops.stops_ignored_after_the_work()
sys.exit(3)
'''


@pytest.mark.parametrize("stop", ["SIGINT", "SIGTERM"])
def test_a_stop_as_python_shuts_down_leaves_the_exit_code(stop):
    """Python puts back the default action of the signals it handles early in its shutdown:
    a handler that exited with the command's code was gone by the time Mitsuba, Dr.Jit and
    Warp were let go, and a finished render was killed by the signal most times."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", _SIGNALLED_AS_PYTHON_ENDS.format(signal=stop)],
                         capture_output=True, text=True, timeout=120)
    assert (run.returncode, run.stderr) == (3, "")


_CLOSED_AT_START = '''
import os, sys
from warptex.cli.console import missing_streams_to_devnull
missing_streams_to_devnull()
with open(os.devnull) as later:
    print(later.fileno(), sys.stderr is not None, file=sys.stdout)
'''


def test_streams_closed_at_the_start_leave_no_standard_descriptor_free():
    """With stdin closed too (`<&- 2>&-`), the null device for stderr took descriptor 0 and
    left 2 free: the next file opened got it, and what libraries write to 2 went there."""
    import subprocess
    import sys

    run = subprocess.run(["sh", "-c", 'exec "$@" <&- 2>&-', "sh", sys.executable, "-c",
                          _CLOSED_AT_START], capture_output=True, text=True, timeout=120)
    fd, stderr_set = run.stdout.split()
    assert int(fd) > 2 and stderr_set == "True", run.stdout
