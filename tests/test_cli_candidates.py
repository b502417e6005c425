"""``warptex precompute`` and ``warptex volume``: summaries, files and their layouts."""

from __future__ import annotations

import io
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from warptex.candidate_set import DEFAULT_PARAMS, CandidateSet
from warptex.candidates import cache_path, precompute
from warptex.cli import console, main, volumes
from warptex.exemplar import Exemplar
from warptex.volume_files import write_volume

GRANITE = Path(__file__).resolve().parent / "data" / "granite_64.png"


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> dict[str, Path]:
    """Small PNG crops of the granite exemplar, as files the commands can load."""
    folder = tmp_path_factory.mktemp("images")
    granite = Image.open(GRANITE).convert("RGB")
    boxes = {"a": (0, 0, 32, 32), "b": (32, 0, 48, 16), "c": (16, 32, 32, 48)}
    paths = {}
    for name, box in boxes.items():
        paths[name] = folder / f"{name}.png"
        granite.crop(box).save(paths[name])
    return paths


@pytest.fixture(scope="module")
def module_cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(autouse=True)
def private_cache(module_cache, monkeypatch) -> Path:
    """One candidate cache for this file, never the user's: later tests reuse candidates."""
    monkeypatch.setenv("WARPTEX_CACHE", str(module_cache))
    return module_cache


def _level_lines(cs: CandidateSet) -> list[str]:
    """The summary's per-level rows, rebuilt from a candidate set."""
    rows = []
    kept = any(any(s.margins) for lvl in cs.sources for s in lvl)  # a crop may not tile
    for level, roles in enumerate(cs.roles):
        size = "/".join(f"{s.size[1]}x{s.size[0]}" for s in cs.sources[level])
        mean = np.concatenate([r.count for r in roles]).mean()
        fallback = sum(int(r.fallback.sum()) for r in roles)
        margins = [" / ".join(f"{s.margins[0]}, {s.margins[1]}" for s in cs.sources[level])]
        rows.append((str(level), size, f"{mean:.2f}", str(fallback), *(margins if kept else [])))
    return [" ".join(row) for row in rows]


def _rows(out: str) -> list[str]:
    return [" ".join(line.split()) for line in out.splitlines() if re.match(r"\s+\d+\s", line)]


# -- precompute ---------------------------------------------------------------------------


def test_precompute_summary_file_and_cache(images, tmp_path, monkeypatch, capsys):
    # A cache of its own: the file's shared one may already hold a.png's candidates.
    monkeypatch.setenv("WARPTEX_CACHE", str(tmp_path / "cache"))
    out_file = tmp_path / "a.wtc"
    assert main(["precompute", str(images["a"]), "-o", str(out_file)]) == 0
    captured = capsys.readouterr()
    out = captured.out
    cs = CandidateSet.load(out_file)
    ex = Exemplar.load(images["a"])
    cache = cache_path([ex, ex, ex], dict(DEFAULT_PARAMS))
    assert "exemplar: a.png on all three axes (candidates shared)" in out
    assert "levels: 3" in out
    assert _rows(out) == _level_lines(cs)
    assert [row.split()[1] for row in _rows(out)] == ["8x8", "16x16", "32x32"]
    assert re.search(r"^time: \d+\.\d\d s$", out, re.M)
    # Captured, stderr is no terminal: the bar is a few lines, not carriage returns (after
    # the line that says Warp builds the kernels, on a machine's first run).
    assert "\r" not in captured.err
    assert re.search(r"^candidates: +0%.*\n(.*\n)*candidates: 100%.*\n", captured.err, re.M)
    assert f"bytes: {cs.nbytes()} (" in out
    assert f"written: {cache} (cache)" in out
    assert f"written: {out_file}" in out
    assert "candidates" in captured.err  # the progress bar
    # The -o file holds what precompute returns, and the cache file the same bytes.
    assert out_file.read_bytes() == cache.read_bytes()
    assert [s.size for s in cs.sources[-1]] == [(32, 32)]
    assert cs.digests == (ex.digest(),) * 3

    assert main(["precompute", str(images["a"])]) == 0
    out = capsys.readouterr().out
    assert f"loaded from cache: {cache}" in out
    assert "written:" not in out
    assert _rows(out) == _level_lines(cs)


def test_precompute_shows_the_margins_of_a_photo_that_does_not_tile(tmp_path, images, capsys):
    """A ramp's left and right edges form a seam: its rows say how many columns candidates
    keep from them (none at the 8 px level, too small for 5 columns inside); a photo that
    tiles gets no margins column."""
    rng = np.random.default_rng(5)
    ramp = np.linspace(0, 200, 32)[None, :, None] + rng.integers(0, 40, (24, 32, 3))
    Image.fromarray(ramp.astype(np.uint8)).save(tmp_path / "ramp.png")
    assert main(["precompute", str(tmp_path / "ramp.png")]) == 0
    out = capsys.readouterr().out
    assert "margins (rows, columns)" in out
    assert [row.split(maxsplit=4)[4] for row in _rows(out)] == ["0, 0", "0, 2", "0, 2"]
    assert main(["precompute", str(images["a"])]) == 0
    out = capsys.readouterr().out
    assert "margins" not in out and all(len(row.split()) == 4 for row in _rows(out))


def test_tileable_overrides_what_the_photo_suggests(tmp_path, images, capsys):
    """--tileable yes takes the ramp as a torus (no margins), --tileable no keeps candidates
    from every edge of a photo that tiles; each setting caches its own candidates, which
    the volume command synthesizes from and info finds."""
    from warptex.synthesis import Synthesizer

    rng = np.random.default_rng(5)
    ramp = np.linspace(0, 200, 32)[None, :, None] + rng.integers(0, 40, (24, 32, 3))
    Image.fromarray(ramp.astype(np.uint8)).save(tmp_path / "ramp.png")
    assert main(["precompute", str(tmp_path / "ramp.png"), "--tileable", "yes"]) == 0
    out = capsys.readouterr().out
    assert "margins" not in out
    assert main(["precompute", str(images["a"]), "--tileable", "no"]) == 0
    out = capsys.readouterr().out
    assert [row.split(maxsplit=4)[4] for row in _rows(out)] == ["0, 0", "2, 2", "2, 2"]
    never = precompute(images["a"], tileable=False)
    assert never.cache_status == "loaded"
    assert never.content_digest != precompute(images["a"]).content_digest

    out_file = tmp_path / "v.npy"
    assert main(["volume", str(images["a"]), "--tileable", "no", "--size", "8", "--seed", "7",
                 "-o", str(out_file)]) == 0
    np.testing.assert_array_equal(np.load(out_file),
                                  Synthesizer(never, seed=7).box((0, 0, 0), (8, 8, 8)))
    capsys.readouterr()
    assert main(["info", str(images["a"]), "--tileable", "no"]) == 0
    out = capsys.readouterr().out
    assert "--tileable no: candidates keep away from all four edges" in out
    cached = cache_path([Exemplar.load(images["a"])] * 3, never.params)
    assert f"candidates: cached at {cached}" in out
    with pytest.raises(SystemExit):
        main(["precompute", str(images["a"]), "--tileable", "maybe"])
    assert "invalid choice: 'maybe'" in capsys.readouterr().err


def test_precompute_says_when_it_could_not_replace_a_damaged_cache(images, private_cache,
                                                                  capsys, monkeypatch):
    """A damaged cache file that cannot be replaced (a full disk) is left as it was; the
    summary must not call it loaded, nor written, and the command fails (exit 1)."""
    ex = Exemplar.load(images["a"])
    cache = cache_path([ex, ex, ex], dict(DEFAULT_PARAMS))
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_bytes(b"damaged")

    def disk_full(self, path):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(CandidateSet, "_write", disk_full)
    # A job warming the cache failed, and exit 1 says so (it was 0: the step went green).
    assert main(["precompute", str(images["a"])]) == 1
    captured = capsys.readouterr()
    assert "ignoring damaged candidate cache" in captured.err
    assert "candidates not cached: cannot write" in captured.err
    assert "loaded from cache" not in captured.out
    assert "(cache)" not in captured.out
    assert captured.err.endswith(f"warptex: error: {cache}: the candidates could not be cached "
                                 "(the warning above says why); WARPTEX_CACHE sets the cache "
                                 "folder\n")
    assert cache.read_bytes() == b"damaged"


def test_precompute_reads_a_cache_it_could_not_write(images, private_cache, capsys,
                                                     monkeypatch):
    """A shared cache on a read-only mount that holds the candidates already: read, not
    refused for the write it does not need."""
    import warptex.cli

    assert main(["precompute", str(images["a"])]) == 0
    capsys.readouterr()

    def read_only(folder, *args):
        raise warptex.cli.common.CliError(f"{folder}: cannot write (Read-only file system)")

    monkeypatch.setattr(warptex.cli.exemplars, "check_writable_folder", read_only)
    assert main(["precompute", str(images["a"])]) == 0
    assert "loaded from cache" in capsys.readouterr().out
    assert main(["precompute", str(images["b"])]) == 2  # not there: it would be written
    assert "Read-only file system" in capsys.readouterr().err


def test_a_cache_folder_that_cannot_be_looked_up_is_reported_not_a_traceback(
        images, tmp_path, monkeypatch, capsys):
    """WARPTEX_CACHE under a folder this user may not search (here: a name too long, which
    fails the same way for root) raised a bare OSError from looking the cache file up: in
    precompute(), and so in every command that synthesizes, and in ``warptex info``."""
    folder = tmp_path / ("a" * 300) / "cache"
    monkeypatch.setenv("WARPTEX_CACHE", str(folder))
    assert main(["precompute", str(images["b"])]) == 2
    assert f"{folder}: cannot make the cache folder" in capsys.readouterr().err
    assert main(["info", str(images["b"])]) == 0
    assert "candidates: not cached" in capsys.readouterr().out
    with pytest.warns(UserWarning, match="candidates not cached: .*cannot look up"):
        cs = precompute(images["b"])
    assert cs.cache_status == "not written"


def test_a_cache_folder_given_with_a_tilde_is_the_home_folder(monkeypatch, tmp_path):
    from warptex.candidates import cache_dir

    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("WARPTEX_CACHE", "~/warptex-cache")
    assert cache_dir() == tmp_path / "warptex-cache"
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("WARPTEX_CACHE", "relative")
    assert cache_dir() == tmp_path / "relative"


def test_precompute_no_cache_three_exemplars(images, private_cache, capsys):
    before = set(private_cache.iterdir())
    args = ["precompute", str(images["a"]), "--ey", str(images["b"]), "--ez", str(images["c"])]
    assert main([*args, "--no-cache"]) == 0
    out = capsys.readouterr().out
    assert "exemplars: x a.png, y b.png, z c.png (3 roles)" in out
    assert "written: nothing (--no-cache without -o)" in out
    assert set(private_cache.iterdir()) == before
    cs = precompute(*(Exemplar.load(images[k]) for k in "abc"), cache=False)
    assert _rows(out) == _level_lines(cs)
    assert _rows(out)[-1].split()[1] == "32x32/16x16/16x16"


def test_precompute_errors(images, tmp_path, capsys):
    mask = tmp_path / "mask.png"
    Image.fromarray(np.eye(32, dtype=np.uint8) * 255).save(mask)
    args = ["precompute", str(images["a"]), "--feature-mask", str(mask), "--ey", str(images["a"])]
    assert main(args) == 2
    assert "--feature-mask marks one image" in capsys.readouterr().err
    assert main([*args[:4], "--ez", str(images["a"])]) == 2  # z's alone as well
    assert "--feature-mask marks one image" in capsys.readouterr().err
    assert main(["precompute", str(tmp_path / "missing.png")]) == 2
    assert "missing.png: image file not found" in capsys.readouterr().err
    target = tmp_path / "no" / "such" / "dir" / "c.wtc"
    assert main(["precompute", str(images["a"]), "-o", str(target)]) == 0
    assert CandidateSet.load(target).num_levels == 3  # missing folders are made
    (tmp_path / "file").write_text("not a folder")
    assert main(["precompute", str(images["a"]), "-o", str(tmp_path / "file" / "c.wtc")]) == 2
    assert f"{tmp_path / 'file' / 'c.wtc'}: cannot write" in capsys.readouterr().err
    # Refused before the work, not a traceback after it: a file of another kind, and the
    # exemplar itself (a copy named .wtc), which it silently replaced.
    other = tmp_path / "other.wtc"
    other.write_text("hello")
    assert main(["precompute", str(images["a"]), "--no-cache", "-o", str(other)]) == 2
    assert capsys.readouterr().err.endswith(
        f"warptex: error: {other}: exists and is not a warptex candidate file; it would be "
        "overwritten\n")
    photo = tmp_path / "photo.wtc"
    photo.write_bytes(images["a"].read_bytes())
    assert main(["precompute", str(photo), "--no-cache", "-o", str(photo)]) == 2
    assert f"{photo}: would overwrite the input {photo}" in capsys.readouterr().err
    assert other.read_text() == "hello" and photo.read_bytes() == images["a"].read_bytes()


# -- volume -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def expected(images, module_cache) -> np.ndarray:
    """Synthesizer.box of the whole 8^3 cube in one call, the reference for the files."""
    from warptex.synthesis import Synthesizer

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("WARPTEX_CACHE", str(module_cache))
        cs = precompute(images["a"])
    return Synthesizer(cs, seed=7, jitter=0.5).box((0, 0, 0), (8, 8, 8))


def _volume(images, out: Path, *extra: str) -> int:
    args = ["volume", str(images["a"]), "--size", "8", "--seed", "7", "--jitter", "0.5"]
    return main([*args, *extra, "-o", str(out)])


def test_volume_slabs():
    assert volumes._slab_edges(8) == [0, 8]
    assert volumes._slab_edges(128) == [0, 64, 128]
    assert volumes._slab_edges(150) == [0, 36, 76, 112, 150]  # 37.5 voxels rounded to blocks
    assert volumes._slab_edges(300) == [0, 32, 60, 88, 120, 152, 180, 208, 240, 272, 300]
    # Two slabs over half a million voxels, so the bar moves; none of one voxel (a whole
    # apron's work for it: 101 was 100 and 1).
    assert volumes._slab_edges(80) == [0, 80]
    assert volumes._slab_edges(100) == [0, 48, 100]
    assert volumes._slab_edges(101) == [0, 52, 101]


def test_work_voxels_counts_the_aprons_of_many_passes():
    """The measure of a volume's time that decides its bar: a 16^3 box of 8 passes took
    longer than an 80^3 one of the default 2 (3.0 s against 1.4 s), as its aprons grow."""
    from warptex.synthesis import work_voxels

    assert work_voxels((64,) * 3) < work_voxels((80,) * 3) < work_voxels((81,) * 3)
    assert work_voxels((64,) * 3, 2) < work_voxels((64,) * 3, 3)
    assert work_voxels((16,) * 3, 8) > work_voxels((80,) * 3)
    assert work_voxels((16, 32, 32), 0) > 0  # upsampling alone is work too


def test_a_slow_volume_of_one_slab_shows_its_bar_ticking(images, tmp_path, capsys,
                                                          monkeypatch):
    """A volume of one slab whose work is slow (a small one of many passes) shows its bar,
    redrawn by a thread while the slab is synthesized; a quick one shows none."""
    import threading

    import warptex.synthesis
    from warptex.synthesis import Synthesizer

    ticking = []
    box = Synthesizer.box

    def seen(self, origin, shape):
        ticking.append(any(t.name == "warptex-bar" for t in threading.enumerate()))
        return box(self, origin, shape)

    monkeypatch.setattr(Synthesizer, "box", seen)
    capsys.readouterr()
    assert _volume(images, tmp_path / "quick.npy") == 0
    assert "volume" not in capsys.readouterr().err and ticking == [False]
    # As if 3 passes made 8^3 voxels slow, as 8 passes make 16^3 (seconds on a GPU-less CPU).
    monkeypatch.setattr(warptex.synthesis, "work_voxels",
                        lambda shape, passes=2: 10**9 if passes == 3 else 1)
    assert _volume(images, tmp_path / "slow.npy", "--passes", "3") == 0
    err = capsys.readouterr().err
    assert "volume: 100%" in err and "1/1" in err and ticking == [False, True]


def test_ticking_redraws_a_bar_until_the_block_ends(monkeypatch):
    """The bar is redrawn again and again while the block runs (here until the third
    redraw, however slowly this machine runs the thread), and never once it has ended: its
    thread is gone. Not counted against a sleep, which a loaded machine may stretch."""
    import threading

    class Bar:
        def __init__(self):
            self.refreshed = 0
            self.third = threading.Event()

        def refresh(self):
            self.refreshed += 1
            if self.refreshed == 3:
                self.third.set()

    monkeypatch.setattr(console, "_TICK_SECONDS", 0.01)
    bar = Bar()
    with console.ticking(bar):
        assert bar.third.wait(timeout=60)  # a bound against hanging, not a timing
    assert not any(t.name == "warptex-bar" for t in threading.enumerate())
    assert bar.refreshed >= 3


def test_volume_npy_equals_box(images, expected, tmp_path, capsys, monkeypatch):
    out = tmp_path / "v.npy"
    monkeypatch.setattr(volumes, "_slab_edges", lambda size: [0, 3, 4, size])
    assert _volume(images, out) == 0
    captured = capsys.readouterr()
    assert f"written: {out}" in captured.out
    assert "volume" in captured.err  # the progress bar over slabs
    got = np.load(out)
    assert got.dtype == np.float32 and got.shape == (8, 8, 8, 3)
    np.testing.assert_array_equal(got, expected)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.npy"]  # no temporary left


def test_volume_reads_exemplars_shrunk_to_max_size(tmp_path):
    from warptex.synthesis import Synthesizer

    out = tmp_path / "v.npy"
    assert main(["volume", str(GRANITE), "--exemplar-max-size", "32", "--size", "8",
                 "--seed", "7", "-o", str(out)]) == 0
    shrunk = Exemplar.load(GRANITE, max_size=32)
    assert shrunk.shape == (32, 32)
    box = Synthesizer(precompute(shrunk), seed=7).box((0, 0, 0), (8, 8, 8))
    np.testing.assert_array_equal(np.load(out), box)


def test_volume_seed_changes_result(images, expected, tmp_path):
    assert main(["volume", str(images["a"]), "--size", "8", "-o", str(tmp_path / "s.npy")]) == 0
    assert not np.array_equal(np.load(tmp_path / "s.npy"), expected)


def test_volume_and_slice_take_shifted_tiles(images, module_cache, tmp_path):
    """--shifted-tiles reaches the engine in the volume and slice commands."""
    from warptex.synthesis import Synthesizer

    assert _volume(images, tmp_path / "v.npy", "--shifted-tiles") == 0
    cs = precompute(images["a"])
    shifted = Synthesizer(cs, seed=7, jitter=0.5, shifted_tiles=True).box((0, 0, 0), (8, 8, 8))
    np.testing.assert_array_equal(np.load(tmp_path / "v.npy"), shifted)
    plain = Synthesizer(cs, seed=7, jitter=0.5).box((0, 0, 0), (8, 8, 8))
    assert not np.array_equal(shifted, plain)
    cut = tmp_path / "c.npy"
    assert main(["slice", str(images["a"]), "--seed", "7", "--jitter", "0.5", "--shifted-tiles",
                 "--origin", "0.5", "0.5", "3.5", "--u", "1", "0", "0", "--v", "0", "1", "0",
                 "--shape", "8", "8", "-o", str(cut)]) == 0
    np.testing.assert_allclose(np.load(cut), shifted[:, :, 3], atol=1e-6)


def test_volume_vol_and_exr_are_the_box_written_by_volume_files(images, expected, tmp_path):
    """The command writes the engine's box as warptex.volume_files does (whose layouts
    tests/test_volume_files.py checks), byte for byte: the PNG's colors decoded to linear,
    as these formats are read, or as stored with --raw."""
    for suffix in (".vol", ".exr"):
        for raw in (False, True):
            out, reference = tmp_path / f"v{raw}{suffix}", tmp_path / f"reference{suffix}"
            assert _volume(images, out, *(["--raw"] if raw else [])) == 0
            write_volume(reference, expected, srgb=not raw)  # raw: nothing to decode
            assert out.read_bytes() == reference.read_bytes(), (suffix, raw)
    for suffix in (".vol", ".exr"):  # decoded, then raw
        decoded, raw = (tmp_path / f"v{raw}{suffix}" for raw in (False, True))
        assert decoded.read_bytes() != raw.read_bytes(), suffix


_MITSUBA_READ = """
import sys
import numpy as np
import warptex, mitsuba as mi
mi.set_variant(warptex.best_mitsuba_variant())
np.save(sys.argv[2], np.array(mi.VolumeGrid(sys.argv[1])))
"""


def test_volume_vol_reads_in_mitsuba(images, expected, tmp_path):
    from warptex.srgb import srgb_to_linear

    pytest.importorskip("mitsuba")
    assert _volume(images, tmp_path / "v.vol") == 0
    # A child process, so the Mitsuba variant chosen here leaves other tests alone.
    subprocess.run(
        [sys.executable, "-c", _MITSUBA_READ, str(tmp_path / "v.vol"), str(tmp_path / "m.npy")],
        check=True,
        capture_output=True,
    )
    np.testing.assert_array_equal(np.load(tmp_path / "m.npy"),
                                  srgb_to_linear(expected).transpose(2, 1, 0, 3))


def test_volume_of_exemplars_encoded_differently_is_refused_unless_stored_as_is(
        images, tmp_path, capsys):
    linear = tmp_path / "linear.npy"
    np.save(linear, np.asarray(Image.open(images["b"]), np.float32) / 255)
    out = tmp_path / "v.vol"
    assert _volume(images, out, "--ey", str(linear)) == 2
    assert capsys.readouterr().err == (
        "warptex: error: the exemplars' colors are encoded differently (a.png sRGB-encoded, "
        "linear.npy linear): convert one image, or keep the values as stored (--raw)\n")
    assert not out.exists()
    assert _volume(images, out, "--ey", str(linear), "--raw") == 0
    # A .npy file holds values as stored, but averaging two encodings is still asked for.
    capsys.readouterr()
    assert _volume(images, tmp_path / "v.npy", "--ey", str(linear)) == 2
    assert "encoded differently" in capsys.readouterr().err
    assert not (tmp_path / "v.npy").exists()
    assert _volume(images, tmp_path / "v.npy", "--ey", str(linear), "--raw") == 0


def test_volume_bad_extension_names_the_path(images, tmp_path, capsys):
    out = tmp_path / "v.png"
    assert _volume(images, out) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"warptex: error: {out}: a volume file must end in .npy, .exr or .vol")
    assert not out.exists()
    assert main(["volume", str(images["a"]), "-o", str(tmp_path / "v")]) == 2
    assert "v: a volume file must end in" in capsys.readouterr().err


def test_volume_bad_arguments(images, tmp_path, capsys):
    assert main(["volume", str(images["a"]), "--size", "0", "-o", str(tmp_path / "v.npy")]) == 2
    assert "--size must be at least 1" in capsys.readouterr().err
    assert _volume(images, tmp_path / "j.npy", "--jitter", "100") == 2
    assert "jitter must be within" in capsys.readouterr().err
    (tmp_path / "file").write_text("not a folder")
    assert _volume(images, tmp_path / "file" / "v.npy") == 2
    assert f"{tmp_path / 'file' / 'v.npy'}: cannot write" in capsys.readouterr().err
    assert _volume(images, tmp_path / "new" / "v.npy") == 0  # missing folders are made
    assert (tmp_path / "new" / "v.npy").exists()


def test_a_filling_bar_in_a_log_is_its_first_and_last_line():
    """A real tqdm bar of each kind the commands draw: its fill, counts and units changing
    are no new step (a line per cell of the bar was written)."""
    from tqdm import tqdm

    for options in ({"unit": "slab"}, {"unit": "px", "unit_scale": True},
                    {"ascii": True, "ncols": 200}, {"postfix": "lazy"}):
        log = io.StringIO()
        with tqdm(total=2_000_000, file=console._LogLines(log), mininterval=0, desc="bar",
                  **options) as bar:
            for _ in range(1000):
                bar.update(2000)
        lines = log.getvalue().splitlines()
        assert len(lines) == 2 and "100%" in lines[-1], (options, lines)


def test_bars_of_two_threads_in_a_log_are_lines_without_cursor_moves():
    """Mitsuba pre-computes two textures' candidates at once: tqdm draws the second bar on
    the line below and moves the cursor back up, which a log shows as escape codes."""
    from tqdm import tqdm

    log = io.StringIO()
    lines = console._LogLines(log)
    first = tqdm(total=4, file=lines, mininterval=0, desc="first")
    second = tqdm(total=4, file=lines, mininterval=0, desc="second")
    for _ in range(4):
        first.update(1)
        second.update(1)
    second.close()
    first.close()
    written = log.getvalue()
    assert "\x1b" not in written
    assert all(line.startswith(("first: ", "second: ")) for line in written.splitlines())
    assert "first: 100%" in written and "second: 100%" in written


def test_progress_bars_in_a_log_are_lines_at_most_every_few_seconds(monkeypatch):
    """A bar's first redraw, then one every ``_LOG_SECONDS`` at most, and its last, each a
    line; other text passes as it is."""
    written: list[str] = []

    class Log:
        def write(self, text: str) -> None:
            written.append(text)

    clock = iter([0.0, 1.0, 2.0, 11.0, 12.0, 13.0, 14.0])
    monkeypatch.setattr(console.time, "monotonic", lambda: next(clock))
    log = console._LogLines(Log())
    for text in ("\rbar: 0%", "\rbar: 10%", "\rbar: 20%  ", "\rbar: 90%", "\rbar: 100%",
                 "", "\n", "warning\n", "\r", "\rnext: 0%"):
        log.write(text)
    assert "".join(written) == "bar: 0%\nbar: 90%\nbar: 100%\nwarning\nnext: 0%\n"
    # A bar whose last update was written (10 s after the one before) and which then closes
    # with that update's redraw, tqdm's rate changed: one line of it, not two.
    written.clear()
    clock = iter([20.0, 20.0, 31.0, 31.5])
    for text in ("\r", "\rvol: 0%| 0/3 [00:00<?, ?slab/s]",
                 "\rvol: 100%| 3/3 [00:11<00:00, 1.67slab/s]",
                 "\rvol: 100%| 3/3 [00:11<00:00, 1.66slab/s]", "\n"):
        log.write(text)
    assert "".join(written) == ("vol: 0%| 0/3 [00:00<?, ?slab/s]\n"
                                "vol: 100%| 3/3 [00:11<00:00, 1.67slab/s]\n")
    # A new step or phase is a line at once, before the long call it names: it was held
    # back until the next redraw, after that call (25 s of unwrapping shown as step 0/2).
    written.clear()
    clock = iter([40.0, 40.0, 40.1, 40.2, 41.0, 41.5, 42.0])
    for text in ("\r", "\rUV: step 0/2 [00:00]", "\rUV: step 0/2, unwrapping [00:00]",
                 "\rUV: step 0/2, unwrapping [00:01]",
                 "\rm:   0%|     | 0/2 [00:00<?, ?it/s, lazy]",
                 "\rm:   0%|     | 0/2 [00:01<?, ?it/s, lazy: measuring]",
                 "\rm:   0%|     | 0/2 [00:02<?, ?it/s, lazy: measuring]"):
        log.write(text)
    assert written == ["UV: step 0/2 [00:00]\n", "UV: step 0/2, unwrapping [00:00]\n",
                       "m:   0%|     | 0/2 [00:00<?, ?it/s, lazy]\n",
                       "m:   0%|     | 0/2 [00:01<?, ?it/s, lazy: measuring]\n"]
