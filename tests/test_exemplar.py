"""Exemplar loading for every input kind, validation of bad input, feature distance, pyramid."""

from __future__ import annotations

import re
import struct
import warnings
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import OpenEXR
import png
import pytest
from PIL import Image
from scipy import ndimage

from warptex.exemplar import (
    SEAM_LIMIT,
    SEAM_SHARE,
    AlphaDropped,
    Exemplar,
    ExemplarError,
    PyramidLevel,
    feature_distance_from_mask,
    otsu_mask,
    seam_contrast_of,
    seams_of,
)
from warptex.settings import SettingError


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def _write_png16(path: Path, pixels: np.ndarray) -> Path:
    height, width, planes = pixels.shape
    writer = png.Writer(
        width, height, greyscale=planes in (1, 2), alpha=planes in (2, 4), bitdepth=16
    )
    with path.open("wb") as file:
        writer.write(file, pixels.reshape(height, width * planes).tolist())
    return path


def _write_exr(path: Path, channels: dict[str, np.ndarray]) -> Path:
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    # OpenEXR reads an array's memory as if contiguous: a channel sliced off writes garbage.
    channels = {name: np.ascontiguousarray(data) for name, data in channels.items()}
    OpenEXR.File(header, channels).write(str(path))
    return path


def _write_tiff(path: Path, samples: np.ndarray, photometric: int, signed: bool = False,
                order: str = "<") -> Path:
    """An uncompressed TIFF of (H, W, S) integer or float ``samples`` in one strip,
    little-endian or (``order`` ">") big-endian, of kinds Pillow does not write (16-bit
    CMYK, 16-bit signed gray, float RGB)."""
    h, w, count = samples.shape
    data = samples.astype(samples.dtype.newbyteorder(order)).tobytes()
    short, long = 3, 4
    tags = {256: (long, [w]), 257: (long, [h]), 258: (short, [samples.dtype.itemsize * 8] * count),
            259: (short, [1]), 262: (short, [photometric]), 273: (long, [0]),
            277: (short, [count]), 278: (long, [h]), 279: (long, [len(data)]),
            284: (short, [1]),
            339: (short, [3 if samples.dtype.kind == "f" else 2 if signed else 1] * count)}

    def packed(kind: int, values: list[int]) -> bytes:
        return struct.pack(order + ("H" if kind == short else "I") * len(values), *values)

    ifd_end = 8 + 2 + 12 * len(tags) + 4
    outside = [packed(*tags[t]) for t in sorted(tags) if len(packed(*tags[t])) > 4]
    tags[273] = (long, [ifd_end + sum(map(len, outside))])  # the strip, after all else
    entries, offset = b"", ifd_end
    for tag, (kind, values) in sorted(tags.items()):
        value = packed(kind, values)
        if len(value) > 4:  # stored after the IFD, in the order of the tags
            entries += struct.pack(order + "HHII", tag, kind, len(values), offset)
            offset += len(value)
        else:
            entries += struct.pack(order + "HHI", tag, kind, len(values)) + value.ljust(4, b"\0")
    magic = b"II*\0" if order == "<" else b"MM\0*"
    path.write_bytes(magic + struct.pack(order + "IH", 8, len(tags)) + entries
                     + struct.pack(order + "I", 0) + b"".join(outside) + data)
    return path


def _load_quiet(path: Path, **kwargs) -> Exemplar:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return Exemplar.load(path, **kwargs)


# --- input kinds ---------------------------------------------------------------------------


def test_png_8bit_rgb_scaled_to_unit_range(data_dir):
    path = data_dir / "granite_64.png"
    expected = np.asarray(Image.open(path), dtype=np.float32) / 255
    exemplar = _load_quiet(path)
    assert exemplar.shape == (64, 64)
    assert exemplar.channels == 3
    assert exemplar.colors.dtype == np.float32
    np.testing.assert_array_equal(exemplar.colors, expected)
    assert exemplar.features is exemplar.colors
    assert exemplar.name == "granite_64.png"
    assert exemplar.path == path.resolve()


def test_png_16bit_rgb_round_trip_keeps_16_bits(tmp_path, rng):
    pixels = rng.integers(0, 65536, size=(20, 24, 3), dtype=np.uint16)
    exemplar = _load_quiet(_write_png16(tmp_path / "rgb16.png", pixels))
    assert exemplar.shape == (20, 24)
    assert exemplar.channels == 3
    np.testing.assert_array_equal(exemplar.colors, pixels.astype(np.float32) / 65535)
    # Neighbouring 16-bit codes stay distinct, which an 8-bit decode would merge.
    assert np.unique(np.round(exemplar.colors * 65535)).size > 256


def test_png_16bit_grayscale_round_trip(tmp_path, rng):
    pixels = rng.integers(0, 65536, size=(17, 33, 1), dtype=np.uint16)
    exemplar = _load_quiet(_write_png16(tmp_path / "gray16.png", pixels))
    assert exemplar.channels == 1
    np.testing.assert_array_equal(exemplar.colors, pixels.astype(np.float32) / 65535)


def test_tiff_16bit_grayscale_keeps_16_bits(tmp_path, rng):
    """Pillow reads a 16-bit grey TIFF as mode I;16 (16-bit PNGs go through pypng): its
    values are scaled by 65535, not reduced to 8 bits first."""
    grey = rng.integers(0, 65536, size=(16, 20), dtype=np.uint16)
    Image.fromarray(grey).save(tmp_path / "grey16.tif")
    exemplar = _load_quiet(tmp_path / "grey16.tif")
    assert exemplar.channels == 1 and exemplar.srgb
    np.testing.assert_array_equal(exemplar.colors[..., 0],
                                  grey.astype(np.float32) / np.float32(65535))


def _gray_icc_profile(name: bytes = b"Dot Gain 20%") -> bytes:
    """An ICC profile of the GRAY color space (Photoshop's gray working spaces), which
    Pillow's ImageCms cannot make: header, description, white point and a gamma curve."""

    def padded(b: bytes) -> bytes:
        return b + b"\0" * (-len(b) % 4)

    white = struct.pack(">iii", int(0.9642 * 65536), 65536, int(0.8249 * 65536))
    tags = [(b"desc", padded(b"desc\0\0\0\0" + struct.pack(">I", len(name) + 1) + name
                             + b"\0" * 79)),
            (b"wtpt", b"XYZ \0\0\0\0" + white),
            (b"kTRC", b"curv\0\0\0\0" + struct.pack(">IH", 1, 0x0233) + b"\0\0")]
    offset = 128 + 4 + 12 * len(tags)
    table, data = struct.pack(">I", len(tags)), b""
    for signature, body in tags:
        table += signature + struct.pack(">II", offset + len(data), len(body))
        data += padded(body)
    header = (struct.pack(">I", offset + len(data)) + b"lcms" + struct.pack(">I", 0x02100000)
              + b"mntrGRAYXYZ " + b"\0" * 12 + b"acsp" + b"\0" * 24 + white)
    return header.ljust(128, b"\0") + table + data


def test_a_gray_image_s_gray_profile_brings_no_warning(tmp_path, rng):
    """A gray profile's curve is the gray image's own encoding, which is read as sRGB's
    gray: nothing shifts, so nothing is said."""
    pixels = rng.integers(0, 256, (16, 16), dtype=np.uint8)
    Image.fromarray(pixels, "L").save(tmp_path / "gray.png", icc_profile=_gray_icc_profile())
    np.testing.assert_array_equal(_load_quiet(tmp_path / "gray.png").colors[..., 0],
                                  pixels / np.float32(255))


def test_16bit_color_that_pillow_reads_as_8_bits_is_said_so(tmp_path, rng):
    """Pillow decodes 16-bit RGB PPM and TIFF files into 8 bits: loaded, with a warning
    naming the file, where 8-bit ones and 16-bit grey ones load quietly."""
    rgb16 = rng.integers(0, 65536, size=(16, 20, 3), dtype=np.uint16)
    ppm = tmp_path / "rgb16.ppm"
    ppm.write_bytes(b"P6\n20 16\n65535\n" + rgb16.astype(">u2").tobytes())
    with pytest.warns(UserWarning, match=r"rgb16\.ppm: 16-bit color image read as 8 bits"):
        exemplar = Exemplar.load(ppm)
    np.testing.assert_allclose(exemplar.colors, rgb16 / 65535, atol=1 / 255)
    Image.fromarray((rgb16 >> 8).astype(np.uint8)).save(tmp_path / "rgb8.ppm")
    _load_quiet(tmp_path / "rgb8.ppm")
    # Plain-text PPMs name their levels to Pillow's decoder: 255 of them are 8 bits.
    plain = " ".join(map(str, (rgb16 >> 8).ravel()))
    (tmp_path / "rgb8_plain.ppm").write_text(f"P3\n20 16\n255\n{plain}\n")
    np.testing.assert_array_equal(_load_quiet(tmp_path / "rgb8_plain.ppm").colors,
                                  (rgb16 >> 8) / np.float32(255))
    # 256 levels are two bytes a sample too.
    ppm.write_bytes(b"P6\n20 16\n256\n" + (rgb16 >> 8).astype(">u2").tobytes())
    with pytest.warns(UserWarning, match=r"rgb16\.ppm: 16-bit color image read as 8 bits"):
        Exemplar.load(ppm)
    Image.fromarray(rgb16[..., 0]).save(tmp_path / "grey16.tif")
    _load_quiet(tmp_path / "grey16.tif")


@pytest.mark.parametrize("bits", [8, 16])
def test_a_color_profile_other_than_srgb_is_said_not_to_be_applied(tmp_path, rng, bits,
                                                                   monkeypatch):
    """Values are taken as sRGB: an Adobe RGB or Display P3 profile would shift every
    color, so it is named in a warning (8-bit PNGs go through Pillow, 16-bit ones through
    pypng, which reads no profile); an sRGB profile says nothing new."""
    from PIL import ImageCms

    def profile(kind: str) -> bytes:
        return ImageCms.ImageCmsProfile(ImageCms.createProfile(kind)).tobytes()

    pixels = rng.integers(0, 2**bits, size=(16, 20, 3)).astype(np.uint8 if bits == 8
                                                                 else np.uint16)
    for kind in ("LAB", "sRGB"):
        path = tmp_path / f"{kind}.png"
        if bits == 8:
            Image.fromarray(pixels).save(path, icc_profile=profile(kind))
        else:
            chunks = list(png.Reader(filename=_write_png16(path, pixels)).chunks())
            iccp = (b"iCCP", b"profile\0\0" + zlib.compress(profile(kind)))
            with path.open("wb") as file:
                png.write_chunks(file, [chunks[0], iccp, *chunks[1:]])
        if kind == "sRGB":
            exemplar = _load_quiet(path)
        else:
            with pytest.warns(UserWarning, match=r"LAB\.png: embedded color profile 'Lab "
                              r"identity built-in' not applied"):
                exemplar = Exemplar.load(path)
            if bits == 16:  # where warnings are errors, none of Pillow's stands in its way
                with monkeypatch.context() as patched, warnings.catch_warnings():
                    patched.setattr(Image, "MAX_IMAGE_PIXELS", 200)  # Pillow would warn
                    warnings.simplefilter("error")
                    with pytest.raises(UserWarning, match=r"LAB\.png: embedded color"):
                        Exemplar.load(path)
        np.testing.assert_array_equal(exemplar.colors, pixels / np.float32(2**bits - 1))


def test_a_color_profile_that_cannot_be_read_is_said_not_to_be_applied(tmp_path, rng):
    """A profile that no color management reads (damaged, or of a kind LittleCMS does not
    know) may be any color space: it is named "(unreadable)" in the warning, through Pillow
    (8 bits) as through pypng (16 bits), not taken for sRGB nor a traceback."""
    said = (r"{}: embedded color profile '\(unreadable\)' not applied: its values are taken "
            r"as sRGB")
    pixels = rng.integers(0, 256, size=(16, 20, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(tmp_path / "odd.png", icc_profile=b"garbage")
    with pytest.warns(UserWarning, match=said.format(r"odd\.png")):
        exemplar = Exemplar.load(tmp_path / "odd.png")
    np.testing.assert_array_equal(exemplar.colors, pixels / np.float32(255))
    deep = rng.integers(0, 65536, size=(16, 20, 3), dtype=np.uint16)
    path = _png_with_chunk(tmp_path / "odd16.png", deep, b"iCCP",
                           b"profile\0\0" + zlib.compress(b"garbage"), write=_write_png16)
    with pytest.warns(UserWarning, match=said.format(r"odd16\.png")):
        exemplar = Exemplar.load(path)
    np.testing.assert_array_equal(exemplar.colors, deep / np.float32(65535))


def test_what_pillow_reads_in_part_is_said_naming_the_file(tmp_path, rng):
    """An animation's first frame is read, with a warning; Pillow's own warnings (corrupt
    EXIF data) come again naming the file; a TIFF that Pillow cannot read is called one."""
    frames = [Image.fromarray(rng.integers(0, 256, (16, 20, 3), dtype=np.uint8))
              for _ in range(3)]
    frames[0].save(tmp_path / "anim.gif", save_all=True, append_images=frames[1:])
    with pytest.warns(UserWarning, match=r"anim\.gif: an animation of 3 frames \(or pages\), "
                      "of which the first is read"):
        Exemplar.load(tmp_path / "anim.gif")
    frames[0].save(tmp_path / "still.gif")
    _load_quiet(tmp_path / "still.gif")
    # APNGs that pypng decodes (16-bit, a transparent color) were read without the warning.
    gray16 = [Image.fromarray(np.asarray(f)[..., 0].astype(np.uint16) * 257) for f in frames]
    gray16[0].save(tmp_path / "anim16.png", save_all=True, append_images=gray16[1:])
    frames[0].save(tmp_path / "trns.png", save_all=True, append_images=frames[1:],
                   transparency=(1, 2, 3))
    for name in ("anim16.png", "trns.png"):
        with pytest.warns(UserWarning, match=rf"{name[:-4]}\.png: an animation of 3 frames"):
            Exemplar.load(tmp_path / name)
    jpeg = tmp_path / "exif.jpg"
    frames[0].save(jpeg, quality=95)
    junk = b"Exif\0\0MM\0\x2a\0\0\0\x08\xff\xff" + b"\x01" * 40
    data = jpeg.read_bytes()
    jpeg.write_bytes(data[:2] + b"\xff\xe1" + (len(junk) + 2).to_bytes(2, "big") + junk
                     + data[2:])
    with pytest.warns(UserWarning, match=r"exif\.jpg: Corrupt EXIF data"):
        Exemplar.load(jpeg)
    twin = tmp_path / "twin.jpg"
    twin.write_bytes(jpeg.read_bytes())
    with pytest.warns(UserWarning) as shown, warnings.catch_warnings():
        warnings.simplefilter("default")  # Python's: the same words are said once
        Exemplar.load(jpeg)
        Exemplar.load(twin)  # Pillow says the same words of another file
    assert [str(w.message).partition(": Corrupt EXIF data")[0] for w in shown] == [
        str(jpeg), str(twin)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(UserWarning, match=r"exif\.jpg: Corrupt EXIF data"):
            Exemplar.load(jpeg)
    (tmp_path / "odd.tif").write_bytes(b"II*\0" + bytes(40))
    _raises(tmp_path / "odd.tif", r"odd\.tif: a TIFF file of a kind Pillow cannot read")
    # Float RGB, which Pillow reads in neither byte order: named as a TIFF either way.
    colors = rng.random((16, 16, 3)).astype(np.float32)
    for order in "<>":
        path = _write_tiff(tmp_path / f"float{order == '>'}.tif", colors, 2, order=order)
        _raises(path, r"a TIFF file of a kind Pillow cannot read \(float RGB.*save it as "
                      r"OpenEXR")


def test_an_animation_of_two_frames_is_said_so(tmp_path, rng):
    """Two frames are an animation too, read through Pillow (a GIF) or pypng (an APNG of
    16 bits)."""
    frames = [Image.fromarray(rng.integers(0, 256, (16, 20, 3), dtype=np.uint8))
              for _ in range(2)]
    frames[0].save(tmp_path / "two.gif", save_all=True, append_images=frames[1:])
    gray16 = [Image.fromarray(np.asarray(f)[..., 0].astype(np.uint16) * 257) for f in frames]
    gray16[0].save(tmp_path / "two16.png", save_all=True, append_images=gray16[1:])
    for name in ("two.gif", "two16.png"):
        with pytest.warns(UserWarning, match=rf"{name}: an animation of 2 frames"):
            Exemplar.load(tmp_path / name)
    # An APNG of one frame (its acTL chunk put in by hand: Pillow writes none for one) is
    # a still image.
    data = (tmp_path / "two16.png").read_bytes()
    gray16[0].save(tmp_path / "one16.png")
    still = (tmp_path / "one16.png").read_bytes()
    body = b"acTL" + (1).to_bytes(4, "big") + (0).to_bytes(4, "big")
    actl = len(body[4:]).to_bytes(4, "big") + body + zlib.crc32(body).to_bytes(4, "big")
    header_end = 8 + 8 + 13 + 4  # the signature and the IHDR chunk
    assert b"acTL" in data and b"acTL" not in still
    (tmp_path / "one16.png").write_bytes(still[:header_end] + actl + still[header_end:])
    np.testing.assert_array_equal(_load_quiet(tmp_path / "one16.png").colors[..., 0],
                                  np.asarray(gray16[0]) / np.float32(65535))


def test_png_8bit_grayscale_is_one_channel(tmp_path, rng):
    pixels = rng.integers(0, 256, size=(32, 40), dtype=np.uint8)
    Image.fromarray(pixels, mode="L").save(tmp_path / "gray.png")
    exemplar = _load_quiet(tmp_path / "gray.png")
    assert exemplar.colors.shape == (32, 40, 1)
    np.testing.assert_array_equal(exemplar.colors[..., 0], pixels / np.float32(255))


def test_png_low_bit_depth_scaled_to_unit_range(tmp_path, rng):
    pixels = rng.integers(0, 16, size=(16, 16), dtype=np.uint8)
    pixels[0, 0], pixels[0, 1] = 0, 15
    with (tmp_path / "gray4.png").open("wb") as file:
        png.Writer(16, 16, greyscale=True, bitdepth=4).write(file, pixels.tolist())
    exemplar = _load_quiet(tmp_path / "gray4.png")
    np.testing.assert_allclose(exemplar.colors[..., 0], pixels / 15, rtol=0, atol=1e-7)


@pytest.mark.parametrize("suffix", ["bmp", "tif"])
def test_a_1_bit_image_is_one_gray_channel_of_0_and_1(tmp_path, rng, suffix):
    """A black-and-white scan (a 1-bit BMP or TIFF, Pillow's mode "1"): one gray channel,
    black 0 and white 1, not three channels of a color image."""
    bits = rng.random((16, 20)) < 0.5
    path = tmp_path / f"scan.{suffix}"
    Image.fromarray(bits).save(path)
    with Image.open(path) as image:
        assert image.mode == "1"
    exemplar = _load_quiet(path)
    assert exemplar.colors.shape == (16, 20, 1) and exemplar.srgb
    np.testing.assert_array_equal(exemplar.colors[..., 0], bits.astype(np.float32))


# 8 colors are stored in 4 bits, read by pypng; 256 in 8 bits without transparency, read by
# Pillow as mode P, which must not gain an alpha channel read as a fourth color.
@pytest.mark.parametrize("colors", [8, 256])
def test_png_palette_expands_to_rgb(tmp_path, rng, colors):
    rgb = rng.integers(0, 256, size=(16, 16, 3), dtype=np.uint8)
    Image.fromarray(rgb).quantize(colors=colors).save(tmp_path / "palette.png")
    expected = np.asarray(Image.open(tmp_path / "palette.png").convert("RGB")) / np.float32(255)
    exemplar = _load_quiet(tmp_path / "palette.png")
    assert exemplar.channels == 3
    np.testing.assert_array_equal(exemplar.colors, expected)


def test_png_rgba_alpha_dropped_with_warning(tmp_path, rng):
    rgba = rng.integers(0, 256, size=(16, 20, 4), dtype=np.uint8)
    Image.fromarray(rgba, mode="RGBA").save(tmp_path / "rgba.png")
    with pytest.warns(AlphaDropped, match=r"rgba\.png: alpha channel dropped"):
        exemplar = Exemplar.load(tmp_path / "rgba.png")
    assert exemplar.channels == 3
    np.testing.assert_array_equal(exemplar.colors, rgba[..., :3] / np.float32(255))


def test_an_alpha_channel_opaque_everywhere_is_dropped_without_a_warning(tmp_path, rng):
    """Photos saved with an alpha channel that is opaque everywhere are common; dropping
    it loses nothing, so nothing is said. One transparent pixel brings the warning back."""
    rgba = rng.integers(0, 256, size=(16, 20, 4), dtype=np.uint8)
    rgba[..., 3] = 255
    Image.fromarray(rgba, mode="RGBA").save(tmp_path / "opaque.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        exemplar = Exemplar.load(tmp_path / "opaque.png")
    np.testing.assert_array_equal(exemplar.colors, rgba[..., :3] / np.float32(255))
    rgba[3, 4, 3] = 254
    Image.fromarray(rgba, mode="RGBA").save(tmp_path / "almost.png")
    with pytest.warns(AlphaDropped, match=r"almost\.png: alpha channel dropped"):
        Exemplar.load(tmp_path / "almost.png")


def test_an_alpha_that_pypng_decodes_is_dropped_by_default_too(tmp_path, rng):
    """16-bit RGBA, and a transparent color (tRNS), are decoded by pypng: their alpha is
    dropped with a warning, not taken for a fourth color, and kept where asked."""
    rgba16 = rng.integers(0, 65536, size=(16, 16, 4)).astype(np.uint16)
    rgb = rng.integers(0, 256, size=(16, 16, 3), dtype=np.uint8)
    rgb[0, 0] = (1, 2, 3)
    Image.fromarray(rgb).save(tmp_path / "trns.png", transparency=(1, 2, 3))
    for path in (_write_png16(tmp_path / "rgba16.png", rgba16), tmp_path / "trns.png"):
        with pytest.warns(AlphaDropped, match=rf"{path.name}: alpha channel dropped"):
            assert Exemplar.load(path).channels == 3
        kept = _load_quiet(path, alpha="keep")
        assert kept.channels == 4 and kept.kept_alpha


def test_png_rgba_alpha_kept_as_last_channel(tmp_path, rng):
    rgba = rng.integers(0, 256, size=(16, 20, 4), dtype=np.uint8)
    Image.fromarray(rgba, mode="RGBA").save(tmp_path / "rgba.png")
    exemplar = _load_quiet(tmp_path / "rgba.png", alpha="keep")
    assert exemplar.channels == 4
    np.testing.assert_array_equal(exemplar.colors, rgba / np.float32(255))


def test_png_gray_alpha_dropped_to_one_channel(tmp_path, rng):
    la = rng.integers(0, 256, size=(16, 16, 2), dtype=np.uint8)
    Image.fromarray(la, mode="LA").save(tmp_path / "la.png")
    with pytest.warns(UserWarning, match="alpha"):
        exemplar = Exemplar.load(tmp_path / "la.png")
    np.testing.assert_array_equal(exemplar.colors[..., 0], la[..., 0] / np.float32(255))


def test_jpeg_rgb_close_to_source(tmp_path):
    y, x = np.mgrid[0:48, 0:64]
    smooth = np.stack([x / 63, y / 47, (x + y) / 110], axis=2)
    Image.fromarray(np.round(smooth * 255).astype(np.uint8)).save(
        tmp_path / "smooth.jpg", quality=100
    )
    exemplar = _load_quiet(tmp_path / "smooth.jpg")
    assert exemplar.shape == (48, 64)
    assert exemplar.channels == 3
    assert np.abs(exemplar.colors - smooth).mean() < 0.01


@pytest.mark.parametrize(("orientation", "turns"), [(1, 0), (3, 2), (6, -1), (8, 1)])
def test_jpeg_camera_orientation_is_applied(tmp_path, orientation, turns):
    """EXIF orientation 6: a portrait photo stored sideways, shown turned a quarter
    clockwise (np.rot90 with k=-1); 8 the other way; 3 upside down."""
    y, x = np.mgrid[0:48, 0:64]
    smooth = np.stack([x / 63, y / 47, (x + y) / 110], axis=2)
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(np.round(smooth * 255).astype(np.uint8)).save(
        tmp_path / "camera.jpg", quality=100, exif=exif
    )
    exemplar = _load_quiet(tmp_path / "camera.jpg")
    upright = np.rot90(smooth, k=turns)
    assert exemplar.shape == upright.shape[:2]
    assert np.abs(exemplar.colors - upright).mean() < 0.01


@pytest.mark.parametrize("compression", [None, "tiff_lzw"])
@pytest.mark.parametrize(("orientation", "turns"), [(6, -1), (8, 1)])
def test_tiff_camera_orientation_is_applied_compressed_or_not(tmp_path, rng, compression,
                                                             orientation, turns):
    """An uncompressed one-strip TIFF turned a quarter came out scrambled: Pillow 13
    memory-mapped its strip at the turned size."""
    pixels = rng.integers(0, 256, size=(48, 64), dtype=np.uint8)
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(pixels).save(tmp_path / "camera.tif", exif=exif,
                                 **({"compression": compression} if compression else {}))
    np.testing.assert_array_equal(_load_quiet(tmp_path / "camera.tif").colors[..., 0],
                                  np.rot90(pixels, k=turns) / np.float32(255))


def test_tiff_premultiplied_alpha_is_undone_and_signed_pixels_refused_in_words(tmp_path, rng):
    """Gray with associated (premultiplied) alpha was refused as "conversion from La to L
    not supported"; signed 16-bit pixels were called 32-bit ones."""
    gray = rng.integers(0, 128, (16, 16), dtype=np.uint8)
    Image.fromarray(np.stack([gray, np.full_like(gray, 128)], axis=2), "LA").save(
        tmp_path / "la.tif")
    unassociated = b"\x52\x01\x03\x00\x01\x00\x00\x00\x02\x00"  # ExtraSamples = 2
    data = (tmp_path / "la.tif").read_bytes()
    assert data.count(unassociated) == 1
    (tmp_path / "la.tif").write_bytes(data.replace(unassociated, unassociated[:8] + b"\1\0"))
    kept = _load_quiet(tmp_path / "la.tif", alpha="keep")
    np.testing.assert_allclose(kept.colors[..., 0], np.minimum(gray * 2, 255) / 255, atol=1 / 255)
    signed = np.zeros((16, 16), np.int32)
    signed[0, 0] = -3000
    Image.fromarray(signed, "I").save(tmp_path / "signed.tif")
    _raises(tmp_path / "signed.tif", r"signed or 32-bit integer pixels are not supported")


def test_integer_tiffs_are_told_by_their_kind_not_their_values(tmp_path, rng):
    """Signed 16-bit and 32-bit gray were read as unsigned 16-bit wherever their values
    fitted it (a signed image at half its brightness); they are refused whatever their
    values, and unsigned 16-bit gray is read as before."""
    values = rng.integers(0, 300, (16, 18, 1))
    expected = values[..., 0].astype(np.float32) / np.float32(65535)
    for order in "<>":  # Pillow's raw modes I;16S and I;16BS
        _raises(_write_tiff(tmp_path / "signed16.tif", values.astype(np.int16), 1, signed=True,
                            order=order), "signed or 32-bit integer pixels are not supported")
        unsigned = _write_tiff(tmp_path / "gray16.tif", values.astype(np.uint16), 1, order=order)
        np.testing.assert_array_equal(_load_quiet(unsigned).colors[..., 0], expected)
    Image.fromarray(values[..., 0].astype(np.int32), "I").save(tmp_path / "wide32.tif")
    _raises(tmp_path / "wide32.tif", "signed or 32-bit integer pixels are not supported")
    # A plain-text (P2) 16-bit PGM, which Pillow widens to 32 bits as it does a binary one.
    pgm = tmp_path / "plain16.pgm"
    pgm.write_text("P2\n18 16\n65535\n" + " ".join(map(str, values.ravel())) + "\n")
    np.testing.assert_array_equal(_load_quiet(pgm).colors[..., 0], expected)
    values[0, 0] = 65535  # full white is a 16-bit value too, not a 32-bit one
    pgm.write_text("P2\n18 16\n65535\n" + " ".join(map(str, values.ravel())) + "\n")
    assert _load_quiet(pgm).colors[0, 0, 0] == 1.0


def test_16bit_cmyk_that_pillow_reads_as_8_bits_is_said_so(tmp_path, rng):
    cmyk = rng.integers(0, 65536, (16, 18, 4)).astype(np.uint16)
    with pytest.warns(UserWarning, match=r"cmyk16\.tif: 16-bit color image read as 8 bits"):
        Exemplar.load(_write_tiff(tmp_path / "cmyk16.tif", cmyk, photometric=5))


def test_damaged_files_are_refused_in_one_error_naming_them(tmp_path, monkeypatch):
    """A TIFF whose second page has no size met Pillow's TypeError (a traceback), and an
    OpenEXR file cut short was said to have zero channels."""
    Image.fromarray(np.zeros((16, 16), np.uint8)).save(tmp_path / "pages.tif")
    data = bytearray((tmp_path / "pages.tif").read_bytes())
    ifd = struct.unpack_from("<I", data, 4)[0]
    entries = struct.unpack_from("<H", data, ifd)[0]
    struct.pack_into("<I", data, ifd + 2 + 12 * entries, len(data))  # a next page, appended
    data += struct.pack("<HHHII", 1, 259, 3, 1, 1) + struct.pack("<I", 0)  # no width, height
    (tmp_path / "pages.tif").write_bytes(bytes(data))
    _raises(tmp_path / "pages.tif", r"pages\.tif: unreadable image")
    header = {"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"RGB": np.zeros((32, 32, 3), np.float32)}).write(
        str(tmp_path / "whole.exr"))
    whole = (tmp_path / "whole.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(whole[: len(whole) // 2])  # within the pixels
    _raises(tmp_path / "cut.exr", r"cut\.exr: damaged or truncated OpenEXR file")
    # An error without a message is named by its kind, not shown as "()".
    import warptex.exemplar_files

    def cut_short(*args, **kwargs):
        raise EOFError

    monkeypatch.setattr(warptex.exemplar_files, "_pillow_decoded", cut_short)
    Image.fromarray(np.zeros((16, 16), np.uint8)).save(tmp_path / "short.tif")
    _raises(tmp_path / "short.tif", r"short\.tif: unreadable image \(EOFError\)")


def test_png_orientation_is_not_applied(tmp_path, rng):
    """PNGs are read as stored whatever their eXIf chunk says, as pypng reads those it
    decodes (16-bit, transparent color) and as Mitsuba's bitmap reads them."""
    pixels = rng.integers(0, 256, size=(16, 20, 3), dtype=np.uint8)
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(pixels).save(tmp_path / "turned.png", exif=exif)
    np.testing.assert_array_equal(_load_quiet(tmp_path / "turned.png").colors,
                                  pixels / np.float32(255))


def test_jpeg_grayscale_is_one_channel(tmp_path):
    pixels = np.tile(np.linspace(0, 255, 32).astype(np.uint8), (24, 1))
    Image.fromarray(pixels, mode="L").save(tmp_path / "gray.jpg", quality=100)
    exemplar = _load_quiet(tmp_path / "gray.jpg")
    assert exemplar.colors.shape == (24, 32, 1)
    assert np.abs(exemplar.colors[..., 0] - pixels / 255).max() < 0.02


def test_format_told_from_content_not_name(tmp_path, rng):
    pixels = rng.integers(0, 256, size=(16, 16, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(tmp_path / "really_a_png.jpg", format="PNG")
    exemplar = _load_quiet(tmp_path / "really_a_png.jpg")
    np.testing.assert_array_equal(exemplar.colors, pixels / np.float32(255))


def test_exr_float32_round_trip_exact_and_unclamped(tmp_path, rng):
    rgb = rng.normal(0.5, 2.0, size=(18, 26, 3)).astype(np.float32)
    exemplar = _load_quiet(_write_exr(tmp_path / "rgb.exr", {"RGB": rgb}))
    assert exemplar.channels == 3
    np.testing.assert_array_equal(exemplar.colors, rgb)
    assert exemplar.colors.min() < 0 and exemplar.colors.max() > 1


def test_exr_half_rgba_alpha_handling(tmp_path, rng):
    rgba = rng.random(size=(16, 16, 4)).astype(np.float16)
    path = _write_exr(tmp_path / "half.exr", {"RGBA": rgba})
    with pytest.warns(UserWarning, match="alpha"):
        dropped = Exemplar.load(path)
    np.testing.assert_array_equal(dropped.colors, rgba[..., :3].astype(np.float32))
    kept = _load_quiet(path, alpha="keep")
    np.testing.assert_array_equal(kept.colors, rgba.astype(np.float32))


def test_exr_extra_channels_follow_rgb(tmp_path, rng):
    rgb = rng.random(size=(16, 16, 3)).astype(np.float32)
    depth = rng.random(size=(16, 16)).astype(np.float32)
    rough = rng.random(size=(16, 16)).astype(np.float32)
    path = _write_exr(tmp_path / "multi.exr", {"RGB": rgb, "Z": depth, "roughness": rough})
    exemplar = _load_quiet(path)
    assert exemplar.channels == 5
    np.testing.assert_array_equal(exemplar.colors[..., :3], rgb)
    np.testing.assert_array_equal(exemplar.colors[..., 3], depth)  # "Z" sorts before "roughness"
    np.testing.assert_array_equal(exemplar.colors[..., 4], rough)


def test_exr_alpha_follows_the_extra_channels(tmp_path, rng):
    """Alpha comes last, after depth and the like: where it is dropped, it is alpha that
    goes, not the last extra channel."""
    rgba = rng.random(size=(16, 16, 4)).astype(np.float32)
    depth = rng.random(size=(16, 16)).astype(np.float32)
    path = _write_exr(tmp_path / "alpha.exr", {"RGBA": rgba, "Z": depth})
    kept = _load_quiet(path, alpha="keep").colors
    np.testing.assert_array_equal(kept, np.concatenate([rgba[..., :3], depth[..., None],
                                                        rgba[..., 3:]], axis=2))
    with pytest.warns(AlphaDropped):
        dropped = Exemplar.load(path).colors
    np.testing.assert_array_equal(dropped, kept[..., :4])


def test_exr_channels_are_told_by_their_name_in_either_case_and_after_a_layer(tmp_path, rng):
    """As Mitsuba's bitmap reads them: r, g, b are R, G, B, and so are diffuse.R and
    diffuse.g; sorted by their names they would come out blue first."""
    rgb = rng.random(size=(16, 16, 3)).astype(np.float32)
    expected = _load_quiet(_write_exr(tmp_path / "upper.exr", {"RGB": rgb})).colors
    lower = {"r": rgb[..., 0], "g": rgb[..., 1], "b": rgb[..., 2]}
    np.testing.assert_array_equal(_load_quiet(_write_exr(tmp_path / "lower.exr", lower)).colors,
                                  expected)
    layered = {"diffuse.R": rgb[..., 0], "diffuse.g": rgb[..., 1], "diffuse.B": rgb[..., 2]}
    np.testing.assert_array_equal(
        _load_quiet(_write_exr(tmp_path / "layer.exr", layered)).colors, expected)


def test_exr_of_layers_reads_the_one_that_holds_colors(tmp_path, rng):
    """A render's layers (Blender's ViewLayer.Combined with its alpha, ViewLayer.Depth.Z):
    the colors and their alpha, the other layers left out with a warning naming them; two
    layers of colors are refused unless one is the default layer."""
    rgba = rng.random(size=(16, 16, 4)).astype(np.float32)
    depth = np.full((16, 16), np.inf, np.float32)  # as renders write the background
    channels = {f"ViewLayer.Combined.{c}": rgba[..., i] for i, c in enumerate("RGBA")}
    path = _write_exr(tmp_path / "render.exr", {**channels, "ViewLayer.Depth.Z": depth})
    with pytest.warns(UserWarning, match=r"render\.exr: OpenEXR layer ViewLayer\.Combined read, "
                      r"channels of other layers left out: ViewLayer\.Depth\.Z"):
        kept = Exemplar.load(path, alpha="keep")
    np.testing.assert_array_equal(kept.colors, rgba)
    two = {**channels, **{f"ViewLayer.Glossy.{c}": rgba[..., i] for i, c in enumerate("RGB")}}
    _raises(_write_exr(tmp_path / "two.exr", two),
            r"two\.exr: OpenEXR file has colors in 2 layers \(ViewLayer\.Combined, "
            r"ViewLayer\.Glossy\): save the one to use alone")
    default = {**{c: rgba[..., i] for i, c in enumerate("RGB")}, **two}
    with pytest.warns(UserWarning, match="channels of other layers left out"):
        np.testing.assert_array_equal(
            Exemplar.load(_write_exr(tmp_path / "default.exr", default)).colors, rgba[..., :3])


def test_exr_of_parts_reads_the_one_that_holds_colors_as_of_layers(tmp_path, rng):
    """A multi-part file (render passes, one part each): only the first part was read,
    without a word, so a depth pass written first became a one-channel exemplar."""
    import OpenEXR

    rgb = rng.random(size=(16, 16, 3)).astype(np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    depth = OpenEXR.Part(header, {"Z": rgb[..., 0].copy()}, "depth")
    beauty = OpenEXR.Part(dict(header), {c: rgb[..., i].copy() for i, c in enumerate("RGB")},
                          "beauty")
    OpenEXR.File([depth, beauty]).write(str(tmp_path / "passes.exr"))
    with pytest.warns(UserWarning, match=r"passes\.exr: OpenEXR layer beauty read, channels "
                      r"of other layers left out: Z"):
        np.testing.assert_array_equal(Exemplar.load(tmp_path / "passes.exr").colors, rgb)
    # The first part is the default layer, which wins over other parts' colors (an AOV),
    # and a part whose channels carry its name (Nuke's) keeps them.
    albedo = OpenEXR.Part(dict(header), {f"albedo.{c}": rgb[..., 2 - i].copy()
                                         for i, c in enumerate("RGB")}, "albedo")
    OpenEXR.File([beauty, albedo]).write(str(tmp_path / "aov.exr"))
    with pytest.warns(UserWarning, match=r"channels of other layers left out: albedo\.B, "
                      r"albedo\.G, albedo\.R"):
        np.testing.assert_array_equal(Exemplar.load(tmp_path / "aov.exr").colors, rgb)


def test_an_exr_channel_in_two_parts_is_refused_naming_it(tmp_path, rng):
    """A part named diffuse beside the default part's own diffuse.R, .G and .B: each of
    them would be one channel of two parts, and neither is chosen without a word. The
    file is named once, and not called unreadable: it is whole."""
    rgb = rng.random(size=(16, 16, 3)).astype(np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    beauty = OpenEXR.Part(header, {f"diffuse.{c}": rgb[..., i].copy()
                                   for i, c in enumerate("RGB")}, "beauty")
    diffuse = OpenEXR.Part(dict(header), {c: rgb[..., 2 - i].copy()
                                          for i, c in enumerate("RGB")}, "diffuse")
    path = tmp_path / "twice.exr"
    OpenEXR.File([beauty, diffuse]).write(str(path))
    with pytest.raises(ExemplarError, match=rf"^{re.escape(str(path))}: OpenEXR channel "
                       r"diffuse\.[RGB] is in two parts: save the part to use alone$"):
        Exemplar.load(path)


def test_exr_parts_of_different_sizes_are_refused_in_words(tmp_path, rng):
    """Two passes of no color, one at half the resolution (each part has a data window of
    its own): they cannot be stacked as one exemplar, which is said naming the file, not in
    NumPy's words."""
    def header() -> dict:
        corner = (np.array([0, 0], np.int32), np.array([31, 31], np.int32))
        return {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                "displayWindow": corner}  # the same in every part, as OpenEXR requires

    full = OpenEXR.Part(header(), {"Z": rng.random((32, 32), dtype=np.float32)}, "depth")
    half = OpenEXR.Part(header(), {"Z": rng.random((16, 16), dtype=np.float32)}, "coarse")
    OpenEXR.File([full, half]).write(str(tmp_path / "sizes.exr"))
    _raises(tmp_path / "sizes.exr", r"sizes\.exr: OpenEXR channels have different sizes")


def test_exr_layer_choice_prefers_colors_and_refuses_channels_told_apart_by_case(tmp_path,
                                                                                 rng):
    rgb = rng.random(size=(16, 16, 3)).astype(np.float32)
    grey_and_color = {"Y": rgb[..., 0], **{f"diffuse.{c}": rgb[..., i]
                                           for i, c in enumerate("RGB")}}
    with pytest.warns(UserWarning, match="channels of other layers left out: Y"):
        loaded = Exemplar.load(_write_exr(tmp_path / "y.exr", grey_and_color))
    np.testing.assert_array_equal(loaded.colors, rgb)
    _raises(_write_exr(tmp_path / "case.exr", {"RGB": rgb, "r": rgb[..., 0]}),
            r"case\.exr: OpenEXR channels (R and r|r and R) are one channel told apart by case")
    no_color = {"depth": rgb[..., 0], "a": rgb[..., 1]}
    np.testing.assert_array_equal(
        _load_quiet(_write_exr(tmp_path / "data.exr", no_color), alpha="keep").colors,
        rgb[..., :2])  # depth, then the alpha last


def test_exr_of_numbered_data_channels_keeps_their_numeric_order(tmp_path, rng):
    """Channels of no color (C1, C2, C10) are read in the order of their numbers, not of
    their names' letters."""
    planes = {f"C{k}": np.full((16, 16), float(k), np.float32) for k in (10, 1, 2)}
    planes["C1"][0, 1] = 0.5  # not constant
    colors = _load_quiet(_write_exr(tmp_path / "data.exr", planes)).colors
    assert colors[0, 0].tolist() == [1.0, 2.0, 10.0]


def test_exr_channels_that_cannot_be_colors_are_named(tmp_path, rng):
    rgb = rng.random(size=(16, 16, 3)).astype(np.float32)
    ids = {"RGB": rgb, "id": np.arange(256, dtype=np.uint32).reshape(16, 16)}
    _raises(_write_exr(tmp_path / "ids.exr", ids),
            r"ids\.exr: OpenEXR channel id holds integers \(object or material ids\)")
    depth = {"RGB": rgb, "Z": np.full((16, 16), np.inf, np.float32)}
    _raises(_write_exr(tmp_path / "depth.exr", depth),
            r"depth\.exr: image contains NaN or Inf values \(in OpenEXR channel Z\)")
    alpha = _write_exr(tmp_path / "alpha.exr", {"A": rgb[..., 0]})
    _raises(alpha, r"alpha\.exr: image holds only an alpha channel \(alpha='keep'")
    from warptex.sheets import to_png8

    alone = _load_quiet(alpha, alpha="keep")
    assert alone.channels == 1 and not alone.kept_alpha  # one color: no PNG of no colors
    assert to_png8(alone.colors, alone.kept_alpha).shape == (16, 16, 3)


def test_an_image_beyond_the_memory_the_process_may_use_is_refused_by_name(tmp_path, rng,
                                                                           monkeypatch):
    """Under a memory limit (ulimit -v, a batch job's), decoding or converting a photo fails
    where NumPy or Pillow allocates: the file is named, no traceback; warnings the load
    gives before still point at its caller."""
    import warptex.exemplar

    path = tmp_path / "huge.png"
    Image.fromarray((rng.random((16, 16, 4)) * 255).astype(np.uint8)).save(path)
    monkeypatch.setattr(warptex.exemplar, "_opaque", lambda alpha: False)
    monkeypatch.setattr(warptex.exemplar, "_shrunk",
                        lambda *_: np.zeros((2**31, 2**30), np.uint8))  # NumPy refuses it
    with pytest.warns(AlphaDropped) as caught:
        error = _raises(path, r"huge\.png: too large to load in the memory this process may "
                              r"use \(Unable to allocate", max_size=16)
    assert caught[0].filename == __file__ and error.__cause__ is None
    read_image = warptex.exemplar.read_image
    mask = tmp_path / "mask.png"
    Image.fromarray(np.zeros((16, 16), np.uint8)).save(mask)

    def no_room_for(name: str):
        def read(path):
            if Path(path).name == name:
                raise MemoryError()
            return read_image(path)
        return read

    monkeypatch.undo()
    monkeypatch.setattr(warptex.exemplar, "read_image", no_room_for("huge.png"))
    _raises(path, r"huge\.png: too large to load in the memory this process may use "
                  r"\(out of memory\)$", alpha="keep")
    # A feature mask too large is the mask's fault, not the exemplar's.
    monkeypatch.setattr(warptex.exemplar, "read_image", no_room_for("mask.png"))
    _raises(path, r"mask\.png: too large to load in the memory this process may use",
            alpha="keep", feature_mask=mask)


def test_exr_luminance_only_is_one_channel(tmp_path, rng):
    y = rng.random(size=(16, 20)).astype(np.float32)
    exemplar = _load_quiet(_write_exr(tmp_path / "y.exr", {"Y": y}))
    assert exemplar.colors.shape == (16, 20, 1)
    np.testing.assert_array_equal(exemplar.colors[..., 0], y)


def test_npy_any_number_of_channels_as_stored(tmp_path, rng):
    data = rng.normal(size=(16, 18, 7)) * 10
    np.save(tmp_path / "multi.npy", data)
    exemplar = _load_quiet(tmp_path / "multi.npy")
    assert exemplar.channels == 7
    np.testing.assert_array_equal(exemplar.colors, data.astype(np.float32))


def test_an_exr_of_many_channels_that_warptex_wrote_reads_back_in_order(tmp_path, rng):
    """Its channels C0 ... C11 are taken in their numbers' order, C10 after C9."""
    from warptex.volume_files import write_image

    data = rng.random(size=(16, 16, 12)).astype(np.float32)
    write_image(tmp_path / "many.exr", data, srgb=False)
    np.testing.assert_array_equal(_load_quiet(tmp_path / "many.exr").colors, data)


def test_npy_2d_and_uint16(tmp_path, rng):
    data = rng.integers(0, 65536, size=(16, 16), dtype=np.uint16)
    np.save(tmp_path / "gray16.npy", data)
    exemplar = _load_quiet(tmp_path / "gray16.npy")
    assert exemplar.colors.shape == (16, 16, 1)
    np.testing.assert_array_equal(exemplar.colors[..., 0], data / np.float32(65535))


def test_big_endian_integers_are_the_integers_they_hold(tmp_path, rng):
    """A .npy of big-endian uint16 (written on another machine, or raw PNG rows read with
    np.frombuffer) was refused as an "unsupported data type >u2; use ... uint16"."""
    data = rng.integers(0, 65536, size=(16, 16), dtype=np.uint16)
    np.save(tmp_path / "big.npy", data.astype(">u2"))
    for exemplar in (_load_quiet(tmp_path / "big.npy"), Exemplar(data.astype(">u2"))):
        np.testing.assert_array_equal(exemplar.colors[..., 0], data / np.float32(65535))
        assert exemplar.srgb


def test_array_kinds(rng):
    floats = rng.normal(size=(16, 16, 64)).astype(np.float64)
    assert Exemplar(floats).channels == 64
    np.testing.assert_array_equal(Exemplar(floats).colors, floats.astype(np.float32))

    gray = rng.integers(0, 256, size=(20, 16), dtype=np.uint8)
    exemplar = Exemplar(gray)
    assert exemplar.shape == (20, 16)
    assert exemplar.channels == 1
    assert exemplar.name == "array"
    assert exemplar.path is None
    np.testing.assert_array_equal(exemplar.colors[..., 0], gray / np.float32(255))

    mask = np.zeros((16, 16), dtype=bool)
    mask[4:9] = True
    np.testing.assert_array_equal(Exemplar(mask).colors[..., 0], mask.astype(np.float32))


def _write_png8(path: Path, pixels: np.ndarray, **options) -> Path:
    height, width, _ = pixels.shape
    with path.open("wb") as file:
        writer = png.Writer(width, height, greyscale=False, **options)
        writer.write(file, pixels.reshape(height, -1).tolist())
    return path


def _write_pillow(path: Path, pixels: np.ndarray) -> Path:
    Image.fromarray(pixels).save(path)
    return path


@pytest.mark.parametrize(("write", "srgb"), [
    (lambda p, c: _write_png8(p / "a.png", c), True),
    (lambda p, c: _write_png8(p / "a.png", c, gamma=0.45455), True),
    (lambda p, c: _write_png8(p / "a.png", c, gamma=1.0), True),  # gAMA ignored, as Mitsuba
    (lambda p, c: _write_png16(p / "a.png", c.astype(np.uint16) * 257), True),
    (lambda p, c: _write_pillow(p / "a.jpg", c), True),
    (lambda p, c: _write_pillow(p / "a.tif", c), True),
    (lambda p, c: _write_pillow(p / "a.tif", c[..., 0] / np.float32(255)), False),
    (lambda p, c: _write_exr(p / "a.exr", {"RGB": c / np.float32(255)}), False),
    (lambda p, c: np.save(p / "a.npy", c) or p / "a.npy", True),
    (lambda p, c: np.save(p / "a.npy", c / np.float32(255)) or p / "a.npy", False),
], ids=["png", "png-gamma-srgb", "png-gamma-1", "png16", "jpeg", "tiff", "tiff-float", "exr",
        "npy-uint8", "npy-float"])
def test_integer_images_are_srgb_encoded_float_images_linear(tmp_path, rng, write, srgb):
    """As Mitsuba's bitmap reads them, so the plugin decodes what it would decode."""
    pixels = rng.integers(0, 256, size=(16, 16, 3), dtype=np.uint8)
    path = write(tmp_path, pixels)
    assert _load_quiet(path).srgb is srgb
    assert _load_quiet(path, max_size=16).srgb is srgb  # shrinking makes floats of integers
    assert _load_quiet(path, srgb=not srgb).srgb is not srgb
    assert ("linear" in repr(_load_quiet(path))) is not srgb


def test_srgb_transfer_functions():
    """IEC 61966-2-1: the linear segment, its joint and a known mid-tone; each the other's
    inverse; re-encoding touches the leading color channels only."""
    from warptex.srgb import linear_to_srgb, reencoded, srgb_to_linear

    np.testing.assert_allclose(srgb_to_linear([0.0, 0.04045, 0.5, 1.0]),
                               [0.0, 0.0031308, 0.2140411, 1.0], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(linear_to_srgb([0.0, 0.0031308, 0.2140411, 1.0, 1.7, -0.2]),
                               [0.0, 0.04045, 0.5, 1.0, 1.0, 0.0], rtol=1e-5, atol=1e-7)
    values = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(values)), values, atol=1e-6)
    # Each segment up to its joint, to the bit: a 16-bit value just below the decoding
    # joint (2622/65535) is linear, one just above the encoding joint is not (a joint of
    # 0.04 decoded it 1.5e-4 off, and passed the tolerances above).
    low = np.float32(2622 / 65535)
    assert srgb_to_linear(low) == np.float32(np.float64(low) / 12.92)
    above = np.float32(0.0031309)
    assert linear_to_srgb(above) == np.float32(1.055 * np.float64(above) ** (1 / 2.4) - 0.055)
    rgba = np.random.default_rng(0).random((5, 4)).astype(np.float32)
    decoded = reencoded(rgba, srgb=True, to_srgb=False)
    np.testing.assert_array_equal(decoded[:, :3], srgb_to_linear(rgba[:, :3]))
    np.testing.assert_array_equal(decoded[:, 3], rgba[:, 3])
    gray_alpha = reencoded(rgba[:, :2], srgb=False, to_srgb=True)
    np.testing.assert_array_equal(gray_alpha, np.c_[linear_to_srgb(rgba[:, 0]), rgba[:, 1]])
    np.testing.assert_array_equal(reencoded(rgba, srgb=True, to_srgb=True), rgba)
    # Exactly three channels are RGB, all three re-encoded (compare decodes a volume's RGB).
    np.testing.assert_array_equal(reencoded(rgba[:, :3], srgb=True, to_srgb=False),
                                  srgb_to_linear(rgba[:, :3]))


def test_array_encoding_follows_the_dtype_unless_given(rng):
    pixels = rng.integers(0, 256, size=(16, 16, 3), dtype=np.uint8)
    assert Exemplar(pixels).srgb and Exemplar(pixels.astype(np.uint16)).srgb
    assert not Exemplar(pixels / 255.0).srgb and not Exemplar(pixels > 127).srgb
    assert Exemplar(pixels / 255.0, srgb=True).srgb and not Exemplar(pixels, srgb=False).srgb


def test_arrays_are_read_only_copies(rng):
    source = rng.random(size=(16, 16, 3)).astype(np.float32)
    exemplar = Exemplar(source)
    source[0, 0, 0] = 99.0
    assert exemplar.colors[0, 0, 0] != 99.0
    assert not exemplar.colors.flags.writeable
    assert not exemplar.features.flags.writeable


def test_shared_exemplars_all_load(exemplar_dir):
    paths = sorted(exemplar_dir.glob("*.png"))
    assert paths
    for path in paths:
        exemplar = _load_quiet(path)
        assert exemplar.channels in (1, 3)
        assert 0 <= exemplar.colors.min() <= exemplar.colors.max() <= 1


# --- bad input -----------------------------------------------------------------------------


def _raises(path_or_array, match: str, **kwargs) -> ExemplarError:
    with pytest.raises(ExemplarError, match=match) as info:
        if isinstance(path_or_array, Path):
            Exemplar.load(path_or_array, **kwargs)
        else:
            Exemplar(path_or_array, **kwargs)
    return info.value


def test_missing_file(tmp_path):
    error = _raises(tmp_path / "nope.png", "image file not found")
    assert "nope.png" in str(error)
    assert isinstance(error, ValueError)
    (tmp_path / "dangling.png").symlink_to(tmp_path / "gone.png")
    _raises(tmp_path / "dangling.png",
            r"dangling\.png: image file not found \(a broken symbolic link\)")
    # A loop of links is no missing file: the system's reason is given.
    (tmp_path / "a.png").symlink_to(tmp_path / "b.png")
    (tmp_path / "b.png").symlink_to(tmp_path / "a.png")
    _raises(tmp_path / "a.png", r"a\.png: cannot look up image file \(Too many levels of symbolic")


def test_directory_is_not_an_image(tmp_path):
    _raises(tmp_path, "is a folder, expected an image file")


def test_text_file_is_not_an_image(tmp_path):
    path = tmp_path / "notes.png"
    path.write_text("just some words, no pixels here\n")
    assert "notes.png" in str(_raises(path, "not an image"))


def test_empty_file_is_not_an_image(tmp_path):
    (tmp_path / "empty.jpg").write_bytes(b"")
    _raises(tmp_path / "empty.jpg", "empty.jpg: not an image")


def test_truncated_png_is_unreadable(tmp_path, rng):
    Image.fromarray(rng.integers(0, 256, size=(32, 32, 3), dtype=np.uint8)).save(
        tmp_path / "full.png"
    )
    data = (tmp_path / "full.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    _raises(tmp_path / "cut.png", r"cut\.png: unreadable PNG")


def test_a_png_cut_inside_its_header_is_unreadable_naming_it(tmp_path):
    """A half-downloaded PNG: its signature and then zeros, or a header (IHDR) whose
    checksum does not match, or the signature alone. Its reading stops before any pixel,
    with the one error naming the file."""
    magic = b"\x89PNG\r\n\x1a\n"
    header = struct.pack(">IIBBBBB", 16, 16, 8, 2, 0, 0, 0)
    damaged = {"zeros.png": magic + bytes(20),
               "crc.png": magic + struct.pack(">I", 13) + b"IHDR" + header + bytes(4),
               "magic.png": magic}
    for name, data in damaged.items():
        (tmp_path / name).write_bytes(data)
        _raises(tmp_path / name, rf"{name[:-4]}\.png: unreadable PNG \(\w+Error: ")


def test_truncated_jpeg_is_unreadable(tmp_path, rng):
    Image.fromarray(rng.integers(0, 256, size=(32, 32, 3), dtype=np.uint8)).save(
        tmp_path / "full.jpg"
    )
    data = (tmp_path / "full.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[:200])
    _raises(tmp_path / "cut.jpg", r"cut\.jpg: unreadable image")


def _png_with_chunk(path: Path, pixels: np.ndarray, kind: bytes, data: bytes,
                    write: Callable[[Path, np.ndarray], Path] = _write_png8) -> Path:
    """A PNG (8-bit RGB unless ``write`` says) with a chunk of ``kind`` inserted after its
    header."""
    raw = write(path, pixels).read_bytes()
    chunk = (len(data).to_bytes(4, "big") + kind + data
             + zlib.crc32(kind + data).to_bytes(4, "big"))
    path.write_bytes(raw[:33] + chunk + raw[33:])  # signature 8, IHDR 25
    return path


def _png_kinds(folder: Path, rng) -> dict[str, Path]:
    """PNGs of every color type and depth pypng writes, with and without a transparent
    color or a palette's transparency."""
    def write(name, rows, **options):
        path = folder / f"{name}.png"
        with path.open("wb") as file:
            png.Writer(width=20, height=16, **options).write(file, rows)
        return path

    def values(top, planes):
        return rng.integers(0, top, (16, 20 * planes)).tolist()

    pixel = rng.integers(0, 256, 3)
    kinds = {
        "rgb8": write("rgb8", values(256, 3), greyscale=False),
        "rgba8": write("rgba8", values(256, 4), greyscale=False, alpha=True),
        "grey8": write("grey8", values(256, 1), greyscale=True),
        "grey-alpha8": write("la8", values(256, 2), greyscale=True, alpha=True),
        "rgb8-trns": write("rgbt", values(256, 3), greyscale=False,
                           transparent=tuple(int(c) for c in pixel)),
        "grey8-trns": write("lt", values(256, 1), greyscale=True, transparent=int(pixel[0])),
        "rgb16": write("rgb16", values(65536, 3), greyscale=False, bitdepth=16),
    }
    for depth in (1, 2, 4, 8):
        palette = [tuple(int(c) for c in rng.integers(0, 256, 4)) for _ in range(2**depth)]
        kinds[f"palette{depth}"] = write(f"p{depth}", values(2**depth, 1), palette=palette,
                                         bitdepth=depth)
        if depth < 8:
            kinds[f"grey{depth}"] = write(f"l{depth}", values(2**depth, 1), greyscale=True,
                                          bitdepth=depth)
    return kinds


def test_every_kind_of_png_gives_the_values_pypng_decodes(tmp_path, rng):
    """8-bit PNGs are decoded by Pillow, in C (pypng took about a second a megapixel), the
    others by pypng: both give each kind's values as pypng alone does, alpha included."""
    for kind, path in _png_kinds(tmp_path, rng).items():
        reader = png.Reader(filename=str(path))
        width, height, rows, info = reader.asDirect()
        stored = np.vstack([np.asarray(r) for r in rows]).reshape(height, width, -1)
        expected = stored.astype(np.float32) / np.float32(2 ** info["bitdepth"] - 1)
        loaded = Exemplar.load(path, alpha="keep")
        np.testing.assert_array_equal(loaded.colors, expected, err_msg=kind)
        assert loaded.srgb, kind


def test_png_values_are_read_as_stored_whatever_its_significant_bits(tmp_path, rng):
    """An sBIT chunk (RGB565) leaves the stored values as they are, as Mitsuba and Pillow
    read them; pypng would rescale them to 6 significant bits."""
    pixels = rng.integers(0, 256, size=(16, 16, 3), dtype=np.uint8)
    path = _png_with_chunk(tmp_path / "sbit.png", pixels, b"sBIT", bytes([5, 6, 5]))
    np.testing.assert_array_equal(_load_quiet(path).colors,
                                  pixels.astype(np.float32) / np.float32(255))
    # 16-bit PNGs, which pypng decodes, of 12 significant bits as scanners write them.
    pixels = rng.integers(0, 65536, size=(16, 16, 3), dtype=np.uint16)
    path = _png_with_chunk(tmp_path / "sbit16.png", pixels, b"sBIT", bytes([12, 12, 12]),
                           write=_write_png16)
    np.testing.assert_array_equal(_load_quiet(path).colors,
                                  pixels.astype(np.float32) / np.float32(65535))


def test_damaged_files_of_valid_checksums_are_unreadable(tmp_path, rng):
    """A PNG whose compressed data is damaged under valid CRCs; a .npy whose header is."""
    raw = bytearray(_write_png8(tmp_path / "a.png", rng.integers(
        0, 256, size=(16, 16, 3), dtype=np.uint8)).read_bytes())
    start = raw.index(b"IDAT")
    length = int.from_bytes(raw[start - 4:start], "big")
    raw[start + 4:start + 4 + length] = bytes([0xFF]) * length
    raw[start + 4 + length:start + 8 + length] = zlib.crc32(
        bytes(raw[start:start + 4 + length])).to_bytes(4, "big")
    (tmp_path / "zlib.png").write_bytes(bytes(raw))
    _raises(tmp_path / "zlib.png", r"zlib\.png: unreadable PNG")
    np.save(tmp_path / "a.npy", np.zeros((16, 16, 3), np.float32))
    # A bracket left open: NumPy's parser of the header raises tokenize's own error.
    header = (tmp_path / "a.npy").read_bytes().replace(b"{'descr'", b"{'descr'(")
    (tmp_path / "header.npy").write_bytes(header)
    _raises(tmp_path / "header.npy", r"header\.npy: unreadable \.npy file")


def test_a_photograph_larger_than_pillow_decodes_is_named(tmp_path, rng, monkeypatch):
    """Over Pillow's decompression-bomb limit: one error naming the file; between half of
    it and it, no warning in Pillow's words, which name no file (an error naming it where
    warnings are errors)."""
    from PIL import Image

    Image.fromarray(rng.integers(0, 256, size=(16, 16, 3), dtype=np.uint8)).save(
        tmp_path / "a.bmp")
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 200)  # 256 pixels: warned
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        assert Exemplar.load(tmp_path / "a.bmp").shape == (16, 16)
    assert shown == []
    with warnings.catch_warnings():  # where warnings are errors, Pillow's names the file
        warnings.simplefilter("error")
        with pytest.raises(Image.DecompressionBombWarning, match=r"a\.bmp: Image size"):
            Exemplar.load(tmp_path / "a.bmp")
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 100)  # over twice the limit: refused
    _raises(tmp_path / "a.bmp", r"a\.bmp: too large to read")


def test_a_png_that_pillow_refuses_is_read_by_pypng(tmp_path, rng, monkeypatch):
    """Over Pillow's pixel limit (or with a text chunk larger than it takes): pypng reads
    it, as before Pillow decoded 8-bit PNGs."""
    from PIL import Image

    pixels = rng.integers(0, 256, size=(16, 16, 3), dtype=np.uint8)
    path = _write_png8(tmp_path / "a.png", pixels)
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 100)  # over twice the limit
    np.testing.assert_array_equal(_load_quiet(path).colors,
                                  pixels.astype(np.float32) / np.float32(255))


def test_an_exr_alpha_is_checked_only_where_it_is_kept(tmp_path, rng):
    rgba = rng.random(size=(16, 16, 4)).astype(np.float32)
    rgba[3, 4, 3] = np.nan
    path = _write_exr(tmp_path / "alpha.exr", {"RGBA": rgba})
    with pytest.warns(UserWarning, match="alpha channel dropped"):
        np.testing.assert_array_equal(Exemplar.load(path).colors, rgba[..., :3])
    _raises(path, r"alpha\.exr: image contains NaN or Inf values", alpha="keep")


def test_a_file_that_cannot_be_looked_up_or_is_named_empty_is_one_error(tmp_path,
                                                                         monkeypatch):
    """A folder on the way that cannot be searched; an empty name, which Path takes for
    the working folder."""
    def unsearchable(self, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(self))

    _raises(Path(""), r"\.: is a folder")  # a Path given as such names that folder
    with pytest.raises(ExemplarError, match="the exemplar's file name is empty"):
        Exemplar.load("")
    monkeypatch.setattr(Path, "stat", unsearchable)
    _raises(tmp_path / "locked" / "a.png",
            r"a\.png: cannot look up image file \(Permission denied\)")


def test_corrupt_exr_is_unreadable(tmp_path):
    (tmp_path / "bad.exr").write_bytes(b"\x76\x2f\x31\x01" + b"\x00" * 40)
    _raises(tmp_path / "bad.exr", r"bad\.exr: unreadable OpenEXR")


@pytest.mark.parametrize(("mode", "kind"), [("MIPMAP_LEVELS", "mip"), ("RIPMAP_LEVELS", "rip")])
def test_a_tiled_exr_of_several_levels_is_named_so_not_damaged(tmp_path, rng, mode, kind):
    """OpenEXR's Python module reads no part of a valid mip-mapped file (Mitsuba reads it):
    it was refused as "damaged or truncated"; one level of tiles reads."""
    def tiled(name: str, levels) -> Path:
        tiles = OpenEXR.TileDescription()
        tiles.xSize, tiles.ySize, tiles.mode = 16, 16, levels
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.tiledimage,
                  "tiles": tiles}
        OpenEXR.File(header, {"RGB": rng.random((32, 32, 3), dtype=np.float32)}).write(
            str(tmp_path / name))
        return tmp_path / name

    assert Exemplar.load(tiled("one.exr", OpenEXR.ONE_LEVEL)).colors.shape == (32, 32, 3)
    _raises(tiled("levels.exr", getattr(OpenEXR, mode)),
            rf"levels\.exr: a {kind}-mapped tiled OpenEXR file, whose levels OpenEXR's Python "
            rf"module cannot read: save it without {kind}-maps")


def test_corrupt_npy_is_unreadable(tmp_path):
    (tmp_path / "bad.npy").write_bytes(b"\x93NUMPY\x01\x00garbage")
    _raises(tmp_path / "bad.npy", r"bad\.npy: unreadable \.npy")


def test_an_npy_header_larger_than_memory_is_one_clear_error(tmp_path):
    """np.load allocates the size its header declares first: a damaged header's 3.5 TiB
    was a MemoryError's traceback (or, where memory is overcommitted, a reshape's error)."""
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (400000, 400000, 3), }"
    header = header.ljust(117) + "\n"
    (tmp_path / "liar.npy").write_bytes(b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little")
                                        + header.encode() + bytes(4096))
    _raises(tmp_path / "liar.npy", r"liar\.npy: unreadable \.npy file \(mmap length is "
            r"greater than file size\)")


def test_unreadable_file(tmp_path, monkeypatch):
    """A file this user may not read (a chmod 0 file, which root reads all the same: the
    refusal is made so, not by the file's mode)."""
    path = tmp_path / "locked.png"
    Image.fromarray(np.zeros((16, 16), dtype=np.uint8)).save(path)
    opened = Path.open

    def forbidden(self, *args, **kwargs):
        if self == path:
            raise PermissionError(13, "Permission denied", str(self))
        return opened(self, *args, **kwargs)

    monkeypatch.setattr(Path, "open", forbidden)
    _raises(path, r"locked\.png: cannot read file \(Permission denied\)")


@pytest.mark.parametrize("shape", [(15, 16), (16, 15), (8, 8, 3)])
def test_too_small(shape):
    _raises(np.zeros(shape, dtype=np.float32), "at least 16x16")


def test_too_small_file_names_size(tmp_path):
    Image.fromarray(np.zeros((10, 30, 3), dtype=np.uint8)).save(tmp_path / "tiny.png")
    _raises(tmp_path / "tiny.png", r"tiny\.png: image is 30x10 pixels")


def test_nan_in_exr(tmp_path, rng):
    rgb = rng.random(size=(16, 16, 3)).astype(np.float32)
    rgb[3, 4, 1] = np.nan
    _raises(_write_exr(tmp_path / "nan.exr", {"RGB": rgb}), r"nan\.exr: .*NaN or Inf")


def test_inf_in_npy(tmp_path):
    data = np.ones((16, 16, 2), dtype=np.float32)
    data[0, 0, 0] = np.inf
    np.save(tmp_path / "inf.npy", data)
    _raises(tmp_path / "inf.npy", r"inf\.npy: .*NaN or Inf")


def test_float64_beyond_float32_is_refused_as_such():
    """Not as NaN or Inf, which the array does not hold: float32 cannot hold it."""
    data = np.full((16, 16), 1e300)
    data[0, 0] = 0
    _raises(data, r"array: image holds values beyond float32's range \(±3\.4e\+38\)$")
    data[0, 0] = np.inf
    _raises(data, "array: image contains NaN or Inf values$")


def test_zero_channels():
    _raises(np.zeros((16, 16, 0), dtype=np.float32), "zero channels")


def test_too_many_channels(tmp_path, rng):
    np.save(tmp_path / "wide.npy", rng.random(size=(16, 16, 65)).astype(np.float32))
    _raises(tmp_path / "wide.npy", r"wide\.npy: image has 65 channels; at most 64")


@pytest.mark.parametrize(
    ("array", "match"),
    [
        (np.zeros((16, 16, 3, 2), dtype=np.float32), "expected an"),
        (np.zeros(16, dtype=np.float32), "expected an"),
        (np.zeros((16, 16), dtype=np.int64), "unsupported data type int64"),
        (np.full((16, 16), "a"), "unsupported data type"),
    ],
)
def test_unusable_arrays(array, match):
    _raises(array, match)


def test_constant_image_warns(tmp_path):
    Image.fromarray(np.full((16, 16, 3), 128, dtype=np.uint8)).save(tmp_path / "flat.png")
    with pytest.warns(UserWarning, match=r"flat\.png: .*nothing to synthesize"):
        exemplar = Exemplar.load(tmp_path / "flat.png")
    assert exemplar.colors.min() == exemplar.colors.max() == np.float32(128 / 255)


def test_constant_per_channel_but_varying_across_channels_is_constant():
    data = np.ones((16, 16, 3), dtype=np.float32) * np.array([0.1, 0.5, 0.9], dtype=np.float32)
    with pytest.warns(UserWarning, match="nothing to synthesize"):
        Exemplar(data)


def test_invalid_options(data_dir):
    path = data_dir / "granite_64.png"
    with pytest.raises(ValueError, match="alpha"):
        Exemplar.load(path, alpha="premultiply")
    with pytest.raises(ValueError, match="feature_distance"):
        Exemplar.load(path, feature_distance="sdf")
    with pytest.raises(ValueError, match="not both"):
        Exemplar.load(path, feature_mask=path, feature_distance="auto")


# --- feature distance ----------------------------------------------------------------------


def test_feature_distance_from_mask_values():
    mask = np.zeros((16, 16), dtype=bool)
    mask[:, 4:8] = True
    distance = feature_distance_from_mask(mask)
    assert distance.dtype == np.float32
    assert distance.shape == (16, 16)
    assert distance.min() == 0.0
    assert distance.max() <= 1.0
    assert (distance[mask] > 0.5).all()
    assert (distance[~mask] < 0.5).all()
    # Pixels either side of an edge sit at +-0.5 pixel, scaled by the largest |distance|: 7.5,
    # from column 15 to the stripe's edge at 7.5 (distances do not wrap around the border).
    np.testing.assert_allclose(distance[0, 4], 0.5 + 0.5 * 0.5 / 7.5, rtol=1e-6)
    np.testing.assert_allclose(distance[0, 3], 0.5 - 0.5 * 0.5 / 7.5, rtol=1e-6)
    np.testing.assert_allclose(distance[0, 15], 0.0, atol=1e-7)


def test_feature_distance_is_euclidean_between_pixel_centres():
    """Against a brute-force reference: each pixel's distance to the nearest pixel on the
    other side of the mask, Euclidean (a diagonal step is sqrt(2), as no chamfer or
    city-block metric has it), less half a pixel, signed and scaled as documented."""
    mask = np.zeros((16, 16), dtype=bool)
    mask[5:9, 3:12] = True
    mask[9:14, 6] = True
    pixels = np.indices(mask.shape).reshape(2, -1).T
    inside = mask.ravel()
    apart = np.sqrt(((pixels[:, None] - pixels[None]) ** 2).sum(axis=2))
    nearest = np.where(inside[:, None] != inside[None], apart, np.inf).min(axis=1)
    signed = np.where(inside, nearest - 0.5, 0.5 - nearest)
    expected = 0.5 + 0.5 * signed / np.abs(signed).max()
    np.testing.assert_allclose(feature_distance_from_mask(mask).ravel(), expected, rtol=1e-6)


def test_feature_distance_needs_an_edge():
    with pytest.raises(ExemplarError, match="no edges"):
        feature_distance_from_mask(np.ones((16, 16), dtype=bool))
    with pytest.raises(ExemplarError, match="no edges"):
        feature_distance_from_mask(np.zeros((16, 16), dtype=bool))


def test_otsu_mask_splits_two_levels(rng):
    image = np.full((16, 16, 3), 0.2, dtype=np.float32)
    image[5:11, 3:9] = 0.8
    image += rng.normal(0, 0.02, size=image.shape).astype(np.float32)
    expected = np.zeros((16, 16), dtype=bool)
    expected[5:11, 3:9] = True
    np.testing.assert_array_equal(otsu_mask(image), expected)
    # Fewer than three channels (grey and a kept alpha): the first alone.
    grey_alpha = np.stack([image[..., 0], rng.random((16, 16)).astype(np.float32)], axis=2)
    np.testing.assert_array_equal(otsu_mask(grey_alpha), expected)


def _blob_files(folder: Path, shape: tuple[int, int], rows: slice, cols: slice) -> np.ndarray:
    """``blob.png``, a light rectangle on a dark ground, and ``blob_mask.png`` marking it,
    in ``folder``; returns the mask."""
    image = np.full((*shape, 3), 40, dtype=np.uint8)
    image[rows, cols] = 220
    Image.fromarray(image).save(folder / "blob.png")
    mask = np.zeros(shape, dtype=np.uint8)
    mask[rows, cols] = 255
    Image.fromarray(mask).save(folder / "blob_mask.png")
    return mask


def test_feature_distance_in_features_not_colors(tmp_path):
    mask = _blob_files(tmp_path, (24, 20), slice(6, 14), slice(5, 12))

    from_mask = _load_quiet(tmp_path / "blob.png", feature_mask=tmp_path / "blob_mask.png")
    automatic = _load_quiet(tmp_path / "blob.png", feature_distance="auto")
    plain = _load_quiet(tmp_path / "blob.png")
    expected = feature_distance_from_mask(mask > 0)
    for exemplar in (from_mask, automatic):
        assert exemplar.channels == 3
        assert exemplar.colors.shape == (24, 20, 3)
        assert exemplar.features.shape == (24, 20, 4)
        np.testing.assert_array_equal(exemplar.features[..., :3], plain.colors)
        np.testing.assert_array_equal(exemplar.features[..., 3], expected)
    assert _load_quiet(tmp_path / "blob.png", feature_distance=True).digest() == automatic.digest()


def test_feature_distance_argument_of_constructor(rng):
    colors = rng.random(size=(16, 16, 2)).astype(np.float32)
    distance = rng.random(size=(16, 16)).astype(np.float32)
    exemplar = Exemplar(colors, feature_distance=distance)
    np.testing.assert_array_equal(exemplar.features[..., 2], distance)
    with pytest.raises(ExemplarError, match="feature distance has shape"):
        Exemplar(colors, feature_distance=distance[:8])
    with pytest.raises(ExemplarError, match="feature distance contains NaN"):
        Exemplar(colors, feature_distance=np.full((16, 16), np.nan))


def test_a_feature_distance_of_one_channel_is_taken_as_its_plane(rng):
    """A distance given as (H, W, 1), as a channel sliced off an image keeps it: the same
    features, digest included, as the (H, W) plane it holds."""
    colors = rng.random(size=(16, 16, 3)).astype(np.float32)
    distance = rng.normal(size=(16, 16)).astype(np.float32)
    plane = Exemplar(colors, feature_distance=distance)
    channel = Exemplar(colors, feature_distance=distance[..., None])
    assert channel.features.shape == (16, 16, 4)
    np.testing.assert_array_equal(channel.features, plane.features)
    assert channel.digest() == plane.digest()


def test_feature_mask_problems(tmp_path, data_dir):
    path = data_dir / "granite_64.png"
    Image.fromarray(np.zeros((32, 32), dtype=np.uint8)).save(tmp_path / "small_mask.png")
    with pytest.raises(ExemplarError, match=r"small_mask\.png: feature mask is 32x32 .* 64x64"):
        Exemplar.load(path, feature_mask=tmp_path / "small_mask.png")
    Image.fromarray(np.zeros((64, 64), dtype=np.uint8)).save(tmp_path / "empty_mask.png")
    with pytest.raises(ExemplarError, match=r"empty_mask\.png: feature mask has no edges"):
        Exemplar.load(path, feature_mask=tmp_path / "empty_mask.png")
    with pytest.raises(ExemplarError, match="file not found"):
        Exemplar.load(path, feature_mask=tmp_path / "missing_mask.png")


def test_a_feature_mask_with_nan_or_inf_is_refused(tmp_path, data_dir):
    """A NaN made its maximum NaN: the mask was thresholded at zero instead of half its
    maximum, without a word; an Inf was said to leave the mask without edges."""
    mask = np.zeros((64, 64), np.float32)
    mask[8:40, 8:40] = 1.0
    for bad in (np.nan, np.inf):
        mask[63, 63] = bad
        np.save(tmp_path / "mask.npy", mask)
        with pytest.raises(ExemplarError, match=r"mask\.npy: feature mask contains NaN or Inf"):
            Exemplar.load(data_dir / "granite_64.png", feature_mask=tmp_path / "mask.npy")


def test_a_photo_given_as_feature_mask_is_used_with_a_warning(tmp_path, data_dir):
    """A mask with many grey pixels is no black-and-white mask (a photo given by mistake):
    it is thresholded at half its maximum as any mask is, and a warning says so. A binary
    one, RGB or with a few grey pixels along its edges, brings none."""
    path = data_dir / "granite_64.png"
    with pytest.warns(UserWarning, match=r"granite_64\.png: not a black-and-white feature "
                                         r"mask \(\d+% of its pixels are grey\); features are "
                                         r"marked where its first channel exceeds half") as said:
        photo = Exemplar.load(path, feature_mask=path)
    assert said[0].filename == __file__  # the line that loads, not the loader's own
    first = np.asarray(Image.open(path))[..., 0]
    np.testing.assert_array_equal(photo.features[..., 3],
                                  feature_distance_from_mask(first > 0.5 * first.max()))
    binary = np.zeros((64, 64, 3), np.uint8)
    binary[10:40, 20:50] = 255
    binary[10, 20:50] = 128  # one anti-aliased edge
    Image.fromarray(binary).save(tmp_path / "mask.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Exemplar.load(path, feature_mask=tmp_path / "mask.png")
    # Up to 5 % of grey pixels pass as edges; more do not.
    for grey, said in ((204, False), (246, True)):  # 4.98 % and 6.0 % of 4096
        mask = binary.copy()
        mask[10] = 0
        mask.reshape(-1, 3)[:grey] = 128
        Image.fromarray(mask).save(tmp_path / "edges.png")
        with warnings.catch_warnings(record=True) as shown:
            warnings.simplefilter("always")
            Exemplar.load(path, feature_mask=tmp_path / "edges.png")
        assert any("not a black-and-white" in str(w.message) for w in shown) == said, grey


def test_a_boolean_feature_mask_marks_what_its_0_255_image_marks(tmp_path):
    """A mask saved from NumPy as booleans (.npy) marks the features its True pixels are,
    as the same mask of 0 and 255 does, with no warning that it is not black and white;
    shrunk with the image too."""
    mask = _blob_files(tmp_path, (48, 40), slice(12, 28), slice(10, 24))
    np.save(tmp_path / "mask.npy", mask > 0)
    for max_size in (None, 24):
        image = _load_quiet(tmp_path / "blob.png", feature_mask=tmp_path / "blob_mask.png",
                            max_size=max_size)
        flags = _load_quiet(tmp_path / "blob.png", feature_mask=tmp_path / "mask.npy",
                            max_size=max_size)
        assert flags.features.shape == image.features.shape
        np.testing.assert_array_equal(flags.features, image.features)
    assert flags.features_from == "mask.npy"


# --- shrinking (max_size) ------------------------------------------------------------------


def _area_reference(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Area averaging by brute force: every pixel repeated onto a grid that both sizes
    divide, then each output pixel's block of it averaged."""
    h, w = image.shape[:2]
    fine_h, fine_w = np.lcm(h, shape[0]), np.lcm(w, shape[1])
    fine = np.repeat(np.repeat(image.astype(np.float64), fine_h // h, axis=0), fine_w // w, axis=1)
    blocks = fine.reshape(shape[0], fine_h // shape[0], shape[1], fine_w // shape[1], -1)
    return blocks.mean(axis=(1, 3))


@pytest.mark.parametrize(("size", "max_size", "shrunk"), [
    ((48, 64), 32, (24, 32)),  # halved: 2 x 2 blocks
    ((64, 64), 24, (24, 24)),  # 8 / 3 pixels per output pixel
    ((42, 100), 50, (21, 50)),  # portrait and landscape alike
    ((100, 42), 50, (50, 21)),
    ((45, 100), 50, (22, 50)),  # 22.5 rounds to even
    ((47, 100), 50, (24, 50)),  # 23.5 too
])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
@pytest.mark.parametrize("band", [256, 7])  # photos are shrunk a band of columns at a time
def test_max_size_area_averages_keeping_the_aspect(tmp_path, rng, monkeypatch, size, max_size,
                                                   shrunk, dtype, band):
    import warptex.exemplar

    monkeypatch.setattr(warptex.exemplar, "_SHRINK_BAND", band)
    pixels = rng.integers(0, 255, size=(*size, 3)).astype(dtype)
    np.save(tmp_path / "photo.npy", pixels)
    plain = _load_quiet(tmp_path / "photo.npy")
    exemplar = _load_quiet(tmp_path / "photo.npy", max_size=max_size)
    assert exemplar.shape == shrunk
    assert exemplar.colors.dtype == np.float32 and not exemplar.colors.flags.writeable
    np.testing.assert_allclose(exemplar.colors, _area_reference(plain.colors, shrunk),
                               rtol=1e-6, atol=1e-6 * float(plain.colors.max()))


def test_max_size_keeps_images_that_fit(data_dir):
    path = data_dir / "granite_64.png"
    plain = _load_quiet(path)
    for max_size in (64, 100):
        assert _load_quiet(path, max_size=max_size).digest() == plain.digest()
    assert _load_quiet(path, max_size=63).shape == (63, 63)


def test_max_size_shrinks_the_feature_mask_with_the_image(tmp_path):
    # Edges inside the 5/3-pixel footprints: shrunk pixels the blob covers partly.
    mask = _blob_files(tmp_path, (40, 32), slice(7, 29), slice(5, 23))
    exemplar = _load_quiet(tmp_path / "blob.png", feature_mask=tmp_path / "blob_mask.png",
                           max_size=24)
    assert exemplar.features.shape == (24, 19, 4)
    coverage = _area_reference(mask[..., None] / 255.0, (24, 19))[..., 0]
    assert ((coverage > 0) & (coverage < 0.5)).any() and ((coverage > 0.5) & (coverage < 1)).any()
    np.testing.assert_array_equal(exemplar.features[..., 3],
                                  feature_distance_from_mask(coverage > 0.5))
    automatic = _load_quiet(tmp_path / "blob.png", feature_distance="auto", max_size=24)
    np.testing.assert_array_equal(automatic.features[..., 3],
                                  feature_distance_from_mask(otsu_mask(automatic.colors)))
    # Sizes are compared as the files hold them.
    Image.fromarray(mask[:20, :16]).save(tmp_path / "small_mask.png")
    with pytest.raises(ExemplarError, match=r"small_mask\.png: feature mask is 16x20 .* 32x40"):
        Exemplar.load(tmp_path / "blob.png", feature_mask=tmp_path / "small_mask.png",
                      max_size=20)


@pytest.mark.parametrize(("max_size", "problem"), [
    (15, "must be at least 16 pixels, got 15"), (0, "must be at least 16 pixels, got 0"),
    (32.0, "must be an integer, got 32.0"), (True, "must be an integer, got True"),
    ("32", "must be an integer, got '32'"),
])
def test_max_size_must_be_a_size(data_dir, max_size, problem):
    with pytest.raises(SettingError, match=f"^max_size {problem}$"):
        Exemplar.load(data_dir / "granite_64.png", max_size=max_size)
    assert Exemplar.load(data_dir / "granite_64.png", max_size=np.int64(32)).shape == (32, 32)


def test_max_size_names_a_file_it_would_shrink_too_far(tmp_path, rng):
    np.save(tmp_path / "strip.npy", rng.random(size=(20, 200)).astype(np.float32))
    with pytest.raises(ExemplarError,
                       match=r"strip\.npy: image is 200x20 pixels, 32x3 when shrunk to a "
                             r"larger side of 32; at least 16x16 needed"):
        Exemplar.load(tmp_path / "strip.npy", max_size=32)


# --- pyramid -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("shape", "min_size", "sizes"),
    [
        ((64, 64), 8, [(8, 8), (16, 16), (32, 32), (64, 64)]),
        ((100, 37), 8, [(7, 3), (13, 5), (25, 10), (50, 19), (100, 37)]),
        ((100, 37), 16, [(13, 5), (25, 10), (50, 19), (100, 37)]),
        ((16, 16), 8, [(8, 8), (16, 16)]),
        ((17, 16), 8, [(5, 4), (9, 8), (17, 16)]),
        ((48, 48), 64, [(48, 48)]),
    ],
)
def test_pyramid_sizes(shape, min_size, sizes, rng):
    exemplar = Exemplar(rng.random(size=(*shape, 2)).astype(np.float32))
    levels = exemplar.pyramid(min_size=min_size)
    assert [level.shape for level in levels] == sizes
    assert all(isinstance(level, PyramidLevel) for level in levels)
    assert all(level.colors.shape[2] == 2 and level.colors.dtype == np.float32 for level in levels)


def test_pyramid_finest_level_is_the_image_and_coarser_levels_wrap_or_reflect_at_seams():
    """Blurred as a torus where the edges tile; reflected at the edges that form a seam."""
    image = np.zeros((64, 64, 1), dtype=np.float32)
    image[0, 0] = 1.0
    image[40:48, 20:30] = 0.5
    exemplar = Exemplar(image)
    levels = exemplar.pyramid(seams=(False, False))
    np.testing.assert_array_equal(levels[-1].colors, image)
    expected = ndimage.gaussian_filter(image, sigma=(1, 1, 0), mode="wrap")[::2, ::2]
    np.testing.assert_allclose(levels[-2].colors, expected, rtol=1e-6)
    # The corner pixel bleeds across the border into the last row, as it would on a tiled plane.
    assert levels[-2].colors[-1, 0, 0] > 0.01
    assert levels[-2].colors[0, -1, 0] > 0.01

    seamed = exemplar.pyramid(seams=(True, True))
    expected = ndimage.gaussian_filter(image, sigma=(1, 1, 0), mode="reflect")[::2, ::2]
    np.testing.assert_allclose(seamed[-2].colors, expected, rtol=1e-6)
    assert seamed[-2].colors[-1, 0, 0] == seamed[-2].colors[0, -1, 0] == 0.0
    torus = exemplar.pyramid(seams=(False, True))[-2].colors
    assert torus[-1, 0, 0] > 0.01 and torus[0, -1, 0] == 0.0


# Seams too: the features' colors are blurred as the colors are, reflected across a seam.
@pytest.mark.parametrize("seams", [None, (True, False), (False, True)])
def test_pyramid_keeps_feature_channel_at_every_level(rng, seams):
    colors = rng.random(size=(40, 24, 3)).astype(np.float32)
    distance = np.linspace(0, 1, 40 * 24).reshape(40, 24)
    exemplar = Exemplar(colors, feature_distance=distance)
    alone = Exemplar(distance.astype(np.float32)).pyramid(seams=seams or exemplar.seams())
    for level, distance_level in zip(exemplar.pyramid(seams=seams), alone, strict=True):
        assert level.colors.shape[2] == 3
        assert level.features.shape[2] == 4
        np.testing.assert_array_equal(level.features[..., :3], level.colors)
        np.testing.assert_array_equal(level.features[..., 3], distance_level.colors[..., 0])


def test_pyramid_rejects_bad_min_size(rng):
    with pytest.raises(ValueError, match="min_size"):
        Exemplar(rng.random(size=(16, 16))).pyramid(min_size=0)


# --- digest --------------------------------------------------------------------------------


def test_digest_follows_content_not_path(tmp_path, data_dir):
    source = data_dir / "granite_64.png"
    copy = tmp_path / "elsewhere.png"
    copy.write_bytes(source.read_bytes())
    digest = _load_quiet(source).digest()
    assert len(digest) == 64
    int(digest, 16)
    assert _load_quiet(copy).digest() == digest
    assert Exemplar(np.asarray(Image.open(source))).digest() == digest

    changed = np.asarray(Image.open(source)).copy()
    changed[10, 10, 0] ^= 1
    assert Exemplar(changed).digest() != digest
    assert _load_quiet(source, feature_distance="auto").digest() != digest


def test_digest_follows_every_channel_and_the_feature_distance(rng):
    data = rng.random(size=(16, 16, 4)).astype(np.float32)
    distance = rng.random(size=(16, 16)).astype(np.float32)
    digest = Exemplar(data, feature_distance=distance).digest()
    for c in range(4):
        changed = data.copy()
        changed[3, 5, c] += 0.25
        assert Exemplar(changed, feature_distance=distance).digest() != digest, c
    moved = distance.copy()
    moved[3, 5] += 0.25
    assert Exemplar(data, feature_distance=moved).digest() != digest


def test_digest_depends_on_shape(rng):
    data = rng.random(size=(32, 32)).astype(np.float32)
    assert Exemplar(data).digest() != Exemplar(data.reshape(16, 64)).digest()


def test_a_periodic_pattern_whose_edge_lies_on_the_wrap_tiles():
    """Stripes 4 pixels wide change across the wrap 4.4x as much as between neighbouring
    rows on average, as much as at each stripe's edge: a quarter of the row pairs, so the
    wrap is one of the pattern's own edges, not a seam. A ramp's wrap differs more than
    any neighbouring columns do."""
    stripes = np.repeat((np.arange(32) // 4 % 2).astype(np.float32)[:, None], 32, axis=1)
    ex = Exemplar(stripes)
    assert ex.seam_contrast()[1] > SEAM_LIMIT
    assert ex.seams() == seams_of(ex.colors) == (False, False)
    assert ex.seam_problem() is None
    ramp = np.repeat(np.linspace(0.0, 1.0, 32, dtype=np.float32)[None, :], 24, axis=0)
    assert Exemplar(ramp).seams() == seams_of(ramp[:, :, None]) == (False, True)
    # Stripes 16 pixels wide have too few edges (3 of 63 row pairs): taken for a seam, which
    # tileable=True (--tileable yes) overrides.
    wide = np.repeat((np.arange(64) // 16 % 2).astype(np.float32)[:, None], 64, axis=1)
    assert seams_of(wide[:, :, None]) == (True, False)


def test_the_setting_tileable_decides_the_seams_where_it_is_not_auto():
    """tileable=True takes any exemplar for the paper's torus, False for a seam at every
    edge; "auto" is the photo's own decision; other values are refused."""
    ramp = np.repeat(np.linspace(0.0, 1.0, 32, dtype=np.float32)[None, :], 24, axis=0)
    ex = Exemplar(ramp)
    assert ex.seams("auto") == ex.seams() == (False, True)
    assert ex.seams(True) == seams_of(ex.colors, True) == (False, False)
    assert ex.seams(np.bool_(False)) == seams_of(ex.colors, False) == (True, True)
    assert ex.seams() == (False, True)  # an override is not remembered as the decision
    with pytest.raises(ValueError, match='tileable must be "auto", True or False'):
        ex.seams("yes")
    with pytest.raises(TypeError, match="tileable must be"):
        seams_of(ex.colors, 1)


def test_arguments_without_a_meaning_are_refused_naming_them(tmp_path, data_dir):
    """srgb is a flag ("no" would count as true), a path is a file name, and an Exemplar
    takes an array: a file name points to Exemplar.load."""
    colors = np.random.default_rng(0).random((16, 16, 3)).astype(np.float32)
    with pytest.raises(SettingError, match="srgb must be True or False, got 'no'"):
        Exemplar(colors, srgb="no")
    with pytest.raises(SettingError, match="srgb must be True or False"):
        Exemplar.load(data_dir / "granite_64.png", srgb="false")
    assert Exemplar(colors, srgb=np.bool_(True)).srgb is True
    with pytest.raises(TypeError, match="path must be a file name"):
        Exemplar.load(5)
    with pytest.raises(ExemplarError, match=r"Exemplar\.load reads the file x\.png"):
        Exemplar("x.png")
    with pytest.raises(SettingError, match="min_size must be an integer"):
        Exemplar(colors).pyramid(min_size="a")


@pytest.mark.parametrize(("ground", "square"), [(2, (1.0, 0.0, 0.0)), (0, (0.0, 1.0, 0.0))])
def test_otsu_mask_weighs_the_channels_as_rec_709(ground, square):
    """A red square on a blue ground, a green one on a red ground: by Rec. 709 luminance
    the square is the brighter (red 0.2126 against blue 0.0722, green 0.7152 against red),
    so it is the feature; channels read in the wrong order, or the red channel alone, would
    invert it."""
    image = np.zeros((16, 16, 3), np.float32)
    image[..., ground] = 1.0
    image[4:10, 5:12] = square
    expected = np.zeros((16, 16), bool)
    expected[4:10, 5:12] = True
    np.testing.assert_array_equal(otsu_mask(image), expected)


@pytest.mark.parametrize(("contrast", "seam"), [(2.25, True), (1.9, False)])
def test_a_wrap_above_twice_the_neighbours_difference_is_a_seam(contrast, seam):
    """SEAM_LIMIT is 2: bundled photos whose wrap lies between 2 and 2.5 (bricks_red_128
    2.26, fabric_gingham_128 2.25, dry_mud_128 2.07) keep their candidates away from it.
    40 columns alternating 0 and 1, then one whose wrap to the first is ``contrast`` times
    the mean neighbouring difference, and which no neighbouring pair matches."""
    last = 38 * contrast / (40 - contrast)  # contrast = 40 last / (39 + last - 1)
    columns = np.append(np.arange(40) % 2, last).astype(np.float64)
    image = np.repeat(columns[None, :, None], 16, axis=0)
    assert seam_contrast_of(image)[0] == pytest.approx(contrast)
    assert seams_of(image) == (False, seam)


def test_seam_contrast_compares_each_wrap_with_its_own_direction():
    """A ramp along the columns with rows alternating by 0.75: the left and right edges
    differ W - 1 times as much as neighbouring columns, the top and bottom exactly as
    much as neighbouring rows; only the former is a seam."""
    h, w = 16, 21
    image = (np.linspace(0.0, 1.0, w)[None, :] + 0.75 * (np.arange(h) % 2)[:, None])
    columns, rows = seam_contrast_of(image[..., None])
    assert columns == pytest.approx(w - 1) and rows == pytest.approx(1.0)
    assert Exemplar(image.astype(np.float32)).seams() == (False, True)


def test_a_wrap_matched_by_exactly_seam_share_of_the_pairs_is_no_seam():
    """21 rows, 0 above row 10 and 1 from it: one of the 20 pairs of neighbouring rows
    (5%, SEAM_SHARE) differs as much as the wrap, so the wrap is one of the image's own
    edges, although it differs 20x as much as neighbouring rows on average."""
    step = np.repeat((np.arange(21) >= 10).astype(np.float32)[:, None], 16, axis=1)
    assert SEAM_SHARE * 20 == 1
    assert seam_contrast_of(step[..., None])[1] == pytest.approx(20.0)
    assert seams_of(step[..., None]) == (False, False)


def test_an_unpickled_exemplar_keeps_its_arrays_read_only(data_dir):
    """compare sends exemplars to its worker processes: they arrive as they were read."""
    import pickle

    ex = Exemplar.load(data_dir / "granite_64.png")
    again = pickle.loads(pickle.dumps(ex))
    assert not again.colors.flags.writeable and not again.features.flags.writeable
    assert again.features is again.colors and again.digest() == ex.digest()


def test_axes_must_agree_on_color_channels_as_well_as_feature_channels():
    """Three colors and a feature distance match four colors in feature channels, not in
    colors, which a voxel averages: precompute and Kopf refuse the pair, naming the axes."""
    from warptex.baselines import kopf
    from warptex.candidates import precompute
    from warptex.exemplar import check_same_channels

    rng = np.random.default_rng(0)
    rgb = Exemplar(rng.random((16, 16, 3), dtype=np.float32), name="rgb",
                   feature_distance=rng.random((16, 16), dtype=np.float32))
    rgba = Exemplar(rng.random((16, 16, 4), dtype=np.float32), name="rgba")
    assert rgb.features.shape[2] == rgba.features.shape[2] == 4
    check_same_channels([rgb, None, rgb])  # an unconstrained axis is left out
    message = "same number of color channels; found x rgb 3, y rgba 4, z rgba 4"
    with pytest.raises(ExemplarError, match=message):
        check_same_channels([rgb, rgba, rgba])
    with pytest.raises(ExemplarError, match=message):
        precompute(rgb, rgba, cache=False)
    with pytest.raises(ExemplarError, match="found x rgb 3, z rgba 4"):
        kopf.synthesize(None, size=8, exemplars=[rgb, None, rgba], progress=False)


def test_a_photo_given_for_several_axes_is_read_and_warned_of_once(tmp_path, rng,
                                                                   warp_device, monkeypatch):
    """precompute(path) read its file once an axis (a large photo's shrinking took its
    seconds three times) and said each of its warnings three times, at a line of warptex's;
    the texture's and the candidates' loading say them once, at the caller's line."""
    from warptex.candidates import precompute
    from warptex.texture import SolidTexture

    rgb16 = rng.integers(0, 65536, size=(32, 32, 3), dtype=np.uint16)
    ppm = tmp_path / "rgb16.ppm"
    ppm.write_bytes(b"P6\n32 32\n65535\n" + rgb16.astype(">u2").tobytes())
    calls = (lambda: precompute(ppm, cache=False), lambda: precompute(ppm, ey=str(ppm)),
             lambda: SolidTexture(ppm), lambda: SolidTexture(ppm, ey=ppm, ez=ppm))
    for call in calls:
        with pytest.warns(UserWarning, match="16-bit color image read as 8 bits") as caught:
            call()
        assert [w.filename for w in caught] == [__file__]
    loads = []
    load = Exemplar.load.__func__
    monkeypatch.setattr(Exemplar, "load", classmethod(
        lambda cls, path, **kw: (loads.append(path), load(cls, path, **kw))[1]))
    for call in calls:
        loads.clear()
        with pytest.warns(UserWarning, match="16-bit color image read as 8 bits"):
            call()
        assert len(loads) == 1
