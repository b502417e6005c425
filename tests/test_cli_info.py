"""``warptex info``: what it prints, and clean errors without tracebacks."""

from __future__ import annotations

import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from warptex.cli import main


@pytest.fixture
def no_candidates(monkeypatch):
    """Make ``warptex.candidates`` unimportable, as before that module existed."""
    monkeypatch.setitem(sys.modules, "warptex.candidates", None)


def test_info_prints_size_channels_range_pyramid(data_dir, capsys, no_candidates):
    assert main(["info", str(data_dir / "granite_64.png")]) == 0
    out = capsys.readouterr().out
    colors = np.asarray(Image.open(data_dir / "granite_64.png")) / 255
    assert f"file: {(data_dir / 'granite_64.png').resolve()}" in out
    assert "size: 64 x 64 pixels (width x height)" in out
    assert "channels: 3\n" in out
    for channel in range(3):
        low, high = colors[..., channel].min(), colors[..., channel].max()
        assert f"channel {channel}: {low:.4f} .. {high:.4f}" in out
    assert "encoding: sRGB (the Mitsuba plugin decodes it to linear colors unless raw)" in out
    assert "pyramid: 4 levels (8x8, 16x16, 32x32, 64x64)" in out
    assert "tiles: yes (edges differ 1.0x left-right and 1.1x top-bottom" in out
    assert "candidates: not available" in out


def _tiles_line(folder: Path, pixels: np.ndarray, capsys) -> str:
    """The ``tiles:`` line ``warptex info`` prints for an 8-bit image of ``pixels``."""
    Image.fromarray(pixels.astype(np.uint8)).save(folder / "image.png")
    assert main(["info", str(folder / "image.png")]) == 0
    return next(t for t in capsys.readouterr().out.splitlines() if t.startswith("tiles:"))


def test_info_says_a_photo_that_does_not_tile_and_what_synthesis_does(tmp_path, capsys,
                                                                       no_candidates):
    """A ramp's left and right edges differ 31 steps of it."""
    ramp = np.repeat(np.arange(32)[None, :] * 8, 24, axis=0)
    assert _tiles_line(tmp_path, ramp, capsys) == (
        "tiles: no: its left and right edges differ 31.0x as much as neighbouring pixels; "
        "candidates keep away from those edges and the pyramid does not blur across them, "
        "so corrections never continue the seam")


def test_info_says_why_a_pattern_whose_edge_lies_on_the_wrap_tiles(tmp_path, capsys,
                                                                   no_candidates):
    """Stripes change 4.4x as much across the wrap as between neighbouring rows, as much as
    at every stripe's edge: said where the photo tiles and beside a seam."""
    stripes = np.repeat((np.arange(32) // 4 % 2)[:, None] * 200, 32, axis=1)
    assert _tiles_line(tmp_path, stripes, capsys) == (
        "tiles: yes (left-right edges identical; top-bottom edges differ 4.4x as much as "
        "neighbouring pixels; its top and bottom edges differ 4.4x, but at least 5% of its "
        "neighbouring rows differ as much: the wrap is one of the pattern's own edges)")
    # Beside a seam: a ramp from left to right, striped from top to bottom.
    line = _tiles_line(tmp_path, np.linspace(0, 120, 32)[None, :] + stripes * 0.5, capsys)
    assert line.startswith("tiles: no: its left and right edges differ")
    assert line.endswith("never continue the seam; its top and bottom edges differ 4.4x, but "
                         "at least 5% of its neighbouring rows differ as much: the wrap is one "
                         "of the pattern's own edges")


def test_info_says_a_float_image_is_linear(tmp_path, capsys, no_candidates):
    np.save(tmp_path / "float.npy", np.random.default_rng(0).random((16, 16, 3)))
    assert main(["info", str(tmp_path / "float.npy")]) == 0
    assert "encoding: linear (rendered as stored)\n" in capsys.readouterr().out


def test_info_non_square_with_feature_distance(tmp_path, capsys, no_candidates):
    image = np.zeros((37, 100), dtype=np.uint8)
    image[10:20, 30:60] = 200
    Image.fromarray(image).save(tmp_path / "wide.png")
    assert main(["info", "--feature-distance", str(tmp_path / "wide.png")]) == 0
    out = capsys.readouterr().out
    assert "size: 100 x 37 pixels" in out
    assert "channels: 1 + feature distance" in out
    assert "channel 0: 0.0000 .. 0.7843" in out
    assert "pyramid: 5 levels (7x3, 13x5, 25x10, 50x19, 100x37)" in out


def test_info_of_an_exemplar_shrunk_to_max_size(data_dir, capsys, no_candidates):
    assert main(["info", "--exemplar-max-size", "24", str(data_dir / "granite_64.png")]) == 0
    out = capsys.readouterr().out
    assert "size: 24 x 24 pixels (width x height), shrunk from 64 x 64\n" in out
    assert "pyramid: 3 levels (6x6, 12x12, 24x24)" in out


def test_info_of_a_wide_exemplar_shrunk_gives_both_sizes_width_first(data_dir, tmp_path,
                                                                     capsys, no_candidates):
    from PIL import Image

    wide = tmp_path / "wide.png"
    Image.open(data_dir / "granite_64.png").crop((0, 0, 48, 32)).save(wide)
    assert main(["info", "--exemplar-max-size", "24", str(wide)]) == 0
    assert ("size: 24 x 16 pixels (width x height), shrunk from 48 x 32\n"
            in capsys.readouterr().out)


def test_info_reports_cached_candidates(data_dir, capsys, monkeypatch):
    seen = []

    def cached_candidate_path(exemplar, tileable):
        seen.append((exemplar.name, tileable))
        return Path("/cache/granite.npz")

    fake = types.ModuleType("warptex.candidates")
    fake.cached_candidate_path = cached_candidate_path
    fake.check_feature_channels = lambda channels: None
    fake.precompute_bytes = lambda exemplars: 3 << 30
    fake.LARGE_PIXELS = 64 * 64
    monkeypatch.setitem(sys.modules, "warptex.candidates", fake)
    assert main(["info", str(data_dir / "granite_64.png")]) == 0
    assert "candidates: cached at /cache/granite.npz" in capsys.readouterr().out
    assert seen == [("granite_64.png", "auto")]

    fake.cached_candidate_path = lambda exemplar, tileable: None
    assert main(["info", str(data_dir / "granite_64.png")]) == 0
    assert ("candidates: not cached; pre-computing them takes about 3 GiB of memory\n"
            in capsys.readouterr().out)
    fake.LARGE_PIXELS = 64 * 64 - 1
    assert main(["info", str(data_dir / "granite_64.png")]) == 0
    assert ("candidates: not cached; pre-computing them takes about 3 GiB of memory and "
            "minutes (over 63x63 pixels)\n" in capsys.readouterr().out)
    monkeypatch.setattr("warptex.machine.physical_memory", lambda: 2 << 30)
    assert main(["info", str(data_dir / "granite_64.png")]) == 0
    assert ("candidates: not cached; pre-computing them needs about 3 GiB, this machine has "
            "2 GiB: shrink it with --exemplar-max-size" in capsys.readouterr().out)


def test_info_and_slice_say_which_exemplars_no_command_synthesizes(tmp_path, capsys):
    """35 channels: info quoted the memory to pre-compute them, which every command then
    refused, and slice sent such an exemplar to `warptex volume`, which refuses it too."""
    from warptex.candidate_set import check_feature_channels

    rng = np.random.default_rng(0)
    for channels in (5, 35):
        path = tmp_path / f"c{channels}.npy"
        np.save(path, rng.random((16, 16, channels), np.float32))
        assert main(["info", str(path)]) == 0
        out = capsys.readouterr().out
        assert main(["slice", str(path), "-o", str(tmp_path / "s.npy")]) == 2
        err = capsys.readouterr().err
        if channels == 35:
            with pytest.raises(ValueError) as refusal:
                check_feature_channels(channels)
            assert f"candidates: cannot be pre-computed: {refusal.value}\n" in out
            assert err.endswith("(gray, RGB or RGBA)\n")
        else:
            assert "candidates: not cached; pre-computing them takes about" in out
            assert err.endswith("(gray, RGB or RGBA); `warptex volume` synthesizes them\n")
    assert not (tmp_path / "s.npy").exists()


def test_info_alpha_keep(tmp_path, capsys, no_candidates):
    rgba = np.random.default_rng(1).integers(0, 256, size=(16, 16, 4), dtype=np.uint8)
    Image.fromarray(rgba, mode="RGBA").save(tmp_path / "rgba.png")
    assert main(["info", "--alpha", "keep", str(tmp_path / "rgba.png")]) == 0
    assert "channels: 4" in capsys.readouterr().out
    assert main(["info", str(tmp_path / "rgba.png")]) == 0
    captured = capsys.readouterr()
    assert "channels: 3" in captured.out
    assert f"warptex: warning: {tmp_path / 'rgba.png'}: alpha channel dropped" in captured.err


def test_info_missing_file_is_exit_2_without_traceback(tmp_path, capsys):
    assert main(["info", str(tmp_path / "missing.png")]) == 2
    captured = capsys.readouterr()
    assert captured.err == f"warptex: error: {tmp_path / 'missing.png'}: image file not found\n"
    assert captured.out == ""


def test_info_not_an_image(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("hello")
    assert main(["info", str(tmp_path / "notes.txt")]) == 2
    assert "notes.txt: not an image" in capsys.readouterr().err


def test_info_constant_image_warns(tmp_path, capsys, no_candidates):
    Image.fromarray(np.full((16, 16), 9, dtype=np.uint8)).save(tmp_path / "flat.png")
    assert main(["info", str(tmp_path / "flat.png")]) == 0
    out, err = capsys.readouterr()
    assert f"warptex: warning: {tmp_path / 'flat.png'}: image is constant" in err
    # No pixel differs from its neighbours: there is no ratio, not a ratio of 0.0x.
    assert "tiles: yes (left-right edges identical; top-bottom edges identical)\n" in out


def test_console_script_error_has_no_traceback(tmp_path):
    (tmp_path / "tiny.png").write_bytes(b"")
    script = Path(sys.executable).with_name("warptex")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "warptex"]
    result = subprocess.run(
        [*command, "info", str(tmp_path / "tiny.png")], capture_output=True, text=True
    )
    assert result.returncode == 2
    assert result.stderr.startswith("warptex: error: ")
    assert "Traceback" not in result.stderr


def test_no_command_shows_the_commands_and_is_exit_2(capsys):
    """``warptex`` alone said only that a command is required; it now lists them."""
    with pytest.raises(SystemExit) as info:
        main([])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: warptex") and "COMMAND --help" in err
    assert all(f"    {name} " in err for name in ("info", "slice", "render", "compare"))


def test_info_on_shared_exemplar(exemplar_dir, capsys):
    assert main(["info", str(exemplar_dir / "wood_rosewood_64.png")]) == 0
    out = capsys.readouterr().out
    assert "size: 64 x 64 pixels" in out
    assert "candidates: " in out
