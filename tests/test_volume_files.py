"""Volume files for other tools (warptex.volume_files): layouts checked on a volume whose
three sides differ, with 1 to 4 channels."""

import struct
from pathlib import Path

import numpy as np
import pytest

from warptex.exemplar import Exemplar
from warptex.volume_files import exr_sheet, write_image, write_volume


def _volume(channels: int) -> np.ndarray:
    return np.random.default_rng(channels).random((2, 3, 4, channels)).astype(np.float32)


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_vol_header_and_data_of_a_non_cubic_volume(tmp_path, channels):
    """Mitsuba's grid: dims x, y, z; the channel count; the unit box; x fastest."""
    vol = _volume(channels)
    write_volume(tmp_path / "v.vol", vol, srgb=False)
    data = (tmp_path / "v.vol").read_bytes()
    assert data[:4] == b"VOL\x03"
    assert struct.unpack("<5i", data[4:24]) == (1, 2, 3, 4, channels)
    assert struct.unpack("<6f", data[24:48]) == (0, 0, 0, 1, 1, 1)
    values = np.frombuffer(data[48:], "<f4")
    assert values.size == vol.size
    x, y, z, c = 1, 0, 2, channels - 1
    assert values[((z * 3 + y) * 2 + x) * channels + c] == vol[x, y, z, c]
    np.testing.assert_array_equal(values.reshape(4, 3, 2, channels), vol.transpose(2, 1, 0, 3))


@pytest.mark.parametrize(("channels", "alpha", "names"),
                         [(1, False, ["Y"]), (1, True, ["Y"]), (2, True, ["Y", "A"]),
                          (2, False, ["Y", "C1"]),
                          (3, False, list("RGB")), (4, True, list("RGBA")),
                          (4, False, ["R", "G", "B", "C3"]),
                          (5, False, ["R", "G", "B", "C3", "C4"]),
                          (5, True, ["R", "G", "B", "C3", "A"])])
def test_exr_channel_names_and_layout(tmp_path, channels, alpha, names):
    """A last channel is named A only where it is an alpha: a .npy exemplar's is data,
    which readers would take for coverage."""
    import OpenEXR

    vol = _volume(channels)
    write_volume(tmp_path / "v.exr", vol, srgb=False, alpha=alpha)
    with OpenEXR.File(str(tmp_path / "v.exr"), separate_channels=True) as file:
        got = {name: ch.pixels for name, ch in file.channels().items()}
        layout = file.header()["warptexLayout"]
    assert sorted(got) == sorted(names)
    sheet = np.stack([got[n] for n in names], axis=2)
    assert sheet.dtype == np.float32 and sheet.shape == (3, 4 * 2, channels)  # Y, Z*X
    for x, y, z in ((0, 1, 3), (1, 2, 0)):  # pixel (y, z*X + x) holds voxel (x, y, z)
        np.testing.assert_array_equal(sheet[y, z * 2 + x], vol[x, y, z])
    np.testing.assert_array_equal(sheet, exr_sheet(vol))
    assert "2x3x4" in layout
    write_image(tmp_path / "i.exr", vol[0], srgb=False, alpha=alpha)
    with OpenEXR.File(str(tmp_path / "i.exr"), separate_channels=True) as file:
        assert sorted(file.channels()) == sorted(names)
    image = np.random.default_rng(channels).random((16, 16, channels), np.float32)
    write_image(tmp_path / "back.exr", image, srgb=False, alpha=alpha)
    back = Exemplar.load(tmp_path / "back.exr", alpha="keep")
    np.testing.assert_array_equal(back.colors, image)
    assert back.kept_alpha == (alpha and channels > 1)  # an alpha alone is one color


def test_a_gray_and_alpha_exr_reads_back_as_gray_and_alpha(tmp_path):
    """Two channels were written as C0, C1, which no reader takes for gray and alpha (nor
    warptex: it read them as two gray channels without alpha)."""
    from warptex.exemplar import Exemplar

    image = np.random.default_rng(3).random((16, 16, 2), np.float32)
    write_image(tmp_path / "la.exr", image, srgb=False, alpha=True)
    back = Exemplar.load(tmp_path / "la.exr", alpha="keep")
    np.testing.assert_array_equal(back.colors, image)
    assert back.kept_alpha


def test_an_exr_named_in_no_utf8_is_written_and_read(tmp_path):
    """A name of an old share's Latin-1 bytes: OpenEXR takes no such name, so a volume
    was synthesized, then lost in a traceback, and such an exemplar called unreadable."""
    import os

    folder = tmp_path / os.fsdecode(b"caf\xe9")
    image = np.random.default_rng(5).random((16, 16, 3), np.float32)
    write_image(folder / os.fsdecode(b"\xe9t\xe9.exr"), image, srgb=False)
    write_volume(folder / "v.exr", np.stack([image] * 4, axis=2), srgb=False)
    np.testing.assert_array_equal(
        Exemplar.load(folder / os.fsdecode(b"\xe9t\xe9.exr")).colors, image)
    assert Exemplar.load(folder / "v.exr").colors.shape == (16, 4 * 16, 3)


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_srgb_colors_are_decoded_in_exr_and_vol_files_only(tmp_path, channels, srgb_decoded):
    """.exr and .vol hold linear colors, as their readers assume: sRGB-encoded ones are
    decoded there, in the color channels only (RGB of RGBA, gray of gray-alpha); .npy
    keeps what was synthesized."""
    import OpenEXR

    vol = _volume(channels)
    linear = vol.astype(np.float64)
    color = 3 if channels >= 3 else 1
    linear[..., :color] = srgb_decoded(vol[..., :color])
    write_volume(tmp_path / "v.vol", vol, srgb=True)
    values = np.frombuffer((tmp_path / "v.vol").read_bytes()[48:], "<f4")
    np.testing.assert_allclose(values.reshape(4, 3, 2, channels), linear.transpose(2, 1, 0, 3),
                               rtol=1e-5)
    write_image(tmp_path / "i.exr", vol[0], srgb=True, alpha=channels in (2, 4))
    with OpenEXR.File(str(tmp_path / "i.exr"), separate_channels=True) as file:
        got = file.channels()
        names = sorted(got, key=lambda n: ["R", "G", "B", "Y", "A"].index(n))
        image = np.stack([got[n].pixels for n in names], axis=2)
    np.testing.assert_allclose(image, linear[0], rtol=1e-5)
    for name in ("v.npy", "i.npy"):
        data = vol if name == "v.npy" else vol[0]
        (write_volume if name == "v.npy" else write_image)(tmp_path / name, data, srgb=True)
        np.testing.assert_array_equal(np.load(tmp_path / name), data)


def test_a_kept_alpha_after_gray_and_data_is_no_color(tmp_path, srgb_decoded):
    """Gray, a data channel and a kept alpha: only the gray is decoded, and the channels
    are named Y, C1, A (the three were decoded as RGB, though named as gray, data, alpha)."""
    import OpenEXR

    image = _volume(3)[0]
    write_image(tmp_path / "i.exr", image, srgb=True, alpha=True)
    with OpenEXR.File(str(tmp_path / "i.exr"), separate_channels=True) as file:
        got = {name: channel.pixels for name, channel in file.channels().items()}
    assert sorted(got) == ["A", "C1", "Y"]
    np.testing.assert_allclose(got["Y"], srgb_decoded(image[..., 0]), rtol=1e-5)
    np.testing.assert_array_equal(got["C1"], image[..., 1])
    np.testing.assert_array_equal(got["A"], image[..., 2])


def test_colors_are_decoded_alike_in_parts(tmp_path, monkeypatch):
    """Large volumes are decoded a part at a time (the float64 of a whole volume's decoding
    took nine copies of it): parts of a few rows give the same file."""
    import warptex.srgb

    vol = _volume(4)
    write_volume(tmp_path / "whole.vol", vol, srgb=True, alpha=True)
    monkeypatch.setattr(warptex.srgb, "_REENCODED_ROWS", 5)
    write_volume(tmp_path / "parts.vol", vol, srgb=True, alpha=True)
    assert (tmp_path / "parts.vol").read_bytes() == (tmp_path / "whole.vol").read_bytes()


def test_volumes_of_any_memory_layout_are_written(tmp_path):
    """A view (colors of an RGBA volume, a transposed one, Fortran order) is written as its
    values, not refused by the writer's byte view."""
    volume = _volume(4)
    for view in (volume[..., :3], volume.transpose(2, 1, 0, 3), np.asfortranarray(volume)):
        write_volume(tmp_path / "v.npy", view, srgb=False)
        np.testing.assert_array_equal(np.load(tmp_path / "v.npy"), view)


def test_a_suffix_in_capitals_names_the_same_format(tmp_path):
    volume = _volume(3)
    write_volume(tmp_path / "v.NPY", volume, srgb=False)
    np.testing.assert_array_equal(np.load(tmp_path / "v.NPY"), volume)
    write_volume(tmp_path / "v.EXR", volume, srgb=False)
    assert (tmp_path / "v.EXR").read_bytes()[:4] == b"\x76\x2f\x31\x01"  # OpenEXR's magic
    write_volume(tmp_path / "v.Vol", volume, srgb=False)
    assert (tmp_path / "v.Vol").read_bytes()[:3] == b"VOL"


def test_a_path_that_names_a_folder_or_is_no_file_name_is_refused(tmp_path):
    """A trailing slash was dropped (a file written under the name of the folder meant),
    and a number met pathlib's error, which names no argument."""
    vol = _volume(3)
    with pytest.raises(ValueError, match=r"v\.npy/: names a folder, not a file"):
        write_volume(f"{tmp_path}/v.npy/", vol, srgb=False)
    assert not (tmp_path / "v.npy").exists()
    with pytest.raises(TypeError, match="path must be a file name"):
        write_image(3, vol[0], srgb=False)


def test_empty_volumes_and_images_and_a_non_bool_srgb_are_refused(tmp_path):
    """An empty volume once failed inside OpenEXR naming a temporary file, or was written
    as a 48-byte grid; srgb="no" counted as true."""
    from warptex.volume_files import write_image, write_volume

    for suffix in (".exr", ".vol", ".npy"):
        with pytest.raises(ValueError, match=r"the volume is empty: shape \(0, 2, 2, 3\)"):
            write_volume(tmp_path / f"e{suffix}", np.zeros((0, 2, 2, 3), np.float32), srgb=True)
    with pytest.raises(ValueError, match="the image is empty"):
        write_image(tmp_path / "e.exr", np.zeros((2, 2, 0), np.float32), srgb=False)
    with pytest.raises(ValueError, match="srgb must be True or False, got 'no'"):
        write_volume(tmp_path / "v.vol", np.zeros((2, 2, 2, 3), np.float32), srgb="no")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(("write", "name", "writers"), [
    (write_volume, "v.npy", "_VOLUME_WRITERS"), (write_volume, "v.exr", "_VOLUME_WRITERS"),
    (write_volume, "v.vol", "_VOLUME_WRITERS"), (write_image, "i.npy", "_IMAGE_WRITERS"),
    (write_image, "i.exr", "_IMAGE_WRITERS")])
def test_a_write_that_fails_half_way_leaves_the_old_file(tmp_path, monkeypatch, write, name,
                                                        writers):
    """A full disk in the middle of a write: the file of the same name keeps its old
    content, no temporary file is left, and the error names the file asked for."""
    import errno

    import warptex.volume_files

    data = _volume(3) if write is write_volume else _volume(3)[0]
    path = tmp_path / name
    write(path, data, srgb=False)
    before = path.read_bytes()

    def disk_full(target, *args):
        Path(target).write_bytes(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device", str(target))

    monkeypatch.setitem(getattr(warptex.volume_files, writers), path.suffix, disk_full)
    with pytest.raises(OSError, match="No space") as failed:
        write(path, data + 1, srgb=False)
    assert failed.value.filename == str(path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == [name]


def test_a_short_npy_write_says_why(tmp_path):
    """A file larger than the process may write (as a full disk, a write that falls short)
    is an OSError with the system's reason, naming the file, not NumPy's byte counts."""
    script = f"""
import resource, signal, sys
import numpy as np
from warptex.volume_files import write_volume
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (8192, 8192))
try:
    write_volume(r"{tmp_path / 'big.npy'}", np.zeros((16, 16, 16, 3), np.float32), srgb=False)
except OSError as error:
    print(error.errno, error.strerror, error.filename)
"""
    import errno
    import os
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parent.parent, timeout=120, check=True)
    assert done.stdout.strip() == (f"{errno.EFBIG} {os.strerror(errno.EFBIG)} "
                                   f"{tmp_path / 'big.npy'}")
    assert not any(tmp_path.iterdir())
