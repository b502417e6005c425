"""`warptex compare` (issue 7): every file, and rankings that follow from the methods."""

import errno
import json
import os
import re
import signal
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from warptex import compare
from warptex.cli import main
from warptex.compare import measure, methods
from warptex.metrics import histogram_distance, repetition_score


def test_repetition_score_sees_tiling():
    rng = np.random.default_rng(0)
    tile = rng.random((32, 32, 3)).astype(np.float32)
    assert repetition_score(np.tile(tile, (8, 8, 1))) > 0.99
    assert repetition_score(rng.random((256, 256, 3)).astype(np.float32)) < 0.1


def test_histogram_distance_is_zero_for_the_exemplar_itself():
    rng = np.random.default_rng(1)
    ex = rng.random((16, 16, 3)).astype(np.float32)
    vol = np.repeat(ex[None], 16, axis=0)  # every x-slice is the exemplar
    assert histogram_distance(vol, ex, 0) == 0.0
    assert histogram_distance(np.zeros_like(vol), ex, 0) > 1.5


def test_compare_writes_every_file_and_ranks_the_baselines(tmp_path, data_dir, warp_device):
    out = tmp_path / "cmp"
    code = main(["compare", str(data_dir / "granite_64.png"), "--size", "16",
                 "--methods", "lazy,tiled,extrude,noise,flat", "-o", str(out)])
    assert code == 0
    assert {p.name for p in out.iterdir()} == {"sheet.png", "table.md", "table.json"}
    rows = {r["method"]: r for r in json.loads((out / "table.json").read_text())["methods"]}
    assert set(rows) == {"lazy", "tiled", "extrude", "noise", "flat"}
    # Noise has no structure: the worst neighbourhood energy on every axis. A flat volume,
    # no texture either, scores far better: what the energy rewards.
    for axis in range(3):
        assert rows["noise"]["energy"][axis] == max(r["energy"][axis] for r in rows.values())
        assert rows["flat"]["energy"][axis] < rows["noise"]["energy"][axis] / 2
        # Completeness looks the other way: the flat volume lacks every textured patch.
        assert rows["flat"]["completeness"][axis] > rows["lazy"]["completeness"][axis] + 0.2
    assert rows["flat"]["repetition"] == 0.0
    # Extrusion is perfect along z and, across it, worst of all but noise; lazy synthesis is
    # even on all three.
    extrude = rows["extrude"]["energy"]
    assert extrude[2] == 0.0 and min(extrude[:2]) > max(rows["lazy"]["energy"])
    for axis in (0, 1):
        ranked = sorted(rows, key=lambda m, axis=axis: rows[m]["energy"][axis], reverse=True)
        assert ranked[:2] == ["noise", "extrude"]
    # Tiling repeats; lazy synthesis does not.
    assert rows["tiled"]["repetition"] > 0.9 > rows["lazy"]["repetition"]
    assert "| lazy |" in (out / "table.md").read_text()
    # The figures say where they were measured: volume, machine, versions, date, device.
    table = json.loads((out / "table.json").read_text())
    run = table["run"]
    assert table["format"] == 6 and table["axes"] == ["x", "y", "z"]
    assert table["exemplar"] == "granite_64.png"  # its name: no local path in a shared table
    assert run["size"] == 16 and run["seed"] == 0 and run["cores"] >= 1 and run["passes"] == 2
    # Both methods that run the engine say with how many passes.
    assert rows["lazy"]["notes"] == rows["tiled"]["notes"] == "correction passes per level: 2"
    assert run["cpu"] and run["warp"] and 1 <= run["threads"] <= run["cores"]
    assert {"numpy", "scipy", "python", "mitsuba", "drjit", "warptex_code"} <= set(
        run["versions"])
    # How the numbers were taken: the methods' settings, the measures', timing and memory.
    assert run["settings"]["lazy"] == {"passes": 2, "jitter": 1.0, "levels": 3,
                                       "subpasses": 1, "shifted_tiles": False}
    assert "kopf" not in run["settings"]
    assert run["measures"]["repetition_slice"] == 256 and run["measures"]["patch"] == 5
    # Completeness reads every slice patch, the one-way measures every second.
    assert run["measures"]["completeness_patch_stride"] == 1
    assert run["measures"]["patch_stride"] == 2
    assert "fresh process" in run["timing"] and "resident host memory" in run["memory"]
    assert run["scores"].startswith("Lower is better in every score. energy:")
    assert run["scores"] in (out / "table.md").read_text()  # the legend of table.md
    # The lazy engine's candidates are computed and timed apart, once: tiled reads them.
    for method, row in rows.items():
        assert ((row["precompute_seconds"] or 0) > 0) == (method == "lazy")
        assert row["device_peak_mib"] is None or row["device"] == "cuda"
    assert "Lower is better in every score" in (out / "table.md").read_text()
    assert datetime.strptime(run["date"], "%Y-%m-%dT%H:%M:%SZ")  # ISO 8601, UTC
    from warptex.exemplar import Exemplar

    exemplar = Exemplar.load(data_dir / "granite_64.png")
    assert run["exemplar_digest"] == exemplar.digest() and run["exemplar_max_size"] is None
    assert run["axis_exemplars"] == [{"file": "granite_64.png", "size": [64, 64],
                                      "digest": exemplar.digest()}] * 3
    assert f"16^3, seed 0; {run['cpu']}" in (out / "table.md").read_text()
    assert rows["lazy"]["device"] in ("cpu", "cuda") and rows["noise"]["device"] == "cpu"
    assert main(["compare", str(data_dir / "granite_64.png"), "--methods", "bogus",
                 "-o", str(out)]) == 2


def test_compare_runs_lazy_synthesis_with_the_passes_asked_for(tmp_path, data_dir,
                                                              warp_device):
    from warptex import metrics
    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar
    from warptex.synthesis import Synthesizer

    out = tmp_path / "cmp"
    path = data_dir / "granite_64.png"
    assert main(["compare", str(path), "--size", "16", "--methods", "lazy", "--seed", "3",
                 "--passes", "1", "-o", str(out)]) == 0
    (row,) = json.loads((out / "table.json").read_text())["methods"]
    ex = Exemplar.load(path)
    one = Synthesizer(precompute(ex), seed=3, passes=1).box((0, 0, 0), (16, 16, 16))
    assert not np.array_equal(one, Synthesizer(precompute(ex), seed=3).box((0, 0, 0),
                                                                             (16, 16, 16)))
    expected = [metrics.neighborhood_energy(one, ex.colors, a) for a in range(3)]
    assert row["energy"] == pytest.approx(expected, rel=1e-6)
    assert row["notes"] == "correction passes per level: 1"
    assert "correction passes per level: 1 |" in (out / "table.md").read_text()
    assert json.loads((out / "table.json").read_text())["run"]["passes"] == 1
    assert "16^3, seed 3, 1 correction passes; " in (out / "table.md").read_text()


def test_compare_shrinks_the_exemplar_to_max_size(tmp_path, data_dir, warp_device):
    from warptex import metrics
    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar
    from warptex.synthesis import Synthesizer

    out = tmp_path / "cmp"
    path = data_dir / "granite_64.png"
    assert main(["compare", str(path), "--size", "16", "--methods", "lazy",
                 "--exemplar-max-size", "32", "-o", str(out)]) == 0
    table = json.loads((out / "table.json").read_text())
    ex = Exemplar.load(path, max_size=32)
    box = Synthesizer(precompute(ex)).box((0, 0, 0), (16, 16, 16))
    expected = [metrics.neighborhood_energy(box, ex.colors, a) for a in range(3)]
    assert table["methods"][0]["energy"] == pytest.approx(expected, rel=1e-6)
    assert table["run"]["exemplar_size"] == [32, 32] and table["run"]["exemplar_max_size"] == 32
    assert table["run"]["exemplar_digest"] == ex.digest()
    assert (out / "table.md").read_text().startswith("# granite_64.png, shrunk to 32x32\n")


def test_compare_runs_lazy_and_kopf_with_the_feature_distance(tmp_path, data_dir, warp_device):
    """--feature-distance: lazy synthesis and Kopf match the feature-distance channel, so
    their volumes are those made apart from the exemplar loaded with it; the measures take
    its colors; the table says so."""
    from warptex import metrics
    from warptex.baselines.kopf import synthesize
    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar
    from warptex.synthesis import Synthesizer

    path = data_dir / "granite_64.png"
    out = tmp_path / "cmp"
    assert main(["compare", str(path), "--size", "16", "--methods", "lazy,kopf",
                 "--feature-distance", "-o", str(out)]) == 0
    table = json.loads((out / "table.json").read_text())
    rows = {r["method"]: r for r in table["methods"]}
    ex = Exemplar.load(path, feature_distance="auto")
    assert ex.features.shape[2] == 4 and table["run"]["exemplar_digest"] == ex.digest()
    lazy = Synthesizer(precompute(ex)).box((0, 0, 0), (16, 16, 16))
    assert rows["lazy"]["energy"] == [metrics.neighborhood_energy(lazy, ex.colors, a)
                                      for a in range(3)]
    kopf = synthesize(ex, size=16, seed=0, progress=False)
    assert rows["kopf"]["energy"] == [metrics.neighborhood_energy(kopf, ex.colors, a)
                                      for a in range(3)]
    assert table["run"]["feature_distance"] is True and table["run"]["feature_mask"] is None
    assert "16^3, seed 0, feature distance;" in (out / "table.md").read_text()


def test_a_feature_mask_marks_the_one_exemplar_and_reaches_the_lazy_cube(tmp_path, data_dir,
                                                                       capsys):
    """A mask is read with the exemplar, named in the table, passed to the lazy cube's
    plugin; beside --feature-distance or --ey/--ez it is refused before any work."""
    from warptex.compare import Setup
    from warptex.compare.methods import _cube_texture, _Job
    from warptex.exemplar import Exemplar

    granite = data_dir / "granite_64.png"
    gray = np.asarray(Image.open(granite).convert("L"))
    mask = tmp_path / "mask.png"
    Image.fromarray(((gray > np.median(gray)) * 255).astype(np.uint8)).save(mask)
    setup = Setup(granite, 16, feature_mask=mask)
    assert setup.exemplars()[0].digest() == Exemplar.load(granite, feature_mask=mask).digest()
    texture = _cube_texture("lazy", _Job(setup, setup.exemplars()), np.zeros((16, 16, 16, 3)))
    assert texture["feature_mask"] == str(mask) and "feature_distance" not in texture
    automatic = Setup(granite, 16, feature_distance=True)
    assert _cube_texture("lazy", _Job(automatic, automatic.exemplars()),
                         np.zeros((16, 16, 16, 3)))["feature_distance"] is True
    with pytest.raises(ValueError, match="feature_mask and feature_distance exclude"):
        Setup(granite, feature_mask=mask, feature_distance=True)
    for axis in ("ey", "ez"):
        with pytest.raises(ValueError, match="feature_mask marks one exemplar"):
            Setup(granite, feature_mask=mask, **{axis: granite})
    out = tmp_path / "cmp"
    assert main(["compare", str(granite), "--feature-mask", str(mask), "--ey", str(granite),
                 "--methods", "noise", "-o", str(out)]) == 2
    assert "--feature-mask marks one image" in capsys.readouterr().err and not out.exists()
    assert main(["compare", str(granite), "--size", "16", "--feature-mask", str(mask),
                 "--methods", "noise", "-o", str(out)]) == 0
    run = json.loads((out / "table.json").read_text())["run"]
    assert run["feature_mask"] == "mask.png" and run["feature_distance"] is True
    assert "features from mask.png;" in (out / "table.md").read_text()


@pytest.fixture
def swapped_file(tmp_path, data_dir):
    """Granite turned a quarter and its red and blue swapped: another exemplar of the same
    size and channels, far from granite's patches and colors."""
    from PIL import Image

    granite = np.asarray(Image.open(data_dir / "granite_64.png"))
    Image.fromarray(np.ascontiguousarray(np.rot90(granite)[..., ::-1])).save(
        tmp_path / "swapped.png")
    return tmp_path / "swapped.png"


def test_compare_measures_each_axis_against_its_own_exemplar(tmp_path, data_dir, swapped_file,
                                                             warp_device):
    """--ez gives the z axis an exemplar of its own: lazy synthesis and Kopf read it, the z
    slices are measured against it, extrusion stacks it, noise draws from both, and the
    table names each axis' file; --jitter and --shifted-tiles reach the lazy engine, whose
    volume is the one any other command gets with the same settings, and --seed each
    method that draws."""
    from warptex import metrics
    from warptex.baselines.kopf import synthesize
    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar
    from warptex.synthesis import Synthesizer

    granite_file = data_dir / "granite_64.png"
    out = tmp_path / "cmp"
    assert main(["compare", str(granite_file), "--ez", str(swapped_file), "--size", "16",
                 "--methods", "lazy,kopf,extrude,flat,noise", "--jitter", "0.5",
                 "--shifted-tiles", "--seed", "3", "-o", str(out)]) == 0
    rows = {r["method"]: r for r in json.loads((out / "table.json").read_text())["methods"]}
    granite, swapped = Exemplar.load(granite_file), Exemplar.load(swapped_file)
    axes = (granite, granite, swapped)
    candidates = precompute(*axes)
    lazy = Synthesizer(candidates, seed=3, jitter=0.5, passes=2,
                       shifted_tiles=True).box((0, 0, 0), (16, 16, 16))
    assert rows["lazy"]["energy"] == [metrics.neighborhood_energy(lazy, e, a)
                                      for a, e in enumerate(axes)]
    kopf = synthesize(None, size=16, seed=3, progress=False, exemplars=axes)
    energy = [metrics.neighborhood_energy(kopf, e, a) for a, e in enumerate(axes)]
    assert rows["kopf"]["energy"] == energy
    seed_0 = synthesize(None, size=16, seed=0, progress=False, exemplars=axes)
    assert energy != [metrics.neighborhood_energy(seed_0, e, a) for a, e in enumerate(axes)]
    assert rows["extrude"]["energy"][2] == 0.0 and rows["extrude"]["energy"][0] > 0.2
    pixels = np.concatenate([granite.colors, swapped.colors]).reshape(-1, 3)
    flat = np.broadcast_to(pixels.mean(axis=0), (16, 16, 16, 3)).astype(np.float32)
    assert rows["flat"]["histogram"] == [metrics.histogram_distance(flat, e, a)
                                         for a, e in enumerate(axes)]
    noise = metrics.iid_noise(pixels[:, None], (16, 16, 16), seed=3)
    assert rows["noise"]["energy"] == [metrics.neighborhood_energy(noise, e, a)
                                       for a, e in enumerate(axes)]
    table = json.loads((out / "table.json").read_text())
    assert [e["file"] for e in table["run"]["axis_exemplars"]] == [
        "granite_64.png", "granite_64.png", "swapped.png"]
    assert table["run"]["axis_exemplars"][2]["digest"] == swapped.digest()
    assert table["run"]["settings"]["lazy"]["jitter"] == 0.5
    assert table["run"]["settings"]["lazy"]["shifted_tiles"] is True
    markdown = (out / "table.md").read_text()
    assert markdown.startswith("# x: granite_64.png; y: granite_64.png; z: swapped.png\n")
    assert "16^3, seed 3, jitter 0.5, shifted tiles;" in markdown


def test_the_passes_reach_the_rendered_cube_and_the_tiled_volume(data_dir, warp_device):
    from warptex.compare import Setup
    from warptex.compare.methods import _cube_texture, _Job, _tiled
    from warptex.exemplar import Exemplar

    path = data_dir / "granite_64.png"
    ex = Exemplar.load(path)

    def job(setup):
        return _Job(setup, (ex, ex, ex))

    volume = np.zeros((8, 8, 8, 3), np.float32)
    one_pass = job(Setup(path, passes=1))
    assert _cube_texture("lazy", one_pass, volume)["passes"] == 1
    assert "exemplar_max_size" not in _cube_texture("lazy", one_pass, volume)
    shrunk = job(Setup(path, passes=1, max_size=24))
    assert _cube_texture("lazy", shrunk, volume)["exemplar_max_size"] == 24
    assert _cube_texture("lazy", job(Setup(path, tileable=False)), volume)["tileable"] == "no"
    one, two = (_tiled(job(Setup(path, passes=passes)), 8) for passes in (1, 2))
    assert not np.array_equal(one, two)
    with pytest.raises(ValueError, match="passes must be within"):
        Setup(path, 16, passes=9)


def test_a_setting_refused_in_a_method_s_process_comes_through_as_itself(data_dir):
    """The worker's SettingError reaches the caller whole, not as a broken process pool."""
    import pickle

    from warptex import compare
    from warptex.settings import SettingError

    error = pickle.loads(pickle.dumps(SettingError("max_size", "must be at least 16")))
    assert (error.name, error.problem, str(error)) == ("max_size", "must be at least 16",
                                                      "max_size must be at least 16")
    with pytest.raises(SettingError, match="max_size must be at least 16 pixels, got 8"):
        compare.Setup(data_dir / "granite_64.png", 16, max_size=8)
    # Past the parent's checks, the worker's own refusal.
    setup = compare.Setup(data_dir / "granite_64.png", 16)
    object.__setattr__(setup, "passes", 99)
    with pytest.raises(SettingError, match="passes must be within"):
        compare.compare(setup, ["tiled"], progress=False)


def test_every_rendered_cube_shows_linear_colors(data_dir, warp_device, srgb_decoded):
    """The grid textures of the other methods are decoded from sRGB as the plugin decodes
    the lazy cube's, so cubes compare in one color space; a float exemplar is left as is."""
    from warptex.compare import Setup
    from warptex.compare.methods import _cube_texture, _Job
    from warptex.exemplar import Exemplar

    ex = Exemplar.load(data_dir / "granite_64.png")
    volume = np.random.default_rng(0).random((4, 5, 6, 3)).astype(np.float32)
    for srgb, expected in ((True, srgb_decoded(volume)), (False, volume)):
        ex.srgb = srgb
        job = _Job(Setup(ex.path), (ex, ex, ex))
        grid = _cube_texture("tiled", job, volume)["volume"]["data"]
        np.testing.assert_allclose(np.array(grid), expected.transpose(2, 1, 0, 3), rtol=1e-5)


def test_a_flat_cube_renders_as_its_converged_shading_without_noise(warp_device):
    """Each visible face of a one-color cube shows one color: albedo x (sun's cosine-weighted
    irradiance / pi + sky), what the path-traced sun and sky converge to; the sky around
    it. Only pixels the cube's edges cut (antialiased) show anything else."""
    from warptex.srgb import srgb_to_linear

    albedo, sky = np.array([0.45, 0.38, 0.28]), np.array(methods._SKY)
    sun = -np.array(methods._SUN_DIRECTION) / np.linalg.norm(methods._SUN_DIRECTION)
    irradiance = np.array(methods._SUN_IRRADIANCE)
    faces = [albedo * (irradiance * sun[axis] / np.pi + sky) for axis in range(3)]
    image = srgb_to_linear(compare.render_cube({"type": "rgb", "value": list(albedo)},
                                               resolution=64)).reshape(-1, 3)
    for expected in (*faces, sky):
        matches = np.abs(image - expected).max(axis=1) < 2e-3
        assert matches.mean() > 0.05, expected
        image = image[~matches]
    assert len(image) < 0.05 * 64 * 64  # the edges


def test_compare_runs_both_kopf_variants(tmp_path, data_dir, warp_device):
    out = tmp_path / "cmp"
    assert main(["compare", str(data_dir / "granite_64.png"), "--size", "16",
                 "--methods", "kopf,kopf-meanshift", "-o", str(out)]) == 0
    rows = {r["method"]: r for r in json.loads((out / "table.json").read_text())["methods"]}
    assert set(rows) == {"kopf", "kopf-meanshift"}
    plain, clustered = rows["kopf"], rows["kopf-meanshift"]
    # Clustering keeps granite's grain instead of averaging it out: colour and patch
    # distributions come closer to the exemplar's, while the L2 neighbourhood energy, which
    # rewards blur, rises.
    for axis in range(3):
        assert clustered["histogram"][axis] < 0.7 * plain["histogram"][axis]
        assert clustered["swd"][axis] < 0.7 * plain["swd"][axis]
        assert clustered["energy"][axis] > plain["energy"][axis]


@pytest.fixture
def ramp_file(tmp_path, data_dir):
    """Granite over a ramp from its left edge to its right: a photo whose left and right
    edges form a seam."""
    from PIL import Image

    granite = np.asarray(Image.open(data_dir / "granite_64.png"), dtype=np.float64)
    ramp = 0.5 * granite + np.linspace(0, 127, 64)[None, :, None]
    Image.fromarray(ramp.astype(np.uint8)).save(tmp_path / "ramp.png")
    return tmp_path / "ramp.png"


def test_compare_follows_the_setting_tileable(tmp_path, ramp_file, warp_device):
    """--tileable reaches the lazy engine's candidates, Kopf's search and the measures, and
    the report says which it was."""
    from warptex import metrics
    from warptex.baselines.kopf import synthesize
    from warptex.candidates import precompute
    from warptex.exemplar import Exemplar
    from warptex.synthesis import Synthesizer

    out = tmp_path / "cmp"
    assert main(["compare", str(ramp_file), "--size", "16", "--methods", "lazy,kopf",
                 "--tileable", "yes", "-o", str(out)]) == 0
    table = json.loads((out / "table.json").read_text())
    assert table["run"]["tileable"] == "yes"
    assert "16^3, seed 0, tileable yes; " in (out / "table.md").read_text()
    rows = {r["method"]: r for r in table["methods"]}
    ex = Exemplar.load(ramp_file)
    assert ex.seams() == (False, True)
    volumes = {"lazy": Synthesizer(precompute(ex, tileable=True)).box((0, 0, 0), (16, 16, 16)),
               "kopf": synthesize(ex, size=16, progress=False, tileable=True)}
    for method, volume in volumes.items():
        torus = [metrics.neighborhood_energy(volume, ex, a, tileable=True) for a in range(3)]
        assert rows[method]["energy"] == pytest.approx(torus, rel=1e-6), method
        # The wrapped patches join the exemplar's distribution of patches.
        torus = [metrics.sliced_wasserstein(volume, ex, a, tileable=True) for a in range(3)]
        assert rows[method]["swd"] == pytest.approx(torus, rel=1e-6), method
        assert torus != [metrics.sliced_wasserstein(volume, ex, a) for a in range(3)]
    auto = synthesize(ex, size=16, progress=False)
    assert not np.array_equal(auto, volumes["kopf"])


def test_volume_command_runs_kopf_with_the_setting_tileable(tmp_path, ramp_file, warp_device):
    from warptex.baselines.kopf import synthesize
    from warptex.exemplar import Exemplar

    out = tmp_path / "k.npy"
    assert main(["volume", str(ramp_file), "--method", "kopf", "--size", "8", "--tileable",
                 "no", "-o", str(out)]) == 0
    ramp = Exemplar.load(ramp_file)
    expected = synthesize(ramp, size=8, progress=False, tileable=False)
    np.testing.assert_array_equal(np.load(out), expected)
    assert not np.array_equal(expected, synthesize(ramp, size=8, progress=False))


def test_volume_command_runs_kopf_with_its_seed_and_mean_shift(tmp_path, data_dir,
                                                                warp_device):
    """--seed and --mean-shift reach Kopf: the volume is the one Python makes with them,
    which neither setting's default makes."""
    from warptex.baselines.kopf import synthesize
    from warptex.exemplar import Exemplar

    out = tmp_path / "k.npy"
    path = data_dir / "granite_64.png"
    assert main(["volume", str(path), "--method", "kopf", "--size", "8", "--seed", "3",
                 "--mean-shift", "-o", str(out)]) == 0
    granite = Exemplar.load(path)
    expected = synthesize(granite, size=8, seed=3, mean_shift=True, progress=False)
    np.testing.assert_array_equal(np.load(out), expected)
    for other in ({"seed": 0, "mean_shift": True}, {"seed": 3, "mean_shift": False}):
        assert not np.array_equal(expected, synthesize(granite, size=8, progress=False, **other))


def test_volume_command_leaves_the_free_axis_of_kopf_unconstrained(tmp_path, data_dir,
                                                                   warp_device, capsys):
    """--free-axis y: Kopf's solid of the x and z exemplars alone (section 6.2), as from
    Python; refused for lazy synthesis and beside an exemplar for that axis."""
    from warptex.baselines.kopf import synthesize
    from warptex.exemplar import Exemplar

    path = data_dir / "granite_64.png"
    out = tmp_path / "k.npy"
    assert main(["volume", str(path), "--method", "kopf", "--size", "8", "--free-axis", "y",
                 "-o", str(out)]) == 0
    assert "y free" in capsys.readouterr().out
    granite = Exemplar.load(path)
    expected = synthesize(None, exemplars=(granite, None, granite), size=8, progress=False)
    np.testing.assert_array_equal(np.load(out), expected)
    assert not np.array_equal(expected, synthesize(granite, size=8, progress=False))
    refused = tmp_path / "refused.npy"
    assert main(["volume", str(path), "--free-axis", "y", "-o", str(refused)]) == 2
    assert "--free-axis applies to --method kopf only" in capsys.readouterr().err
    assert main(["volume", str(path), "--method", "kopf", "--size", "8", "--free-axis", "z",
                 "--ez", str(path), "-o", str(refused)]) == 2
    assert "drop --ez" in capsys.readouterr().err
    assert main(["volume", str(path), "--method", "kopf", "--size", "8", "--free-axis", "x",
                 "--ey", str(path), "-o", str(refused)]) == 2
    assert "give the y axis' exemplar as EXEMPLAR, not --ey" in capsys.readouterr().err
    assert not refused.exists()


def test_volume_command_refuses_mean_shift_for_lazy(tmp_path, data_dir, capsys):
    out = tmp_path / "v.npy"
    assert main(["volume", str(data_dir / "granite_64.png"), "--mean-shift", "-o", str(out)]) == 2
    assert "--mean-shift applies to --method kopf only" in capsys.readouterr().err
    assert not out.exists()


@pytest.fixture
def measured(data_dir, monkeypatch):
    """``measure._measure`` in this process, without the rendered cube."""
    from warptex import compare

    monkeypatch.setattr(measure, "render_cube", lambda texture: np.zeros((2, 2, 3)))
    monkeypatch.setattr(measure, "_cube_texture", lambda *args: {})
    path = str(data_dir / "granite_64.png")
    return lambda method, size=16, tileable="auto", seed=0: measure._measure(
        method, compare.Setup(path, size, tileable=tileable, seed=seed))


def test_scores_are_those_of_the_metrics_axis_by_axis(measured, data_dir):
    from warptex import compare, metrics
    from warptex.exemplar import Exemplar

    row = measured("extrude")
    ex = Exemplar.load(data_dir / "granite_64.png")
    job = methods._Job(compare.Setup(ex.path, 16), (ex, ex, ex))
    volume = methods._extrude(job, 16)
    for key, metric in (("energy", metrics.neighborhood_energy),
                        ("completeness", metrics.completeness_energy),
                        ("swd", metrics.sliced_wasserstein),
                        ("histogram", metrics.histogram_distance)):
        assert row[key] == [metric(volume, ex.colors, axis) for axis in range(3)], key
    for key in ("energy", "completeness"):  # three different values: an axis swap shows
        assert len(set(row[key])) == 3, key
    # The sheet's slices are the middle ones, oriented like each axis' exemplar.
    for a in range(3):
        np.testing.assert_array_equal(row["slices"][a], metrics.axis_slice(volume, a, 8))
    assert not np.array_equal(row["slices"][0], metrics.axis_slice(volume, 0, 0))
    large = methods._extrude_large(job, volume)
    assert large.shape[:2] == (compare.LARGE, compare.LARGE)
    assert row["repetition"] == metrics.repetition_score(large)


def test_the_patch_scores_follow_the_setting_tileable_and_not_the_methods_seed(measured,
                                                                             data_dir):
    """Energy, completeness and sliced Wasserstein distance measure against the exemplar's
    patches as ``tileable`` says (granite tiles: "no" takes its wrapped patches away), and
    the distance's projections are drawn from the measures' own seed, as table.json gives
    it (``swd_seed``), whatever seed the methods ran with."""
    from warptex import compare, metrics
    from warptex.exemplar import Exemplar

    row = measured("extrude", tileable=False, seed=3)
    ex = Exemplar.load(data_dir / "granite_64.png")
    volume = methods._extrude(methods._Job(compare.Setup(ex.path, 16), (ex, ex, ex)), 16)
    for key, metric in (("energy", metrics.neighborhood_energy),
                        ("completeness", metrics.completeness_energy),
                        ("swd", metrics.sliced_wasserstein)):
        expected = [metric(volume, ex, a, tileable=False) for a in range(3)]
        assert row[key] == expected, key
        assert expected != [metric(volume, ex, a) for a in range(3)], key
    assert row["swd"] != [metrics.sliced_wasserstein(volume, ex, a, seed=3, tileable=False)
                          for a in range(3)]


def test_the_time_leaves_out_the_warm_up_run(measured, monkeypatch):
    """The first, small run builds the kernels; the time is that of the second alone (on a
    clock that the warm-up moves 100 s and the timed run 1 s)."""
    import types

    from warptex import metrics

    clock = [0.0]
    monkeypatch.setattr(measure, "time", types.SimpleNamespace(perf_counter=lambda: clock[0]))

    def slow_first(job, size):
        clock[0] += 100.0 if size == 8 else 1.0
        return metrics.iid_noise(job.axes[0].colors, (size, size, size), job.setup.seed)

    monkeypatch.setitem(methods._RUN, "noise", (slow_first, methods._noise_large))
    assert measured("noise")["seconds"] == 1.0


def test_repeated_runs_are_each_kept_and_the_median_reported(data_dir, monkeypatch, capsys,
                                                              tmp_path):
    """--repeats 3: three timed runs (each a whole volume), their median as the seconds, all
    three in table.json; repeats below 1 are refused."""
    import types

    from warptex import compare

    # Runs of 5, 2 and 1 s: neither their mean, first, last, least nor largest is 2.
    clock = iter([0.0, 5.0, 10.0, 12.0, 20.0, 21.0])
    monkeypatch.setattr(measure, "time", types.SimpleNamespace(perf_counter=lambda: next(clock)))
    monkeypatch.setattr(measure, "render_cube", lambda texture: np.zeros((2, 2, 3)))
    monkeypatch.setattr(measure, "_cube_texture", lambda *args: {})
    sizes = []
    noise, noise_large = methods._RUN["noise"]
    monkeypatch.setitem(methods._RUN, "noise", (lambda job, size: sizes.append(size)
                                                or noise(job, size), noise_large))
    setup = compare.Setup(data_dir / "granite_64.png", 16)
    row = measure._measure("noise", setup, repeats=3)
    assert sizes == [8, 16, 16, 16]  # the warm-up, then three timed volumes
    assert row["seconds_runs"] == [5.0, 2.0, 1.0] and row["seconds"] == 2.0
    result = compare.MethodResult(**row)
    compare.write_report(compare.Comparison(setup, [result]), tmp_path)
    table = json.loads((tmp_path / "table.json").read_text())
    assert table["run"]["repeats"] == 3
    assert table["methods"][0]["seconds_runs"] == [5.0, 2.0, 1.0]
    assert "the median of 3 wall-clock runs" in (tmp_path / "table.md").read_text()
    with pytest.raises(ValueError, match="repeats must be"):
        compare.compare(setup, ["noise"], repeats=0)
    assert main(["compare", str(data_dir / "granite_64.png"), "--repeats", "0",
                 "-o", str(tmp_path / "c")]) == 2
    assert "--repeats must be at least 1, got 0" in capsys.readouterr().err


def test_a_methods_process_says_on_the_bar_when_it_builds_the_kernels(data_dir, tmp_path,
                                                                      monkeypatch):
    """In the method's process, where the command's note would be drawn over: a phase."""
    import queue

    from warptex import warp_runtime

    monkeypatch.setattr(warp_runtime, "build_folder", lambda name, cpu: tmp_path / name)
    monkeypatch.setattr(warp_runtime, "_LAUNCHED", set())  # as in a fresh process
    monkeypatch.setattr(measure, "render_cube", lambda texture: np.zeros((2, 2, 3)))
    monkeypatch.setattr(measure, "_cube_texture", lambda *args: {})
    phases = queue.Queue()
    monkeypatch.setattr(measure, "_phases", phases)
    measure._measure_in_child("lazy", compare.Setup(data_dir / "granite_64.png", 8), 1)
    said = [phases.get_nowait() for _ in range(phases.qsize())]
    built = "Warp builds the kernels (once a version), then pre-computing candidates"
    assert said.count(built) == 1 and said.index(built) < said.index("8^3, timed"), said


def test_peak_memory_is_that_of_the_timed_runs_in_mib(measured, monkeypatch):
    """The memory window holds the timed runs alone: not the warm-up before them, nor the
    large slice and the measures after; its rise in bytes is reported in MiB."""

    said = []

    class Window:  # a PeakMemory that says when it opens and closes, and rose by 3 MiB
        growth = 0

        def __enter__(self):
            said.append("open")
            return self

        def __exit__(self, *exc):
            said.append("close")
            self.growth = 3 * 2**20

    noise, noise_large = methods._RUN["noise"]
    monkeypatch.setattr(measure, "PeakMemory", Window)
    monkeypatch.setitem(methods._RUN, "noise", (
        lambda job, size: said.append(size) or noise(job, size),
        lambda job, volume: said.append("large") or noise_large(job, volume)))
    row = measured("noise")
    assert said == [8, "open", 16, "close", "large"]
    assert row["peak_mib"] == 3.0


def test_table_cells_sit_under_their_headers():
    from warptex.compare import MethodResult, table_markdown

    r = MethodResult("m", energy=[1, 2, 3], completeness=[1.5, 2.5, 3.5], swd=[4, 5, 6],
                     histogram=[7, 8, 9], repetition=0.5, seconds=1.25, peak_mib=2.0,
                     precompute_seconds=0.75)
    for gpu in (None, 12.0):
        r.device_peak_mib = gpu
        header, _, line = table_markdown([r]).splitlines()
        cells = dict(zip([c.strip() for c in header.split("|")],
                         [c.strip() for c in line.split("|")], strict=True))
        assert cells["energy x / y / z"] == "1.000 / 2.000 / 3.000"
        assert cells["completeness x / y / z"] == "1.500 / 2.500 / 3.500"
        assert cells["SWD x / y / z"] == "4.000 / 5.000 / 6.000"
        assert cells["histogram x / y / z"] == "7.000 / 8.000 / 9.000"
        assert cells["repetition"] == "0.500" and cells["seconds"] == "1.25"
        assert cells["pre-computation s"] == "0.75" and cells["peak MiB"] == "2.0"
        assert cells.get("GPU MiB") == (None if gpu is None else "12.0")
    # Every column under its rule (Markdown drops a row of fewer); none values as "-"; the
    # GPU column where any method ran there, a CPU method's cell "-".
    r.notes, r.device = "n", "cuda:0"
    cpu = compare.MethodResult("c", [0] * 3, [0] * 3, [0] * 3, [0] * 3, 0.0, 0.0, 0.0)
    header, rule, line, cpu_line = table_markdown([r, cpu]).splitlines()
    assert header.count("|") == rule.count("|") == line.count("|") == cpu_line.count("|")
    cells = dict(zip([c.strip() for c in header.split("|")],
                     [c.strip() for c in cpu_line.split("|")], strict=True))
    assert cells["pre-computation s"] == cells["GPU MiB"] == "-"
    assert (cells["device"], cells["notes"]) == ("cpu", "")
    cells = dict(zip([c.strip() for c in header.split("|")],
                     [c.strip() for c in line.split("|")], strict=True))
    assert (cells["device"], cells["notes"]) == ("cuda:0", "n")


def test_the_report_says_what_was_measured_where(tmp_path, data_dir, monkeypatch):
    """table.md's run line and legend, and table.json's exemplar of the x axis, from
    hand-made results: one run's seconds, the repetition slice's edge and exclusion, the
    machine's cores, the GPU legend where a method ran there; each axis' exemplar size
    width first; the sheet titled."""
    from warptex.exemplar import Exemplar

    wide = tmp_path / "wide.png"
    Image.open(data_dir / "granite_64.png").crop((0, 0, 48, 32)).save(wide)
    granite = data_dir / "granite_64.png"
    drawn = {}
    monkeypatch.setattr("warptex.parallel.THREADS", 7)  # threads apart from cores
    monkeypatch.setattr("warptex.sheets.sheet",
                        lambda rows, **kw: drawn.update(kw) or np.zeros((2, 2, 3), np.uint8))
    slices = [np.zeros((4, 4, 3), np.float32)] * 3
    rows = [compare.MethodResult(m, [0.0] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3, 0.0, 0.0, 0.0,
                                 slices=slices, device_peak_mib=gpu, seconds_runs=[0.0])
            for m, gpu in (("noise", None), ("lazy", 5.0))]
    setup = compare.Setup(granite, 16, ez=wide)
    compare.write_report(compare.Comparison(setup, rows), tmp_path / "out")
    table = json.loads((tmp_path / "out" / "table.json").read_text())
    run, md = table["run"], (tmp_path / "out" / "table.md").read_text()
    measures = run["measures"]
    assert (f"a {measures['repetition_slice']}-voxel slice at a peak past "
            f"{measures['repetition_exclude']} voxels") in run["scores"]
    assert measures["repetition_slice"] != measures["repetition_exclude"]
    assert "seconds: one wall-clock run in a fresh process" in md
    assert f", {run['cores']} cores, no GPU; warptex" in md and run["threads"] == 7
    assert "GPU MiB: high-water mark of Warp's CUDA memory pool" in md
    assert run["exemplar_digest"] == Exemplar.load(granite).digest()
    assert run["exemplar_size"] == [64, 64]
    assert [a["size"] for a in run["axis_exemplars"]] == [[64, 64], [64, 64], [48, 32]]
    assert drawn["title"] == "x: granite_64.png; y: granite_64.png; z: wide.png: 16^3, seed 0"
    # The settings of the methods that ran: the lazy engine's here, Kopf's defaults there.
    import inspect

    from warptex.baselines import kopf

    assert set(run["settings"]) == {"lazy"}
    rows[1].method = "kopf-meanshift"
    compare.write_report(compare.Comparison(setup, rows), tmp_path / "kopf")
    run = json.loads((tmp_path / "kopf" / "table.json").read_text())["run"]
    defaults = inspect.signature(kopf.synthesize).parameters
    assert run["settings"] == {"kopf": {"iterations": list(defaults["iterations"].default),
                                        "histogram_matching": True}}


def test_stopping_a_comparison_ends_the_running_worker_at_once():
    """Ctrl-C or SIGTERM while a method runs in its worker process ends that process,
    instead of leaving the pool waiting for the method to finish."""
    import multiprocessing
    import os
    import time
    from concurrent.futures import ProcessPoolExecutor

    from warptex.parallel import stop_workers

    def ended(worker) -> bool:
        worker.join(120)
        if worker.exitcode is not None:
            return True
        # The pool's own thread may have reaped it first: then is_alive() stays True on
        # Python 3.11, and only the process table tells.
        try:
            os.kill(worker.pid, 0)
        except ProcessLookupError:
            return True
        return False

    pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
    pool.submit(time.sleep, 600)
    workers = list(pool._processes.values())
    try:
        stop_workers(pool)
        assert workers and all(ended(w) for w in workers)
    finally:
        for worker in workers:
            worker.kill()


def test_report_gives_the_size_of_a_shrunk_exemplar_as_width_by_height(tmp_path, data_dir):
    """A 48-column, 32-row crop shrunk to a larger side of 24: 24x16, [24, 16] in the JSON."""
    path = tmp_path / "wide.png"
    Image.open(data_dir / "granite_64.png").crop((0, 0, 48, 32)).save(path)
    slices = [np.zeros((4, 4, 3), np.float32)] * 3
    results = [compare.MethodResult("noise", [0.0] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3,
                                    0.0, 0.0, 0.0,
                                    slices=slices)]
    compare.write_report(compare.Comparison(compare.Setup(path, 8, max_size=24), results),
                         tmp_path / "out")
    run = json.loads((tmp_path / "out" / "table.json").read_text())["run"]
    assert run["exemplar_size"] == [24, 16]
    assert (tmp_path / "out" / "table.md").read_text().startswith("# wide.png, shrunk to 24x16\n")


def test_large_slices_are_256_pixels_whatever_the_tile():
    """A tile whose side does not divide 256 is repeated past it and cut."""
    tile = np.random.default_rng(0).random((24, 40, 3))
    large = methods._tile_slice(tile, compare.LARGE)
    assert large.shape == (compare.LARGE, compare.LARGE, 3)
    np.testing.assert_array_equal(large[24:48, 40:80], tile)


@pytest.mark.parametrize(("size", "exemplar", "edge"),
                         [(64, (64, 64), 256), (72, (64, 64), 256), (160, (64, 64), 320),
                          (16, (128, 96), 256), (16, (256, 256), 512)])
def test_large_slices_hold_every_period_twice(size, exemplar, edge):
    """The slice is at least 256 voxels and twice the volume (Kopf's period) and the
    exemplar (extrusion's), for the repetition score sees periods up to half of it."""
    assert compare.large_edge(size, exemplar) == edge


def test_the_large_slices_are_taken_at_the_middle_z(monkeypatch):
    """The repetition score's slice is the z-slice the sheet shows, at size // 2: the lazy
    engine's asked for there, 256 voxels each way; a periodic volume's repeated from its own
    middle slice."""
    asked = []

    class Engine:  # a Synthesizer that says which box it is asked for
        def box(self, origin, shape):
            asked.append((origin, shape))
            return np.zeros((*shape, 3), np.float32)

    monkeypatch.setattr(methods, "_synthesizer", lambda job: Engine())
    ex = type("Ex", (), {"shape": (64, 64)})()
    job = methods._Job(None, (ex, ex, ex))
    volume = np.random.default_rng(4).random((16, 16, 16, 3)).astype(np.float32)
    assert methods._lazy_large(job, volume).shape == (256, 256, 3)
    assert asked == [((0, 0, 8), (256, 256, 1))]
    large = methods._periodic_large(job, volume)
    np.testing.assert_array_equal(large[16:32, 48:64], volume[:, :, 8])


def test_a_tiled_volume_of_a_size_its_block_does_not_divide_repeats_by_the_block(
        monkeypatch):
    """At 72^3 the tiled volume is its 64^3 block repeated and cut: its large slice repeats
    that block (score 1), not the 72-voxel cut with a seam in it (it scored 0.19)."""
    from warptex import metrics

    rng = np.random.default_rng(3)
    block = rng.random((64, 64, 64, 3)).astype(np.float32)
    volume = np.tile(block, (2, 2, 2, 1))[:72, :72, :72]
    ex = type("Ex", (), {"shape": (64, 64)})()
    large = methods._tiled_large(methods._Job(None, (ex, ex, ex)), volume)
    assert large.shape[:2] == (256, 256)
    np.testing.assert_array_equal(large[64:128, 128:192], block[:, :, 36])
    assert metrics.repetition_score(large) == pytest.approx(1.0)
    # The volume itself is the block repeated and cut: as large as asked.
    monkeypatch.setattr(methods, "_lazy", lambda job, size: block[:size, :size, :size])
    np.testing.assert_array_equal(methods._tiled(None, 72), volume)


def test_results_come_in_the_order_of_the_methods_asked(monkeypatch, data_dir):
    """Each method's process is replaced by a call here; the rows keep the order asked."""
    def inline(fn, method, *args, **kwargs):
        return {"method": method, "energy": [0.0] * 3, "completeness": [0.0] * 3,
                "swd": [0.0] * 3, "histogram": [0.0] * 3, "repetition": 0.0, "seconds": 0.0,
                "peak_mib": 0.0}

    monkeypatch.setattr(measure, "in_child_process", inline)
    asked = ["noise", "extrude", "tiled", "lazy"]
    results = compare.compare(compare.Setup(data_dir / "granite_64.png", 16), asked,
                              progress=False).results
    assert [r.method for r in results] == asked


def test_methods_are_a_sequence_of_names_not_one_string(monkeypatch, data_dir):
    """A string was split into letters ("unknown method(s) n, o, i, s, e"); a generator was
    used up by the check for names given twice, and nothing ran."""
    def inline(fn, method, *args, **kwargs):
        return {"method": method, "energy": [0.0] * 3, "completeness": [0.0] * 3,
                "swd": [0.0] * 3, "histogram": [0.0] * 3, "repetition": 0.0, "seconds": 0.0,
                "peak_mib": 0.0}

    monkeypatch.setattr(measure, "in_child_process", inline)
    setup = compare.Setup(data_dir / "granite_64.png", 16)
    with pytest.raises(TypeError, match=r"such as \['noise'\], got the string 'noise'"):
        compare.compare(setup, "noise", progress=False)
    results = compare.compare(setup, (m for m in ["noise", "flat"]), progress=False).results
    assert [r.method for r in results] == ["noise", "flat"]


def test_compare_refuses_exemplars_that_one_volume_cannot_mix(tmp_path, data_dir, capsys):
    """Axes whose exemplars differ in channels or in color encoding are refused at once,
    naming the files, and nothing is written."""
    from PIL import Image

    granite = data_dir / "granite_64.png"
    Image.open(granite).convert("L").save(tmp_path / "gray.png")
    np.save(tmp_path / "linear.npy",
            np.asarray(Image.open(granite), np.float32) / 255.0)
    out = tmp_path / "cmp"
    assert main(["compare", str(granite), "--ez", str(tmp_path / "gray.png"),
                 "--methods", "noise", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "same number of feature channels" in err
    assert "z " + str(tmp_path / "gray.png") + " 1" in err and "granite_64.png 3" in err
    assert main(["compare", str(granite), "--ey", str(tmp_path / "linear.npy"),
                 "--methods", "noise", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "encoded differently" in err and "linear.npy linear" in err
    assert "--raw" not in err and "(raw)" not in err  # compare keeps no values as stored
    assert not out.exists()
    with pytest.raises(ValueError, match="encoded differently"):
        compare.compare(compare.Setup(granite, 16, ey=tmp_path / "linear.npy"), ["noise"],
                        progress=False)


def test_an_image_given_under_two_names_is_one_exemplar(tmp_path, data_dir, warp_device):
    """--ey naming a copy of the x axis' image changes no score: one exemplar, as the
    candidates' cache has it; the table still names the file each axis was given."""
    import shutil

    granite = data_dir / "granite_64.png"
    shutil.copy(granite, tmp_path / "copy.png")
    rows = {}
    for name, extra in (("one", []), ("two", ["--ey", str(tmp_path / "copy.png")])):
        out = tmp_path / name
        assert main(["compare", str(granite), *extra, "--size", "16", "--methods",
                     "noise,flat", "-o", str(out)]) == 0
        rows[name] = json.loads((out / "table.json").read_text())
    assert rows["one"]["methods"][0]["energy"] == rows["two"]["methods"][0]["energy"]
    assert [e["file"] for e in rows["two"]["run"]["axis_exemplars"]] == [
        "granite_64.png", "copy.png", "copy.png"]
    assert (tmp_path / "two" / "table.md").read_text().startswith("# granite_64.png\n")


def test_the_lazy_cube_renders_the_exemplars_and_settings_measured(data_dir, swapped_file):
    """The lazy cube's lazy_solid texture names each axis' file where they differ, and
    carries the engine's settings, so it shows the volume the table measures."""
    from warptex.compare import Setup
    from warptex.compare.methods import _cube_texture, _Job

    granite = data_dir / "granite_64.png"
    setup = Setup(granite, 16, seed=3, passes=1, jitter=0.5, shifted_tiles=True, ez=swapped_file)
    job = _Job(setup, setup.exemplars())
    texture = _cube_texture("lazy", job, np.zeros((16, 16, 16, 3)))
    assert {k: texture[k] for k in ("exemplar_x", "exemplar_y", "exemplar_z")} == {
        "exemplar_x": str(granite), "exemplar_y": str(granite), "exemplar_z": str(swapped_file)}
    assert "exemplar" not in texture
    assert (texture["seed"], texture["passes"], texture["jitter"], texture["shifted_tiles"],
            texture["scale"]) == (3, 1, 0.5, True, 16.0)


def test_a_setup_is_checked_as_made(data_dir):
    from warptex.compare import MIN_SIZE, Setup
    from warptex.settings import SettingError

    granite = data_dir / "granite_64.png"
    assert Setup(str(granite), jitter=1).jitter == 1.0 and Setup(granite).paths() == (
        granite, granite, granite)
    assert Setup(granite, ey="y.png").paths() == (granite, Path("y.png"), Path("y.png"))
    for bad, message in (({"size": MIN_SIZE - 1}, "size must be at least 8"),
                         ({"jitter": 65}, "jitter must be within"),
                         ({"shifted_tiles": "yes"}, "shifted_tiles must be True or False"),
                         ({"tileable": "maybe"}, "tileable must be")):
        with pytest.raises((SettingError, ValueError), match=message):
            Setup(granite, **bad)
    with pytest.raises(TypeError, match="exemplar must be a file name"):
        Setup(None)


def test_an_exemplar_s_alpha_is_dropped_with_one_warning_that_fits_compare(tmp_path, data_dir,
                                                                         capfd):
    """The warning comes once, from the command, not again from each method's process, and
    names no --alpha option, which compare does not have."""
    rgba = np.dstack([np.asarray(Image.open(data_dir / "granite_64.png")),
                      np.full((64, 64), 128, np.uint8)])  # half transparent
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    assert main(["compare", str(tmp_path / "rgba.png"), "--size", "16", "--methods",
                 "noise,flat,lazy", "-o", str(tmp_path / "cmp")]) == 0
    err = capfd.readouterr().err
    assert err.count("alpha channel dropped") == 1  # lazy's cube, rendered, read it again
    assert "compare measures colors only" in err and "--alpha" not in err
    assert "AlphaDropped" not in err  # no warning in Python's own format


def test_every_method_sees_the_exemplars_as_first_read(tmp_path, data_dir):
    """The images travel with the Setup: a file changed after the comparison has read it
    changes no method's volume."""
    from PIL import Image

    path = tmp_path / "granite.png"
    Image.open(data_dir / "granite_64.png").save(path)
    setup = compare.Setup(path, 16)
    ex = setup.exemplars()[0]
    Image.fromarray(np.zeros((64, 64, 3), np.uint8) + 200).save(path)
    (row,) = compare.compare(setup, ["flat"], progress=False).results
    mean = ex.colors.reshape(-1, 3).mean(axis=0)
    flat = np.broadcast_to(mean, (16, 16, 16, 3)).astype(np.float32)
    assert row.histogram == [histogram_distance(flat, ex, a) for a in range(3)]


def test_the_progress_bar_names_the_method_running(data_dir, capfd):
    compare.compare(compare.Setup(data_dir / "granite_64.png", 16), ["noise", "flat"])
    bar = capfd.readouterr().err
    assert "methods" in bar and "0/2 [" in bar
    assert bar.index("noise") < bar.index("1/2") < bar.index("flat")


def test_a_setup_holds_plain_values_that_table_json_can_write(tmp_path, data_dir):
    """NumPy integers are taken as the Python ints they are; settings after the size are
    keywords; a Comparison of something else is refused before anything is written."""
    granite = data_dir / "granite_64.png"
    setup = compare.Setup(granite, np.int64(16), seed=np.int64(1), passes=np.int64(2),
                          max_size=np.int64(32), jitter=np.float32(0.5))
    assert [type(v) for v in (setup.size, setup.seed, setup.passes, setup.max_size)] == [int] * 4
    assert type(setup.jitter) is float
    row = compare.MethodResult("noise", [0.0] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3, 0.0, 0.0,
                               0.0, slices=[np.zeros((16, 16, 3), np.float32)] * 3)
    compare.write_report(compare.Comparison(setup, [row]), tmp_path / "out")
    run = json.loads((tmp_path / "out" / "table.json").read_text())["run"]
    assert (run["size"], run["seed"], run["exemplar_max_size"]) == (16, 1, 32)
    with pytest.raises(TypeError):
        compare.Setup(granite, 16, 0)
    with pytest.raises(TypeError, match=r"must be a warptex\.compare\.Comparison"):
        compare.write_report(compare.Comparison(str(granite), [row]), tmp_path / "bad")
    assert not (tmp_path / "bad").exists()
    # A file in the folder's place was a FileExistsError naming sheet.png below it.
    (tmp_path / "a_file").write_text("kept")
    with pytest.raises(ValueError, match=r"a_file/sheet\.png: cannot write, .*a_file is a file, "
                       "not a folder"):
        compare.write_report(compare.Comparison(setup, [row]), tmp_path / "a_file")
    assert (tmp_path / "a_file").read_text() == "kept"


def test_a_folder_lost_during_the_comparison_is_a_write_failure_not_a_traceback(
        tmp_path, data_dir, monkeypatch, capsys):
    """write_report's check of its folder raised a ValueError that the command did not
    take: a file put in the output folder's place meanwhile ended in a traceback."""
    from warptex.cli import main

    out = tmp_path / "out"
    made = compare.compare

    def then_a_file_in_its_place(*args, **kwargs):
        comparison = made(*args, **kwargs)
        out.write_text("someone's file")
        return comparison

    monkeypatch.setattr(compare, "compare", then_a_file_in_its_place)
    assert main(["compare", str(data_dir / "granite_64.png"), "--size", "16", "--methods",
                 "flat", "-o", str(out)]) == 1
    assert capsys.readouterr().err.endswith(f"\nwarptex: error: {out / 'sheet.png'}: cannot "
                                            f"write, {out} is a file, not a folder\n")
    assert out.read_text() == "someone's file"


def _json_disk_full(monkeypatch) -> None:
    """Writes of .json files fail as on a full disk; the others succeed."""
    write_text = Path.write_text

    def full(self, text, *args, **kwargs):
        if self.suffix == ".json":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
        return write_text(self, text, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full)


def test_a_report_that_cannot_be_written_whole_leaves_the_last_one(tmp_path, data_dir,
                                                                   monkeypatch):
    """sheet.png, table.md and table.json are written together: a full disk at the last
    leaves the last report's three files as they were, not a new sheet beside old tables."""
    setup = compare.Setup(data_dir / "granite_64.png", 16)
    row = compare.MethodResult("noise", [0.0] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3, 0.0, 0.0,
                               0.0, slices=[np.zeros((16, 16, 3), np.float32)] * 3)
    out = tmp_path / "out"
    files = compare.write_report(compare.Comparison(setup, [row]), out)
    before = [f.read_bytes() for f in files]
    _json_disk_full(monkeypatch)
    brighter = compare.MethodResult("noise", [1.0] * 3, [1.0] * 3, [1.0] * 3, [1.0] * 3, 1.0,
                                    1.0, 1.0, slices=[np.ones((16, 16, 3), np.float32)] * 3)
    with pytest.raises(OSError) as caught:
        compare.write_report(compare.Comparison(setup, [brighter]), out)
    assert caught.value.filename == str(out / "table.json")
    assert [f.read_bytes() for f in files] == before
    assert sorted(p.name for p in out.iterdir()) == sorted(f.name for f in files)


def test_a_mixed_axis_error_names_the_file_given_for_that_axis(tmp_path, data_dir):
    """An image given twice is merged only after the checks, so they name what was given."""
    import shutil

    granite = data_dir / "granite_64.png"
    shutil.copy(granite, tmp_path / "copy.png")
    Image.open(granite).convert("L").save(tmp_path / "gray.png")
    setup = compare.Setup(granite, ey=tmp_path / "copy.png", ez=tmp_path / "gray.png")
    with pytest.raises(ValueError, match=re.escape(f"y {tmp_path / 'copy.png'} 3")):
        setup.exemplars()


def test_a_file_changed_before_the_lazy_cube_reads_it_again_is_refused(tmp_path, data_dir):
    """The lazy cube's plugin reads the exemplar files again: one that no longer holds the
    image the scores were taken of is refused, naming it."""
    from warptex.compare.measure import _check_unchanged
    from warptex.exemplar import ExemplarError

    path = tmp_path / "granite.png"
    Image.open(data_dir / "granite_64.png").save(path)
    setup = compare.Setup(path, 16)
    setup.exemplars()
    _check_unchanged(setup)
    Image.open(data_dir / "granite_64.png").rotate(90).save(path)
    with pytest.raises(ExemplarError, match=re.escape(f"{path}: changed while the comparison")):
        _check_unchanged(setup)


def test_compare_refuses_a_constant_exemplar_before_any_method(tmp_path, capsys):
    """Its scores would be float32 rounding noise in units of a variance it does not have
    (flat, identical to it, scored energy 1 and noise 0)."""
    from PIL import Image

    path = tmp_path / "const.png"
    Image.fromarray(np.full((32, 32, 3), 77, np.uint8)).save(path)
    out = tmp_path / "out"
    assert main(["compare", str(path), "--size", "16", "--methods", "flat", "-o", str(out)]) == 2
    assert f"{path}: image is constant: the measures are in units of its variance" in (
        capsys.readouterr().err)
    assert not out.exists()


def test_the_lazy_cube_reads_the_candidates_its_method_computed(data_dir, tmp_path,
                                                                 monkeypatch):
    """They are computed once, afresh and timed, then cached where the cube's plugin looks
    (it computed them a second time: minutes for a large exemplar)."""
    import mitsuba as mi

    import mitsuba_plugin
    from warptex import compare

    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path / "cache"))
    setup = compare.Setup(str(data_dir / "granite_64.png"), 16)
    job, _ = measure._precomputed(methods._Job(setup, setup.exemplars()))
    mi.set_variant("scalar_rgb")
    mitsuba_plugin.register()
    cube = mi.load_dict(methods._cube_texture("lazy", job, np.zeros((16, 16, 16, 3))))
    assert cube.solid.synthesizer.candidates.cache_status == "loaded"


def test_the_bar_says_what_each_method_s_process_is_doing(data_dir, tmp_path, monkeypatch,
                                                         capfd):
    """Pre-computing candidates alone takes about a minute for a 256 px exemplar, which the
    bar spent saying only the method's name."""
    from warptex.compare import Setup, compare

    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path / "cache"))
    compare(Setup(str(data_dir / "granite_64.png"), 8), ["lazy", "noise"], progress=True)
    err = capfd.readouterr().err
    for said in ("lazy: pre-computing candidates", "lazy: 8^3, timed",
                 "lazy: rendering its cube", "lazy: measuring energy",
                 "lazy: measuring completeness", "lazy: measuring repetition",
                 "noise: 8^3, timed"):
        assert said in err
    assert "noise: pre-computing" not in err


def test_a_second_ctrl_c_while_compare_stops_prints_no_traceback(data_dir, tmp_path):
    """Ctrl-C twice (or timeout's signal, which reaches the process and then its group): the
    first left the wait for the workers' pool thread to the interpreter's exit, which the
    second cut short with "Exception ignored ... KeyboardInterrupt" tracebacks."""
    env = {**os.environ, "WARPTEX_CACHE": str(tmp_path / "cache")}
    run = subprocess.Popen(
        [sys.executable, "-m", "warptex", "compare", str(data_dir / "granite_64.png"),
         "--size", "64", "--methods", "lazy,flat", "-o", str(tmp_path / "out")],
        stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)
    said = ""
    while "measuring" not in said and run.poll() is None:  # its method's process at work
        said += run.stderr.readline()
    for _ in range(2):  # to the process group, as a terminal's Ctrl-C goes
        os.killpg(run.pid, signal.SIGINT)
        time.sleep(0.5)
    err = said + run.communicate(timeout=120)[1]
    # 130, or ended by the second signal once the command returned (a shell says 130 too).
    assert run.returncode in (130, -signal.SIGINT), err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    assert not (tmp_path / "out").exists()


def test_a_report_file_s_place_taken_is_named_before_any_method_and_after(tmp_path, data_dir,
                                                                         monkeypatch, capsys):
    """A folder where table.md goes is refused before any method runs (it was found only
    after all of them, as "OUT: cannot write (Is a directory)", naming the folder asked
    for); a write failing once the work is done names the report file that failed."""
    granite = str(data_dir / "granite_64.png")
    out = tmp_path / "out"
    (out / "table.md").mkdir(parents=True)
    ran = []
    row = compare.MethodResult("noise", [0.0] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3, 0.0, 0.0,
                               0.0, slices=[np.zeros((16, 16, 3), np.float32)] * 3)
    monkeypatch.setattr(compare, "compare", lambda setup, methods, repeats: ran.append(
        methods) or compare.Comparison(setup, [row]))
    args = ["compare", granite, "--size", "16", "--methods", "noise", "-o", str(out)]
    assert main(args) == 2 and not ran
    assert f"{out / 'table.md'}: is a folder, expected a file name" in capsys.readouterr().err

    (out / "table.md").rmdir()
    # Two report files that are one (a link): found only once every method had run.
    (out / "table.md").symlink_to("table.json")
    assert main(args) == 2 and not ran
    assert (f"{out / 'table.md'} and {out / 'table.json'} are one file"
            in capsys.readouterr().err)
    (out / "table.md").unlink()
    _json_disk_full(monkeypatch)
    assert main(args) == 1 and ran
    assert f"{out / 'table.json'}: cannot write (No space left on device)" in (
        capsys.readouterr().err)
    assert list(out.iterdir()) == []


def test_the_tiled_volume_is_lazy_s_own_up_to_its_block_as_its_note_says(monkeypatch):
    """Up to 64 voxels, the default --size included, ``tiled`` is the lazy volume itself
    (its note said "below 64"); past it, the 64^3 block repeated."""
    blocks = {}
    monkeypatch.setattr(methods, "_lazy", lambda job, size: blocks.setdefault(
        size, np.random.default_rng(size).random((size, size, size, 1), np.float32)))
    for size in (compare.TILE - 8, compare.TILE, compare.TILE + 8):
        same = np.array_equal(methods._tiled(None, size), methods._lazy(None, size))
        assert same == (size <= compare.TILE)
    assert f"up to {compare.TILE} voxels" in compare.METHOD_NOTES["tiled"]


def test_a_two_channel_exemplar_renders_its_cubes_in_gray(tmp_path, data_dir):
    """Mitsuba's grid volume takes 1, 3 or 6 channels: a 2-channel exemplar's cubes failed
    after every method had run, and the report was lost. They show the first channel in gray,
    as the plugin shows the lazy one."""
    from warptex.exemplar import Exemplar

    colors = Exemplar.load(data_dir / "granite_64.png").colors
    path = tmp_path / "two.npy"
    np.save(path, np.ascontiguousarray(colors[..., :2]))
    comparison = compare.compare(compare.Setup(path, 8), ["noise", "flat"], progress=False)
    files = compare.write_report(comparison, tmp_path / "out")
    assert {f.name for f in files} == {"sheet.png", "table.md", "table.json"}
    volume = np.repeat(colors[None, :8, :8, :2], 8, axis=0)
    job = methods._Job(compare.Setup(path, 8), (Exemplar.load(path),) * 3)
    grid = methods._cube_texture("noise", job, volume)["volume"]["data"]
    assert np.asarray(grid).shape == (8, 8, 8, 1)


def test_method_names_and_cube_arguments_that_are_no_such_things_are_refused(data_dir):
    """Non-string method names failed inside str.join or a dict lookup, and render_cube(None)
    ended the interpreter in Mitsuba: each is now one error naming the argument."""
    for names, match in ((None, "methods must be a sequence"), ([1], "got 1"),
                         (["noise", ["flat"]], r"got \['flat'\]"), ([b"noise"], "got b'noise'")):
        with pytest.raises(TypeError, match=match):
            compare.check_methods(names)
    with pytest.raises(TypeError, match="texture must be a Mitsuba texture dict"):
        compare.render_cube(None, 8)
    # A path where a Setup belongs: named before any method's process starts.
    with pytest.raises(TypeError, match=r"setup must be a warptex.compare.Setup, got '.*granite"):
        compare.compare(str(data_dir / "granite_64.png"), ["noise"])
    for resolution in (0, -5, 1.5):
        with pytest.raises(ValueError, match="resolution"):
            compare.render_cube({"type": "rgb", "value": 0.5}, resolution)


def test_the_sheet_shows_each_axis_exemplar_and_each_method_s_slices_and_cube(
        tmp_path, data_dir, monkeypatch):
    """The sheet's rows, as drawn: one exemplar row (per axis where they differ), then per
    method its three middle slices and its rendered cube."""
    from warptex import sheets

    drawn = []
    sheet = sheets.sheet
    monkeypatch.setattr(sheets, "sheet", lambda rows, **kw: (drawn.append(rows),
                                                             sheet(rows, **kw))[1])
    granite, onyx = data_dir / "granite_64.png", data_dir / "onyx_banded_64.png"
    linear = tmp_path / "granite.npy"  # linear colors, which the sheet encodes
    np.save(linear, np.asarray(Image.open(granite), np.float32) / 255.0)
    comparisons = []
    for setup in (compare.Setup(linear, 16), compare.Setup(granite, 16, ey=onyx)):
        comparisons.append(compare.compare(setup, ["noise"], progress=False))
        compare.write_report(comparisons[-1], tmp_path / f"cmp{len(drawn)}")
    (same, *noise), (per_axis, *_) = drawn
    assert [label for label, _ in same[1]] == ["exemplar"]
    assert [label for label, _ in per_axis[1]] == ["x exemplar", "y exemplar", "z exemplar"]
    assert [(method, [label for label, _ in images]) for method, images in noise] == [
        ("noise", ["x = 8", "y = 8", "z = 8", "rendered cube"])]
    # Colors as an 8-bit picture shows them: sRGB-encoded; each slice under its own axis.
    from warptex.srgb import reencoded

    ex = comparisons[0].setup.exemplars()[0]
    assert not ex.srgb

    def shown(image):
        return reencoded(image, srgb=False, to_srgb=True)

    np.testing.assert_array_equal(same[1][0][1], shown(ex.colors))
    for (_, image), expected in zip(noise[0][1], comparisons[0].results[0].slices, strict=False):
        np.testing.assert_array_equal(image, shown(expected))
    assert len({s.tobytes() for s in comparisons[0].results[0].slices}) == 3
